"""A context-modelled observation mask (map extension ``coded-observation-mask``, spec/map-format.md section 6e).

The mask of a fused map (one bit per voxel of each coded block, section 6b) is spatially coherent: whether a
voxel was observed is well predicted by whether its neighbours were. Blosc's zstd sees packed bytes and stores
the held-out kitchen half's mask in 66.1 B per coded block; this coder, lossless, in 46.2
(docs/side-information.md).

Order and contexts: per partial block (a row not all 255), first the states of its 512 sub-cubes of 2^3 voxels
(none observed, all, mixed; context: the states of the sub-cubes before it along each axis), then the voxels of
the mixed sub-cubes only (a tenth of them on the kitchen: 4x fewer symbols to decode), each under the context of
the ten face, edge and corner neighbours with a smaller coordinate sum (:data:`OFFSETS`; outside the block they
read 0). Both steps go wavefront by wavefront (cells with equal ``i + j + k``), so a whole wavefront of every
partial block of the chunk decodes in one vectorised call: 22 + 46 calls a chunk instead of 4096 per block.

Probabilities: ``p(1 | c) = (n1[c] + 1/2) / (n[c] + 1)`` (Krichevsky-Trofimov) from the counts of the wavefronts
before, per chunk, so that no table is stored and any mask is coded. The probabilities are computed in float64
from integer counts (exact, identical on every machine) and constriction's Bernoulli model quantises them the
same way in the writer and the reader.

Stream (the chunk's bytes before the CRC32C; spec section 6e): ``b"M1"``, the number ``P`` of partial rows
(uint32 LE), then constriction's AnsCoder words (uint32 LE). Decoded first: one flag per row, partial or not,
under the fixed probability ``P / R`` (``R`` rows in the chunk; no flags when ``P`` is 0 or ``R``); then the
sub-cube states, then the voxels of mixed sub-cubes. Rows that are not partial are 255.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from typing import Any

import numpy as np
import zarr
from zarr.abc.buffer import Buffer, NDBuffer

from ..core import ans
from ..core._validate import BLOCK
from ..errors import ChecksumError, FormatError
from ..core.header import CODED_MASK_EXTENSION
from .field import ThreadedArrayBytesCodec

__all__ = ["MASK_ANS_CODEC", "CODED_MASK_EXTENSION", "MaskANS", "encode_mask_rows", "decode_mask_rows", "OFFSETS"]

#: Name of the Zarr v3 codec in the ``observed`` array's metadata.
MASK_ANS_CODEC = "sdfcodec.mask-ans"
#: Context neighbours ``(di, dj, dk)`` of a voxel, bit ``q`` of its context for ``OFFSETS[q]``: the three faces,
#: three edges and the corner before it along every axis, and the three neighbours one step back along two axes
#: and one forward along the third (all on earlier wavefronts). Entropy of the kitchen half's voxels (191 partial
#: blocks, every voxel coded under adaptive counts): these ten 45.5 B per block, the first seven alone 49.2.
OFFSETS = ((-1, 0, 0), (0, -1, 0), (0, 0, -1), (-1, -1, 0), (-1, 0, -1), (0, -1, -1), (-1, -1, -1),
           (-1, 1, -1), (-1, -1, 1), (1, -1, -1))
_MAGIC = b"M1"
_ROW = BLOCK ** 3 // 8  # 512 packed bytes per block
_PAD = BLOCK + 2  # padded block edge: one layer of zeros on every side
_SUB = BLOCK // 2  # sub-cubes of 2^3 voxels per block edge
_NCTX = 1 << len(OFFSETS)


def _stream():
    import constriction  # a core dependency (variable-rate codes use it too), imported on first use

    return constriction.stream


def _wavefronts(edge: int, pad: int) -> tuple[tuple[np.ndarray, np.ndarray], ...]:
    """Per wavefront ``s`` of an ``edge``^3 grid: (flat indices of its cells in the grid padded by ``pad`` on every
    side, their C-order flat indices in the unpadded grid)."""
    i, j, k = np.meshgrid(*[np.arange(edge)] * 3, indexing="ij")
    s = (i + j + k).ravel()
    e = edge + 2 * pad
    padded = (((i + pad) * e + (j + pad)) * e + (k + pad)).ravel()
    return tuple((padded[s == w], np.flatnonzero(s == w)) for w in range(3 * (edge - 1) + 1))


@lru_cache(maxsize=1)
def _waves() -> tuple[tuple[tuple[np.ndarray, np.ndarray], ...], tuple[tuple[np.ndarray, np.ndarray], ...],
                      ]:
    """(voxel wavefronts, sub-cube wavefronts)."""
    return _wavefronts(BLOCK, 1), _wavefronts(_SUB, 1)


@lru_cache(maxsize=1)
def _flat_waves() -> tuple[tuple[np.ndarray, np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """(sub-cube, voxel) wavefronts as the compiled decoder takes them: (padded flat indices, unpadded flat
    indices, bounds of each wavefront) concatenated in wavefront order."""
    def cat(waves):
        return (np.concatenate([a for a, _ in waves]), np.concatenate([b for _, b in waves]),
                np.concatenate([[0], np.cumsum([len(a) for a, _ in waves])]).astype(np.int64))

    vox, cube = _waves()
    return cat(cube), cat(vox)


@lru_cache(maxsize=1)
def _voxel_tables() -> tuple[np.ndarray, np.ndarray]:
    """Per C-order voxel of a block: its wavefront ``i + j + k`` and its flat index in the padded block."""
    wave, padded = np.zeros(BLOCK ** 3, np.int64), np.zeros(BLOCK ** 3, np.int64)
    for w, (wpad, wflat) in enumerate(_waves()[0]):
        wave[wflat], padded[wflat] = w, wpad
    return wave, padded


_DELTAS = np.array([(a * _PAD + b) * _PAD + c for a, b, c in OFFSETS], dtype=np.int64)
_CUBE_DELTAS = np.array([-(_SUB + 2) ** 2, -(_SUB + 2), -1], dtype=np.int64)  # its -x, -y, -z neighbours


def _gather_context(flat: np.ndarray, at: np.ndarray, deltas: np.ndarray, base: int) -> np.ndarray:
    """Context ``(n,)`` int64 of cells at flat indices ``at`` of the padded, flattened ``flat``: the values at
    ``at + deltas[q]`` as digits of base ``base``, ``q = 0`` least significant."""
    ctx = np.zeros(len(at), dtype=np.int64)
    for q in range(len(deltas) - 1, -1, -1):
        ctx *= base
        ctx += flat[at + deltas[q]]
    return ctx


class _Adaptive:
    """Krichevsky-Trofimov counts of ``k`` symbols in ``n`` contexts: ``p(x | c) = (n_x[c] + 1/2) / (n[c] + k/2)``."""

    def __init__(self, n: int, k: int) -> None:
        self.n, self.k = n, k
        self.counts = np.zeros((k, n), dtype=np.int64)

    def probabilities(self, ctx: np.ndarray) -> np.ndarray:
        """``(len(ctx), k)`` float64; for ``k == 2`` only ``p(1)``, ``(len(ctx),)``."""
        c = self.counts[:, ctx] + 0.5
        return c[1] / (c[0] + c[1]) if self.k == 2 else (c / c.sum(axis=0)).T

    def add(self, ctx: np.ndarray, sym: np.ndarray) -> None:
        self.counts += np.bincount(sym * self.n + ctx, minlength=self.k * self.n).reshape(self.k, self.n)


def _cube_states(bits: np.ndarray) -> np.ndarray:
    """``(P, 4096)`` voxel bits (0/1) -> ``(P, 512)`` int64 sub-cube states: 0 none observed, 1 all, 2 mixed."""
    b = bits.reshape(-1, BLOCK, BLOCK, BLOCK)
    s = sum(b[:, i::2, j::2, k::2].astype(np.uint8) for i in (0, 1) for j in (0, 1) for k in (0, 1))  # 8 strided adds
    return np.where(s == 0, 0, np.where(s == 8, 1, 2)).reshape(len(b), _SUB ** 3).astype(np.int64)


def _per_voxel(states: np.ndarray) -> np.ndarray:
    """``(P, 512)`` sub-cube states -> ``(P, 16, 16, 16)``, each voxel its sub-cube's (a broadcast, no gather)."""
    s = states.astype(np.uint8).reshape(-1, _SUB, 1, _SUB, 1, _SUB, 1)
    return np.broadcast_to(s, (len(states), _SUB, 2, _SUB, 2, _SUB, 2)).reshape(-1, BLOCK, BLOCK, BLOCK)


