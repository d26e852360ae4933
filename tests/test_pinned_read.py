"""The pinned mask read from the reader's own float decode (sdfcodec.map.pinread, sdfcodec.core.pinkernels): the
margin bounds the codec's float32 decode against the exact integer decode on real codes, and the pinned voxels
told from a float decode are the exact decode's, bit for bit, whatever the float decode within the margin (voxels
on the thresholds included); a map read through it reads what the exact decode's pins give."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

import sdfcodec
from _fused_maps import TRUNC, VS, fused_like
from sdfcodec.core import ans
from sdfcodec.core.blocks import split_blocks
from sdfcodec.core.sdf import sample_volume
from sdfcodec.map import pinmask as pm
from sdfcodec.map import pinread
from sdfcodec.map.grouping import each_chunk
from sdfcodec.registry import pretrained_codec
from sdfcodec.testing import analytic_scene

pytestmark = pytest.mark.skipif(not ans.available(), reason="numba is not installed: the exact decode is the read")
GOLDEN = Path(__file__).parent / "golden" / "maps" / "pinned-mask-pca-8" / "map.zarr"
R = TRUNC[1] - TRUNC[0]


def _case(step: float, size: int = 64, trunc=TRUNC):
    """A fused room under the shipped pca-``size`` quantised at ``step``: coords, integer codes, fixed-point basis,
    and the codec's own float32 decode in metres (as a reader decodes: the output scaling folded in, unclipped)."""
    vol, _ = fused_like(sample_volume(analytic_scene(), (64, 64, 48), VS, truncation=trunc))
    blocks = split_blocks(vol, fill=trunc[1]).reshape(-1, 16, 16, 16)
    coords = np.argwhere(np.ones(split_blocks(vol, fill=trunc[1]).shape[:3], bool))
    keep = ~(blocks >= trunc[1] - 1e-6).reshape(len(blocks), -1).all(axis=1)
    coords, blocks = coords[keep], blocks[keep]
    codec = pretrained_codec("pca", size)
    r = trunc[1] - trunc[0]
    q = np.rint(np.asarray(codec.encode(((blocks - trunc[0]) / r).astype(np.float32))) / step)
    sd = codec.state_dict()
    basis = pm.fixed_point_basis(sd["components"], sd["mean"], np.full(size, step), trunc)
    codes = torch.from_numpy((q.astype(np.int32) * np.full(size, step)).astype(np.float32))  # as codes_for
    v = codec.decode_core(codes, scale=r, offset=trunc[0]).numpy().reshape(len(q), -1)
    return coords, q, basis, v


def _bools(rows: np.ndarray) -> np.ndarray:
    """(n, 16, 16, 16) bool of pin rows (n, 16, 16) uint16, bit z for voxel z."""
    return ((rows[..., None] >> np.arange(16, dtype=np.uint16)) & 1).astype(bool)


@pytest.mark.parametrize("step", [0.02, 0.3, 1.5])
def test_the_margin_bounds_the_codecs_float_decode(step):
    """|2^24 x - w| <= float_margin for every voxel (x: the codec's float32 decode, w: the exact decode), on codes
    from small to large. The margin is nearly reached: the basis's rounding to integers, times a large leading
    code, is most of it (step 0.02: 0.85 of it)."""
    _, q, basis, v = _case(step)
    w, _ = pm.exact_decode(q, basis)
    peak, _ = pm.decode_bounds(q, basis)
    dev = np.abs(v.astype(np.float64) * 2.0 ** 24 - w).max(axis=1)
    margin = pinread.float_margin(q, peak)
    assert (dev <= margin).all()
    assert 0.2 < (dev / margin).max()  # the bound is not vacuous


