"""How the reader walks a map: which code chunks it reads together (:func:`chunk_groups`), how groups are
fetched ahead of the caller (:func:`prefetched`), and how a group's chunks are decoded on every core
(:func:`each_chunk`, with decoded chunks kept in a :class:`ChunkCache` any thread may fill).

A group is the unit of one batched fetch and one batched decode. Grouping follows the block states only, never
the chunks' volume, so a sparse map (or a hostile, huge and empty grid) costs what it stores; a group never
holds more than the reader's ``max_decode_bytes`` of codes and decoded blocks.
"""

from __future__ import annotations

import collections
import itertools
import os
import threading
from concurrent.futures import ThreadPoolExecutor
from typing import Any, Callable, Iterable, Iterator, Sequence

import numpy as np

from ..core._validate import BLOCK
from ..errors import InvalidValueError
from ..core.header import BlockState, CodesSpec

__all__ = ["Box", "chunk_box", "chunk_groups", "prefetched", "READ_THREADS", "read_threads", "each_chunk",
           "thread_shares", "ChunkCache"]

Box = tuple[slice, slice, slice]  # a block box: half-open block index ranges per axis


def chunk_box(key: Any, chunk: Any, shape: Any) -> tuple[slice, ...]:
    """The index box of chunk ``key`` (its index per axis) of an array of ``shape`` cut in chunks of ``chunk``
    elements (one int for every axis, or one per axis): half-open slices, the last chunk of an axis ending with
    the array."""
    sizes = [int(chunk)] * len(key) if isinstance(chunk, (int, np.integer)) else [int(c) for c in chunk]
    return tuple(slice(int(k) * c, min(int(k) * c + c, int(n))) for k, c, n in zip(key, sizes, shape))