def encode_mask_rows(rows: np.ndarray) -> bytes:
    """The stream of packed mask rows ``(R, 512)`` uint8 (a chunk's, in C order of its blocks)."""
    rows = np.ascontiguousarray(rows, dtype=np.uint8).reshape(-1, _ROW)
    partial = (rows != 255).any(axis=1)
    p_rows = int(partial.sum())
    flags = partial if 0 < p_rows < len(rows) else None
    bits = np.unpackbits(rows[partial], axis=1)
    if ans.available():  # compiled, the same words (tests/test_ans.py)
        words = ans.encode_mask(flags, p_rows / max(len(rows), 1), bits, _flat_waves()[0], len(_waves()[0]),
                                _CUBE_DELTAS, _DELTAS)
    else:
        words = _encode_words(flags, p_rows / max(len(rows), 1), bits)
    return _MAGIC + np.uint32(p_rows).astype("<u4").tobytes() + np.asarray(words, dtype="<u4").tobytes()


def _encode_words(flags: np.ndarray | None, p_flag: float, bits: np.ndarray) -> np.ndarray:
    """constriction's words (the path without numba) of row flags ``flags`` (None: not coded) and the partial
    rows' bits ``(P, 4096)``."""
    p_rows = len(bits)
    st = _stream()
    bern, cat = st.model.Bernoulli(perfect=False), st.model.Categorical(perfect=False)
    coder = st.stack.AnsCoder()
    parts: list[tuple[Any, np.ndarray, np.ndarray]] = []  # (model, symbols, probabilities) in decode order
    if flags is not None:
        parts.append((bern, flags.astype(np.int32), np.full(len(flags), p_flag)))
    vox_waves, cube_waves = _waves()
    states = _cube_states(bits)
    cpad = np.full((p_rows, _SUB + 2, _SUB + 2, _SUB + 2), 3, dtype=np.int64)
    cpad[:, 1:-1, 1:-1, 1:-1] = states.reshape(p_rows, _SUB, _SUB, _SUB)
    cflat, model = cpad.reshape(-1), _Adaptive(64, 3)
    cstride = (_SUB + 2) ** 3
    for wpad, wflat in cube_waves:
        at = (np.arange(p_rows)[:, None] * cstride + wpad[None, :]).ravel()
        ctx, sym = _gather_context(cflat, at, _CUBE_DELTAS, 4), states[:, wflat].ravel()
        parts.append((cat, sym.astype(np.int32), model.probabilities(ctx)))
        model.add(ctx, sym)
    vpad = np.pad(bits.reshape(p_rows, BLOCK, BLOCK, BLOCK), ((0, 0), (1, 1), (1, 1), (1, 1))).astype(np.int64)
    vflat, model = vpad.reshape(-1), _Adaptive(_NCTX, 2)
    mixed = (_per_voxel(states) == 2).reshape(p_rows, BLOCK ** 3)
    for wpad, wflat in vox_waves:
        r, c = np.nonzero(mixed[:, wflat])
        at = r * _PAD ** 3 + wpad[c]
        ctx, sym = _gather_context(vflat, at, _DELTAS, 2), vflat[at]
        parts.append((bern, sym.astype(np.int32), model.probabilities(ctx)))
        model.add(ctx, sym)
    for m, sym, p in reversed(parts):  # a stack: the last decoded goes in first
        if len(sym):
            coder.encode_reverse(sym, m, p)
    return np.asarray(coder.get_compressed(), dtype="<u4")