@pytest.mark.parametrize("step,trunc", [(0.05, TRUNC), (0.6, TRUNC), (0.05, (-0.02, 0.02))])
def test_pins_told_from_a_float_decode_are_the_exact_pins(step, trunc):
    """decode_pins gives pinned_voxels_of the exact decode's signs: from the codec's decode (truncated to the
    range, as a reader has it), from a decode moved anywhere within the margin (many voxels then near the
    thresholds, decided exactly), and for blocks not decoded (rows -1); both truncation rules."""
    coords, q, basis, v = _case(step, trunc=trunc)
    n = len(coords)
    outside = coords[-3:] + [0, 0, 40]  # coded blocks of another chunk, next to none: no effect, still accepted
    want = pm.pinned_voxels_of(coords, *pm.sign_bounds(*pm.exact_decode(q, basis)), outside, trunc)
    assert want.any() and not want.all()
    rows = np.arange(n)
    clipped = np.clip(v, *trunc)
    assert np.array_equal(_bools(pinread.decode_pins(clipped, rows, q, basis, coords, outside, trunc)), want)
    w, e = pm.exact_decode(q, basis)
    peak, _ = pm.decode_bounds(q, basis)
    margin = pinread.float_margin(q, peak)[:, None]
    rng = np.random.default_rng(3)
    t = np.where(w > 0, e[:, None], -e[:, None])  # the threshold nearer each voxel
    anywhere = w + margin * rng.uniform(-0.9, 0.9, w.shape)
    on_threshold = np.where(np.abs(w - t) <= 0.9 * margin, t, w)
    assert (on_threshold != w).sum() > 10  # (13 to 396 here; test_sign_rows_... puts 256 on them)
    for moved in (anywhere, on_threshold):
        x = (moved / 2.0 ** 24).astype(np.float32)
        assert np.array_equal(_bools(pinread.decode_pins(x, rows, q, basis, coords, outside, trunc)), want)
    half = np.where(np.arange(n) % 2 == 0, rows, -1)  # every other block not decoded: its exact decode decides
    assert np.array_equal(_bools(pinread.decode_pins(v, half, q, basis, coords, outside, trunc)), want)


def test_sign_rows_decides_voxels_on_the_thresholds_exactly():
    """Voxels whose exact decode is E - 1, E, -E - 1, -E (where may-be-negative and may-be-non-negative flip),
    given a float decode far off but within the margin: the bits are the exact decode's."""
    from sdfcodec.core import pinkernels

    rng = np.random.default_rng(4)
    basis = np.zeros((3, 4096))
    basis[0] = rng.integers(-50, 50, 4096)
    basis[1] = rng.integers(-50, 50, 4096)
    basis[2] = rng.integers(-50, 50, 4096)
    q = np.array([[3.0, -2.0]])
    w = basis[0] + q[0] @ basis[1:]
    e = np.array([float(np.median(np.abs(w)))])
    for target in (e[0] - 1, e[0], -e[0] - 1, -e[0]):
        basis[0, :64] += target - w[:64]  # the first 64 voxels exactly on the threshold
        w = basis[0] + q[0] @ basis[1:]
        x = ((w + rng.choice([-3.0, 3.0], 4096)) / 2.0 ** 24).astype(np.float32)[None]
        neg, pos = (np.zeros((1, 16, 16), np.uint32) for _ in range(2))
        exact = pinkernels.sign_rows(x, np.zeros(1, np.int64), e, np.array([4.0]), q, np.ascontiguousarray(basis.T),
                                     neg, pos)
        assert exact >= 64
        bits = 1 << (np.arange(16) + 1)
        got_neg = (neg.reshape(256, 1) & bits) != 0
        got_pos = (pos.reshape(256, 1) & bits) != 0
        assert np.array_equal(got_neg.reshape(-1), w < e[0]) and np.array_equal(got_pos.reshape(-1), w >= -e[0])


def test_the_kernels_exact_decode_is_exact_near_its_limit():
    """Blocks not decoded (every voxel decided by the kernels' exact decode, summed in eight running sums, codes
    after the last non-zero one skipped) with terms near 2^47 and a bound term near 2^50 (exact_decode's limit is
    2^52): the signs are those of the sum in Python integers, voxels placed on +-E included."""
    from sdfcodec.core import pinkernels

    rng = np.random.default_rng(11)
    k = 13  # eight running sums and a tail of five
    basis = rng.integers(-2 ** 30, 2 ** 30, (k + 1, 4096)).astype(np.float64)
    q = rng.integers(-2 ** 17, 2 ** 17, (3, k)).astype(np.float64)
    q[1, 9:] = 0  # a shorter prefix
    q[2, 1::2] = 0  # zeros inside the prefix
    peak = np.abs(basis).max(axis=1)[0] + np.abs(q) @ np.abs(basis).max(axis=1)[1:]
    assert peak.max() < 2.0 ** 52 and peak.max() > 2.0 ** 49
    b_int = [[int(x) for x in row] for row in basis]
    w = [[b_int[0][j] + sum(int(q[b, i]) * b_int[i + 1][j] for i in range(k)) for j in range(4096)] for b in range(3)]
    e = np.array([float(abs(w[b][5])) for b in range(3)])  # voxel 5 of each block on a threshold
    neg, pos = (np.zeros((3, 16, 16), np.uint32) for _ in range(2))
    exact = pinkernels.sign_rows(np.zeros((1, 4096), np.float32), np.full(3, -1, np.int64), e, np.full(3, np.inf),
                                 q, np.ascontiguousarray(basis.T), neg, pos)
    assert exact == 3 * 4096
    bits = 1 << (np.arange(16) + 1)
    for b in range(3):
        want = np.array(w[b], dtype=object)
        got_neg = ((neg[b].reshape(256, 1) & bits) != 0).reshape(-1)
        got_pos = ((pos[b].reshape(256, 1) & bits) != 0).reshape(-1)
        assert np.array_equal(got_neg, want < int(e[b])) and np.array_equal(got_pos, want >= -int(e[b]))


