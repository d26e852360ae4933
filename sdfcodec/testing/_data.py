"""Small, exact test blocks for the conformance suite (no training data needed)."""

from __future__ import annotations

import numpy as np

from ..core.blocks import normalise
from ..core.sdf import Box, Cylinder, Plane, Scene, Sphere, grid_points

__all__ = ["analytic_blocks", "analytic_scene"]


def analytic_blocks(n: int, seed: int = 0, voxel_size: float = 0.02,
                    truncation: tuple[float, float] = (-0.04, 0.1)) -> np.ndarray:
    """``n`` normalised blocks ``(n, 16, 16, 16)`` float32 of planes, spheres and boxes through the block.

    Each block samples one exact primitive whose surface passes within a few voxels of the block centre, so
    every block holds both a surface and free space (what real maps code). Deterministic by ``seed``.
    """
    rng = np.random.default_rng(seed)
    pts = grid_points((16, 16, 16), voxel_size)
    centre = pts[8, 8, 8]
    out = np.empty((n, 16, 16, 16), dtype=np.float32)
    for i in range(n):
        kind = i % 3
        jitter = rng.normal(scale=2 * voxel_size, size=3)
        if kind == 0:
            normal = rng.normal(size=3)
            normal /= np.linalg.norm(normal)
            sdf = Plane(normal, float(normal @ (centre + jitter)))
        elif kind == 1:
            r = rng.uniform(3, 12) * voxel_size
            direction = rng.normal(size=3)
            direction /= np.linalg.norm(direction)
            sdf = Sphere(centre + jitter + r * direction, r)
        else:
            half = rng.uniform(3, 10, size=3) * voxel_size
            sdf = Box(centre + jitter + half * rng.choice([-1, 1], size=3), half)
        d = np.clip(sdf(pts), *truncation)
        out[i] = normalise(d, *truncation)
    return out


def analytic_scene() -> Scene:
    """A small exact scene for map tests: a floor (z = 0.1 m), a wall (x = 0.05 m), a sphere, a box and a
    cylinder inside about 1.8 x 1.4 x 0.9 m. Sample it with :func:`sdfcodec.core.sdf.sample_volume`."""
    return Scene([Plane((0, 0, 1), 0.1), Plane((1, 0, 0), 0.05), Sphere((0.6, 0.6, 0.5), 0.2),
                  Box((1.2, 0.4, 0.35), (0.15, 0.1, 0.2)), Cylinder((1.5, 1.1, 0.45), 0.15, 0.3)])
