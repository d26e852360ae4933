"""The residual stage of block codecs (spec/map-format.md section 6d; ``--max-error``, ``--sign-exact``).

A block codec's decode is lossy without bound. The residual stage stores, per voxel of each coded block, a small
integer ``q`` (the array ``residual``, ``(Bx, By, Bz, 4096)`` int8 or int16, chunked like ``codes`` so that it
streams with them); a reader adds ``step * q`` to the full-level decode (float32 metres) and clamps to the
truncation. The codes stay as they are, so they still work as search descriptors and prefix levels.

* ``--max-error E``: ``q`` is the smallest move that brings every observed voxel within ``E`` of the input
  (``q = sign(r) * ceil((|r| - E') / step)``, ``r = input - decode``, ``E' = E (1 - MARGIN)``, zero where
  ``|r| <= E'``), so most ``q`` are 0 and Blosc/zstd stores them almost for free. ``step = 2 E'``, or ``E'``
  with ``--sign-exact`` too (then a lattice point within the bound with the right sign always exists).
  The margin absorbs the float32 differences of the codec's decode between devices and batch sizes.
* ``--sign-exact``: every observed voxel touching a surface crossing of the input (an edge of
  :func:`sdfcodec.core.surface.crossing_edges` with both voxels observed) whose decode has the wrong sign is moved
  to the nearest lattice point with the right sign (within ``[-step, step)`` of 0). Crossings are found among
  the blocks of one write call (neighbouring blocks written in separate calls do not see each other's edges).

The writer computes ``q`` from the decode a reader makes (:func:`stored_code_values`, the reader's own
``decode_codes``) and checks the result with the reader's arithmetic (:func:`apply_residual`) before storing it.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
import zarr
from zarr.codecs import BloscCodec, Crc32cCodec
from zarr.core.sync import sync as zarr_sync

from ..core._lazy import lazy_module
from ..core._validate import BLOCK
from ..errors import FormatError, InvalidValueError
from ..core.header import CodesSpec, ResidualSpec
from ..core.quantize import quantise_step, quantize_codes
from ..core.surface import JUMP, crossing_edges
from .format import code_values

if TYPE_CHECKING:
    from ..codec import Codec
    from .reader import MapReader

torch = lazy_module("torch")  # imported on first use: reading a header never needs it

__all__ = ["RESIDUAL_ARRAY", "MARGIN", "SIGN_STEP_VOXELS", "residual_spec", "residual_compressors",
           "stored_code_values", "crossing_voxels", "residual_rows", "apply_residual", "checked_residual_array",
           "check_residual_stored"]

RESIDUAL_ARRAY = "residual"
VOXELS = BLOCK ** 3
#: The writer aims at ``E (1 - MARGIN)``: 39 um of slack at E = 1 cm, against float32 decode differences of about
#: 1e-6 m between devices and batch sizes (pca, ae), so the bound holds on any reader.
MARGIN = 2.0 ** -8
#: ``--sign-exact`` alone: the residual step in voxels (a corrected voxel lands within one step of 0).
SIGN_STEP_VOXELS = 0.5
#: The smallest bound, in truncation ranges: below it float32 decoding itself is too coarse to promise it.
MIN_ERROR = 1e-4


def residual_spec(codec: Codec, code_dtype: str, voxel_size: float, truncation: tuple[float, float],
                  max_error: float | None, sign_exact: bool) -> ResidualSpec | None:
    """The header's ``residual`` for a new map (None: neither flag), the flags checked against the codec.

    Raises:
        InvalidValueError: a bound that is not a positive number of metres below the truncation range (or is
            below what float32 resolves), a codec whose map is field-compressed (sz3 bounds its error itself),
            a codec with neighbour context (halo), or lossless float32 voxel codes (raw: nothing to bound).
    """
    if max_error is None and not sign_exact:
        return None
    what = "--sign-exact" if sign_exact else "--max-error"
    d_min, d_max = truncation
    rng = d_max - d_min
    if codec.field_compression() is not None:
        raise InvalidValueError(f"{what} adds a residual to a block codec's decode; codec {codec.codec_id!r} stores "
                                "its voxels through a field compressor, which bounds the error itself (sz3: "
                                "--max-error alone), so it cannot carry one")
    if codec.halo:
        raise InvalidValueError(f"{what} adds a residual to each block's decode; codec {codec.codec_id!r} decodes "
                                "with its neighbours' context (halo), which would move the bounded values: use a "
                                "block codec such as pca or ae")
    if codec.codec_id == "raw" and code_dtype == "float32":
        raise InvalidValueError(f"{what}: codec 'raw' with float32 codes is lossless (every voxel decodes exactly), "
                                "so there is nothing to bound; use a lossy codec (pca, ae) or int8/int16 codes")
    step = voxel_size * SIGN_STEP_VOXELS
    if max_error is not None:
        e = float(max_error)
        if not (math.isfinite(e) and e > 0):
            raise InvalidValueError(f"--max-error must be a positive number of metres, got {max_error}")
        if e >= rng:
            raise InvalidValueError(f"--max-error {e} m is not below the truncation range {rng:g} m "
                                    f"([{d_min}, {d_max}]): every decode already lies within it; pass a smaller bound")
        if e < MIN_ERROR * rng:
            raise InvalidValueError(f"--max-error {e} m is below {MIN_ERROR * rng:.3g} m ({MIN_ERROR:g} truncation "
                                    "ranges), finer than float32 decoding resolves; pass a larger bound or store "
                                    "the map losslessly (--codec raw)")
        inner = e * (1 - MARGIN)
        step = inner if sign_exact else 2 * inner
    qmax = math.ceil(rng / step) + 2
    dtype = "int8" if qmax <= np.iinfo(np.int8).max else "int16"
    return ResidualSpec(step=step, dtype=dtype, max_error=None if max_error is None else float(max_error),
                        sign_exact=bool(sign_exact))


def residual_compressors() -> list:
    """The chain of ``residual``: mostly zeros and small integers. Blosc zstd level 9 without shuffle stores the
    analytic room's residuals (pca-16; 2 and 10 mm, sign-exact, both) in 0.65-0.76x the bytes of level 3; bit
    shuffle takes 1.04-1.15x of level 3, plain zstd 9 0.78-0.90x (docs/error-bounds.md)."""
    return [BloscCodec(cname="zstd", clevel=9, shuffle="noshuffle"), Crc32cCodec()]


def stored_code_values(codes: np.ndarray, spec: CodesSpec) -> np.ndarray:
    """Codes ``(n, D)`` float32 as a reader will read them back from a map with codes layout ``spec``: quantised
    and dequantised as stored (int8 per block, int16 with the step, float16), through the reader's
    :func:`~sdfcodec.map.format.code_values`."""
    if spec.dtype == "int8":
        q, params = quantize_codes(codes, per="block")
        return code_values(q, params)[0]
    if spec.dtype == "int16":
        quant = spec.quantisation
        return code_values(quantise_step(codes, quant.step, quant.offset), None, quant)[0]
    return code_values(codes.astype(spec.dtype), None)[0]


def _face(blocks: np.ndarray, ax: int, index: int) -> tuple:
    """The index of layer ``index`` along voxel axis ``ax`` of the blocks ``blocks`` (indices into the batch)."""
    return (blocks,) + (slice(None),) * ax + (index,)


def crossing_voxels(coords: np.ndarray, blocks: np.ndarray, observed: np.ndarray | None,
                    jump: float = JUMP) -> np.ndarray:
    """``(n, 16, 16, 16)`` bool: the voxels of blocks ``blocks`` ``(n, 16, 16, 16)`` float32 metres at block indices
    ``coords`` ``(n, 3)`` that touch a surface crossing (:func:`~sdfcodec.core.surface.crossing_edges`) whose two voxels
    are observed (``observed`` ``(n, 16, 16, 16)`` bool; None: all), inside a block or across the face of two of
    these blocks."""
    obs = np.ones(blocks.shape, bool) if observed is None else observed
    out = np.zeros(blocks.shape, bool)
    keys = _keys(coords)
    order = np.argsort(keys)
    for ax in range(3):
        lo_s = (slice(None),) * (ax + 1) + (slice(0, -1),)
        hi_s = (slice(None),) * (ax + 1) + (slice(1, None),)
        e = crossing_edges(blocks[lo_s], blocks[hi_s], jump) & obs[lo_s] & obs[hi_s]
        out[lo_s] |= e
        out[hi_s] |= e
        if not len(keys):
            continue
        # across faces: block i and its neighbour j along +ax, when both are among these blocks
        want = _keys(coords + np.eye(3, dtype=np.int64)[ax])
        j = order[np.clip(np.searchsorted(keys, want, sorter=order), 0, len(keys) - 1)]
        i = np.flatnonzero(keys[j] == want)
        j = j[i]
        if not len(i):
            continue
        last, first = _face(i, ax, BLOCK - 1), _face(j, ax, 0)  # faces only: no copy of whole blocks
        e = crossing_edges(blocks[last], blocks[first], jump) & obs[last] & obs[first]
        out[last] |= e  # i (and j) hold each block once: the fancy-index update is exact
        out[first] |= e
    return out


def _keys(coords: np.ndarray) -> np.ndarray:
    """One int64 per block index (blocks stay below 2**21 per axis in any map a reader accepts for writing)."""
    c = np.asarray(coords, np.int64)
    return (c[:, 0] << 42) | (c[:, 1] << 21) | c[:, 2]


def apply_residual(v: torch.Tensor, rows: np.ndarray, step: float, lo: float, hi: float) -> torch.Tensor:
    """Add ``step * q`` to decoded blocks ``v`` ``(n, 16, 16, 16)`` float32 (any device) and clamp to ``[lo, hi]``,
    in place; ``rows`` ``(n, 4096)`` int8/int16, the stored ``q`` (C-order voxels). Spec 6d's arithmetic:
    ``float32(q) * float32(step)`` rounded, then added, each in float32. Only blocks with a non-zero ``q`` are
    touched (one gather and one scatter of those)."""
    nz = np.flatnonzero(rows.any(axis=1))
    if not len(nz):
        return v
    idx = torch.from_numpy(nz).to(v.device)
    q = torch.from_numpy(np.ascontiguousarray(rows[nz])).to(v.device).to(v.dtype).view(-1, BLOCK, BLOCK, BLOCK)
    q.mul_(torch.tensor(step, dtype=v.dtype, device=v.device))
    sub = v.index_select(0, idx)
    sub.add_(q).clamp_(lo, hi)
    v.index_copy_(0, idx, sub)
    return v


def residual_rows(spec: ResidualSpec, orig: np.ndarray, dec: torch.Tensor, observed: np.ndarray | None,
                  crossing: np.ndarray | None, truncation: tuple[float, float]) -> np.ndarray:
    """The stored ``q`` ``(n, 4096)`` (``spec.dtype``) of blocks whose input is ``orig`` ``(n, 16, 16, 16)`` float32
    metres and whose reader decode (full level, no residual) is ``dec`` (same shape, torch, any device);
    ``observed`` and ``crossing`` (``(n, 16, 16, 16)`` bool; None: all observed, no crossings) as in the module
    docstring. Checked with the reader's arithmetic (:func:`apply_residual`): raises ``InvalidValueError`` if a
    bound still fails after the corrections (a bug, never expected)."""
    n = len(orig)
    d_min, d_max = truncation
    o = orig.reshape(n, -1).astype(np.float64)
    d32 = dec.detach().cpu().numpy().reshape(n, -1)
    d = d32.astype(np.float64)
    obs = np.ones(o.shape, bool) if observed is None else observed.reshape(n, -1)
    s = spec.step
    q = np.zeros(o.shape, np.int64)
    if spec.max_error is not None:
        inner = spec.max_error * (1 - MARGIN)
        r = o - d
        q = (np.sign(r) * np.ceil(np.maximum(np.abs(r) - inner, 0) / s)).astype(np.int64)
        q[~obs] = 0
    cross = None if crossing is None or not spec.sign_exact else crossing.reshape(n, -1) & obs
    neg = o < 0
    for _ in range(4):  # the first pass sets q, the others fix what float32 rounding moved (rare)
        out = _simulate(d32, q, spec, d_min, d_max)
        bad = np.zeros(o.shape, bool)
        if spec.max_error is not None:
            err = out - o
            over = obs & (np.abs(err) > spec.max_error)
            q[over] -= np.sign(err[over]).astype(np.int64)
            bad |= over
        if cross is not None:
            wrong = cross & ((out < 0) != neg)
            if wrong.any():
                # the lattice point nearest 0 on the right side: [0, s) for a non-negative input, [-s, 0) else
                k = np.ceil(-d[wrong] / s).astype(np.int64) - neg[wrong]
                k = np.where(q[wrong] == k, k + np.where(neg[wrong], -1, 1), k)  # rounding left it on 0: one more
                q[wrong] = k
                bad |= wrong
        if not bad.any():
            break
    else:
        raise InvalidValueError("the residual stage could not meet its bound after 4 passes; nothing was stored "
                                "(a bug: please report it with the input)")
    if np.abs(q).max(initial=0) > np.iinfo(spec.dtype).max:
        raise InvalidValueError(f"residual value {int(np.abs(q).max())} beyond {spec.dtype}; nothing was stored (a bug: "
                                "please report it with the input)")
    return q.astype(spec.dtype)


def _simulate(d32: np.ndarray, q: np.ndarray, spec: ResidualSpec, d_min: float, d_max: float) -> np.ndarray:
    """What a reader decodes from ``d32`` ``(n, 4096)`` float32 and ``q``: :func:`apply_residual`, as float64."""
    v = torch.from_numpy(d32.copy()).view(-1, BLOCK, BLOCK, BLOCK)
    limit = np.iinfo(spec.dtype).max
    rows = np.clip(q, -limit, limit).astype(spec.dtype)
    return apply_residual(v, rows, spec.step, d_min, d_max).numpy().reshape(len(d32), -1).astype(np.float64)


def checked_residual_array(reader: MapReader) -> zarr.Array | None:
    """The ``residual`` array of the map ``reader`` opens, its metadata checked against the header; None when the
    header has no residual stage.

    Raises:
        FormatError: the header names the residual stage but the array is missing, or has the wrong dtype,
            shape or chunks.
    """
    h = reader.header
    if h.residual is None:
        return None
    arr = reader.member(RESIDUAL_ARRAY)
    if arr is None:
        raise FormatError(f"{reader.location}: map has a residual stage but lacks array '{RESIDUAL_ARRAY}' (spec "
                          "section 6d); it is incomplete")
    cb = h.codes.chunk_blocks
    reader.check_array(arr, dtype=np.dtype(h.residual.dtype), shape=(*h.grid_blocks, VOXELS),
                       chunks=(cb, cb, cb, VOXELS), zero_fill=True)
    return arr


def check_residual_stored(reader: MapReader, arr: zarr.Array, coords: np.ndarray, rows: np.ndarray) -> None:
    """Refuse coded blocks ``coords`` ``(n, 3)`` whose ``residual`` chunk is not stored (writers store every chunk
    holding coded blocks): Zarr reads it as zeros. Only the chunks of blocks whose ``rows`` ``(n, 4096)`` are all
    zero are looked up, each once per reader."""
    suspects = coords[~rows.any(axis=1)]
    if not len(suspects):
        return
    seen = reader.residual_chunks_checked
    for chunk in np.unique(suspects // np.asarray(arr.chunks[:3]), axis=0):
        key = f"{arr.path}/{arr.metadata.encode_chunk_key((*(int(c) for c in chunk), 0))}"
        if key in seen:
            continue
        if not zarr_sync(reader.group.store.exists(key)):
            raise FormatError(f"{reader.location}: chunk {key} of array '{arr.path}' is missing, but blocks in it are "
                              "coded; their residual (the error bound) would be lost: restore the map from a copy "
                              "or re-encode it")
        seen.add(key)