def decode_mask_rows(stream: bytes | np.ndarray, n_rows: int, where: str = "a coded mask chunk") -> np.ndarray:
    """Inverse of :func:`encode_mask_rows`: ``(n_rows, 512)`` uint8.

    Raises:
        ChecksumError: the stream is not one this module writes (its CRC32C passed: a writer's bug or a forged
            chunk), named by ``where``.
    """
    buf = np.frombuffer(bytes(stream), dtype=np.uint8)
    if len(buf) < 6 or bytes(buf[:2]) != _MAGIC or (len(buf) - 6) % 4:
        raise ChecksumError(f"{where} is not a {MASK_ANS_CODEC} stream (bad header or length {len(buf)})")
    p_rows = int(buf[2:6].view("<u4")[0])
    if p_rows > n_rows:
        raise ChecksumError(f"{where} claims {p_rows} partial rows in a chunk of {n_rows}")
    out = np.full((n_rows, _ROW), 255, dtype=np.uint8)
    if p_rows == 0:
        return out
    words = np.ascontiguousarray(buf[6:].view("<u4"), dtype=np.uint32)
    try:
        if ans.available():  # compiled, the same stream (tests/test_ans.py)
            partial, states, vpad = ans.decode_mask(words, n_rows, p_rows, *_flat_waves(), _CUBE_DELTAS, _DELTAS)
        else:
            partial, states, vpad = _decode_words(words, n_rows, p_rows)
    except Exception as e:  # noqa: BLE001 - constriction raises on an exhausted or inconsistent stream
        raise ChecksumError(f"{where} is not a sound {MASK_ANS_CODEC} stream ({e})") from e
    if int(partial.sum()) != p_rows:
        raise ChecksumError(f"{where} decodes {int(partial.sum())} partial rows, its header says {p_rows}")
    if ans.available():
        packed, sound = ans.pack_mask(vpad, states)
    else:
        bits = vpad[:, 1:-1, 1:-1, 1:-1].reshape(p_rows, -1).astype(np.uint8)
        packed, sound = np.packbits(bits, axis=1), not (_cube_states(bits) != states).any()
    if not sound:
        raise ChecksumError(f"{where} decodes voxels that contradict its sub-cube states; it is corrupted")
    out[partial] = packed
    return out


