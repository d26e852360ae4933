"""Variable-rate codes (the map extension ``variable-rate-codes``, spec section 4e): per block a prefix of its code
(the first ``K`` elements of a prefix-ordered codec such as PCA), each element quantised with its own step and
entropy-coded with a rANS coder (``constriction``) under a probability model fitted on the map's codes.

Pure functions of arrays; the map glue (writing the chunk streams, reading them back) is
:mod:`sdfcodec.map.varrate`.

**The probability model** (:class:`EntropyModel`): element ``j``'s quantised value ``q`` follows a two-sided
geometric (discrete Laplace) law ``P(q) ~ decay_j ** |q - center_j|`` on ``[center_j - extent_j, center_j +
extent_j]``; the prefix length ``K`` follows the table ``lengths`` (frequencies of ``0..D``). The tables are built
from these numbers with IEEE-exact arithmetic only (a running product), so every machine builds the same ones.

**The length of each block** (:func:`choose_lengths`): the ``K`` minimising the Lagrangian ``D(K) + lam * R(K)``,
where ``R(K)`` is the bits of the length and of the first ``K`` quantised elements under the model, and ``D(K) =
sum_j g_j (z_j - zhat_j) ** 2`` (``zhat_j = 0`` for ``j >= K``) is the writer's weighted squared error to second
order: the writer fits ``z`` by weighted least squares (error weights of :mod:`sdfcodec.map.observed`), so the
error of another code ``zhat`` is ``E(z) + (zhat - z)^T G (zhat - z)`` with ``G = B W B^T`` (``B`` the basis);
``g`` is the diagonal of ``G`` (:func:`gains`), which drops the cross terms of the weighted Gram matrix. Each
element is first rounded to the nearest step or one step toward its law's centre, whichever costs less in the
same ``D + lam R`` (:func:`_rd_round`, rate-distortion optimised quantisation).

**Chunk streams** (:func:`encode_chunk` / :func:`decode_chunk`): the blocks of one chunk of the map in C order,
first their lengths, then element by element (all blocks with ``K > j`` for element ``j``), in one rANS stream.
"""

from __future__ import annotations

import base64
import zlib
from typing import Sequence

import numpy as np

from . import ans
from ..errors import FormatError, InvalidValueError

__all__ = ["EntropyModel", "fit_model", "quantise", "choose_lengths", "encode_chunk", "decode_chunk", "gains",
           "LAGRANGE", "CODER", "stream_bytes", "SHRINK", "SHRINK_BELOW"]

#: The coder a map names (spec section 4e): constriction's AnsCoder (32-bit words, 64-bit state) with
#: ``Categorical(table, perfect=False)`` models (24-bit precision).
CODER = "constriction-ans-1"
#: ``lam = LAGRANGE * step ** 2 * mean gain``: 2.5 times the slope of distortion against rate of a finely
#: quantised, entropy-coded element (``dD/dR = -2 ln 2 * step ** 2 / 12``, ln 2 / 6). The high-rate slope
#: understates the real one where most elements take a bit or two: at 64 B per coded block 2.5x gave Chamfer-L1
#: 7.81 against 8.23 mm on the kitchen half, 1.42 against 1.50 on the synthetic room, 1.51 against 1.60 on the
#: posed rooms, and the same surfaces at 128 B (docs/variable-rate.md).
LAGRANGE = float(2.5 * np.log(2) / 6)
#: The variable-rate writer's ridge towards the zero code (relative to the mean error weight) for its second
#: encode below :data:`SHRINK_BELOW` bytes (:meth:`sdfcodec.map.varrate.VariableRateWriter._shrunk` then keeps, per
#: block, the cheaper of the two codes in D + lam R). The reader's error is flat along the code directions that
#: only move voxels it truncates or does not weigh; its exact optimum drifts along them to large codes, which cost
#: bits once a coarse step quantises them. Kitchen half at 64 B, every block shrunk, Chamfer-L1: 8.00 mm without,
#: 6.40 / 5.99 / 5.99 / 7.24 / 11.6 mm at 1e-3 / 3e-3 / 1e-2 / 3e-2 / 1e-1 (towards the plain code: 6.67 at 1e-3).
#: Every block shrunk also lost on finer steps (kitchen 112 B 4.02 -> 4.15 mm; synthetic room, posed rooms at 40 B
#: 2.65 -> 2.99, 2.94 -> 3.09; at 64 B 1.44 -> 1.57, 1.57 -> 1.83, building 1.39 -> 1.97): the per-block choice
#: gains on all of them, kitchen 112 B aside (4.02 -> 4.04; docs/variable-rate.md).
SHRINK = 3e-3
#: Byte targets (per coded block) from which a writer never shrinks (so it need not keep the blocks for a second
#: encode): at 128 B the kitchen half's step is 0.08.
SHRINK_BELOW = 128.0
_MIN_DECAY, _MAX_DECAY = 1e-6, 1 - 1e-9
#: Entries of all of a model's tables together a reader builds at most (128 MiB of float64).
MAX_TABLE = 1 << 24
#: First bytes of a model in the compact layout (spec section 4e); the fixed-width layout before it starts with
#: ``D`` as a little-endian uint32 <= 65536, never these.
COMPACT_MAGIC = b"\xff\xff\xff\x02"


