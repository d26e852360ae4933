"""The pinned voxels of a chunk (spec/map-format.md section 6g) told from the reader's own float decode of its
codes, so that a read of a map with a pinned mask multiplies its codes once, not twice.

The writer and the reader must agree on the pinned voxels bit for bit, so they are defined by the exact integer
decode ``w`` of :func:`sdfcodec.map.pinmask.exact_decode` and its bound ``E`` (a voxel may be negative where ``w <
E``, non-negative where ``w >= -E``). Computing ``w`` is a float64 matrix product over every voxel, as large as the
field's own decode and twice as slow. But a reader decodes the field anyway: ``x``, in metres, the codec's
float32 decode of the dequantised codes, and ``2^24 x`` lies within a margin ``D`` of ``w`` (:func:`float_margin`).
So ``2^24 x < E - D`` proves ``w < E``, ``2^24 x >= E + D`` proves ``w >= E`` (and alike at ``-E``): only the
voxels whose float decode lies within ``D`` of ``E`` or ``-E`` (a few in 10^4) need their exact decode, one
voxel at a time (:func:`sdfcodec.core.pinkernels.sign_rows`). The signs, and so the pinned voxels, are those of
the exact decode, whatever the float decode's rounding.

The margin, for a pca codec with a dataset mean (what :func:`sdfcodec.map.pinstore.linear_basis` accepts): the
float decode is a float32 dot product, in any order, with or without FMA, of ``(1, fl(q_i s_i))`` and the rows
``fl(R a_0 + d_min)``, ``fl(R a_i)`` (the codec's folded decoder; ``R = d_max - d_min``), ``w`` the same sum with
the rows rounded to integers of ``2^-24`` m instead. So ``|2^24 x - w|`` is at most the rounding of those
integers, ``(1 + sum|q|) / 2``, plus ``(k + 1) 2^-24`` (the dot product, ``k`` terms and the mean's) and
``2 2^-24`` (the rounding of ``q s`` and of the folded rows) relative to ``T + (1 + sum|q|) / 2`` (``T`` of the
bound): :func:`float_margin` takes ``(k + 8) 2^-24`` of ``T + 1 + sum|q|`` and two units more. A decode
truncated to ``[d_min, d_max]`` keeps every decision where ``E + D`` stays below ``2^24 min(-d_min, d_max)``;
elsewhere (and for blocks not decoded, ``D`` infinite) every voxel is decided exactly.

**A surface refinement** (spec 6h; :func:`decode_refined_pins`) selects the voxels whose clipped exact decode
``c(w) = clip(w, L, H)`` (``L``, ``H``: the truncation times ``2^24``, float64) has ``|c(w)| < tau``, adds
``e step`` units there and decides the pins on ``r = clip(c(w) + e step)`` with the bound ``E + 1``. The reader's
refined decode is ``y = clip32(fl32(x + e step 2^-24))``, ``x`` its float decode clipped to ``(L32, H32) 2^-24``
(the truncation rounded to float32, ``|L32 - L| <= |d_min| < 1`` unit). Both sides are told from that float
decode, never from a second one:

* *Selection.* Clipping is 1-Lipschitz in the value and in each bound, so ``|2^24 x - c(w)| <= D + 1``, and
  ``c(w)`` lies in ``[L, H]``: in ``[a, b] = [max(2^24 x - D - 1, L), min(2^24 x + D + 1, H)]``. Where ``-tau <
  a`` and ``b < tau`` the voxel is selected, where ``a >= tau`` or ``b <= -tau`` it is not (a decode clipped at
  ``d_min`` with ``tau`` just beyond ``|d_min|`` is then decided without its exact decode); any other voxel (or
  one of a block not decoded) is decided by its exact decode. The selection, and so the number of corrections
  the stream holds, is the exact one.
* *Refined pins.* ``e step 2^-24`` is exact in float32 (spec 6h), so the sum ``x + e step 2^-24`` has one
  rounding, at most ``2^-24`` of its magnitude: at most ``rho = max(|d_min|, |d_max|) + max|e| step 2^-24``
  units (metres as a number of units). The final clip adds at most one unit more, so ``|2^24 y - r| <= D + 2 +
  rho``: :func:`decode_refined_pins` takes ``D_r = D + 3 + ceil(rho)`` and decides, as above, only the voxels
  within ``D_r`` of ``+-(E + 1)`` exactly (``r`` from ``w``, the voxel's correction and two clips, all exact
  float64). No room condition is needed: ``r`` and ``y`` are both clipped.
"""

