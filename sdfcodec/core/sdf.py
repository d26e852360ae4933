"""Exact analytic signed distance functions: the project's independent ground truth.

Each primitive maps points ``(..., 3)`` in metres to signed distances ``(...)`` (negative inside). The
formulas are the exact Euclidean distances (Inigo Quilez's box and capped-cylinder forms), so tests can
compare decoded maps, fused maps and synthetic training blocks with them. A :class:`Scene` is a union of
primitives; its distance is the minimum, which is exact outside all primitives and inside any primitive
that overlaps no other.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from ..errors import InvalidValueError

__all__ = ["Plane", "Sphere", "Box", "Cylinder", "Scene", "grid_points", "sample_volume", "Barrel", "ConcaveCorner"]


def _local(points: np.ndarray, center: np.ndarray, rotation: np.ndarray | None) -> np.ndarray:
    p = np.asarray(points, dtype=np.float64) - center
    # rotation maps local to world, so world-to-local is its transpose: p_local = R^T p
    return p if rotation is None else p @ np.asarray(rotation, dtype=np.float64)


def _length(v: np.ndarray) -> np.ndarray:
    """``np.linalg.norm(v, axis=-1)`` bit for bit (the squares summed in the same order), without numpy's
    reduction over a short last axis: ~7x faster on ``(n, 3)`` points, where the analytic scenes spend their time."""
    total = v[..., 0] * v[..., 0]
    for k in range(1, v.shape[-1]):
        total = total + v[..., k] * v[..., k]
    return np.sqrt(total)


def _largest(v: np.ndarray) -> np.ndarray:
    """``v.max(axis=-1)`` (NaN kept, as there), one component at a time (as :func:`_length`)."""
    out = v[..., 0]
    for k in range(1, v.shape[-1]):
        out = np.maximum(out, v[..., k])
    return out


@dataclass
class Plane:
    """Half-space ``n . p <= offset`` is solid (``n`` is normalised on use)."""

    normal: Sequence[float]
    offset: float = 0.0

    def __call__(self, points: np.ndarray) -> np.ndarray:
        n = np.asarray(self.normal, dtype=np.float64)
        n = n / np.linalg.norm(n)
        return np.asarray(points, dtype=np.float64) @ n - self.offset


@dataclass
class Sphere:
    center: Sequence[float]
    radius: float

    def __call__(self, points: np.ndarray) -> np.ndarray:
        p = np.asarray(points, dtype=np.float64) - np.asarray(self.center, dtype=np.float64)
        return _length(p) - self.radius


@dataclass
class Box:
    """Solid cuboid with half extents ``half`` about ``center``, optionally rotated (3x3, local to world)."""

    center: Sequence[float]
    half: Sequence[float]
    rotation: np.ndarray | None = None

    def __call__(self, points: np.ndarray) -> np.ndarray:
        q = np.abs(_local(points, np.asarray(self.center, np.float64), self.rotation)) - np.asarray(self.half)
        outside = _length(np.maximum(q, 0.0))
        inside = np.minimum(_largest(q), 0.0)
        return outside + inside


@dataclass
class Cylinder:
    """Solid capped cylinder along local z with ``radius`` and ``half_height``, optionally rotated."""

    center: Sequence[float]
    radius: float
    half_height: float
    rotation: np.ndarray | None = None

    def __call__(self, points: np.ndarray) -> np.ndarray:
        p = _local(points, np.asarray(self.center, np.float64), self.rotation)
        d = np.stack([_length(p[..., :2]) - self.radius, np.abs(p[..., 2]) - self.half_height], -1)
        return np.minimum(_largest(d), 0.0) + _length(np.maximum(d, 0.0))


@dataclass
class Scene:
    """Union of primitives (minimum of their distances)."""

    primitives: list = field(default_factory=list)

    def __call__(self, points: np.ndarray) -> np.ndarray:
        if not self.primitives:
            raise InvalidValueError("a Scene needs at least one primitive")
        out = self.primitives[0](points)
        for prim in self.primitives[1:]:
            out = np.minimum(out, prim(points))
        return out


def grid_points(shape: Sequence[int], voxel_size: float, origin: Sequence[float] = (0.0, 0.0, 0.0)) -> np.ndarray:
    """World positions ``(X, Y, Z, 3)`` of the voxels of a lattice; voxel ``(i, j, k)`` is at
    ``origin + voxel_size * (i, j, k)`` (the map format's convention, spec/map-format.md)."""
    axes = [np.arange(n, dtype=np.float64) * voxel_size + o for n, o in zip(shape, origin)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)


def sample_volume(sdf, shape: Sequence[int], voxel_size: float, origin: Sequence[float] = (0.0, 0.0, 0.0),
                  truncation: tuple[float, float] | None = (-0.04, 0.1)) -> np.ndarray:
    """Sample ``sdf`` on a lattice, truncated to ``truncation`` (None keeps raw distances); float32 metres."""
    d = sdf(grid_points(shape, voxel_size, origin))
    if truncation is not None:
        d = np.clip(d, truncation[0], truncation[1])
    return d.astype(np.float32)


@dataclass
class Barrel:
    """Solid barrel along local z: a surface of revolution whose profile is a circular arc.

    The radius is ``radius`` at the middle (local z = 0) and ``cap_radius`` (``<= radius``) at the flat caps
    ``z = +-half_height``; between them it follows the circular arc through ``(cap_radius, -half_height)``,
    ``(radius, 0)`` and ``(cap_radius, half_height)``. ``cap_radius == radius`` is the straight capped cylinder
    (same distances as :class:`Cylinder`). The bulge ``radius - cap_radius`` may be at most ``half_height``
    (the profile is then a half circle); a larger one raises ``ValueError``.

    The distance is exact: by rotational symmetry the nearest surface point lies in the query point's meridian
    half-plane, where the boundary is one circular arc and two cap segments, each with a closed-form
    distance; the signed distance is the smallest of the three, negative inside.

    ``radius``, ``cap_radius`` and ``half_height`` may be arrays and ``center`` ``(..., 3)`` / ``rotation``
    ``(..., 3, 3)`` stacks, as long as they broadcast against the points' leading axes (e.g. parameters
    ``(N, 1)``, points ``(N, M, 3)``): the synthetic data generator evaluates many barrels in one call.
    """

    center: Sequence[float]
    radius: float
    cap_radius: float
    half_height: float
    rotation: np.ndarray | None = None

    def __call__(self, points: np.ndarray) -> np.ndarray:
        r_mid = np.asarray(self.radius, np.float64)
        r_cap = np.asarray(self.cap_radius, np.float64)
        h = np.asarray(self.half_height, np.float64)
        if np.any(h <= 0) or np.any(r_cap <= 0) or np.any(r_cap > r_mid) or np.any(r_mid - r_cap > h):
            raise InvalidValueError("a Barrel needs half_height > 0 and 0 < cap_radius <= radius <= cap_radius + "
                                    "half_height (a larger bulge would bend the profile arc past a semicircle)")
        p = _local(points, np.asarray(self.center, np.float64), self.rotation)
        # component-wise arithmetic throughout: reductions over a length-3 axis are slow in numpy
        x, y = p[..., 0], p[..., 1]
        rho = np.sqrt(x * x + y * y)
        dz = np.abs(p[..., 2])
        dz2 = dz * dz
        delta = rho - r_mid
        to_rim = np.sqrt((rho - r_cap) ** 2 + (dz - h) ** 2)  # distance to the nearer rim circle
        d_cap = np.sqrt(np.maximum(rho - r_cap, 0.0) ** 2 + (dz - h) ** 2)  # to the nearer cap disc
        straight = (r_mid - r_cap) <= 1e-12 * r_mid
        # straight side: the segment rho = r_mid, |z| <= h
        if np.all(straight):
            side = np.where(dz <= h, np.abs(delta), to_rim)
            inside = (dz <= h) & (delta <= 0)
        else:
            b = np.where(straight, 1.0, r_mid - r_cap)  # placeholder where straight, replaced below
            # arc radius from the chord condition R - sqrt(R^2 - h^2) = bulge; its centre is (r_mid - R, 0)
            big_r = (h * h + b * b) / (2.0 * b)
            root = np.sqrt(big_r * big_r - h * h)  # the arc centre's horizontal distance to a cap rim
            # written relative to r_mid so nearly straight barrels (huge R) lose no precision:
            # |v| - R = (2 R delta + delta^2 + z^2) / (|v| + R), v = (rho, z) - centre, delta = rho - r_mid
            v_rho = big_r + delta
            v_norm = np.sqrt(v_rho * v_rho + dz2)
            on_arc = (v_rho >= 0) & (dz * root <= v_rho * h)  # within the arc's angular span
            side = np.where(on_arc, np.abs((2.0 * big_r * delta + delta * delta + dz2) / (v_norm + big_r)), to_rim)
            # inside: |z| <= h and rho <= r(z) = r_mid - z^2 / (R + sqrt(R^2 - z^2)) (stable form of the arc)
            zc2 = np.minimum(dz2, h * h)
            inside = (dz <= h) & (delta <= -zc2 / (big_r + np.sqrt(big_r * big_r - zc2)))
            if np.any(straight):
                side = np.where(straight, np.where(dz <= h, np.abs(delta), to_rim), side)
                inside = np.where(straight, (dz <= h) & (delta <= 0), inside)
        unsigned = np.minimum(side, d_cap)
        return np.where(inside, -unsigned, unsigned)


@dataclass
class ConcaveCorner:
    """Concave room corner: solid everywhere except the open octant (or quadrant wedge) in front of it.

    In local coordinates the free space is ``x > 0, y > 0, z > 0`` for ``planes=3`` (floor and two walls
    meeting at a corner, seen from inside the room) and ``x > 0, y > 0`` for ``planes=2`` (two walls meeting
    at a concave edge along local z). ``center`` is the corner point. Exact signed distance: in free space the
    distance to the nearest of the planes, ``min(x, y[, z])``; in the solid minus the distance to the free
    octant, ``-|min(p, 0)|``.

    ``planes`` may be an array of 2s and 3s and ``center`` / ``rotation`` stacks, broadcasting against the
    points' leading axes as for :class:`Barrel`.
    """

    center: Sequence[float]
    rotation: np.ndarray | None = None
    planes: int = 3

    def __call__(self, points: np.ndarray) -> np.ndarray:
        k = np.asarray(self.planes)
        if not np.all((k == 2) | (k == 3)):
            raise InvalidValueError(f"a ConcaveCorner has 2 or 3 planes, got {self.planes}")
        p = _local(points, np.asarray(self.center, np.float64), self.rotation)
        x, y, z = p[..., 0], p[..., 1], p[..., 2]
        # with 2 planes local z plays no part: +inf never wins the min and never counts as solid
        z = np.where(k == 3, z, np.inf)
        nearest = np.minimum(np.minimum(x, y), z)
        depth = np.sqrt(np.minimum(x, 0.0) ** 2 + np.minimum(y, 0.0) ** 2 + np.minimum(z, 0.0) ** 2)
        return np.where(nearest > 0, nearest, -depth)
