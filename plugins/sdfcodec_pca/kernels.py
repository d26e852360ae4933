"""The compiled per-block steps of :mod:`sdfcodec_pca.truncated` (numba; imported only when that pass runs).

Module-level functions, so numba caches their machine code on disk (functions nested in another cannot be
cached, and compiling them takes tens of seconds: every process would pay it)."""

from __future__ import annotations

import numpy as np
from numba import config, njit, prange

# numba tries TBB first and warns (at the first parallel call) when the installed TBB is older than it supports;
# OpenMP is what torch's CPU build runs on too and, unlike numba's own workqueue, may be entered from several
# threads at once. A layer the user chose (NUMBA_THREADING_LAYER) is kept: only the order of the default's tries
# changes.
config.THREADING_LAYER_PRIORITY = ["omp", "tbb", "workqueue"]

__all__ = ["kernel"]

_LINE_STEPS = 4  # Newton steps of the line search along each direction
_BOUND_EPS = 1e-6  # a stored value within this of 0 or 1 sits at a bound (as encode_truncated tests it)
#: fastmath without 'nnan' and 'ninf': reordered sums vectorise, the NaN and definiteness checks stay
_FAST = {"nsz", "arcp", "contract", "afn", "reassoc"}


@njit(fastmath=_FAST, cache=True)
def add_rows(g, dt, idx, scale, m):
    """g (k, k) lower triangle += sum_t scale[t] d_idx[t] d_idx[t]^T: four voxels by two rows of g at a time
    (each load of a basis row feeds two multiply-adds: 1.35x the one-row loop here)."""
    k = g.shape[0]
    t = 0
    while t + 4 <= m:
        r0, r1, r2, r3 = dt[idx[t]], dt[idx[t + 1]], dt[idx[t + 2]], dt[idx[t + 3]]
        s0, s1, s2, s3 = scale[t], scale[t + 1], scale[t + 2], scale[t + 3]
        for a in range(0, k - 1, 2):
            u0, u1, u2, u3 = s0 * r0[a], s1 * r1[a], s2 * r2[a], s3 * r3[a]
            v0, v1, v2, v3 = s0 * r0[a + 1], s1 * r1[a + 1], s2 * r2[a + 1], s3 * r3[a + 1]
            ga, gb = g[a], g[a + 1]
            for b in range(a + 1):
                x0, x1, x2, x3 = r0[b], r1[b], r2[b], r3[b]
                ga[b] += u0 * x0 + u1 * x1 + u2 * x2 + u3 * x3
                gb[b] += v0 * x0 + v1 * x1 + v2 * x2 + v3 * x3
            gb[a + 1] += v0 * r0[a + 1] + v1 * r1[a + 1] + v2 * r2[a + 1] + v3 * r3[a + 1]
        if k % 2:
            a = k - 1
            u0, u1, u2, u3 = s0 * r0[a], s1 * r1[a], s2 * r2[a], s3 * r3[a]
            ga = g[a]
            for b in range(k):
                ga[b] += u0 * r0[b] + u1 * r1[b] + u2 * r2[b] + u3 * r3[b]
        t += 4
    while t < m:
        r0, s0 = dt[idx[t]], scale[t]
        for a in range(k):
            u0 = s0 * r0[a]
            ga = g[a]
            for b in range(a + 1):
                ga[b] += u0 * r0[b]
        t += 1


@njit(fastmath=_FAST, cache=True)
def build(g, rhs, wc, xi, dt, dec_b, gfull, c0i, idx, scale):
    """Gram (lower triangle) and unregularised right-hand side D diag(wc) (x - d) of weights wc, from the
    cheaper reference (0 or all ones); returns the weight sum."""
    n_vox, k = dt.shape
    nz = 0
    nd = 0
    wsum = 0.0
    for j in range(n_vox):
        nz += wc[j] != 0
        nd += wc[j] != 1
        wsum += wc[j]
    ref = 0.0 if nz <= nd else 1.0
    m = 0
    for j in range(n_vox):
        if wc[j] != ref:
            idx[m] = j
            scale[m] = wc[j] - ref
            m += 1
    for a in range(k):
        for b in range(a + 1):
            g[a, b] = ref * gfull[a, b]
        rhs[a] = ref * c0i[a]  # D (x - d) = c0: the plain projection
    add_rows(g, dt, idx, scale, m)
    for t in range(m):
        j = idx[t]
        r = scale[t] * (xi[j] - dec_b[j])
        for a in range(k):
            rhs[a] += r * dt[j, a]
    return wsum


