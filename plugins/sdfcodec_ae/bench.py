"""Throughput of the ``ae``, ``parallel`` and ``sequential`` codecs beside their matrix-product roofline.

``sdfcodec bench --codec ae|parallel|sequential`` measures these codecs through what their plugins register
with the benchmark (:func:`sdfcodec.plugin.register_bench`; no codec id is special-cased anywhere): a ready
codec without training (the shipped weights where they exist: ae-64, parallel and sequential 64 + 64; else
untrained weights of the same shapes, since speed does not depend on the values) and the matrix products an
operation cannot avoid, timed as plain numpy in the same run:

=============================  ========================================================================
operation                      matrix products per batch of ``B`` blocks (``h`` hidden, ``d``/``k`` codes)
=============================  ========================================================================
ae encode                      ``(B,4096)(4096,h)``, ``(B,h)(h,d)``
ae decode                      ``(B,d)(d,h)``, ``(B,h)(h,4096)``
parallel encode, per-block w   PCA ``(B,4096)(4096,k)`` + ae encode + PCA ``(B,k)(k,4096)`` + ae decode
parallel encode, fixed w       PCA ``(B,4096)(4096,k)`` + ae encode
sequential encode, per-block   PCA encode + PCA decode (the residual) + ae encode + ae decode
sequential encode, fixed w     PCA encode + PCA decode + ae encode
parallel/sequential decode     PCA ``(B,k)(k,4096)`` + ae decode
=============================  ========================================================================

A ratio near 1 means the codec adds little beyond those products (activations, the weight search, the
element-wise mix). :func:`bench_records` is the Python entry point used by ``examples/eval_codecs.py``.
"""

from __future__ import annotations

from typing import Any, Callable, Iterable

from sdfcodec import Codec
from sdfcodec.errors import SDFCodecError
from sdfcodec.plugin import bench_codec_instance, bench_instance, roofline_shapes

from .network import N_VOXELS

__all__ = ["bench_records", "bench_codec_instance", "roofline_shapes", "ae_roofline_shapes", "random_ae",
           "ae_bench_instance", "UNTRAINED"]

UNTRAINED = "untrained (random init; speed does not depend on the values)"


def ae_roofline_shapes(code_size: int, hidden: int, operation: str) -> list[tuple[int, int]]:
    """Right-hand shapes of the ae's matrix products: encode ``(4096, h), (h, d)``; decode ``(d, h), (h, 4096)``."""
    if operation == "encode":
        return [(N_VOXELS, hidden), (hidden, code_size)]
    return [(code_size, hidden), (hidden, N_VOXELS)]


def random_ae(code_size: int, hidden: int = 512, output: str = "sigmoid", seed: int = 0) -> Codec:
    """An ``ae`` codec with its initial (untrained) weights, deterministic by ``seed``
    (:meth:`sdfcodec_ae.AECodec.untrained`)."""
    from . import AECodec

    return AECodec.untrained(code_size, hidden, output, seed)


def ae_bench_instance(code_size: int) -> tuple[Codec, str]:
    """The shipped AE-64 for ``code_size=64`` (when installed), else an untrained paper-sized network."""
    if code_size == 64:
        try:
            from . import default_ae

            return default_ae(64), "shipped sdfcodec_ae/models/ae-64.npz"
        except SDFCodecError:
            pass
    return random_ae(code_size), UNTRAINED


def bench_records(codec_id: str, code_size: int, batches: Iterable[int], *, device: str = "cpu",
                  weight: str | float = "block", min_time: float = 0.2,
                  progress: Callable[[str], None] | None = None, **options: Any) -> list[dict]:
    """Benchmark records for ``ae-<code_size>`` or ``parallel``/``sequential`` ``<code_size> + <code_size>``
    (or any codec, built by :func:`sdfcodec.bench.bench_instance`).

    Parameters
    ----------
    codec_id : str
        e.g. ``"ae"``, ``"parallel"``, ``"sequential"``.
    code_size : int
        Nominal code size: the AE's; for the mixtures, the size of each part (64: the shipped 64 + 64).
    batches : iterable of int
        Batch sizes (blocks per call).
    device : str
        Torch device of the blocks and codes.
    weight : "block" or float
        Mixing weight mode of the mixtures (an option their benchmark instance takes; ``ae`` takes none).
    **options
        Further options for the codec's benchmark instance (:func:`sdfcodec.plugin.register_bench`).

    Returns
    -------
    list of dict
        As :func:`sdfcodec.bench.bench_codec`: one record per (operation, batch) with ``codec``, ``code_size``,
        ``operation``, ``batch``, ``device``, ``blocks_per_s``, ``baseline`` (``"numpy matmul of the layer
        shapes"``), ``baseline_blocks_per_s``, ``ratio_to_baseline``, ``us_per_block``, ``roofline_shapes``,
        ``weights`` (where the weights come from) and ``torch_threads``.
    """
    codec, weights = bench_instance(codec_id, code_size, weight=weight, **options)
    return bench_codec_instance(codec, batches, device=device, min_time=min_time, weights=weights, name=codec_id,
                                progress=progress)
