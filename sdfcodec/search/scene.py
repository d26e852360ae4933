"""The map-level stage of a search: what a structural query means in the scene, decided after code-space scoring.

A shape model cannot tell a floor from a table top (both are up-facing planes), a ceiling from the underside of
a shelf, or a wall from the side of a cabinet. The map can: every block the code-space stage selected carries
its nearest descriptor, whose rotation and offset place a plane in the map's grid, so the selected blocks can be
grouped into connected planar patches (neighbouring blocks whose planes agree) and the patches compared by
height along ``up`` and by extent. :func:`scene_select` keeps

* ``"floor"``: the lowest large up-facing level (patches at one height along ``up``): the surface everything
  else stands on. Table and counter tops are higher levels;
* ``"ceiling"``: the highest large down-facing level, and only where it closes the map from above (little of
  the map's surface lies above it): a map that never saw its ceiling selects none, rather than the undersides
  of tables and shelves;
* ``"wall"``: vertical planar patches that are large: at least :data:`WALL_SHARE` of the largest vertical
  patch's blocks and :data:`MIN_PATCH_BLOCKS` blocks. Furniture sides are small patches.

Candidates are the blocks scoring up to :data:`WEAK_FACTOR` times the threshold; a patch is kept only when at
least one of its blocks scores under the threshold itself (hysteresis, as in edge detection: a block whose
surface fusion observed too little to score well still joins the plane it continues).

Everything here is in voxels or relative to the map itself (its largest patch, its coded blocks); the one scale
in metres is none: heights are compared in voxels of the map. What was decided, and why, is in the ``info``
dict the search reports (``stats["scene"]``).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

import numpy as np

from ..core._validate import BLOCK
from ..errors import InvalidValueError

if TYPE_CHECKING:
    from .models import QueryModel

__all__ = [
    "SCENE_QUERIES",
    "WEAK_FACTOR",
    "PLANE_TOL_VOXELS",
    "PLANE_ANGLE_DEG",
    "ANGLE_SLACK_DEG",
    "LEVEL_TOL_VOXELS",
    "LEVEL_SHARE",
    "WALL_SHARE",
    "MIN_PATCH_BLOCKS",
    "MAP_SHARE",
    "BEYOND_SHARE",
    "block_planes",
    "plane_components",
    "plane_levels",
    "scene_select",
]

#: The built-in queries with a map-level meaning.
SCENE_QUERIES: tuple[str, ...] = ("floor", "ceiling", "wall")
#: Blocks scoring up to this multiple of the threshold are candidates that may join a patch holding a block
#: under the threshold.
WEAK_FACTOR = 2.0
#: Neighbouring blocks lie on one plane when each one's plane passes within this many voxels of the other's
#: plane point (planes a voxel apart are one surface to the offset lattice, plus a voxel of fusion noise)...
PLANE_TOL_VOXELS = 2.0
#: ... and their normals agree within this angle (degrees): one step of the wall model's yaws (15 degrees apart,
#: so that any wall is within 7.5 degrees of one), so blocks of a wall between two yaws agree whichever one each
#: is nearest to.
PLANE_ANGLE_DEG = 15.0
#: Normals exactly PLANE_ANGLE_DEG apart agree: the model's neighbouring yaws, stored as float32 rotations, lie
#: 15 degrees apart give or take 1e-4, and without this slack rounding alone split a wall between two yaws into
#: patches that never joined (the kitchen's side wall).
ANGLE_SLACK_DEG = 1e-3
#: Patches whose heights along up differ by less than this (voxels) are one level (one floor seen in pieces).
LEVEL_TOL_VOXELS = 4.0
#: A level is large when it holds at least this share of the largest level's blocks (and MIN_PATCH_BLOCKS).
LEVEL_SHARE = 0.2
#: A vertical patch is a wall when it holds at least this share of the largest vertical patch's blocks.
WALL_SHARE = 0.2
#: The fewest blocks of a floor level, a ceiling level or a wall.
MIN_PATCH_BLOCKS = 3
#: A floor or ceiling level also covers at least this share of the map's footprint (the block columns along up
#: that hold coded blocks): the few blocks of a shelf's underside at the top of a map that never saw its
#: ceiling are not a ceiling.
MAP_SHARE = 0.1
#: A ceiling closes the map from above: at most this share of the map's coded blocks lies above it (a block or
#: more); a floor, from below. Beyond it the level is not the floor or ceiling the query means.
BEYOND_SHARE = 0.03


def _cos_within(degrees: float) -> float:
    """The cosine a normals' dot product must reach to lie within ``degrees`` (:data:`ANGLE_SLACK_DEG` included)."""
    return math.cos(math.radians(degrees + ANGLE_SLACK_DEG))