from __future__ import annotations

import numpy as np

from ..core import ans
from ..core._validate import BLOCK
from ..core.surface import JUMP
from . import pinmask as pm
from .grouping import each_chunk

__all__ = ["float_margin", "decode_pins", "decode_refined_pins"]

_SCALE = 2.0 ** pm.FRACTION_BITS


def float_margin(q: np.ndarray, peak: np.ndarray) -> np.ndarray:
    """``(n,)`` float64: a bound on ``|2^24 x - w|`` (module docstring) for integer codes ``q`` ``(n, k)`` whose
    exact decode ``w`` has the bound term ``T`` ``peak`` ``(n,)`` (:func:`~sdfcodec.map.pinmask.decode_bounds`)."""
    q = np.asarray(q, np.float64)
    k = q.shape[1]
    spread = 1.0 + np.abs(q).sum(axis=1)
    return spread * (0.5 + 2.0 ** -20) + np.ceil((k + 8) / _SCALE * (np.asarray(peak) + spread)) + 2.0


def decode_pins(v: np.ndarray | None, rows: np.ndarray, q: np.ndarray, basis: np.ndarray, coords: np.ndarray,
                outside_coded: np.ndarray, truncation: tuple[float, float], threads: int = 1) -> np.ndarray:
    """The pinned voxels of a chunk's coded blocks ``coords`` ``(n, 3)`` with integer codes ``q`` ``(n, k)``, as rows
    ``(n, 16, 16)`` uint16 (bit ``z``: voxel ``z``; :func:`~sdfcodec.map.pinmask.pinned_rows` of their exact
    decode's signs, :func:`~sdfcodec.map.pinmask.pinned_voxels_of` unpacked), told from the
    float decode ``v[rows[b]]`` of block ``b`` (``v`` ``(m, 4096)`` float32 metres, truncated to ``[d_min,
    d_max]`` or not; ``rows[b] < 0``: not decoded, decided exactly). ``outside_coded``: as ``pinned_voxels_of``.
    ``threads``: the compiled signs computed on that many threads, each on its share of the blocks.

    Raises:
        InvalidValueError: codes too large for the exact decode (:func:`~sdfcodec.map.pinmask.decode_bounds`).
    """
    n = len(coords)
    rows = np.asarray(rows, np.int64)
    if not ans.available() or v is None or not len(v):  # numpy: the exact decode of every voxel
        pins = pm.pinned_voxels_of(coords, *pm.sign_bounds(*pm.exact_decode(q, basis)), outside_coded, truncation)
        return np.packbits(pins.reshape(n, -1), axis=1, bitorder="little").view("<u2").reshape(n, BLOCK, BLOCK)
    from ..core import pinkernels

    q = np.ascontiguousarray(q, np.float64)
    peak, bound = pm.decode_bounds(q, basis)
    d_min, d_max = (float(t) for t in truncation)
    room = _SCALE * min(-d_min, d_max) * (1 - 2.0 ** -20)  # a truncated decode still decides the signs below it
    margin = float_margin(q, peak)
    margin = np.where((rows >= 0) & (bound + margin < room), margin, np.inf)
    neg, pos = (np.empty((n, BLOCK, BLOCK), np.uint32) for _ in range(2))
    flat, at, basis_t = np.asarray(v).reshape(len(v), -1), np.maximum(rows, 0), _transposed(basis, q.shape[1] + 1)
    each_chunk(lambda s: pinkernels.sign_rows(flat, at[s], bound[s], margin[s], q[s], basis_t, neg[s], pos[s]),
               _shares(n, threads), threads)
    return _pinned(coords, neg, pos, outside_coded, d_max)


