"""The pca codec's compiled truncation-aware encode (sdfcodec_pca.truncated, issue 42 item 5) against a float64
least-squares reference and against the batched torch path it replaces, on synthetic and real fused blocks and
the edge cases of their weights (all observed, none, one voxel, weights of one value, weights of any value); its
conjugate-gradient refits (the default) against its exact refits.
scipy's L-BFGS reference of the refits is tests/test_observed.py's (it runs this pass too)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import sdfcodec
from sdfcodec.core.blocks import normalise
from sdfcodec.map.observed import error_weights, encode_truncated

pytest.importorskip("numba")

import sdfcodec_pca  # noqa: E402
from sdfcodec_pca import truncated  # noqa: E402
from test_observed import TRUNC, VS, fused_like, scene, weighted_lstsq  # noqa: E402


@pytest.fixture(scope="module")
def fused():
    """Normalised blocks ``(n, 16, 16, 16)`` of a fused-like synthetic scene that are not all free space, and
    their error weights (three values: 0, 1, 51)."""
    vol, obs = fused_like(scene())
    v = normalise(vol, *TRUNC).reshape(4, 16, 4, 16, 4, 16).transpose(0, 2, 4, 1, 3, 5).reshape(-1, 16, 16, 16)
    o = obs.reshape(4, 16, 4, 16, 4, 16).transpose(0, 2, 4, 1, 3, 5).reshape(-1, 16, 16, 16)
    keep = ~(v >= 1 - 1e-6).reshape(len(v), -1).all(axis=1)
    v, o = np.ascontiguousarray(v[keep]), o[keep]
    return v, error_weights(v, o, TRUNC, VS)


def _one_voxel(w: np.ndarray) -> np.ndarray:
    out = np.zeros_like(w)
    out.reshape(len(w), -1)[:, 1234] = 1.0
    return out


WEIGHTS = {
    "fused": lambda w, rng: w,
    "all observed": lambda w, rng: np.ones_like(w),
    "none observed": lambda w, rng: np.zeros_like(w),
    "one voxel observed": lambda w, rng: _one_voxel(w),
    "all of one value": lambda w, rng: np.full_like(w, 51.0),
    "any values": lambda w, rng: rng.uniform(0, 3, w.shape).astype(np.float32) * (rng.random(w.shape) < 0.6),
}


def batched(codec, x: np.ndarray, w: np.ndarray, rounds: int, monkeypatch) -> np.ndarray:
    """The batched torch path (the compiled pass switched off)."""
    with monkeypatch.context() as m:
        m.setattr(truncated, "available", lambda: False)
        return encode_truncated(codec, torch.from_numpy(x), torch.from_numpy(w), rounds=rounds).numpy()


def compiled(codec, x: np.ndarray, w: np.ndarray, rounds: int) -> np.ndarray:
    assert truncated.available()
    got = codec.encode_truncated(torch.from_numpy(x), torch.from_numpy(w), rounds)
    assert got is not None and got.dtype == torch.float32 and got.shape == (len(x), codec.code_size)
    return got.numpy()


def reader_error(codec, c: np.ndarray, x: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Per block: the weighted squared error of the decode a reader truncates to [0, 1]."""
    s = codec.state_dict()
    d = np.clip(c.astype(np.float64) @ s["components"] + s["mean"], 0, 1)
    return (w.reshape(len(w), -1) * (d - x.reshape(len(x), -1)) ** 2).sum(axis=1)


