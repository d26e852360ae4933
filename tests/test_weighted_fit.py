"""Fitting from error weights (Codec.fit(blocks, weights=...), hook fit_weighted; PCA: weighted alternating
least squares in nested stages), checked against plain PCA and its own objective."""

from __future__ import annotations

import numpy as np
import pytest

import sdfcodec
from sdfcodec.errors import InvalidValueError, ShapeError
from sdfcodec.map.observed import error_weights
from sdfcodec.testing import analytic_blocks

TRUNC, VS = (-0.04, 0.1), 0.02


def fused_style(n: int = 300, seed: int = 5) -> tuple[np.ndarray, np.ndarray]:
    """Normalised analytic blocks as fusion leaves them (nothing seen deeper than |d_min| behind a surface:
    those voxels read free space) and their error weights."""
    v = analytic_blocks(n, seed=seed)
    observed = v > 0  # exact blocks clip the deep inside to d_min, i.e. 0 normalised
    return np.where(observed, v, np.float32(1.0)), error_weights(v, observed, TRUNC, VS)


def weighted_error(codec, v: np.ndarray, w: np.ndarray) -> float:
    rec = codec.decode(codec.encode(v, weights=w))
    return float((w * (rec - v) ** 2).sum())


def test_uniform_weights_give_the_principal_components():
    v = analytic_blocks(120, seed=1)
    plain = sdfcodec.get_codec("pca", code_size=8).fit(v)
    fitted = sdfcodec.get_codec("pca", code_size=8).fit(v, weights=np.ones(v.shape, np.float32))
    # the same subspace, component by component up to sign (plain PCA is the optimum of uniform weights)
    overlap = np.abs(fitted.state_dict()["components"] @ plain.state_dict()["components"].T)
    np.testing.assert_allclose(np.diag(overlap), 1.0, atol=2e-3)
    np.testing.assert_allclose(fitted.state_dict()["mean"], plain.state_dict()["mean"], atol=1e-4)


def test_weighted_fit_lowers_the_weighted_error_at_every_prefix():
    v, w = fused_style(160)
    plain = sdfcodec.get_codec("pca", code_size=8).fit(v)
    fitted = sdfcodec.get_codec("pca", code_size=8).fit(v, weights=w)
    for k in (2, 4, 8):  # the nested stages: every prefix is fitted, not only the whole basis
        assert weighted_error(fitted.prefix(k), v, w) < 0.97 * weighted_error(plain.prefix(k), v, w), k
    held, hw = fused_style(100, seed=99)  # and on blocks it never saw
    assert weighted_error(fitted, held, hw) < weighted_error(plain, held, hw)
    var = fitted.state_dict()["explained_variance"]
    assert np.all(np.diff(var[:2]) <= 1e-6) and np.all(np.diff(var[4:8]) <= 1e-6)  # ordered within stages
    comp = fitted.state_dict()["components"]
    np.testing.assert_allclose(comp @ comp.T, np.eye(8), atol=1e-4)  # orthonormal: plain projection still exact


def test_weighted_fit_refuses_what_it_cannot_do():
    v, w = fused_style(40)
    with pytest.raises(InvalidValueError, match="mean='dataset'"):
        sdfcodec.get_codec("pca", code_size=8, mean="block").fit(v, weights=w)
    with pytest.raises(ShapeError, match="weights"):
        sdfcodec.get_codec("pca", code_size=8).fit(v, weights=w[:3])
    with pytest.raises(InvalidValueError, match="weights"):
        sdfcodec.get_codec("pca", code_size=8).fit(v, weights=-w)


def test_fit_codec_learns_a_map_as_the_writer_encodes_it():
    # with the observation, fit_codec hands the writer's error weights to a codec that learns from them
    # (lower weighted error than the same codec fitted on the blocks as they are); without, a plain fit
    from sdfcodec.map.observed import fit_codec

    v, w = fused_style(90, seed=11)
    o = w > 0
    seen = []
    fitted, plain = (sdfcodec.get_codec("pca", code_size=4) for _ in range(2))
    assert fit_codec(fitted, v, o, TRUNC, VS, max_blocks=80, log=seen.append) == 80 and seen == [80]
    fit_codec(plain, v, None, TRUNC, VS, max_blocks=80)
    assert weighted_error(fitted, v, w) < 0.97 * weighted_error(plain, v, w)
    again = sdfcodec.get_codec("pca", code_size=4)
    fit_codec(again, v, None, TRUNC, VS, max_blocks=80)
    np.testing.assert_array_equal(again.state_dict()["components"], plain.state_dict()["components"])  # seeded
