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