def assert_weighted_fit(codec, got: np.ndarray, x: np.ndarray, w: np.ndarray) -> None:
    """``got`` is the weighted least-squares fit: what the weights see of it equals float64 lstsq's to 0.1 % of
    the block's weighted norm, and its objective (with the ridge) is no worse than lstsq's by 0.1 %."""
    ref = weighted_lstsq(codec, x, w, sdfcodec_pca.RIDGE)
    s = codec.state_dict()
    comp, mean = s["components"].astype(np.float64), s["mean"].astype(np.float64)
    xf, wf = x.reshape(len(x), -1).astype(np.float64), w.reshape(len(w), -1).astype(np.float64)
    c0 = (xf - mean) @ comp.T
    lam = sdfcodec_pca.RIDGE * wf.mean(axis=1)
    norm = np.linalg.norm(np.sqrt(wf) * xf, axis=1)
    seen = lambda c: np.sqrt(wf) * (c @ comp)  # noqa: E731
    np.testing.assert_array_less(np.linalg.norm(seen(got) - seen(ref), axis=1), 1e-3 * norm + 1e-6)
    obj = lambda c: (wf * (c @ comp + mean - xf) ** 2).sum(1) + lam * ((c - c0) ** 2).sum(1)  # noqa: E731
    np.testing.assert_array_less(obj(got), obj(ref) * 1.001 + 1e-6)


@pytest.mark.parametrize("case", list(WEIGHTS))
@pytest.mark.parametrize("k", [32, 33])  # an odd code size: the Gram loop's last row and the last short panel
def test_compiled_weighted_fit_is_the_weighted_least_squares(fused, case, k):
    v, w0 = fused
    x, w = v[:6], WEIGHTS[case](w0[:6], np.random.default_rng(1))
    codec = sdfcodec.pretrained_codec("pca", k)
    got = codec.encode(x, weights=w)  # encode_weighted: the compiled pass without refits
    assert_weighted_fit(codec, got, x, w)
    if case == "none observed":  # nothing weighs: the ridge keeps the plain projection
        np.testing.assert_allclose(got, codec.encode(x), rtol=0, atol=1e-4)
    if case in ("all observed", "all of one value"):  # uniform weights: the projection itself
        np.testing.assert_allclose(got, codec.encode(x), rtol=0, atol=2e-5 * np.abs(codec.encode(x)).max())


@pytest.mark.parametrize("case", list(WEIGHTS))
@pytest.mark.parametrize("rounds", [1, 3])
def test_compiled_refits_equal_the_batched_path(fused, case, rounds, monkeypatch):
    monkeypatch.setattr(sdfcodec_pca.PCACodec, "cg_steps_per_refit", 0)  # the exact refits, as the batched path
    # the same active-set iteration. It is discontinuous: a voxel decoded within float32 rounding of its bound
    # flips in one path and not in the other, and the next refit differs by more than rounding (measured: the
    # compiled pass 1.3 % better to 0.26 % worse on single blocks). So: never worse than the batched path by
    # more than 0.5 % on any block (1e-5 absolute: errors of a single voxel, whose value is at most 1), nor by
    # 0.1 % in total; and on fused weights never worse than no refit (with one voxel weighed, dropping it leaves
    # the ridge's plain projection, which a reader may see worse: the iteration's own behaviour, both paths')
    v, w0 = fused
    w = WEIGHTS[case](w0, np.random.default_rng(2))
    codec = sdfcodec.pretrained_codec("pca", 64)
    got, ref = compiled(codec, v, w, rounds), batched(codec, v, w, rounds, monkeypatch)
    assert_same_refits(codec, got, ref, v, w)
    if case == "fused":
        assert np.all(reader_error(codec, got, v, w) <= reader_error(codec, codec.encode(v, weights=w), v, w) + 1e-6)


def assert_same_refits(codec, got: np.ndarray, ref: np.ndarray, x: np.ndarray, w: np.ndarray,
                       per_block: float = 1.005) -> None:
    e_got, e_ref = reader_error(codec, got, x, w), reader_error(codec, ref, x, w)
    np.testing.assert_array_less(e_got, e_ref * per_block + 1e-5)
    assert e_got.sum() <= e_ref.sum() * 1.001 + 1e-5


