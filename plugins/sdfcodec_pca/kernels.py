"""The compiled per-block steps of :mod:`sdfcodec_pca.truncated` (numba; imported only when that pass runs).

Module-level functions, so numba caches their machine code on disk (functions nested in another cannot be
cached, and compiling them takes tens of seconds: every process would pay it)."""

from __future__ import annotations

import numpy as np
from numba import njit

from .vecdot import dot, dot4

__all__ = ["kernel"]

_LINE_STEPS = 4  # Newton steps of the line search along each direction
_BOUND_EPS = 1e-6  # a stored value within this of 0 or 1 sits at a bound (as encode_truncated tests it)
#: Bound voxels that the fit decodes more than this beyond their bound sit out the refits' steps (the fit and
#: the steps give them weight 0 anyway); after the steps, those that came back within it join and the steps
#: rerun, at most this many rounds, the last bringing in every voxel inside its bound. On the bench's blocks
#: none decoded 0.05 beyond came back inside in 6 steps; they are 72 % of the bound voxels.
_FAR = np.float32(0.05)
_FAR_ROUNDS = 3
#: fastmath flags that keep a sum's order the source's: no 'reassoc'. With it the code generator chose the order of
#: a sum's additions, and chose it differently for a kernel compiled in the process and the same kernel loaded from
#: numba's on-disk cache: the same blocks got different codes (a map written by the first process of a fresh
#: install differed from the next one's). :func:`sdfcodec_pca.vecdot.dot` gives the dot products their vectors
#: back. No 'afn'/'arcp' either (approximate square roots and reciprocals); 'contract' fuses multiply-adds.
_FAST = {"nsz", "contract"}
#: The octree of Gram pieces (:func:`plan`): the block, its 8 cells of 8^3, 64 of 4^3 and 512 of 2^3 voxels,
#: numbered level by level (the first id of each level here), C order within a level
_OFF = np.array([0, 1, 9, 73], np.int64)
_NODES = 585


@njit(fastmath=_FAST, cache=True)
def add_rows(g, dt, idx, scale, m):
    """g (k, k) += sum_t scale[t] d_idx[t] d_idx[t]^T in the lower triangle, four voxels at a time. Row ``a``
    runs to the end of its group of eight columns (``(a | 7) + 1``), past the diagonal: whole vectors of eight,
    no short ragged loops, 0.56x the multiply-adds of whole rows (k = 64; measured 0.7-0.85x their time for the
    same lower triangle, bit for bit). Readers use the lower triangle only; above it, ``g`` holds partial sums."""
    k = g.shape[0]
    t = 0
    while t + 4 <= m:
        r0, r1, r2, r3 = dt[idx[t]], dt[idx[t + 1]], dt[idx[t + 2]], dt[idx[t + 3]]
        s0, s1, s2, s3 = scale[t], scale[t + 1], scale[t + 2], scale[t + 3]
        for a in range(k):
            u0, u1, u2, u3 = s0 * r0[a], s1 * r1[a], s2 * r2[a], s3 * r3[a]
            ga = g[a]
            for b in range(min(k, (a | 7) + 1)):
                ga[b] += u0 * r0[b] + u1 * r1[b] + u2 * r2[b] + u3 * r3[b]
        t += 4
    while t < m:
        r0, s0 = dt[idx[t]], scale[t]
        for a in range(k):
            u0 = s0 * r0[a]
            ga = g[a]
            for b in range(min(k, (a | 7) + 1)):
                ga[b] += u0 * r0[b]
        t += 1


@njit(fastmath=_FAST, cache=True)
def reference_weight(w):
    """(the cheaper reference weight, 0.0 or 1.0: the one fewer voxels differ from; the sum of ``w``): a block's
    Gram and right-hand side start from the reference's (none, or the plain projection's) and add only the
    voxels whose weight differs from it."""
    nz = 0
    nd = 0
    wsum = 0.0
    for j in range(len(w)):
        nz += w[j] != 0
        nd += w[j] != 1
        wsum += w[j]
    return (0.0 if nz <= nd else 1.0), wsum


