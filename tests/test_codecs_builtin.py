"""The built-in linear codecs (pca, raw, gaussian-blur): golden fixtures, the PCA against sklearn, shipped eigenshapes,
the blur's halo. Every conformance check of every built-in codec runs in test_conformance_builtin.py."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import sdfcodec
from sdfcodec.testing import analytic_blocks

GOLDEN = Path(__file__).parent / "golden"


@pytest.fixture(scope="module")
def train_blocks():
    return analytic_blocks(600, seed=7)


@pytest.mark.parametrize("mean", ["dataset", "block"])
@pytest.mark.parametrize("code_size", [32, 64])
def test_pca_golden_and_round_trip(train_blocks, code_size, mean, regen_golden, golden_round_trip):
    codec = sdfcodec.get_codec("pca", code_size=code_size, mean=mean).fit(train_blocks)
    golden = GOLDEN / f"pca-{code_size}-{mean}" if code_size == 32 else None
    report = golden_round_trip(codec, golden, regen_golden)
    assert report["mse"] < 0.01


def test_raw_golden_and_round_trip(regen_golden, golden_round_trip):
    report = golden_round_trip(sdfcodec.get_codec("raw"), GOLDEN / "raw", regen_golden)
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


@pytest.mark.parametrize("mean", ["dataset", "block"])
def test_streamed_pca_equals_sklearn(mean):
    """One pass of streamed covariance gives sklearn's exact (full SVD) basis, in bounded memory."""
    from sdfcodec.data.synthetic import synthetic_blocks

    # 300 blocks in 3 batches: more blocks than the 16 components need many times over, and a full SVD that
    # stays cheap (its cost grows with the square of the block count; the streamed 4096 x 4096 second moment's
    # with the block count)
    x = synthetic_blocks(300, seed=3)
    ref = sdfcodec.get_codec("pca", code_size=16, mean=mean, svd_solver="full").fit(x)
    streamed = sdfcodec.get_codec("pca", code_size=16, mean=mean).fit_stream(x[i:i + 100] for i in range(0, 300, 100))
    # components agree up to sign; the variances and the mean to float32 precision
    assert np.all(np.abs(np.sum(ref.components_ * streamed.components_, axis=1)) > 1 - 1e-5)
    assert np.allclose(ref.explained_variance_, streamed.explained_variance_, rtol=1e-4)
    assert np.allclose(ref.mean_, streamed.mean_, atol=1e-6)
    rec = lambda c: float(np.mean((c.decode(c.encode(x)) - x) ** 2))  # noqa: E731
    assert rec(streamed) == pytest.approx(rec(ref), rel=1e-5)


def test_pca_prefix_is_the_truncated_basis(train_blocks):
    big = sdfcodec.get_codec("pca", code_size=64).fit(train_blocks)
    small = big.prefix(32)
    assert small.code_size == 32 and small.is_fitted
    assert np.allclose(small.encode(train_blocks), big.encode(train_blocks)[:, :32], atol=1e-4)
    assert np.allclose(small.decode(big.encode(train_blocks)[:, :32]), big.decode(big.encode(train_blocks)[:, :32]))
    with pytest.raises(sdfcodec.errors.InvalidValueError, match="prefix size"):
        big.prefix(65)


def test_shipped_default_model():
    """The shipped eigenshapes load without pickles, are orthonormal, and reconstruct real-like blocks."""
    from sdfcodec import pretrained_codec as default_codec
    from sdfcodec.data.synthetic import synthetic_blocks

    c = default_codec("pca", 128)
    w = c.components_.astype(np.float64)
    assert np.allclose(w @ w.T, np.eye(128), atol=1e-4)
    for stage in (slice(0, 32), slice(32, 64), slice(64, 128)):  # fitted in nested stages, each ordered
        assert np.all(np.diff(c.explained_variance_[stage]) <= 0)
    x = synthetic_blocks(500, seed=99)
    errs = [float(np.mean((default_codec("pca", k).decode(default_codec("pca", k).encode(x)) - x) ** 2))
            for k in (32, 64, 128)]
    assert errs[0] > errs[1] > errs[2] and errs[0] < 0.01
    with pytest.raises(sdfcodec.errors.InvalidValueError, match="129"):
        default_codec("pca", 129)