def test_real_fused_blocks_encode_as_the_batched_path(shared_data, tmp_path, monkeypatch):
    # a voxblox layer fused by voxblox itself: its observed voxels, band and bound voxels (at d_min here)
    sdfcodec.import_map(shared_data / "voxblox" / "labeltsdf_integrator_test_1.tsdf.voxblox", tmp_path / "r.sdfz")
    m = sdfcodec.open_map(tmp_path / "r.sdfz")
    h = m.header
    trunc = (h.truncation.d_min, h.truncation.d_max)
    pairs = list(m.iter_blocks())
    coords = np.concatenate([c for c, _ in pairs])
    v = normalise(np.clip(np.concatenate([b for _, b in pairs]), *trunc), *trunc).astype(np.float32)
    w = error_weights(v, m.read_observed(coords), trunc, h.voxel_size)
    assert (w == 0).any() and (w > 1).any() and ((v <= 1e-6) & (w > 0)).any()  # all three weights, bound voxels
    codec = sdfcodec.pretrained_codec("pca", 64)
    assert_weighted_fit(codec, codec.encode(v, weights=w), v, w)
    ref = batched(codec, v, w, 3, monkeypatch)
    assert_cg_refits_as_good(codec, compiled(codec, v, w, 3), ref, v, w)  # the default: conjugate-gradient steps
    monkeypatch.setattr(sdfcodec_pca.PCACodec, "cg_steps_per_refit", 0)
    assert_same_refits(codec, compiled(codec, v, w, 3), ref, v, w)


def assert_cg_refits_as_good(codec, got: np.ndarray, exact: np.ndarray, x: np.ndarray, w: np.ndarray) -> None:
    """The conjugate-gradient refits (``got``) leave a reader the error the exact refits (``exact``) leave, in
    total (within 1 %), and no block more than 1.3x its exact error (measured at the writer's 6 steps: kitchen
    half +0.0 % in total, worst block +23 %; analytic blocks -0.1 %, worst +13 %)."""
    e_got, e_ref = reader_error(codec, got, x, w), reader_error(codec, exact, x, w)
    assert e_got.sum() <= e_ref.sum() * 1.01 + 1e-5
    np.testing.assert_array_less(e_got, e_ref * 1.3 + 1e-5)


@pytest.mark.parametrize("case", list(WEIGHTS))
def test_cg_refits_leave_the_error_of_the_exact_refits(fused, case, monkeypatch):
    # the writer's default (PCACodec.cg_steps_per_refit steps per refit asked for) against the exact active-set
    # refits, on a fused-like scene and the edge cases of its weights; and more steps reach the exact refits'
    # error or better on every block (both minimise the same convex error; the refits stop after 3 rounds)
    v, w0 = fused
    w = WEIGHTS[case](w0, np.random.default_rng(2))
    codec = sdfcodec.pretrained_codec("pca", 64)
    got = compiled(codec, v, w, 3)
    with monkeypatch.context() as m:
        m.setattr(sdfcodec_pca.PCACodec, "cg_steps_per_refit", 0)
        exact = compiled(codec, v, w, 3)
    assert_cg_refits_as_good(codec, got, exact, v, w)
    with monkeypatch.context() as m:
        m.setattr(sdfcodec_pca.PCACodec, "cg_steps_per_refit", 10)
        np.testing.assert_array_less(reader_error(codec, compiled(codec, v, w, 3), v, w),
                                     reader_error(codec, exact, v, w) * 1.005 + 1e-5)
    if case == "none observed":  # nothing weighs, nothing to refit: the plain projection
        np.testing.assert_allclose(got, codec.encode(v), rtol=0, atol=1e-4)
    if case == "fused":  # and a reader sees less error than without refits
        assert np.all(reader_error(codec, got, v, w) <= reader_error(codec, codec.encode(v, weights=w), v, w) + 1e-6)


