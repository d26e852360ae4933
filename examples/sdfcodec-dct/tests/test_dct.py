"""The plugin runs sdfcodec's public conformance suite, one test per named check, as every codec plugin must."""

from pathlib import Path

import numpy as np
from scipy.fft import dctn

import sdfcodec
from sdfcodec.testing import analytic_blocks, parametrize_codec_checks

GOLDEN = Path(__file__).parent / "golden"
SIZES = (32, 128)


# the golden fixtures were written once (pytest --regen-golden) and are checked in: they freeze the format
@parametrize_codec_checks([sdfcodec.get_codec("dct", code_size=k) for k in SIZES],
                          golden=[GOLDEN / f"dct-{k}" for k in SIZES])
def test_conformance(codec, check, regen_golden):
    check(codec, regen_golden=regen_golden)


def test_codes_are_scipy_dct_coefficients():
    x = analytic_blocks(4)
    codes = sdfcodec.get_codec("dct", code_size=10).encode(x)
    ref = dctn(x.astype(np.float64), type=2, norm="ortho", axes=(1, 2, 3))
    assert np.allclose(codes[:, 0], ref[:, 0, 0, 0], atol=1e-4)  # DC first
    # then the three first-order frequencies, in C order of (i, j, k): (0, 0, 1), (0, 1, 0), (1, 0, 0)
    first = np.stack([ref[:, 0, 0, 1], ref[:, 0, 1, 0], ref[:, 1, 0, 0]], axis=1)
    assert np.allclose(codes[:, 1:4], first, atol=1e-4)