@njit(fastmath=_FAST, cache=True)
def build(g, rhs, wc, xi, dt, dec_b, gfull, c0i, idx, scale):
    """Gram (whole rows; readers use the lower triangle) and unregularised right-hand side D diag(wc) (x - d) of weights wc, from the
    cheaper reference (0 or all ones); returns the weight sum."""
    n_vox, k = dt.shape
    ref, wsum = reference_weight(wc)
    m = 0
    for j in range(n_vox):
        if wc[j] != ref:
            idx[m] = j
            scale[m] = wc[j] - ref
            m += 1
    for a in range(k):
        for b in range(k):  # whole rows: add_rows adds past the diagonal (gfull is symmetric)
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
        out[i] = (b[i] - dot(ci, out, i)) / ci[i]
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
    """out[:nb] = the decode of ``code`` at voxels ``vox[:nb]`` (vector dot products, :func:`dot`), four voxels
    per pass over ``code`` (:func:`dot4`: the same sums, four independent chains)."""
    k = dt.shape[1]
    t = 0
    while t + 4 <= nb:
        j0, j1, j2, j3 = vox[t], vox[t + 1], vox[t + 2], vox[t + 3]
        a0, a1, a2, a3 = dot4(code, dt[j0], dt[j1], dt[j2], dt[j3], k)
        out[t], out[t + 1], out[t + 2], out[t + 3] = a0 + dec_b[j0], a1 + dec_b[j1], a2 + dec_b[j2], a3 + dec_b[j3]
        t += 4
    while t < nb:
        out[t] = dot(code, dt[vox[t]], k) + dec_b[vox[t]]
        t += 1


@njit(fastmath=_FAST, cache=True)
def symv(g, v, out):
    """out = G v for the symmetric G whose lower triangle ``g`` (k, k) holds (k^2 multiply-adds)."""
    k = v.shape[0]
    for a in range(k):
        out[a] = 0
    for a in range(k):
        ga, va = g[a], v[a]
        for b in range(a):
            out[b] += ga[b] * va
        out[a] += dot(ga, v, a) + ga[a] * va


@njit(fastmath=_FAST, cache=True)
def plan(wi, cand, piece_cost, deep, cost, choice, idx, scale, nodes, node_scale):
    """How to build the Gram of weights ``wi`` (4096,) from the octree pieces (:func:`add_pieces`): fills
    ``nodes``/``node_scale`` with the pieces to add (node id, weight change) and ``idx``/``scale`` with the voxels
    left to add one by one (rank-one updates); returns (voxels, pieces). Each node of the octree (the block, its
    8^3, 4^3 and 2^3 cells) holds a reference weight (one of ``cand``; the root's parent holds 0); a node whose
    reference differs from its parent's adds its piece times the difference, and each voxel whose weight
    differs from its 2^3 cell's reference adds its own term: a telescoping sum, every voxel weighs exactly its
    weight. The references minimise voxels + ``piece_cost`` times pieces (dynamic programming over the tree,
    ``cost`` (585, 3) and ``choice`` (585,) scratch). ``deep`` False: the block's piece only (no cell table)."""
    nc = cand.shape[0]
    for u in range(_NODES):
        for r in range(nc):
            cost[u, r] = 0
    c0, c1, c2 = cand[0], cand[1], cand[2]
    for xx in range(16):  # the 2^3 cells: voxels whose weight differs from each candidate reference
        for yy in range(16):
            row = wi[(xx * 16 + yy) * 16:(xx * 16 + yy + 1) * 16]
            base = 73 + ((xx >> 1) * 8 + (yy >> 1)) * 8
            for zz in range(0, 16, 2):
                u = base + (zz >> 1)
                a, b = row[zz], row[zz + 1]
                cost[u, 0] += np.float32((a != c0) + (b != c0))
                cost[u, 1] += np.float32((a != c1) + (b != c1))
                cost[u, 2] += np.float32((a != c2) + (b != c2))
    for lv in range(3, 0, -1):  # bottom up: a subtree's cost under each inherited reference, into its parent
        n = 1 << lv
        h = n >> 1
        pc = piece_cost if deep else np.float32(1e30)
        for x in range(n):
            for y in range(n):
                for z in range(n):
                    u = _OFF[lv] + (x * n + y) * n + z
                    par = _OFF[lv - 1] + ((x >> 1) * h + (y >> 1)) * h + (z >> 1)
                    for r in range(nc):
                        best = cost[u, r]
                        for r2 in range(nc):
                            if r2 != r and pc + cost[u, r2] < best:
                                best = pc + cost[u, r2]
                        cost[par, r] += best
    npc = 0
    for lv in range(4):  # top down: each node's reference, given its parent's
        n = 1 << lv
        h = n >> 1
        pc = piece_cost if deep or lv == 0 else np.float32(1e30)
        for x in range(n):
            for y in range(n):
                for z in range(n):
                    u = _OFF[lv] + (x * n + y) * n + z
                    inh = 0 if lv == 0 else choice[_OFF[lv - 1] + ((x >> 1) * h + (y >> 1)) * h + (z >> 1)]
                    pick = inh
                    best = cost[u, inh]
                    for r2 in range(nc):
                        if r2 != inh and pc + cost[u, r2] < best:
                            best = pc + cost[u, r2]
                            pick = r2
                    choice[u] = pick
                    if pick != inh:
                        nodes[npc] = u if deep else 0
                        node_scale[npc] = cand[pick] - cand[inh]
                        npc += 1
    m = 0
    for c in range(512):
        cx, cy, cz = c >> 6, (c >> 3) & 7, c & 7
        ref = cand[choice[73 + c]]
        for dx in range(2):
            for dy in range(2):
                for dz in range(2):
                    j = ((2 * cx + dx) * 16 + 2 * cy + dy) * 16 + 2 * cz + dz
                    if wi[j] != ref:
                        idx[m] = j
                        scale[m] = wi[j] - ref
                        m += 1
    return m, npc