def test_cg_refits_on_analytic_blocks(monkeypatch):
    # what the benchmark's encode-masked times: analytic SDF blocks with the weights a fused map gives them
    from sdfcodec.bench.codecs import fused_style_weights
    from sdfcodec.testing import analytic_blocks

    v = analytic_blocks(256, seed=3)
    w = fused_style_weights(v)
    codec = sdfcodec.pretrained_codec("pca", 64)
    got = compiled(codec, v, w, 3)
    monkeypatch.setattr(sdfcodec_pca.PCACodec, "cg_steps_per_refit", 0)
    assert_cg_refits_as_good(codec, got, compiled(codec, v, w, 3), v, w)


def test_cg_refits_reach_the_optimum_of_the_readers_error():
    # the writer's default steps (3 refits) against the exact optimum of the same convex objective (squared error,
    # one-sided at the bound voxels, plus the ridge of the given weights): within 1 % in total on the benchmark's
    # analytic blocks. The steps start from the fit without the bound voxels, which most blocks' optimum decodes
    # beyond their bound; from the fit with them (the earlier start) 6 steps left 5.7 % above it.
    from sdfcodec.bench.codecs import fused_style_weights
    from sdfcodec.testing import analytic_blocks

    v = analytic_blocks(24, seed=5)
    w = fused_style_weights(v)
    codec = sdfcodec.pretrained_codec("pca", 64)
    got = compiled(codec, v, w, 3).astype(np.float64)
    s = codec.state_dict()
    comp, mean = s["components"].astype(np.float64), s["mean"].astype(np.float64)
    f_got, f_opt = 0.0, 0.0
    for i in range(len(v)):
        x, wi = v[i].reshape(-1).astype(np.float64), w[i].reshape(-1).astype(np.float64)
        c0, lam = (x - mean) @ comp.T, sdfcodec_pca.RIDGE * wi.mean()
        top, bot = (x >= 1 - 1e-6) & (wi > 0), (x <= 1e-6) & (wi > 0)

        def objective(c):
            r = c @ comp + mean - x
            r = np.where(top, np.minimum(r, 0), np.where(bot, np.maximum(r, 0), r))
            return (wi * r * r).sum() + lam * ((c - c0) ** 2).sum(), 2 * comp @ (wi * r) + 2 * lam * (c - c0)

        # the optimum, by float64 Newton steps on the objective (a quadratic on each set of counted voxels: solve
        # it exactly, count again, until the set stays): where the set stays, the gradient is zero and the convex
        # objective at its minimum (scipy's L-BFGS run to convergence found the same minima to 1e-13, 10x slower)
        c, counted = c0, None
        for _ in range(100):
            r = c @ comp + mean - x
            now = ~((top & (r > 0)) | (bot & (r < 0)))
            if counted is not None and np.array_equal(now, counted):
                break
            counted, a = now, comp[:, now] * wi[now]
            c = np.linalg.solve(a @ comp[:, now].T + lam * np.eye(len(c0)), a @ (x - mean)[now] + lam * c0)
        else:
            raise AssertionError(f"block {i}: the counted voxels still change after 100 Newton steps")
        f, grad = objective(c)
        assert np.abs(grad).max() <= 1e-9 * max(1.0, f), (i, np.abs(grad).max())
        f_got += objective(got[i])[0]
        f_opt += f
    assert f_opt <= f_got <= f_opt * 1.01


def test_the_batched_path_runs_where_the_pass_does_not_apply(fused):
    # mean="block" codes have a block-mean slot (no least-squares coefficient of one basis): the batched path
    v, w = fused
    codec = sdfcodec.get_codec("pca", code_size=16, mean="block").fit(v)
    assert codec.encode_truncated(torch.from_numpy(v), torch.from_numpy(w), 3) is None
    assert encode_truncated(codec, torch.from_numpy(v), torch.from_numpy(w)).shape == (len(v), 16)


