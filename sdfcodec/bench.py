"""Throughput benchmarks, each beside a baseline measured in the same run (never as timed unit tests).

The baseline ("roofline") of an operation is the chain of plain numpy matrix products ``(B, m) @ (m, n)`` that
the operation cannot avoid for a batch of ``B`` blocks, timed in the same run. For a linear codec of code size
``k`` (the default) that is ``(B, 4096) @ (4096, k)`` for encode and ``(B, k) @ (k, 4096)`` for decode. A ratio
near 1 means the codec adds no overhead to those products; the paper's GPU implementation took 405-645
microseconds per block.

Benchmark hooks
---------------
A codec class MAY provide two optional hooks; :func:`bench_codec` uses them when present and never looks at
codec ids:

``bench_instance(code_size) -> (codec, weights)`` (classmethod)
    A ready codec for timing at the nominal ``code_size`` (what ``sdfcodec bench --sizes`` passes; a codec
    defines what it means, e.g. the size of each part of a mixture), built without training, and a short
    phrase saying where its weights come from (e.g. ``"shipped sdfcodec/models/ae-64.npz"`` or
    ``"untrained (random init)"``: speed does not depend on the values). Without the hook the benchmark builds
    ``get_codec(id, code_size=k)`` (``get_codec(id)`` when the class takes no ``code_size``) and fits it on
    512 analytic blocks when it ``requires_fit``, which suits codecs that fit in moments (PCA).
``roofline_shapes(operation) -> list[(m, n)]`` (method)
    The right-hand matrix shapes of the products ``operation`` (``"encode"`` or ``"decode"``) needs per batch,
    in order: each is timed as ``(B, m) @ (m, n)``. Without it: ``[(4096, k)]`` / ``[(k, 4096)]``.

Records of a codec with either hook also carry ``roofline_shapes``, ``weights`` and ``torch_threads``; the
records of a codec with neither keep the original keys (see :func:`bench_codec`). Every record carries
``paper_us_per_block`` (405, 645) and ``speedup_vs_paper`` (those divided by ``us_per_block``).

Decode on read (:func:`bench_decode_on_read`) has a second roofline, memory-copy bandwidth: ``np.copyto``
between two 64 MiB buffers, timed in the same run, expressed as the blocks/s at which the decoded float32
blocks (16 KiB each) could merely be copied (``memcpy_blocks_per_s``): no decoder that writes its output can
beat it.
"""

from __future__ import annotations

import inspect
import time
from typing import Any, Callable, Iterable

import numpy as np
import torch

from .codec import Codec
from .errors import InvalidValueError
from .registry import get_codec, get_codec_class
from .testing import analytic_blocks

__all__ = ["time_call", "bench_codec", "bench_codec_instance", "bench_decode_on_read", "memcpy_bytes_per_s",
           "roofline_shapes", "PAPER_US_PER_BLOCK"]

PAPER_US_PER_BLOCK = (405.0, 645.0)
_N = 16 ** 3
_BLOCK_BYTES = 4 * _N  # one decoded float32 block
_OPS = ("encode", "decode")


def time_call(fn: Callable[[], object], min_time: float = 0.2, repeats: int = 3) -> float:
    """Best seconds per call of ``fn`` over ``repeats`` rounds, each running at least ``min_time``."""
    fn()  # warm-up: allocations, kernel selection, caches
    best = float("inf")
    for _ in range(repeats):
        n, t0 = 0, time.perf_counter()
        while True:
            fn()
            n += 1
            dt = time.perf_counter() - t0
            if dt >= min_time:
                break
        best = min(best, dt / n)
    return best


def _vs_paper(us_per_block: float) -> dict[str, Any]:
    return {"paper_us_per_block": list(PAPER_US_PER_BLOCK),
            "speedup_vs_paper": [p / us_per_block for p in PAPER_US_PER_BLOCK]}