@njit(fastmath=_FAST, cache=True)
def add_pieces(g, gp, pieces, nodes, node_scale, npc):
    """g (k, k) = sum_t node_scale[t] times piece nodes[t] in the lower triangle, 0 above it (rows of ``pieces``: packed lower
    triangles, row by row), summed in the packed scratch ``gp`` (one contiguous pass per piece)."""
    k = g.shape[0]
    gp[:] = 0
    for t in range(npc):
        s, pc = node_scale[t], pieces[nodes[t]]
        for e in range(gp.shape[0]):
            gp[e] += s * pc[e]
    off = 0
    for a in range(k):
        ga = g[a]
        for b in range(a + 1):
            ga[b] = gp[off + b]
        for b in range(a + 1, k):
            ga[b] = 0  # whole rows: add_rows adds to them
        off += a + 1


@njit(fastmath=_FAST, cache=True)
def sub_rows(acc, rows, sel, coef, m):
    """acc (k,) -= sum_t coef[t] rows[sel[t]] over t < m, four rows at a time (one read and write of ``acc`` per
    four rows)."""
    k = acc.shape[0]
    t = 0
    while t + 4 <= m:
        r0, r1, r2, r3 = rows[sel[t]], rows[sel[t + 1]], rows[sel[t + 2]], rows[sel[t + 3]]
        s0, s1, s2, s3 = coef[t], coef[t + 1], coef[t + 2], coef[t + 3]
        for a in range(k):
            acc[a] -= s0 * r0[a] + s1 * r1[a] + s2 * r2[a] + s3 * r3[a]
        t += 4
    while t < m:
        r0, s0 = rows[sel[t]], coef[t]
        for a in range(k):
            acc[a] -= s0 * r0[a]
        t += 1


@njit(fastmath=_FAST, cache=True)
def dots_acc(p, rows, nb, coef, q, acc):
    """One pass over the gathered rows ``rows`` (>= nb, k), four at a time: q[t] = rows[t] . p for t < nb, and
    acc (k,) += sum_t coef[t] q[t] rows[t] (rows whose ``coef`` is 0 add nothing; each row is read once for both)."""
    k = rows.shape[1]
    t = 0
    while t + 4 <= nb:
        r0, r1, r2, r3 = rows[t], rows[t + 1], rows[t + 2], rows[t + 3]
        a0, a1, a2, a3 = dot4(p, r0, r1, r2, r3, k)
        q[t], q[t + 1], q[t + 2], q[t + 3] = a0, a1, a2, a3
        s0, s1, s2, s3 = coef[t] * a0, coef[t + 1] * a1, coef[t + 2] * a2, coef[t + 3] * a3
        if s0 != 0 or s1 != 0 or s2 != 0 or s3 != 0:
            for a in range(k):
                acc[a] += s0 * r0[a] + s1 * r1[a] + s2 * r2[a] + s3 * r3[a]
        t += 4
    while t < nb:
        r0 = rows[t]
        a0 = dot(p, r0, k)
        q[t] = a0
        s0 = coef[t] * a0
        if s0 != 0:
            for a in range(k):
                acc[a] += s0 * r0[a]
        t += 1