def _octree_weights(rng) -> np.ndarray:
    """Weights ``(6, 4096)`` whose patterns reach every level of the Gram's octree: uniform octants, 4^3 and 2^3
    cells of 0, 1 and 51, a fused-like band, single voxels of other values, and noise."""
    out = []
    for cell in (8, 4, 2, 1):
        n = 16 // cell
        coarse = rng.choice(np.array([0.0, 1.0, 51.0], np.float32), size=(n, n, n))
        out.append(np.kron(coarse, np.ones((cell,) * 3, np.float32)).reshape(-1))
    mixed = out[1].copy()
    mixed[rng.choice(4096, 40, replace=False)] = rng.uniform(0, 3, 40).astype(np.float32)
    out.append(mixed)
    out.append(rng.uniform(0, 3, 4096).astype(np.float32) * (rng.random(4096) < 0.6))
    return np.stack(out)


def test_octree_plan_gives_every_voxel_its_weight():
    # the plan's telescoping sum (pieces of octree nodes times weight changes, plus voxels left over) weighs each
    # voxel exactly as given: rebuilt here from the plan by walking every node's voxels
    from sdfcodec_pca import kernels

    rng = np.random.default_rng(5)
    k = 3
    for wi in _octree_weights(rng):
        cand = np.array([0, 1, wi.max() if wi.max() != 1 else 0], np.float32)
        idx, scale = np.empty(4096, np.int64), np.empty(4096, np.float32)
        nodes, node_scale = np.empty(585, np.int64), np.empty(585, np.float32)
        m, npc = kernels.plan(wi, cand, np.float32(1.5), True, np.empty((585, 3), np.float32),
                              np.empty(585, np.int64), idx, scale, nodes, node_scale)
        got = np.zeros(4096, np.float64)
        grid = np.arange(4096).reshape(16, 16, 16)
        for u, s in zip(nodes[:npc], node_scale[:npc]):
            level = int(np.searchsorted([0, 1, 9, 73, 585], u, side="right")) - 1
            n, cell = 1 << level, 16 >> level
            x, y, z = np.unravel_index(u - [0, 1, 9, 73][level], (n, n, n))
            got[grid[x * cell:(x + 1) * cell, y * cell:(y + 1) * cell, z * cell:(z + 1) * cell].reshape(-1)] += s
        np.add.at(got, idx[:m], scale[:m])
        np.testing.assert_allclose(got, wi, rtol=0, atol=1e-4)
        assert m + npc <= np.count_nonzero(wi) + 1  # never more work than the voxels one by one
    uniform = np.kron(np.array([0.0, 51.0] * 4, np.float32).reshape(2, 2, 2), np.ones((8, 8, 8), np.float32))
    m, npc = kernels.plan(uniform.reshape(-1), np.array([0, 1, 51], np.float32), np.float32(1.5), True,
                          np.empty((585, 3), np.float32), np.empty(585, np.int64), np.empty(4096, np.int64),
                          np.empty(4096, np.float32), np.empty(585, np.int64), np.empty(585, np.float32))
    assert (m, npc) == (0, 4)  # four octants of 51: four pieces, no voxel


