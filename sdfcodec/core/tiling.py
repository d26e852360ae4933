"""Cache-sized tiles on the CPU's cores: the machinery behind the optional ``decode_tiles`` hook
(spec/codec-plugins.md, section 4).

A decode into memory costs one pass over its output when each piece of work on a block (the product that makes
it, the truncation to ``[d_min, d_max]``, the copy to its place in a volume) happens while the block is still in
the core's cache. :func:`run_tiles` cuts rows ``[0, n)`` into tiles of :data:`TILE_ROWS` rows that one thread
per core takes in turn; each runs a one-threaded BLAS on its tile (OpenBLAS's threads are held at 1 for the
call), so the product, the clip and the placing of a tile all see the same core's cache (a tile of
:data:`TILE_ROWS`, four times the core's L2, comes back from L3 at worst: :func:`tile_rows_for`).
The work function releases the GIL in its numpy calls (matmul, clip, copies), so Python threads run in parallel.
What it is worth, interleaved with the bare product, is measured at :func:`tile_rows_for`; ``sdfcodec bench``
reports it on the machine at hand (record ``decode-on-read`` against the memory copy).
"""

from __future__ import annotations

import contextlib
import itertools
import os
import threading
from concurrent.futures import ThreadPoolExecutor
from typing import Callable, Iterator

import numpy as np

__all__ = ["TILE_ROWS", "l2_bytes", "one_blas_thread", "run_tiles", "scratch", "tile_rows_for"]


def l2_bytes(sysfs: str = "/sys/devices/system/cpu/cpu0/cache") -> int | None:
    """The first core's level-2 (data or unified) cache in bytes, as Linux describes it; None where it does not."""
    with contextlib.suppress(OSError, ValueError):
        for entry in sorted(os.listdir(sysfs)):
            d = os.path.join(sysfs, entry)
            if not entry.startswith("index"):
                continue
            with open(os.path.join(d, "level")) as f:
                level = int(f.read())
            with open(os.path.join(d, "type")) as f:
                kind = f.read().strip()
            if level == 2 and kind in ("Unified", "Data"):
                with open(os.path.join(d, "size")) as f:
                    size = f.read().strip().upper()
                scale = {"K": 1 << 10, "M": 1 << 20, "G": 1 << 30}.get(size[-1:], 1)
                return int(size.rstrip("KMG")) * scale
    return None


