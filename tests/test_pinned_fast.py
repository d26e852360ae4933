"""The pinned mask's fast read (sdfcodec.map.pinmask with sdfcodec.core.ans): the compiled M2 decoder and encoder
write and read constriction's words, on random and real pinned masks and the golden map; the shortcuts of the
exact decode and of the layout give what the plain definitions give."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import zarr

import sdfcodec
from _fused_maps import TRUNC, VS, fused_like
from sdfcodec.core import ans
from sdfcodec.core.blocks import split_blocks
from sdfcodec.core.sdf import sample_volume
from sdfcodec.map import pinmask as pm
from sdfcodec.map.pinstore import PINNED_ARRAY, chunk_blocks
from sdfcodec.registry import pretrained_codec
from sdfcodec.testing import analytic_scene

constriction = pytest.importorskip("constriction")
pytestmark = pytest.mark.skipif(not ans.available(), reason="numba is not installed: no compiled path to compare")
GOLDEN = Path(__file__).parent / "golden" / "maps" / "pinned-mask-pca-8" / "map.zarr"


def _reference_stream(coords, bits, pinned) -> bytes:
    """M2 as spec section 6g words it, written here with constriction: the chunk's blocks in one grid padded by
    one voxel, pinned voxels ordered by wavefront x + y + z then C order, ternary contexts of NEIGHBOURS (first
    most significant; 2 = not pinned), Krichevsky-Trofimov counts added after each wavefront."""
    coords = np.asarray(coords, np.int64)
    lo = coords.min(axis=0)
    shape = tuple((coords.max(axis=0) - lo + 1) * 16 + 2)
    grid = np.full(shape, 2, np.int64)
    for c, b, p in zip(coords, bits, pinned):
        x, y, z = (c - lo) * 16 + 1
        view = grid[x:x + 16, y:y + 16, z:z + 16]
        view[p] = b[p]
    pts = np.argwhere(grid != 2)
    wave = pts.sum(axis=1)
    pts = pts[np.lexsort((np.ravel_multi_index(pts.T, shape), wave))]
    wave = pts.sum(axis=1)
    sym = grid[tuple(pts.T)]
    ctx = np.zeros(len(pts), np.int64)
    for d in pm.NEIGHBOURS:
        ctx = ctx * 3 + grid[tuple((pts + d).T)]
    counts, p1 = np.zeros((2, 729)), np.empty(len(pts))
    for w in np.unique(wave):
        sel = wave == w
        c = counts[:, ctx[sel]] + 0.5
        p1[sel] = c[1] / (c[0] + c[1])
        np.add.at(counts, (sym[sel], ctx[sel]), 1)
    coder = constriction.stream.stack.AnsCoder()
    coder.encode_reverse(sym.astype(np.int32), constriction.stream.model.Bernoulli(perfect=False), p1)
    words = np.asarray(coder.get_compressed(), "<u4")
    return b"M2" + np.uint32(len(pts)).astype("<u4").tobytes() + words.tobytes()


def _both_paths(monkeypatch, coords, bits, pinned) -> bytes:
    """The stream of both paths (asserted equal), each decoded by both paths to the stored bits."""
    stream = pm.encode_pinned(coords, bits, pinned)
    with monkeypatch.context() as m:
        m.setattr(ans, "available", lambda: False)
        assert pm.encode_pinned(coords, bits, pinned) == stream
        slow = pm.decode_pinned(stream, coords, pinned)
    fast = pm.decode_pinned(stream, coords, pinned)
    assert np.array_equal(fast, slow)
    assert np.array_equal(fast[pinned], np.asarray(bits, bool)[pinned]) and fast[~pinned].all()
    return stream


def _real_case(step: float):
    """A fused room under pca-64 at ``step``: (coords, canonical bits, pins), as the writer makes them."""
    vol, obs = fused_like(sample_volume(analytic_scene(), (64, 64, 48), VS, truncation=TRUNC))
    blocks = split_blocks(vol, fill=TRUNC[1]).reshape(-1, 16, 16, 16)
    truth = split_blocks(obs, fill=False).reshape(-1, 16, 16, 16)
    coords = np.argwhere(np.ones(split_blocks(vol, fill=TRUNC[1]).shape[:3], bool))
    keep = ~(blocks >= TRUNC[1] - 1e-6).reshape(len(blocks), -1).all(axis=1)
    coords, blocks, truth = coords[keep], blocks[keep], truth[keep]
    codec = pretrained_codec("pca", 64)
    z = np.asarray(codec.encode(((blocks - TRUNC[0]) / (TRUNC[1] - TRUNC[0])).astype(np.float32)))
    q = np.rint(z / step)
    sd = codec.state_dict()
    basis = pm.fixed_point_basis(sd["components"], sd["mean"], np.full(64, step), TRUNC)
    neg, pos = pm.sign_bounds(*pm.exact_decode(q, basis))
    pins, _, _ = pm.exact_pins(coords, neg, pos, np.zeros((0, 3)), TRUNC)
    return coords, pm.canonical_bits(coords, truth, neg, pos, TRUNC), pins, q, basis


def test_random_pinned_masks_give_constrictions_stream_on_both_paths(monkeypatch):
    rng = np.random.default_rng(11)
    layouts = [np.array([[0, 0, 0]]), np.array([[0, 0, 0], [0, 0, 1], [3, 1, 2]]),
               np.array([[2, 2, 2], [2, 3, 2], [3, 2, 2], [3, 3, 3], [5, 0, 1]])]
    for coords in layouts:
        for density, ones in ((0.0, 0.5), (0.02, 0.5), (0.3, 0.2), (1.0, 0.9)):
            pinned = rng.random((len(coords), 16, 16, 16)) < density
            bits = rng.random(pinned.shape) < ones
            stream = _both_paths(monkeypatch, coords, bits, pinned)
            assert stream == _reference_stream(coords, bits, pinned), (len(coords), density)


@pytest.mark.parametrize("step", [0.05, 0.6])
def test_real_pinned_masks_give_constrictions_stream_on_both_paths(monkeypatch, step):
    coords, bits, pins, _, _ = _real_case(step)
    assert pins.sum() > 10000 and 0 < bits[pins].mean() < 1
    assert _both_paths(monkeypatch, coords, bits, pins) == _reference_stream(coords, bits, pins)


def test_the_free_bits_are_chosen_alike_on_both_paths(monkeypatch):
    """The writer's choice of the free bits (pinmask.cheapest_bits: each set to the value its context has seen more
    often, counted over the wavefronts before) compiled and in numpy: the same bits, on random chunks and on a
    real one, and the choice shortens the stream it feeds."""
    rng = np.random.default_rng(16)
    coords_r, bits_r, pins_r, _, _ = _real_case(0.6)
    cases = [(coords_r, bits_r, pins_r, ~bits_r & (rng.random(bits_r.shape) < 0.7))]
    for coords in (np.array([[0, 0, 0]]), np.array([[0, 0, 0], [0, 0, 1], [3, 1, 2]])):
        for density in (0.02, 0.3, 1.0):
            pinned = rng.random((len(coords), 16, 16, 16)) < density
            bits = rng.random(pinned.shape) < 0.3
            cases.append((coords, bits, pinned, pinned & (rng.random(pinned.shape) < 0.5)))
    for coords, bits, pinned, free in cases:
        fast = pm.cheapest_bits(coords, bits, free, pinned)
        with monkeypatch.context() as m:
            m.setattr(ans, "available", lambda: False)
            slow = pm.cheapest_bits(coords, bits, free, pinned)
        assert np.array_equal(fast, slow), (len(coords), int(pinned.sum()))
        kept = pinned & ~free  # the other pinned bits stay (unpinned ones are not stored: read 0 here)
        assert np.array_equal(fast[kept], np.asarray(bits, bool)[kept])
    coords, bits, pinned, free = cases[0]
    chosen = pm.cheapest_bits(coords, bits, free, pinned)
    assert not np.array_equal(chosen, bits)
    assert len(pm.encode_pinned(coords, chosen, pinned)) < len(pm.encode_pinned(coords, bits, pinned))


def test_the_golden_maps_streams_read_alike_and_are_rewritten_byte_for_byte(monkeypatch):
    """The frozen map's M2 streams (written before the compiled path existed): both paths read the same mask,
    and encoding it again on either path gives the stored bytes."""
    m = sdfcodec.open_map(GOLDEN)
    r, arr = m.reader, m.reader.mask_array
    states = r.vr.states()
    stored = zarr.open_group(str(GOLDEN), mode="r")[PINNED_ARRAY]
    coords = np.argwhere(states == 2)
    with monkeypatch.context() as mp:
        mp.setattr(ans, "available", lambda: False)
        slow = type(arr)(r).block_rows(coords)
    assert np.array_equal(type(arr)(r).block_rows(coords), slow)
    step = np.broadcast_to(np.asarray(r.header.codes.variable_rate.step, np.float64), (r.header.codes.size,))
    seen = 0
    for key in np.unique(coords // arr.cb, axis=0):
        own, outside = chunk_blocks(states, key, arr.cb)
        row = np.asarray(stored[tuple(int(k) for k in key)])
        stream = row[4:4 + int(row[:4].view("<u4")[0])].tobytes()
        q = np.rint(r.vr.codes_for(own, r.header.codes.size).astype(np.float64) / step)
        pins, _, _ = pm.exact_pins(own, *pm.sign_bounds(*pm.exact_decode(q, arr.basis())), outside, r.truncation)
        bits = pm.decode_pinned(stream, own, pins)
        assert _both_paths(monkeypatch, own, bits, pins) == stream
        seen += int(pins.sum())
    assert seen > 1000


def test_the_exact_decode_cut_to_prefixes_is_the_full_product():
    """Blocks of every prefix length (zeros after it, zeros inside it), of small codes (bound T below 2^24: the
    float32 product) and large ones (float64): the exact decode equals the plain float64 product of all columns
    bit for bit."""
    rng = np.random.default_rng(12)
    sd = pretrained_codec("pca", 64).state_dict()
    basis = pm.fixed_point_basis(sd["components"], sd["mean"], np.full(64, 0.1), TRUNC)
    q = rng.integers(-1000, 1001, (260, 64)).astype(np.float64)
    q[130:] = rng.integers(-1, 2, (130, 64))  # small codes
    q[rng.random(q.shape) < 0.3] = 0
    for half in (0, 130):
        q[half + np.arange(65) * 2, :] *= np.arange(64) < np.arange(65)[:, None]  # prefix lengths 0..64
    v, e = pm.exact_decode(q, basis)
    full = q @ basis[1:] + basis[0]
    peak = np.abs(basis[0]).max() + np.abs(q) @ np.abs(basis[1:]).max(axis=1)
    small = peak < 2 ** 24
    assert 50 < small.sum() < 200 and np.abs(full[~small]).max() > 2 ** 24  # both products, sums past float32's
    assert np.array_equal(v, full)
    assert not np.array_equal(q.astype(np.float32) @ basis[1:].astype(np.float32) + basis[0].astype(np.float32),
                              full)  # float32 alone would not do for the large codes
    peak = np.abs(basis[0]).max() + np.abs(q) @ np.abs(basis[1:]).max(axis=1)
    assert np.array_equal(e, 1 + np.abs(q).sum(axis=1) + np.ceil(peak * 68 / 2 ** 20))


def test_pinned_voxels_on_rows_are_exact_pins():
    """pinned_voxels_of (rows of bits) gives exact_pins' pinned voxels (per voxel, padded arrays) bit for bit:
    random signs, dense and sparse, with coded blocks of another chunk beside some, both truncation rules; and a
    fused room's."""
    rng = np.random.default_rng(14)
    for trial in range(24):
        coords = np.unique(rng.integers(0, 4, (rng.integers(1, 20), 3)), axis=0)
        n = len(coords)
        outside = np.unique(rng.integers(4, 6, (rng.integers(1, 6), 3)), axis=0) if trial % 2 else np.zeros((0, 3))
        neg = rng.random((n, 16, 16, 16)) < rng.random() * 0.05
        pos = ~neg | (rng.random(neg.shape) < 0.01)
        if trial % 3 == 0:  # few voxels may be non-negative: the d_max padding decides more cells
            pos = rng.random(neg.shape) < rng.random() * 0.05
            neg |= ~pos
        for trunc in (TRUNC, (-0.02, 0.02)):  # d_max at or above the jump, and below it (neg alone decides)
            want = pm.exact_pins(coords, neg, pos, outside, trunc)[0]
            assert np.array_equal(pm.pinned_voxels_of(coords, neg, pos, outside, trunc), want), (trial, trunc)
    coords, _, pins, q, basis = _real_case(0.05)
    got = pm.pinned_voxels_of(coords, *pm.sign_bounds(*pm.exact_decode(q, basis)), np.zeros((0, 3)), TRUNC)
    assert np.array_equal(got, pins) and pins.any() and not pins.all()


