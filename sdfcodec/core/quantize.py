"""8-bit code storage: affine quantisation of code vectors (the map extension ``int8-codes``, spec section 4a).

Per block (what maps store): each code vector ``z`` (length ``k``) gets its own ``offset = (max z + min z) / 2``
and ``scale = (max z - min z) / 254``, both float32, and ``q = round((z - offset) / scale)`` in ``[-127, 127]``
(``q = 0`` when ``scale == 0``); it decodes as ``z' = offset + scale * q``, so ``|z' - z| <= scale / 2`` (plus
float32 rounding). Per component (``per="component"``, used by the rate-distortion study) does the same along
each code element over all blocks, giving one ``(offset, scale)`` pair per element.

The float32 parameters are rounded *before* ``q`` is computed, so the bound holds for what is stored.

Per map (the extension ``quantised-codes``, spec section 4b): one step ``step_j > 0`` (and offset ``offset_j``)
per code element for the whole map, ``q = rint((z - offset_j) / step_j)`` stored as int16 and entropy-coded by
the array's compressor (Blosc zstd with bit shuffle); it decodes as ``z' = offset_j + step_j * q``, so
``|z' - z| <= step_j / 2`` (plus float32 rounding of ``z'``). :func:`check_step` validates a requested step,
:func:`check_quantisable` the codec, and :func:`fit_rate_model` / :func:`step_for_bytes` choose the step that
gives a byte budget (``sdfcodec encode --target-bytes``).
"""

from __future__ import annotations

from typing import Any, Callable, Sequence

import numpy as np

from ..errors import InvalidValueError, ShapeError

__all__ = ["quantize_codes", "dequantize_codes", "QMAX", "QMAX16", "check_step", "check_quantisable",
           "quantise_step", "dequantise_step", "RateModel", "fit_rate_model", "step_for_bytes",
           "UNIFORM_STEP_CODECS"]

#: Largest stored magnitude: ``q`` lies in ``[-QMAX, QMAX]`` (-128 is never written).
QMAX = 127
#: Largest stored magnitude of int16 codes (-32768 is never written, as -128 for int8).
QMAX16 = 32767
#: Codecs whose codes one step per element quantises soundly: their codes are coordinates of the normalised
#: block in an orthonormal basis (pca) or the voxels themselves (raw, gaussian-blur), so a code error of
#: ``e`` is a field error of ``e`` (rms) and a uniform step spreads it evenly. A plugin codec opts in with the
#: class attribute ``uniform_step_codes = True``. Codes of a nonlinear decoder (ae, the mixtures: their last
#: element is a blend weight) have per-element scales a single step does not know: those use int8 codes.
UNIFORM_STEP_CODECS = frozenset({"pca", "raw", "gaussian-blur"})


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


def check_quantisable(codec: Any) -> None:
    """Refuse a codec whose codes one step per element does not quantise soundly (:data:`UNIFORM_STEP_CODECS`)."""
    cid = getattr(codec, "codec_id", None)
    if cid in UNIFORM_STEP_CODECS or getattr(codec, "uniform_step_codes", False) is True:
        return
    raise InvalidValueError(f"codec {cid!r} cannot store step-quantised (int16) codes: its codes are not "
                            "coordinates in an orthonormal basis of the block, so one step per element has no "
                            f"meaning for its error (codecs that can: {', '.join(sorted(UNIFORM_STEP_CODECS))}); "
                            "use --code-dtype int8 (per-block scale) or float16 instead")