@njit(fastmath=_FAST, cache=True)
def refine(c, g, lam, rhs, c0i, chol, rows, xb, wb, sg, bv, db, nb, iters, tol, dec, q, wa, sel):
    """The truncation refits as preconditioned nonlinear conjugate gradients (Polak-Ribiere+) on the reader's
    error itself, ``f(c) = sum_j w_j r_j^2 + lam |c - c0|^2`` over the voxels not at a bound decoded beyond it
    (``r`` the residual of the decode; the set follows ``c`` at every step), from ``c`` (k,) float32, updated in
    place: the fit without the bound voxels. No Gram is rebuilt nor refactorised: ``G + lam I`` (lower triangle
    ``g`` plus ``lam``, of the weights without the bound voxels) gives the Hessian once the bound voxels
    decoded inside their bound add their rank-one terms, and its Cholesky factor ``chol`` preconditions. The
    ``nb`` bound voxels come gathered: their basis rows ``rows`` (>= nb, k: contiguous, so a pass reads them in
    order from the cache), values ``xb``, weights ``wb``, bound ``bv`` and its side ``sg`` (1 and +1 at d_max:
    counted where the decode is < 1; 0 and -1 at d_min: counted where it is > 0) and decode bias ``db``;
    ``dec``, ``q``, ``wa`` (>= nb) float32 and ``sel`` (>= nb) int64 scratch.

    One pass over the bound voxels' rows per step: the counted voxels' gradient terms ``S = sum_I w_t (dec_t -
    x_t) d_t`` are carried from step to step (``S + alpha sum_I w_t q_t d_t``, the sum taken in the same pass as
    the direction's decode change ``q = D p``), and only the voxels whose state flipped along the step are
    added or removed (few: their rows read once more). Per step also one G v product and one preconditioner
    solve. Stops after ``iters`` steps or when ``z^T grad`` falls below ``tol`` times its first value."""
    k = c.shape[0]
    for t in range(nb):
        wa[t] = 0
    s2 = np.zeros(k, np.float32)
    dots_acc(c, rows, nb, wa, dec, s2)  # the decode only (no coefficient: nothing summed)
    m = 0
    for t in range(nb):  # the counted bound voxels (sg (d - bound) < 0: decoded inside it) and their residuals
        d = dec[t] + db[t]
        dec[t] = d
        on = sg[t] * (d - bv[t]) < 0
        if on:
            sel[m] = t
            q[m] = -wb[t] * (d - xb[t])
            m += 1
        wa[t] = wb[t] if on else np.float32(0)
    s = np.zeros(k, np.float32)
    sub_rows(s, rows, sel, q, m)  # s = S
    hc = np.empty(k, np.float32)
    symv(g, c, hc)
    for a in range(k):
        hc[a] += lam * c[a] - rhs[a] - lam * c0i[a]  # the gradient of the fit's quadratic (no bound voxel)
    grad = np.empty(k, np.float32)
    z = np.empty(k, np.float32)
    zprev = np.zeros(k, np.float32)
    p = np.zeros(k, np.float32)
    hp = np.empty(k, np.float32)
    gz0 = np.float32(0)
    gzprev = np.float32(0)
    one, zero = np.float32(1), np.float32(0)
    for it in range(iters):
        for a in range(k):
            grad[a] = hc[a] + s[a]
        chol_solve(chol, grad, z)
        gz = dot(grad, z, k)
        gzo = dot(grad, zprev, k)
        if it == 0:
            gz0 = gz
        if not gz > tol * gz0:
            break
        beta = max(np.float32(0), (gz - gzo) / gzprev) if it else np.float32(0)
        for a in range(k):
            p[a] = -z[a] + beta * p[a]
            zprev[a] = z[a]
        slope = dot(grad, p, k)
        if not slope < 0:  # not a descent direction any more: restart from the preconditioned gradient
            for a in range(k):
                p[a] = -z[a]
            slope = dot(grad, p, k)
        gzprev = gz
        symv(g, p, hp)
        for a in range(k):
            hp[a] += lam * p[a]
            s2[a] = 0
        php = dot(p, hp, k)  # p^T (G + lam I) p and p^T (G + lam I) c - p^T b: the fit's quadratic
        s0 = dot(p, hc, k)
        dots_acc(p, rows, nb, wa, q, s2)  # q = the direction's decode change; s2 = sum_A w_t q_t d_t
        # exact line search: the error along p is piecewise quadratic and convex; Newton on its derivative
        # (piecewise linear) from 0 lands on its minimum in a few steps, each O(nb)
        alpha = np.float32(0)
        for _ in range(_LINE_STEPS):
            d1 = s0 + alpha * php
            d2 = php
            for t in range(nb):
                d = dec[t] + alpha * q[t]
                wq = (one if sg[t] * (d - bv[t]) < 0 else zero) * wb[t] * q[t]
                d1 += wq * (d - xb[t])
                d2 += wq * q[t]
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
            s[a] += alpha * s2[a]  # the voxels counted before, at the new decode
        m = 0
        for t in range(nb):  # then the voxels whose state flipped: in with their term, out with theirs
            d = dec[t] + alpha * q[t]
            dec[t] = d
            on = sg[t] * (d - bv[t]) < 0
            if on != (wa[t] != 0):
                sel[m] = t
                q[m] = -wb[t] * (d - xb[t]) * (np.float32(1) if on else np.float32(-1))
                m += 1
                wa[t] = wb[t] if on else np.float32(0)
        sub_rows(s, rows, sel, q, m)