def test_chunk_blocks_are_the_coded_blocks_and_their_coded_neighbours_elsewhere():
    """chunk_blocks (neighbours found by marking) against the definition, block by block: the chunk's coded
    blocks in C order, and every coded block of another chunk among their 26 neighbours, once, in C order."""
    rng = np.random.default_rng(15)
    for trial in range(6):
        states = np.where(rng.random((9, 7, 10)) < 0.4, 2, rng.integers(0, 2, (9, 7, 10)))
        for key in np.argwhere(np.ones((3, 2, 3), bool)):
            own, outside = chunk_blocks(states, key, 4)
            lo = key * 4
            want_own = [c for c in np.argwhere(states == 2) if ((c >= lo) & (c < lo + 4)).all()]
            near = {tuple(c + d) for c in want_own for d in np.argwhere(np.ones((3, 3, 3), bool)) - 1}
            want_out = sorted(c for c in near if all(0 <= x < s for x, s in zip(c, states.shape))
                              and states[c] == 2 and not ((np.array(c) >= lo) & (np.array(c) < lo + 4)).all())
            assert np.array_equal(own.reshape(-1, 3), np.array(want_own, np.int64).reshape(-1, 3))
            assert [tuple(int(x) for x in c) for c in outside] == want_out, (trial, key)
