"""Rerun recordings of a map: its mesh, a code-space search's scores and selection, a trajectory against ground
truth (the work behind ``sdfcodec view``).

:func:`write_recording` writes one ``.rrd`` file with rerun's file sink (no viewer, no network, nothing
spawned); open it with ``rerun FILE.rrd`` (the viewer ships with ``pip install 'sdfcodec[view]'``). Every
position is in the map's world frame, in metres. The recording's entities (:data:`ENTITIES`):

``world``
    View coordinates: right-handed, +z up.
``world/map``
    A rotation taking the map's up direction (its header's ``up``, else +z) to +z, so the viewer shows the map
    level whatever its grid's axes; everything below is in the map's own frame.
``world/map/mesh``
    Marching cubes of the decoded blocks (:func:`sdfcodec.fusion.tsdf.mesh_from_blocks`); with a search, each
    vertex coloured by the score of its block.
``world/map/search/scores``
    One point per scored block at the block's centre, coloured by its score (log scale, bright = close to
    the query; the same colours as ``sdfcodec search``'s picture); the raw scores ride along as ``score``.
``world/map/search/selected``
    One box per selected block (the block's extent).
``world/map/trajectory/estimate``, ``.../groundtruth``
    The camera positions as a line strip and as points (one per pose of the file).
``world/map/trajectory/errors``
    With ground truth: a segment from each associated estimated position to its ground-truth position.
``summary``
    A markdown note of what the recording holds and its headline figures.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InvalidValueError, MissingDependencyError
from ..map import Map, open_map

__all__ = ["write_recording", "require_rerun", "up_rotation", "score_colours", "ENTITIES", "RERUN_VERSION"]

#: The rerun-sdk release the recordings are written with (pinned by the ``view`` extra).
RERUN_VERSION = "0.41.0"

ENTITIES = {
    "world": "world", "map": "world/map", "mesh": "world/map/mesh", "scores": "world/map/search/scores",
    "selected": "world/map/search/selected", "estimate": "world/map/trajectory/estimate",
    "groundtruth": "world/map/trajectory/groundtruth", "errors": "world/map/trajectory/errors",
    "summary": "summary",
}

# viridis at six stops, reversed so that a low score (close to the query) is bright yellow, as in
# search_picture; a fixed table keeps matplotlib out of the recording's dependencies
_STOPS = np.array([[253, 231, 37], [122, 209, 81], [34, 168, 132], [42, 120, 142], [65, 68, 135], [68, 1, 84]],
                  np.float64)


def require_rerun():
    """The ``rerun`` module, or a MissingDependencyError naming the extra that installs it."""
    try:
        import rerun as rr
    except ImportError as exc:
        raise MissingDependencyError("writing a Rerun recording needs rerun-sdk: pip install 'sdfcodec[view]'") from exc
    return rr


def up_rotation(up) -> np.ndarray:
    """The rotation ``(3, 3)`` taking the unit vector ``up`` to +z by the shortest arc (identity for +z; a half
    turn about x for -z)."""
    u = np.asarray(up, np.float64)
    u = u / np.linalg.norm(u)
    z = np.array([0.0, 0.0, 1.0])
    c = float(u @ z)
    if c > 1 - 1e-12:
        return np.eye(3)
    if c < -1 + 1e-12:
        return np.diag([1.0, -1.0, -1.0])
    k = np.cross(u, z)
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + kx + kx @ kx / (1 + c)  # Rodrigues with sin = |k|, 1 - cos = |k|^2 / (1 + c)


def score_colours(scores: np.ndarray) -> np.ndarray:
    """``(N, 3)`` uint8 colours of search scores on a log scale between their minimum and maximum (scores
    below 1e-3 count as 1e-3): bright yellow for the closest, dark purple for the farthest."""
    s = np.log(np.maximum(np.asarray(scores, np.float64), 1e-3))
    if not len(s):
        return np.zeros((0, 3), np.uint8)
    span = s.max() - s.min()
    x = (s - s.min()) / span if span > 0 else np.zeros_like(s)
    pos = x * (len(_STOPS) - 1)
    i = np.minimum(pos.astype(int), len(_STOPS) - 2)
    f = (pos - i)[:, None]
    return np.round(_STOPS[i] * (1 - f) + _STOPS[i + 1] * f).astype(np.uint8)


def _block_centres(m: Map, coords: np.ndarray) -> np.ndarray:
    # voxel i sits at origin + i * voxel_size; a block spans voxels 16c .. 16c + 15, so its centre is 16c + 7.5
    return np.asarray(m.origin) + m.voxel_size * (16 * np.asarray(coords, np.float64).reshape(-1, 3) + 7.5)


def _trajectory(x: Any, name: str):
    from ..core.trajectory import Trajectory, as_trajectory, read_tum

    if x is None or isinstance(x, Trajectory):
        return x
    if isinstance(x, (str, os.PathLike)):
        return read_tum(x)
    return as_trajectory(x, name)


def write_recording(map: Map | str | os.PathLike, path: str | os.PathLike, *, query: Any = None,
                    level: int | None = None, threshold: float | str | None = "auto", top: int | None = None,
                    search_result: Any = None, trajectory: Any = None, groundtruth: Any = None,
                    max_diff: float = 0.02, device: str | None = None, mesh: Any = None,
                    application_id: str = "sdfcodec") -> dict:
    """Write a Rerun recording (``.rrd``) of a map, optionally a search of it and a trajectory in it.

    Parameters
    ----------
    map : Map or path/URL
        The map (``open_map``).
    path : path
        The ``.rrd`` file to write (replaced if it exists; the CLI writes beside and renames).
    query : str, path or QueryModel, optional
        Search the map's codes (:func:`sdfcodec.search.engine.search` with ``keep_scores``) and record every block's
        score and the selected blocks. ``level``, ``threshold`` (default: the automatic one), ``top`` and
        ``device`` are passed to the search; ``level`` also decodes the mesh at that prefix level.
    search_result : SearchResult, optional
        A search already run with ``keep_scores=True`` (instead of ``query``), e.g. the demo's.
    trajectory, groundtruth : path, Trajectory or poses ``(N, 4, 4)``, optional
        TUM files (``timestamp tx ty tz qx qy qz qw``, camera-to-world, in the map's world frame) or
        trajectories. With both, the poses are associated by timestamp (within ``max_diff`` seconds) and the
        ATE (no alignment: both are in the map's frame) is recorded and returned.
    mesh : open3d TriangleMesh, optional
        The map's mesh when the caller has it already (default: decoded and meshed here).

    Returns
    -------
    dict
        ``output``, ``map``, ``codec``, ``up`` and ``up_source``, ``mesh`` (``vertices``, ``triangles``),
        with a search ``search`` (``query``, ``level``, ``threshold``, ``scored``, ``selected``), with a
        trajectory ``trajectory`` (``poses``, and with ground truth ``groundtruth_poses``, ``associated``,
        ``ate_rmse``, ``ate_mean``, ``ate_max`` in metres), and ``entities``: each entity written and how
        many items it holds.
    """
    rr = require_rerun()
    from ..fusion.tsdf import mesh_from_blocks

    m = map if isinstance(map, Map) else open_map(map)
    if groundtruth is not None and trajectory is None:
        raise InvalidValueError("ground truth needs a trajectory to compare with: give --trajectory too")
    if query is not None and search_result is not None:
        raise InvalidValueError("give a query or a search result, not both")
    est, gt = _trajectory(trajectory, "trajectory"), _trajectory(groundtruth, "groundtruth")
    res = search_result
    if query is not None:
        from ..search.engine import search

        res = search(m, query, level=level, threshold=threshold, top=top, device=device, keep_scores=True)
    if res is not None and res.all_scores is None:
        raise InvalidValueError("the search result lacks every block's score: search with keep_scores=True")
    if mesh is None:
        pairs = list(m.iter_blocks(level=level))
        if pairs:
            coords, blocks = zip(*pairs)
            mesh = mesh_from_blocks(np.concatenate(coords), np.concatenate(blocks), origin=m.origin,
                                    voxel_size=m.voxel_size, truncation=m.truncation)
    up = m.header.up
    summary: dict[str, Any] = {"output": str(path), "map": str(m.location), "codec": m.header.codec.id,
                               "up": list(up) if up is not None else [0.0, 0.0, 1.0],
                               "up_source": "header" if up is not None else "default +z (the map records no up)",
                               "entities": {}}
    ent = summary["entities"]
    # open the file ourselves first: a missing or read-only directory is then the OSError it is (naming the
    # file), where rerun's sink would raise a bare RuntimeError
    with open(path, "wb"):
        pass
    rec = rr.RecordingStream(application_id, make_default=False, make_thread_default=False)
    rec.save(str(path))
    with rec:  # leaving the block flushes and finalises the file sink (the .rrd's footer)
        rec.log(ENTITIES["world"], rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        rec.log(ENTITIES["map"], rr.Transform3D(mat3x3=up_rotation(summary["up"])), static=True)
        ent[ENTITIES["map"]] = 1
        nv = nt = 0
        if mesh is not None and len(mesh.triangles):
            verts = np.asarray(mesh.vertices, np.float32)
            nv, nt = len(verts), len(mesh.triangles)
            colours = None
            if res is not None and len(res.all_coords):
                colours = _vertex_colours(m, verts, res.all_coords, res.all_scores)
            rec.log(ENTITIES["mesh"], rr.Mesh3D(
                vertex_positions=verts, triangle_indices=np.asarray(mesh.triangles, np.uint32),
                vertex_normals=np.asarray(mesh.vertex_normals, np.float32) if mesh.has_vertex_normals() else None,
                vertex_colors=colours, albedo_factor=None if colours is not None else [200, 200, 205]), static=True)
            ent[ENTITIES["mesh"]] = nv
        summary["mesh"] = {"vertices": nv, "triangles": nt}
        if res is not None:
            _log_search(rr, rec, m, res, summary)
        if est is not None:
            _log_trajectories(rr, rec, est, gt, max_diff, summary)
        rec.log(ENTITIES["summary"], rr.TextDocument(_summary_text(summary), media_type=rr.MediaType.MARKDOWN),
                static=True)
    return summary


def _vertex_colours(m: Map, verts: np.ndarray, coords: np.ndarray, scores: np.ndarray) -> np.ndarray:
    """Each vertex coloured by the score of the block it lies in (grey where no block was scored)."""
    grid = np.asarray(m.block_states().shape)
    b = np.floor((verts - np.asarray(m.origin)) / (16 * m.voxel_size) + 0.5 / 16).astype(np.int64)
    b = np.clip(b, 0, grid - 1)  # a vertex on the grid's outer face belongs to the last block
    lut = np.full(tuple(grid), -1, np.int64)
    c = np.asarray(coords, np.int64)
    lut[c[:, 0], c[:, 1], c[:, 2]] = np.arange(len(c))
    idx = lut[b[:, 0], b[:, 1], b[:, 2]]
    out = np.full((len(verts), 3), 160, np.uint8)
    pal = score_colours(scores)
    out[idx >= 0] = pal[idx[idx >= 0]]
    return out


def _log_search(rr, rec, m: Map, res, summary: dict) -> None:
    scores = np.asarray(res.all_scores, np.float64)
    cell = 16 * m.voxel_size
    rec.log(ENTITIES["scores"], rr.Points3D(_block_centres(m, res.all_coords), colors=score_colours(scores),
                                            radii=0.15 * cell), rr.AnyValues(score=scores), static=True)
    n = len(res.coords)
    rec.log(ENTITIES["selected"], rr.Boxes3D(centers=_block_centres(m, res.coords), half_sizes=np.full((n, 3), cell / 2),
                                             colors=np.tile([[230, 40, 40]], (n, 1)), radii=0.004), static=True)
    summary["entities"][ENTITIES["scores"]] = len(scores)
    summary["entities"][ENTITIES["selected"]] = n
    summary["search"] = {"query": res.query.name, "level": res.level,
                         "threshold": None if res.threshold is None else float(res.threshold),
                         "scored": len(scores), "selected": n}


def _log_trajectories(rr, rec, est, gt, max_diff: float, summary: dict) -> None:
    from ..core.metrics import ate
    from ..core.trajectory import associate

    info: dict[str, Any] = {"poses": len(est)}
    for key, traj, colour in (("estimate", est, [40, 110, 230]), ("groundtruth", gt, [40, 170, 60])):
        if traj is None:
            continue
        p = np.asarray(traj.positions, np.float32)
        rec.log(ENTITIES[key], rr.LineStrips3D([p], colors=[colour], radii=0.006),
                rr.Points3D(p, colors=[colour], radii=0.012), static=True)
        summary["entities"][ENTITIES[key]] = len(p)
    if gt is not None:
        ref, e = associate(gt, est, max_diff=max_diff)
        st = ate(ref, e)
        segs = np.stack([e.positions, ref.positions], 1).astype(np.float32)
        rec.log(ENTITIES["errors"], rr.LineStrips3D(segs, colors=[[220, 50, 50]], radii=0.003), static=True)
        summary["entities"][ENTITIES["errors"]] = len(segs)
        info.update(groundtruth_poses=len(gt), associated=len(segs), ate_rmse=float(st.rmse),
                    ate_mean=float(st.mean), ate_max=float(st.max))
    summary["trajectory"] = info


def _summary_text(s: dict) -> str:
    lines = [f"# {Path(s['map']).name}", "", f"codec `{s['codec']}`; up {s['up']} ({s['up_source']}); "
             f"positions in metres in the map's frame.", "",
             f"- mesh: {s['mesh']['vertices']:,} vertices, {s['mesh']['triangles']:,} triangles"]
    if "search" in s:
        q = s["search"]
        th = "none" if q["threshold"] is None else f"{q['threshold']:.4g}"
        lines.append(f"- search `{q['query']}` at level {q['level']}: {q['selected']} of {q['scored']} blocks selected "
                     f"(threshold {th}); points coloured by score, bright = close; boxes = selected")
    if "trajectory" in s:
        t = s["trajectory"]
        line = f"- trajectory: {t['poses']} poses (blue)"
        if "ate_rmse" in t:
            line += (f"; ground truth {t['groundtruth_poses']} poses (green), {t['associated']} associated, ATE RMSE "
                     f"{1000 * t['ate_rmse']:.1f} mm (no alignment; red: the error of each pose)")
        lines.append(line)
    return "\n".join(lines) + "\n"
