"""The pca codec's fast truncation-aware weighted encode on the CPU (what map writers run on fused blocks).

The same computation as :func:`sdfcodec.map.observed.encode_truncated` over :meth:`PCACodec.encode_weighted`
(a weighted least-squares fit with a ridge towards the plain projection, then active-set refits that give
weight 0 to the bound voxels a reader's truncation makes exact), one compiled kernel per block instead of
batched tensor operations. Why a kernel (numba): the exact fit needs one ``k x k`` Gram matrix and one Cholesky
factorisation per solve, and on the CPU torch's batched 64 x 64 Cholesky costs 3.5 plain projections of the
block (LAPACK's per-matrix overhead; 87 k flops of work), its batched Gram from an outer-product table 17.

What the kernel does instead, per block, in cache:

- **Grams from octree pieces** (:func:`gram_pieces`, :func:`sdfcodec_pca.kernels.plan`). With basis rows
  ``d_j`` (``D`` is ``(k, 4096)``), ``G(w) = sum_j w_j d_j d_j^T``. The Grams of the voxels of each node of the
  block's octree (the block, 8 cells of 8^3 voxels, 64 of 4^3, 512 of 2^3) are precomputed once per basis; each
  node takes a reference weight (0, 1 or the block's largest: fused maps' weights take three values, 0
  unobserved, 1, 51 near the surface, in spatially coherent regions), adds its piece times the change from
  its parent's reference, and each voxel whose weight differs from its 2^3 cell's reference adds its own
  rank-one term. A telescoping sum: exact for any weights. The references minimise the work (dynamic
  programming over the tree): on the benchmark's blocks 302 rank-one updates and 60 pieces a block instead of
  the 1,115 updates against the block's reference alone (kitchen half: 197 and 36 instead of 735).
- **Refits as conjugate-gradient steps** (the default, ``iters > 0``: :func:`sdfcodec_pca.kernels.refine`):
  the reader's error, one-sided at the bound voxels, minimised by preconditioned nonlinear conjugate
  gradients. They start from the fit *without* the bound voxels (weight 0 there, in the Gram and the
  right-hand side): the optimum decodes most bound voxels beyond their bound (bench blocks: 1,375 of 1,429,
  where the fit with them leaves 749), so that fit's Cholesky factor is nearly the optimum's Hessian's and
  preconditions well; each step's Hessian products add the bound voxels decoded inside their bound (few) to
  the fit's Gram: no Gram rebuilt, nothing refactorised. From the fit with the bound voxels (the earlier start)
  the same 6 steps left the error 5.7 % above its optimum on the bench's blocks; from this one 0.02 %
  (tests/test_fast_encode.py), the kitchen half's Chamfer 1.3-1.6 % lower. The bound voxels the fit
  decodes far beyond their bound sit out the steps (their rows are not gathered) and are checked after them:
  only those whose decode can have come back (their last distance beyond the bound less ``|d_j|`` times how
  far the code moved) are decoded again, about half of them on the bench's blocks.
  The gathered rows (``nb x k``, contiguous, in the core's cache) are read once per step: the direction's
  decode change and the counted voxels' Hessian terms together; their gradient terms are carried from step to
  step and corrected for the voxels whose state flipped only. Leaves the exact rounds' error in total or
  less at 2 steps per round (tests/test_fast_encode.py).
- **Right-hand sides in one product** (:func:`normal_rhs`): ``D diag(w) (x - d)`` of all blocks as a matrix
  product per slab of blocks, at the BLAS's speed, before the per-block pass (the weighted residuals and the
  weight sums in one compiled pass before it).
- **Exact refits as updates** (``iters = 0``). Each truncation refit changes the weights of the voxels whose
  active state flipped only: the Gram and right-hand side are updated with those (or rebuilt from a
  reference, whichever touches fewer voxels), then refactorised (``k^3 / 3`` flops). Only the bound voxels
  are decoded to find the flips.

Blocks are independent: ranges of them (:data:`KERNEL_CHUNKS`) run on every core (``sdfcodec.plugin.run_tiles``,
the kernel without the GIL). With exact refits, results equal the batched
path's to float32 rounding (Grams, factorisations and solves in float32, as the batched path's).
"""

from __future__ import annotations

import importlib.util

import numpy as np

from sdfcodec.plugin import run_tiles

__all__ = ["COMPILED_RESIDUALS_MIN", "KERNEL_CHUNKS", "PIECE_COST", "available", "gram_pieces", "normal_rhs", "truncated_codes"]


#: The blocks are handed to the cores in this many ranges (at least 64 blocks each, run_tiles' least), each range
#: with its own scratch.
KERNEL_CHUNKS = 256


