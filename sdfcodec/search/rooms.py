"""Synthetic labelled rooms: furnished rooms sampled as TSDFs with exact distances and analytic per-block
labels (which blocks hold floor, which face up), for retrieval experiments with known ground truth
(:func:`sdfcodec.search.metrics.evaluate_retrieval`, ``docs/search.md``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any, Sequence

import numpy as np

from ..core._validate import BLOCK
from ..errors import InvalidValueError
from ..core.geometry import rot_x, rot_z

__all__ = ["LabelledRoom", "synthetic_room"]

LABELS_FURNITURE = 3  # sdfcodec.data.scene.LABELS.index("furniture"), checked in block_labels


@dataclass
class LabelledRoom:
    """A synthetic room TSDF with analytic ground truth (from :func:`synthetic_room`).

    Attributes
    ----------
    volume : np.ndarray
        ``(X, Y, Z)`` float32 metres, truncated; voxel ``(i, j, k)`` at ``origin + voxel_size * (i, j, k)``.
    origin : np.ndarray
        ``(3,)`` float64 metres (use it as the map's origin).
    voxel_size : float
    truncation : tuple of float
    scene : sdfcodec.data.scene.RoomScene
        The room's exact primitives, posed in the same world frame, with labels (floor, wall, ceiling,
        furniture).
    rotation : np.ndarray
        ``(3, 3)`` room-to-world rotation (yaw, then tilt); the room's interior is
        ``rotation @ [0, size]`` per axis.
    size : tuple of float
        Interior extent metres (room frame).
    up : np.ndarray
        ``(3,)`` the room's up direction in the world (``rotation @ z``).
    behind : str
        How voxels behind surfaces were stored (see the :mod:`sdfcodec.search` docstring).
    """

    volume: np.ndarray
    origin: np.ndarray
    voxel_size: float
    truncation: tuple[float, float]
    scene: Any
    rotation: np.ndarray
    size: tuple[float, float, float]
    up: np.ndarray
    behind: str

    _OBSERVED_MARGIN = 0.15  # metres beyond the interior still observed (inside the 0.2 m slabs)

    def observed(self, points: np.ndarray) -> np.ndarray:
        """``(...)`` bool: points inside the room's observed region (interior plus 0.15 m, within the slabs)."""
        local = np.asarray(points, dtype=np.float64) @ self.rotation  # world -> room frame (R^T p)
        mg = self._OBSERVED_MARGIN
        return _within(local, np.full(3, -mg), np.asarray(self.size) + mg)

    def block_labels(self, coords: np.ndarray, up_tolerance_deg: float = 20.0) -> dict:
        """Per block, what its surface is: fractions of its *surface voxels* (voxels within one voxel of the
        exact surface, so that both blocks on either side of a surface that passes between them count it: a
        mesh of that surface needs both) that are

        ``"floor"``
            nearest to the floor primitive (``RoomScene.floor_blocks``'s definition);
        ``"up"``
            on an upward-facing surface (the exact SDF's gradient within ``up_tolerance_deg`` of ``up``):
            the floor and the tops of furniture (tables, cabinets, cylinders) alike.

        Also ``"floor_cover"`` and ``"up_cover"``: the fraction of the block's 256 columns (along the grid
        axis nearest ``up``) holding such a surface voxel, and ``"surface_voxels"``: the count. ``"wall"`` and
        ``"ceiling"``: the fractions nearest a wall or the ceiling primitive, with ``"wall_cover"`` and
        ``"ceiling_cover"`` across the grid axis nearest that surface's mean normal in the block. Blocks without
        surface voxels get fractions 0.

        Parameters
        ----------
        coords : np.ndarray
            ``(N, 3)`` int block indices.

        Returns
        -------
        dict of str to np.ndarray
            ``(N,)`` float32 fractions (``"floor"``, ``"up"``, ``"floor_cover"``, ``"up_cover"``) and int64
            counts (``"surface_voxels"``).
        """
        from ..data.scene import LABELS

        coords = np.asarray(coords, dtype=np.int64).reshape(-1, 3)
        vs = self.voxel_size
        band = vs
        n = len(coords)
        # the volume holds the exact distance wherever it is within the truncation, so surface voxels come
        # from it; only they are evaluated primitive by primitive (nearest label, gradient)
        pad = [(0, (-s) % BLOCK) for s in self.volume.shape]
        vol = np.pad(self.volume, pad, constant_values=self.truncation[1])
        g = [s // BLOCK for s in vol.shape]
        view = vol.reshape(g[0], BLOCK, g[1], BLOCK, g[2], BLOCK).transpose(0, 2, 4, 1, 3, 5)
        blk = view[tuple(coords.T)].reshape(n, -1)  # (n, 4096)
        surf = np.abs(blk) <= band
        which, vox = np.nonzero(surf)
        local = np.stack(np.unravel_index(vox, (BLOCK,) * 3), -1)
        pts = self.origin + vs * (BLOCK * coords[which] + local).astype(np.float64)  # (S, 3)
        prim_label = np.array([LABELS.index(lab) for lab in self.scene.labels])
        assert LABELS[LABELS_FURNITURE] == "furniture"
        h = 0.25 * vs
        reach = band + 2 * h  # surface points and their gradient stencils are this close to their surface
        dist, nearest = _union_at(self.scene.primitives, pts, reach)
        is_floor = prim_label[nearest] == LABELS.index("floor")
        grad = np.zeros_like(pts)
        for ax in range(3):  # the exact SDF's gradient, central differences a quarter voxel apart
            e = np.zeros(3)
            e[ax] = h
            grad[:, ax] = (_union_at(self.scene.primitives, pts + e, reach)[0]
                           - _union_at(self.scene.primitives, pts - e, reach)[0]) / (2 * h)
        upward = grad @ self.up >= math.cos(math.radians(up_tolerance_deg)) * np.maximum(np.linalg.norm(grad, axis=1),
                                                                                           1e-12)
        n_surf = np.bincount(which, minlength=n)
        denom = np.maximum(n_surf, 1)
        axis = int(np.argmax(np.abs(self.up)))
        col = np.delete(local, axis, axis=1) @ np.array([BLOCK, 1])  # column index 0..255 across the up axis

        def cover(mask: np.ndarray) -> np.ndarray:
            cells = np.unique(which[mask] * BLOCK * BLOCK + col[mask])
            return (np.bincount(cells // (BLOCK * BLOCK), minlength=n) / (BLOCK * BLOCK)).astype(np.float32)

        out = {"floor": (np.bincount(which, weights=is_floor, minlength=n) / denom).astype(np.float32),
               "up": (np.bincount(which, weights=upward, minlength=n) / denom).astype(np.float32),
               "floor_cover": cover(is_floor), "up_cover": cover(upward), "surface_voxels": n_surf.astype(np.int64)}
        out.update(_structure_shares(which, nearest, prim_label, n_surf))
        poles = np.array([_is_pole(p, self.up, vs) for p in self.scene.primitives])
        side = np.abs(grad @ self.up) <= 0.5 * np.maximum(np.linalg.norm(grad, axis=1), 1e-12)
        out["pole"] = (np.bincount(which, weights=poles[nearest] & side, minlength=n) / denom).astype(np.float32)
        for name in ("floor", "wall", "ceiling"):
            out.update(_section_cover(which, local, dist / vs, nearest, grad, prim_label[nearest] == LABELS.index(name),
                                      n_surf, name))
        for name in ("wall", "ceiling"):
            # cover across the grid axis nearest the block's mean normal of that surface (walls face any way)
            is_lab = prim_label[nearest] == LABELS.index(name)
            g_sum = np.zeros((n, 3))
            np.add.at(g_sum, which[is_lab], grad[is_lab])
            ax_b = np.argmax(np.abs(g_sum), axis=1)[which]
            cells = np.unique(which[is_lab] * 3 * BLOCK * BLOCK + ax_b[is_lab] * BLOCK * BLOCK
                              + np.take_along_axis(np.stack([local[:, 1] * BLOCK + local[:, 2],
                                                             local[:, 0] * BLOCK + local[:, 2],
                                                             local[:, 0] * BLOCK + local[:, 1]], 1),
                                                   ax_b[:, None], 1)[is_lab, 0])
            out[name] = (np.bincount(which, weights=is_lab, minlength=n) / denom).astype(np.float32)
            out[f"{name}_cover"] = (np.bincount(cells // (3 * BLOCK * BLOCK), minlength=n)
                                    / (BLOCK * BLOCK)).astype(np.float32)
        return out


def _structure_shares(which: np.ndarray, nearest: np.ndarray, prim_label: np.ndarray, n_surf: np.ndarray) -> dict:
    """Per block, how its surface voxels spread over the room's structure (floor, wall and ceiling primitives):
    ``structure`` (their share), ``structure_parts`` (how many such primitives hold >= 10 % of the surface
    voxels: 2 on an edge of the room, 3 at a corner) and ``structure_touch`` (how many hold >= 2 %)."""
    n = len(n_surf)
    structural = prim_label[nearest] != LABELS_FURNITURE
    out = {"structure": (np.bincount(which, weights=structural, minlength=n) / np.maximum(n_surf, 1)
                         ).astype(np.float32)}
    k = int(nearest.max()) + 1 if len(nearest) else 1
    u, cnt = np.unique(which[structural] * k + nearest[structural], return_counts=True)
    share = cnt / np.maximum(n_surf[u // k], 1)
    out["structure_parts"] = np.bincount(u // k, weights=share >= 0.1, minlength=n).astype(np.int64)
    out["structure_touch"] = np.bincount(u // k, weights=share >= 0.02, minlength=n).astype(np.int64)
    return out


def _is_pole(prim, up: np.ndarray, voxel_size: float) -> bool:
    """A thin upright primitive: an upright cylinder of radius up to 10 voxels (the pole model's largest), or an
    upright box (a table leg) whose horizontal half-extents are at most that."""
    from ..core.sdf import Box, Cylinder

    axis = np.asarray(prim.rotation, np.float64)[:, 2] if getattr(prim, "rotation", None) is not None else np.eye(3)[2]
    if abs(float(axis @ up)) < math.cos(math.radians(10)):
        return False
    if isinstance(prim, Cylinder):
        return prim.radius <= 10 * voxel_size
    if isinstance(prim, Box):
        return max(prim.half[0], prim.half[1]) <= 10 * voxel_size
    return False


#: :func:`_section_cover`'s cells (voxels a side) on a surface's plane: surface voxels (a band two voxels thick)
#: fill every cell of this size, at any orientation.
_CELL = 2.0


def _section_cover(which: np.ndarray, local: np.ndarray, dist: np.ndarray, nearest: np.ndarray, grad: np.ndarray,
                   is_label: np.ndarray, n_surf: np.ndarray, name: str) -> dict:
    """Per block, how a labelled surface spans it, measured in the surface's own plane (whatever its angle to
    the grid): ``{name}_main``, the share of the block's surface voxels on the label's single largest primitive
    there; ``{name}_section``, the area (voxels squared) of that primitive's plane inside the block's voxels' cells
    (``[-0.5, 15.5]`` per axis: a surface passing between two blocks' voxel layers has none), the plane through
    the surface points of its surface voxels (``local`` moved along the gradient ``grad`` by the distance ``dist``,
    voxels); ``{name}_section_cover``, the share of that section the primitive's surface voxels cover (cells of
    ``_CELL`` voxels). A wall crossing a block obliquely covers its
    whole section; a wall ending inside the block (a door, a corner with another surface) does not."""
    n = len(n_surf)
    main = np.zeros(n, np.float32)
    section = np.zeros(n, np.float32)
    cover = np.zeros(n, np.float32)
    sel = np.flatnonzero(is_label)
    if len(sel):
        # the label's largest primitive in each block
        pair = which[sel] * (int(nearest.max()) + 1) + nearest[sel]
        u, inv, cnt = np.unique(pair, return_inverse=True, return_counts=True)
        blk = u // (int(nearest.max()) + 1)
        best = np.zeros(n, np.int64) - 1
        best_cnt = np.zeros(n, np.int64)
        for k in np.argsort(cnt, kind="stable"):
            best[blk[k]], best_cnt[blk[k]] = u[k] % (int(nearest.max()) + 1), cnt[k]
        main = (best_cnt / np.maximum(n_surf, 1)).astype(np.float32)
        ab = np.arange(-15, 16) * _CELL
        grid_a, grid_b = np.meshgrid(ab, ab, indexing="ij")
        on = sel[nearest[sel] == best[which[sel]]]  # the voxels of each block's largest primitive
        on = on[np.argsort(which[on], kind="stable")]
        starts = np.r_[0, np.flatnonzero(np.diff(which[on])) + 1, len(on)]
        for lo, hi in zip(starts[:-1], starts[1:]):
            b = which[on[lo]]
            gg = grad[on[lo:hi]]
            # the surface points: each surface voxel moved onto the surface along its gradient by its distance. The
            # plane measured passes through them, not through the voxel centres (measured: a tilted floor in a
            # block's top layers, its voxel centres a voxel below it on average, put the plane a voxel low; its
            # cells at the block's face then held no surface voxel, and the strip covered 0.8 of its "section")
            unit = gg / np.maximum(np.linalg.norm(gg, axis=1), 1e-12)[:, None]
            pts = local[on[lo:hi]].astype(np.float64) - dist[on[lo:hi], None] * unit
            # one face of the primitive: a slab thinner than a block shows both faces in it (their gradients
            # cancel); the face holding more of the block's voxels is the one measured
            side = gg @ gg[np.argmax(np.abs(gg).max(axis=1))] >= 0
            if 2 * side.sum() < len(side):
                side = ~side
            pts, g = pts[side], gg[side].sum(axis=0)
            if np.linalg.norm(g) < 1e-9:  # no direction to measure a section across: left uncovered
                continue
            nrm = g / np.linalg.norm(g)
            e1 = np.cross(nrm, [1.0, 0.0, 0.0] if abs(nrm[0]) < 0.9 else [0.0, 1.0, 0.0])
            e1 /= np.linalg.norm(e1)
            e2 = np.cross(nrm, e1)
            p0 = pts.mean(axis=0)
            q = p0 + grid_a[..., None] * e1 + grid_b[..., None] * e2
            inside = np.all((q >= -0.5) & (q <= BLOCK - 0.5), axis=-1)
            hit = np.zeros(inside.shape, bool)
            ij = np.round(np.stack([(pts - p0) @ e1, (pts - p0) @ e2], 1) / _CELL).astype(np.int64) + 15
            ok = np.all((ij >= 0) & (ij < len(ab)), axis=1)
            hit[ij[ok, 0], ij[ok, 1]] = True
            section[b] = inside.sum() * _CELL ** 2
            cover[b] = (hit & inside).sum() / max(int(inside.sum()), 1)
    return {f"{name}_main": main, f"{name}_section": section, f"{name}_section_cover": cover}


def _aabb(prim) -> tuple[np.ndarray, np.ndarray] | None:
    """World bounding box ``(lo, hi)`` of a Box/Cylinder/Sphere primitive (None for others)."""
    from ..core.sdf import Box, Cylinder, Sphere

    c = np.asarray(prim.center, np.float64)
    if isinstance(prim, Sphere):
        return c - prim.radius, c + prim.radius
    if isinstance(prim, Box):
        half = np.asarray(prim.half, np.float64)
    elif isinstance(prim, Cylinder):
        half = np.array([prim.radius, prim.radius, prim.half_height])
    else:
        return None
    ext = half if prim.rotation is None else np.abs(np.asarray(prim.rotation, np.float64)) @ half
    return c - ext, c + ext


def _within(points: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """``(...)`` bool: points ``(..., 3)`` inside the box ``[lo, hi]``, one axis at a time (numpy's ``all`` over
    a last axis of 3 cost more than the comparisons themselves)."""
    out = (points[..., 0] >= lo[0]) & (points[..., 0] <= hi[0])
    for k in (1, 2):
        out &= (points[..., k] >= lo[k]) & (points[..., k] <= hi[k])
    return out


def _union_at(primitives: Sequence, points: np.ndarray, reach: float) -> tuple[np.ndarray, np.ndarray]:
    """Union distance ``(S,)`` and index of the nearest primitive ``(S,)`` at points ``(S, 3)``, evaluating each
    primitive only at points within ``reach`` of its bounding box (exact wherever the union is below
    ``reach``; ``+inf`` and index 0 where no primitive is that close)."""
    d = np.full(len(points), np.inf)
    idx = np.zeros(len(points), np.int64)
    for k, prim in enumerate(primitives):
        box = _aabb(prim)
        sel = (np.flatnonzero(_within(points, box[0] - reach, box[1] + reach))
               if box is not None else np.arange(len(points)))
        if not len(sel):
            continue
        dk = prim(points[sel])
        closer = dk < d[sel]
        d[sel[closer]] = dk[closer]
        idx[sel[closer]] = k
    return d, idx


def _sample_union(primitives: Sequence, shape: tuple[int, int, int], voxel_size: float, origin: np.ndarray,
                  reach: float) -> np.ndarray:
    """Union (minimum) distance of primitives on a lattice, metres float32, evaluating each primitive only
    within ``reach`` metres of its bounding box: elsewhere it cannot bring the union below ``reach`` (the
    distances are 1-Lipschitz), and the result there is ``+inf``."""
    from ..core.sdf import grid_points

    d = np.full(shape, np.inf, np.float32)
    for prim in primitives:
        box = _aabb(prim)
        if box is None:
            lo_i, hi_i = np.zeros(3, int), np.asarray(shape)
        else:
            lo_i = np.clip(np.floor((box[0] - reach - origin) / voxel_size).astype(int), 0, shape)
            hi_i = np.clip(np.ceil((box[1] + reach - origin) / voxel_size).astype(int) + 1, 0, shape)
        if np.any(hi_i <= lo_i):
            continue
        for x0 in range(lo_i[0], hi_i[0], BLOCK):  # slabs of x: bounded memory
            x1 = min(x0 + BLOCK, hi_i[0])
            sub = (slice(x0, x1), slice(lo_i[1], hi_i[1]), slice(lo_i[2], hi_i[2]))
            pts = grid_points((x1 - x0, hi_i[1] - lo_i[1], hi_i[2] - lo_i[2]), voxel_size,
                              origin + voxel_size * np.array([x0, lo_i[1], lo_i[2]]))
            np.minimum(d[sub], prim(pts).astype(np.float32), out=d[sub])
    return d


def _pose(prim, rot: np.ndarray):
    """A primitive of :mod:`sdfcodec.core.sdf` rotated about the world origin by ``rot``."""
    from ..core.sdf import Box, Cylinder, Sphere

    if isinstance(prim, (Box, Cylinder)):
        r = rot if prim.rotation is None else rot @ np.asarray(prim.rotation, np.float64)
        return replace(prim, center=tuple(rot @ np.asarray(prim.center, np.float64)), rotation=r)
    if isinstance(prim, Sphere):
        return replace(prim, center=tuple(rot @ np.asarray(prim.center, np.float64)))
    raise InvalidValueError(f"cannot pose a {type(prim).__name__}")


def synthetic_room(seed: int = 0, *, geometry: str = "normal", size: Sequence[float] | None = None,
                   voxel_size: float = 0.02, truncation: tuple[float, float] = (-0.04, 0.1), tilt_deg: float = 0.0,
                   yaw: bool = True, behind: str = "unobserved") -> LabelledRoom:
    """A furnished room (``sdfcodec.data.render.room_scene`` with a ceiling) sampled as a TSDF with exact
    distances, randomly posed, for retrieval experiments with known labels.

    The floor lands at a random height inside its blocks (the grid's origin is shifted by a random fraction
    of a block), the room is turned by a random yaw about ``z`` (when ``yaw``) and tilted by an angle uniform
    in ``[0, tilt_deg]`` about a random horizontal axis. Voxels behind surfaces follow ``behind``; so do those
    outside the room's observed region (more than 0.15 m beyond its interior): free space ``d_max`` for
    ``"unobserved"`` (the unobserved space around a fused room), solid ``d_min`` for ``"solid"`` (the room is
    a cavity in solid ground).

    Parameters
    ----------
    seed : int
        Deterministic seed (furniture, size, pose).
    geometry : {"poor", "normal", "rich"}
        Furniture (see ``room_scene``): a table and 4 boxes/cylinders for "normal"; 10 pieces including
        rotated boxes, lying cylinders and balls for "rich".
    size : sequence of 3 floats, optional
        Interior metres; default uniform in ``[3, 5] x [3, 4.2] x [2.3, 2.8]``.
    voxel_size, truncation :
        Metres.
    tilt_deg : float
        Largest tilt of the room's up direction from the grid's ``+z``, degrees.
    yaw : bool
        Random rotation about ``z``.
    behind : {"unobserved", "solid"}

    Returns
    -------
    LabelledRoom
    """
    from ..core.sdf import grid_points
    from .shapes import BEHIND, truncate  # here: sdfcodec.search imports this module
    from ..data.render import room_scene
    from ..data.scene import RoomScene

    if behind not in BEHIND:
        raise InvalidValueError(f"behind must be one of {BEHIND}, got {behind!r}")
    rng = np.random.default_rng([seed, 7])
    if size is None:
        size = (rng.uniform(3.0, 5.0), rng.uniform(3.0, 4.2), rng.uniform(2.3, 2.8))
    size = tuple(float(s) for s in size)
    keep_out = max(0.0, min(1.15, (min(size[:2]) - 0.4) / 2 - 0.01))
    room = room_scene(seed, geometry=geometry, ceiling=True, size=size, keep_out=keep_out)
    rot = rot_z(rng.uniform(0, 2 * math.pi)) if yaw else np.eye(3)
    if tilt_deg > 0:
        axis_angle = rng.uniform(0, 2 * math.pi)
        tilt = rng.uniform(0.0, tilt_deg)
        rot = rot_z(axis_angle) @ rot_x(math.radians(tilt)) @ rot_z(-axis_angle) @ rot
    posed = RoomScene([_pose(p, rot) for p in room.primitives], list(room.labels), room.size, room.seed, room.geometry)
    mg = LabelledRoom._OBSERVED_MARGIN
    corners = np.array([[x, y, z] for x in (-mg, size[0] + mg) for y in (-mg, size[1] + mg)
                        for z in (-mg, size[2] + mg)]) @ rot.T
    lo, hi = corners.min(axis=0), corners.max(axis=0)
    origin = lo - rng.uniform(0, BLOCK * voxel_size, 3)  # the floor at a random height within its block
    shape = tuple(int(n) for n in np.ceil((hi - origin) / voxel_size) + 1)
    lab = LabelledRoom(volume=np.empty(shape, np.float32), origin=origin, voxel_size=float(voxel_size),
                       truncation=tuple(truncation), scene=posed, rotation=rot, size=size, up=rot[:, 2].copy(),
                       behind=behind)
    raw = _sample_union(posed.primitives, shape, voxel_size, origin, reach=truncation[1] + voxel_size)
    for x0 in range(0, shape[0], BLOCK):  # slabs of x: bounded memory
        n = min(BLOCK, shape[0] - x0)
        pts = grid_points((n, shape[1], shape[2]), voxel_size, origin + np.array([x0 * voxel_size, 0.0, 0.0]))
        d = truncate(raw[x0:x0 + n], truncation, behind)  # +inf (far from every surface) becomes d_max
        # beyond the room's slabs: never observed (free, like a fused map) or, for solid scenes, the room is
        # a cavity in solid ground (the slabs' far sides would otherwise be more surfaces)
        d[~lab.observed(pts)] = truncation[1] if behind == "unobserved" else truncation[0]
        lab.volume[x0:x0 + n] = d
    return lab