@njit(fastmath=False, cache=True)
def _beyond(xj, d):
    """How far the decode ``d`` of a bound voxel stored at ``xj`` lies beyond its bound (negative: inside it)."""
    return d - 1 if xj >= 1 - _BOUND_EPS else -d


@njit(fastmath=False, cache=True)
def gather(xi, wi, dt, dec_b, j, nr, rows, xb, wb, sg, bv, db):
    """Appends bound voxel ``j`` to the gathered rows at ``nr`` (its basis row, value, weight, bound, side and
    decode bias, as :func:`refine` takes them); returns ``nr + 1``."""
    k = dt.shape[1]
    top = xi[j] >= 1 - _BOUND_EPS
    xb[nr], wb[nr], db[nr] = xi[j], wi[j], dec_b[j]
    sg[nr] = 1 if top else -1
    bv[nr] = 1 if top else 0
    rt, dj = rows[nr], dt[j]
    for a in range(k):  # a contiguous row copy (an element loop: numba's slice copy costs 7x)
        rt[a] = dj[a]
    return nr + 1


@njit(fastmath=False, cache=True, nogil=True)
def residuals(lo, hi, x, w, dec_b, drop_bound, r, wsum):
    """r[i] = w[i] (x[i] - dec_b) (``(n, n_vox)`` float32; with ``drop_bound``, 0 at the voxels stored at a
    bound, 0 or 1) and wsum[i] = the sum of w[i] (float64, in order) for blocks ``lo`` to ``hi``:
    :func:`sdfcodec_pca.truncated.normal_rhs`'s residuals, one pass over the blocks and their weights (without the
    GIL: the caller runs disjoint ranges on its threads)."""
    n_vox = x.shape[1]
    for i in range(lo, hi):
        xi, wi, ri = x[i], w[i], r[i]
        s = 0.0
        for j in range(n_vox):
            s += wi[j]
            v = (xi[j] - dec_b[j]) * wi[j]
            if drop_bound and (xi[j] >= 1 - _BOUND_EPS or xi[j] <= _BOUND_EPS):
                v = np.float32(0)
            ri[j] = v
        wsum[i] = s


@njit(fastmath=False, cache=True)
def row_norms(dt):
    """|d_j| of each row of ``dt`` (n_vox, k) as float32, summed in float64 (rounded up by a relative 1e-6)."""
    n_vox, k = dt.shape
    out = np.empty(n_vox, np.float32)
    for j in range(n_vox):
        s = 0.0
        for a in range(k):
            s += np.float64(dt[j, a]) * np.float64(dt[j, a])
        out[j] = np.float32(np.sqrt(s) * (1 + 1e-6))
    return out