def available() -> bool:
    """Whether the compiled kernel can run here: numba (optional, the extra ``fast``) is installed. Without it
    the batched torch path runs, slower, with the same codes. Checked without importing it: listing codecs and
    reading headers import this plugin and must stay light."""
    if not _FOUND:
        _FOUND.append(importlib.util.find_spec("numba") is not None)
    return _FOUND[0]


_FOUND: list[bool] = []


def truncated_codes(x: np.ndarray, w: np.ndarray, dt: np.ndarray, dec_b: np.ndarray, c0: np.ndarray,
                    ridge: float, rounds: int, iters: int = 0, tol: float = 0.0,
                    pieces: np.ndarray | None = None) -> np.ndarray:
    """Codes ``(n, k)`` float32 of blocks ``x`` ``(n, 4096)`` float32 under error weights ``w`` (same shape,
    finite, >= 0), refitted at most ``rounds`` times for the reader's truncation to ``[0, 1]``: ``dt`` is the
    decode matrix transposed ``(4096, k)`` (float32, columns orthonormal or not), ``dec_b`` the decode bias
    ``(4096,)``, ``c0`` the plain codes ``D (x - d)`` ``(n, k)`` (the ridge's centre), ``ridge`` the relative
    Tikhonov weight (times the mean weight). ``iters > 0``: the refits as at most that many conjugate-gradient
    steps (stopping where ``z^T grad`` falls below ``tol`` times its first value) instead of ``rounds`` exact
    active-set refits, from the fit without the bound voxels; the ridge is then the given weights' throughout
    (the exact refits take the current active set's).
    ``pieces``: :func:`gram_pieces` of ``dt`` where the caller keeps it (else computed here)."""
    kernel, row_norms = _kernel()
    dt = np.ascontiguousarray(dt, dtype=np.float32)
    if pieces is None:
        pieces = gram_pieces(dt)
    x = np.ascontiguousarray(x, dtype=np.float32)
    w = np.ascontiguousarray(w, dtype=np.float32)
    dec_b = np.ascontiguousarray(dec_b, dtype=np.float32)
    rhs, wsum = normal_rhs(x, w, dt, dec_b, drop_bound=iters > 0)
    out = np.empty_like(c0)
    gfull, c0, rn = _full_gram(pieces, dt.shape[1]), np.ascontiguousarray(c0, dtype=np.float32), row_norms(dt)

    def blocks(a: int, b: int) -> None:
        kernel(a, b, x, w, dt, dec_b, gfull, pieces, np.float32(PIECE_COST), c0, rhs, wsum, np.float32(ridge),
               int(rounds), int(iters), np.float32(tol), out, rn)

    # the blocks in KERNEL_CHUNKS ranges, taken in turn by one thread per core (each range's fit is independent)
    run_tiles(len(x), blocks, rows=max(1, -(-len(x) // KERNEL_CHUNKS)))
    return out


#: What adding one precomputed piece costs against one voxel's rank-one update (:func:`gram_pieces`): the
#: octree plan minimises voxels + this times pieces (a piece is k (k + 1) / 2 additions read from the table in
#: the cache, an update as many multiply-adds). Measured per block on the bench's blocks (CPU time, loaded
#: machine): 1.0, 1.5, 2 and 3 within the noise (302-323 updates, 60-51 pieces).
PIECE_COST = 1.5
_PIECES_MAX_K = 128  # the octree's table is 585 packed Grams: 19 MB at k = 128; beyond, the block's Gram only


_BOUND_EPS = 1e-6  # as the kernel's: a stored value within this of 0 or 1 sits at a bound
_RHS_SLAB = 256  # blocks per product of normal_rhs: their weighted residuals (4 MiB) stay in the cache


def normal_rhs(x: np.ndarray, w: np.ndarray, dt: np.ndarray, dec_b: np.ndarray,
               drop_bound: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """The right-hand sides ``D diag(w_i) (x_i - d)`` ``(n, k)`` float32 and weight sums ``(n,)`` float64 of blocks
    ``x`` under weights ``w`` (both ``(n, 4096)`` float32; ``dt`` ``(4096, k)``, ``dec_b`` ``(4096,)``; with
    ``drop_bound`` the voxels stored at a bound, 0 or 1, weigh 0 in the sides, not in the sums): one matrix
    product ``(w * (x - d)) @ dt`` per slab of blocks, at the BLAS's speed (the same work as the plain projection),
    instead of a per-block loop over the voxels whose weight differs from a reference (4-5 projections' time)."""
    rhs = np.empty((len(x), dt.shape[1]), np.float32)
    if len(x) >= COMPILED_RESIDUALS_MIN:
        return _compiled_rhs(x, w, dt, dec_b, drop_bound, rhs)
    wsum = w.sum(axis=1, dtype=np.float64)
    for i in range(0, len(x), _RHS_SLAB):
        r = np.subtract(x[i:i + _RHS_SLAB], dec_b)
        r *= w[i:i + _RHS_SLAB]
        if drop_bound:
            xs = x[i:i + _RHS_SLAB]
            r[(xs >= 1 - _BOUND_EPS) | (xs <= _BOUND_EPS)] = 0
        np.matmul(r, dt, out=rhs[i:i + _RHS_SLAB])
    return rhs, wsum


#: From this many blocks, :func:`normal_rhs` forms the weighted residuals and weight sums in one compiled pass on
#: every core (:func:`sdfcodec_pca.kernels.residuals`): numpy's five single-thread passes and masked store took
#: 1-1.5 projections' time, a serial share that both cores' pass leaves (bench blocks). Fewer blocks keep numpy:
#: a first small encode (a search's query shapes) then loads one compiled kernel, not two. The same values, but
#: for a value within float32 rounding of a bound's 1e-6: the compiled pass compares in float64, as the kernel.
COMPILED_RESIDUALS_MIN = 1024


def _compiled_rhs(x: np.ndarray, w: np.ndarray, dt: np.ndarray, dec_b: np.ndarray, drop_bound: bool,
                  rhs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`normal_rhs` with the residuals from :func:`sdfcodec_pca.kernels.residuals`, into ``rhs``."""
    from .kernels import residuals

    x, w = np.ascontiguousarray(x, dtype=np.float32), np.ascontiguousarray(w, dtype=np.float32)
    dec_b = np.ascontiguousarray(dec_b, dtype=np.float32)
    wsum = np.empty(len(x), np.float64)
    r = np.empty((min(len(x), _RHS_SLAB), x.shape[1]), np.float32)
    for i in range(0, len(x), _RHS_SLAB):
        sl = slice(i, i + _RHS_SLAB)
        xs, ws, rs, wss = x[sl], w[sl], r[:len(x[sl])], wsum[sl]
        run_tiles(len(xs), lambda a, b: residuals(a, b, xs, ws, dec_b, drop_bound, rs, wss))
        np.matmul(rs, dt, out=rhs[sl])
    return rhs, wsum


def gram_pieces(dt: np.ndarray) -> np.ndarray:
    """The Gram ``sum_j d_j d_j^T`` over the voxels of each node of the block's octree (the block, its 8 cells
    of 8^3 voxels, 64 of 4^3, 512 of 2^3; numbered level by level, C order within each), lower triangles packed
    row by row: ``(585, k (k + 1) / 2)`` float32 for the decode matrix transposed ``dt`` ``(4096, k)``, summed in
    float64. For k above 128 the block's alone ``(1, k (k + 1) / 2)``. The compiled pass builds each block's
    Gram from these and the voxels they leave (:func:`sdfcodec_pca.kernels.plan`): exact, whatever the weights."""
    k = dt.shape[1]
    d = np.asarray(dt, dtype=np.float64).reshape(8, 2, 8, 2, 8, 2, k).transpose(0, 2, 4, 1, 3, 5, 6)
    rows, cols = np.tril_indices(k)
    if k > _PIECES_MAX_K:
        g = np.asarray(dt, dtype=np.float64).T @ np.asarray(dt, dtype=np.float64)
        return np.ascontiguousarray(g[rows, cols][None], dtype=np.float32)
    cells = d.reshape(512, 8, k)
    level = np.einsum("cva,cvb->cab", cells, cells).reshape(8, 8, 8, k, k)  # the 2^3 cells, C order
    levels = [level]
    for _ in range(3):  # each coarser level: the sum of its 8 children
        n = level.shape[0] // 2
        level = level.reshape(n, 2, n, 2, n, 2, k, k).sum(axis=(1, 3, 5))
        levels.append(level)
    return np.ascontiguousarray(np.concatenate([lv.reshape(-1, k, k)[:, rows, cols] for lv in levels[::-1]]),
                                dtype=np.float32)


def _full_gram(pieces: np.ndarray, k: int) -> np.ndarray:
    """The block's Gram ``(k, k)`` float32 (both triangles) from its packed piece (the first row of ``pieces``)."""
    rows, cols = np.tril_indices(k)
    g = np.zeros((k, k), np.float32)
    g[rows, cols] = pieces[0]
    g[cols, rows] = pieces[0]
    return g


def _kernel():
    """The compiled kernel and :func:`~sdfcodec_pca.kernels.row_norms` (:mod:`sdfcodec_pca.kernels`: compiled on
    first use, then cached on disk)."""
    from .kernels import kernel, row_norms

    return kernel, row_norms