def decode_refined_pins(v: np.ndarray, rows: np.ndarray, q: np.ndarray, basis: np.ndarray, coords: np.ndarray,
                        outside_coded: np.ndarray, truncation: tuple[float, float], tau: int, step: int,
                        corrections, threads: int = 1) -> np.ndarray:
    """:func:`decode_pins` of a map with a surface refinement (spec 6h, module docstring), compiled only: the
    pinned voxels of the refined exact field, as rows ``(n, 16, 16)`` uint16. ``v`` ``(m, 4096)`` float32 metres,
    the float decode clipped to the truncation, becomes the reader's refined decode at rows ``rows[b] >= 0`` (in
    place). ``tau``, ``step``: the refinement's, in units of ``2^-24`` m; ``corrections(sel)``: the corrections
    ``(m,)`` int32 of the selected voxels ``sel`` ``(n, 4096)`` bool (the chunk's stream). ``threads``: as
    :func:`decode_pins`.

    Raises:
        InvalidValueError: codes too large for the exact decode (:func:`~sdfcodec.map.pinmask.decode_bounds`).
    """
    from ..core import pinkernels

    n = len(coords)
    rows = np.asarray(rows, np.int64)
    q = np.ascontiguousarray(q, np.float64)
    peak, bound = pm.decode_bounds(q, basis)
    lo, hi = (float(t) * _SCALE for t in truncation)
    margin = np.where(rows >= 0, float_margin(q, peak) + 1.0, np.inf)  # clip(x) against clip(w): one unit more
    basis_t = _transposed(basis, q.shape[1] + 1)
    flat = np.asarray(v).reshape(len(v), -1)
    sel = np.empty((n, BLOCK ** 3), bool)
    shares = _shares(n, threads)
    each_chunk(lambda s: pinkernels.select_rows(flat, rows[s], float(tau), margin[s], q[s], basis_t, lo, hi, sel[s]),
               shares, threads)
    c = np.asarray(corrections(sel), np.int32)
    rho = max(-float(truncation[0]), float(truncation[1])) + float(np.abs(c).max(initial=0)) * step / _SCALE
    margin = margin + 2.0 + np.ceil(rho)  # D + 3 + ceil(rho)
    bound = bound + 1.0
    neg, pos = (np.empty((n, BLOCK, BLOCK), np.uint32) for _ in range(2))
    # each share's corrections start after those of the blocks before it (C order, block by block)
    first = np.r_[0, np.cumsum([np.count_nonzero(sel[s]) for s in shares])]
    each_chunk(lambda i: pinkernels.refined_sign_rows(
        flat, rows[shares[i]], sel[shares[i]], c[first[i]:first[i + 1]], float(step), lo, hi, bound[shares[i]],
        margin[shares[i]], q[shares[i]], basis_t, neg[shares[i]], pos[shares[i]]), range(len(shares)), threads)
    return _pinned(coords, neg, pos, outside_coded, float(truncation[1]))


#: Fewest blocks worth a thread of their own in :func:`_shares` (a thread's start is ~0.1 ms, a block's signs
#: 3-10 us with the float32 thresholds, more where many voxels are decided exactly).
MIN_SHARE = 32


def _shares(n: int, threads: int) -> list[slice]:
    """``n`` blocks as up to ``threads`` consecutive slices of about equal size, each of at least
    :data:`MIN_SHARE` blocks (one slice when that leaves one)."""
    k = max(1, min(int(threads), n // MIN_SHARE))
    edges = np.linspace(0, n, k + 1).astype(np.int64)
    return [slice(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:])]


def _pinned(coords: np.ndarray, neg: np.ndarray, pos: np.ndarray, outside_coded: np.ndarray, d_max: float
            ) -> np.ndarray:
    """The pinned rows ``(n, 16, 16)`` uint16 of blocks ``coords`` from their sign rows ``neg``, ``pos``."""
    from ..core import pinkernels

    return pinkernels.pinned_rows(np.ascontiguousarray(coords, np.int64).reshape(-1, 3), neg, pos,
                                  np.ascontiguousarray(outside_coded, np.int64).reshape(-1, 3), d_max >= JUMP)


_BASIS_T: list = []  # (the basis, its transpose): a map's reads use one basis, transposed once


def _transposed(basis: np.ndarray, rows: int) -> np.ndarray:
    """``basis[:rows].T`` C-contiguous (each voxel's column contiguous for the exact decode of one voxel),
    kept for the last basis asked."""
    kept = _BASIS_T[0] if _BASIS_T else None  # (a local: another thread may replace the entry meanwhile)
    if kept is None or kept[0] is not basis or kept[1].shape[1] != rows:
        kept = (basis, np.ascontiguousarray(basis[:rows].T))
        _BASIS_T[:] = [kept]
    return kept[1]
