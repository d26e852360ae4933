"""Decoding in cache-sized tiles (issue 19; ``sdfcodec.core.tiling``, the ``decode_tiles`` hook, the reader's fused
decode + truncation + placement): tiles cover every row once on several threads, BLAS gets its threads back,
and the decodes placed tile by tile equal an independent decode (codes times the basis, then ``np.clip``) placed
by hand and the analytic volume the map was written from, with tiles small enough to split runs of blocks."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest
import torch
from threadpoolctl import ThreadpoolController

import sdfcodec
from sdfcodec.core import tiling
from sdfcodec.codec import decodes_tiles

TRUNC = (-0.04, 0.1)


def _blas_threads() -> int:
    """Threads of numpy's own BLAS (what run_tiles holds at one): scipy, once another test has imported it,
    brings an OpenBLAS of its own, which may come first in threadpoolctl's list."""
    libs = ThreadpoolController().select(user_api="blas").lib_controllers
    return ([lib for lib in libs if "numpy" in lib.filepath] or libs)[0].num_threads


def test_run_tiles_covers_every_row_once_across_threads():
    seen = np.zeros(1000, np.int64)
    names, sizes = set(), []
    before = _blas_threads()
    with ThreadpoolController().limit(limits=2, user_api="blas"):  # two shares, whatever the machine has

        def work(a, b):
            seen[a:b] += 1
            sizes.append(b - a)
            names.add(threading.current_thread().name)
            assert _blas_threads() == 1  # each thread runs one BLAS thread of its own
            time.sleep(0.002)  # the GIL let go, as numpy's kernels do: the other thread gets tiles too

        tiling.run_tiles(1000, work, rows=7)
    assert (seen == 1).all() and max(sizes) <= 7 and len(names) == 2
    assert _blas_threads() == before


def test_a_batch_shorter_than_two_tiles_still_reaches_every_core(monkeypatch):
    monkeypatch.setattr(tiling, "TILE_ROWS", 512)
    for n, want in ((300, [150, 150]), (100, [64, 36]), (40, [40])):  # one tile per core, none under 64 rows
        sizes, names = [], set()
        with ThreadpoolController().limit(limits=2, user_api="blas"):

            def work(a, b):
                sizes.append(b - a)
                names.add(threading.current_thread().name)
                time.sleep(0.01)  # the GIL let go: the second thread takes the second tile

            tiling.run_tiles(n, work)
        assert sorted(sizes, reverse=True) == want and len(names) == len(want)


def test_run_tiles_raises_a_workers_error_after_all_stopped():
    done = []

    def work(a, b):
        if a >= 500:
            raise ValueError(f"tile {a}")
        done.append(a)

    with ThreadpoolController().limit(limits=2, user_api="blas"):
        with pytest.raises(ValueError, match="tile 5"):
            tiling.run_tiles(1000, work, rows=50)
        assert _blas_threads() == 2  # restored on the error path too
    assert sorted(done) == list(range(0, 500, 50))


def test_pca_tiles_equal_an_independent_product_and_clip(monkeypatch):
    codec = sdfcodec.pretrained_codec("pca", 32)
    assert decodes_tiles(codec) and not decodes_tiles(sdfcodec.get_codec("raw"))
    state = codec.state_dict()
    comp, mean = state["components"].astype(np.float64), state["mean"].astype(np.float64)
    codes = np.random.default_rng(3).normal(0, 2, (301, 32)).astype(np.float32)
    scale, offset = 0.14, -0.04
    want = np.clip((codes.astype(np.float64) @ comp + mean) * scale + offset, -0.03, 0.05).reshape(-1, 16, 16, 16)
    monkeypatch.setattr(tiling, "TILE_ROWS", 13)  # many tiles, a short last one per share
    for level in (32, 9):  # a prefix too: the basis rows the tiles use follow the code length
        ref = np.clip((codes[:, :level].astype(np.float64) @ comp[:level] + mean) * scale + offset, -0.03, 0.05)
        out = torch.full((301, 16, 16, 16), float("nan"))
        got = np.full((301, 16, 16, 16), np.nan, np.float32)
        codec.decode_tiles(torch.from_numpy(codes[:, :level].copy()), scale, offset, (-0.03, 0.05),
                           lambda a, b, t: got.__setitem__(slice(a, b), t.numpy()), out)
        np.testing.assert_allclose(out.numpy().reshape(301, -1), ref, rtol=0, atol=2e-6)
        np.testing.assert_array_equal(got, out.numpy())
    assert np.abs(want - np.clip(want, -0.03, 0.05)).max() == 0 and (want == 0.05).mean() > 0.1  # the clip bites


@pytest.fixture(scope="module")
def sphere_map(tmp_path_factory):
    """A pca-64 map of a sphere's TSDF (analytic), 6 x 5 x 7 blocks in chunks of 4^3 blocks, all observed
    (blocks of free space only are stored as empty)."""
    shape = (96, 80, 112)
    g = np.stack(np.meshgrid(*[np.arange(n) + 0.5 for n in shape], indexing="ij"), -1) * 0.02
    sdf = np.linalg.norm(g - np.array([0.9, 0.85, 1.1]), axis=-1) - 0.6
    vol = np.clip(sdf, *TRUNC).astype(np.float32)
    path = tmp_path_factory.mktemp("tiles") / "sphere.sdfz"
    blocks = vol.reshape(6, 16, 5, 16, 7, 16).transpose(0, 2, 4, 1, 3, 5)
    coords = np.argwhere(np.ones((6, 5, 7), bool))
    with sdfcodec.create_map(path, codec=sdfcodec.pretrained_codec("pca", 64), voxel_size=0.02, truncation=TRUNC,
                             chunk_blocks=4, shape_voxels=shape) as m:
        m.write_blocks(coords, blocks[tuple(coords.T)])
    return path, vol