def block_planes(model: QueryModel, coords: np.ndarray, nearest: np.ndarray, origin: np.ndarray, voxel_size: float
                 ) -> tuple[np.ndarray, np.ndarray]:
    """The plane of each block's nearest plane descriptor, in the map's grid.

    Parameters
    ----------
    model : QueryModel
        A built-in plane model (floor, ceiling, wall): ``rotations`` ``(M, 3, 3)`` and ``positions`` ``(M, 3)``.
    coords : np.ndarray
        ``(N, 3)`` int64 block indices.
    nearest : np.ndarray
        ``(N,)`` int64 index of each block's nearest descriptor.
    origin, voxel_size :
        The map's (metres).

    Returns
    -------
    normals : np.ndarray
        ``(N, 3)`` float64 unit normals pointing into free space.
    points : np.ndarray
        ``(N, 3)`` float64 metres: the point of the plane nearest the block's centre.
    """
    r = np.asarray(model.rotations, np.float64)[nearest]
    off = np.asarray(model.positions, np.float64)[nearest, 2]
    normals = r[:, :, 2]
    centres = np.asarray(origin, np.float64) + voxel_size * (BLOCK * np.asarray(coords, np.float64) + (BLOCK - 1) / 2)
    return normals, centres + voxel_size * off[:, None] * normals


def plane_components(coords: np.ndarray, normals: np.ndarray, points: np.ndarray, voxel_size: float) -> np.ndarray:
    """Connected planar patches: blocks ``(N, 3)`` joined when they are neighbours (26-connected) and their
    planes agree (normals within :data:`PLANE_ANGLE_DEG`, each plane within :data:`PLANE_TOL_VOXELS` of the
    other's point). Returns ``(N,)`` int64 patch labels ``0..P-1``."""
    c = np.asarray(coords, np.int64)
    n = len(c)
    if n == 0:
        return np.zeros(0, np.int64)
    lo = c.min(axis=0) - 1
    dims = c.max(axis=0) - lo + 2
    key = np.ravel_multi_index((c - lo).T, dims)
    order = np.argsort(key)
    skey = key[order]
    cos_a = _cos_within(PLANE_ANGLE_DEG)
    tol = PLANE_TOL_VOXELS * voxel_size
    rows, cols = [], []
    # the 13 neighbour offsets of one half of the 26-neighbourhood: each pair once
    offs = [(i, j, k) for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1) if (i, j, k) > (0, 0, 0)]
    for o in offs:
        nk = np.ravel_multi_index((c + np.asarray(o) - lo).T, dims)
        pos = np.searchsorted(skey, nk)
        pos = np.minimum(pos, n - 1)
        hit = skey[pos] == nk
        a = np.flatnonzero(hit)
        b = order[pos[hit]]
        d = points[b] - points[a]
        ok = ((np.einsum("ij,ij->i", normals[a], normals[b]) >= cos_a)
              & (np.abs(np.einsum("ij,ij->i", normals[a], d)) <= tol)
              & (np.abs(np.einsum("ij,ij->i", normals[b], d)) <= tol))
        rows.append(a[ok])
        cols.append(b[ok])
    return _components(n, np.concatenate(rows), np.concatenate(cols))


