"""Rate control of step-quantised (int16) codes: the step that makes a map take a given number of stored bytes
per coded block (``sdfcodec encode --target-bytes``).

"Stored bytes per coded block" counts every file of the map but its codec state (``codec/``): the codes, the
observation mask, fusion weights, the residual stage (``--max-error``/``--sign-exact``), block states and the Zarr
metadata, divided by the coded blocks. Two parts:

* the codes, which fall with the step: :func:`codes_rate_model` measures them on a sample of the map's codes,
  compressed as the ``codes`` array's chunks would be (:func:`~sdfcodec.map.format.code_compressors`);
* everything else, which does not depend on the step: estimated from the sample's observation masks before
  the write (:func:`mask_bytes_estimate`) and measured on the written map (:func:`stored_bytes`).

:func:`plan_step` picks the first step; :func:`correct_step` the one correction once the map is written and
measured (only when it missed by more than :data:`TOLERANCE`).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numcodecs
import numpy as np

from ..errors import InvalidValueError
from ..core.quantize import RateModel, fit_rate_model, step_for_bytes
from .format import QUANT_CLEVEL
from .observed import MASK_ARRAY
from .residual import RESIDUAL_ARRAY
from .varread import STREAM_ARRAY

__all__ = ["TOLERANCE", "SAMPLE_BLOCKS", "codes_rate_model", "mask_bytes_estimate", "stored_bytes", "plan_step",
           "correct_step", "check_target", "metadata_bytes_estimate"]

#: A written map off its target by more than this fraction is rewritten once with a corrected step.
TOLERANCE = 0.05
#: Coded blocks sampled for the rate model.
SAMPLE_BLOCKS = 4096


def check_target(target: Any) -> float:
    """``--target-bytes``: a finite number > 0."""
    try:
        t = float(target)
    except (TypeError, ValueError) as e:
        raise InvalidValueError(f"target bytes per coded block must be a number, got {target!r}") from e
    if not (np.isfinite(t) and t > 0):
        raise InvalidValueError(f"target bytes per coded block must be finite and > 0, got {target!r}")
    return t


def _blosc_bytes(rows: np.ndarray, chunk_rows: int, codec: numcodecs.abc.Codec) -> int:
    """Compressed bytes of ``rows`` cut into chunks of ``chunk_rows`` rows, each compressed alone (+4: CRC32C)."""
    return sum(len(codec.encode(np.ascontiguousarray(rows[i:i + chunk_rows]))) + 4
               for i in range(0, len(rows), chunk_rows))


def codes_rate_model(codes: np.ndarray, chunk_code: int, chunk_blocks: int) -> RateModel:
    """:class:`~sdfcodec.core.quantize.RateModel` of sample codes ``(n, k)`` stored as int16 in chunks of
    ``chunk_blocks`` ^ 3 blocks by ``chunk_code`` elements (the sample's blocks packed densely: a sparse map's
    chunks hold zeros between coded blocks too, which bit shuffle and zstd store almost for free)."""
    blosc = numcodecs.Blosc("zstd", QUANT_CLEVEL, numcodecs.Blosc.BITSHUFFLE)
    per_chunk = max(1, chunk_blocks ** 3)

    def compress(q: np.ndarray) -> int:
        return sum(_blosc_bytes(q[:, j:j + chunk_code], per_chunk, blosc) for j in range(0, q.shape[1], chunk_code))

    return fit_rate_model(codes, compress)


def mask_bytes_estimate(packed: np.ndarray | None, chunk_blocks: int, compressor: Any) -> float:
    """Bytes per coded block of the observation mask: the sample's packed masks ``(n, 512)`` uint8 compressed with
    the mask array's ``compressor`` (a Zarr Blosc codec) in chunks of ``chunk_blocks`` ^ 3 blocks; 0 without a
    mask."""
    if packed is None or not len(packed):
        return 0.0
    c = numcodecs.Blosc(compressor.cname.value, compressor.clevel, int(compressor.shuffle.value != "noshuffle"))
    return _blosc_bytes(packed, max(1, chunk_blocks ** 3), c) / len(packed)


def metadata_bytes_estimate(code_size: int) -> float:
    """Bytes of a map's Zarr metadata documents (header and array documents), counted with the map: about 6 KB
    (the kitchen's pca-64 map: 8.9 KB, of it 4.9 KB header) plus the header's step and offset (two JSON numbers
    of ~20 characters per code element)."""
    return 6000.0 + 44.0 * code_size


def stored_bytes(path: str | os.PathLike) -> dict[str, float]:
    """Per coded block of the written map at ``path``: ``total`` (every file but ``codec/``), ``codes`` (the
    ``codes`` array's files), ``mask`` (``observed``, or a pinned mask's ``mask_streams``), ``residual`` (the residual stage of ``--max-error`` /
    ``--sign-exact``, spec 6d; in ``total`` and ``other`` too), ``refinement`` (``refine_streams``, spec 6h; in
    ``total`` and ``other`` too) and ``other`` (``total - codes``)."""
    from .facade import open_map

    root = Path(path)
    with open_map(root) as m:
        n = max(1, m.count_states()["coded"])

    def size(sub: str) -> int:
        p = root / sub
        return sum(f.stat().st_size for f in p.rglob("*") if f.is_file()) if p.is_dir() else 0

    total = size("") - size("codec")
    codes = size("codes") + size(STREAM_ARRAY)  # variable-rate codes live in their chunk streams (spec 4e)
    return {"total": total / n, "codes": codes / n, "mask": (size(MASK_ARRAY) + size("mask_streams")) / n, "residual": size(RESIDUAL_ARRAY) / n,
            "refinement": size("refine_streams") / n, "other": (total - codes) / n}


def plan_step(target: float, model: RateModel, other: float) -> float:
    """The first step: the model's step for ``target - other`` bytes of codes (``other``: the estimate of the
    rest), refused (naming the least reachable) when that is below what codes can take."""
    return step_for_bytes(model, target - other, other)


def correct_step(target: float, model: RateModel, step: float, measured: dict[str, float]) -> float | None:
    """After writing at ``step`` and measuring (:func:`stored_bytes`): None when within :data:`TOLERANCE` of
    ``target``, else the corrected step (the model scaled to the measured codes, the measured rest)."""
    if abs(measured["total"] - target) <= TOLERANCE * target:
        return None
    ratio = measured["codes"] / model.bytes_at(step)
    scaled = RateModel([(s, b * ratio) for s, b in model.points], model.floor * ratio)
    return step_for_bytes(scaled, target - measured["other"], measured["other"])
