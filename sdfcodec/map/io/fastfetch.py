"""Chunk reads of a local map without Zarr's event loop: the code-fetch path of every streaming reader
(``iter_codes``, search, ``iter_decoded``) for maps in a local directory.

Why it exists: Zarr reads a chunk through its asyncio event loop thread (a coroutine per chunk and per codec,
the Blosc stage sent to yet another thread), so a reader that streams a whole map spent most of its time
waiting on that thread (a cProfile of ``Map.iter_codes`` on a 65,536-block pca-64 map: 0.11 s of 0.18 s),
and read codes at 0.4-0.8 M blocks/s where Blosc alone decompresses them at about 1.8 M blocks/s on one core.
Here a chunk file is read, checked and decompressed by one plain function call in a small thread pool
(file reads, CRC32C and Blosc all release the GIL, so the threads run in parallel), straight into its
output array.

Nothing is skipped: the file is read through the map's guard (:meth:`GuardStore.read_chunk_file`: links,
FIFOs and files growing while read refused, the size bounded, the Blosc frame's structure checked before the
decompressor trusts it), every chunk's CRC32C is verified, and the frame must decompress to exactly the
chunk's size. Only the chain sdfcodec's writers use is read this way (bytes, Blosc, CRC32C), in chunk files or
in shards (the shard's index fetched through the guard, CRC32C-checked and kept, each chunk read as its byte
range), on a little-endian host; any other store or chain (HTTP, S3, zip, zstd or gzip, field compression)
goes through Zarr as before. A failure raises a :class:`~sdfcodec.errors.ChecksumError` naming the chunk's
key; the reader then reads it again through Zarr, whose error names it as it always did.

A store wrapper that only watches what is read (search's byte counter) joins in by giving ``inner`` (the
store it wraps) and ``observe(key, nbytes)``, called for every stored object read here (from several
threads); any other wrapper keeps the Zarr path.
"""

from __future__ import annotations

import itertools
import os
import sys
import threading
from concurrent.futures import ThreadPoolExecutor
from typing import Any, Callable, Sequence

import numcodecs.blosc
import numpy as np
import zarr
from zarr.abc.store import RangeByteRequest, SuffixByteRequest

from ...errors import ChecksumError
from .frames import crc32c_matches
from .shards import chunk_ranges
from .shards import index_entry, index_size
from .stores import GuardStore, SafeLocalStore

__all__ = ["LocalChunks", "local_chunks"]

#: Threads decoding chunks, shared by every reader of the process (decodes release the GIL).
WORKERS = max(1, min(8, os.cpu_count() or 1))
_pool: list[ThreadPoolExecutor] = []
_pool_lock = threading.Lock()
_scratch = threading.local()  # each decoding thread's chunk buffer, reused (a fresh one faults its pages in)


def _forget_pool() -> None:
    # a forked child has none of the parent's threads: submitting to their executor would wait forever
    global _pool_lock
    _pool.clear()
    _pool_lock = threading.Lock()


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_forget_pool)


def _executor() -> ThreadPoolExecutor:
    with _pool_lock:
        if not _pool:
            _pool.append(ThreadPoolExecutor(max_workers=WORKERS, thread_name_prefix="sdfcodec-chunk"))
        return _pool[0]