def _components(n: int, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Labels ``(n,)`` int64 of the connected components of the undirected graph of ``n`` nodes and edges
    ``a[i] - b[i]``, numbered in the order of their lowest node (as ``scipy.sparse.csgraph.connected_components``
    numbers them; its import is a quarter of a second of a warm search's start, for graphs of a few hundred
    blocks): each node takes the lowest label among its neighbours', labels jump to their label's, until stable."""
    lab = np.arange(n)
    while len(a):
        low = np.minimum(lab[a], lab[b])
        new = lab.copy()
        np.minimum.at(new, a, low)
        np.minimum.at(new, b, low)
        new = new[new]
        if np.array_equal(new, lab):
            break
        lab = new
    return np.unique(lab, return_inverse=True)[1].astype(np.int64).reshape(n)


def _fit_plane(normals: np.ndarray, points: np.ndarray, voxel_size: float) -> tuple[np.ndarray, float]:
    """A plane ``(n, d)`` (``n . p = d``, metres) through block plane points ``(K, 3)``: the least-squares plane when
    the points spread over at least two blocks in two directions and its normal is within 30 degrees of the
    descriptors' mean normal (a surface a few degrees off the models' up is fitted as it is), else the mean
    normal through their centroid."""
    mean_n = normals.mean(axis=0)
    mean_n /= max(np.linalg.norm(mean_n), 1e-12)
    mu = points.mean(axis=0)
    if len(points) >= 3:
        _, sv, vt = np.linalg.svd(points - mu, full_matrices=False)
        n = vt[2] * (1.0 if vt[2] @ mean_n >= 0 else -1.0)
        if sv[1] / math.sqrt(len(points)) >= 0.5 * BLOCK * voxel_size and n @ mean_n >= math.cos(math.radians(30)):
            return n, float(n @ mu)
    return mean_n, float(mean_n @ mu)


def plane_levels(comp: np.ndarray, normals: np.ndarray, points: np.ndarray, live: np.ndarray, voxel_size: float
                 ) -> tuple[np.ndarray, list[dict]]:
    """Patches on one plane (a floor seen in pieces, a wall behind furniture) grouped into *levels*: patches in
    order of size join the first level whose plane their blocks' plane points lie within
    :data:`LEVEL_TOL_VOXELS` of (median) with normals within :data:`PLANE_ANGLE_DEG`, else start a level with
    their own fitted plane. Only ``live`` patches (holding a block under the threshold) are grouped.

    Returns ``(level of each patch, -1 for dead ones)`` and the levels (``normal``, ``d``, ``blocks``)."""
    n_comp = int(comp.max()) + 1 if len(comp) else 0
    size = np.bincount(comp, minlength=n_comp)
    level = np.full(n_comp, -1, np.int64)
    levels: list[dict] = []
    cos_a = _cos_within(PLANE_ANGLE_DEG)
    tol = LEVEL_TOL_VOXELS * voxel_size
    members = np.argsort(comp, kind="stable")
    bounds = np.r_[0, np.cumsum(size)]
    for k in np.argsort(-size, kind="stable"):
        if not live[k]:
            continue
        idx = members[bounds[k]:bounds[k + 1]]
        nk, pk = normals[idx], points[idx]
        mean_n = nk.mean(axis=0)
        mean_n /= max(np.linalg.norm(mean_n), 1e-12)
        for j, lv in enumerate(levels):
            if mean_n @ lv["normal"] >= cos_a and np.median(np.abs(pk @ lv["normal"] - lv["d"])) <= tol:
                level[k] = j
                lv["blocks"] += len(idx)
                break
        else:
            n, d = _fit_plane(nk, pk, voxel_size)
            level[k] = len(levels)
            levels.append({"normal": n, "d": d, "blocks": len(idx)})
    return _merge_levels(level, levels, comp, normals, points, voxel_size)


def _merge_levels(level: np.ndarray, levels: list[dict], comp: np.ndarray, normals: np.ndarray, points: np.ndarray,
                  voxel_size: float) -> tuple[np.ndarray, list[dict]]:
    """Levels that are one plane, merged: a level's plane is its largest patch's, and a small patch's fit (or the
    model's nearest yaw, 7.5 degrees off at worst) tilts it by a few degrees, so the far patches of one wall or
    floor miss its :data:`LEVEL_TOL_VOXELS` (measured: the kitchen's side wall, 10 degrees from the models' nearest
    yaw, was four levels of 11, 6, 6 and 5 blocks, and its 17 blocks outside the first were dropped as small
    levels). Two levels merge when the plane fitted through both levels' block plane points lies within
    :data:`PLANE_TOL_VOXELS` (median) of each level's points, and its normal within :data:`PLANE_ANGLE_DEG` of
    both (so only levels whose normals agree within twice that angle are tried: a wall between two of the model's
    yaws is levels of either yaw, 15 degrees apart, that a check of their own normals within one step missed);
    the largest levels first, until nothing merges."""
    if len(levels) < 2:
        return level, levels
    cos_a = _cos_within(PLANE_ANGLE_DEG)
    cos_2a = _cos_within(2 * PLANE_ANGLE_DEG)  # implied by the fit's check below: a filter
    tol = PLANE_TOL_VOXELS * voxel_size
    of = level[comp]  # each block's level
    owner = list(range(len(levels)))  # what each level merged into
    # pairs found not to merge, by what each level holds then: a pass after a merge tries only the pairs that
    # changed (the same decisions as trying every pair again, without refitting the ones that cannot have changed)
    apart: set[tuple] = set()
    merged = True
    while merged:
        merged = False
        alive = sorted({owner[j] for j in range(len(levels))}, key=lambda j: -levels[j]["blocks"])
        for a in alive:
            for b in alive:
                if b == a or levels[b]["blocks"] > levels[a]["blocks"] or owner[b] != b or owner[a] != a:
                    continue
                la, lb = levels[a], levels[b]
                if la["normal"] @ lb["normal"] < cos_2a:
                    continue
                pair = tuple(tuple(j for j in range(len(levels)) if owner[j] == o) for o in (a, b))
                if pair in apart:
                    continue
                ia = np.flatnonzero(np.isin(of, pair[0]))
                ib = np.flatnonzero(np.isin(of, pair[1]))
                both = np.r_[ia, ib]
                n, d = _fit_plane(normals[both], points[both], voxel_size)
                if (n @ la["normal"] < cos_a or n @ lb["normal"] < cos_a
                        or np.median(np.abs(points[ia] @ n - d)) > tol or np.median(np.abs(points[ib] @ n - d)) > tol):
                    apart.add(pair)
                    continue
                la.update(normal=n, d=d, blocks=la["blocks"] + lb["blocks"])
                owner = [a if o == b else o for o in owner]
                merged = True
    keep = sorted({owner[j] for j in range(len(levels))})
    new_id = {j: i for i, j in enumerate(keep)}
    remap = np.array([new_id[owner[j]] for j in range(len(levels))], np.int64)
    return np.where(level >= 0, remap[np.maximum(level, 0)], -1), [levels[j] for j in keep]


def _plane_json(level: dict) -> dict:
    """A level's plane ``n . p = d`` (metres, ``n`` into free space) as JSON, for the plane check that follows."""
    return {"normal": [float(v) for v in level["normal"]], "d": float(level["d"])}


