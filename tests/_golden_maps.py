"""The frozen-map check the format's golden maps share (tests/golden/maps/*: int8, int16, sharded...): written
once by ``make(path)`` under ``--regen-golden`` (only for a format change), then opened, verified and decoded
to the frozen values by every later reader."""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Callable

import numpy as np

import sdfcodec
from sdfcodec.map.verify import verify_map


def check_golden_map(golden: Path, make: Callable[[Path], object], regen: bool) -> sdfcodec.Map:
    """Regenerate ``golden`` (``map.zarr`` and its ``decoded.npy``) when ``regen``; then assert that today's
    reader verifies the map and decodes it to the frozen values. Returns the open map for format checks."""
    if regen:
        shutil.rmtree(golden, ignore_errors=True)
        golden.mkdir(parents=True)
        make(golden / "map.zarr")
        np.save(golden / "decoded.npy", sdfcodec.open_map(golden / "map.zarr").decode_region())
    assert (golden / "map.zarr" / "zarr.json").is_file(), "golden map missing: run pytest --regen-golden once"
    m = sdfcodec.open_map(golden / "map.zarr")
    rep = verify_map(golden / "map.zarr")
    assert rep.ok, rep.problems
    # the frozen values are the codec's; readers truncate decoded distances to the map's range
    np.testing.assert_allclose(m.decode_region(), np.clip(np.load(golden / "decoded.npy"), *m.truncation), atol=1e-6)
    return m


def check_true_mask_surface(m: sdfcodec.Map, observed: np.ndarray) -> None:
    """Assert that map ``m`` (a golden map with an approximate mask) reads a mask other than the true one,
    ``observed`` (its voxels' bool volume), yet decodes the surface points the true mask gives with its codes."""
    import torch

    from sdfcodec.core.blocks import split_blocks
    from sdfcodec.core.surface import surface_points

    r = m.reader
    vs, free = m.voxel_size, np.float32(m.truncation[1])
    coords, codes = r.codes_in(r.block_range(r.block_box(None, "voxels")), r.level(None))
    raw = np.asarray(r.decode_codes(torch.from_numpy(codes), metres=True, coords=coords,
                                    mask_rows=np.full((len(coords), 512), 255, np.uint8)))
    true = (split_blocks(observed.astype(np.float32), fill=1.0) > 0.5)[tuple(coords.T)].reshape(-1, 16, 16, 16)
    dec = m.decode_region()
    exact = split_blocks(dec, fill=free)
    exact[tuple(coords.T)] = np.where(true, raw, free)
    nx, ny, nz = dec.shape
    exact = exact.transpose(0, 3, 1, 4, 2, 5).reshape(exact.shape[0] * 16, exact.shape[1] * 16, -1)[:nx, :ny, :nz]
    assert (m.read_observed(coords) != true).mean() > 0.002  # the mask is not the truth
    np.testing.assert_array_equal(surface_points(dec, vs), surface_points(exact, vs))