@njit(fastmath=_FAST, cache=True)
def chol_solve(chol, b, out):
    """out = (L L^T)^-1 b for the Cholesky factor L in the lower triangle of ``chol`` (k, k); ``out`` may be ``b``.
    Forward L y = b, then back L^T x = y by columns of L^T (rows of L)."""
    k = b.shape[0]
    for i in range(k):
        ci = chol[i]
        acc = b[i]
        for t in range(i):
            acc -= ci[t] * out[t]
        out[i] = acc / ci[i]
    for i in range(k - 1, -1, -1):
        out[i] /= chol[i, i]
        ci, v = chol[i], out[i]
        for t in range(i):
            out[t] -= v * ci[t]


@njit(fastmath=_FAST, cache=True)
def solve(g, rhs, c0i, lam, chol, panel, sol):
    """sol = (G + lam I)^-1 (rhs + lam c0) by Cholesky (float32, as the batched path): right-looking in
    panels of four columns, the trailing triangle updated four columns at a time (the Gram's loop: 1.8
    projections per factorisation here, against 3.1 unblocked and 3.5 for torch's batched LAPACK); False
    where not positive definite or not finite."""
    k = g.shape[0]
    for i in range(k):
        for j in range(i + 1):
            chol[i, j] = g[i, j]
        chol[i, i] += lam
    for jb in range(0, k, 4):
        je = min(jb + 4, k)
        for j in range(jb, je):  # the panel, unblocked
            d = chol[j, j]
            if not d > 0:
                return False
            d = np.sqrt(d)
            chol[j, j] = d
            for r in range(j + 1, k):
                chol[r, j] /= d
            for j2 in range(j + 1, je):
                c = chol[j2, j]
                for r in range(j2, k):
                    chol[r, j2] -= chol[r, j] * c
        for q in range(je - jb):  # its columns below it, contiguous
            for r in range(k):
                panel[q, r] = chol[r, jb + q] if r >= je else 0
        if je - jb == 4:
            p0, p1, p2, p3 = panel[0], panel[1], panel[2], panel[3]
            for r in range(je, k):
                u0, u1, u2, u3 = p0[r], p1[r], p2[r], p3[r]
                cr = chol[r]
                for b in range(je, r + 1):
                    cr[b] -= u0 * p0[b] + u1 * p1[b] + u2 * p2[b] + u3 * p3[b]
        else:
            for q in range(je - jb):
                pq = panel[q]
                for r in range(je, k):
                    u, cr = pq[r], chol[r]
                    for b in range(je, r + 1):
                        cr[b] -= u * pq[b]
    for i in range(k):
        sol[i] = rhs[i] + lam * c0i[i]
    chol_solve(chol, sol, sol)
    for i in range(k):
        if not np.isfinite(sol[i]):
            return False
    return True


@njit(fastmath=_FAST, cache=True)
def decode_at(code, dt, dec_b, vox, nb, out):
    """out[:nb] = the decode of ``code`` at voxels ``vox[:nb]`` (reordered sums: vector dot products)."""
    k = dt.shape[1]
    for t in range(nb):
        r = dt[vox[t]]
        d = np.float32(0)
        for a in range(k):
            d += code[a] * r[a]
        out[t] = d + dec_b[vox[t]]


@njit(fastmath=_FAST, cache=True)
def symv(g, v, out):
    """out = G v for the symmetric G whose lower triangle ``g`` (k, k) holds (k^2 multiply-adds)."""
    k = v.shape[0]
    for a in range(k):
        out[a] = 0
    for a in range(k):
        ga, va = g[a], v[a]
        acc = np.float32(0)
        for b in range(a):
            acc += ga[b] * v[b]
            out[b] += ga[b] * va
        out[a] += acc + ga[a] * va


