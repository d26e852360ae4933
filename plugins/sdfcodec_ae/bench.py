"""Throughput of the ``ae``, ``parallel`` and ``sequential`` codecs beside their matrix-product roofline.

:func:`bench_records` returns records shaped like :func:`sdfcodec.bench.bench_codec`'s, so the ``sdfcodec
bench`` table prints them unchanged. The baseline ("roofline") of each operation is the chain of plain numpy
matrix products of the layer shapes that operation cannot avoid, timed in the same run:

============================  =====================================================================
operation                     matrix products per batch of ``B`` blocks (``h`` hidden, ``d`` code)
============================  =====================================================================
ae encode                     ``(B,4096)(4096,h)``, ``(B,h)(h,d)``
ae decode                     ``(B,d)(d,h)``, ``(B,h)(h,4096)``
parallel encode, per-block w  PCA ``(B,4096)(4096,k)`` and ``(B,k)(k,4096)`` + ae encode + ae decode
parallel encode, fixed w      PCA ``(B,4096)(4096,k)`` + ae encode
sequential encode             as parallel (the residual needs the PCA decode even for a fixed w)
parallel/sequential decode    PCA ``(B,k)(k,4096)`` + ae decode
============================  =====================================================================

A ratio near 1 means the codec adds little beyond those products (activations, the weight search, the
element-wise mix).
"""

from __future__ import annotations

from typing import Callable, Iterable

import numpy as np
import torch

import sdfcodec
from sdfcodec.bench import time_call
from sdfcodec.codec import Codec
from sdfcodec.errors import SDFCodecError
from sdfcodec.testing import analytic_blocks

from .network import N_VOXELS, build_module, export_state, module_state

__all__ = ["bench_records", "bench_codec_instance", "roofline_shapes"]


def _random_ae(code_size: int, hidden: int, output: str, seed: int = 0) -> Codec:
    """An AE with initial (untrained) weights: throughput does not depend on the values."""
    torch.manual_seed(seed)
    state = export_state(module_state(build_module(code_size, hidden, output)))
    return sdfcodec.get_codec("ae", code_size=code_size, hidden=hidden, output=output).load_state_dict(state)


def _codec(codec_id: str, code_size: int, weight: str | float) -> Codec:
    """The shipped model where there is one (ae-64, parallel/sequential 64 + 64), else random weights."""
    if codec_id == "ae":
        try:
            from . import default_ae

            return default_ae(code_size)
        except SDFCodecError:
            return _random_ae(code_size, 512, "sigmoid")
    if codec_id in ("parallel", "sequential"):
        if code_size == 64:
            try:
                import sdfcodec_mixed as mixed

                fn = mixed.default_parallel if codec_id == "parallel" else mixed.default_sequential
                return fn(weight=weight)
            except SDFCodecError:
                pass
        from sdfcodec.models import default_codec

        cls = type(sdfcodec.get_codec(codec_id))
        ae = _random_ae(code_size, 512, "sigmoid" if codec_id == "parallel" else "tanh")
        return cls.from_parts(default_codec("pca", code_size), ae, weight=weight)
    raise SDFCodecError(f"bench_records measures 'ae', 'parallel' and 'sequential', not {codec_id!r}")


def roofline_shapes(codec: Codec, operation: str) -> list[tuple[int, int]]:
    """``(in, out)`` right-hand matrix shapes of the products ``operation`` needs (see the module table)."""
    def ae_parts(ae: Codec) -> tuple[list, list]:
        d, h = ae.code_size, ae.hidden
        return [(N_VOXELS, h), (h, d)], [(d, h), (h, N_VOXELS)]

    if codec.codec_id == "ae":
        enc, dec = ae_parts(codec)
        return enc if operation == "encode" else dec
    enc, dec = ae_parts(codec.ae_)
    k = codec.pca_size
    if operation == "decode":
        return [(k, N_VOXELS)] + dec
    needs_decode = codec.per_block or codec.codec_id == "sequential"
    return [(N_VOXELS, k)] + enc + (([(k, N_VOXELS)] + dec) if needs_decode else [])


def _roofline_fn(shapes: list[tuple[int, int]], batch: int) -> Callable[[], object]:
    rng = np.random.default_rng(0)
    mats = [rng.standard_normal(s, dtype=np.float32) for s in shapes]
    lhs = [rng.standard_normal((batch, s[0]), dtype=np.float32) for s in shapes]

    def run() -> None:
        for a, m in zip(lhs, mats):
            a @ m
    return run


def bench_codec_instance(codec: Codec, batches: Iterable[int], *, device: str = "cpu", min_time: float = 0.2,
                         progress: Callable[[str], None] | None = None) -> list[dict]:
    """Encode/decode blocks/s of a fitted ``ae``/``parallel``/``sequential`` codec at each batch size, beside
    the numpy roofline of its layer shapes; records as :func:`sdfcodec.bench.bench_codec`'s plus
    ``roofline_shapes``."""
    train = analytic_blocks(512, seed=3)
    dev = torch.device(device)
    sync = torch.cuda.synchronize if dev.type == "cuda" else (lambda: None)
    name = codec.codec_id if codec.codec_id == "ae" else f"{codec.codec_id}"
    records = []
    for b in batches:
        x = torch.from_numpy(np.concatenate([train] * -(-b // len(train)))[:b]).to(dev)
        codes = codec.encode(x)
        for op, fn in (("encode", lambda: (codec.encode(x), sync())), ("decode", lambda: (codec.decode(codes), sync()))):
            if progress:
                progress(f"{name}-{codec.code_size} {op} batch {b}")
            shapes = roofline_shapes(codec, op)
            t = time_call(fn, min_time)
            tb = time_call(_roofline_fn(shapes, b), min_time)
            records.append({
                "codec": name, "code_size": codec.code_size, "operation": op, "batch": b, "device": str(dev),
                "blocks_per_s": b / t, "baseline": "numpy matmul of the layer shapes",
                "baseline_blocks_per_s": b / tb, "ratio_to_baseline": tb / t, "us_per_block": 1e6 * t / b,
                "roofline_shapes": [list(s) for s in shapes], "torch_threads": torch.get_num_threads(),
            })
    return records


def bench_records(codec_id: str, code_size: int, batches: Iterable[int], *, device: str = "cpu",
                  weight: str | float = "block", min_time: float = 0.2,
                  progress: Callable[[str], None] | None = None) -> list[dict]:
    """Benchmark records for ``ae-<code_size>`` or ``parallel``/``sequential`` ``<code_size> + <code_size>``.

    Parameters
    ----------
    codec_id : {"ae", "parallel", "sequential"}
    code_size : int
        AE code size; for the mixtures, the size of each part (64: the shipped 64 + 64).
    batches : iterable of int
        Batch sizes (blocks per call).
    device : str
        Torch device of the blocks and codes.
    weight : "block" or float
        Mixing weight mode of the mixtures (ignored by ``ae``).

    Returns
    -------
    list of dict
        One record per (operation, batch) with ``codec``, ``code_size``, ``operation``, ``batch``, ``device``,
        ``blocks_per_s``, ``baseline`` (``"numpy matmul of the layer shapes"``), ``baseline_blocks_per_s``,
        ``ratio_to_baseline``, ``us_per_block``, ``roofline_shapes``, ``torch_threads``. Shipped weights are
        used where they exist, else untrained weights of the same shapes (speed does not depend on values).
    """
    codec = _codec(codec_id, code_size, weight)
    return bench_codec_instance(codec, batches, device=device, min_time=min_time, progress=progress)