@njit(fastmath=False, cache=True)
def recheck_far(code, cprev, xi, wi, dt, dec_b, rn, far, lbf, nf, thr, nr, rows, xb, wb, sg, bv, db, vox, dec):
    """After a round of steps: the bound voxels ``far[:nf]`` that the code ``code`` (k,) decodes within ``thr``
    of their bound (or inside it) join the gathered rows at ``nr`` (:func:`gather`), in order; the others stay
    in ``far``. Returns (nf, nr). ``lbf[:nf]`` holds a lower bound of how far each lies beyond its bound at the
    code ``cprev`` (updated to ``code``): the decode at voxel j moves by at most ``|d_j| |code - cprev|``
    (``rn`` the row norms), so a voxel whose bound, less that move, stays above ``thr`` is kept without its
    decode (about half of them on the bench's blocks); the others are decoded as before (:func:`decode_at`,
    ``vox`` (>= nf) int64 and ``dec`` (>= nf) float32 scratch). The margin (1e-4 of the decode's scale) covers
    float32 rounding of both decodes: the same voxels join, in the same order, as when every one is decoded."""
    k = code.shape[0]
    dd = 0.0
    cn = 0.0
    for a in range(k):
        diff = np.float64(code[a]) - np.float64(cprev[a])
        dd += diff * diff
        cn += np.float64(code[a]) * np.float64(code[a])
        cprev[a] = code[a]
    move = np.sqrt(dd) * (1 + 1e-6)
    cn = np.sqrt(cn)
    nd = 0
    for t in range(nf):  # the bounds at this code; the voxels whose bound does not keep them, decoded together
        j = far[t]
        lb = lbf[t] - rn[j] * move
        lbf[t] = np.float32(lb)
        if not lb - 1e-4 * (1 + cn * rn[j]) > thr:
            vox[nd] = j
            nd += 1
            lbf[t] = np.float32(np.nan)  # decoded below
    decode_at(code, dt, dec_b, vox, nd, dec)
    kept = 0
    nd = 0
    for t in range(nf):
        j = far[t]
        if lbf[t] == lbf[t]:  # kept on its bound
            far[kept] = j
            lbf[kept] = lbf[t]
            kept += 1
            continue
        e = _beyond(xi[j], dec[nd])
        nd += 1
        if e <= thr:
            nr = gather(xi, wi, dt, dec_b, j, nr, rows, xb, wb, sg, bv, db)
        else:
            far[kept] = j
            lbf[kept] = e
            kept += 1
    return kept, nr


