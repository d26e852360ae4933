"""Cutting volumes into 16^3 blocks and back, and the metres <-> normalised mapping.

Volumes and blocks are indexed (x, y, z); block ``(bx, by, bz)`` covers voxels ``[16 bx, 16 bx + 16)`` etc.
"""

from __future__ import annotations

import numpy as np

from ._validate import BLOCK
from ..errors import InvalidValueError, ShapeError

__all__ = ["normalise", "denormalise", "split_blocks", "assemble_blocks", "blocks_grid_shape", "BLOCK",
           "DECODE_LIMIT", "truncation_problem"]

#: Decoded normalised values (0 at d_min, 1 at d_max) a reader accepts: anything beyond +-DECODE_LIMIT (1000
#: truncation ranges, 140 m at the paper's defaults) is absurd output of corrupted codes or a corrupted codec
#: state, refused like NaN/Inf (spec section 9a). A codec whose ``decode_bound`` is at most this skips the
#: pass over its output.
DECODE_LIMIT = 1e3


def truncation_problem(d_min: float, d_max: float) -> str | None:
    """What is wrong with the truncation ``[d_min, d_max]`` metres (a phrase following "truncation"), or None.
    Beyond finite and ordered, the decode's arithmetic must not overflow: readers compute
    ``v * (d_max - d_min) + d_min`` in float32 for normalised values ``v`` up to :data:`DECODE_LIMIT` in size, so
    a finite header such as ``[-1e308, 1e308]`` (whose range is infinite in float32) would decode every voxel to
    NaN; and the range must stay positive once rounded to float32 (else normalising divides by zero)."""
    usage = "must be d_min,d_max with d_min < d_max (finite metres, e.g. -0.04,0.1)"
    if not (np.isfinite(d_min) and np.isfinite(d_max) and d_min < d_max):
        return f"{usage}, got [{d_min}, {d_max}]"
    with np.errstate(all="ignore"):
        lo, hi = np.float32(d_min), np.float32(d_max)
        scale = hi - lo
        ends = np.array([lo - np.float32(DECODE_LIMIT) * scale, hi + np.float32(DECODE_LIMIT) * scale], np.float32)
    if not (np.isfinite(scale) and scale > 0 and np.isfinite(ends).all()):
        return (f"{usage}, got [{d_min}, {d_max}], which overflows the float32 arithmetic of a decode (d_max - d_min "
                f"must be a positive float32 number and {DECODE_LIMIT:g} ranges beyond either end finite)")
    return None


def check_truncation(d_min: float, d_max: float) -> None:
    if (problem := truncation_problem(d_min, d_max)) is not None:
        raise InvalidValueError(f"truncation {problem}")


def normalise(d: np.ndarray, d_min: float, d_max: float) -> np.ndarray:
    """Metres in ``[d_min, d_max]`` -> ``[0, 1]`` (free space 1.0). Does not clip."""
    return ((np.asarray(d, dtype=np.float32) - np.float32(d_min)) / np.float32(d_max - d_min)).astype(np.float32,
                                                                                                  copy=False)


def denormalise(v: np.ndarray, d_min: float, d_max: float) -> np.ndarray:
    """``[0, 1]`` -> metres (the inverse of :func:`normalise`)."""
    return (np.asarray(v, dtype=np.float32) * np.float32(d_max - d_min) + np.float32(d_min)).astype(np.float32)


def blocks_grid_shape(shape_voxels) -> tuple[int, int, int]:
    """Number of blocks along each axis needed to cover ``shape_voxels`` (ceil division)."""
    return tuple(-(-int(n) // BLOCK) for n in shape_voxels)  # type: ignore[return-value]


def split_blocks(volume: np.ndarray, fill: float | None = None) -> np.ndarray:
    """``(X, Y, Z)`` -> ``(Bx, By, Bz, 16, 16, 16)``, the far faces padded with ``fill``, or by repeating the
    volume's last voxel layer along each axis (None, what a TSDF is padded with); a view of ``volume`` when it
    needs no padding.

    Why not free space: a volume that ends inside solid (an exact SDF cut through the ground, a wall or the slab
    above a ceiling) padded with ``d_max`` had a surface the codec had to code where the volume ends; its smear
    decoded voxels of the solid as free space (sign errors up to +1.3 voxels in the last layers of a room cut at
    166 voxels) and every such block read as holding a surface (a ceiling search found 11 % of the map's blocks
    "above the ceiling" and kept none). Repeating the last layer creates no zero crossing; the padded voxels lie
    beyond the map's extent and are never read."""
    if volume.ndim != 3:
        raise ShapeError(f"a volume must have 3 axes (x, y, z), got shape {volume.shape}")
    gb = blocks_grid_shape(volume.shape)
    pad = [(0, g * BLOCK - n) for g, n in zip(gb, volume.shape)]
    if not any(p for _, p in pad):
        padded = volume
    elif fill is None:
        padded = np.pad(volume, pad, mode="edge")
    else:
        padded = np.pad(volume, pad, mode="constant", constant_values=fill)
    v = padded.reshape(gb[0], BLOCK, gb[1], BLOCK, gb[2], BLOCK)
    return v.transpose(0, 2, 4, 1, 3, 5)


def assemble_blocks(blocks: np.ndarray) -> np.ndarray:
    """``(Bx, By, Bz, 16, 16, 16)`` -> ``(16 Bx, 16 By, 16 Bz)`` (inverse of :func:`split_blocks` before cropping)."""
    if blocks.ndim != 6 or blocks.shape[3:] != (BLOCK,) * 3:
        raise ShapeError(f"blocks must have shape (Bx, By, Bz, 16, 16, 16), got {blocks.shape}")
    bx, by, bz = blocks.shape[:3]
    return blocks.transpose(0, 3, 1, 4, 2, 5).reshape(bx * BLOCK, by * BLOCK, bz * BLOCK)