def test_a_read_equals_the_exact_decodes_read(monkeypatch):
    """The golden pinned map read whole and by a region inside one chunk (its other blocks not decoded): the same
    values as the read that computes every voxel's exact decode (numba off)."""
    m = sdfcodec.open_map(GOLDEN)
    fast = m.decode_region()
    part = tuple(slice(8, 40) for _ in range(2)) + (slice(0, 20),)
    fast_part = sdfcodec.open_map(GOLDEN).decode_region(part)
    with monkeypatch.context() as mp:
        mp.setattr(ans, "available", lambda: False)
        slow = sdfcodec.open_map(GOLDEN).decode_region()
        slow_part = sdfcodec.open_map(GOLDEN).decode_region(part)
    assert np.array_equal(fast, slow) and np.array_equal(fast_part, slow_part)
    assert (fast == m.truncation[1]).any() and (fast < 0).any()


def test_the_compiled_pinned_rows_are_pinmasks():
    """pinkernels.pinned_rows (per block, a table of neighbours) gives pinmask.pinned_rows (whole-row numpy
    operations) bit for bit: random signs, dense and sparse, coded blocks of another chunk beside some, blocks
    that are not coded around others, both truncation rules."""
    from sdfcodec.core import pinkernels

    rng = np.random.default_rng(5)
    for trial in range(16):
        coords = np.unique(rng.integers(0, 4, (rng.integers(1, 20), 3)), axis=0)
        n = len(coords)
        outside = np.unique(rng.integers(3, 6, (rng.integers(1, 8), 3)), axis=0) if trial % 2 else np.zeros((0, 3))
        outside = outside[~(outside[:, None] == coords[None]).all(axis=2).any(axis=1)].astype(np.int64)
        bits = 1 << (np.arange(16, dtype=np.uint32) + 1)
        neg_b = rng.random((n, 16, 16, 16)) < rng.random() * 0.1
        pos_b = ~neg_b | (rng.random(neg_b.shape) < 0.02)
        neg, pos = ((b * bits).sum(axis=3).astype(np.uint32) for b in (neg_b, pos_b))
        for trunc, both in ((TRUNC, True), ((-0.02, 0.02), False)):
            want = pm.pinned_rows(coords, neg, pos, outside, trunc)
            got = pinkernels.pinned_rows(np.ascontiguousarray(coords, np.int64), neg, pos,
                                         np.ascontiguousarray(outside, np.int64).reshape(-1, 3), both)
            assert np.array_equal(got, want), (trial, trunc)
            assert want.any()


