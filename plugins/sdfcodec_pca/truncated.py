"""The pca codec's fast truncation-aware weighted encode on the CPU (what map writers run on fused blocks).

The same computation as :func:`sdfcodec.map.observed.encode_truncated` over :meth:`PCACodec.encode_weighted`
(a weighted least-squares fit with a ridge towards the plain projection, then active-set refits that give
weight 0 to the bound voxels a reader's truncation makes exact), one compiled kernel per block instead of
batched tensor operations. Why a kernel (numba): the exact fit needs one ``k x k`` Gram matrix and one Cholesky
factorisation per solve, and on the CPU torch's batched 64 x 64 Cholesky costs 3.5 plain projections of the
block (LAPACK's per-matrix overhead; 87 k flops of work), its batched Gram from an outer-product table 17.

What the kernel does instead, per block, in cache:

- **Grams from the voxels that differ from a reference.** With basis rows ``d_j`` (``D`` is ``(k, 4096)``),
  ``G(w) = G(r) + sum_j (w_j - r_j) d_j d_j^T`` for any reference weights ``r`` whose Gram is known. Fused
  maps' weights take three values (0 unobserved, 1, 51 near the surface), so the references ``r = 0``
  (``G = 0``: the observed voxels) and ``r = 1`` (``G = D D^T``, precomputed: the unobserved and the surface
  band) cost ``min(|O|, |U| + |S|)`` rank-one updates, not 4096.
- **Refits as conjugate-gradient steps** (the default, ``iters > 0``: :func:`sdfcodec_pca.kernels.refine`):
  the reader's error, one-sided at the bound voxels, minimised from the weighted fit by preconditioned
  nonlinear conjugate gradients, its Hessian products from the fit's Gram minus the active bound voxels, its
  preconditioner the fit's Cholesky factor: no Gram rebuilt, nothing refactorised. Leaves the exact rounds'
  error in total at 2 steps per round (tests/test_fast_encode.py).
- **Exact refits as updates** (``iters = 0``). Each truncation refit changes the weights of the voxels whose
  active state flipped only: the Gram and right-hand side are updated with those (or rebuilt from a
  reference, whichever touches fewer voxels), then refactorised (``k^3 / 3`` flops). Only the bound voxels
  are decoded to find the flips.

Blocks are independent: ``prange`` runs them on every core. With exact refits, results equal the batched
path's to float32 rounding (Grams, factorisations and solves in float32, as the batched path's).
"""

from __future__ import annotations

import importlib.util

import numpy as np

__all__ = ["available", "truncated_codes"]


def available() -> bool:
    """Whether the compiled kernel can run here: numba (optional, the extra ``fast``) is installed. Without it
    the batched torch path runs, slower, with the same codes. Checked without importing it: listing codecs and
    reading headers import this plugin and must stay light."""
    if not _FOUND:
        _FOUND.append(importlib.util.find_spec("numba") is not None)
    return _FOUND[0]


_FOUND: list[bool] = []


def truncated_codes(x: np.ndarray, w: np.ndarray, dt: np.ndarray, dec_b: np.ndarray, c0: np.ndarray,
                    ridge: float, rounds: int, iters: int = 0, tol: float = 0.0) -> np.ndarray:
    """Codes ``(n, k)`` float32 of blocks ``x`` ``(n, 4096)`` float32 under error weights ``w`` (same shape,
    finite, >= 0), refitted at most ``rounds`` times for the reader's truncation to ``[0, 1]``: ``dt`` is the
    decode matrix transposed ``(4096, k)`` (float32, columns orthonormal or not), ``dec_b`` the decode bias
    ``(4096,)``, ``c0`` the plain codes ``D (x - d)`` ``(n, k)`` (the ridge's centre), ``ridge`` the relative
    Tikhonov weight (times the mean weight). ``iters > 0``: the refits as at most that many conjugate-gradient
    steps (stopping where ``z^T grad`` falls below ``tol`` times its first value) instead of ``rounds`` exact
    active-set refits; the ridge is then the given weights' throughout (the exact refits take the current
    active set's)."""
    kernel = _kernel()
    dt = np.ascontiguousarray(dt, dtype=np.float32)
    gfull = dt.T.astype(np.float64) @ dt.astype(np.float64)  # D D^T: the Gram of weights all 1
    out = np.empty_like(c0)
    kernel(np.ascontiguousarray(x, dtype=np.float32), np.ascontiguousarray(w, dtype=np.float32), dt,
           np.ascontiguousarray(dec_b, dtype=np.float32), gfull.astype(np.float32),
           np.ascontiguousarray(c0, dtype=np.float32), np.float32(ridge), int(rounds), int(iters), np.float32(tol), out)
    return out


def _kernel():
    """The compiled kernel (:mod:`sdfcodec_pca.kernels`: compiled on first use, then cached on disk)."""
    from .kernels import kernel

    return kernel