@njit(fastmath=False, cache=True, nogil=True)
def kernel(lo, hi, x, w, dt, dec_b, gfull, pieces, piece_cost, c0, rhs_all, wsum_all, ridge, rounds, iters, tol, out,
           rn):
    """The codes of blocks ``lo`` to ``hi`` into ``out[lo:hi]``, with scratch of its own: see
    :func:`sdfcodec_pca.truncated.truncated_codes` (``out`` ``(n, k)`` float32; ``dt`` the decode matrix transposed
    ``(4096, k)``; ``pieces`` the octree's Grams, :func:`plan`, or the block's alone; ``rhs_all`` ``(n, k)`` the
    unregularised right-hand sides ``D diag(w) (x - d)`` and ``wsum_all`` ``(n,)`` the weight sums, computed by the
    caller in one matrix product for all blocks; ``rn`` :func:`row_norms` of ``dt``). Without the GIL: the caller
    runs disjoint ranges on its threads (a numba parallel loop around this took ~8 s more to compile on a first
    encode, 2-core Xeon, for no faster codes)."""
    n_vox, k = dt.shape
    deep = pieces.shape[0] == _NODES
    g = np.zeros((k, k), np.float32)
    chol = np.zeros((k, k), np.float32)
    panel = np.zeros((4, k), np.float32)
    sol = np.zeros(k, np.float32)
    idx = np.empty(n_vox, np.int64)
    scale = np.empty(n_vox, np.float32)
    cost = np.empty((_NODES, 3), np.float32)
    choice = np.empty(_NODES, np.int64)
    nodes = np.empty(_NODES, np.int64)
    node_scale = np.empty(_NODES, np.float32)
    cand = np.zeros(3, np.float32)
    gp = np.empty(pieces.shape[1], np.float32)
    rows = np.empty((n_vox, k), np.float32)
    xb = np.empty(n_vox, np.float32)
    wb = np.empty(n_vox, np.float32)
    db = np.empty(n_vox, np.float32)
    sg = np.empty(n_vox, np.float32)
    bv = np.empty(n_vox, np.float32)
    dec_s = np.empty(n_vox, np.float32)
    q_s = np.empty(n_vox, np.float32)
    rr_s = np.empty(n_vox, np.float32)
    wfit = np.empty(n_vox, np.float32)
    far = np.empty(n_vox, np.int64)
    bnd = np.empty(n_vox, np.int64)
    lbf = np.empty(n_vox, np.float32)
    cprev = np.empty(k, np.float32)
    for i in range(lo, hi):
        xi, wi, c0i, rhs = x[i], w[i], c0[i], rhs_all[i]
        wmax = np.float32(0)
        nb = 0
        for j in range(n_vox):  # the fit's weights: with CG refits, 0 at the bound voxels (see truncated.py)
            # the bound voxels (``bnd[:nb]``): observed and stored at d_max (1) or d_min (0)
            bound = wi[j] > 0 and (xi[j] >= 1 - _BOUND_EPS or xi[j] <= _BOUND_EPS)
            bnd[nb] = j
            nb += bound
            wfit[j] = np.float32(0) if bound and iters > 0 else wi[j]
            wmax = max(wmax, wfit[j])
        cand[1] = 1
        cand[2] = wmax if wmax != 1 else np.float32(0)  # references 0, 1 and the largest weight (the band's)
        m, npc = plan(wfit, cand, piece_cost, deep, cost, choice, idx, scale, nodes, node_scale)
        add_pieces(g, gp, pieces, nodes, node_scale, npc)
        add_rows(g, dt, idx, scale, m)
        lam = np.float32((ridge / n_vox) * max(wsum_all[i], 1e-12))
        if not solve(g, rhs, c0i, lam, chol, panel, sol):
            out[i] = c0i
            continue
        for a in range(k):
            out[i, a] = sol[a]
        if nb == 0:
            continue
        if iters > 0:
            # the refits see the bound voxels near their bound or inside it; those decoded far beyond it
            # (weight 0 in the fit's Gram already) are checked after the steps and brought in if they came back
            decode_at(out[i], dt, dec_b, bnd, nb, dec_s)
            nr = 0
            nf = 0
            for t in range(nb):
                j = bnd[t]
                e = _beyond(xi[j], dec_s[t])
                if e > _FAR:
                    far[nf] = j
                    lbf[nf] = e
                    nf += 1
                else:
                    nr = gather(xi, wi, dt, dec_b, j, nr, rows, xb, wb, sg, bv, db)
            for a in range(k):
                cprev[a] = out[i, a]
            for _ in range(_FAR_ROUNDS):
                if nr:
                    refine(out[i], g, lam, rhs, c0i, chol, rows, xb, wb, sg, bv, db, nr, iters, tol, dec_s, q_s,
                           rr_s, idx)
                if nf == 0:
                    break
                back = nr
                # after the last round, every voxel that came inside its bound
                thr = np.float32(0) if _ == _FAR_ROUNDS - 1 else _FAR
                nf, nr = recheck_far(out[i], cprev, xi, wi, dt, dec_b, rn, far, lbf, nf, thr, nr, rows, xb, wb,
                                     sg, bv, db, idx, dec_s)
                if nr == back:
                    break
            continue
        exact_refits(out[i], xi, wi, dt, dec_b, gfull, c0i, ridge, rounds, g, rhs.copy(), chol, panel, sol,
                     bnd[:nb].copy(), idx, scale)


@njit(fastmath=False, cache=True)
def exact_refits(code, xi, wi, dt, dec_b, gfull, c0i, ridge, rounds, g, rhs, chol, panel, sol, bound, idx, scale):
    """The truncation refits as exact active-set rounds (``iters = 0``) from the weighted fit ``code`` (k,),
    updated in place: each round decodes the ``bound`` voxels, updates the Gram ``g`` and right-hand side
    ``rhs`` of that fit with the voxels whose active state flipped (or rebuilds them from a reference,
    whichever touches fewer voxels), and refactorises."""
    n_vox, k = dt.shape
    nb = bound.shape[0]
    wc = wi.copy()
    active = np.zeros(nb, np.bool_)
    flip = np.empty(nb, np.int64)
    dec = np.empty(nb, np.float32)
    for _ in range(rounds):
        nf = 0
        decode_at(code, dt, dec_b, bound, nb, dec)  # the bound voxels only, as the codes stored
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
            code[:] = c0i
            return
        for a in range(k):
            code[a] = sol[a]