@pytest.mark.parametrize("k", [64, 130])  # 130: above the octree table's limit, the block's Gram only
def test_gram_pieces_are_the_grams_of_their_voxels(k):
    # each node's packed triangle against numpy's float64 Gram of the basis rows of that node's voxels
    rng = np.random.default_rng(7)
    dt = rng.standard_normal((4096, k)).astype(np.float32)
    pieces = truncated.gram_pieces(dt)
    rows, cols = np.tril_indices(k)
    grid = np.arange(4096).reshape(16, 16, 16)
    d64 = dt.astype(np.float64)
    if k > 128:
        assert pieces.shape == (1, k * (k + 1) // 2)
        np.testing.assert_allclose(pieces[0], (d64.T @ d64)[rows, cols], rtol=1e-5, atol=1e-2)
        return
    assert pieces.shape == (585, k * (k + 1) // 2)
    for u in (0, 1, 8, 9, 40, 72, 73, 300, 584):
        level = int(np.searchsorted([0, 1, 9, 73, 585], u, side="right")) - 1
        n, cell = 1 << level, 16 >> level
        x, y, z = np.unravel_index(u - [0, 1, 9, 73][level], (n, n, n))
        vox = grid[x * cell:(x + 1) * cell, y * cell:(y + 1) * cell, z * cell:(z + 1) * cell].reshape(-1)
        np.testing.assert_allclose(pieces[u], (d64[vox].T @ d64[vox])[rows, cols], rtol=1e-5, atol=1e-2)


@pytest.mark.parametrize("k", [64, 33])
def test_compiled_fit_on_octree_patterns_is_the_weighted_least_squares(fused, k):
    # weights uniform over octants and cells (the Gram from pieces only), mixed, and noise: float64 lstsq's fit
    v, _ = fused
    w = _octree_weights(np.random.default_rng(3)).reshape(-1, 16, 16, 16)
    x = v[:len(w)]
    codec = sdfcodec.pretrained_codec("pca", k)
    assert_weighted_fit(codec, codec.encode(x, weights=w), x, w)


@pytest.mark.parametrize("compiled", [False, True])  # numpy's residuals (few blocks) or the compiled pass
def test_normal_rhs_is_the_weighted_projection(compiled, monkeypatch):
    # the right-hand sides from one product per slab against float64 D diag(w) (x - d), block by block, across
    # more blocks than one slab holds; all weights 0 give exactly 0 and the weight sums are the weights' sums
    monkeypatch.setattr(truncated, "COMPILED_RESIDUALS_MIN", 0 if compiled else 10 ** 9)
    rng = np.random.default_rng(11)
    n, k = truncated._RHS_SLAB + 3, 33
    dt = rng.standard_normal((4096, k)).astype(np.float32)
    dec_b = rng.uniform(0, 1, 4096).astype(np.float32)
    x = rng.uniform(0, 1, (n, 4096)).astype(np.float32)
    w = rng.choice(np.array([0, 1, 51], np.float32), size=(n, 4096))
    w[0] = 0
    w[1] = 0
    w[1, 77] = 2.5  # one voxel
    rhs, wsum = truncated.normal_rhs(x, w, dt, dec_b)
    x64, w64, d64 = x.astype(np.float64), w.astype(np.float64), dt.astype(np.float64)
    ref = np.stack([d64.T @ (wi * (xi - dec_b)) for xi, wi in zip(x64, w64)])
    assert rhs.dtype == np.float32 and rhs.shape == (n, k)
    np.testing.assert_allclose(rhs, ref, rtol=1e-4, atol=1e-4 * np.abs(ref).max())
    assert np.all(rhs[0] == 0)
    np.testing.assert_allclose(rhs[1], 2.5 * (x64[1, 77] - dec_b[77]) * d64[77], rtol=1e-6)
    np.testing.assert_allclose(wsum, w64.sum(axis=1))
    # drop_bound: the voxels stored at a bound (0 or 1) weigh nothing in the sides, as much as given in the sums
    x[2:, ::7] = 1.0
    x[2:, 3::7] = 0.0
    rhs, wsum = truncated.normal_rhs(x, w, dt, dec_b, drop_bound=True)
    x64 = x.astype(np.float64)
    keep = (x64 > 1e-6) & (x64 < 1 - 1e-6)
    ref = np.stack([d64.T @ (wi * ki * (xi - dec_b)) for xi, wi, ki in zip(x64, w64, keep)])
    np.testing.assert_allclose(rhs, ref, rtol=1e-4, atol=1e-4 * np.abs(ref).max())
    np.testing.assert_allclose(wsum, w64.sum(axis=1))


@pytest.mark.parametrize("k", [64, 33])  # 33: the last row's group of eight columns runs past k
def test_gram_rows_fill_the_lower_triangle(k):
    # add_rows against float64 D^T diag(s) D over the same voxels (any number, not a multiple of four; scales of
    # both signs, as a weight change has), onto a Gram that already holds something: the lower triangle only
    from sdfcodec_pca import kernels

    rng = np.random.default_rng(13)
    dt = rng.standard_normal((4096, k)).astype(np.float32)
    m = 203
    idx = rng.choice(4096, m, replace=False).astype(np.int64)
    scale = rng.uniform(-2, 51, m).astype(np.float32)
    g0 = rng.standard_normal((k, k)).astype(np.float32)
    g = g0.copy()
    kernels.add_rows(g, dt, idx, scale, m)
    d64 = dt[idx].astype(np.float64)
    ref = g0 + d64.T @ (scale[:, None].astype(np.float64) * d64)
    rows, cols = np.tril_indices(k)
    np.testing.assert_allclose(g[rows, cols], ref[rows, cols], rtol=1e-4, atol=1e-4 * np.abs(ref).max())


def test_far_bound_voxels_join_as_when_every_one_is_decoded():
    # recheck_far keeps the far bound voxels that cannot have come within the threshold without decoding them,
    # from a lower bound of how far each lay beyond its bound at the previous code: the voxels that join (in
    # order, their rows gathered) and those kept must be what decoding every one of them gives (numpy, float64),
    # and the bounds it carries on must stay below the true distances
    from sdfcodec_pca import kernels

    rng = np.random.default_rng(17)
    k = 64
    q, _ = np.linalg.qr(rng.standard_normal((4096, k)))
    dt = np.ascontiguousarray(q, dtype=np.float32)  # orthonormal columns, as a basis's
    xi = np.where(rng.random(4096) < 0.5, 1.0, 0.0).astype(np.float32)  # at d_max or d_min
    # decoded from 0.2 inside their bound to 0.6 beyond it; the code moves by ~0.4 (each decode by up to ~0.07)
    dec_b = np.where(xi >= 1, 1 + rng.uniform(-0.2, 0.6, 4096), -rng.uniform(-0.2, 0.6, 4096)).astype(np.float32)
    d64 = dt.astype(np.float64)
    prev = rng.standard_normal(k).astype(np.float32)
    code = (prev + 0.05 * rng.standard_normal(k)).astype(np.float32)
    dec_prev, dec_now = d64 @ prev + dec_b, d64 @ code + dec_b
    wi = np.full(4096, 1.0, np.float32)

    def beyond(dec):
        return np.where(xi >= 1, dec - 1, -dec)

    thr = 0.05
    far = np.flatnonzero(beyond(dec_prev) > thr)
    far = far[np.abs(beyond(dec_now)[far] - thr) > 1e-3]  # no voxel within rounding of the threshold
    nf = len(far)
    far_k, lbf = far.astype(np.int64), beyond(dec_prev)[far].astype(np.float32)
    cprev = prev.copy()
    bufs = [np.zeros((4096, k), np.float32)] + [np.zeros(4096, np.float32) for _ in range(5)]
    kept, nr = kernels.recheck_far(code, cprev, xi, wi, dt, dec_b, kernels.row_norms(dt), far_k, lbf, nf,
                                   np.float32(thr), 0, *bufs, np.empty(4096, np.int64), np.empty(4096, np.float32))
    joins = beyond(dec_now)[far] <= thr
    assert 0 < nr < nf and nr == joins.sum() and kept == nf - nr
    np.testing.assert_array_equal(bufs[0][:nr], dt[far[joins]])
    np.testing.assert_array_equal(far_k[:kept], far[~joins])
    assert np.all(lbf[:kept] <= beyond(dec_now)[far[~joins]] + 1e-5)
    assert np.any(lbf[:kept] < beyond(dec_now)[far[~joins]] - 1e-3)  # some kept on their bound, not decoded
    np.testing.assert_array_equal(cprev, code)
