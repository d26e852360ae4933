"""Every built-in codec passes the public conformance suite, golden fixtures included."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import sdfcodec
from sdfcodec.testing import analytic_blocks, check_codec

GOLDEN = Path(__file__).parent / "golden"


@pytest.fixture(scope="module")
def train_blocks():
    return analytic_blocks(600, seed=7)


@pytest.mark.parametrize("mean", ["dataset", "block"])
@pytest.mark.parametrize("code_size", [32, 64])
def test_pca_conforms(train_blocks, code_size, mean, regen_golden):
    codec = sdfcodec.get_codec("pca", code_size=code_size, mean=mean).fit(train_blocks)
    golden = GOLDEN / f"pca-{code_size}-{mean}" if code_size == 32 else None
    report = check_codec(codec, golden=golden, regen_golden=regen_golden)
    assert report["mse"] < 0.01


def test_raw_conforms(regen_golden):
    report = check_codec(sdfcodec.get_codec("raw"), golden=GOLDEN / "raw", regen_golden=regen_golden)
    assert report["mse"] == 0.0


def test_pca_matches_independent_projection(train_blocks):
    """Codes equal a plain numpy projection onto sklearn's basis; the prefix decode is its truncation."""
    from sklearn.decomposition import PCA

    x = train_blocks.reshape(len(train_blocks), -1).astype(np.float64)
    codec = sdfcodec.get_codec("pca", code_size=64).fit(train_blocks)
    ref = PCA(n_components=64, random_state=0).fit(train_blocks.reshape(len(train_blocks), -1))
    w, mu = ref.components_.astype(np.float64), ref.mean_.astype(np.float64)
    # sklearn's sign convention is deterministic, so the bases agree up to float32 rounding
    assert np.allclose(codec.components_, w, atol=1e-4)
    codes = codec.encode(train_blocks)
    assert np.allclose(codes, (x - mu) @ w.T, atol=2e-4)
    for level in (32, 64):
        dec = codec.decode(codes[:, :level]).reshape(len(x), -1)
        assert np.allclose(dec, codes[:, :level].astype(np.float64) @ w[:level] + mu, atol=2e-5)


def test_pca_block_mean_slot_is_the_block_mean(train_blocks):
    codec = sdfcodec.get_codec("pca", code_size=32, mean="block").fit(train_blocks)
    codes = codec.encode(train_blocks)
    assert np.allclose(codes[:, 0], train_blocks.reshape(len(train_blocks), -1).mean(axis=1), atol=1e-5)
    # slot 0 alone decodes to a constant block at the block mean plus the small centred-data mean
    flat = codec.decode(codes[:, :1]).reshape(len(codes), -1)
    assert np.allclose(flat - codec.mean_, codes[:, :1], atol=1e-5)


def test_pca_needs_enough_blocks():
    with pytest.raises(sdfcodec.errors.ShapeError, match="needs at least 64 blocks"):
        sdfcodec.get_codec("pca", code_size=64).fit(analytic_blocks(10))


def test_pca_bad_parameters():
    with pytest.raises(sdfcodec.errors.InvalidValueError, match="mean must be"):
        sdfcodec.get_codec("pca", mean="median").fit(analytic_blocks(100))
    with pytest.raises(sdfcodec.errors.InvalidValueError, match="code_size"):
        sdfcodec.get_codec("pca", code_size=0).fit(analytic_blocks(100))
