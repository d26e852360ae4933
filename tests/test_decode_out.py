"""Decoding into place (issue 19, item 1): ``Codec.decode(codes, out=)`` for every shipped codec, the reader's
ring of output buffers (``iter_decoded(copy=False)``) and ``decode_region`` writing blocks straight into the
volume, checked against decodes placed by hand, with its peak memory bounded by the output plus a few groups."""

from __future__ import annotations

import collections
import tracemalloc

import numpy as np
import pytest
import torch

import sdfcodec
from sdfcodec import errors
from sdfcodec.codec import decodes_into
from sdfcodec.map.grouping import chunk_groups
from sdfcodec.testing import analytic_blocks

TRUNC = (-0.04, 0.1)
SHIPPED = ("pca", "ae", "parallel", "sequential", "raw", "gaussian-blur", "sz3")


def _codec(cid: str) -> sdfcodec.Codec:
    if cid in ("pca", "ae", "parallel", "sequential"):
        return sdfcodec.pretrained_codec(cid)
    if cid == "sz3":
        pytest.importorskip("pysz")
    return sdfcodec.get_codec(cid)


@pytest.fixture(scope="module")
def blocks() -> np.ndarray:
    return analytic_blocks(24)


@pytest.mark.parametrize("cid", SHIPPED)
def test_out_equals_plain_decode_for_every_shipped_codec(cid, blocks):
    codec = _codec(cid)
    codes = codec.encode(blocks)
    plain = codec.decode(codes)
    for shape in ((len(codes), 16, 16, 16), (len(codes), 4096)):
        buf = np.full(shape, np.nan, np.float32)
        assert codec.decode(codes, out=buf) is buf
        np.testing.assert_array_equal(buf.reshape(plain.shape), plain)
    metres = codec.decode_core(codes, scale=0.14, offset=-0.04)
    tbuf = torch.full((len(codes), 16, 16, 16), float("nan"))
    got = codec.decode_core(torch.from_numpy(codes), scale=0.14, offset=-0.04, out=tbuf)
    assert got is tbuf
    np.testing.assert_allclose(tbuf.numpy(), metres, rtol=0, atol=1e-6)
    # pca and the codecs whose code is the voxels write in place; the others use the decode-then-copy fallback
    assert decodes_into(codec) == (cid in ("pca", "raw", "gaussian-blur", "sz3"))


def test_out_at_pca_prefix_levels_matches_an_independent_product(blocks):
    codec = sdfcodec.pretrained_codec("pca", 64)
    state = codec.state_dict()
    comp, mean = state["components"].astype(np.float64), state["mean"].astype(np.float64)
    codes = codec.encode(blocks)
    for level in (1, 7, 32, 64):
        buf = np.empty((len(codes), 4096), np.float32)
        codec.decode_core(codes[:, :level], scale=0.14, offset=-0.04, out=buf)
        # the prefix decode is the mean plus the first `level` eigenshapes, in metres (float64 reference)
        ref = (codes[:, :level].astype(np.float64) @ comp[:level] + mean) * 0.14 - 0.04
        np.testing.assert_allclose(buf, ref, rtol=0, atol=2e-5)
        np.testing.assert_array_equal(buf.reshape(-1, 16, 16, 16), codec.decode_core(codes[:, :level], scale=0.14,
                                                                                      offset=-0.04))


@pytest.mark.parametrize("bad, exc, words", [
    (np.empty((5, 16, 16, 16), np.float32), errors.ShapeError, "shape"),
    (np.empty((4, 4096), np.float64), errors.DTypeError, "float32"),
    (torch.empty((4, 4096)), errors.DTypeError, "numpy array"),
    (np.empty((4, 8192), np.float32)[:, ::2], errors.InvalidValueError, "C-contiguous"),
])
def test_bad_out_is_refused_with_a_clear_error(bad, exc, words, blocks):
    codec = sdfcodec.pretrained_codec("pca", 16)
    codes = codec.encode(blocks[:4])
    with pytest.raises(exc, match=words):
        codec.decode(codes, out=bad)
    ro = np.empty((4, 4096), np.float32)
    ro.flags.writeable = False
    with pytest.raises(errors.InvalidValueError, match="read-only"):
        codec.decode(codes, out=ro)
    with pytest.raises(errors.InvalidValueError, match="device"):
        codec.decode(torch.from_numpy(codes), out=torch.empty((4, 4096), device="meta"))