def tile_rows_for(l2: int | None) -> int:
    """Rows per tile for a core with ``l2`` bytes of level-2 cache: decoded blocks (16 KiB each) filling four
    times the L2, a power of two in [64, 1024]; 512 when the cache is not known. What sets the size is the
    BLAS call (each one packs the (k + 1, 4096) decoder again, so short tiles pay that per few rows) against the
    placement's reads of the tile (a tile much larger than the L2 comes back from L3). Measured, interleaved with
    the roofline, 65,536 pca-64 blocks, decode_region into a reused volume: Intel Xeon, L2 2 MiB a core, 0.45 /
    0.47 / 0.50 / 0.51 of the roofline at 128 / 256 / 512 / 1024 rows (decode on read 0.65 / 0.74 / 0.72 at 256 /
    512 / 1024); AMD EPYC, L2 512 KiB a core, 0.52 / 0.46-0.47 / 0.38-0.40 at 128 / 256 / 512 (64 rows: 0.48;
    decode on read 0.55-0.62 at every size)."""
    if not l2:
        return 512
    rows = max(64, min(1024, 4 * l2 // (16 << 10)))
    return 1 << (rows.bit_length() - 1)


#: Rows per tile on this machine (:func:`tile_rows_for` its L2), read at each :func:`run_tiles` call.
TILE_ROWS = tile_rows_for(l2_bytes())
#: The fewest rows a tile is cut to so that a short batch reaches every core (below it the calls cost more than
#: the threads win: 16-row tiles decoded 30 % slower than 128-row ones).
_MIN_ROWS = 64

_lock = threading.Lock()
_state: dict = {"pool": None, "workers": 0, "held": 0, "before": None, "ctl": None}
_local = threading.local()


def _blas():
    """numpy's BLAS as a threadpoolctl controller (found once), or None when threadpoolctl finds none."""
    if _state["ctl"] is None:
        from threadpoolctl import ThreadpoolController

        libs = ThreadpoolController().select(user_api="blas").lib_controllers
        # numpy's own (scipy may bring another OpenBLAS; torch's BLAS is not numpy's matmul)
        mine = [lib for lib in libs if "numpy" in lib.filepath]
        _state["ctl"] = (mine or libs or [False])[0]
    return _state["ctl"] or None


@contextlib.contextmanager
def one_blas_thread() -> Iterator[int]:
    """Hold numpy's BLAS at one thread (the caller brings its own threads: the tiles, the tracker's chunk
    threads); yields the threads it had, the cores the caller may use. Nested and concurrent holders share one
    limit; the last to leave restores it."""
    blas = _blas()
    with _lock:
        if _state["held"] == 0:
            _state["before"] = blas.num_threads if blas is not None else (os.cpu_count() or 1)
            if blas is not None and _state["before"] != 1:
                blas.set_num_threads(1)
        _state["held"] += 1
        threads = _state["before"]
    try:
        yield threads
    finally:
        with _lock:
            _state["held"] -= 1
            if _state["held"] == 0 and blas is not None and _state["before"] != 1:
                blas.set_num_threads(_state["before"])


def _pool(workers: int) -> ThreadPoolExecutor:
    """A persistent pool of ``workers`` threads (kept between calls: a decode runs it once per group)."""
    with _lock:
        if _state["workers"] < workers:
            if _state["pool"] is not None:
                _state["pool"].shutdown(wait=False)
            _state["pool"] = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="sdfcodec-tiles")
            _state["workers"] = workers
        return _state["pool"]


def run_tiles(n: int, work: Callable[[int, int], None], *, rows: int | None = None) -> None:
    """Call ``work(a, b)`` for consecutive tiles ``[a, b)`` of at most ``rows`` rows (None: :data:`TILE_ROWS`,
    read at each call) covering ``[0, n)`` once each, on as many threads as numpy's BLAS had (the calling thread
    one of them; each takes the next tile when done with one), with BLAS held at one thread meanwhile. ``work``
    must be safe to run on disjoint tiles at once. After an exception no tile is started; the first one is
    raised once all threads have stopped."""
    if n <= 0:
        return
    with one_blas_thread() as threads:
        rows = TILE_ROWS if rows is None else int(rows)
        # a short batch is still shared by every core: tiles of at least _MIN_ROWS rows, as many as the threads
        rows = max(1, min(rows, max(_MIN_ROWS, -(-n // int(threads)))))
        tiles = -(-n // rows)
        workers = max(1, min(int(threads), tiles))
        # tiles are taken in turn from one counter (next() on it is atomic under the GIL), not cut into fixed
        # shares: on a loaded machine a thread the scheduler holds back takes fewer, and no thread waits long
        # for another at the end of the batch
        turn = itertools.count()
        stop: list[BaseException] = []

        def share() -> None:
            for i in iter(turn.__next__, tiles):
                if i >= tiles or stop:
                    return
                try:
                    work(i * rows, min(i * rows + rows, n))
                except BaseException as e:
                    stop.append(e)
                    raise

        if workers == 1:
            share()
            return
        futures = [_pool(workers - 1).submit(share) for _ in range(1, workers)]
        try:
            share()
        finally:
            errors = [f.exception() for f in futures]
        for e in errors:
            if e is not None:
                raise e


def scratch(name: str, shape: tuple[int, ...], dtype=np.float32) -> np.ndarray:
    """A buffer of ``shape`` private to the calling thread, kept between calls under ``name`` (a tile's
    decodes stay in that core's cache from one tile to the next); its contents are undefined."""
    bufs = _local.__dict__.setdefault("bufs", {})
    buf = bufs.get(name)
    size = int(np.prod(shape))
    if buf is None or buf.size < size or buf.dtype != dtype:
        buf = bufs[name] = np.empty(size, dtype=dtype)
    return buf[:size].reshape(shape)