def _footprint(coded: np.ndarray, up: np.ndarray) -> int:
    """How many block-sized cells across ``up`` hold coded blocks (the map seen from above)."""
    if not len(coded):
        return 0
    ref = np.array([1.0, 0.0, 0.0]) if abs(up[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = ref - (ref @ up) * up
    u /= np.linalg.norm(u)
    v = np.cross(up, u)
    c = np.asarray(coded, np.float64)
    cells = np.round(np.stack([c @ u, c @ v], axis=1)).astype(np.int64)
    return int(len(np.unique(cells, axis=0)))


def scene_select(query: str, model: QueryModel, coords: np.ndarray, scores: np.ndarray, nearest: np.ndarray,
                 threshold: float, coded: np.ndarray, origin: np.ndarray, voxel_size: float,
                 has_surface: Any = None) -> tuple[np.ndarray, dict]:
    """Keep the candidates that are what ``query`` means in this map (module docstring).

    Parameters
    ----------
    query : str
        One of :data:`SCENE_QUERIES`.
    model : QueryModel
        The built-in plane model the candidates were scored against (its ``up``, rotations and positions).
    coords, scores, nearest : np.ndarray
        The candidates: ``(N, 3)`` int64 block indices, ``(N,)`` scores (up to ``WEAK_FACTOR * threshold``) and
        nearest descriptors.
    threshold : float
        The selection threshold (candidates above it are weak).
    coded : np.ndarray
        ``(B, 3)`` int64 indices of every coded block of the map (what lies above or below a level).
    origin, voxel_size :
        The map's.
    has_surface : callable, optional
        ``coords (K, 3) -> (K,) bool``: which coded blocks hold a surface (an exact SDF codes the solid around a
        room too); only those count as lying beyond a level. Default: every coded block.

    Returns
    -------
    keep : np.ndarray
        ``(N,)`` bool.
    info : dict
        JSON-able: the rule, the levels found (height, normal, blocks), what was kept and why.
    """
    up = np.asarray(model.up, np.float64)
    n = len(coords)
    strong = scores <= threshold
    info: dict = {"query": query, "candidates": int(n), "under_threshold": int(strong.sum()),
                  "weak_factor": WEAK_FACTOR}
    keep = np.zeros(n, bool)
    if n == 0:
        info.update(kept=0, rule="no candidates")
        return keep, info
    normals, points = block_planes(model, coords, nearest, origin, voxel_size)
    comp = plane_components(coords, normals, points, voxel_size)
    n_comp = int(comp.max()) + 1
    centres = np.asarray(origin) + voxel_size * (BLOCK * np.asarray(coded, np.float64) + (BLOCK - 1) / 2)
    # levels anchored by a block under the threshold; a floor or ceiling found no other way is then looked for
    # among the weak candidates too. The threshold keeps 99 % of clean planes at offsets drawn across a block,
    # but a level floor has one offset for all its blocks: at the offset the model's lattice fits worst (a floor
    # exactly on a layer of voxel centres) every block of it scores just over the threshold, and the whole floor
    # was lost (fused-style rooms of seed 8201: 0 of 312 floor blocks). A weak level must pass the same rules
    # (its size, its share of the map's footprint, nothing beyond it), and each block the plane check.
    anchors = ("strong", "weak") if query in ("floor", "ceiling") else ("strong",)
    for anchor in anchors:
        live = (np.bincount(comp, weights=strong, minlength=n_comp) > 0 if anchor == "strong"
                else np.ones(n_comp, bool))
        level, levels = plane_levels(comp, normals, points, live, voxel_size)
        lv_of = level[comp]  # each candidate's level (-1: its patch holds no block under the threshold)
        if not levels:
            continue
        sizes = np.array([lv["blocks"] for lv in levels])
        least = max(MIN_PATCH_BLOCKS, (LEVEL_SHARE if query != "wall" else WALL_SHARE) * sizes.max())
        if query != "wall":
            least = max(least, MAP_SHARE * _footprint(coded, up))
        large = sizes >= least
        report = []
        for j, lv in enumerate(levels):
            on = lv_of == j
            report.append({"height": round(float(np.median(points[on] @ up)), 4),
                           "normal": [round(float(x), 4) for x in lv["normal"]], "blocks": int(lv["blocks"]),
                           "large": bool(large[j])})
        if query not in ("floor", "ceiling"):
            break
        sign = 1.0 if query == "floor" else -1.0  # the floor is the lowest level, the ceiling the highest
        word, end = ("below", "lowest") if query == "floor" else ("above", "highest")
        margin = (BLOCK + PLANE_TOL_VOXELS) * voxel_size
        order = sorted(range(len(levels)), key=lambda j: sign * report[j]["height"])
        chosen = next((j for j in order if large[j]), None)
        info.pop("rejected", None)
        if chosen is None:
            info["rejected"] = f"no level of {query}-shaped blocks holds {least:.0f} blocks: no {query} in view"
        if chosen is not None:
            lv = levels[chosen]
            # signed distance of every coded block's centre to the level's plane, along the side it faces
            past = (centres @ lv["normal"] - lv["d"]) < -margin
            if has_surface is not None and past.any():
                past[past] = has_surface(np.asarray(coded)[past])
            beyond = float(np.mean(past)) if len(centres) else 0.0
            report[chosen]["beyond_share"] = round(beyond, 4)
            if beyond > BEYOND_SHARE:
                info["rejected"] = (f"the {end} large level ({report[chosen]['height']:.3f} m along up) has "
                                    f"{beyond:.0%} of the map's coded blocks {word} it: no {query} in view")
                chosen = None
        if chosen is not None:
            break
    if not levels:  # no level at all (for a floor or ceiling: not even of weak candidates)
        info.update(kept=0, levels=[], rule="no level holds a block under the threshold")
        return keep, info
    info["anchored_by"] = ("blocks under the threshold" if anchor == "strong" else
                           "candidates under the weak threshold (no level of blocks under the threshold qualified)")
    if query in ("floor", "ceiling"):
        if chosen is not None:
            keep = lv_of == chosen
            info["planes"] = [_plane_json(levels[chosen])]
            info["height"] = report[chosen]["height"]
            info["chosen_level"] = int(chosen)
        info["rule"] = (f"{query}: the {end} level of {'up' if query == 'floor' else 'down'}-facing planar patches "
                        f"holding at least {LEVEL_SHARE:.0%} of the largest level's blocks and covering "
                        f"{MAP_SHARE:.0%} of the map's footprint ({least:.0f} blocks), with at most {BEYOND_SHARE:.0%} of the map's coded blocks {word} it")
    elif query == "wall":
        keep = (lv_of >= 0) & large[np.maximum(lv_of, 0)]
        info["planes"] = [_plane_json(lv) for lv, big in zip(levels, large) if big]
        info["rule"] = (f"wall: vertical planes (patches grouped by plane) holding at least {WALL_SHARE:.0%} of the "
                        f"largest one's blocks (and {MIN_PATCH_BLOCKS})")
    else:
        raise InvalidValueError(f"no scene rule for query {query!r}: the scene stage knows floor, ceiling and wall")
    info["levels"] = sorted(report, key=lambda r: -r["blocks"])[:16]
    info["kept"] = int(keep.sum())
    info["kept_over_threshold"] = int((keep & ~strong).sum())
    return keep, info