def _coder():
    import constriction  # imported on first use: only variable-rate maps need it

    return constriction.stream


#: The cumulative tables of the models readers built last (keyed by their numbers, least recent first) and the most
#: entries kept in all (32 MiB): a map opened again (a server's requests, reads in turn) skips rebuilding them,
#: 12 ms at 3.3 M entries (the kitchen half at 256 B, where the steps are fine and each element's table spans
#: thousands of values). A model larger than that is built at every open.
_CDFS: dict[bytes, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
_CDF_CACHE_ENTRIES = 1 << 22


class EntropyModel:
    """Per-element two-sided geometric laws (``center``, ``decay``, ``extent``: ``(D,)``) and the prefix-length
    frequencies ``lengths`` ``(D + 1,)`` of a variable-rate map; the constriction models are built on first use."""

    def __init__(self, center: Sequence[int], decay: Sequence[float], extent: Sequence[int], lengths: Sequence[int]):
        self.center = np.asarray(center, np.int64)
        self.decay = np.asarray(decay, np.float64)
        self.extent = np.asarray(extent, np.int64)
        self.lengths = np.asarray(lengths, np.float64)
        d = len(self.center)
        if not (self.decay.shape == self.extent.shape == (d,) and self.lengths.shape == (d + 1,)):
            raise FormatError(f"variable-rate model: center, decay and extent need {d} entries and lengths {d + 1}")
        if not ((self.decay > 0) & (self.decay < 1)).all() or (self.extent < 0).any() or (self.lengths < 0).any() \
                or not self.lengths.sum() > 0:
            raise FormatError("variable-rate model: decay must lie in (0, 1), extent and lengths be >= 0 "
                              "(lengths not all 0)")
        if int((2 * np.maximum(self.extent, 1) + 1).sum()) > MAX_TABLE:
            raise FormatError(f"variable-rate model: its tables would hold {int((2 * self.extent + 1).sum())} "
                              f"entries, above the limit of {MAX_TABLE} (a step far too small, or a corrupted header)")
        self._models = None
        self._cdfs = None

    @property
    def size(self) -> int:
        return len(self.center)

    def table(self, j: int) -> np.ndarray:
        """Unnormalised probabilities ``(2 e + 1,)`` float64 of ``q - center_j + e``, ``e = max(extent_j, 1)`` (the
        coder needs two symbols at least)."""
        half = np.cumprod(np.concatenate([[1.0], np.full(max(int(self.extent[j]), 1), self.decay[j])]))
        return np.concatenate([half[:0:-1], half])

    def models(self):
        """(length model, [element models]) as constriction Categorical models."""
        if self._models is None:
            cat = _coder().model.Categorical
            self._models = (cat(self.lengths, perfect=False),
                            [cat(self.table(j), perfect=False) for j in range(self.size)])
        return self._models

    def cdfs(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The cumulative tables of :meth:`models` (lengths, then each element) for the compiled decoder
        (:func:`sdfcodec.core.ans.table_cdfs`)."""
        if self._cdfs is None:
            key = b"".join(a.tobytes() for a in (self.lengths, self.decay, self.extent))
            self._cdfs = _CDFS.pop(key, None)
            if self._cdfs is None:
                self._cdfs = ans.table_cdfs(self.lengths, self.decay, self.extent)
            _CDFS[key] = self._cdfs  # most recent last
            while sum(len(c[0]) for c in _CDFS.values()) > _CDF_CACHE_ENTRIES:
                del _CDFS[next(iter(_CDFS))]
        return self._cdfs

    def bits(self, q: np.ndarray) -> np.ndarray:
        """``(n, D)`` ideal code lengths (bits) of quantised values ``q`` ``(n, D)`` under each element's law (the
        rate the length choice weighs; values beyond the extent cost as its edge)."""
        logd = np.log2(self.decay)
        # log2 of the normaliser of each truncated two-sided geometric: 1 + 2 d (1 - d^T) / (1 - d)
        norm = np.log2(1 + 2 * self.decay * (1 - self.decay ** self.extent) / (1 - self.decay))
        dist = np.minimum(np.abs(q - self.center), self.extent)
        return norm - dist * logd

    def length_bits(self) -> np.ndarray:
        """``(D + 1,)`` bits of each prefix length."""
        p = np.maximum(self.lengths, 0.5) / self.lengths.sum()
        return -np.log2(p)

    def pack(self) -> str:
        """The model as the header stores it (spec section 4e): base64 of zlib of the magic ``ff ff ff 02``, then
        ``D`` as a LEB128 varint, ``decay`` as one byte each (:func:`_decay_byte`), then varints: ``center``
        zigzag-mapped, ``extent``, ``lengths`` (``D + 1``). Under half the bytes of the fixed-width layout
        :meth:`unpack` still reads (most extents and lengths fit in one byte, most centres are 0). Decays must
        lie on the byte grid (:func:`fit_model`'s do)."""
        codes = _decay_byte(self.decay)
        if not np.array_equal(_DECAYS[codes], self.decay):
            raise InvalidValueError("variable-rate model: a decay off the one-byte grid cannot be stored")
        raw = b"".join([COMPACT_MAGIC, _varints([self.size]), codes.astype(np.uint8).tobytes(),
                        _varints(np.where(self.center >= 0, 2 * self.center, -2 * self.center - 1)),
                        _varints(self.extent), _varints(self.lengths.astype(np.int64))])
        return base64.b64encode(zlib.compress(raw, 9)).decode("ascii")

    @classmethod
    def unpack(cls, text: str, size: int) -> "EntropyModel":
        """:meth:`pack` read back for codes of ``size`` elements, the compact layout or the fixed-width one of
        maps written before it (``D`` uint32, decay uint16, centre int32, extent and lengths uint32); a malformed
        one is a FormatError."""
        try:
            raw = zlib.decompressobj().decompress(base64.b64decode(text, validate=True), 64 + 18 * (size + 1))
            if raw[:4] == COMPACT_MAGIC:
                d, o = _read_varints(raw, 4, 1)
                d = int(d[0])
                if d != size:
                    raise ValueError(f"it holds {d} elements")
                byte = np.frombuffer(raw[o:o + d], np.uint8)
                if len(byte) != d or not ((byte >= 1) & (byte < len(_DECAYS))).all():
                    raise ValueError(f"its decay bytes are truncated or outside 1..{len(_DECAYS) - 1}")
                dec = _DECAYS[byte]
                zig, o = _read_varints(raw, o + d, d)
                center = np.where(zig % 2 == 0, zig // 2, -(zig + 1) // 2)
                extent, o = _read_varints(raw, o, d)
                lengths, o = _read_varints(raw, o, d + 1)
                if o != len(raw) or (np.abs(center) > 2 ** 31 - 1).any() or (extent > 2 ** 32 - 1).any():
                    raise ValueError("trailing bytes or values out of range")
                return cls(center, dec, extent, lengths)
            d = int(np.frombuffer(raw[:4], "<u4")[0])
            if d != size or len(raw) != 4 + 14 * d + 4:
                raise ValueError(f"it holds {len(raw)} bytes for {d} elements")
            o = 4
            dec = np.frombuffer(raw[o:o + 2 * d], "<u2").astype(np.float64) / 65536
            o += 2 * d
            center = np.frombuffer(raw[o:o + 4 * d], "<i4")
            o += 4 * d
            extent = np.frombuffer(raw[o:o + 4 * d], "<u4")
            o += 4 * d
            lengths = np.frombuffer(raw[o:], "<u4")
        except (ValueError, TypeError, IndexError, zlib.error) as e:
            raise FormatError(f"codes.variable_rate.model does not unpack into a model of {size} elements ({e})") \
                from e
        return cls(center, dec, extent, lengths)


def _varints(values) -> bytes:
    """LEB128 of non-negative integers: 7 bits a byte, low first, the high bit set on all but the last."""
    out = bytearray()
    for v in np.asarray(values, np.int64).tolist():
        while v >= 0x80:
            out.append((v & 0x7F) | 0x80)
            v >>= 7
        out.append(v)
    return bytes(out)


def _read_varints(raw: bytes, o: int, n: int) -> tuple[np.ndarray, int]:
    """``n`` LEB128 integers of ``raw`` from offset ``o``: ``(values (n,) int64, offset after them)``."""
    out = np.zeros(n, np.int64)
    for i in range(n):
        v = shift = 0
        while True:
            if o >= len(raw) or shift > 35:  # 5 bytes hold every value the model allows
                raise FormatError("a varint is truncated or too long")  # a ValueError: unpack names the field
            b = raw[o]
            o += 1
            v |= (b & 0x7F) << shift
            shift += 7
            if b < 0x80:
                break
        out[i] = v
    return out, o


def _decay_table() -> np.ndarray:
    """Decay of each byte ``c`` (index 0 unused): ``1 - u / 65536`` with ``u = c`` below 16, else
    ``u = (16 + c % 16) * 2 ** (c // 16 - 1)`` (a 4-bit mantissa: 1 - decay to within 1/32 relative), up to
    ``c = 207``; each an exact binary64 number."""
    c = np.arange(208)
    u = np.where(c < 16, c, (16 + c % 16) << np.maximum(c // 16 - 1, 0))
    return np.where(c == 0, np.nan, (65536 - u) / 65536)


#: ``_DECAYS[c]``: the decay byte ``c`` of the compact model layout stands for (spec section 4e).
_DECAYS = _decay_table()


def _decay_byte(decay: np.ndarray) -> np.ndarray:
    """The byte (1..207, int64) whose decay is nearest to ``decay`` in ``log(1 - decay)``."""
    u = np.clip((1 - np.asarray(decay, np.float64)) * 65536, 1, 65536 - _DECAYS[-1] * 65536)
    grid = np.log(65536 * (1 - _DECAYS[1:]))
    return 1 + np.abs(np.log(u)[..., None] - grid).argmin(axis=-1)


def quantise(z: np.ndarray, step: np.ndarray) -> np.ndarray:
    """``rint(z / step)`` as int64 ``(n, D)`` (offsets are 0)."""
    return np.rint(np.asarray(z, np.float64) / step).astype(np.int64)


def fit_model(q: np.ndarray, k: np.ndarray) -> EntropyModel:
    """The :class:`EntropyModel` of quantised codes ``q`` ``(n, D)`` with prefix lengths ``k`` ``(n,)`` (elements
    ``j >= k`` are not coded): per element the median as centre, the maximum-likelihood decay of the coded values'
    mean distance ``m`` from it (``(sqrt(1 + m^2) - 1) / m``), the largest distance as extent."""
    n, d = q.shape
    center, decay, extent = np.zeros(d, np.int64), np.full(d, 0.5), np.zeros(d, np.int64)
    for j in range(d):
        col = q[k > j, j]
        if not len(col):
            continue
        center[j] = int(np.median(col))
        dist = np.abs(col - center[j])
        m = float(dist.mean())
        decay[j] = (np.sqrt(1 + m * m) - 1) / m if m > 0 else _MIN_DECAY
        extent[j] = int(dist.max())
    # one byte each, as the header stores them: the coder builds its tables from what is stored
    decay = _DECAYS[_decay_byte(np.clip(decay, _MIN_DECAY, _MAX_DECAY))]
    if (np.abs(center) > 2 ** 31 - 1).any() or (extent > 2 ** 32 - 1).any():
        raise InvalidValueError("quantised codes beyond 2**31 steps: use a larger step")
    return EntropyModel(center, decay, extent, np.bincount(k, minlength=d + 1))


def gains(weights: np.ndarray, basis_sq: np.ndarray) -> np.ndarray:
    """``(n, D)`` float32 diagonal of each block's weighted Gram matrix ``B W B^T``: error ``weights`` ``(n, 4096)``
    times the squared basis ``basis_sq`` ``(D, 4096)`` (None weights: every voxel 1)."""
    return np.asarray(weights, np.float32).reshape(len(weights), -1) @ basis_sq.T.astype(np.float32)


def choose_lengths(z: np.ndarray, g: np.ndarray, step: np.ndarray, lam: float, rounds: int = 2,
                   rdoq: bool = True) -> tuple[np.ndarray, np.ndarray, EntropyModel]:
    """Per block the prefix length minimising ``D(K) + lam * R(K)`` (module docstring) for codes ``z`` ``(n, D)``
    with gains ``g`` ``(n, D)`` at ``step`` ``(D,)``: ``(q (n, D) int64, zero from K on; K (n,) int64; the model
    fitted on them)``. The model the rate is measured with is refitted ``rounds`` times on the lengths chosen;
    ``rdoq``: each round first rounds the elements by rate and distortion under it (module docstring), else to
    the nearest step.
    ``K`` is the last non-zero element + 1 (a zero tail costs bits and changes nothing)."""
    z = np.asarray(z, np.float64)
    n, d = z.shape
    q0 = q = quantise(z, step)
    k = np.full(n, d, np.int64)
    model = fit_model(q, k)
    cols = np.arange(d)
    for _ in range(rounds):
        if rdoq:  # each element rounded to nearest or one step toward its law's centre, whichever costs less D + lam R
            q = _rd_round(z, g, step, lam, q0, model)
        err = g * ((z - q * step) ** 2 - z * z)  # distortion change when element j is coded instead of dropped
        cost = np.cumsum(err + lam * model.bits(q), axis=1)
        cost = np.concatenate([np.zeros((n, 1)), cost], axis=1) + lam * model.length_bits()
        k = np.argmin(cost, axis=1)
        qk = np.where(cols < k[:, None], q, 0)
        nz = qk != 0
        k = np.where(nz.any(axis=1), d - np.argmax(nz[:, ::-1], axis=1), 0)
        model = fit_model(qk, k)
    return np.where(cols < k[:, None], q, 0), k, model


def _rd_round(z: np.ndarray, g: np.ndarray, step: np.ndarray, lam: float, q: np.ndarray, model: EntropyModel
              ) -> np.ndarray:
    """Rate-distortion-optimised rounding: per element of ``q`` ``(n, D)`` (``rint(z / step)``) the value, ``q`` or
    one step toward the model's centre, with the smaller ``g (z - q step) ** 2 + lam bits(q)``."""
    toward = q - np.sign(q - model.center)
    cost = g * (z - q * step) ** 2 + lam * model.bits(q)
    alt = g * (z - toward * step) ** 2 + lam * model.bits(toward)
    return np.where(alt < cost, toward, q)


def encode_chunk(q: np.ndarray, k: np.ndarray, model: EntropyModel) -> np.ndarray:
    """One chunk's stream: uint32 words of the rANS coder holding the lengths ``k`` ``(n,)`` and then, element
    by element, the quantised values ``q`` ``(n, D)`` of the blocks with ``k > j``."""
    lm, em = model.models()
    coder = _coder().stack.AnsCoder()
    ext = np.maximum(model.extent, 1)
    off = ext - model.center  # symbol = q + e - center
    for j in range(model.size - 1, -1, -1):  # a stack: the last pushed is the first read
        sel = k > j
        if sel.any():
            sym = q[sel, j] + off[j]
            if sym.min() < 0 or sym.max() > 2 * ext[j]:
                raise InvalidValueError(f"code element {j} holds a value beyond the model's extent")
            coder.encode_reverse(sym.astype(np.int32), em[j])
    coder.encode_reverse(np.asarray(k, np.int32), lm)
    return np.asarray(coder.get_compressed(), np.uint32)


def decode_chunk(words: np.ndarray, n: int, model: EntropyModel, level: int | None = None
                 ) -> np.ndarray:
    """Quantised codes ``(n, level)`` int32 of the ``n`` blocks of a chunk stream (``level``: only the first
    elements, default all; elements beyond a block's length are 0)."""
    d = model.size
    level = d if level is None else level
    off = np.maximum(model.extent, 1) - model.center
    if ans.available():  # compiled, the same stream (tests/test_ans.py)
        return ans.decode_chunk(words, n, level, model.cdfs(), off)
    lm, em = model.models()
    coder = _coder().stack.AnsCoder(np.ascontiguousarray(words, np.uint32))
    k = coder.decode(lm, n) if n else np.zeros(0, np.int32)
    out = np.zeros((n, level), np.int32)
    for j in range(level):
        sel = np.flatnonzero(k > j)
        if not len(sel):
            break
        out[sel, j] = coder.decode(em[j], len(sel)) - off[j]
    return out


def stream_bytes(words: np.ndarray) -> int:
    """Bytes a chunk's stream takes in a map row: the 4-byte word count and the words."""
    return 4 + 4 * len(words)
