"""Surface refinement of a linear decode (pure array functions; the map's stage is :mod:`sdfcodec.map.refine`,
spec/map-format.md section 6h).

A block's exact integer decode ``v`` (metres times ``2^S``, :func:`sdfcodec.map.pinmask.exact_decode`) is
clipped to the truncation (in the same units, :func:`clip_units`); the voxels with ``|v| < tau`` are *selected*
(:func:`select`): a pure function of the codes, so the reader finds them without a bit. Each selected voxel gets
an integer correction ``c``: the refined value is ``clip(v) + c R`` (``R`` the correction step in units of
``2^-S`` m), clipped again. ``c`` is the rounded difference to the true value where the true voxel is observed and
0 elsewhere (:func:`corrections`), clipped to ``[-M, M]``; the corrections of a chunk, block by block in the
chunk's C order and voxel by voxel in each block's C order, form one stream of constriction's ``AnsCoder`` under
one categorical law per map (:class:`CorrectionModel`, ``Categorical(perfect=False)``).

Every step is one IEEE float64 operation on exact values (a clip, a product of integers below ``2^53``, a sum),
so writer and reader compute the same refined field on any machine: the pinned mask (spec 6g) is decided on it.
"""

from __future__ import annotations

import base64
import zlib
from typing import Any

import numpy as np

from ..errors import FormatError, InvalidValueError

__all__ = ["MAX_CORRECTION", "clip_units", "select", "select_unclipped", "corrections", "refine", "CorrectionModel",
           "encode_corrections", "decode_corrections", "corrections_ahead"]

#: The largest ``|c|`` a map's law may hold (its table then has 2 M + 1 entries).
MAX_CORRECTION = 1023
_MAGIC = b"R1"


def clip_units(v: np.ndarray, truncation: tuple[float, float], scale: float) -> np.ndarray:
    """``v`` (float64, metres times ``scale``) clipped to ``[d_min, d_max]`` times ``scale`` (a new array)."""
    return np.clip(v, float(truncation[0]) * scale, float(truncation[1]) * scale)


def select(v: np.ndarray, tau: int) -> np.ndarray:
    """``(n, 4096)`` bool: the voxels of clipped exact decodes ``v`` ``(n, 4096)`` with ``|v| < tau`` (units)."""
    return np.abs(v) < tau


def select_unclipped(v: np.ndarray, tau: int, truncation: tuple[float, float], scale: float) -> np.ndarray:
    """:func:`select` of ``clip_units(v)`` from the unclipped ``v`` without clipping it (one pass fewer): a side
    of the band beyond its bound holds every clipped value."""
    lo, hi = float(truncation[0]) * scale, float(truncation[1]) * scale
    t = float(tau)
    if t > hi and -t < lo:
        return np.ones(v.shape, bool)
    if t > hi:
        return v > -t
    if -t < lo:
        return v < t
    return (v < t) & (v > -t)


def corrections(truth: np.ndarray, observed: np.ndarray | None, v: np.ndarray, sel: np.ndarray, step: int,
                limit: int = MAX_CORRECTION, scale: float = 1.0) -> np.ndarray:
    """``(m,)`` int32 corrections of the ``m`` selected voxels (``sel`` ``(n, 4096)``, C order): the true values
    ``truth`` ``(n, 4096)`` times ``scale`` (then in the units of ``v``) less ``v``, in steps of ``step`` units,
    rounded and clipped to ``+-limit``; 0 where ``observed`` ``(n, 4096)`` bool is False (no true value to
    approach)."""
    c = np.rint((truth[sel].astype(np.float64) * scale - v[sel]) / float(step))
    if observed is not None:
        c[~observed[sel]] = 0
    return np.clip(c, -limit, limit).astype(np.int32)


def refine(v: np.ndarray, sel: np.ndarray, c: np.ndarray, step: int, truncation: tuple[float, float],
           scale: float) -> np.ndarray:
    """The refined field ``(n, 4096)`` float64 (units): ``v`` plus ``c step`` at ``sel``, clipped to the
    truncation (a new array)."""
    out = v.copy()
    out[sel] += c.astype(np.float64) * float(step)
    return clip_units(out, truncation, scale)


def _varints(values) -> bytes:
    out = bytearray()
    for x in values:
        x = int(x)
        while True:
            b = x & 0x7F
            x >>= 7
            out.append(b | (0x80 if x else 0))
            if not x:
                break
    return bytes(out)