def test_the_wave_planes_order_is_the_grids():
    """ans.wave_order_planes (the pins' set bits, as (i, j) per wavefront, each with its block and voxel) gives
    ans.wave_order's positions and wavefront bounds (a scan of the grid) on random pins of scattered blocks, and
    the same array placed in runs of slabs (in turn, in reverse, or on threads)."""
    rng = np.random.default_rng(6)
    split = []  # the runs each placement in reverse was given
    for trial in range(8):
        coords = np.unique(rng.integers(0, 4, (rng.integers(1, 12), 3)), axis=0)
        pinned = rng.random((len(coords), 16, 16, 16)) < [0.0, 0.01, 0.2, 0.9][trial % 4]
        lo = coords.min(axis=0)
        shape = tuple(int(x) for x in (coords.max(axis=0) - lo + 1) * 16 + 2)
        corner = (coords - lo) * 16 + 1
        at, bounds = ans.wave_order(np.full(int(np.prod(shape)), 2, np.uint8), shape, corner, pinned)
        rows = np.packbits(pinned.reshape(len(coords), -1), axis=1, bitorder="little").view("<u2")
        order, waves, got_bounds = ans.wave_order_planes(shape, corner, rows.reshape(-1, 16, 16))
        i, j = (order >> 16) & 0xFFFF, order & 0xFFFF
        w = np.repeat(waves, np.diff(got_bounds))
        assert np.array_equal(got_bounds, bounds) and np.array_equal(np.ravel_multi_index((i, j, w - i - j), shape), at)
        grid = np.stack((i, j, w - i - j), axis=1)  # each position's block and voxel, from the blocks' corners
        b = np.flatnonzero(np.all((grid[:, None] >= corner) & (grid[:, None] < corner + 16), axis=2).reshape(-1))
        b = b % len(corner)
        voxel = np.ravel_multi_index(tuple((grid - corner[b]).T), (16, 16, 16)) if len(b) else b
        assert len(b) == len(order) and np.array_equal(order >> 32, b * 4096 + voxel)
        for parts in (2, 3, 5):
            def backwards(job, runs):
                split.append(len(runs))
                return [job(r) for r in runs[::-1]]

            def threaded(job, runs):
                return each_chunk(job, runs, threads=len(runs))

            for each in (None, backwards, threaded):
                again = ans.wave_order_planes(shape, corner, rows.reshape(-1, 16, 16), parts, each)
                assert all(np.array_equal(x, y) for x, y in zip(again, (order, waves, got_bounds))), (trial, parts)
    assert max(split) >= 3  # the blocks were placed in several runs


def test_the_plane_decoder_reads_the_grid_decoders_bits():
    """unobserved_voxels of pins as rows (the decoder of wavefront planes, no grid) finds exactly the voxels the
    grid decoder (decode_pinned, checked against constriction in test_pinned_fast) reads as 0, on random pins
    and bits; a stream for other pins is refused as decode_pinned refuses it."""
    rng = np.random.default_rng(7)
    for trial in range(8):
        coords = np.unique(rng.integers(0, 4, (rng.integers(1, 10), 3)), axis=0)
        pinned = rng.random((len(coords), 16, 16, 16)) < [0.01, 0.2, 0.6, 0.95][trial % 4]
        bits = rng.random(pinned.shape) < [0.5, 0.1, 0.9, 0.5][trial % 4]
        stream = pm.encode_pinned(coords, bits, pinned)
        rows = np.packbits(pinned.reshape(len(coords), -1), axis=1, bitorder="little").view("<u2").reshape(-1, 16, 16)
        want = np.flatnonzero(~pm.decode_pinned(stream, coords, pinned).reshape(-1))
        got = pm.unobserved_voxels(stream, coords, rows)
        assert np.array_equal(np.sort(got), want)
        assert np.array_equal(pm.unobserved_voxels(stream, coords, rows, threads=3), got)  # and in the same order
        assert np.array_equal(want, np.flatnonzero((pinned & ~bits).reshape(-1)))
    fewer = rows.copy()
    fewer[0, 0, 0] ^= 1
    with pytest.raises(sdfcodec.errors.ChecksumError, match="pinned voxels"):
        pm.unobserved_voxels(stream, coords, fewer)


def test_a_pinned_maps_decode_runs_in_full_float32_whatever_the_users_precision(monkeypatch):
    """The pins are proven against a true float32 decode (spec 6g): a user's
    ``torch.set_float32_matmul_precision("medium")`` (TF32/bfloat16 products on hardware that has them) must not
    reach the decode of a pinned map, and is the user's again afterwards."""
    from sdfcodec.map import groupdecode

    seen = []
    inner = groupdecode._decode_group

    def spy(*a, **kw):
        seen.append(torch.get_float32_matmul_precision())
        return inner(*a, **kw)

    monkeypatch.setattr(groupdecode, "_decode_group", spy)
    was = torch.get_float32_matmul_precision()
    torch.set_float32_matmul_precision("medium")
    try:
        whole = sdfcodec.open_map(GOLDEN).decode_region()
        assert seen and set(seen) == {"highest"}
        assert torch.get_float32_matmul_precision() == "medium"
    finally:
        torch.set_float32_matmul_precision(was)
    np.testing.assert_array_equal(whole, sdfcodec.open_map(GOLDEN).decode_region())


REFINED = Path(__file__).parent / "golden" / "maps" / "refined-pca-8" / "map.zarr"
S = 2.0 ** pm.FRACTION_BITS


