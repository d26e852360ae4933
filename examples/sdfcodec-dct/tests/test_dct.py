"""The plugin runs sdfcodec's public conformance suite, as every codec plugin must."""

from pathlib import Path

import numpy as np
import pytest
from scipy.fft import dctn

import sdfcodec
from sdfcodec.testing import analytic_blocks, check_codec

GOLDEN = Path(__file__).parent / "golden"


@pytest.mark.parametrize("code_size", [32, 128])
def test_conformance(code_size):
    # the golden fixtures were written once (regen_golden=True) and are checked in: they freeze the format
    check_codec(sdfcodec.get_codec("dct", code_size=code_size), golden=GOLDEN / f"dct-{code_size}")


def test_codes_are_scipy_dct_coefficients():
    x = analytic_blocks(4)
    codes = sdfcodec.get_codec("dct", code_size=10).encode(x)
    ref = dctn(x.astype(np.float64), type=2, norm="ortho", axes=(1, 2, 3))
    assert np.allclose(codes[:, 0], ref[:, 0, 0, 0], atol=1e-4)  # DC first
    # then the three first-order frequencies, in C order of (i, j, k): (0, 0, 1), (0, 1, 0), (1, 0, 0)
    first = np.stack([ref[:, 0, 0, 1], ref[:, 0, 1, 0], ref[:, 1, 0, 0]], axis=1)
    assert np.allclose(codes[:, 1:4], first, atol=1e-4)