def memcpy_bytes_per_s(nbytes: int = 64 << 20, min_time: float = 0.2) -> float:
    """Memory-copy bandwidth of this machine, now: bytes/s of ``np.copyto`` between two ``nbytes`` buffers
    (both touched first, so page faults are not timed)."""
    src = np.ones(max(1, nbytes // 4), np.float32)
    dst = np.zeros_like(src)
    return src.nbytes / time_call(lambda: np.copyto(dst, src), min_time)


def roofline_shapes(codec: Codec, operation: str) -> list[tuple[int, int]]:
    """The ``(m, n)`` right-hand shapes of the matrix products ``operation`` needs: the codec's
    ``roofline_shapes`` hook, else the single product of a linear codec."""
    if operation not in _OPS:
        raise InvalidValueError(f"operation must be 'encode' or 'decode', got {operation!r}")
    hook = getattr(codec, "roofline_shapes", None)
    if callable(hook):
        shapes = [(int(m), int(n)) for m, n in hook(operation)]
        if not shapes or any(m < 1 or n < 1 for m, n in shapes):
            raise InvalidValueError(f"{codec!r}.roofline_shapes({operation!r}) must be a non-empty list of "
                                    f"positive (m, n) shapes, got {shapes}")
        return shapes
    k = codec.code_size
    return [(_N, k)] if operation == "encode" else [(k, _N)]


def _roofline_fn(shapes: list[tuple[int, int]], batch: int) -> Callable[[], object]:
    rng = np.random.default_rng(0)
    mats = [rng.standard_normal(s, dtype=np.float32) for s in shapes]
    lhs = [rng.standard_normal((batch, s[0]), dtype=np.float32) for s in shapes]

    def run() -> None:
        for a, m in zip(lhs, mats):
            a @ m
    return run


def _has_hooks(codec: Codec) -> bool:
    return callable(getattr(type(codec), "bench_instance", None)) or callable(getattr(codec, "roofline_shapes", None))


def bench_codec_instance(codec: Codec, batches: Iterable[int], *, device: str = "cpu", min_time: float = 0.2,
                         weights: str | None = None, name: str | None = None,
                         progress: Callable[[str], None] | None = None) -> list[dict]:
    """Encode/decode blocks/s of a ready ``codec`` at each batch size, beside the numpy roofline of its layer
    shapes (:func:`roofline_shapes`), timed in the same run. Returns records as :func:`bench_codec`'s;
    ``weights`` (where the codec's weights come from) is recorded when given."""
    data = analytic_blocks(512, seed=3)
    dev = torch.device(device)
    sync = torch.cuda.synchronize if dev.type == "cuda" else (lambda: None)
    name = name or codec.codec_id
    extra = _has_hooks(codec) or weights is not None
    records = []
    for b in batches:
        x = torch.from_numpy(np.concatenate([data] * -(-b // len(data)))[:b]).to(dev)
        codes = codec.encode(x)
        for op, fn in (("encode", lambda: (codec.encode(x), sync())),
                       ("decode", lambda: (codec.decode(codes), sync()))):
            if progress:
                progress(f"{name}-{codec.code_size} {op} batch {b}")
            shapes = roofline_shapes(codec, op)
            t = time_call(fn, min_time)
            tb = time_call(_roofline_fn(shapes, b), min_time)
            rec: dict[str, Any] = {
                "codec": name, "code_size": codec.code_size, "operation": op, "batch": b, "device": str(dev),
                "blocks_per_s": b / t, "baseline": "numpy matmul of the layer shapes" if extra else "numpy matmul",
                "baseline_blocks_per_s": b / tb, "ratio_to_baseline": tb / t, "us_per_block": 1e6 * t / b,
                **_vs_paper(1e6 * t / b),
            }
            if extra:
                rec.update(roofline_shapes=[list(s) for s in shapes], weights=weights,
                           torch_threads=torch.get_num_threads())
            records.append(rec)
    return records


def _instance(codec_id: str, k: int) -> tuple[Codec, str | None]:
    cls = get_codec_class(codec_id)
    hook = getattr(cls, "bench_instance", None)
    if callable(hook):
        codec, weights = hook(k)
        return codec, str(weights)
    takes_size = "code_size" in inspect.signature(cls.__init__).parameters
    codec = get_codec(codec_id, code_size=k) if takes_size else get_codec(codec_id)
    if codec.requires_fit:
        codec.fit(analytic_blocks(512, seed=3))
    return codec, None


def bench_codec(codec_id: str, code_sizes: Iterable[int], batches: Iterable[int], *, device: str = "cpu",
                min_time: float = 0.2, progress: Callable[[str], None] | None = None,
                read_blocks: int = 0, http: bool = False) -> list[dict]:
    """Encode/decode blocks/s of ``codec_id`` at each code size and batch, beside the numpy matmul roofline.

    Returns one record per (code_size, operation, batch) with ``codec``, ``code_size`` (the codec's actual
    code length), ``operation``, ``batch``, ``device``, ``blocks_per_s``, ``baseline``,
    ``baseline_blocks_per_s``, ``ratio_to_baseline`` and ``us_per_block``; codecs with a benchmark hook (see
    the module docstring) add ``roofline_shapes``, ``weights`` and ``torch_threads``. With ``read_blocks > 0``,
    each code size also gets a ``"decode-on-read"`` record (:func:`bench_decode_on_read` over a map of that
    many blocks), and with ``http`` a ``"decode-on-read-http"`` one (the same map served on loopback).
    """
    records = []
    for k in code_sizes:
        codec, weights = _instance(codec_id, k)
        records += bench_codec_instance(codec, batches, device=device, min_time=min_time, weights=weights,
                                        name=codec_id, progress=progress)
        if read_blocks > 0:
            if progress:
                progress(f"{codec_id}-{codec.code_size} decode-on-read {read_blocks} blocks")
            records += bench_decode_on_read(codec, read_blocks, device=device, min_time=min_time,
                                            name=codec_id, weights=weights, http=http)
    return records


def bench_decode_on_read(codec: Codec, n_blocks: int, *, device: str = "cpu", min_time: float = 0.2,
                         name: str | None = None, weights: str | None = None, prefetch: int = 2,
                         http: bool = False) -> list[dict]:
    """Decode on read: blocks/s of :meth:`sdfcodec.Map.iter_decoded` over a whole map of ``n_blocks`` coded
    blocks (codes read, checksummed, decompressed, decoded to float32 metres) from local disk, and with
    ``http`` also over HTTP from a server on loopback, beside three baselines timed in the same run: the numpy
    roofline of the decode's layer shapes (``baseline``), memory-copy bandwidth (``memcpy_blocks_per_s``, see
    the module docstring) and the codec's own decode of the same codes already in memory
    (``in_memory_decode_blocks_per_s``).

    The map (float32 codes, default chunking) is written to a temporary directory and removed afterwards.
    Returns one record per source, ``operation`` ``"decode-on-read"`` (local) or ``"decode-on-read-http"``,
    with ``batch=n_blocks``.
    """
    import shutil
    import tempfile
    from pathlib import Path

    from .map import create_map, open_map

    if n_blocks < 1:
        raise InvalidValueError(f"n_blocks must be >= 1, got {n_blocks}")
    d_min, d_max = -0.04, 0.1
    data = analytic_blocks(512, seed=3)
    side = int(np.ceil(n_blocks ** (1 / 3)))
    coords = np.stack(np.unravel_index(np.arange(n_blocks), (side, side, side)), axis=1)
    tmp = Path(tempfile.mkdtemp(prefix="sdfcodec-bench-"))
    dev = None if device == "cpu" else torch.device(device)
    sync = torch.cuda.synchronize if dev is not None and dev.type == "cuda" else (lambda: None)
    timed: dict[str, float] = {}
    try:
        codes = np.asarray(codec.encode(data))  # real codes of 512 analytic blocks, tiled (reading is timed)
        with create_map(tmp / "bench.sdfz", codec=codec, voxel_size=0.02, truncation=(d_min, d_max)) as m:
            for i in range(0, n_blocks, 16384):
                j = min(i + 16384, n_blocks)
                m.write_codes(coords[i:j], np.concatenate([codes] * -(-(j - i) // len(codes)))[: j - i])
        sources = {"decode-on-read": str(tmp / "bench.sdfz")}
        server = _serve(tmp) if http else None
        if server is not None:
            sources["decode-on-read-http"] = f"http://127.0.0.1:{server.server_address[1]}/bench.sdfz"
        try:
            for op, where in sources.items():
                m = open_map(where)

                def read() -> None:
                    n = sum(len(c) for c, _ in m.iter_decoded(device=dev, prefetch=prefetch))
                    sync()
                    if n != n_blocks:  # the reader lost or invented blocks: the timing would be meaningless
                        raise InvalidValueError(f"decode on read yielded {n} blocks of the {n_blocks} written")

                timed[op] = time_call(read, min_time)
                m.close()
        finally:
            if server is not None:
                server.shutdown()
                server.server_close()
        m = open_map(tmp / "bench.sdfz")
        _, codes = m.read_codes()
        m.close()
        z = torch.from_numpy(codes).to(device)
        t_mem = time_call(lambda: (codec.decode(z), sync()), min_time)
        shapes = roofline_shapes(codec, "decode")
        tb = time_call(_roofline_fn(shapes, n_blocks), min_time)
        copy_bps = memcpy_bytes_per_s(min_time=min_time)
        code_bytes = sum(f.stat().st_size for f in (tmp / "bench.sdfz" / "codes").rglob("*") if f.is_file())
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    records = []
    for op, t in timed.items():
        us = 1e6 * t / n_blocks
        rec: dict[str, Any] = {
            "codec": name or codec.codec_id, "code_size": codec.code_size, "operation": op,
            "batch": n_blocks, "device": str(device), "blocks_per_s": n_blocks / t,
            "baseline": "numpy matmul of the layer shapes", "baseline_blocks_per_s": n_blocks / tb,
            "ratio_to_baseline": tb / t, "us_per_block": us, **_vs_paper(us),
            "memcpy_bytes_per_s": copy_bps, "memcpy_blocks_per_s": copy_bps / _BLOCK_BYTES,
            "ratio_to_memcpy": (n_blocks / t) / (copy_bps / _BLOCK_BYTES),
            "in_memory_decode_blocks_per_s": n_blocks / t_mem, "ratio_to_in_memory_decode": t_mem / t,
            "code_bytes_on_disk": code_bytes, "prefetch": prefetch, "torch_threads": torch.get_num_threads(),
        }
        if weights is not None:
            rec["weights"] = weights
        records.append(rec)
    return records


def _serve(root: Any):
    """A static HTTP server for the files under ``root`` on a free loopback port, serving from a thread."""
    import http.server
    import threading
    from functools import partial

    class Quiet(http.server.SimpleHTTPRequestHandler):
        # as production servers do: without it, headers and body leave in separate segments and the client's
        # delayed ACK stalls every response by ~40 ms (Nagle), which would time the TCP stack, not the reader
        disable_nagle_algorithm = True
        protocol_version = "HTTP/1.1"  # keep-alive: one connection per client thread, as with a real server

        def log_message(self, format: str, *args: Any) -> None:  # noqa: A002 - the stdlib's signature
            pass

    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), partial(Quiet, directory=str(root)))
    threading.Thread(target=server.serve_forever, daemon=True, name="sdfcodec-bench-http").start()
    return server