def _decode_words(words: np.ndarray, n_rows: int, p_rows: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """constriction's decode of a stream's words (the path without numba): (partial ``(n_rows,)`` bool, sub-cube
    states ``(p_rows, 512)`` int64, voxels padded by one ``(p_rows, 18, 18, 18)`` uint8)."""
    st = _stream()
    coder = st.stack.AnsCoder(words) if len(words) else st.stack.AnsCoder()
    bern, cat = st.model.Bernoulli(perfect=False), st.model.Categorical(perfect=False)
    if p_rows < n_rows:
        partial = coder.decode(bern, np.full(n_rows, p_rows / n_rows)).astype(bool)
    else:
        partial = np.ones(n_rows, dtype=bool)
    vox_waves, cube_waves = _waves()
    cpad = np.full((p_rows, _SUB + 2, _SUB + 2, _SUB + 2), 3, dtype=np.int64)
    cflat, model, cstride = cpad.reshape(-1), _Adaptive(64, 3), (_SUB + 2) ** 3
    states = np.empty((p_rows, _SUB ** 3), dtype=np.int64)
    for wpad, wflat in cube_waves:
        at = (np.arange(p_rows)[:, None] * cstride + wpad[None, :]).ravel()
        ctx = _gather_context(cflat, at, _CUBE_DELTAS, 4)
        sym = coder.decode(cat, model.probabilities(ctx)).astype(np.int64)
        cflat[at] = sym
        states[:, wflat] = sym.reshape(p_rows, -1)
        model.add(ctx, sym)
    per = _per_voxel(states)
    vpad = np.zeros((p_rows, _PAD, _PAD, _PAD), dtype=np.uint8)
    vpad[:, 1:-1, 1:-1, 1:-1] = per == 1  # uniform sub-cubes known; mixed ones decoded next
    vflat, model = vpad.reshape(-1), _Adaptive(_NCTX, 2)
    # every mixed voxel at once, grouped by wavefront; a stable sort keeps rows, then C order, in each
    wave_of, padded_of = _voxel_tables()
    r, c = np.nonzero((per == 2).reshape(p_rows, BLOCK ** 3))
    order = np.argsort(wave_of[c], kind="stable")
    at_all = (r * _PAD ** 3 + padded_of[c])[order]
    bounds = np.searchsorted(wave_of[c][order], np.arange(len(vox_waves) + 1))
    for w in range(len(vox_waves)):
        at = at_all[bounds[w]:bounds[w + 1]]
        if not len(at):
            continue
        ctx = _gather_context(vflat, at, _DELTAS, 2)
        sym = coder.decode(bern, model.probabilities(ctx)).astype(np.int64)
        vflat[at] = sym
        model.add(ctx, sym)
    return partial, states, vpad


@dataclass(frozen=True)
class MaskANS(ThreadedArrayBytesCodec):
    """Zarr v3 array-to-bytes codec ``sdfcodec.mask-ans``: a uint8 chunk ``(c, c, c, 512)`` of packed observation
    masks as one stream (:func:`encode_mask_rows`). It has no configuration."""

    is_fixed_size = False

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> "MaskANS":
        if not isinstance(data, dict) or data.get("name") != MASK_ANS_CODEC or data.get("configuration", {}) != {}:
            raise FormatError(f"a {MASK_ANS_CODEC} codec has no configuration, got {data!r}")
        return cls()

    def to_dict(self) -> dict[str, Any]:
        return {"name": MASK_ANS_CODEC}

    def _check_spec(self, spec) -> tuple[int, ...]:
        shape = tuple(int(n) for n in spec.shape)
        if np.dtype(spec.dtype.to_native_dtype()) != np.uint8 or len(shape) != 4 or shape[3] != _ROW:
            raise FormatError(f"{MASK_ANS_CODEC} codes uint8 chunks of packed masks (c, c, c, 512), got "
                              f"{spec.dtype} {shape}")
        return shape

    def _encode_sync(self, chunk_array: NDBuffer, chunk_spec) -> Buffer:
        self._check_spec(chunk_spec)
        stream = encode_mask_rows(np.asarray(chunk_array.as_numpy_array(), dtype=np.uint8))
        return chunk_spec.prototype.buffer.from_bytes(stream)

    def _decode_sync(self, chunk_bytes: Buffer, chunk_spec) -> NDBuffer:
        shape = self._check_spec(chunk_spec)
        rows = decode_mask_rows(chunk_bytes.as_numpy_array(), int(np.prod(shape[:3])))
        return chunk_spec.prototype.nd_buffer.from_numpy_array(rows.reshape(shape))



zarr.registry.register_codec(MASK_ANS_CODEC, MaskANS)