def chunk_groups(spec: CodesSpec, box: Box, states: np.ndarray, level: int, *, max_decode_bytes: int,
                 batch_blocks: int | None = None, chunks_per_group: int | None = None,
                 columns: bool = False) -> list[np.ndarray]:
    """Chunk indices ``(G, 3)`` (of the block axes of the ``codes`` array laid out by ``spec``) holding coded
    blocks inside ``box`` (``states``: the block states of that box), in grid order, grouped:
    ``chunks_per_group`` chunks, or (``batch_blocks``) consecutive chunks until they hold that many coded
    blocks; ``columns``: a group then also runs to the end of its column of chunks along z (what a dense volume
    is filled best by: whole rows of blocks) unless it reaches twice that many first. A group never holds more
    than ``max_decode_bytes`` of codes (the first ``level`` elements' chunks) and decoded blocks."""
    cb = spec.chunk_blocks
    b0 = np.array([s.start for s in box], dtype=np.int64)
    n = np.array(states.shape, dtype=np.int64)
    if not n.all():
        return []
    lead = b0 % cb
    # coded blocks per chunk, summed axis by axis between chunk boundaries: time and memory follow the block
    # states, never the chunks' volume (a hostile 256^3-block chunk over a thin box costs nothing extra)
    counts = states == BlockState.CODED
    for ax in range(3):
        starts = np.r_[0, np.arange(cb - lead[ax] if lead[ax] else cb, n[ax], cb)]
        counts = np.add.reduceat(counts, starts, axis=ax, dtype=np.int32)
    idx = np.argwhere(counts)
    if not len(idx):
        return []
    per_block = counts[tuple(idx.T)]
    idx += b0 // cb
    read = -(-level // spec.chunk_code) * spec.chunk_code * np.dtype(spec.dtype).itemsize
    cap = max(1, max_decode_bytes // (cb ** 3 * (read + 4 * BLOCK ** 3)))
    if chunks_per_group is not None:
        cap, target = min(cap, chunks_per_group), None
    else:
        target = batch_blocks
    # where a column of chunks along z ends: a group of `columns` closes only there, or mid-column at twice the
    # batch (a tall map's column: the memory stays O(batch)), or at the cap
    ends = np.r_[np.any(idx[1:, :2] != idx[:-1, :2], axis=1), True] if columns else np.ones(len(idx), bool)
    groups, start, acc = [], 0, 0
    for i, (c, end) in enumerate(zip(per_block.tolist(), ends.tolist())):
        acc += c
        if (target is not None and acc >= target and (end or acc >= 2 * target)) or i + 1 - start >= cap:
            groups.append(idx[start:i + 1])
            start, acc = i + 1, 0
    if start < len(idx):
        groups.append(idx[start:])
    return groups


def prefetched(job: Callable[[Any], Any], groups: Iterable[Any], prefetch: int) -> Iterator[Any]:
    """``job(g)`` for every group, in order, with up to ``prefetch`` further groups run ahead by a thread pool
    while the caller works on the result yielded; with one group or ``prefetch == 0``, everything runs inline.
    A consumer that stops early (or an error) cancels what was not started and does not wait for it."""
    if isinstance(prefetch, bool) or not isinstance(prefetch, (int, np.integer)) or prefetch < 0:
        raise InvalidValueError(f"prefetch must be an int >= 0 (groups read ahead), got {prefetch!r}")
    groups = list(groups)
    if len(groups) <= 1 or prefetch == 0:
        for g in groups:
            yield job(g)
        return
    pool = ThreadPoolExecutor(max_workers=int(prefetch), thread_name_prefix="sdfcodec-read")
    pending: collections.deque = collections.deque()
    todo = iter(groups)
    finished = False
    try:
        for g in itertools.islice(todo, int(prefetch)):
            pending.append(pool.submit(job, g))
        while pending:
            result = pending.popleft().result()
            nxt = next(todo, None)
            if nxt is not None:
                pending.append(pool.submit(job, nxt))
            yield result
        finished = True
    finally:
        # abandoned early (an error, a consumer that stopped): do not wait for reads nobody will use
        for f in pending:
            f.cancel()
        pool.shutdown(wait=finished, cancel_futures=True)


#: Threads a read decodes the chunks of one group on (:func:`each_chunk`); None: :func:`read_threads` decides.
#: The compiled kernels of a variable-rate read release the GIL, so each thread keeps a core busy.
READ_THREADS: int | None = None


def read_threads() -> int:
    """The threads :func:`each_chunk` runs on: :data:`READ_THREADS`, else the CPUs this process may use, at most
    8 (a group's chunks are few, and each thread holds its chunk's decode in memory) and at most
    ``NUMBA_NUM_THREADS`` where that is set (the threads run numba's kernels: a process given a share of the
    cores, such as a test worker, keeps to it)."""
    if READ_THREADS is not None:
        return max(1, int(READ_THREADS))
    try:
        cpus = len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        cpus = os.cpu_count() or 1
    share = os.environ.get("NUMBA_NUM_THREADS", "")
    if share.isdigit() and int(share) > 0:
        cpus = min(cpus, int(share))
    return max(1, min(cpus, 8))


def thread_shares(sizes: Sequence[int], threads: int) -> list[int]:
    """Threads for each of the jobs of ``sizes`` (their work) run side by side on ``threads`` threads: each job's
    share of ``threads`` in proportion to its size, at least 1. A job of most of the work gets most of the cores
    (a map whose coded blocks lie nearly all in one chunk: the kitchen's 494 and 13), jobs of like sizes one each."""
    total = float(sum(sizes))
    if total <= 0 or threads <= 1:
        return [1] * len(sizes)
    return [max(1, min(threads, round(threads * s / total))) for s in sizes]


def each_chunk(job: Callable[[Any], Any], items: Iterable[Any], threads: int | None = None) -> list[Any]:
    """``[job(item) for item in items]``, the items shared among up to ``threads`` (default :func:`read_threads`)
    threads, the calling thread one of them; inline with one item or one thread. ``job`` must be safe to run on
    several items at once (each writes only its own part of any shared output). The first error is raised once
    every job started has ended."""
    items = list(items)
    threads = read_threads() if threads is None else max(1, int(threads))
    if len(items) <= 1 or threads == 1:
        return [job(it) for it in items]
    out: list[Any] = [None] * len(items)
    nxt = itertools.count()  # next() of a count is atomic under the GIL: each item is taken once
    errors: list[BaseException] = []

    def work() -> None:
        for i in iter(lambda: next(nxt), None):
            if i >= len(items) or errors:
                return
            try:
                out[i] = job(items[i])
            except BaseException as e:  # noqa: BLE001 - handed to the calling thread
                errors.append(e)
                return

    helpers = [threading.Thread(target=work, name="sdfcodec-chunk", daemon=True)
               for _ in range(min(threads, len(items)) - 1)]
    for t in helpers:
        t.start()
    work()
    for t in helpers:
        t.join()
    if errors:
        raise errors[0]
    return out


class ChunkCache:
    """The last ``size`` decoded chunks by key, oldest dropped first; safe to fill from several threads (a lock
    around each change: :func:`each_chunk` gives each thread its own chunks, so none is decoded twice)."""

    def __init__(self, size: int):
        self.size = size
        self._items: dict[Any, Any] = {}
        self._lock = threading.Lock()

    def get(self, key: Any) -> Any:
        """The value kept for ``key``, or None."""
        return self._items.get(key)

    def __contains__(self, key: Any) -> bool:
        return key in self._items

    def __getitem__(self, key: Any) -> Any:
        return self._items[key]

    def __len__(self) -> int:
        return len(self._items)

    def put(self, key: Any, value: Any) -> None:
        """Keep ``value`` for ``key``, dropping the oldest entries beyond ``size``."""
        with self._lock:
            self._items[key] = value
            while len(self._items) > self.size:
                self._items.pop(next(iter(self._items)))
