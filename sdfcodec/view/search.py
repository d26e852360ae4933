"""The work behind ``sdfcodec search``: search a map, draw the paper's Fig. 7, expand and mesh the selection.

The CLI module wires a thin command to :func:`search_command` and prints :func:`format_summary` (or the
returned dict as JSON with ``--json``)::

    sdfcodec search MAP --query floor [--level K] [--threshold T | --top K] [--out DIR] [--json] [--device D]

With ``--out DIR`` it writes ``DIR/search.png`` (a top-down view of the map coloured by descriptor distance,
selected cells outlined, beside a rendering of the expanded blocks' mesh) and ``DIR/expanded.ply`` (the mesh
of the selected blocks, decoded at full quality and nothing else).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InvalidValueError, MapExistsError
from ..map import Map, open_map
from ..search.engine import Expansion, SearchResult, expand, search

__all__ = ["search_command", "format_summary", "search_picture", "selection_mesh", "top_down", "empty_hint"]


def _basis(up: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors spanning the plane perpendicular to ``up`` (``x``, ``y`` when ``up`` is ``z``)."""
    up = up / np.linalg.norm(up)
    ref = np.array([1.0, 0.0, 0.0]) if abs(up[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = ref - (ref @ up) * up
    u /= np.linalg.norm(u)
    return u, np.cross(up, u)


def top_down(m: Map, coords: np.ndarray, values: np.ndarray, up=(0.0, 0.0, 1.0), reduce: str = "min"
             ) -> tuple[np.ndarray, tuple[float, float, float, float]]:
    """Rasterise per-block values seen from above: block centres projected along ``up`` onto cells one block
    wide; each cell keeps the ``reduce`` ("min" or "max") of its blocks (NaN where none).

    Parameters
    ----------
    m : Map
        For the grid geometry (origin, voxel size).
    coords : np.ndarray
        ``(N, 3)`` int block indices.
    values : np.ndarray
        ``(N,)`` float.
    up : sequence of 3 floats
        The viewing direction is ``-up``.

    Returns
    -------
    raster : np.ndarray
        ``(nu, nv)`` float64 (index ``[i, j]``: ``i`` along the first in-plane axis).
    extent : tuple of float
        ``(u0, u1, v0, v1)`` metres, for ``imshow(raster.T, origin="lower", extent=extent)``.
    """
    up = np.asarray(up, dtype=np.float64)
    u, v = _basis(up)
    cell = 16 * m.voxel_size
    centres = np.asarray(m.origin) + m.voxel_size * (16 * np.asarray(coords, np.float64) + 7.5)
    pu, pv = centres @ u, centres @ v
    if not len(pu):
        return np.full((1, 1), np.nan), (0.0, cell, 0.0, cell)
    i = np.round((pu - pu.min()) / cell).astype(int)
    j = np.round((pv - pv.min()) / cell).astype(int)
    fill = np.inf if reduce == "min" else -np.inf
    raster = np.full((i.max() + 1, j.max() + 1), fill)
    (np.minimum if reduce == "min" else np.maximum).at(raster, (i, j), np.asarray(values, np.float64))
    raster[~np.isfinite(raster)] = np.nan
    extent = (pu.min() - cell / 2, pu.min() + cell * (i.max() + 0.5),
              pv.min() - cell / 2, pv.min() + cell * (j.max() + 0.5))
    return raster, extent


def selection_mesh(m: Map, coords: np.ndarray, *, level: int | None = None, device: str | None = None):
    """The mesh of the blocks ``coords`` whole: decoded with their coded neighbours, meshed, and cut back to
    the blocks (one voxel beyond them).

    Marching cubes needs both sides of a block face: the cubes between a block and an absent neighbour are
    missing from a mesh of the blocks alone, so a floor lying on a block seam (z = 0 on a grid with its
    origin one block below) shows as fragments. The neighbours supply the far side; the cut keeps their own
    surfaces out.
    """
    from ..fusion.tsdf import mesh_from_blocks

    sel = np.asarray(coords, np.int64).reshape(-1, 3)
    states = m.block_states()
    grid = np.asarray(states.shape)
    offs = np.array([(i, j, k) for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1)])
    near = np.unique((sel[:, None, :] + offs[None]).reshape(-1, 3), axis=0)
    near = near[np.all((near >= 0) & (near < grid), axis=1)]
    near = near[states[tuple(near.T)] == 2]  # coded blocks only (BlockState.CODED)
    exp = expand(m, near, as_="blocks", level=level, device=device)
    mesh = mesh_from_blocks(exp.coords, exp.blocks, origin=m.origin, voxel_size=m.voxel_size, truncation=m.truncation)
    if not len(mesh.triangles):
        return mesh
    chosen = np.zeros(tuple(grid), bool)
    chosen[tuple(sel.T)] = True
    # a triangle stays when its centre lies within a chosen block's extent (voxels 16c - 0.5 .. 16c + 15.5)
    # widened by one voxel: the seam cubes straddle the extents' common face
    tri = np.asarray(mesh.triangles)
    q = (np.asarray(mesh.vertices)[tri].mean(1) - np.asarray(m.origin)) / m.voxel_size
    keep = np.zeros(len(tri), bool)
    for d in offs[np.all(offs != 0, axis=1)]:
        b = np.clip(np.floor((q + 0.5 + d) / 16).astype(np.int64), 0, grid - 1)
        keep |= chosen[tuple(b.T)]
    mesh.triangles = type(mesh.triangles)(tri[keep])
    mesh.remove_unreferenced_vertices()
    mesh.compute_vertex_normals()
    return mesh


def search_picture(m: Map, result: SearchResult, path: str | os.PathLike, *, mesh: Any = None, up=None,
                   title: str | None = None, whole_blocks: bool = True, device: str | None = None) -> Path:
    """The paper's Fig. 7 for a search: (a) the map from above, each cell coloured by the smallest descriptor
    distance of its blocks (log scale), selected cells outlined; (b) the selected blocks decoded and meshed,
    in a level orthographic view from above and to the side with a scale bar in metres (or, without a mesh,
    the selected cells).

    Needs ``result`` from ``search(..., keep_scores=True)``. ``up`` defaults to the query's up direction.
    Panel (b) is drawn when ``mesh`` (e.g. the expansion's) has triangles; with ``whole_blocks`` (default) it
    shows :func:`selection_mesh` of the selection instead, which keeps the surfaces on block seams that a mesh
    of the selected blocks alone loses.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import LogNorm

    if result.all_scores is None:
        raise InvalidValueError("search_picture needs every block's score: search with keep_scores=True")
    up = result.query.up if up is None else np.asarray(up, np.float64)
    scores = np.maximum(result.all_scores.astype(np.float64), 1e-3)
    dist, extent = top_down(m, result.all_coords, scores, up)
    sel, _ = top_down(m, np.concatenate([result.all_coords, result.coords]),
                      np.r_[np.zeros(len(result.all_coords)), np.ones(len(result.coords))], up, reduce="max")
    # the selection raster shares the grid of the distance raster because it projects the same blocks
    has_mesh = mesh is not None and len(getattr(mesh, "triangles", [])) > 0
    fig, axes = plt.subplots(1, 2, figsize=(12, 5.4), constrained_layout=True)
    ax = axes[0]
    ax.set_facecolor("#e6e6e6")
    lo, hi = float(np.nanmin(dist)), float(np.nanmax(dist))
    # bright = close to the query, so the matches stand out as in the paper's figure
    im = ax.imshow(dist.T, origin="lower", extent=extent, cmap="viridis_r",
                   norm=LogNorm(vmin=lo, vmax=max(hi, lo * 1.01)), interpolation="nearest")
    cell = 16 * m.voxel_size
    for i, j in np.argwhere(sel > 0.5):
        ax.add_patch(plt.Rectangle((extent[0] + i * cell, extent[2] + j * cell), cell, cell, fill=False,
                                   edgecolor="red", linewidth=1.2))
    fig.colorbar(im, ax=ax, shrink=0.85, label="min squared code distance to the query (log)")
    ax.set_title(f"(a) distance to '{result.query.name}' ({len(result.query)} "
                 f"descriptors, level {result.level}); red: selected")
    ax.set_xlabel("m")
    ax.set_ylabel("m")
    ax.set_aspect("equal")
    ax = axes[1]
    if has_mesh:
        from .pictures import mesh_picture

        how = "decoded and meshed whole" if whole_blocks else "decoded and meshed"
        if whole_blocks:
            mesh = selection_mesh(m, result.coords, level=result.level, device=device)
        # the mesh's own heights (at least 1 m of tint) and the map's up: a level view, not the query's tilt
        mesh_picture(mesh, None, up=tuple(up), width=800, height=600, ax=ax,
                     title=f"(b) the {len(result)} selected blocks, {how}")
    else:
        ax.set_facecolor("#e6e6e6")
        ax.imshow(np.where(np.isnan(dist), np.nan, np.where(sel > 0.5, 1.0, 0.25)).T, origin="lower", extent=extent,
                  cmap="Reds", vmin=0, vmax=1, interpolation="nearest")
        ax.set_title(f"(b) the {len(result)} selected cells")
        ax.set_aspect("equal")
        ax.set_xlabel("m")
    if title:
        fig.suptitle(title)
    from ..core._atomic import write_file

    try:
        return write_file(path, lambda tmp: fig.savefig(tmp, dpi=90), "writing the picture")
    finally:
        plt.close(fig)


def search_command(map_path: str | os.PathLike, query: str = "floor", level: int | None = None,
                   threshold: float | None = None, top: int | None = None, out_dir: str | os.PathLike | None = None,
                   as_json: bool = False, device: str | None = None, *, mesh: bool = True,
                   overwrite: bool = False, behind: str | None = None, up: Any = None,
                   tilt: float | None = None, scene: bool = True) -> dict:
    """Everything ``sdfcodec search`` does; returns a JSON-able summary.

    Parameters
    ----------
    map_path : path or URL
        The map.
    query : str
        A built-in query name (floor, ceiling, wall, edge, corner) or the path of a saved query model (.npz).
    level : int, optional
        Compare the first ``level`` code elements (prefix-ordered codecs only).
    threshold : float, optional
        Select blocks scoring ``<= threshold``.
    top : int, optional
        Select the ``top`` best blocks (with ``threshold``: the best ``top`` under it). With neither, the
        automatic threshold of :func:`sdfcodec.search.engine.auto_threshold` is used.
    out_dir : path, optional
        Write ``search.png`` (Fig. 7-style picture) and, with ``mesh``, ``expanded.ply`` there.
    as_json : bool
        Include every selected block as ``{"coords": [x, y, z], "score": s}`` (``"blocks"``).
    device : str, optional
        Where distances are computed and blocks decoded (default CUDA when available).
    mesh : bool
        With ``out_dir``, decode the selected blocks and write their mesh.
    overwrite : bool
        Replace existing files in ``out_dir``.
    behind, up, tilt :
        For built-in queries: ``"solid"`` / ``"unobserved"``, the up direction (``"x,y,z"`` or 3 numbers) and
        a tilt allowance in degrees (see :func:`sdfcodec.search.query.build_query`); default: what the map records.
    scene : bool
        Floor, ceiling and wall: the map-level stage after scoring (:mod:`sdfcodec.search.scene`); False is
        ``--shape-only``.

    Returns
    -------
    dict
        ``map``, ``codec``, ``code_size``, ``level``, ``query``, ``descriptors``, ``threshold``,
        ``threshold_mode`` ("given", "auto" or "none"), ``top``, ``coded_blocks``, ``selected``,
        ``code_bytes_read``, ``code_bytes_level``, ``code_bytes_full``, ``bytes_read``, ``seconds``,
        ``blocks_per_s``, ``device``, ``scene`` (the map-level stage of floor, ceiling and wall searches: its
        rule, the levels or planes found, what it kept or why it kept nothing; None when it did not run),
        ``threshold_info`` (how the threshold was chosen: ``method``
        "calibrated", "calibrated on shifted copies" or "given", and for calibrated ones the simulated scores), ``context``
        (``behind``, ``up``, each with where it came from, ``weighted_encoding``), ``observed_scoring``,
        ``hint`` (what to try, when nothing was selected), and when written ``picture``, ``mesh``,
        ``expanded`` (``blocks_decoded``, ``code_bytes_read``, ``triangles``); with ``as_json`` also
        ``blocks``.
    """
    m = open_map(map_path)
    out = Path(out_dir) if out_dir is not None else None
    if out is not None and not overwrite:
        clash = [p for p in (out / "search.png", out / "expanded.ply") if p.exists()]
        if clash:
            raise MapExistsError(f"{clash[0]} exists; pass --overwrite to replace it or choose another --out")
        # a path through a file is refused before the search's work (and its notes), not after it
        blocked = next((p for p in (out, *out.parents) if p.exists() and not p.is_dir()), None)
        if blocked is not None:
            raise InvalidValueError(f"--out {out}: Not a directory ({blocked} is a file); choose another --out")
    mode = "given" if threshold is not None else ("none" if top is not None else "auto")
    res = search(m, query, level=level, threshold="auto" if mode == "auto" else threshold, top=top, device=device,
                 keep_scores=True, behind=behind, up=up, tilt=tilt, scene=scene)
    summary: dict[str, Any] = {
        "map": str(map_path), "codec": m.header.codec.id, "code_size": m.code_size, "level": res.level,
        "query": res.query.name, "descriptors": len(res.query), "threshold": res.threshold, "threshold_mode": mode,
        "top": top, "coded_blocks": res.stats["blocks_scored"], "selected": len(res),
        **{k: res.stats[k] for k in ("code_bytes_read", "code_bytes_level", "code_bytes_full", "bytes_read",
                                     "seconds", "blocks_per_s", "device", "threshold_info", "context",
                                     "observed_scoring", "scene")},
    }
    if not len(res):
        summary["hint"] = empty_hint(res, mode, query)
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
        exp: Expansion | None = None
        if mesh and len(res):
            exp = expand(m, res, as_="mesh", device=device)
            import open3d as o3d

            from ..core._atomic import write_file

            def write_mesh(tmp: Path) -> bool:
                # open3d answers False, or True on a full disk: the file must read back whole
                return (o3d.io.write_triangle_mesh(str(tmp), exp.mesh) and
                        len(o3d.io.read_triangle_mesh(str(tmp)).triangles) == len(exp.mesh.triangles))

            ply = write_file(out / "expanded.ply", write_mesh, "writing the mesh")
            summary["mesh"] = str(ply)
            summary["expanded"] = {"blocks_decoded": exp.stats["blocks_decoded"],
                                   "code_bytes_read": exp.stats["code_bytes_read"],
                                   "triangles": len(exp.mesh.triangles)}
        summary["picture"] = str(search_picture(m, res, out / "search.png", mesh=exp.mesh if exp else None,
                                                title=f"{Path(str(map_path)).name}: {res.query.name} search"))
    if as_json:
        summary["blocks"] = [{"coords": [int(c) for c in xyz], "score": float(s)}
                             for xyz, s in zip(res.coords, res.scores)]
    return summary


def empty_hint(res: SearchResult, mode: str, query: str) -> str:
    """What to try when a search selected nothing: the best score against the threshold, and the flags that
    change the query model or the selection."""
    best = float(res.all_scores.min()) if res.all_scores is not None and len(res.all_scores) else None
    if best is None:
        return "the map has no coded blocks to search"
    ctx = res.stats.get("context") or {}
    scene = res.stats.get("scene") or {}
    if scene.get("rejected") or (scene and scene.get("candidates")):
        why = scene.get("rejected") or "no level or plane of the shape was large enough"
        return (f"{scene.get('candidates', 0)} blocks are shaped like a {query}, but the map-level stage kept none: "
                f"{why}; --shape-only selects by shape alone")
    tips = [f"the best block scores {best:.4g} against threshold {res.threshold:.4g}"]
    tips.append("try --top 20 to see the closest blocks, or --threshold above the best score")
    if ctx:
        if ctx.get("up_source", "").startswith("default"):
            tips.append("the map records no up direction: pass --up x,y,z (opposite gravity), or --tilt 10 if the map "
                        "is only roughly level")
        other = "solid" if ctx.get("behind") == "unobserved" else "unobserved"
        tips.append(f"the query assumes behind={ctx.get('behind')} ({ctx.get('behind_source')}); --behind {other} "
                    "if that is wrong")
    return "; ".join(tips)


def format_summary(s: dict, verbose: bool = True) -> str:
    """Human-readable lines for a :func:`search_command` summary: with ``verbose`` the details first, then (always)
    why nothing was selected when nothing was, and one sentence with the headline figures (selected blocks, code
    bytes read, time, end-to-end blocks/s) as the last line (what ``| tail -1`` gives)."""
    def kib(n):
        return "n/a" if n is None else f"{n / 1024:.1f} KiB"

    info = s.get("threshold_info") or {}
    how = s["threshold_mode"]
    if info.get("method") == "calibrated":
        how = (f"calibrated on this map: keeps {info['quantile']:.0%} of {info['samples']} simulated clean "
               f"{s['query']} blocks")
    elif info.get("method") == "calibrated on shifted copies":
        how = (f"calibrated: keeps {info['quantile']:.0%} of {info['samples']} copies of the query's blocks shifted by "
               f"up to {info['shift_voxels']:g} voxel")
    sel = f"threshold {s['threshold']:.4g} ({how})" if s.get("threshold") is not None else "no threshold"
    if s.get("top"):
        sel += f", top {s['top']}"
    lines = [
        f"{s['map']}: {s['codec']}-{s['code_size']}, query '{s['query']}' ({s['descriptors']} descriptors) at level "
        f"{s['level']}, {sel}",
        f"code bytes read {kib(s['code_bytes_read'])} of {kib(s['code_bytes_full'])} for a full read",
    ]
    ctx = s.get("context")
    if ctx:
        lines.insert(1, f"behind={ctx['behind']} ({ctx['behind_source']}); up={ctx['up']} ({ctx['up_source']})")
    sc = s.get("scene")
    if sc:
        if sc.get("height") is not None:
            kept = f"kept the level at {sc['height']:.3f} m along up"
        elif sc.get("rejected"):
            kept = sc["rejected"]
        else:
            kept = f"kept {sc.get('kept', 0)} blocks on large planes"
        lines.append(f"map-level stage: {sc['rule']}; {sc.get('candidates', 0)} candidates, {kept}"
                     + (f" ({sc['kept_over_threshold']} partly observed blocks over the threshold joined their plane)"
                        if sc.get("kept_over_threshold") else ""))
        pc = sc.get("plane_check")
        if pc:
            planes = pc.get("planes", [])
            lines.append(f"plane check: {pc['rule']}; {sum(p.get('checked', 0) for p in planes)} blocks on "
                         f"{len(planes)} plane(s) checked, {pc.get('selected', 0)} selected")
    if not verbose:
        lines = []
    if s.get("hint"):
        lines.append(f"nothing selected: {s['hint']}")
    headline = (f"selected {s['selected']} of {s['coded_blocks']} coded blocks for '{s['query']}', "
                f"{kib(s['code_bytes_read'])} of codes read, in {s['seconds']:.2f} s ({s['blocks_per_s'] or 0:,.0f} "
                f"blocks/s end to end on {s['device']}" + (", building and calibrating the query included)"
                                                           if s.get("built") else ")"))
    if "expanded" in s:
        e = s["expanded"]
        headline += (f", expanded {e['blocks_decoded']} ({kib(e['code_bytes_read'])} of codes read, "
                     f"{e['triangles']:,} triangles)")
    wrote = [p for p in (s.get("mesh"), s.get("picture")) if p]
    if wrote:
        headline += "; wrote " + " and ".join(map(str, wrote))
    return "\n".join(lines + [headline])
