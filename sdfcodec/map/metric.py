"""Metric codes (spec/map-format.md, section 4f): a ``raw`` map whose codes are the voxels' own float32 metres.

Every other map stores what its codec encodes from the normalised block ``v = (d - d_min) / (d_max - d_min)``
and a reader returns ``d_min + v (d_max - d_min)``: two float32 roundings, so a lossless ``raw`` map returns its
input to about ``(d_max - d_min) x 2^-24`` m, not bit for bit. A map with metric codes stores the metres
themselves (the writer skips the normalisation, the reader the scaling back): what is written is what is read,
bit for bit, and its fusion weights are kept as float32 (``sdfcodec.map.weights``). ``sdfcodec import`` writes
such maps by default with the raw codec; ``create_map(exact=True)`` / ``sdfcodec encode --exact`` on request.

The codec still sees normalised blocks wherever it is asked for codes (``read_codes``, ``iter_codes``, search):
:func:`codec_codes` turns stored metres into them.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from ..errors import InvalidValueError
from ..core.header import CodesSpec

if TYPE_CHECKING:
    from ..codec import Codec

__all__ = ["is_metric", "check_metric", "metric_spec", "decode_affine", "codec_codes", "metric_empty"]


def is_metric(spec: CodesSpec) -> bool:
    """Whether codes of layout ``spec`` are metres (spec 4f)."""
    return spec.units == "metres"


def check_metric(codec: Codec, code_dtype: str, *, step: Any = None, residual: bool = False,
                 variable_rate: bool = False) -> None:
    """Refuse ``exact=True`` where metric codes are not defined: another codec than ``raw`` (its codes are not
    the voxels), codes other than float32 (float16 or integers would round the metres), a residual stage or
    variable-rate codes (both quantise)."""
    why = ("codec is " + repr(codec.codec_id) if codec.codec_id != "raw" else
           f"code_dtype is {code_dtype!r}" if code_dtype != "float32" else
           "a code step is given" if step is not None else
           "a residual stage is asked for (max_error/sign_exact)" if residual else
           "variable-rate codes are asked for" if variable_rate else None)
    if why is not None:
        raise InvalidValueError(f"exact storage (metric codes, bit-exact metres) needs the raw codec with float32 "
                                f"codes, but the {why}: drop exact (CLI: --exact) or use --codec raw")


def metric_spec(spec: CodesSpec) -> CodesSpec:
    """``spec`` with its codes in metres."""
    return spec.model_copy(update={"units": "metres"})


def decode_affine(spec: CodesSpec, truncation: tuple[float, float], metres: bool) -> tuple[float, float]:
    """``(scale, offset)`` a reader folds into the codec's decode to get metres (``metres``) or normalised
    values from the stored codes: ``(d_max - d_min, d_min)`` / ``(1, 0)`` for normalised codes, ``(1, 0)`` /
    ``(1 / (d_max - d_min), -d_min / (d_max - d_min))`` for metric ones."""
    d_min, d_max = truncation
    if not is_metric(spec):
        return (d_max - d_min, d_min) if metres else (1.0, 0.0)
    return (1.0, 0.0) if metres else (1.0 / (d_max - d_min), -d_min / (d_max - d_min))


def codec_codes(spec: CodesSpec, truncation: tuple[float, float], codes: np.ndarray) -> np.ndarray:
    """Stored codes ``(n, L)`` float32 as the codec encodes them: normalised (computed as the writer normalises,
    :func:`sdfcodec.core.blocks.normalise`) for metric codes, unchanged otherwise."""
    if not is_metric(spec):
        return codes
    d_min, d_max = truncation
    return ((codes - np.float32(d_min)) / np.float32(d_max - d_min)).astype(np.float32, copy=False)


def metric_empty(blocks_m: np.ndarray, d_max: float) -> np.ndarray:
    """``(N,)`` bool: which blocks ``(N, 16, 16, 16)`` of metres are free space exactly (every voxel equal to
    ``d_max`` in float32), the only blocks a metric map stores as ``empty``: they decode to ``d_max``, bit for
    bit (the normalised maps' tolerance of 1e-6 would change the values near it)."""
    return (blocks_m == np.float32(d_max)).reshape(len(blocks_m), -1).all(axis=1)
