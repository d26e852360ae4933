"""The variable-rate writer at low byte targets (issue 42, 256:1): the encode's ridge towards the zero code
(``shrink``) against a float64 least-squares reference, its plumbing to codec hooks with and without the
keyword, and the rate control that turns it and the pinned mask's chooser on."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import sdfcodec
from sdfcodec.core.varrate import SHRINK, SHRINK_BELOW, shrink_for_bytes
from sdfcodec.map.observed import encode_blocks
from sdfcodec.map.varrate import VariableRateWriter

pytest.importorskip("numba")

import sdfcodec_pca  # noqa: E402
from test_observed import TRUNC, VS, fused_like, scene  # noqa: E402
from sdfcodec.core.blocks import normalise  # noqa: E402
from sdfcodec.map.observed import error_weights  # noqa: E402


@pytest.fixture(scope="module")
def fused():
    """Six normalised fused-like blocks that are not all free space, with no voxel at a truncation bound (so
    that the refits change nothing and the fit is a plain weighted least squares), and their error weights."""
    vol, obs = fused_like(scene())
    v = normalise(vol, *TRUNC).reshape(4, 16, 4, 16, 4, 16).transpose(0, 2, 4, 1, 3, 5).reshape(-1, 16, 16, 16)
    o = obs.reshape(4, 16, 4, 16, 4, 16).transpose(0, 2, 4, 1, 3, 5).reshape(-1, 16, 16, 16)
    keep = ~(v >= 1 - 1e-6).reshape(len(v), -1).all(axis=1)
    v, o = np.ascontiguousarray(v[keep][:6]), o[keep][:6]
    w = error_weights(v, o, TRUNC, VS)
    return np.ascontiguousarray(np.clip(v, 0.01, 0.99)), w


def two_ridges(codec, x: np.ndarray, w: np.ndarray, shrink: float) -> np.ndarray:
    """Independent reference: ``argmin sum w (x - (c D + d))^2 + RIDGE mean(w) |c - c0|^2 + shrink mean(w) |c|^2``
    (``c0`` the plain projection) by numpy's lstsq on the stacked system, in float64."""
    state = codec.state_dict()
    dec_w, dec_b = state["components"].astype(np.float64), state["mean"].astype(np.float64)
    out = []
    for xi, wi in zip(x.reshape(len(x), -1).astype(np.float64), w.reshape(len(w), -1).astype(np.float64)):
        c0 = (xi - dec_b) @ dec_w.T
        a, s = np.sqrt(sdfcodec_pca.RIDGE * wi.mean()), np.sqrt(shrink * wi.mean())
        eye = np.eye(len(dec_w))
        lhs = np.vstack([np.sqrt(wi)[:, None] * dec_w.T, a * eye, s * eye])
        rhs = np.concatenate([np.sqrt(wi) * (xi - dec_b), a * c0, np.zeros(len(dec_w))])
        out.append(np.linalg.lstsq(lhs, rhs, rcond=None)[0])
    return np.array(out)


@pytest.mark.parametrize("shrink", [0.0, 3e-3, 0.1])
def test_shrink_is_a_ridge_towards_the_zero_code(fused, shrink):
    x, w = fused
    codec = sdfcodec.pretrained_codec("pca", 32)
    ref = two_ridges(codec, x, w, shrink)
    for got in (codec.encode_truncated(torch.from_numpy(x), torch.from_numpy(w), 0, shrink=shrink).numpy(),
                codec.numpy_path().encode_truncated(x.reshape(len(x), -1), w.reshape(len(w), -1), 0, shrink=shrink)):
        np.testing.assert_allclose(got, ref, rtol=0, atol=2e-3 * np.abs(ref).max())
    if shrink:  # the penalty on the code's size makes it smaller than the fit without it
        plain = two_ridges(codec, x, w, 0.0)
        assert (np.linalg.norm(ref, axis=1) < np.linalg.norm(plain, axis=1)).all()


def test_encode_blocks_passes_shrink_only_to_hooks_that_take_it(fused, monkeypatch):
    v, _ = fused
    obs = np.ones(v.shape, bool)
    codec = sdfcodec.pretrained_codec("pca", 16)
    seen = []
    real = type(codec).encode_truncated

    def old_hook(self, blocks, weights, rounds):  # a plugin written before the keyword
        seen.append("old")
        return real(self, blocks, weights, rounds)

    with monkeypatch.context() as m:
        m.setattr(type(codec), "encode_truncated", old_hook)
        old = encode_blocks(codec, v, obs, TRUNC, VS, 51.0, "cpu", shrink=0.05)
    assert seen == ["old"]
    plain = encode_blocks(codec, v, obs, TRUNC, VS, 51.0, "cpu")
    np.testing.assert_array_equal(old, plain)  # the old hook solves the problem without the ridge
    shrunk = encode_blocks(codec, v, obs, TRUNC, VS, 51.0, "cpu", shrink=0.05)
    assert (np.linalg.norm(shrunk, axis=1) < np.linalg.norm(plain, axis=1)).all()


def test_the_rate_control_shrinks_at_low_targets_only():
    codec = sdfcodec.pretrained_codec("pca", 128)
    assert VariableRateWriter(codec, target_bytes=64).shrink == SHRINK > 0
    assert VariableRateWriter(codec, target_bytes=SHRINK_BELOW).shrink == 0.0
    assert VariableRateWriter(codec, target_bytes=128).shrink == 0.0
    assert VariableRateWriter(codec, step=0.5).shrink == 0.0 == shrink_for_bytes(None)