@njit(fastmath=_FAST, cache=True)
def refine(c, g, lam, rhs, c0i, chol, xi, wi, dt, dec_b, bound, nb, iters, tol):
    """The truncation refits as preconditioned nonlinear conjugate gradients (Polak-Ribiere+) on the reader's
    error itself, ``f(c) = sum_j w_j r_j^2 + lam |c - c0|^2`` over the voxels not at a bound decoded beyond it
    (``r`` the residual of the decode; the active set follows ``c`` at every step), from the weighted fit ``c``
    (k,) float32, updated in place. No Gram is rebuilt nor refactorised: ``G + lam I`` (lower triangle ``g``
    plus ``lam``, of all the weights) gives the Hessian minus the active bound voxels' rank-one terms, and its
    Cholesky factor ``chol`` preconditions. Per step: one G v product, one preconditioner solve and the basis
    rows of the ``nb`` bound voxels ``bound`` twice (2 k nb multiply-adds; measured 4-5 plain projections of
    time a step on the bench's blocks, against about 15 for an exact round, which rebuilds a Gram from the
    flipped voxels and refactorises it). Stops after ``iters`` steps or when ``z^T grad`` falls below ``tol``
    times its first value."""
    k = c.shape[0]
    dec = np.empty(nb, np.float32)
    q = np.empty(nb, np.float32)
    decode_at(c, dt, dec_b, bound, nb, dec)
    hc = np.empty(k, np.float32)
    symv(g, c, hc)
    for a in range(k):
        hc[a] += lam * c[a] - rhs[a] - lam * c0i[a]  # the gradient of the full-weight quadratic
    grad = np.empty(k, np.float32)
    z = np.empty(k, np.float32)
    zprev = np.zeros(k, np.float32)
    p = np.zeros(k, np.float32)
    hp = np.empty(k, np.float32)
    gz0 = np.float32(0)
    gzprev = np.float32(0)
    for it in range(iters):
        for a in range(k):
            grad[a] = hc[a]
        for t in range(nb):  # minus the active bound voxels' terms
            j = bound[t]
            d = dec[t]
            if (d >= 1) if xi[j] >= 1 - _BOUND_EPS else (d <= 0):
                r = wi[j] * (d - xi[j])
                row = dt[j]
                for a in range(k):
                    grad[a] -= r * row[a]
        chol_solve(chol, grad, z)
        gz = np.float32(0)
        gzo = np.float32(0)
        for a in range(k):
            gz += grad[a] * z[a]
            gzo += grad[a] * zprev[a]
        if it == 0:
            gz0 = gz
        if not gz > tol * gz0:
            break
        beta = max(np.float32(0), (gz - gzo) / gzprev) if it else np.float32(0)
        slope = np.float32(0)
        for a in range(k):
            p[a] = -z[a] + beta * p[a]
            zprev[a] = z[a]
            slope += grad[a] * p[a]
        if not slope < 0:  # not a descent direction any more: restart from the preconditioned gradient
            slope = np.float32(0)
            for a in range(k):
                p[a] = -z[a]
                slope -= grad[a] * z[a]
        gzprev = gz
        symv(g, p, hp)
        php = np.float32(0)  # p^T (G + lam I) p and p^T (G + lam I) c - p^T b: the full-weight quadratic
        s0 = np.float32(0)
        for a in range(k):
            hp[a] += lam * p[a]
            php += p[a] * hp[a]
            s0 += p[a] * hc[a]
        decode_at(p, dt, dec_b, bound, nb, q)
        for t in range(nb):
            q[t] -= dec_b[bound[t]]  # decode_at adds the bias: the direction's change only
        # exact line search: the error along p is piecewise quadratic and convex; Newton on its derivative
        # (piecewise linear) from 0 lands on its minimum in a few steps, each O(nb)
        alpha = np.float32(0)
        for _ in range(_LINE_STEPS):
            d1 = s0 + alpha * php
            d2 = php
            for t in range(nb):
                j = bound[t]
                d = dec[t] + alpha * q[t]
                if (d >= 1) if xi[j] >= 1 - _BOUND_EPS else (d <= 0):
                    d1 -= wi[j] * (d - xi[j]) * q[t]
                    d2 -= wi[j] * q[t] * q[t]
            if not d2 > 0:
                break
            step = d1 / d2
            alpha -= step
            if abs(step) <= 1e-4 * abs(alpha):
                break
        if not alpha > 0:
            break
        for a in range(k):
            c[a] += alpha * p[a]
            hc[a] += alpha * hp[a]
        for t in range(nb):
            dec[t] += alpha * q[t]


