"""What a first search computes, against independent computations: the built-in query shapes sampled one block
at a time, the duplicates a sort finds, the plane check's residuals and the observed scores by brute force over
every voxel in float64. The fast paths of a search's start-up (sdfcodec.search.shapes, plane_check, scoring)
must give what these give."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sdfcodec import pretrained_codec
from sdfcodec.core.geometry import rot_y, rot_z, rotation_to
from sdfcodec.map.observed import SURFACE_BAND_VOXELS
from sdfcodec.search.plane_check import BAND_VOXELS, JUMP_VOXELS, plane_residuals
from sdfcodec.search.scoring import MIN_OBSERVED_SURFACE, ObservedScorer, Scorer, score_codes
from sdfcodec.search.shapes import (FUSED_STRETCH, MIN_SHAPE_SURFACE, WALL_YAWS, dedupe_blocks, plane_offsets,
                                    query_blocks)

VS, TRUNC = 0.02, (-0.04, 0.1)
_G = np.stack(np.meshgrid(*[np.arange(16, dtype=np.float64) - 7.5] * 3, indexing="ij"), -1)


def _plane_block(normal: np.ndarray, offset: float, stretch: float, behind: str) -> tuple[np.ndarray, np.ndarray]:
    """One plane block by hand: normalised field and observed voxels (a camera in front of it)."""
    d = (_G @ normal - offset) * VS * stretch
    v = np.clip(d, *TRUNC)
    if behind == "unobserved":
        v = np.where(d < TRUNC[0], TRUNC[1], v)
    seen = d >= TRUNC[0] if behind == "unobserved" else np.ones(d.shape, bool)
    return ((v - TRUNC[0]) / (TRUNC[1] - TRUNC[0])).astype(np.float32), seen


@pytest.mark.parametrize("behind", ["unobserved", "solid"])
def test_wall_blocks_are_their_planes_sampled_one_block_at_a_time(behind):
    """Every wall block (a map's gravity up, fused stretches) is the field of its own plane computed here one block
    at a time, at one of the stretches; the planes are the 24 yaws' normals, perpendicular to up, and every plane
    the model holds that crosses more than a corner sliver of the block is there, at every stretch, once."""
    up = np.array([-0.104473, -0.89097, -0.44188])
    stretch = FUSED_STRETCH if behind == "unobserved" else (1.0,)
    v, rot, pos, seen = query_blocks("wall", voxel_size=VS, truncation=TRUNC, up=up, behind=behind,
                                     stretch=stretch, return_observed=True)
    normals = rot[:, :, 2].astype(np.float64)
    assert np.abs(normals @ (up / np.linalg.norm(up))).max() < 1e-6
    wanted = {tuple(np.round(rotation_to(up) @ rot_z(2 * math.pi * k / WALL_YAWS) @ rot_y(math.pi / 2)[:, 2], 5))
              for k in range(WALL_YAWS)}
    assert {tuple(n) for n in np.round(normals, 5)} == wanted
    lattice = set(np.round(plane_offsets(voxel_size=VS, truncation=TRUNC, behind=behind), 4))
    rng = np.random.default_rng(0)
    for i in rng.choice(len(v), 64, replace=False):
        n = normals[i] / np.linalg.norm(normals[i])
        match = [k for k, st in enumerate(stretch)
                 if np.allclose(v[i], _plane_block(n, float(pos[i, 2]), st, behind)[0], atol=2e-6)]
        assert match, f"block {i} is no plane of its normal and offset at any stretch"
        assert np.array_equal(seen[i], _plane_block(n, float(pos[i, 2]), stretch[match[0]], behind)[1])
        assert (np.abs(_G @ n - pos[i, 2]) <= 1.0).sum() >= MIN_SHAPE_SURFACE
    # each (normal, offset) at every stretch, offsets on the model's lattice continued at its step
    keys = {(tuple(np.round(n, 5)), round(float(p), 4)) for n, p in zip(normals, pos[:, 2])}
    assert len(v) == len(keys) * len(stretch)
    start, step = min(lattice), float(np.diff(sorted(lattice))[0])
    assert all(abs((p - start) / step - round((p - start) / step)) < 1e-3 for _, p in keys)


def test_dedupe_keeps_what_a_sort_of_the_rounded_rows_keeps():
    """dedupe_blocks keeps the first of each set of blocks equal to 1e-4 (and -0.0 equal to 0.0), in order, with
    the extra arrays cut alike: what np.unique over the rounded rows' bytes keeps."""
    rng = np.random.default_rng(3)
    for _ in range(30):
        base = np.round(rng.random((int(rng.integers(1, 30)), 16, 16, 16)), int(rng.integers(1, 3)))
        copies = base[rng.integers(0, len(base), int(rng.integers(0, 15)))]
        copies = copies + rng.choice([0.0, 1e-6, -1e-6, 3e-4], size=(len(copies), 1, 1, 1))
        blocks = np.concatenate([base, copies]).astype(np.float32)
        if rng.random() < 0.5:
            blocks[rng.integers(len(blocks))] *= -0.0
        key = np.ascontiguousarray(np.round(blocks.reshape(len(blocks), -1), 4) + 0.0)
        _, first = np.unique(key.view(np.dtype((np.void, key.dtype.itemsize * key.shape[1]))).ravel(),
                             return_index=True)
        got, rows = dedupe_blocks(blocks, np.arange(len(blocks)))
        assert np.array_equal(rows, np.sort(first)) and np.array_equal(got, blocks[np.sort(first)])


def test_plane_residuals_equal_the_brute_force_over_every_voxel():
    """plane_residuals' residual and best move (computed over the observed voxels near each moved plane only) are
    the float64 minimum over every move and stretch of the sum, over all 4,096 voxels, of the squared difference
    to the plane's field where a voxel is observed, within BAND_VOXELS of the moved plane and away from the jump;
    a move leaving the plane a corner sliver of the block, or nothing to compare, is no candidate."""
    rng = np.random.default_rng(11)
    n_blocks, tol, stretches = 40, 2.0, np.asarray(FUSED_STRETCH)
    g = _G.reshape(-1, 3)
    normals = rng.normal(size=(n_blocks, 3))
    normals /= np.linalg.norm(normals, axis=1)[:, None]
    dist = (g @ normals.T).T - rng.uniform(-9, 9, (n_blocks, 1))
    x = np.stack([_plane_block(nk, 0.0, 1.3, "unobserved")[0].ravel() for nk in normals])
    x = np.roll(x, 1, axis=1) + rng.normal(0, 0.05, x.shape).astype(np.float32)  # the plane, shifted and noisy
    observed = rng.random(x.shape) < 0.8
    r, seen, moved, *_ = plane_residuals(x.astype(np.float32), observed, dist.astype(np.float32), voxel_size=VS,
                                         truncation=TRUNC, behind="unobserved", stretches=stretches, tol=tol)
    deltas = np.arange(-tol, tol + 1e-9, 0.5)
    lo, span = np.float32(TRUNC[0]), np.float32(TRUNC[1] - TRUNC[0])
    for i in range(n_blocks):
        by_move = {}
        for delta in deltas:
            t = dist[i].astype(np.float32).astype(np.float64) - delta
            if (np.abs(t) <= 1.0).sum() < MIN_SHAPE_SURFACE:
                continue
            for st in stretches:
                d = (t * st).astype(np.float32) * np.float32(VS)  # the field in float32, as a map stores it
                field = np.where(d < lo, np.float32(1.0), (np.clip(d, lo, np.float32(TRUNC[1])) - lo) / span)
                use = observed[i] & (np.abs(t) <= BAND_VOXELS) & (np.abs(d - lo) > JUMP_VOXELS * VS)
                if use.any():
                    e = float((((field.astype(np.float64) - x[i]) ** 2) * use).sum())
                    by_move[delta] = min(by_move.get(delta, np.inf), e)
        if not by_move:
            assert not np.isfinite(r[i])
            continue
        best = min(by_move.values())
        assert r[i] == pytest.approx(best, rel=1e-4, abs=1e-5)
        assert by_move[moved[i]] == pytest.approx(best, rel=1e-4, abs=1e-5)
        assert seen[i] == ((np.abs(dist[i].astype(np.float32)) <= 1.0) & observed[i]).sum()


def test_observed_scores_equal_the_brute_force_over_the_observed_voxels():
    """The scores of partly observed blocks (ObservedScorer through score_codes, products in row tiles) are the
    float64 minimum over the descriptors of 4096 / n_obs times the squared difference of the truncated decodes
    over the observed voxels; blocks with too little surface observed, and whole blocks, keep their code score."""
    codec = pretrained_codec("pca", 32)
    rng = np.random.default_rng(5)
    q = rng.normal(0, 2.0, (300, 32)).astype(np.float32)
    codes = np.concatenate([q[rng.integers(0, 300, 150)] + rng.normal(0, 0.5, (150, 32)),
                            rng.normal(0, 4.0, (150, 32))]).astype(np.float32)
    observed = np.ones((300, 4096), bool)
    for i in range(250):  # partly observed: a random half-space of each block (the last 50 whole)
        n = rng.normal(size=3)
        observed[i] = _G.reshape(-1, 3) @ n <= rng.uniform(-6, 6)
    observed[:20] &= rng.random((20, 4096)) < 0.002  # a few voxels only: no surface seen to compare
    observed[20:30] = False
    scorer, obs = Scorer(q, "cpu"), ObservedScorer(q, codec, TRUNC, VS)
    s, idx = score_codes(scorer, obs, codes, observed.reshape(-1, 16, 16, 16))
    plain, plain_idx = scorer(codes)

    def dec(c):
        return np.clip(codec.numpy_path().decode(c).astype(np.float64), 0.0, 1.0)

    xq, xc = dec(q), dec(codes)
    v0, half = -TRUNC[0] / (TRUNC[1] - TRUNC[0]), SURFACE_BAND_VOXELS * VS / (TRUNC[1] - TRUNC[0])
    masked = 0
    for i in range(300):
        o = observed[i]
        if o.all() or ((np.abs(xc[i] - v0) < half) & o).sum() < MIN_OBSERVED_SURFACE:
            assert s[i] == plain[i] and idx[i] == plain_idx[i]
            continue
        d = (((xq - xc[i]) ** 2) * o).sum(axis=1) * 4096 / o.sum()
        assert s[i] == pytest.approx(d.min(), rel=2e-3, abs=2e-2)
        assert d[idx[i]] == pytest.approx(d.min(), rel=2e-3, abs=2e-2)
        masked += 1
    assert masked > 100 and all(s[:30] == plain[:30])  # most partly observed blocks scored where observed


def _plane_inputs(seed: int, n_blocks: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Noisy, partly observed plane blocks and their voxels' distances to tilted planes (as the check sees them)."""
    rng = np.random.default_rng(seed)
    g = _G.reshape(-1, 3)
    normals = rng.normal(size=(n_blocks, 3))
    normals /= np.linalg.norm(normals, axis=1)[:, None]
    dist = (g @ normals.T).T - rng.uniform(-9, 9, (n_blocks, 1))
    x = np.stack([_plane_block(nk, 0.0, 1.3, "unobserved")[0].ravel() for nk in normals])
    x = np.roll(x, 1, axis=1) + rng.normal(0, 0.05, x.shape).astype(np.float32)
    return x.astype(np.float32), rng.random(x.shape) < 0.8, dist.astype(np.float32)


def test_plane_residuals_do_not_depend_on_how_the_blocks_are_tiled(monkeypatch):
    """plane_residuals runs its blocks in row tiles on every core: every result of every block is the same, to the
    bit, whether the tiles hold one block, five or the default, with and without the zero-crossing rule."""
    import sdfcodec.search.plane_check as pc

    x, observed, dist = _plane_inputs(5, 45)
    kw = dict(voxel_size=VS, truncation=TRUNC, behind="unobserved", stretches=np.asarray(FUSED_STRETCH), tol=2.0)
    for crossings in (False, True):
        want = plane_residuals(x, observed, dist, crossings=crossings, **kw)
        for rows in (1, 5):
            monkeypatch.setattr(pc, "CHECK_ROWS", rows)
            got = plane_residuals(x, observed, dist, crossings=crossings, **kw)
            assert all(a.dtype == b.dtype and np.array_equal(a, b, equal_nan=True) for a, b in zip(got, want))
        monkeypatch.undo()


def test_the_rise_of_each_block_is_the_median_of_its_pairs():
    """_rise takes every block's median at once: what np.median gives over each block's pairs of observed voxels one
    step apart along the normal's axis, both near the plane and off the truncation bounds (NaN under
    MIN_VERDICT_SURFACE pairs), including blocks with an even and an odd count of pairs."""
    from sdfcodec.search.plane_check import MIN_VERDICT_SURFACE, _rise

    x, observed, dist = _plane_inputs(9, 30)
    observed[:3] = False  # no pairs at all
    observed[3, :4000] = False  # a few
    normal = np.array([0.3, -0.2, 0.93])
    normal /= np.linalg.norm(normal)
    got = _rise(x, observed, dist, normal, voxel_size=VS, truncation=TRUNC)
    dec = ((x * (TRUNC[1] - TRUNC[0]) + TRUNC[0]) / VS).reshape(-1, 16, 16, 16)
    ok = (observed.reshape(dec.shape) & (np.abs(dist).reshape(dec.shape) <= BAND_VOXELS + 1.0)
          & (dec > TRUNC[0] / VS + 0.25) & (dec < TRUNC[1] / VS - 0.25))
    counts = set()
    for i in range(len(x)):  # along z, the normal's largest component, rising with it
        both = ok[i, :, :, 1:] & ok[i, :, :, :-1]
        counts.add(int(both.sum()) % 2)
        if both.sum() < MIN_VERDICT_SURFACE:
            assert np.isnan(got[i])
        else:
            step = (dec[i, :, :, 1:] - dec[i, :, :, :-1]).astype(np.float64)[both]
            assert got[i] == np.median(step) / normal[2]
    assert counts == {0, 1} and np.isnan(got[:3]).all() and np.isfinite(got).sum() > 20


@pytest.fixture
def no_query_cache(monkeypatch):
    from sdfcodec.search import cache

    monkeypatch.setenv(cache.CACHE_ENV, "off")
    cache.clear_memory_cache()
    yield
    cache.clear_memory_cache()


def test_a_first_encode_runs_beside_the_making_of_the_shapes_and_changes_no_code(monkeypatch, no_query_cache):
    """A model built on a cache miss starts the codec's first encode (pca: numba's start) in a thread before the
    shapes are made, and its descriptors are still the shapes encoded as one call of encode_query_blocks gives."""
    import threading

    from sdfcodec.search import models

    codec = pretrained_codec("pca", 64)
    threads: list[str] = []
    real = models.query_blocks

    def spy(*a, **k):
        threads.extend(t.name for t in threading.enumerate())
        return real(*a, **k)

    monkeypatch.setattr(models, "query_blocks", spy)
    args = dict(voxel_size=VS, truncation=TRUNC, up=(0.0, 0.0, 1.0), rotations=None, offsets="auto",
                behind="unobserved", stretch=(1.0, 2.0))
    q = models.shape_model("floor", codec, weighted=True, keep_blocks=False, **args)
    assert "sdfcodec-first-encode" in threads
    v, _, _, seen = real("floor", return_observed=True, **args)
    assert np.array_equal(q.descriptors, models.encode_query_blocks(codec, v, seen, TRUNC, VS, True))


def test_a_failing_first_encode_leaves_one_error_to_the_real_encode(monkeypatch, no_query_cache, capfd):
    """What goes wrong in the first encode's thread is raised once, by the encode of the shapes, in the caller's
    thread; the thread prints nothing."""
    from sdfcodec.errors import InvalidValueError
    from sdfcodec.search import models

    calls = []

    def broken(*a, **k):
        calls.append(1)
        raise InvalidValueError("this codec cannot encode")

    monkeypatch.setattr(models, "encode_query_blocks", broken)
    with pytest.raises(InvalidValueError, match="cannot encode"):
        models.shape_model("floor", pretrained_codec("pca", 64), VS, TRUNC, (0.0, 0.0, 1.0), None, "auto",
                           "unobserved", True, (1.0,), False)
    assert len(calls) == 2  # the thread's and the real one
    assert "Exception in thread" not in capfd.readouterr().err