def _independent(m) -> np.ndarray:
    """Every coded block decoded as codes @ basis + mean in float64, scaled to metres, clipped, placed by a loop."""
    d_min, d_max = m.truncation
    state = m.codec.state_dict()
    comp, mean = state["components"].astype(np.float64), state["mean"].astype(np.float64)
    vol = np.full(tuple(np.array(m.reader.grid_blocks) * 16), d_max, np.float32)
    coords, codes = m.read_codes()
    dec = np.clip((codes.astype(np.float64) @ comp[: codes.shape[1]] + mean) * (d_max - d_min) + d_min, d_min, d_max)
    for c, block in zip(coords, dec.reshape(-1, 16, 16, 16)):
        vol[c[0] * 16:c[0] * 16 + 16, c[1] * 16:c[1] * 16 + 16, c[2] * 16:c[2] * 16 + 16] = block
    return vol


@pytest.mark.parametrize("rows", [3, 128])
@pytest.mark.parametrize("lo, hi", [((0, 0, 0), (96, 80, 112)), ((5, 17, 30), (90, 79, 101))])
def test_decode_region_from_tiles_equals_an_independent_decode(sphere_map, monkeypatch, rows, lo, hi):
    path, vol = sphere_map
    monkeypatch.setattr(tiling, "TILE_ROWS", rows)  # 3: tiles split the runs of blocks placed in one copy
    with sdfcodec.open_map(path) as m:
        got = m.decode_region(tuple(zip(lo, hi)), batch_blocks=50)
        sl = tuple(slice(a, b) for a, b in zip(lo, hi))
        np.testing.assert_allclose(got, _independent(m)[sl], rtol=0, atol=2e-6)
        # and it is the sphere: pca-64 of a TSDF is within a few mm of it
        err = np.abs(got - vol[sl])
        assert err.max() < 0.05 and err.mean() < 2e-3, (err.max(), err.mean())


def test_iter_decoded_ring_from_tiles_equals_an_independent_decode(sphere_map, monkeypatch):
    path, _ = sphere_map
    monkeypatch.setattr(tiling, "TILE_ROWS", 5)
    with sdfcodec.open_map(path) as m:
        ref = _independent(m)
        n = 0
        for copy in (False, True):
            for coords, blocks in m.iter_decoded(batch_blocks=40, copy=copy):
                want = np.stack([ref[x * 16:x * 16 + 16, y * 16:y * 16 + 16, z * 16:z * 16 + 16] for x, y, z in coords])
                np.testing.assert_allclose(blocks, want, rtol=0, atol=2e-6)
                n += len(coords)
        assert n == 2 * m.count_states()["coded"] and n > 150


def test_the_ring_is_kept_for_the_next_iteration_and_not_shared_by_two_at_once(sphere_map):
    path, _ = sphere_map
    with sdfcodec.open_map(path) as m:
        first = [b for _, b in m.iter_decoded(batch_blocks=40, copy=False)]
        again = m.iter_decoded(batch_blocks=40, copy=False)
        _, b0 = next(again)
        assert np.shares_memory(b0, first[0])  # the same buffers, already in memory
        other = [b for _, b in m.iter_decoded(batch_blocks=40, copy=False)]  # while `again` holds the ring
        assert not any(np.shares_memory(b, o) for b in (b0, *first) for o in other)
        np.testing.assert_array_equal(b0, other[0])  # and both decoded the same first group
        again.close()


def _fake_cache(root, entries) -> str:
    """A sysfs cache folder (``/sys/devices/system/cpu/cpu0/cache``) holding ``(level, type, size)`` entries."""
    for i, (level, kind, size) in enumerate(entries):
        d = root / f"index{i}"
        d.mkdir(parents=True)
        (d / "level").write_text(f"{level}\n")
        (d / "type").write_text(f"{kind}\n")
        (d / "size").write_text(f"{size}\n")
    return str(root)


@pytest.mark.parametrize("l2, size, rows", [("512K", 512 << 10, 128), ("2048K", 2 << 20, 512), ("1M", 1 << 20, 256),
                                            ("32K", 32 << 10, 64), ("64M", 64 << 20, 1024)])
def test_tile_rows_follow_the_l2_read_from_sysfs(tmp_path, l2, size, rows):
    # the L1 data and instruction caches and the L3 listed around it, as Linux lists them
    sysfs = _fake_cache(tmp_path / "cache", [(1, "Data", "32K"), (1, "Instruction", "32K"), (2, "Unified", l2),
                                             (3, "Unified", "32768K")])
    assert tiling.l2_bytes(sysfs) == size
    # four L2s of 16 KiB blocks, a power of two within [64, 1024]
    assert tiling.tile_rows_for(size) == rows
    assert tiling.l2_bytes(str(tmp_path / "none")) is None and tiling.tile_rows_for(None) == 512
    assert tiling.l2_bytes(_fake_cache(tmp_path / "l1only", [(1, "Data", "48K")])) is None
