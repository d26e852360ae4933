"""Synthetic training blocks: exact signed distances of random primitives (the paper's "libsdf" data).

Section IV-A of the paper trains on 16^3 blocks sampled from randomly parametrised, randomly posed
primitives of a few shape categories. This module generates them with exact signed distances:

``"cuboid"``
    A solid box (:class:`~sdfcodec.core.sdf.Box`). A block usually sees only part of it, so planes, convex edges
    and convex corners all appear as fragments of cuboids, as the paper intends.
``"cylinder"``
    A barrel-like solid of revolution (:class:`~sdfcodec.core.sdf.Barrel`) for curved convex edges: half of them
    are straight capped cylinders, the other half bulge along a circular-arc profile (the radius shrinks from
    the middle to the caps by 5-35 % of the smaller of the middle radius and the half height). The
    distance is exact (closed form), not an approximation.
``"concave"``
    A concave room corner (:class:`~sdfcodec.core.sdf.ConcaveCorner`): the free space is an octant (floor and
    two walls, 3 planes) or a quadrant wedge (two walls, the concave 2-plane edge), half each.
``"plane"``
    A half-space (:class:`~sdfcodec.core.sdf.Plane`).

Pose. Each shape gets a rotation drawn uniformly over SO(3) (``scipy.spatial.transform.Rotation.random``
with the seeded generator) and a displacement chosen so that its surface passes through the block: a
random point of the surface (area-uniform on cuboids, roughly so on barrels; on a concave corner, a random
point of the 8-voxel cube in front of the corner moved onto its nearest face, so the edge or corner is
usually in view) is placed uniformly at random in the cube 8 voxels wide at the block's centre. A block whose voxel centres do not include at
least one point inside the solid and one outside (each by more than 0.1 % of a voxel) is drawn again, so
every returned block holds a zero crossing.

Sizes are in voxels, so the shapes keep their size relative to the 16-voxel block whatever the voxel
size: cuboid half extents and barrel half heights are log-uniform in [2, 32] voxels, barrel radii in
[2, 24] voxels. Truncation stays in metres.

Coordinates: voxel ``(i, j, k)`` of a block is at ``voxel_size * (i, j, k)`` metres (the convention of
:func:`sdfcodec.core.sdf.grid_points`), so :func:`synthetic_shapes` returns primitives that reproduce each
block exactly when sampled with ``sample_volume(shape.sdf, (16, 16, 16), voxel_size)``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
from scipy.spatial.transform import Rotation

from ..core.blocks import BLOCK, check_truncation, normalise
from ..errors import InvalidValueError, SamplingError
from ..core.sdf import Barrel, Box, ConcaveCorner, Plane, grid_points

__all__ = ["CATEGORIES", "SyntheticShape", "synthetic_blocks", "synthetic_shapes"]

#: The shape categories, in the order labels and default weights use.
CATEGORIES: tuple[str, ...] = ("cuboid", "cylinder", "concave", "plane")

# Shape parameters, in voxels (see the module docstring).
_BOX_HALF = (2.0, 32.0)  # log-uniform half extent per axis
_BARREL_RADIUS = (2.0, 24.0)  # log-uniform radius at the middle
_BARREL_HALF_HEIGHT = (2.0, 32.0)  # log-uniform
_BARREL_BULGE = (0.05, 0.35)  # bulging half: (radius - cap radius) / min(radius, half height)
_CORNER_REACH = 8.0  # concave corners: anchor within this many voxels of the corner
_CENTRAL_HALF = 4.0  # the anchor lands in the block centre +- this many voxels
_CROSSING_MARGIN = 1e-3  # voxels: both signs must be present by more than this
_CHUNK = 64  # blocks evaluated together: big enough to amortise numpy calls, small enough for the cache
_MAX_REDRAWS = 100  # rounds of redrawing blocks without a zero crossing before giving up


@dataclass(frozen=True)
class SyntheticShape:
    """One generated shape, in the block's coordinates (metres; voxel ``(i, j, k)`` at ``voxel_size * (i, j, k)``).

    Attributes
    ----------
    category : str
        One of :data:`CATEGORIES`.
    sdf : Box | Barrel | ConcaveCorner | Plane
        The exact posed primitive; ``sdf(points (..., 3)) -> (...)`` signed distances in metres.
    rotation : np.ndarray
        ``(3, 3)`` float64, the shape's local-to-block rotation (uniform over SO(3)). For a plane, its normal
        is the third column.
    anchor : np.ndarray
        ``(3,)`` float64 metres, the surface point that was placed in the block's central region.
    """

    category: str
    sdf: Box | Barrel | ConcaveCorner | Plane
    rotation: np.ndarray
    anchor: np.ndarray


def synthetic_blocks(n: int, *, seed: int = 0, voxel_size: float = 0.02,
                     truncation: tuple[float, float] = (-0.04, 0.1),
                     categories: Sequence[str] = CATEGORIES, weights: Sequence[float] | None = None,
                     return_labels: bool = False) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """Generate ``n`` normalised synthetic training blocks.

    Parameters
    ----------
    n : int
        Number of blocks (``>= 0``).
    seed : int
        Seed of the generator; the same arguments always give the same blocks.
    voxel_size : float
        Voxel edge in metres (``> 0``).
    truncation : (float, float)
        ``(d_min, d_max)`` in metres, with ``d_min < 0 < d_max``; distances are clipped to it and then mapped
        to ``[0, 1]`` with :func:`sdfcodec.core.blocks.normalise` (free space 1.0).
    categories : sequence of str, or str
        Which of :data:`CATEGORIES` to draw from (distinct names; one name alone is allowed).
    weights : sequence of float, optional
        Relative frequency of each entry of ``categories`` (non-negative, not all zero); uniform if omitted.
    return_labels : bool
        Also return each block's category.

    Returns
    -------
    blocks : np.ndarray
        ``(n, 16, 16, 16)`` float32 in ``[0, 1]``, indexed (x, y, z). Every block holds a zero crossing.
    labels : np.ndarray
        ``(n,)`` str, the category of each block (only with ``return_labels=True``).

    Raises
    ------
    InvalidValueError
        A parameter is out of range or a category is unknown.
    """
    trunc = _check_truncation(truncation)
    blocks, labels, _ = _generate(n, seed, voxel_size, categories, weights, trunc, want_shapes=False)
    return (blocks, labels) if return_labels else blocks


def synthetic_shapes(n: int, *, seed: int = 0, voxel_size: float = 0.02, categories: Sequence[str] = CATEGORIES,
                     weights: Sequence[float] | None = None) -> list[SyntheticShape]:
    """The exact primitives behind :func:`synthetic_blocks` called with the same arguments.

    ``synthetic_shapes(n, seed=s, ...)[i].sdf`` sampled on the block lattice, truncated and normalised, equals
    ``synthetic_blocks(n, seed=s, ...)[i]`` (the truncation does not change which shapes are drawn).

    Parameters
    ----------
    n, seed, voxel_size, categories, weights
        As for :func:`synthetic_blocks`.

    Returns
    -------
    list of SyntheticShape
        ``n`` shapes, in block order.
    """
    _, _, shapes = _generate(n, seed, voxel_size, categories, weights, None, want_shapes=True)
    return shapes


# --------------------------------------------------------------------------------------------------------------


def _check_truncation(truncation) -> tuple[float, float]:
    try:
        d_min, d_max = (float(t) for t in truncation)
    except (TypeError, ValueError) as exc:
        raise InvalidValueError(f"truncation must be a pair (d_min, d_max) of metres, got {truncation!r}") from exc
    check_truncation(d_min, d_max)
    if not d_min < 0.0 < d_max:
        raise InvalidValueError(f"truncation must satisfy d_min < 0 < d_max so the surface is visible, "
                                f"got [{d_min}, {d_max}]")
    return d_min, d_max


def _check_args(n, voxel_size, categories, weights) -> tuple[list[str], np.ndarray]:
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 0:
        raise InvalidValueError(f"n must be a non-negative integer number of blocks, got {n!r}")
    if not (isinstance(voxel_size, (int, float, np.floating)) and np.isfinite(voxel_size) and voxel_size > 0):
        raise InvalidValueError(f"voxel_size must be a positive number of metres, got {voxel_size!r}")
    cats = [categories] if isinstance(categories, str) else list(categories)
    unknown = [c for c in cats if c not in CATEGORIES]
    if not cats or unknown or len(set(cats)) != len(cats):
        raise InvalidValueError(f"categories must be distinct names from {list(CATEGORIES)}, got {cats!r}")
    if weights is None:
        w = np.full(len(cats), 1.0 / len(cats))
    else:
        try:
            w = np.asarray(weights, dtype=np.float64)
        except (TypeError, ValueError):
            w = np.full(0, np.nan)  # reported below
        if w.shape != (len(cats),) or not np.all(np.isfinite(w)) or np.any(w < 0) or w.sum() <= 0:
            raise InvalidValueError(f"weights must be {len(cats)} non-negative numbers (one per category, not all "
                                    f"zero), got {weights!r}")
        w = w / w.sum()
    return cats, w


def _log_uniform(rng: np.random.Generator, lo_hi: tuple[float, float], size) -> np.ndarray:
    lo, hi = lo_hi
    return np.exp(rng.uniform(np.log(lo), np.log(hi), size=size))


def _generate(n, seed, voxel_size, categories, weights, truncation, *, want_shapes: bool):
    """Blocks ``(n, 16, 16, 16)`` float32 normalised (None without ``truncation``), category names ``(n,)``
    and the shapes (an empty list unless ``want_shapes``)."""
    cats, w = _check_args(n, voxel_size, categories, weights)
    h = float(voxel_size)
    rng = np.random.default_rng(seed)
    cat_idx = rng.choice(len(cats), size=n, p=w)
    points = grid_points((BLOCK,) * 3, h).reshape(-1, 3)
    blocks = None if truncation is None else np.empty((n, points.shape[0]), dtype=np.float32)
    shapes: list = [None] * n if want_shapes else []
    # a fixed chunking (not caller-dependent) keeps the random stream, hence the output, a function of the args
    for start in range(0, n, _CHUNK):
        stop = min(start + _CHUNK, n)
        for c, name in enumerate(cats):
            todo = start + np.flatnonzero(cat_idx[start:stop] == c)
            for _ in range(_MAX_REDRAWS):
                if todo.size == 0:
                    break
                d, params = _draw(name, todo.size, rng, points, h)
                ok = (d.min(axis=1) < -_CROSSING_MARGIN * h) & (d.max(axis=1) > _CROSSING_MARGIN * h)
                if blocks is not None:
                    d_min, d_max = truncation
                    # clip in metres (the truncation), and after normalising so float32 rounding stays in [0, 1]
                    v = normalise(np.clip(d[ok], d_min, d_max), d_min, d_max)
                    blocks[todo[ok]] = np.clip(v, 0.0, 1.0, out=v)
                if want_shapes:
                    for j in np.flatnonzero(ok):
                        shapes[todo[j]] = _make_shape(name, params, j)
                todo = todo[~ok]
            else:  # pragma: no cover - the central anchoring makes a miss rare; 100 misses in a row is a bug
                raise SamplingError(f"could not draw {name} blocks with a zero crossing after {_MAX_REDRAWS} tries")
    if blocks is not None:
        blocks = blocks.reshape(n, BLOCK, BLOCK, BLOCK)
    return blocks, np.asarray(cats, dtype=str)[cat_idx], shapes


def _draw(name: str, m: int, rng: np.random.Generator, points: np.ndarray, h: float):
    """Draw ``m`` posed shapes of one category; return their distances ``(m, M)`` and parameters."""
    rot = Rotation.random(m, rng).as_matrix().reshape(m, 3, 3)  # positional: the rng keyword was renamed
    centre = np.full(3, (BLOCK - 1) / 2 * h)
    anchor = centre + rng.uniform(-_CENTRAL_HALF, _CENTRAL_HALF, size=(m, 3)) * h  # world (block) frame
    params: dict[str, np.ndarray] = {"rotation": rot, "anchor": anchor}
    if name == "cuboid":
        half = _log_uniform(rng, _BOX_HALF, (m, 3)) * h
        surf = _box_surface_point(rng, half)
        params["half"] = half
    elif name == "cylinder":
        radius = _log_uniform(rng, _BARREL_RADIUS, m) * h
        half_height = _log_uniform(rng, _BARREL_HALF_HEIGHT, m) * h
        straight = rng.random(m) < 0.5
        # the bulge is a share of the smaller of radius and half height: Barrel allows at most half_height
        share = np.where(straight, 0.0, rng.uniform(*_BARREL_BULGE, size=m))
        cap = radius - share * np.minimum(radius, half_height)
        surf = _barrel_surface_point(rng, radius, cap, half_height)
        params.update(radius=radius, cap_radius=cap, half_height=half_height)
    elif name == "concave":
        planes = np.where(rng.random(m) < 0.5, 2, 3)
        surf = rng.uniform(0.0, _CORNER_REACH * h, size=(m, 3))
        surf[planes == 2, 2] = 0.0  # the 2-plane edge is invariant along local z
        # project onto the nearest face: zero the smallest of the active coordinates
        active = np.where((planes == 2)[:, None] & (np.arange(3) == 2), np.inf, surf)
        surf[np.arange(m), active.argmin(axis=1)] = 0.0
        params["planes"] = planes
    else:  # plane: local z = 0 is the surface, z < 0 the solid
        surf = np.zeros((m, 3))
    params["surface"] = surf
    local = _to_local(points, rot, surf - np.einsum("nk,nkl->nl", anchor, rot))
    origin = np.zeros(3)
    if name == "cuboid":
        d = Box(origin, params["half"][:, None, :])(local)
    elif name == "cylinder":
        # straight and bulging ones apart: Barrel takes a cheaper path when all of a call are straight
        d = np.empty(local.shape[:2])
        for part in (straight, ~straight):
            if part.any():
                d[part] = Barrel(origin, radius[part, None], cap[part, None], half_height[part, None])(local[part])
    elif name == "concave":
        d = ConcaveCorner(origin, None, params["planes"][:, None])(local)
    else:
        d = local[..., 2].copy()
    return d, params


def _to_local(points: np.ndarray, rot: np.ndarray, offset: np.ndarray) -> np.ndarray:
    """Local coordinates ``(m, M, 3)`` of ``points`` ``(M, 3)``: ``points @ rot[n] + offset[n]``.

    Stored component-major (each block's x, y and z are contiguous runs, the last axis is a strided view):
    elementwise formulas then read contiguous memory, several times faster than a batched matmul output.
    """
    m = rot.shape[0]
    out = np.empty((m, 3, points.shape[0]))
    pt = np.ascontiguousarray(points.T)
    for l in range(3):
        np.multiply(pt[0], rot[:, 0, l, None], out=out[:, l])
        out[:, l] += pt[1] * rot[:, 1, l, None]
        out[:, l] += pt[2] * rot[:, 2, l, None]
        out[:, l] += offset[:, l, None]
    return out.transpose(0, 2, 1)


def _box_surface_point(rng: np.random.Generator, half: np.ndarray) -> np.ndarray:
    """Area-uniform random points ``(m, 3)`` on the surfaces of boxes with half extents ``half`` ``(m, 3)``."""
    m = half.shape[0]
    # the two faces normal to axis a have area 4 h_b h_c each
    area = np.stack([half[:, 1] * half[:, 2], half[:, 0] * half[:, 2], half[:, 0] * half[:, 1]], axis=1)
    cum = np.cumsum(area / area.sum(axis=1, keepdims=True), axis=1)
    axis = np.minimum((rng.random((m, 1)) > cum).sum(axis=1), 2)
    p = rng.uniform(-1.0, 1.0, size=(m, 3)) * half
    p[np.arange(m), axis] = np.where(rng.random(m) < 0.5, -1.0, 1.0) * half[np.arange(m), axis]
    return p


def _barrel_surface_point(rng: np.random.Generator, radius, cap, half_height) -> np.ndarray:
    """Random points ``(m, 3)`` on barrel surfaces: side or caps in proportion to (approximate) area."""
    m = radius.shape[0]
    mean_r = (2.0 * radius + cap) / 3.0  # Simpson's mean radius of the side; the split need not be exact
    side_area = 2.0 * np.pi * mean_r * 2.0 * half_height
    caps_area = 2.0 * np.pi * cap * cap
    on_side = rng.random(m) < side_area / (side_area + caps_area)
    theta = rng.uniform(0.0, 2.0 * np.pi, size=m)
    z = rng.uniform(-1.0, 1.0, size=m) * half_height
    # side radius r(z) on the arc through (cap, +-h) and (radius, 0); straight when cap == radius
    bulge = radius - cap
    with np.errstate(divide="ignore", invalid="ignore"):
        big_r = (half_height ** 2 + bulge ** 2) / (2.0 * bulge)
        r_side = np.where(bulge > 0, radius - z * z / (big_r + np.sqrt(np.maximum(big_r ** 2 - z * z, 0.0))), radius)
    r_cap = cap * np.sqrt(rng.random(m))
    z_cap = np.where(rng.random(m) < 0.5, -1.0, 1.0) * half_height
    r = np.where(on_side, r_side, r_cap)
    return np.stack([r * np.cos(theta), r * np.sin(theta), np.where(on_side, z, z_cap)], axis=1)


def _make_shape(name: str, params: dict, j: int) -> SyntheticShape:
    """The posed world-frame primitive of shape ``j`` of a drawn batch."""
    rot = params["rotation"][j]
    anchor = params["anchor"][j]
    # the local origin sits at anchor - R s in the block frame (local = R^T (p - anchor) + s)
    center = anchor - rot @ params["surface"][j]
    if name == "cuboid":
        sdf = Box(center, params["half"][j].copy(), rot)
    elif name == "cylinder":
        sdf = Barrel(center, float(params["radius"][j]), float(params["cap_radius"][j]),
                     float(params["half_height"][j]), rot)
    elif name == "concave":
        sdf = ConcaveCorner(center, rot, int(params["planes"][j]))
    else:
        normal = rot[:, 2].copy()
        sdf = Plane(normal, float(normal @ anchor))
    return SyntheticShape(category=name, sdf=sdf, rotation=rot.copy(), anchor=anchor.copy())
