"""A variable-rate read on every core (sdfcodec.map.grouping.each_chunk): the chunks of a group decoded on several
threads, one chunk's pins split among them, the compiled kernels releasing the GIL. The values read are the same,
byte for byte, as one thread's and as the read that decodes every voxel exactly (numba off)."""

from __future__ import annotations

import threading

import numpy as np
import pytest

import sdfcodec
from _fused_maps import TRUNC, VS, fused_like, write_volume_map
from sdfcodec.core import ans
from sdfcodec.core.sdf import sample_volume
from sdfcodec.map import grouping, pinread
from sdfcodec.map.varread import VariableRateReader
from sdfcodec.registry import pretrained_codec
from sdfcodec.testing import analytic_scene

pytestmark = pytest.mark.skipif(not ans.available(), reason="numba is not installed: nothing runs on threads")


@pytest.fixture(scope="module")
def maps(tmp_path_factory):
    """A fused room (4 x 4 x 3 blocks) as a pinned-mask map and a refined one, in chunks of 2 blocks (8 chunks)
    and of 16 (one chunk)."""
    vol, obs = fused_like(sample_volume(analytic_scene(), (64, 64, 48), VS, truncation=TRUNC))
    out = {}
    for name, vr in (("pinned", {"step": 0.6}), ("refined", {"step": 0.6, "refine_step": 0.004})):
        for cb in (2, 16):
            path = tmp_path_factory.mktemp("par") / f"{name}-{cb}.sdfz"
            write_volume_map(path, vol, obs, pretrained_codec("pca", 64), codec_state="reference",
                             variable_rate=vr, chunk_blocks=cb)
            out[name, cb] = path
    return out


def _read(path, region=None):
    """The decoded blocks sorted by coords, and the mask rows, as bytes."""
    with sdfcodec.open_map(path) as m:
        got = list(m.iter_decoded(region))
        c = np.concatenate([g[0] for g in got])
        b = np.concatenate([g[1] for g in got])
        order = np.lexsort(c.T[::-1])
        return c[order].tobytes() + b[order].tobytes() + np.asarray(m.read_observed(c[order])).tobytes()


@pytest.mark.parametrize("name", ["pinned", "refined"])
@pytest.mark.parametrize("cb", [2, 16])
def test_a_read_on_several_threads_is_one_threads_and_the_exact_reads(maps, name, cb, monkeypatch):
    """The map read on 1, 2 and 3 threads (one chunk's pins split in shares of 8 blocks), and with numba off
    (every voxel's exact decode, no thread): the same bytes; the map holds pinned and selected voxels."""
    path = maps[name, cb]
    m = sdfcodec.open_map(path)
    assert "pinned-observation-mask" in {e.name for e in m.header.extensions}
    assert (m.header.codes.variable_rate.refinement is not None) == (name == "refined")
    monkeypatch.setattr(pinread, "MIN_SHARE", 8)
    reads = {}
    for threads in (1, 2, 3):
        monkeypatch.setattr(grouping, "READ_THREADS", threads)
        reads[threads] = _read(path)
    with monkeypatch.context() as mp:
        mp.setattr(ans, "available", lambda: False)
        exact = _read(path)
    assert reads[1] == reads[2] == reads[3] == exact
    blocks = np.frombuffer(exact, np.float32, offset=m.count_states()["coded"] * 3 * 8)
    assert (blocks[:m.count_states()["coded"] * 4096] == TRUNC[1]).any()  # unobserved voxels set to free space


def test_a_region_read_on_threads_decodes_only_its_chunks(maps, monkeypatch):
    """A region of 2 x 2 x 2 blocks of the 8-chunk map: one chunk's stream decoded, on two threads as on one, and
    the same values read."""
    path = maps["refined", 2]
    seen = []
    real = VariableRateReader._decode

    def spy(self, key, row, level):
        seen.append(tuple(int(k) for k in key))
        return real(self, key, row, level)

    monkeypatch.setattr(VariableRateReader, "_decode", spy)
    region = (slice(32, 64), slice(0, 32), slice(0, 32))
    parts = []
    for threads in (2, 1):
        monkeypatch.setattr(grouping, "READ_THREADS", threads)
        with sdfcodec.open_map(path) as m:
            parts.append(m.decode_region(region))
        assert seen == [(1, 0, 0)]
        seen.clear()
    assert np.array_equal(*parts) and (parts[0] < 0).any()


def test_thread_shares_follow_the_work():
    """Each job's share of the threads in proportion to its size, at least one: a chunk of nearly all the coded
    blocks gets every core, chunks of like sizes one each."""
    assert grouping.thread_shares([494, 13], 2) == [2, 1]
    assert grouping.thread_shares([100, 100], 2) == [1, 1]
    assert grouping.thread_shares([300, 100, 0], 4) == [3, 1, 1]
    assert grouping.thread_shares([5], 8) == [8]
    assert grouping.thread_shares([7, 3], 1) == [1, 1]
    assert grouping.thread_shares([0, 0], 4) == [1, 1]


def test_each_chunk_runs_items_at_once_in_order_and_raises_the_first_error():
    """Two items meet at a barrier (they run at the same time: one thread would wait forever), the results come
    in the items' order, one thread runs them inline, and a failing item's error reaches the caller."""
    barrier = threading.Barrier(2, timeout=10)

    def meet(i):
        barrier.wait()
        return i * i

    assert grouping.each_chunk(meet, [3, 4], threads=2) == [9, 16]
    names = grouping.each_chunk(lambda i: threading.current_thread().name, range(5), threads=1)
    assert set(names) == {threading.current_thread().name}

    def fail(i):
        if i == 2:
            raise ValueError("chunk 2")
        return i

    with pytest.raises(ValueError, match="chunk 2"):
        grouping.each_chunk(fail, range(6), threads=3)


