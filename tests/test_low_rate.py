"""The variable-rate writer at low byte targets (issue 42, 256:1): the encode's ridge towards the zero code
(``shrink``) against a float64 least-squares reference, its plumbing to codec hooks with and without the
keyword, and the rate control that turns it and the pinned mask's chooser on."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import sdfcodec
from sdfcodec.core.varrate import SHRINK, SHRINK_FROM_STEP, shrink_for_step
from sdfcodec.map.observed import encode_blocks

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


def test_the_shrink_follows_the_step():
    assert shrink_for_step(SHRINK_FROM_STEP) == SHRINK > 0
    assert shrink_for_step(0.875) == SHRINK  # the kitchen half's step at 64 B without it
    assert shrink_for_step(0.125) == 0.0  # the synthetic room's at 64 B: the optimum's codes pay there
    assert shrink_for_step(0.296) == 0.0  # the synthetic room at 40 B: the shrink lost there too (2.65 -> 2.99 mm)


def _write(tmp_path, name, coords, tsdf, obs, target):
    path = tmp_path / name
    with sdfcodec.create_map(path, codec=sdfcodec.pretrained_codec("pca", 128), voxel_size=VS, truncation=TRUNC,
                             codec_state="reference", variable_rate={"target_bytes": target}) as m:
        m.write_blocks(coords, tsdf, observed=obs)
    return path


def test_a_coarse_step_encodes_again_with_smaller_codes_and_a_finer_step(tmp_path, monkeypatch):
    """A map whose step is coarse at its target is encoded again with the ridge towards zero and lands on its
    target with a finer step and a surface closer to the analytic scene's than the same map with the shrink
    switched off (which keeps the first encode)."""
    from sdfcodec.core.blocks import split_blocks
    import sdfcodec.map.varrate as mv

    vol, obs = fused_like(scene())
    b, o = split_blocks(vol, fill=TRUNC[1]), split_blocks(obs.astype(np.float32), fill=0.0) > 0.5
    coords = np.argwhere(np.ones(b.shape[:3], bool)).astype(np.int64)
    tsdf, obs = b.reshape(-1, 16, 16, 16), o.reshape(-1, 16, 16, 16)
    reports, steps, errors = {}, {}, {}
    real = mv.VariableRateWriter._commit

    def spy(self, *a, **k):
        out = real(self, *a, **k)
        reports[key] = (self.shrink, self.report["step"])
        return out

    monkeypatch.setattr(mv.VariableRateWriter, "_commit", spy)
    for key, rule in (("on", mv.shrink_for_step), ("off", lambda step: 0.0)):
        monkeypatch.setattr(mv, "shrink_for_step", rule)
        path = _write(tmp_path, f"{key}.sdfz", coords, tsdf, obs, 60.0)
        with sdfcodec.open_map(path) as m:
            steps[key] = m.header.codes.variable_rate.step[0]
            got = np.full(tsdf.shape, TRUNC[1], np.float32)  # blocks not coded read d_max
            index = {tuple(c): i for i, c in enumerate(coords)}
            for c, blocks in m.iter_decoded():
                got[[index[tuple(cc)] for cc in c]] = blocks
        near = obs & (np.abs(tsdf) < 2 * VS)  # observed voxels within two voxels of the analytic surface
        errors[key] = float(np.abs(got - tsdf)[near].mean())
    assert reports["off"][0] == 0.0 and steps["off"] >= SHRINK_FROM_STEP  # coarse without it: the case it is for
    assert reports["on"][0] == SHRINK and steps["on"] < steps["off"]
    # and the surface is closer to the analytic one (here 7.30 against 7.66 mm near it, at 60 B per coded block)
    assert errors["on"] < 0.97 * errors["off"]
