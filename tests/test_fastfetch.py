"""Local chunk reads without Zarr's event loop (sdfcodec.map.io.fastfetch): what they read equals plain Zarr's
reading of the same arrays, their checks refuse what Zarr refuses (a chunk failing its CRC32C, a frame that
decompresses to too few bytes), sharded maps read the same, and maps they do not serve (zip) keep Zarr's path."""

from __future__ import annotations

from pathlib import Path

import google_crc32c
import numcodecs.blosc
import numpy as np
import pytest
import zarr

import sdfcodec
from sdfcodec import errors
from sdfcodec.map.io.fastfetch import local_chunks
from sdfcodec.registry import pretrained_codec

VS = 0.02
GRID = (21, 18, 19)  # not a multiple of the 8-block chunks: edge chunks are partly outside the grid


@pytest.fixture(scope="module")
def codec():
    return pretrained_codec("pca", 64)


def _write(path: Path, codec, *, seed: int = 0, **kw) -> np.ndarray:
    """A map of random codes on 60 % of the blocks of GRID (the shipped eigenshapes' spread); returns its coords."""
    rng = np.random.default_rng(seed)
    every = np.argwhere(np.ones(GRID, bool))
    coords = every[rng.random(len(every)) < 0.6]
    spread = np.sqrt(codec.explained_variance_).astype(np.float32)[:64]
    with sdfcodec.create_map(path, codec=codec, voxel_size=VS, chunk_blocks=8, overwrite=True, **kw) as w:
        w.write_codes(coords, rng.standard_normal((len(coords), 64), dtype=np.float32) * spread)
    return coords


@pytest.fixture(scope="module")
def local_map(tmp_path_factory, codec) -> Path:
    path = tmp_path_factory.mktemp("fastfetch") / "m.sdfz"
    _write(path, codec)
    return path


def _zarr_codes(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(coords, codes) of the coded blocks as plain Zarr reads them: the peer the fast path must equal."""
    g = zarr.open_group(str(path), mode="r")
    coords = np.argwhere(g["state"][...] == 2)
    return coords, g["codes"][...][tuple(coords.T)]


def test_fast_path_serves_a_local_map_and_reads_what_zarr_reads(local_map):
    m = sdfcodec.open_map(local_map)
    assert local_chunks(m.reader.group.store, m.reader.codes_array) is not None
    want_c, want = _zarr_codes(local_map)
    for level in (64, 20, 40):  # whole code chunks, part of the first, part of the second
        got = [(c, k) for c, k in m.iter_codes(level=level, chunks_per_batch=3)]
        c = np.concatenate([g[0] for g in got])
        k = np.concatenate([g[1] for g in got])
        order = np.lexsort(c.T[::-1])
        assert np.array_equal(c[order], want_c)
        assert np.array_equal(k[order], want[:, :level])
    c, k = m.read_codes(level=64)
    assert np.array_equal(c, want_c) and np.array_equal(k, want)


def test_region_decode_reads_the_same_through_both_paths(local_map, tmp_path):
    """A region not aligned with the chunks: the selections cut chunks, decoded the same as through a zip
    (Zarr's path) of the same map."""
    import shutil

    zipped = Path(shutil.make_archive(str(tmp_path / "m"), "zip", local_map))
    a, b = sdfcodec.open_map(local_map), sdfcodec.open_map(zipped)
    assert local_chunks(b.reader.group.store, b.reader.codes_array) is None
    region = ((37, 230), (5, 201), (100, 290))
    np.testing.assert_array_equal(a.decode_region(region), b.decode_region(region))


def _first_chunk(path: Path) -> Path:
    return next(f for f in sorted((path / "codes" / "c").rglob("*")) if f.is_file())


def test_a_chunk_failing_its_crc_is_refused_by_the_fast_path_and_the_reader(local_map, tmp_path, codec):
    path = tmp_path / "bad.sdfz"
    _write(path, codec, manifest=False)  # the fast path's own checks, under the manifest's
    f = _first_chunk(path)
    data = bytearray(f.read_bytes())
    data[len(data) // 2] ^= 0x40  # one bit inside the Blosc payload; the stored CRC32C no longer matches
    f.write_bytes(bytes(data))
    m = sdfcodec.open_map(path)
    fast = local_chunks(m.reader.group.store, m.reader.codes_array)
    key = f.relative_to(path).as_posix()
    idx = tuple(int(p) for p in key.split("/")[2:])
    sel = tuple(slice(i * c, (i + 1) * c) for i, c in zip(idx, m.reader.codes_array.chunks))
    with pytest.raises(errors.ChecksumError, match="CRC32C"):
        fast.read_many([sel])
    with pytest.raises(errors.ChecksumError, match=key.split("/", 1)[1]):
        list(m.iter_codes())


def test_a_frame_of_too_few_bytes_is_refused_even_with_a_valid_checksum(tmp_path, codec):
    """A hand-made chunk: a sound Blosc frame of half the chunk's bytes and its correct CRC32C. Decompressing it
    into the chunk's buffer would leave half of it unset; it is refused instead."""
    path = tmp_path / "short.sdfz"
    _write(path, codec, manifest=False)  # the fast path's own checks, under the manifest's
    f = _first_chunk(path)
    m = sdfcodec.open_map(path)
    arr = m.reader.codes_array
    half = np.zeros(int(np.prod(arr.chunks)) // 2, np.float32).tobytes()
    frame = numcodecs.blosc.compress(half, b"zstd", 3, numcodecs.blosc.SHUFFLE, 4)
    f.write_bytes(frame + np.uint32(google_crc32c.value(frame)).tobytes())
    m = sdfcodec.open_map(path)
    fast = local_chunks(m.reader.group.store, m.reader.codes_array)
    idx = tuple(int(p) for p in f.relative_to(path).as_posix().split("/")[2:])
    sel = tuple(slice(i * c, (i + 1) * c) for i, c in zip(idx, arr.chunks))
    with pytest.raises(errors.ChecksumError, match="holds .* bytes"):
        fast.read_many([sel])
    with pytest.raises(errors.SDFCodecError):
        list(m.iter_codes())


def test_a_sharded_map_reads_what_plain_zarr_reads(tmp_path, codec):
    plain, sharded = tmp_path / "p.sdfz", tmp_path / "s.sdfz"
    _write(plain, codec, seed=3)
    _write(sharded, codec, seed=3, shard_blocks=16)
    a, b = sdfcodec.open_map(plain), sdfcodec.open_map(sharded)
    assert local_chunks(b.reader.group.store, b.reader.codes_array) is not None  # chunks as ranges of shards
    fast = local_chunks(b.reader.group.store, b.reader.codes_array)
    sel = (slice(3, 20), slice(0, 18), slice(5, 11), slice(10, 50))  # across chunks and shards
    np.testing.assert_array_equal(fast.read_many([sel])[0], zarr.open_group(str(sharded), mode="r")["codes"][sel])
    want_c, want = _zarr_codes(sharded)
    cb, kb = b.read_codes()
    assert np.array_equal(cb, want_c) and np.array_equal(kb, want)
    ca, ka = a.read_codes()
    cb, kb = b.read_codes()
    assert np.array_equal(ca, cb) and np.array_equal(ka, kb)
    got = np.concatenate([k for _, k in a.iter_codes(level=48)])
    assert np.array_equal(got, np.concatenate([k for _, k in b.iter_codes(level=48)]))