def _refined_reference(w, e, trunc, tau, step, c_of):
    """A numpy reference of spec 6h from the exact decode ``w`` and bound ``e``: (selected voxels, corrections,
    the refined field ``r`` and its bound ``E + 1``), the corrections ``c_of(m)`` for the ``m`` selected."""
    from sdfcodec.core import refine as cr

    clipped = np.clip(w, trunc[0] * S, trunc[1] * S)
    sel = np.abs(clipped) < tau
    c = c_of(int(sel.sum()))
    r = clipped.copy()
    r[sel] += c * float(step)
    return sel, c, cr.clip_units(r, trunc, S), e + 1.0


@pytest.mark.parametrize("step,trunc,tau_m,r_m", [(0.05, TRUNC, 0.01, 0.002), (0.6, TRUNC, 0.04, 0.004),
                                                  (0.05, (-0.02, 0.02), 0.03, 0.001)])
def test_refined_pins_told_from_a_float_decode_are_the_exact_ones(step, trunc, tau_m, r_m):
    """decode_refined_pins (spec 6h) gives the pins of the refined exact field (a numpy reference), asks the
    stream for the exact selection, and leaves the reader's refined decode in the field: from the codec's
    clipped decode, from one moved anywhere within the margin, from one put on the selection's thresholds
    ``+-tau`` wherever the margin allows, and for blocks not decoded; a band wider than
    ``d_min`` (0.04 m) and ``d_max``, and one of 1 cm."""
    coords, q, basis, v = _case(step, trunc=trunc)
    n = len(coords)
    outside = coords[-3:] + [0, 0, 40]
    tau, rstep = int(round(tau_m * S)), int(round(r_m * S))
    w, e = pm.exact_decode(q, basis, size=q.shape[1])
    rng = np.random.default_rng(7)
    sel, c, r, e1 = _refined_reference(w, e, trunc, tau, rstep, lambda m: rng.integers(-9, 10, m))
    want = pm.pinned_voxels_of(coords, *pm.sign_bounds(r, e1), outside, trunc)
    assert sel.any() and want.any() and not want.all()
    assert sel.all() == (tau_m > max(-trunc[0], trunc[1]))  # a band past both bounds selects every voxel
    step32 = np.float32(rstep / S)

    def read(x, rows):
        asked = []

        def corrections(s):
            asked.append(s.copy())
            return c

        field = x.copy()
        pins = pinread.decode_refined_pins(field, rows, q, basis, coords, outside, trunc, tau, rstep, corrections)
        assert np.array_equal(asked[0], sel)
        return _bools(pins), field

    clipped = np.clip(v, *trunc)
    rows = np.arange(n)
    got, field = read(clipped, rows)
    assert np.array_equal(got, want)
    add = np.zeros_like(clipped)
    add[sel] = c.astype(np.float32) * step32  # the reader's row of corrections, float32 sum, truncated again
    assert np.array_equal(field, np.clip(clipped + add, *trunc))
    peak, _ = pm.decode_bounds(q, basis)
    margin = pinread.float_margin(q, peak)[:, None]
    cw = np.clip(w, trunc[0] * S, trunc[1] * S)
    anywhere = cw + margin * rng.uniform(-0.9, 0.9, w.shape)
    near = np.abs(np.abs(cw) - tau) <= 0.9 * margin
    on_tau = np.where(near, np.sign(cw) * tau, cw)
    assert near.any() or sel.all()
    for moved in (anywhere, on_tau):
        x = np.clip((moved / S).astype(np.float32), *trunc)
        assert np.array_equal(read(x, rows)[0], want)
    half = np.where(np.arange(n) % 2 == 0, rows, -1)
    got, field = read(clipped, half)
    assert np.array_equal(got, want)
    assert np.array_equal(field[::2], np.clip(clipped + add, *trunc)[::2]) and np.array_equal(field[1::2],
                                                                                             clipped[1::2])