class _Doubling(sdfcodec.Codec):
    """A third-party codec without decode_into: the base class must decode and copy."""

    codec_id = "test-doubling"
    code_size = 4096

    def _encode(self, blocks):
        return blocks.reshape(len(blocks), 4096) / 2

    def _decode(self, codes):
        return (codes * 2).reshape(len(codes), 16, 16, 16)


def test_a_plugin_without_decode_into_gets_the_fallback(blocks):
    codec = _Doubling()
    assert not decodes_into(codec)
    buf = np.empty((len(blocks), 16, 16, 16), np.float32)
    assert codec.decode_core(codec.encode(blocks), scale=2.0, offset=1.0, out=buf) is buf
    np.testing.assert_allclose(buf, blocks * 2.0 + 1.0, rtol=1e-6)


# -- maps --------------------------------------------------------------------------------------------------
def _field(shape, rng) -> np.ndarray:
    """A TSDF-like field in metres with surfaces in most blocks (a sum of random waves, distinct values in every
    block) and every fifth block free space (empty), ``shape`` voxels (multiples of 16)."""
    x, y, z = np.ogrid[tuple(slice(0, n) for n in shape)]
    p = rng.uniform(0, 6, 6)
    d = 0.03 * (np.sin(x / 7 + p[0]) * np.cos(y / 9 + p[1]) + np.sin(y / 8 + p[2]) * np.cos(z / 6 + p[3])
                + np.sin(z / 5 + p[4]) * np.cos(x / 11 + p[5]))
    d = np.clip(d, *TRUNC).astype(np.float32)
    free = rng.uniform(size=tuple(n // 16 for n in shape)) < 0.2
    d[np.kron(free, np.ones((16, 16, 16))).astype(bool)] = TRUNC[1]
    return d


@pytest.fixture(scope="module")
def small_map(tmp_path_factory):
    """A pca-16 map of 10 x 8 x 6 blocks in chunks of 4^3 blocks: coded, empty and unobserved blocks."""
    rng = np.random.default_rng(19)
    vol = _field((160, 128, 96), rng)
    path = tmp_path_factory.mktemp("out") / "small.sdfz"
    codec = sdfcodec.pretrained_codec("pca", 16)
    blocks = vol.reshape(10, 16, 8, 16, 6, 16).transpose(0, 2, 4, 1, 3, 5)
    coords = np.argwhere(rng.uniform(size=(10, 8, 6)) < 0.8)  # the rest stays unobserved
    with sdfcodec.create_map(path, codec=codec, voxel_size=0.02, truncation=TRUNC, chunk_blocks=4,
                             shape_voxels=(160, 128, 96)) as m:
        m.write_blocks(coords, blocks[tuple(coords.T)])
    return path


def _by_hand(m, lo, hi) -> np.ndarray:
    """The region decoded block by block: every coded block's codes decoded alone (one call each), clamped to
    the truncation and copied into a d_max volume in a Python loop, then cropped."""
    d_min, d_max = m.truncation
    codec = m.codec
    b0, b1 = np.array(lo) // 16, -(-np.array(hi) // 16)
    vol = np.full(tuple((b1 - b0) * 16), d_max, np.float32)
    coords, codes = m.read_codes()
    for c, code in zip(coords, codes):
        if np.all(c >= b0) and np.all(c < b1):
            block = codec.decode_core(code[None], scale=d_max - d_min, offset=d_min)[0]
            s = (c - b0) * 16
            vol[s[0]:s[0] + 16, s[1]:s[1] + 16, s[2]:s[2] + 16] = np.clip(block, d_min, d_max)
    o = np.array(lo) - b0 * 16
    return vol[o[0]:o[0] + hi[0] - lo[0], o[1]:o[1] + hi[1] - lo[1], o[2]:o[2] + hi[2] - lo[2]]


@pytest.mark.parametrize("lo, hi", [((0, 0, 0), (160, 128, 96)), ((5, 17, 30), (150, 100, 91)),
                                    ((64, 64, 64), (65, 130 - 2, 70)), ((3, 3, 3), (13, 12, 11))])
def test_decode_region_places_blocks_as_by_hand(small_map, lo, hi):
    with sdfcodec.open_map(small_map) as m:
        got = m.decode_region(tuple(zip(lo, hi)), batch_blocks=100)  # several groups, crossing chunks
        assert got.shape == tuple(h - l for l, h in zip(lo, hi)) and got.flags.c_contiguous
        np.testing.assert_allclose(got, _by_hand(m, lo, hi), rtol=0, atol=1e-6)
        counts = m.count_states()  # the map holds blocks of every state, the fill of uncoded blocks is covered
        assert counts["coded"] > 250 and counts["empty"] > 30 and counts["unobserved"] > 30


@pytest.mark.parametrize("lo, hi", [((0, 0, 0), (160, 128, 96)), ((5, 17, 30), (150, 100, 91))])
def test_decode_region_into_a_reused_volume_writes_every_voxel(small_map, lo, hi):
    region = tuple(zip(lo, hi))
    with sdfcodec.open_map(small_map) as m:
        buf = np.full(tuple(h - l for l, h in zip(lo, hi)), np.nan, np.float32)  # stale contents: NaN
        for _ in range(2):  # the second call overwrites the first's result
            got = m.decode_region(region, batch_blocks=100, out=buf)
            assert got is buf and not np.isnan(buf).any()
            np.testing.assert_allclose(buf, _by_hand(m, lo, hi), rtol=0, atol=1e-6)
            buf[::7] = -5.0


def test_decode_region_into_of_a_halo_codec_equals_its_fresh_decode(tmp_path):
    rng = np.random.default_rng(5)
    vol = _field((64, 48, 32), rng)
    path = tmp_path / "blur.sdfz"
    codec = sdfcodec.get_codec("gaussian-blur")
    blocks = vol.reshape(4, 16, 3, 16, 2, 16).transpose(0, 2, 4, 1, 3, 5)
    coords = np.argwhere(np.ones((4, 3, 2), bool))
    with sdfcodec.create_map(path, codec=codec, voxel_size=0.02, truncation=TRUNC, chunk_blocks=2) as m:
        m.write_blocks(coords, blocks[tuple(coords.T)])
    region = ((3, 60), (10, 48), (0, 31))
    with sdfcodec.open_map(path) as m:
        assert m.codec.halo > 0
        buf = np.full((57, 38, 31), np.nan, np.float32)
        assert m.decode_region(region, out=buf) is buf
        np.testing.assert_array_equal(buf, m.decode_region(region))


@pytest.mark.parametrize("bad, exc, words", [
    (np.empty((16, 16, 17), np.float32), errors.ShapeError, r"\(16, 16, 16\)"),
    (np.empty((16, 16, 16), np.float64), errors.DTypeError, "float32"),
    (torch.empty((16, 16, 16)), errors.DTypeError, "numpy array"),
    (np.empty((16, 16, 32), np.float32)[:, :, ::2], errors.InvalidValueError, "C-contiguous"),
])
def test_decode_region_refuses_a_bad_out(small_map, bad, exc, words):
    with sdfcodec.open_map(small_map) as m:
        with pytest.raises(exc, match=words):
            m.decode_region(((0, 16), (0, 16), (0, 16)), out=bad)
        with pytest.raises(errors.DTypeError, match="torch tensor"):
            m.decode_region(((0, 16), (0, 16), (0, 16)), device="cpu", out=np.empty((16, 16, 16), np.float32))


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_decode_region_into_a_cuda_volume_equals_the_cpu_decode(small_map):
    region = ((5, 150), (17, 100), (30, 91))
    with sdfcodec.open_map(small_map) as m:
        buf = torch.full((145, 83, 61), float("nan"), device="cuda")
        assert m.decode_region(region, device="cuda", out=buf) is buf  # "cuda" takes a tensor on cuda:0
        np.testing.assert_allclose(buf.cpu().numpy(), m.decode_region(region), rtol=0, atol=1e-5)


def test_region_groups_are_whole_columns_of_chunks(small_map):
    """decode_region's groups (columns=True) close where a column of chunks along z ends, unless they reach twice
    the batch first, and cover every chunk holding coded blocks once, in grid order."""
    with sdfcodec.open_map(small_map) as m:
        r = m.reader
        box = tuple(slice(0, n) for n in r.grid())
        states = r.states_in(box)
        def groups_of(**kw):
            return chunk_groups(r.header.codes, box, states, 16, max_decode_bytes=r.max_decode_bytes, **kw)

        chunks = np.concatenate(groups_of(batch_blocks=1))  # one chunk a group
        coded = np.argwhere(states == 2)  # BlockState.CODED
        per_column = collections.Counter(tuple(c) for c in coded[:, :2] // 4)
        assert len(per_column) == 6 and len(chunks) == 12  # the small map: 3 x 2 x 2 chunks, all holding blocks
        for batch in (max(per_column.values()), min(per_column.values()), 40):
            groups = groups_of(batch_blocks=batch, columns=True)
            assert np.array_equal(np.concatenate(groups), chunks)
            for g in groups:
                held = sum(per_column[tuple(c[:2])] for c in {tuple(c[:2]) for c in g})
                cols = {tuple(c[:2]) for c in g}
                whole = all((chunks[:, :2] == c).all(axis=1).sum() == (g[:, :2] == c).all(axis=1).sum() for c in cols)
                # whole columns, or a column cut because the group reached twice the batch
                assert whole or held >= 2 * batch, (batch, g.tolist())
        # a batch of one block: every chunk holds more than two, so each is a group of its own
        assert all(len(g) == 1 for g in groups_of(batch_blocks=1, columns=True))


def test_iter_decoded_ring_matches_fresh_decodes_and_wraps(small_map):
    with sdfcodec.open_map(small_map) as m:
        fresh = list(m.iter_decoded(batch_blocks=64))
        assert len(fresh) >= 4
        seen = []
        for i, (coords, blocks) in enumerate(m.iter_decoded(batch_blocks=64, copy=False)):
            np.testing.assert_array_equal(coords, fresh[i][0])
            np.testing.assert_array_equal(blocks, fresh[i][1])  # equal to the fresh decode when yielded
            if i >= 1:  # the previous batch is still intact while this one is used (ring of two)
                np.testing.assert_array_equal(seen[-1][1], fresh[i - 1][1])
            seen.append((coords, blocks))
        # each buffer came back two turns later; fresh arrays never share memory
        assert np.shares_memory(seen[0][1], seen[2][1]) and not np.shares_memory(seen[0][1], seen[1][1])
        assert not any(np.shares_memory(a[1], b[1]) for a, b in zip(fresh, fresh[1:]))
        with pytest.raises(errors.InvalidValueError, match="copy"):
            next(m.iter_decoded(copy="no"))


def test_decode_region_peak_memory_is_output_plus_a_few_groups(tmp_path):
    """A map of 3072 coded blocks decoded whole and over an unaligned region in groups of about 256 blocks:
    tracemalloc's peak (numpy allocations: the output, decode buffers, codes) stays below the output plus four
    groups' decodes; the old path's block-aligned volume and cropping copy needed twice the output."""
    rng = np.random.default_rng(7)
    small = _field((160, 128, 96), rng).reshape(10, 16, 8, 16, 6, 16).transpose(0, 2, 4, 1, 3, 5).reshape(-1, 16, 16, 16)
    surface = small[(small < TRUNC[1]).any(axis=(1, 2, 3))]  # blocks that are not free space (coded)
    coords = np.argwhere(np.ones((16, 16, 12), bool))
    path = tmp_path / "big.sdfz"
    with sdfcodec.create_map(path, codec=sdfcodec.pretrained_codec("pca", 8), voxel_size=0.02,
                             truncation=TRUNC, chunk_blocks=4) as m:
        m.write_blocks(coords, surface[np.arange(len(coords)) % len(surface)])
    group = 256 * 16 ** 3 * 4
    with sdfcodec.open_map(path) as m:
        assert m.count_states()["coded"] > 2000
        for region in (None, ((3, 250), (1, 255), (7, 190))):
            m.decode_region(((0, 16), (0, 16), (0, 16)), batch_blocks=256)  # codec loaded before measuring
            tracemalloc.start()
            try:
                out = m.decode_region(region, batch_blocks=256)
                peak = tracemalloc.get_traced_memory()[1]
            finally:
                tracemalloc.stop()
            assert out.nbytes <= peak < out.nbytes + 4 * group, (region, peak / 2**20, out.nbytes / 2**20)
            del out
