"""Helpers the tests of fused-like maps share (test_error_bounds, test_sz3_field): an exact truncated SDF as
fusion leaves it, and such a volume written block by block with its observation."""

from __future__ import annotations

from pathlib import Path

import numpy as np

import sdfcodec
from sdfcodec.core.blocks import split_blocks

VS, TRUNC = 0.02, (-0.04, 0.1)


def fused_like(volume: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """As fusion leaves an exact SDF: voxels deeper than |d_min| behind a surface unobserved, reading d_max."""
    observed = volume > TRUNC[0] + 1e-6
    return np.where(observed, volume, np.float32(TRUNC[1])).astype(np.float32), observed


def write_volume_map(path: Path, volume: np.ndarray, observed: np.ndarray | None, codec, **kw) -> None:
    """Write ``volume`` (metres) to a new map at ``path`` with ``codec``, every grid block, with the observation
    ``observed`` (same shape, bool; None: all observed); ``kw`` goes to :func:`sdfcodec.create_map`."""
    blocks = split_blocks(volume, fill=TRUNC[1])
    coords = np.argwhere(np.ones(blocks.shape[:3], bool))
    obs = None
    if observed is not None:
        obs = split_blocks(observed.astype(np.float32), fill=1.0).reshape(-1, 16, 16, 16) > 0.5
    with sdfcodec.create_map(path, codec=codec, voxel_size=VS, truncation=TRUNC, shape_voxels=volume.shape,
                             overwrite=True, **kw) as m:
        m.write_blocks(coords, blocks.reshape(-1, 16, 16, 16), observed=obs)