def test_refined_kernels_decide_voxels_on_the_thresholds_exactly():
    """select_rows and refined_sign_rows given a float decode 3 units off (within the margin 4) where the clipped
    exact decode sits on ``tau - 1``, ``tau``, ``-tau``, ``-tau + 1`` (selection) or the refined field on ``E - 1``,
    ``E``, ``-E - 1``, ``-E`` (pins): every answer is the exact one, those voxels decided exactly."""
    from sdfcodec.core import pinkernels

    rng = np.random.default_rng(8)
    q = np.array([[3.0, -2.0]])
    lo, hi = -1e6, 1e6
    rstep = 7
    for target in ("tau - 1", "tau", "-tau", "-tau + 1", "E - 1", "E", "-E - 1", "-E"):
        basis = rng.integers(-50, 50, (3, 4096)).astype(np.float64)
        w = basis[0] + q[0] @ basis[1:]
        tau = float(np.median(np.abs(w)))
        sel = np.abs(w) < tau
        c = rng.integers(-3, 4, 4096)  # a correction for every voxel; the selected ones use theirs
        e = float(np.median(np.abs(w + c * rstep * sel)))
        goal = {"tau - 1": tau - 1, "tau": tau, "-tau": -tau, "-tau + 1": -tau + 1}.get(target)
        if goal is not None:
            basis[0, :64] += goal - w[:64]
        else:
            goal = {"E - 1": e - 1, "E": e, "-E - 1": -e - 1, "-E": -e}[target]
            sel[:64] = np.abs(w[:64]) < tau
            basis[0, :64] += goal - w[:64] - c[:64] * rstep * sel[:64]
        w = basis[0] + q[0] @ basis[1:]
        sel_want = np.abs(w) < tau
        r = np.where(sel_want, w + c * rstep, w)
        noise = rng.choice([-3.0, 3.0], 4096)
        x = ((w + noise) / S).astype(np.float32)[None]
        basis_t = np.ascontiguousarray(basis.T)
        got = np.zeros((1, 4096), bool)
        exact = pinkernels.select_rows(x, np.zeros(1, np.int64), tau, np.array([4.0]), q, basis_t, lo, hi, got)
        assert np.array_equal(got[0], sel_want)
        if target.startswith(("tau", "-tau")):
            assert exact >= 64
        neg, pos = (np.zeros((1, 16, 16), np.uint32) for _ in range(2))
        field = x.copy()
        exact = pinkernels.refined_sign_rows(field, np.zeros(1, np.int64), sel_want[None], c[sel_want].astype(np.int32),
                                             float(rstep), lo, hi, np.array([e]), np.array([4.0 + 1]), q, basis_t,
                                             neg, pos)
        if target.startswith(("E", "-E")):
            assert exact >= 64
        bits = 1 << (np.arange(16) + 1)
        assert np.array_equal(((neg.reshape(256, 1) & bits) != 0).reshape(-1), r < e)
        assert np.array_equal(((pos.reshape(256, 1) & bits) != 0).reshape(-1), r >= -e)
        assert np.array_equal(field[0], ((w + noise + c * rstep * sel_want) / S).astype(np.float32))
    # a float decode clipped at d_min with tau just beyond it: clip(w) is d_min too, selected without an exact
    # decode (the margin's interval ends at the truncation)
    lo = -0.04 * S
    basis[0] = lo - 1000 - q[0] @ basis[1:]
    x = np.full((1, 4096), np.float32(-0.04))
    exact = pinkernels.select_rows(x, np.zeros(1, np.int64), -lo + 1, np.array([4.0]), q, basis_t, lo, hi, got)
    assert got.all() and exact == 0


def test_a_refined_read_equals_the_exact_decodes_read(monkeypatch):
    """The golden refined map read whole, by a region inside one chunk, at a lower level and as mask rows: the
    same values as the read that decodes every voxel exactly (numba off: every selection and pin from the
    refined exact field); and the corrections are in the field (it differs from the plain decode)."""
    def reads():
        m = sdfcodec.open_map(REFINED)
        coords, _ = m.reader.read_codes()
        part = tuple(slice(8, 40) for _ in range(2)) + (slice(0, 20),)
        return (m.decode_region(), sdfcodec.open_map(REFINED).decode_region(part),
                sdfcodec.open_map(REFINED).decode_region(level=4), sdfcodec.open_map(REFINED).read_observed(coords))

    fast = reads()
    with monkeypatch.context() as mp:
        mp.setattr(ans, "available", lambda: False)
        slow = reads()
    for a, b in zip(fast, slow):
        assert np.array_equal(a, b)
    m = sdfcodec.open_map(REFINED)
    assert (fast[0] == m.truncation[1]).any() and (fast[0] < 0).any() and not fast[3].all()
    assert np.abs(fast[0] - fast[2]).max() > 1e-3


