"""Throughput benchmarks, each beside a baseline measured in the same run (never as timed unit tests).

The baseline ("roofline") of an operation is the chain of plain numpy matrix products ``(B, m) @ (m, n)`` that
the operation cannot avoid for a batch of ``B`` blocks, timed in the same run. For a linear codec of code size
``k`` (the default) that is ``(B, 4096) @ (4096, k)`` for encode and ``(B, k) @ (k, 4096)`` for decode. A ratio
near 1 means the codec adds no overhead to those products; the paper's GPU implementation took 405-645
microseconds per block.

A codec's plugin MAY register how to benchmark it with :func:`register_bench` (a ready instance without
training, and the matrix shapes of its roofline); the contract is spec/codec-plugins.md, section 5. Without a
registration the benchmark builds ``get_codec(id, code_size=k)``, fits it on 512 analytic blocks when it
``requires_fit``, and times the single product of a linear codec. No codec id is special-cased here.

Records of a registered codec also carry ``roofline_shapes``, ``weights`` and ``torch_threads``; the records
of others keep the original keys (see :func:`bench_codec`). Every record carries ``paper_us_per_block``
(405, 645) and ``speedup_vs_paper`` (those divided by ``us_per_block``, :func:`vs_paper`).

Codecs with a weighted encode (:meth:`~sdfcodec.Codec.encode_weighted`, the one map writers use for fused maps)
also get ``"encode-weighted"`` records: the same blocks with the error weights a fused map gives them
(:func:`fused_style_weights`), with ``ratio_to_encode`` (plain encode time over weighted encode time: the plain
encode is timed again in the same interleaved rounds and the ratio paired round by round,
:func:`~sdfcodec.bench.harness.paired`; ``encode_blocks_per_s`` is its median there). Its roofline is what an
exact weighted least-squares fit of a linear code of size ``k`` cannot avoid: the plain projection, the Gram
matrices ``(B, 4096) @ (4096, k (k + 1) / 2)`` and the weighted right-hand sides ``(B, 4096) @ (4096, k)``.
``"encode-masked"`` records time what a map writer runs on those blocks
(:func:`sdfcodec.map.observed.encode_truncated`: the weighted fit, refitted for the reader's truncation), against
the same roofline of one fit and with ``ratio_to_encode`` too.

Decode on read (:func:`bench_decode_on_read`) has a second roofline, memory-copy bandwidth: ``np.copyto``
between two 64 MiB buffers, timed in the same run, expressed as the blocks/s at which the decoded float32
blocks (16 KiB each) could merely be copied (``memcpy_blocks_per_s``): no decoder that writes its output can
beat it.

Timing (:mod:`sdfcodec.bench.harness`): a figure and its baselines are timed interleaved, in ``repeats`` equal
rounds; ``blocks_per_s`` and ``ratio_to_baseline`` come from the medians, ``blocks_per_s_best`` and
``ratio_of_bests`` from the bests. The matrix-product roofline writes into preallocated outputs
(``np.matmul(..., out=)``), as the memory copy does (``np.copyto``): a baseline that allocated and faulted in a
fresh output per call would be slower than the hardware allows, flattering the codec.
"""

from __future__ import annotations

import contextlib
import inspect
import warnings
from dataclasses import dataclass
from typing import Any, Callable, Iterable

import numpy as np

from ..core._lazy import lazy_module
from ..codec import Codec, uses_weights
from ..errors import CodecTypeError, InvalidValueError, RegistrationError
from ..registry import get_codec, get_codec_class
from .harness import Timing, interleave, load, paired, ratio, time_call
from .serve import FileServer

torch = lazy_module("torch")  # imported on first use: sdfcodec.plugin imports this module for register_bench

__all__ = ["bench_codec", "fused_style_weights", "bench_codec_instance", "bench_decode_on_read", "memcpy_bytes_per_s",
           "roofline_shapes", "register_bench", "bench_instance", "BenchSpec", "vs_paper", "PAPER_US_PER_BLOCK",
           "roofline_fn", "memcpy_fn", "timed_record", "bench_decode_in_place", "write_bench_map", "bench_steps"]