def test_codecs_compare_by_class_config_and_state():
    """``get_codec(c.get_config()).load_state_dict(c.state_dict()) == c`` (spec: config + state rebuild an equal
    codec); another config, another state or another class is unequal; codecs are mutable, so unhashable."""
    c = sdfcodec.pretrained_codec("pca", 32)
    rebuilt = sdfcodec.get_codec(c.get_config()).load_state_dict(c.state_dict())
    assert rebuilt == c and not rebuilt != c and rebuilt is not c
    assert sdfcodec.get_codec(c.get_config()) != c  # unfitted: no state
    assert sdfcodec.pretrained_codec("pca", 33) != c
    other = sdfcodec.get_codec(c.get_config()).load_state_dict(
        {k: (v + np.float32(1e-7) if k == "mean" else v) for k, v in c.state_dict().items()})
    assert other != c  # one ulp-sized change of one array: compared exactly
    assert sdfcodec.get_codec("raw") == sdfcodec.get_codec("raw") and sdfcodec.get_codec("raw") != c
    assert c != "pca" and c != None  # noqa: E711 - not a codec: unequal, no error
    for codec_id in ("ae", "sequential"):
        nn = sdfcodec.pretrained_codec(codec_id)
        assert sdfcodec.get_codec(nn.get_config()).load_state_dict(nn.state_dict()) == nn
    with pytest.raises(TypeError, match="unhashable"):
        hash(c)


def test_pretrained_through_the_registry():
    """Shipped weights come from the codec class (``pretrained``), reached through the registry; a codec that
    ships none says so with ModelNotFoundError, not MapNotFoundError."""
    from sdfcodec.registry import get_codec_class

    assert sdfcodec.pretrained_codec("pca") == get_codec_class("pca").pretrained(64)
    with pytest.raises(sdfcodec.errors.ModelNotFoundError, match="ships no trained model") as e:
        sdfcodec.pretrained_codec("raw")
    assert not isinstance(e.value, sdfcodec.errors.MapNotFoundError) and isinstance(e.value, FileNotFoundError)
    with pytest.raises(sdfcodec.errors.InvalidValueError, match="no options"):
        sdfcodec.pretrained_codec("pca", 32, mean="block")


def test_gaussian_blur_golden_and_halo(regen_golden, golden_round_trip):
    codec = sdfcodec.get_codec("gaussian-blur")
    assert codec.halo == 4
    golden_round_trip(codec, GOLDEN / "gaussian-blur", regen_golden)
    with pytest.raises(sdfcodec.errors.InvalidValueError, match="odd"):
        sdfcodec.get_codec("gaussian-blur", size=8).halo


def test_gaussian_blur_map_has_no_seams(tmp_path):
    """Decoding a blurred map equals scipy's filter of the whole field: the halo carries neighbour context."""
    from scipy.ndimage import correlate1d

    from sdfcodec.core.sdf import Box, Plane, Scene, Sphere, sample_volume

    trunc = (-0.04, 0.1)
    vol = sample_volume(Scene([Plane((0, 0, 1), 0.2), Sphere((0.4, 0.3, 0.35), 0.15), Box((0.2, 0.5, 0.3), (0.1, 0.1, 0.1))]),
                        (40, 40, 30), 0.02, truncation=trunc)
    with sdfcodec.create_map(tmp_path / "b.sdfz", codec=sdfcodec.get_codec("gaussian-blur"), voxel_size=0.02,
                             truncation=trunc) as m:
        m.write_volume(vol)
    m = sdfcodec.open_map(tmp_path / "b.sdfz")
    k = np.exp(-0.5 * (np.arange(-4, 5) / (4 / 3)) ** 2)
    k /= k.sum()
    # reference: the padded grid (the volume's last layers repeated to the blocks' extent, spec section 4)
    # filtered with free space (d_max) beyond the map, then cropped to the true extent
    ref = np.pad(vol.astype(np.float64), ((0, 8), (0, 8), (0, 2)), mode="edge")
    for ax in range(3):
        ref = correlate1d(ref, k, axis=ax, mode="constant", cval=trunc[1])
    assert np.abs(m.decode_region() - ref[:40, :40, :30]).max() < 1e-5
    part = m.decode_region(((13, 29), (5, 33), (0, 30)))
    assert np.abs(part - ref[13:29, 5:33, :30]).max() < 1e-5
    # the per-block iterator sees the same neighbourhoods
    for coords, blocks in m.iter_blocks():
        for (bx, by, bz), b in zip(coords, blocks):
            assert np.abs(b - ref[bx * 16:bx * 16 + 16, by * 16:by * 16 + 16, bz * 16:bz * 16 + 16]).max() < 1e-5