@njit(parallel=True, fastmath=False, cache=True)
def kernel(x, w, dt, dec_b, gfull, c0, ridge, rounds, iters, tol, out):
    """See :func:`sdfcodec_pca.truncated.truncated_codes` (``out`` ``(n, k)`` float32 receives the codes)."""
    n = x.shape[0]
    n_vox, k = dt.shape
    for i in prange(n):
        xi, wi, c0i = x[i], w[i], c0[i]
        g = np.zeros((k, k), np.float32)
        rhs = np.zeros(k, np.float32)
        chol = np.zeros((k, k), np.float32)
        panel = np.zeros((4, k), np.float32)
        sol = np.zeros(k, np.float32)
        idx = np.empty(n_vox, np.int64)
        scale = np.empty(n_vox, np.float32)
        wc = wi.copy()
        wsum = build(g, rhs, wc, xi, dt, dec_b, gfull, c0i, idx, scale)
        lam = np.float32((ridge / n_vox) * max(wsum, 1e-12))
        if not solve(g, rhs, c0i, lam, chol, panel, sol):
            out[i] = c0i
            continue
        for a in range(k):
            out[i, a] = sol[a]
        # the bound voxels: observed and stored at d_max (1) or d_min (0)
        nb = 0
        for j in range(n_vox):
            if wi[j] > 0 and (xi[j] >= 1 - _BOUND_EPS or xi[j] <= _BOUND_EPS):
                idx[nb] = j
                nb += 1
        if nb == 0:
            continue
        bound = idx[:nb].copy()
        if iters > 0:
            refine(out[i], g, lam, rhs, c0i, chol, xi, wi, dt, dec_b, bound, nb, iters, tol)
            continue
        active = np.zeros(nb, np.bool_)
        flip = np.empty(nb, np.int64)
        dec = np.empty(nb, np.float32)
        for _ in range(rounds):
            nf = 0
            decode_at(out[i], dt, dec_b, bound, nb, dec)  # the bound voxels only, as the codes stored
            for t in range(nb):
                j = bound[t]
                d = dec[t]
                now = (d >= 1) if xi[j] >= 1 - _BOUND_EPS else (d <= 0)
                if now != active[t]:
                    flip[nf] = t
                    nf += 1
            if nf == 0:
                break
            nz = 0
            nd = 0
            for t in range(nf):
                active[flip[t]] = not active[flip[t]]
            for j in range(n_vox):
                nz += wc[j] != 0
                nd += wc[j] != 1
            for t in range(nf):  # the new weights: 0 where active, the given weight elsewhere
                j = bound[flip[t]]
                wn = np.float32(0.0) if active[flip[t]] else wi[j]
                nz += (wn != 0) - (wc[j] != 0)
                nd += (wn != 1) - (wc[j] != 1)
                scale[t] = wn - wc[j]
                wc[j] = wn
            if nf < min(nz, nd):  # update with the flipped voxels only
                for t in range(nf):
                    j = bound[flip[t]]
                    idx[t] = j
                    r = scale[t] * (xi[j] - dec_b[j])
                    for a in range(k):
                        rhs[a] += r * dt[j, a]
                add_rows(g, dt, idx, scale, nf)
                wsum = 0.0
                for j in range(n_vox):
                    wsum += wc[j]
            else:
                wsum = build(g, rhs, wc, xi, dt, dec_b, gfull, c0i, idx, scale)
            lam = np.float32((ridge / n_vox) * max(wsum, 1e-12))
            if not solve(g, rhs, c0i, lam, chol, panel, sol):  # as the batched path: the plain projection
                out[i] = c0i
                break
            for a in range(k):
                out[i, a] = sol[a]