PAPER_US_PER_BLOCK = (405.0, 645.0)
_N = 16 ** 3
_BLOCK_BYTES = 4 * _N  # one decoded float32 block
_OPS = ("encode", "decode", "encode-weighted", "encode-masked")
#: "encode-weighted" and "encode-masked" are timed for code sizes whose exact-fit roofline table (4096 x k (k + 1) / 2 float32)
#: fits in this (k <= 361); beyond it (raw: k = 4096, lossless, its weighted encode is its encode) it is not
_MAX_GRAM_TABLE_BYTES = 1 << 30


def vs_paper(us_per_block: float) -> dict[str, Any]:
    """The paper comparison every benchmark record carries: ``{"paper_us_per_block": [405, 645],
    "speedup_vs_paper": [405 / us, 645 / us]}`` for ``us_per_block`` microseconds per block."""
    return {"paper_us_per_block": list(PAPER_US_PER_BLOCK),
            "speedup_vs_paper": [p / us_per_block for p in PAPER_US_PER_BLOCK]}




# -- benchmark registrations (spec/codec-plugins.md, section 5) --------------------------------------------------
@dataclass(frozen=True)
class BenchSpec:
    """How to benchmark one codec: see :func:`register_bench`."""

    instance: Callable[..., tuple[Codec, str]] | None = None
    roofline_shapes: Callable[[Codec, str], list[tuple[int, int]]] | None = None


_BENCH: dict[Any, BenchSpec] = {}  # keys: codec classes and codec ids


def register_bench(codec: str | type[Codec], *, instance: Callable[..., tuple[Codec, str]] | None = None,
                   roofline_shapes: Callable[[Codec, str], list[tuple[int, int]]] | None = None) -> None:
    """Tell the benchmark how to measure ``codec`` (a codec id, or a class: it then covers its subclasses).

    ``instance(code_size, **options) -> (codec, weights)`` builds a ready codec for timing at the nominal
    ``code_size`` (what ``sdfcodec bench --sizes`` passes; the codec says what it means, e.g. the size of
    each part of a mixture) without training, and a short phrase saying where its weights come from
    (``"untrained (random init)"`` is fine: speed does not depend on the values). ``options`` are
    codec-specific settings given to :func:`bench_instance`; those the function does not name are not passed.
    ``roofline_shapes(codec, operation) -> [(m, n), ...]`` lists the right-hand shapes of the matrix products
    ``operation`` (``"encode"`` or ``"decode"``) needs per batch, in order, each timed as ``(B, m) @ (m, n)``.
    A plugin calls this once, when it is imported (through :mod:`sdfcodec.plugin`); registering again
    replaces the earlier registration.
    """
    if not (isinstance(codec, str) or (isinstance(codec, type) and issubclass(codec, Codec))):
        raise CodecTypeError(f"register_bench takes a codec id or a Codec subclass, got {codec!r}")
    if instance is None and roofline_shapes is None:
        raise RegistrationError(f"register_bench({codec!r}) needs instance= or roofline_shapes=")
    for name, fn in (("instance", instance), ("roofline_shapes", roofline_shapes)):
        if fn is not None and not callable(fn):
            raise CodecTypeError(f"register_bench {name}= must be callable, got {fn!r}")
    _BENCH[codec] = BenchSpec(instance, roofline_shapes)


def _legacy_spec(cls: type) -> BenchSpec | None:
    """Spec 1's benchmark hooks, methods on the codec class (``bench_instance``, ``roofline_shapes``)."""
    inst, shapes = getattr(cls, "bench_instance", None), getattr(cls, "roofline_shapes", None)
    if not (callable(inst) or callable(shapes)):
        return None
    warnings.warn(f"{cls.__qualname__} declares spec-1 benchmark hooks (bench_instance/roofline_shapes "
                  "methods); register them with sdfcodec.plugin.register_bench instead", DeprecationWarning,
                  stacklevel=3)
    return BenchSpec(inst if callable(inst) else None,
                     (lambda codec, op: codec.roofline_shapes(op)) if callable(shapes) else None)


def _spec(cls: type[Codec]) -> BenchSpec | None:
    for klass in cls.__mro__:
        if klass in _BENCH:
            return _BENCH[klass]
    return _BENCH.get(getattr(cls, "codec_id", None)) or _legacy_spec(cls)