class LocalChunks:
    """Reads selections of one checked array of a local map (see the module docstring)."""

    def __init__(self, guard: GuardStore, arr: zarr.Array, observers: Sequence[Callable[[str, int], Any]]):
        self.guard, self.arr, self.observers = guard, arr, tuple(observers)
        self.dtype = np.dtype(arr.dtype)
        self.chunk_shape = tuple(int(c) for c in arr.chunks)
        self.chunk_bytes = int(np.prod(self.chunk_shape)) * self.dtype.itemsize
        self.fill = arr.metadata.fill_value
        # a sharded array (spec 4d): chunks per shard along each axis; a chunk is a byte range of its shard
        self.ratio = None if arr.shards is None else tuple(int(s) // c for s, c in zip(arr.shards, self.chunk_shape))
        self.per = 1 if self.ratio is None else int(np.prod(self.ratio))

    def key(self, idx: tuple[int, ...]) -> str:
        return f"{self.arr.path}/{self.arr.metadata.encode_chunk_key(tuple(int(i) for i in idx))}"

    def _read(self, key: str, byte_range: Any = None) -> bytes | None:
        data = self.guard.read_chunk_file(key, byte_range)
        if data is not None:
            for observe in self.observers:
                observe(key, len(data))
        return data

    def _stored(self, idx: tuple[int, ...]) -> tuple[str, bytes | None]:
        """``(name, stored bytes or None)`` of chunk ``idx``: its file, or its range of its shard (found in the
        shard's index, which is checked and kept by the guard)."""
        if self.ratio is None:
            key = self.key(idx)
            return key, self._read(key)
        key = self.key(tuple(i // r for i, r in zip(idx, self.ratio)))
        index = self._read(key, SuffixByteRequest(index_size(self.per)))
        where = int(np.ravel_multi_index(tuple(i % r for i, r in zip(idx, self.ratio)), self.ratio))
        entry = None if index is None else index_entry(index, self.per, where)
        if entry is None:
            return key, None
        return f"{key} [{entry[0]}, {entry[0] + entry[1]})", self._read(key, RangeByteRequest(*(entry[0], sum(entry))))

    def decode_into(self, idx: tuple[int, ...], out: np.ndarray, sub: tuple[slice, ...]) -> bool:
        """Write the part ``sub`` of chunk ``idx`` (decoded, checked) into ``out`` (the fill value when the chunk
        is not stored: then False)."""
        key, data = self._stored(idx)
        if data is None:  # never written: the fill value, as Zarr reads it
            out[...] = self.fill
            return False
        raw = np.frombuffer(data, np.uint8)
        if len(raw) < 20 or not crc32c_matches(raw):
            raise ChecksumError(f"chunk {key} fails its CRC32C checksum")
        if int.from_bytes(data[4:8], "little") != self.chunk_bytes:  # fewer bytes would leave the buffer unset
            raise ChecksumError(f"chunk {key} holds {int.from_bytes(data[4:8], 'little')} bytes, its shape "
                                f"{self.chunk_shape} takes {self.chunk_bytes}")
        whole = all(s.start == 0 and s.stop == c for s, c in zip(sub, self.chunk_shape))
        if whole and out.flags.c_contiguous:
            numcodecs.blosc.decompress(raw[:-4], out)
            return True
        chunk = np.empty(self.chunk_shape, self.dtype)
        numcodecs.blosc.decompress(raw[:-4], chunk)
        out[...] = chunk[sub]
        return True

    def _decoded(self, idx: tuple[int, ...]) -> np.ndarray | None:
        """Chunk ``idx`` decoded into this thread's scratch buffer (valid until its next call), or None when it
        is not stored."""
        scratch = getattr(_scratch, "buf", None)
        if scratch is None or scratch.nbytes < self.chunk_bytes:
            scratch = _scratch.buf = np.empty(self.chunk_bytes, np.uint8)
        chunk = scratch[:self.chunk_bytes].view(self.dtype).reshape(self.chunk_shape)
        return chunk if self.decode_into(idx, chunk, tuple(slice(0, c) for c in self.chunk_shape)) else None

    def gather(self, sels: Sequence[tuple[slice, ...]], locs: Sequence[np.ndarray]) -> np.ndarray:
        """The rows ``arr[sel][tuple(loc.T)]`` of every selection, stacked ``(sum len(loc), *rest)``: ``sels`` as
        :meth:`read_many`, each inside one chunk along the leading ``loc.shape[1]`` axes; each chunk is decoded
        and its rows copied straight into the output, concurrently."""
        nlead = locs[0].shape[1] if len(locs) else 0
        rest = [s.indices(n)[:2] for s, n in zip(sels[0][nlead:], self.arr.shape[nlead:])] if len(sels) else []
        out = np.empty((sum(len(l) for l in locs), *(b - a for a, b in rest)), self.dtype)
        jobs, row = [], 0
        for sel, loc in zip(sels, locs):
            if not len(loc):
                continue
            lead = [s.indices(n)[0] for s, n in zip(sel[:nlead], self.arr.shape)]
            base = [a // c for a, c in zip(lead, self.chunk_shape)]
            flat = np.ravel_multi_index(tuple((loc + [a - b * c for a, b, c in zip(lead, base, self.chunk_shape)]).T),
                                        self.chunk_shape[:nlead])
            for tail in itertools.product(*chunk_ranges(self.arr, sel)[nlead:]):
                lo = [max(a, i * c) for (a, _), i, c in zip(rest, tail, self.chunk_shape[nlead:])]
                hi = [min(b, (i + 1) * c) for (_, b), i, c in zip(rest, tail, self.chunk_shape[nlead:])]
                dst = (slice(row, row + len(loc)), *(slice(l - a, h - a) for l, h, (a, _) in zip(lo, hi, rest)))
                sub = tuple(slice(l - i * c, h - i * c) for l, h, i, c in zip(lo, hi, tail, self.chunk_shape[nlead:]))
                jobs.append(((*base, *tail), flat, out, dst, sub))
            row += len(loc)
        self._run(self._gather_one, jobs)
        return out

    def _gather_one(self, idx, flat, out, dst, sub) -> None:
        chunk = self._decoded(idx)
        if chunk is None:
            out[dst] = self.fill
            return
        nlead = len(self.chunk_shape) - len(sub)
        rows = chunk.reshape(-1, *self.chunk_shape[nlead:])
        # every block of the chunk wanted: ``flat`` is then 0, 1, ... (np.argwhere's C order), so no gather
        out[dst] = rows[flat][(slice(None), *sub)] if len(flat) < len(rows) else rows[(slice(None), *sub)]

    def _run(self, fn: Callable, jobs: list) -> None:
        if len(jobs) == 1:
            fn(*jobs[0])
            return
        futures = [_executor().submit(fn, *job) for job in jobs]
        errors = [f.exception() for f in futures]
        first = next((e for e in errors if e is not None), None)
        if first is not None:
            raise first

    def read_many(self, sels: Sequence[tuple[slice, ...]]) -> list[np.ndarray]:
        """``arr[sel]`` for every selection (step-1 slices, one per axis, inside the array), every chunk they
        touch decoded concurrently. Raises ChecksumError naming a chunk that fails its checks."""
        outs, jobs = [], []
        for sel in sels:
            bounds = [s.indices(n)[:2] for s, n in zip(sel, self.arr.shape)]
            out = np.empty(tuple(b - a for a, b in bounds), self.dtype)
            outs.append(out)
            for idx in itertools.product(*chunk_ranges(self.arr, sel)):
                lo = [max(a, i * c) for (a, _), i, c in zip(bounds, idx, self.chunk_shape)]
                hi = [min(b, (i + 1) * c) for (_, b), i, c in zip(bounds, idx, self.chunk_shape)]
                dst = out[tuple(slice(l - a, h - a) for l, h, (a, _) in zip(lo, hi, bounds))]
                sub = tuple(slice(l - i * c, h - i * c) for l, h, i, c in zip(lo, hi, idx, self.chunk_shape))
                jobs.append((idx, dst, sub))
        self._run(self.decode_into, jobs)
        return outs


def local_chunks(store: zarr.abc.store.Store, arr: zarr.Array) -> LocalChunks | None:
    """The fast reader of ``arr`` read through ``store`` (the reader's group store), or None where Zarr's path
    must read it (see the module docstring)."""
    observers = []
    while not isinstance(store, GuardStore):
        observe, inner = getattr(store, "observe", None), getattr(store, "inner", None)
        if not callable(observe) or inner is None:
            return None
        observers.append(observe)
        store = inner
    limit = store.limit_of(f"{arr.path}/c")
    if sys.byteorder != "little" or not isinstance(store.inner, SafeLocalStore) or limit is None or not limit[1]:
        return None
    return LocalChunks(store, arr, observers)