def test_a_chunk_cache_filled_from_threads_keeps_the_last_entries():
    """Four threads put 200 keys each: the cache holds its size, each key its own value."""
    cache = grouping.ChunkCache(8)
    grouping.each_chunk(lambda t: [cache.put((t, i), (t, i)) for i in range(200)], range(4), threads=4)
    assert len(cache) == 8
    assert all(cache[k] == k for k in list(cache._items))  # noqa: SLF001 - the entries themselves
    assert cache.get(("none", 0)) is None


def test_the_read_kernels_release_the_gil():
    """Every compiled kernel a variable-rate read calls on its threads is built with nogil."""
    from sdfcodec.core import anskernels, pinkernels

    for mod, names in ((pinkernels, ("sign_rows", "select_rows", "refined_sign_rows", "set_voxels", "pinned_rows")),
                       (anskernels, ("chunk_decode", "categorical_decode", "decode_planes", "wave_sizes",
                                     "wave_place"))):
        for name in names:
            assert getattr(mod, name).targetoptions.get("nogil") is True, name


@pytest.mark.parametrize("case", ["plain", "trailing first symbols", "only first symbols", "random words"])
def test_corrections_decoded_ahead_are_a_decode_of_any_length(case):
    """Symbols decoded before their number is known (corrections_ahead), cut to any length n: the symbols and the
    verdict (empty or not) of constriction's own decode of n symbols, for a stream of corrections, one ending in a
    run of the law's first symbol (the coder is empty before its end), one holding nothing else (no word at all), and
    random words no coder wrote (zeros among them)."""
    import constriction

    from sdfcodec.core import refine as cr

    rng = np.random.default_rng(3)
    model = cr.CorrectionModel(np.array([5, 1, 30, 200, 40, 2, 9]))  # M = 3
    c = rng.integers(-3, 4, 300)
    if case == "trailing first symbols":
        c[-40:] = -3
    elif case == "only first symbols":
        c[:] = -3
    words = cr.encode_corrections(c, model)
    if case == "random words":
        words = rng.integers(0, 2 ** 32, 40, dtype=np.uint64).astype(np.uint32)
        words[::7] = 0
        words[-1] = 5
    cap = 600
    ahead = cr.corrections_ahead(words, cap, model)
    for n in range(1, cap + 1):
        coder = constriction.stream.stack.AnsCoder(words.astype(np.uint32)) if len(words) else \
            constriction.stream.stack.AnsCoder()
        want = np.asarray(coder.decode(model.model(), n), np.int32) - model.m
        got, empty = ans.symbols_ahead(ahead, n)
        assert np.array_equal(got - model.m, want) and empty == coder.is_empty(), n
        if case != "random words" and n == len(c):
            assert empty and np.array_equal(got - model.m, c)
            assert np.array_equal(cr.decode_corrections(words, n, model, ahead), c)
    if case == "plain":  # (a run of first symbols at the end leaves the coder empty before it)
        with pytest.raises(sdfcodec.errors.FormatError, match="holds more than"):
            cr.decode_corrections(words, len(c) - 1, model, ahead)


def test_read_threads_follow_the_cpus_and_numbas_share(monkeypatch):
    """READ_THREADS when set; else the CPUs this process may use, at most 8 and at most NUMBA_NUM_THREADS."""
    import os

    monkeypatch.setattr(grouping, "READ_THREADS", None)
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: set(range(12)), raising=False)
    monkeypatch.delenv("NUMBA_NUM_THREADS", raising=False)
    assert grouping.read_threads() == 8
    monkeypatch.setenv("NUMBA_NUM_THREADS", "3")
    assert grouping.read_threads() == 3
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0, 1}, raising=False)
    assert grouping.read_threads() == 2
    monkeypatch.setattr(grouping, "READ_THREADS", 5)
    assert grouping.read_threads() == 5


def test_a_codec_state_loads_with_one_blas_thread(maps, monkeypatch):
    """A map's codec loads its state with numpy's BLAS at one thread (its products then leave no OpenBLAS thread
    spinning through the read on the cores the read decodes on), and the BLAS threads are back after it."""
    from sdfcodec.core import tiling

    blas = tiling._blas()  # noqa: SLF001 - numpy's BLAS controller, as the reader holds it
    if blas is None:
        pytest.skip("threadpoolctl finds no BLAS of numpy's")
    before = blas.num_threads
    blas.set_num_threads(2)  # (a test worker runs one thread; the point is a BLAS of several)
    if blas.num_threads != 2:
        blas.set_num_threads(before)
        pytest.skip("numpy's BLAS runs one thread here: nothing to hold")
    seen = []
    codec_cls = type(pretrained_codec("pca", 64))
    real = codec_cls.load_state_dict

    def spy(self, state):
        seen.append(blas.num_threads)
        return real(self, state)

    monkeypatch.setattr(codec_cls, "load_state_dict", spy)
    try:
        with sdfcodec.open_map(maps["pinned", 16]) as m:
            m.codec
        after = blas.num_threads
    finally:
        blas.set_num_threads(before)
    assert seen == [1] and after == 2
