"""8-bit code storage: affine quantisation of code vectors (the map extension ``int8-codes``, spec section 4a).

Per block (what maps store): each code vector ``z`` (length ``k``) gets its own ``offset = (max z + min z) / 2``
and ``scale = (max z - min z) / 254``, both float32, and ``q = round((z - offset) / scale)`` in ``[-127, 127]``
(``q = 0`` when ``scale == 0``); it decodes as ``z' = offset + scale * q``, so ``|z' - z| <= scale / 2`` (plus
float32 rounding). Per component (``per="component"``, used by the rate-distortion study) does the same along
each code element over all blocks, giving one ``(offset, scale)`` pair per element.

The float32 parameters are rounded *before* ``q`` is computed, so the bound holds for what is stored.
"""

from __future__ import annotations

import numpy as np

from .errors import InvalidValueError, ShapeError

__all__ = ["quantize_codes", "dequantize_codes", "QMAX"]

#: Largest stored magnitude: ``q`` lies in ``[-QMAX, QMAX]`` (-128 is never written).
QMAX = 127


def _axis(per: str) -> int:
    if per not in ("block", "component"):
        raise InvalidValueError(f"per must be 'block' or 'component', got {per!r}")
    return 1 if per == "block" else 0


def quantize_codes(codes: np.ndarray, per: str = "block") -> tuple[np.ndarray, np.ndarray]:
    """Quantise finite codes ``(N, k)`` to ``(q (N, k) int8, params)``.

    ``params`` is float32 ``(N, 2)`` (``[offset, scale]`` per block) for ``per="block"``, or ``(2, k)`` (offset row,
    scale row) for ``per="component"``."""
    z = np.asarray(codes, dtype=np.float64)
    if z.ndim != 2:
        raise ShapeError(f"codes must have shape (N, k), got {z.shape}")
    axis = _axis(per)
    if not np.isfinite(z).all():
        raise InvalidValueError("codes hold NaN/Inf values; they cannot be quantised")
    if z.size == 0:
        shape = (len(z), 2) if axis == 1 else (2, z.shape[1])
        return np.zeros(z.shape, np.int8), np.zeros(shape, np.float32)
    hi, lo = z.max(axis=axis, keepdims=True), z.min(axis=axis, keepdims=True)
    offset = ((hi + lo) / 2).astype(np.float32)
    scale = ((hi - lo) / (2 * QMAX)).astype(np.float32)
    with np.errstate(divide="ignore", invalid="ignore"):
        q = np.where(scale > 0, np.rint((z - offset) / np.where(scale > 0, scale, 1.0)), 0.0)
    q = np.clip(q, -QMAX, QMAX).astype(np.int8)
    params = np.concatenate([offset, scale], axis=axis)
    return q, params


def dequantize_codes(q: np.ndarray, params: np.ndarray, per: str = "block") -> np.ndarray:
    """``offset + scale * q`` as float32 ``(N, k)``; ``params`` as :func:`quantize_codes` gives them. A prefix of
    the code elements (``q[:, :L]`` with ``params[:, :L]`` per component) dequantises alone."""
    q = np.asarray(q)
    params = np.asarray(params, dtype=np.float32)
    if _axis(per) == 1:
        if params.shape != (len(q), 2):
            raise ShapeError(f"per-block params must have shape ({len(q)}, 2), got {params.shape}")
        offset, scale = params[:, :1], params[:, 1:]
    else:
        if params.shape != (2, q.shape[1]):
            raise ShapeError(f"per-component params must have shape (2, {q.shape[1]}), got {params.shape}")
        offset, scale = params[:1], params[1:]
    return offset + scale * q.astype(np.float32)