class CorrectionModel:
    """The categorical law of a map's corrections: ``counts`` ``(2 M + 1,)`` of ``c = -M .. M``."""

    def __init__(self, counts) -> None:
        self.counts = np.asarray(counts, np.int64)
        if self.counts.ndim != 1 or len(self.counts) % 2 != 1 or len(self.counts) > 2 * MAX_CORRECTION + 1 \
                or (self.counts < 0).any():
            raise FormatError(f"surface refinement: the correction law needs 2 M + 1 <= {2 * MAX_CORRECTION + 1} "
                              "counts >= 0")
        self.m = len(self.counts) // 2
        self._model = None
        self._cdf: tuple[np.ndarray, np.ndarray] | None = None

    @classmethod
    def fit(cls, c: np.ndarray) -> "CorrectionModel":
        """The law of corrections ``c`` (their counts, ``M = max |c|``, at least 1: the coder needs two symbols)."""
        c = np.asarray(c, np.int64)
        m = max(int(np.abs(c).max(initial=0)), 1)
        return cls(np.bincount(c + m, minlength=2 * m + 1))

    def probabilities(self) -> np.ndarray:
        """``(2 M + 1,)`` float64: the counts, a zero count read as 1/2 (every symbol codable), normalised."""
        p = np.where(self.counts > 0, self.counts, 0.5).astype(np.float64)
        return p / p.sum()

    def model(self):
        if self._model is None:
            import constriction

            self._model = constriction.stream.model.Categorical(self.probabilities(), perfect=False)
        return self._model

    def cdf(self) -> tuple[np.ndarray, np.ndarray]:
        """The cumulative table ``(2 M + 2,)`` uint32 of :meth:`model` and its slots (the compiled decoder's,
        :func:`sdfcodec.core.ans.categorical_cdf`)."""
        if self._cdf is None:
            from . import ans

            self._cdf = ans.categorical_cdf(self.probabilities())
        return self._cdf

    def bits(self, c: np.ndarray) -> float:
        """Ideal bits of corrections ``c`` under the law."""
        return float(-np.log2(self.probabilities()[np.asarray(c, np.int64) + self.m]).sum())

    def pack(self) -> str:
        """base64 of zlib of ``b"R1"``, ``M`` and the ``2 M + 1`` counts as LEB128 varints."""
        return base64.b64encode(zlib.compress(_MAGIC + _varints([self.m, *self.counts]), 9)).decode()

    @classmethod
    def unpack(cls, text: str) -> "CorrectionModel":
        try:
            raw = zlib.decompress(base64.b64decode(text, validate=True), bufsize=1 << 16)
        except Exception as e:
            raise FormatError(f"surface refinement: the correction law does not decode ({e})") from e
        if raw[:2] != _MAGIC:
            raise FormatError("surface refinement: the correction law does not start with b'R1'")
        vals, x, shift = [], 0, 0
        for b in raw[2:]:
            x |= (b & 0x7F) << shift
            shift += 7
            if not b & 0x80:
                vals.append(x)
                x, shift = 0, 0
            elif shift > 63:
                raise FormatError("surface refinement: the correction law holds a varint over 64 bits")
        if not vals or vals[0] > MAX_CORRECTION or len(vals) != 2 * vals[0] + 2:
            raise FormatError("surface refinement: the correction law must hold M <= "
                              f"{MAX_CORRECTION} and 2 M + 1 counts")
        return cls(vals[1:])


def encode_corrections(c: np.ndarray, model: CorrectionModel) -> np.ndarray:
    """uint32 words of constriction's AnsCoder holding corrections ``c`` ``(m,)`` in order (``m`` may be 0)."""
    import constriction

    c = np.asarray(c, np.int64)
    if len(c) and np.abs(c).max() > model.m:
        raise InvalidValueError("a correction lies beyond the law's range")
    coder = constriction.stream.stack.AnsCoder()
    if len(c):
        coder.encode_reverse((c + model.m).astype(np.int32), model.model())
    return np.asarray(coder.get_compressed(), np.uint32)


def decode_corrections(words: np.ndarray, m: int, model: CorrectionModel, ahead: Any = None) -> np.ndarray:
    """``(m,)`` int32 corrections of a stream (:func:`encode_corrections`); ``ahead``: the stream's
    :func:`corrections_ahead` (decoded before ``m`` was known), else the stream is decoded here.

    Raises:
        FormatError: the stream does not decode to ``m`` symbols and end there (a corrupted or foreign stream).
    """
    import constriction

    from . import ans

    words = np.ascontiguousarray(words, np.uint32)
    if not m:
        return np.zeros(0, np.int32)
    try:
        if ahead is not None:  # what the coder's start refused, or the symbols decoded ahead
            if isinstance(ahead, BaseException):
                raise ahead
            sym, ok = ans.symbols_ahead(ahead, m)
            c = sym - np.int32(model.m)
        elif ans.available():  # compiled: the same words read as constriction reads them (tests/test_refine.py)
            coder = ans.Decoder(words)
            c = coder.categorical(m, model.cdf()) - np.int32(model.m)
            ok = coder.is_empty()
        else:
            coder = constriction.stream.stack.AnsCoder(words)
            c = np.asarray(coder.decode(model.model(), m), np.int32) - model.m
            ok = coder.is_empty()
    except Exception as e:  # constriction's ValueError on words no coder writes
        raise FormatError(f"surface refinement stream does not decode ({e})") from e
    if not ok:
        raise FormatError(f"surface refinement stream holds more than its {m} corrections")
    return c


def corrections_ahead(words: np.ndarray, cap: int, model: CorrectionModel) -> Any:
    """The symbols of a stream decoded before the number of corrections is known (at most ``cap``, the voxels of
    its blocks), for :func:`decode_corrections`' ``ahead`` (compiled only): the same symbols, and the same verdict on
    the stream, as a decode of the number found later; an error the decode would raise is kept, not raised."""
    from . import ans

    try:
        return ans.Decoder(np.ascontiguousarray(words, np.uint32)).categorical_ahead(cap, model.cdf())
    except Exception as e:  # noqa: BLE001 - raised by decode_corrections when it has corrections to decode
        return e