def bench_instance(codec_id: str, code_size: int, **options: Any) -> tuple[Codec, str | None]:
    """A ready codec ``codec_id`` for timing at nominal ``code_size``, and where its weights come from (None
    when not registered: then ``get_codec(codec_id, code_size=k)``, fitted on 512 analytic blocks when it
    ``requires_fit``; ``options`` are then unused). See :func:`register_bench`."""
    from ..testing import analytic_blocks

    cls = get_codec_class(codec_id)
    spec = _spec(cls)
    if spec is not None and spec.instance is not None:
        params = inspect.signature(spec.instance).parameters.values()
        takes_all = any(p.kind is p.VAR_KEYWORD for p in params)
        names = {p.name for p in params}
        codec, weights = spec.instance(code_size, **{k: v for k, v in options.items() if takes_all or k in names})
        return codec, str(weights)
    takes_size = "code_size" in inspect.signature(cls.__init__).parameters
    codec = get_codec(codec_id, code_size=code_size) if takes_size else get_codec(codec_id)
    if codec.requires_fit:
        codec.fit(analytic_blocks(512, seed=3))
    return codec, None


def memcpy_fn(nbytes: int = 64 << 20) -> Callable[[], object]:
    """One ``np.copyto`` of ``nbytes`` between two preallocated buffers (both touched first, so page faults
    are not timed): the memory-copy roofline."""
    src = np.ones(max(1, nbytes // 4), np.float32)
    dst = np.zeros_like(src)
    return lambda: np.copyto(dst, src)


def memcpy_bytes_per_s(nbytes: int = 64 << 20, min_time: float = 0.2) -> float:
    """Memory-copy bandwidth of this machine, now: bytes/s of :func:`memcpy_fn` (best of 3 rounds)."""
    return (max(1, nbytes // 4) * 4) / time_call(memcpy_fn(nbytes), min_time)


def roofline_shapes(codec: Codec, operation: str) -> list[tuple[int, int]]:
    """The ``(m, n)`` right-hand shapes of the matrix products ``operation`` needs: those registered for the
    codec (:func:`register_bench`), else the single product of a linear codec."""
    if operation not in _OPS:
        raise InvalidValueError(f"operation must be one of {', '.join(map(repr, _OPS))}, got {operation!r}")
    k = codec.code_size
    if operation in ("encode-weighted", "encode-masked"):  # what an exact weighted fit of k numbers needs
        return [(_N, k), (_N, k * (k + 1) // 2), (_N, k)]
    spec = _spec(type(codec))
    if spec is not None and spec.roofline_shapes is not None:
        shapes = [(int(m), int(n)) for m, n in spec.roofline_shapes(codec, operation)]
        if not shapes or any(m < 1 or n < 1 for m, n in shapes):
            raise InvalidValueError(f"roofline_shapes({codec!r}, {operation!r}) must be a non-empty list of "
                                    f"positive (m, n) shapes, got {shapes}")
        return shapes
    return [(_N, k)] if operation == "encode" else [(k, _N)]


def roofline_fn(shapes: list[tuple[int, int]], batch: int) -> Callable[[], object]:
    """The chain of products ``(batch, m) @ (m, n)`` for each of ``shapes``, each into a preallocated output
    (``np.matmul(..., out=)``): the matrix-product roofline."""
    rng = np.random.default_rng(0)
    mats = [rng.standard_normal(s, dtype=np.float32) for s in shapes]
    lhs = [rng.standard_normal((batch, s[0]), dtype=np.float32) for s in shapes]
    outs = [np.ones((batch, s[1]), np.float32) for s in shapes]  # ones: touched, so no page fault is timed

    def run() -> None:
        for a, m, o in zip(lhs, mats, outs):
            np.matmul(a, m, out=o)
    return run


def timed_record(t: Timing, base: Timing, blocks: int, **fields: Any) -> dict[str, Any]:
    """The timing fields of a record for ``blocks`` blocks per call: ``blocks_per_s`` and
    ``baseline_blocks_per_s`` (medians), ``ratio_to_baseline`` (ratio of medians), their bests and
    ``ratio_of_bests``, ``ratio_paired`` and ``ratio_cpu`` (:func:`~sdfcodec.bench.harness.ratio`),
    ``us_per_block`` (median) with the paper comparison, ``repeats``, and ``timed_threads: 1`` where the calls
    were short enough to be timed on one thread (:func:`~sdfcodec.bench.harness.interleave`)."""
    us = 1e6 * t.median / blocks
    return {**fields, "blocks_per_s": blocks / t.median, "baseline_blocks_per_s": blocks / base.median,
            "ratio_to_baseline": base.median / t.median, "us_per_block": us, **vs_paper(us),
            "blocks_per_s_best": blocks / t.best, "baseline_blocks_per_s_best": blocks / base.best,
            **{k: v for k, v in ratio(t, base).items() if k != "ratio_of_medians"}, "repeats": len(t.rounds),
            **({"timed_threads": 1} if t.threads == 1 else {})}


def fused_style_weights(v: np.ndarray, voxel_size: float = 0.02) -> np.ndarray:
    """The error weights ``(N, 16, 16, 16)`` float32 a fused map gives normalised exact blocks ``v`` (default
    truncation): voxels clipped to ``d_min`` (more than ``|d_min|`` behind a surface) unobserved, as a camera
    leaves them, the rest weighted as :func:`sdfcodec.map.observed.error_weights` weights them."""
    from ..map.observed import error_weights

    return error_weights(v, v > 0, (-0.04, 0.1), voxel_size)


def _has_hooks(codec: Codec) -> bool:
    return _spec(type(codec)) is not None


def bench_codec_instance(codec: Codec, batches: Iterable[int], *, device: str = "cpu", min_time: float = 0.2,
                         weights: str | None = None, name: str | None = None,
                         progress: Callable[[str], None] | None = None, repeats: int = 5) -> list[dict]:
    """Encode/decode blocks/s of a ready ``codec`` at each batch size, beside the numpy roofline of its layer
    shapes (:func:`roofline_shapes`), interleaved with it in ``repeats`` rounds. Returns records as
    :func:`bench_codec`'s; ``weights`` (where the codec's weights come from) is recorded when given."""
    from ..map.observed import encode_truncated
    from ..testing import analytic_blocks

    data = analytic_blocks(512, seed=3)
    dev = torch.device(device)
    sync = torch.cuda.synchronize if dev.type == "cuda" else (lambda: None)
    name = name or codec.codec_id
    extra = _has_hooks(codec) or weights is not None
    records = []
    for b in batches:
        x = torch.from_numpy(np.concatenate([data] * -(-b // len(data)))[:b]).to(dev)
        codes = codec.encode(x)
        ops = [("encode", lambda: (codec.encode(x), sync())), ("decode", lambda: (codec.decode(codes), sync()))]
        if _times_weighted(codec):
            w = torch.from_numpy(fused_style_weights(x.cpu().numpy())).to(dev)
            ops.append(("encode-weighted", lambda: (codec.encode(x, weights=w), sync())))
            # what a map writer runs on a fused block: the weighted fit refitted for the reader's truncation
            ops.append(("encode-masked", lambda: (encode_truncated(codec, x, w), sync())))
        plain = ops[0][1]
        for op, fn in ops:
            if progress:
                progress(f"{name}-{codec.code_size} {op} batch {b}")
            shapes = roofline_shapes(codec, op)
            load0 = load()
            # a weighted encode is timed beside the plain one in the same rounds: its ratio_to_encode pairs them
            # round by round (the plain encode's own figure, minutes earlier, ran under another load)
            also = {"encode": plain} if op in ("encode-weighted", "encode-masked") else {}
            tm = interleave({"candidate": fn, "baseline": roofline_fn(shapes, b), **also}, repeats=repeats,
                            min_time=min_time)
            rec = timed_record(tm["candidate"], tm["baseline"], b, codec=name, code_size=codec.code_size,
                               operation=op, batch=b, device=str(dev),
                               baseline="numpy matmul of the layer shapes" if extra else "numpy matmul")
            rec.update(load_before=load0, load_after=load())
            if op in ("encode-weighted", "encode-masked"):
                rec.update(ratio_to_encode=paired(tm["candidate"], tm["encode"]),
                           encode_blocks_per_s=b / tm["encode"].median, roofline_shapes=[list(s) for s in shapes],
                           baseline="numpy matmuls of an exact weighted least-squares fit")
            if extra:
                rec.update(roofline_shapes=[list(s) for s in shapes], weights=weights,
                           torch_threads=torch.get_num_threads())
            records.append(rec)
    return records


def _times_weighted(codec: Codec) -> bool:
    """Whether :func:`bench_codec_instance` times the weighted encodes of ``codec`` (``encode-weighted``,
    ``encode-masked``) beside the plain encode and decode."""
    return uses_weights(codec) and 4 * _N * codec.code_size * (codec.code_size + 1) // 2 <= _MAX_GRAM_TABLE_BYTES


def bench_steps(codec_id: str, code_sizes: Iterable[int], batches: Iterable[int], *, read_blocks: int = 0,
                http: bool = False) -> int:
    """How many times :func:`bench_codec` with these arguments calls its ``progress``: one per timed operation
    and batch, and per code size with ``read_blocks`` one for decode on read, one over HTTP, one for decoding into
    place (a progress bar counted from it stays true to the end)."""
    nb = len(list(batches))
    steps = 0
    for k in code_sizes:
        codec, _ = bench_instance(codec_id, k)
        steps += nb * (4 if _times_weighted(codec) else 2) + (2 + bool(http) if read_blocks > 0 else 0)
    return steps


def bench_codec(codec_id: str, code_sizes: Iterable[int], batches: Iterable[int], *, device: str = "cpu",
                min_time: float = 0.2, progress: Callable[[str], None] | None = None,
                read_blocks: int = 0, http: bool = False, repeats: int = 5) -> list[dict]:
    """Encode/decode blocks/s of ``codec_id`` at each code size and batch, beside the numpy matmul roofline.

    Returns one record per (code_size, operation, batch) with ``codec``, ``code_size`` (the codec's actual
    code length), ``operation``, ``batch``, ``device``, ``blocks_per_s``, ``baseline``,
    ``baseline_blocks_per_s``, ``ratio_to_baseline`` and ``us_per_block`` (medians of ``repeats`` rounds
    interleaved with the baseline), ``blocks_per_s_best``, ``baseline_blocks_per_s_best``, ``ratio_of_bests``,
    ``repeats``, ``load_before`` and ``load_after``; registered codecs
    (:func:`register_bench`) add ``roofline_shapes``, ``weights`` and ``torch_threads``. With ``read_blocks > 0``,
    each code size also gets a ``"decode-on-read"`` record (:func:`bench_decode_on_read` over a map of that
    many blocks), and with ``http`` a ``"decode-on-read-http"`` one (the same map served on loopback).
    """
    records = []
    for k in code_sizes:
        codec, weights = bench_instance(codec_id, k)
        records += bench_codec_instance(codec, batches, device=device, min_time=min_time, weights=weights,
                                        name=codec_id, progress=progress, repeats=repeats)
        if read_blocks > 0:
            records += bench_decode_on_read(codec, read_blocks, device=device, min_time=min_time,
                                            name=codec_id, weights=weights, http=http, repeats=repeats,
                                            progress=progress)
            if progress:
                progress(f"{codec_id}-{codec.code_size} decoding {read_blocks} blocks into place")
            records += bench_decode_in_place(codec, read_blocks, device=device, name=codec_id, repeats=repeats)
    return records


def bench_decode_on_read(codec: Codec, n_blocks: int, *, device: str = "cpu", min_time: float = 0.2,
                         name: str | None = None, weights: str | None = None, prefetch: int = 2,
                         http: bool = False, repeats: int = 5, progress: Callable[[str], None] | None = None
                         ) -> list[dict]:
    """Decode on read: blocks/s of :meth:`sdfcodec.Map.iter_decoded` over a whole map of ``n_blocks`` coded
    blocks (codes read, checksummed, decompressed, decoded to float32 metres) from local disk, and with
    ``http`` also over HTTP from a server on loopback, beside four baselines interleaved with it: the numpy
    roofline of the decode's layer shapes (``baseline``), memory-copy bandwidth (``memcpy_blocks_per_s``, see
    the module docstring), the codec's own decode of the same codes already in memory on ``device``
    (``in_memory_decode_blocks_per_s``) and the copy of the codes to ``device`` (from pinned memory to a GPU;
    ``code_transfer_blocks_per_s``).

    The map (float32 codes, default chunking) is written to a temporary directory and removed afterwards.
    Returns one record per source, ``operation`` ``"decode-on-read"`` (local) or ``"decode-on-read-http"``,
    with ``batch=n_blocks``.
    """
    import shutil
    import tempfile
    from pathlib import Path

    from ..map import open_map

    if n_blocks < 1:
        raise InvalidValueError(f"n_blocks must be >= 1, got {n_blocks}")
    d_min, d_max = -0.04, 0.1
    tmp = Path(tempfile.mkdtemp(prefix="sdfcodec-bench-"))
    dev = None if device == "cpu" else torch.device(device)
    sync = torch.cuda.synchronize if dev is not None and dev.type == "cuda" else (lambda: None)
    timed: dict[str, dict[str, Timing]] = {}
    loads: dict[str, tuple[list[float], list[float]]] = {}
    try:
        write_bench_map(codec, n_blocks, tmp / "bench.sdfz", (d_min, d_max))
        with open_map(tmp / "bench.sdfz") as m:
            _, codes = m.read_codes()
        z = torch.from_numpy(codes).to(device)
        # the codes' transfer to the device (pinned host memory to the GPU; a host copy on the CPU), which no
        # decode on read into the device's memory avoids
        host = torch.from_numpy(codes).pin_memory() if z.device.type == "cuda" else torch.from_numpy(codes.copy())
        baselines = {"roofline": roofline_fn(roofline_shapes(codec, "decode"), n_blocks),
                     "memcpy": memcpy_fn(), "in-memory": lambda: (codec.decode(z), sync()),
                     "transfer": lambda: (z.copy_(host, non_blocking=True), sync())}
        sources = {"decode-on-read": str(tmp / "bench.sdfz")}
        with contextlib.ExitStack() as stack:
            if http:
                sources["decode-on-read-http"] = stack.enter_context(FileServer(tmp)).url("bench.sdfz")
            for op, where in sources.items():
                if progress:
                    progress(f"{name or codec.codec_id}-{codec.code_size} {op} {n_blocks} blocks")
                m = open_map(where)

                def read() -> None:
                    n = sum(len(c) for c, _ in m.iter_decoded(device=dev, prefetch=prefetch))
                    sync()
                    if n != n_blocks:  # the reader lost or invented blocks: the timing would be meaningless
                        raise InvalidValueError(f"decode on read yielded {n} blocks of the {n_blocks} written")

                load0 = load()
                timed[op] = interleave({"candidate": read, **baselines}, repeats=repeats, min_time=min_time)
                loads[op] = (load0, load())
                m.close()
        code_bytes = sum(f.stat().st_size for f in (tmp / "bench.sdfz" / "codes").rglob("*") if f.is_file())
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    copy_bytes = max(1, (64 << 20) // 4) * 4  # what memcpy_fn() copies per call
    records = []
    for op, tm in timed.items():
        copy_bps = copy_bytes / tm["memcpy"].median
        rec = timed_record(tm["candidate"], tm["roofline"], n_blocks, codec=name or codec.codec_id,
                           code_size=codec.code_size, operation=op, batch=n_blocks, device=str(device),
                           baseline="numpy matmul of the layer shapes")
        rec.update({
            "memcpy_bytes_per_s": copy_bps, "memcpy_blocks_per_s": copy_bps / _BLOCK_BYTES,
            # paired round by round, as ratio_paired (sdfcodec.bench.harness.paired): the copy moves copy_bytes a
            # call, the read decodes n_blocks blocks of _BLOCK_BYTES
            "ratio_to_memcpy": paired(tm["candidate"], tm["memcpy"]) * n_blocks * _BLOCK_BYTES / copy_bytes,
            "in_memory_decode_blocks_per_s": n_blocks / tm["in-memory"].median,
            "ratio_to_in_memory_decode": paired(tm["candidate"], tm["in-memory"]),
            "code_transfer_blocks_per_s": n_blocks / tm["transfer"].median,
            "code_bytes_on_disk": code_bytes, "prefetch": prefetch, "torch_threads": torch.get_num_threads(),
            "load_before": loads[op][0], "load_after": loads[op][1],
        })
        if weights is not None:
            rec["weights"] = weights
        records.append(rec)
    return records


def write_bench_map(codec: Codec, n_blocks: int, path: Any, truncation: tuple[float, float]) -> None:
    """A map of ``n_blocks`` coded blocks filling a cube of blocks in grid order (float32 codes, default chunking):
    the real codes of 512 analytic blocks, tiled (reading them is what is timed, not encoding)."""
    from ..map import create_map
    from ..testing import analytic_blocks

    side = int(np.ceil(n_blocks ** (1 / 3)))
    coords = np.stack(np.unravel_index(np.arange(n_blocks), (side, side, side)), axis=1)
    codes = np.asarray(codec.encode(analytic_blocks(512, seed=3)))
    with create_map(path, codec=codec, voxel_size=0.02, truncation=truncation) as m:
        for i in range(0, n_blocks, 16384):
            j = min(i + 16384, n_blocks)
            m.write_codes(coords[i:j], np.concatenate([codes] * -(-(j - i) // len(codes)))[: j - i])


def bench_decode_in_place(codec: Codec, n_blocks: int, *, device: str = "cpu", repeats: int = 5, batch: int = 4096,
                          name: str | None = None, min_time: float = 0.2) -> list[dict]:
    """Decoding into place beside the preallocated roofline, in interleaved rounds
    (:func:`~sdfcodec.bench.harness.interleave`):

    - ``"decode-on-read-into"``: :meth:`sdfcodec.Map.iter_decoded` ``(copy=False)`` of a whole map of
      ``n_blocks`` coded blocks (read, decompressed, decoded to metres into a ring of reused buffers), and
      ``"decode-on-read-fresh"`` the same with the default ``copy=True`` (a fresh array per group);
    - ``"decode-region"``: :meth:`sdfcodec.Map.decode_region` of the whole map (blocks placed into one fresh
      volume), and ``"decode-region-into"`` the same into one reused volume (``out=``: no page faults timed, as
      in the roofline);
    - ``"decode-into"``: the same codes in memory, ``codec.decode_core(codes, scale, offset, out=buf)`` in
      batches of ``batch`` into one reused buffer.

    The baseline is the codec's roofline, the product of its decode shapes for all ``n_blocks`` written into a
    preallocated output (``np.matmul(..., out=)``: no allocation or page faults timed). Records as
    :func:`timed_record`'s, with ``map_blocks`` and ``torch_threads``."""
    import shutil
    import tempfile
    from pathlib import Path

    from ..map import open_map

    d_min, d_max = -0.04, 0.1
    dev = None if device == "cpu" else torch.device(device)
    sync = torch.cuda.synchronize if dev is not None and dev.type == "cuda" else (lambda: None)
    tmp = Path(tempfile.mkdtemp(prefix="sdfcodec-bench-"))
    try:
        write_bench_map(codec, n_blocks, tmp / "bench.sdfz", (d_min, d_max))
        m = open_map(tmp / "bench.sdfz")
        _, codes = m.read_codes()
        z = torch.from_numpy(codes).to(device)
        buf = torch.empty((min(batch, n_blocks), _N), device=device)
        vol = m.decode_region(device=dev)  # touched once: the reused volume
        def read(copy: bool) -> None:
            for _ in m.iter_decoded(device=dev, copy=copy):
                pass
            sync()

        def in_memory() -> None:
            for i in range(0, n_blocks, batch):
                c = z[i:i + batch]
                codec.decode_core(c, scale=d_max - d_min, offset=d_min, out=buf[:len(c)])
            sync()

        cases = {"decode-on-read-into": lambda: read(False), "decode-on-read-fresh": lambda: read(True),
                 "decode-region": lambda: (m.decode_region(device=dev), sync()),
                 "decode-region-into": lambda: (m.decode_region(device=dev, out=vol), sync()), "decode-into": in_memory,
                 "roofline": roofline_fn(roofline_shapes(codec, "decode"), n_blocks)}
        load0 = load()
        timed = interleave(cases, repeats=repeats, min_time=min_time)
        load1 = load()
        m.close()
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    base = timed.pop("roofline")
    return [timed_record(t, base, n_blocks, codec=name or codec.codec_id, code_size=codec.code_size, operation=op,
                         batch=min(batch, n_blocks) if op == "decode-into" else n_blocks, device=str(device),
                         baseline="numpy matmul of the layer shapes into a preallocated output",
                         map_blocks=n_blocks, torch_threads=torch.get_num_threads(), load_before=load0,
                         load_after=load1)
            for op, t in timed.items()]