def test_a_chunk_of_short_prefixes_reads_back(tmp_path, monkeypatch):
    """A pinned map whose every block's prefix is shorter than the codes (step 3: the last 17 of 64 columns are
    zero in every block) reads, with numba and without, to the same values: writer and readers take the bound
    ``E`` of spec 6g with the codes' length ``D`` (the writer took the prefix's, and the compiled reader refused
    the chunk, its pin count differing)."""
    from _fused_maps import write_volume_map

    vol, obs = fused_like(sample_volume(analytic_scene(), (64, 64, 48), VS, truncation=TRUNC))
    path = tmp_path / "short.sdfz"
    write_volume_map(path, vol, obs, pretrained_codec("pca", 64), variable_rate={"step": 3.0})
    m = sdfcodec.open_map(path)
    (_, q), = m.reader.vr.chunk_codes(np.zeros((1, 3), np.int64), m.header.codes.size)
    assert not q[:, -8:].any() and q.any()
    fast = m.decode_region()
    with monkeypatch.context() as mp:
        mp.setattr(ans, "available", lambda: False)
        slow = sdfcodec.open_map(path).decode_region()
    assert np.array_equal(fast, slow) and (fast == TRUNC[1]).any() and (fast < 0).any()


def _float32_around(limits) -> np.ndarray:
    """The float32 decodes (metres) nearest each limit (units of 2^-24 m) and three float32 steps either side."""
    near = []
    with np.errstate(over="ignore"):  # limits past float32's range: +-inf
        for t in limits:
            g = np.float32(t / S)
            for _ in range(3):
                g = np.nextafter(g, np.float32(-np.inf))
            for _ in range(7):
                near.append(g)
                g = np.nextafter(g, np.float32(np.inf))
    return np.array(near, np.float32)