def check_step(step: Any, size: int, what: str = "step") -> np.ndarray:
    """A requested step: one number (uniform over the ``size`` code elements) or ``size`` numbers, each finite
    and > 0, as float64 ``(size,)``."""
    try:
        s = np.asarray(step, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise InvalidValueError(f"{what} must be a positive number (or one per code element), got {step!r}") from e
    if s.ndim == 0:
        s = np.full(size, float(s))
    if s.shape != (size,):
        raise ShapeError(f"{what} must be one number or {size} (one per code element), got shape {s.shape}")
    bad = ~(np.isfinite(s) & (s > 0))
    if bad.any():
        j = int(np.flatnonzero(bad)[0])
        raise InvalidValueError(f"{what} must be finite and > 0 (a step of 0 stores nothing, NaN no number); "
                                f"got {float(s[j])!r}" + (f" for code element {j}" if np.ndim(step) else ""))
    return s


def quantise_step(codes: np.ndarray, step: Sequence[float], offset: Sequence[float]) -> np.ndarray:
    """``rint((codes - offset) / step)`` as int16 ``(N, k)``; codes beyond ``QMAX16`` steps are refused with the
    smallest step that would hold them (clipping would break the ``step / 2`` bound silently)."""
    z = np.asarray(codes)
    st, off = np.asarray(step, np.float64), np.asarray(offset, np.float64)
    if z.ndim != 2 or z.shape[1] != len(st):
        raise ShapeError(f"codes must have shape (N, {len(st)}), got {z.shape}")
    # in place on one float64 copy: this runs on every chunk written, and temporaries cost more than the math
    q = np.subtract(z, off, dtype=np.float64)
    q /= st
    np.rint(q, out=q)
    if q.size and not max(q.max(), -q.min()) <= QMAX16:  # also catches NaN/Inf (they compare False)
        z = np.asarray(z, dtype=np.float64)
        if not np.isfinite(z).all():
            raise InvalidValueError("codes hold NaN/Inf values; they cannot be quantised")
        j = int(np.argmax(np.abs(q).max(axis=0)))
        need = float(np.abs(z[:, j] - off[j]).max()) / (QMAX16 - 0.5)
        raise InvalidValueError(f"code element {j} reaches {float(np.abs(z[:, j] - off[j]).max()):.6g} from its "
                                f"offset, beyond {QMAX16} steps of {st[j]:.6g}: use a step of at least {need:.6g} "
                                "(int16 codes hold +-32767 steps)")
    return q.astype(np.int16)


def dequantise_step(q: np.ndarray, step: Sequence[float], offset: Sequence[float]) -> np.ndarray:
    """``offset + step * q`` as float32 ``(N, L)`` (computed in float64): the first ``L`` steps and offsets serve a
    prefix ``q[:, :L]``, so a prefix level dequantises alone."""
    q = np.asarray(q)
    n = q.shape[1]
    st, off = np.asarray(step, np.float64)[:n], np.asarray(offset, np.float64)[:n]
    out = np.multiply(q, st, dtype=np.float64)
    out += off
    return out.astype(np.float32)


class RateModel:
    """Compressed bytes of a map's codes per coded block as a function of the step (one uniform step, or a
    fixed shape ``step = s * shape``), measured on a sample: ``points`` are ``(s, bytes)`` pairs from
    compressing the sample's quantised codes as the map's chunks would be, interpolated in log-log (bytes fall
    about ``k`` bits per halving of ``s`` while codes are finely quantised, then flatten at the all-zero
    floor). ``floor``: the bytes when every code quantises to 0 (the least the codes can take)."""

    def __init__(self, points: list[tuple[float, float]], floor: float):
        self.points = sorted(points)
        self.floor = floor

    def bytes_at(self, s: float) -> float:
        xs = np.log([p[0] for p in self.points])
        ys = np.log([p[1] for p in self.points])
        return float(np.exp(np.interp(np.log(s), xs, ys)))

    def step_for(self, codes_bytes: float) -> float:
        """The (log-log interpolated) step whose codes take ``codes_bytes`` per block; extrapolated along the end
        segments beyond the measured steps."""
        xs = np.log([p[0] for p in self.points])
        ys = np.log([p[1] for p in self.points])
        y = np.log(codes_bytes)
        order = np.argsort(ys)  # bytes fall as the step grows
        ys_o, xs_o = ys[order], xs[order]
        if y <= ys_o[0] or y >= ys_o[-1]:
            i = (0, 1) if y <= ys_o[0] else (-2, -1)
            slope = (xs_o[i[1]] - xs_o[i[0]]) / (ys_o[i[1]] - ys_o[i[0]] or 1e-12)
            return float(np.exp(xs_o[i[0]] + slope * (y - ys_o[i[0]])))
        return float(np.exp(np.interp(y, ys_o, xs_o)))


def fit_rate_model(codes: np.ndarray, compress: Callable[[np.ndarray], int], shape: np.ndarray | None = None,
                   steps: Sequence[float] | None = None) -> RateModel:
    """Measure :class:`RateModel` on sample ``codes`` ``(n, k)``: ``compress(q)`` gives the stored bytes of
    int16 codes ``q`` ``(n, k)`` laid out as the map would store them; ``shape`` (default ones) scales the step
    per element (``step_j = s * shape_j``); ``steps`` the uniform scales measured (default: 2^-8 .. 2^3)."""
    z = np.asarray(codes, dtype=np.float64)
    if not len(z):
        raise InvalidValueError("no coded blocks to fit a rate model on")
    shp = np.ones(z.shape[1]) if shape is None else np.asarray(shape, np.float64)
    span = float(np.abs(z).max() / shp.min()) if z.size else 1.0
    lo = max(span / (QMAX16 - 1), 1e-12)
    grid = sorted({lo, *(s for s in (steps if steps is not None else 2.0 ** np.arange(-10, 3.5, 0.5)) if s > lo)})
    points = [(float(s), compress(np.rint(z / (s * shp)).astype(np.int16)) / len(z)) for s in grid]
    floor = compress(np.zeros(z.shape, np.int16)) / len(z)
    return RateModel(points, floor)


def step_for_bytes(model: RateModel, codes_bytes: float, other_bytes: float = 0.0) -> float:
    """The step whose codes take ``codes_bytes`` per block by ``model``; raises when that is below the floor
    (all codes 0), naming the smallest reachable total (``floor + other_bytes``: what the mask, weights and
    states take on top), or above what the finest step int16 codes hold gives (naming the largest)."""
    if not codes_bytes > model.floor * 1.02:
        raise InvalidValueError(f"a target of {codes_bytes + other_bytes:.1f} bytes per coded block is below what "
                                f"this codec can reach on this map: at least {model.floor + other_bytes:.1f} "
                                f"(codes {model.floor:.1f} when every code quantises to 0, plus "
                                f"{other_bytes:.1f} of observation mask, weights, block states and metadata)")
    finest = model.points[0]
    if codes_bytes > finest[1]:
        raise InvalidValueError(f"a target of {codes_bytes + other_bytes:.1f} bytes per coded block is above what "
                                f"int16 codes take on this map: at most {finest[1] + other_bytes:.1f} (at their "
                                f"finest step {finest[0]:.4g}, +-{QMAX16} steps); store float32 codes instead")
    return model.step_for(codes_bytes)