def _float64_rule(x: np.ndarray, w: np.ndarray, e: float, d: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The sign flags of a float decode ``x`` (float32 metres) by the rule in float64 (``float64(x) 2^24``
    against ``e - d``, ``e + d``, ``d - e``, ``-e - d``; a voxel the margin leaves open, NaN included, by its exact
    value ``w``): may be negative, may be non-negative, open."""
    y = x.astype(np.float64) * S
    sure = ((y < e - d) | (y >= e + d)) & ((y >= d - e) | (y < -e - d))
    return np.where(sure, y < e - d, w < e), np.where(sure, y >= d - e, w >= -e), ~sure


def test_float32_thresholds_tell_the_signs_the_float64_rule_tells():
    """sign_rows and refined_sign_rows compare float32 decodes with float32 thresholds: on a float decode at, and
    up to three float32 steps either side of, every limit (none of them a float32: margins with fractions, bounds
    past float32's range, an infinite margin), at +-0, subnormals, +-inf, NaN and at random, the flags and the
    count decided exactly are the float64 rule's; the refined decode is the float32 sum, -0 read as +0, NaN kept."""
    from sdfcodec.core import pinkernels

    rng = np.random.default_rng(21)
    f32 = np.finfo(np.float32)
    special = np.array([0.0, -0.0, 1e-45, -1e-45, f32.tiny, np.inf, -np.inf, np.nan, f32.max, -f32.max], np.float32)
    cases = [(7531.0, 2272.0039014816284), (2138.0, 283.00031757354736), (5.0, 0.0), (2.0 ** 40 + 1, 3.25),
             (1e50, 1.5), (100.0, np.inf), (0.0, 0.5), (3.0, 2.0 ** -30)]
    n = len(cases)
    v = np.empty((n, 4096), np.float32)
    w = np.empty((n, 4096))
    with np.errstate(over="ignore"):  # float32 decodes of bounds past its range: +-inf
        for b, (e, d) in enumerate(cases):
            near = _float32_around((e - d, e + d, d - e, -e - d))
            fill = rng.normal(size=4096) * (e + (d if np.isfinite(d) else 0.0)) * 2 / S
            v[b] = np.where(rng.random(4096) < 0.05, np.nan, fill).astype(np.float32)
            picked = rng.choice(4096, len(near) + len(special) + 40, replace=False)
            v[b, picked] = np.concatenate([near, special, rng.choice(special, 40)])
            w[b] = rng.choice([e - 1, e, -e - 1, -e, 3 * e, -3 * e], 4096)
    q = np.zeros((n, 1))  # no codes: each voxel's exact decode is the basis's first row, w
    e, d = np.array(cases).T
    rows = np.arange(n)
    bits = 1 << (np.arange(16) + 1)
    opened = 0
    for b in range(n):
        basis_t = np.ascontiguousarray(w[b][:, None])  # one block at a time: a basis of its own
        one_neg, one_pos = (np.zeros((1, 16, 16), np.uint32) for _ in range(2))
        exact = pinkernels.sign_rows(v, rows[b:b + 1], e[b:b + 1], d[b:b + 1], q[b:b + 1], basis_t, one_neg, one_pos)
        want_neg, want_pos, open_ = _float64_rule(v[b], w[b], e[b], d[b])
        assert exact == open_.sum() > 0
        assert np.array_equal(((one_neg.reshape(256, 1) & bits) != 0).reshape(-1), want_neg)
        assert np.array_equal(((one_pos.reshape(256, 1) & bits) != 0).reshape(-1), want_pos)
        opened += exact
        # refined: a tenth selected, corrections of a few steps; truncation at +-1000 m (beyond: clipped)
        sel = rng.random(4096) < 0.1
        c = rng.integers(-3, 4, int(sel.sum())).astype(np.int32)
        step, lo, hi = 7.0, -1000.0 * S, 1000.0 * S
        add = np.zeros(4096, np.float32)
        add[sel] = c.astype(np.float32) * np.float32(step / S)
        field = v[b:b + 1].copy()
        exact = pinkernels.refined_sign_rows(field, np.zeros(1, np.int64), sel[None], c, step, lo, hi, e[b:b + 1],
                                             d[b:b + 1], q[b:b + 1], basis_t, one_neg, one_pos)
        want_field = np.clip(v[b] + add, np.float32(lo / S), np.float32(hi / S))  # NaN stays NaN
        assert np.array_equal(field[0], want_field, equal_nan=True)
        assert not np.signbit(field[0][field[0] == 0]).any()
        cw = np.zeros(4096)
        cw[sel] = c
        r = np.clip(w[b], lo, hi)
        r = np.where(cw != 0, np.clip(r + cw * step, lo, hi), r)
        want_neg, want_pos, open_ = _float64_rule(want_field, r, e[b], d[b])
        assert exact == open_.sum()
        assert np.array_equal(((one_neg.reshape(256, 1) & bits) != 0).reshape(-1), want_neg)
        assert np.array_equal(((one_pos.reshape(256, 1) & bits) != 0).reshape(-1), want_pos)
    assert opened > 4096  # (the infinite margin opens every finite voxel of its block)


def test_select_rows_in_float32_select_what_the_float64_rule_selects():
    """select_rows compares float32 decodes with float32 thresholds: on decodes at and around each of its four
    limits (``x -+ margin`` against ``-+tau``, rounded in float64), +-0, +-inf, NaN and at random, with tau inside
    and beyond the truncation and an infinite margin, the selection and the count decided exactly are those of
    the rule in float64 (``[max(x - d, lo), min(x + d, hi)]`` against ``+-tau``; open voxels, NaN included, by
    their clipped exact value)."""
    from sdfcodec.core import pinkernels

    rng = np.random.default_rng(22)
    special = np.array([0.0, -0.0, 1e-45, np.inf, -np.inf, np.nan], np.float32)
    lo, hi = -0.04 * S, 0.1 * S
    opened = 0
    for tau, db in ((40000.0, 2272.0039014816284), (1e6 + 0.5, 283.00031757354736), (7.0, 0.0),
                    (-lo + 3, 17.25), (40000.0, np.inf)):
        near = _float32_around((db - tau, tau + db, tau - db, -tau - db))
        x = (rng.normal(size=4096) * 3 * tau / S).astype(np.float32)
        x[rng.random(4096) < 0.05] = np.nan
        x[rng.choice(4096, len(near) + len(special), replace=False)] = np.concatenate([near, special])
        w = rng.choice([tau - 1, tau, -tau, -tau + 1, 3 * tau, lo - 5], 4096)
        got = np.zeros((1, 4096), bool)
        exact = pinkernels.select_rows(x[None], np.zeros(1, np.int64), tau, np.array([db]), np.zeros((1, 1)),
                                       np.ascontiguousarray(w[:, None]), lo, hi, got)
        y = x.astype(np.float64) * S
        with np.errstate(invalid="ignore"):  # inf - inf: NaN, and kept, as numba's max and min keep it
            a, z = np.maximum(y - db, lo), np.minimum(y + db, hi)
        yes = (-tau < a) & (z < tau)
        open_ = ~(yes | (a >= tau) | (z <= -tau))
        assert exact == open_.sum()
        assert np.array_equal(got[0], np.where(open_, np.abs(np.clip(w, lo, hi)) < tau, yes))
        opened += exact
    assert opened > 4096
