"""Compiled steps of a pinned observation mask (numba; imported only by :mod:`sdfcodec.map.pinread`,
:mod:`sdfcodec.map.pinstore` and :mod:`sdfcodec.map.pinmask` when numba is installed): on read, the signs of the
exact decode (or of a surface refinement's refined exact field, with the refinement's selected voxels) told from
the reader's float decode, the pinned voxels from them, and the unobserved voxels set in the decode; on write, the
coder's likelier value chosen for the free bits.

Module-level functions, cached on disk by numba.
"""

from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["sign_rows", "select_rows", "refined_sign_rows", "set_voxels", "pinned_rows", "likelier_bits"]

_SCALE = 2.0 ** 24  # FRACTION_BITS of sdfcodec.map.pinmask: metres -> the exact decode's integers


@njit(cache=True, inline="always")
def _exact(q, basis_t, b, j, k):
    """The exact decode ``basis[0, j] + sum_i q[b, i] basis[i + 1, j]`` of voxel ``j`` of block ``b`` (``basis_t``:
    the basis transposed, ``(4096, k + 1)``: one voxel's column is contiguous) over its first ``k`` codes
    (:func:`_width`: the rest are 0): float64 integers whose every partial sum, in any order and grouping, is an
    integer of magnitude at most the bound term ``T`` below 2^52 (checked by the caller), so exact with eight
    running sums too (no branch on zero codes: they add an exact 0; eight chains of additions measured 10-30%
    faster than four on the kitchen's and a room's open voxels)."""
    row = basis_t[j]
    qb = q[b]
    t0, t1, t2, t3, t4, t5, t6, t7 = row[0], 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    i = 0
    while i + 8 <= k:
        t0 += qb[i] * row[i + 1]
        t1 += qb[i + 1] * row[i + 2]
        t2 += qb[i + 2] * row[i + 3]
        t3 += qb[i + 3] * row[i + 4]
        t4 += qb[i + 4] * row[i + 5]
        t5 += qb[i + 5] * row[i + 6]
        t6 += qb[i + 6] * row[i + 7]
        t7 += qb[i + 7] * row[i + 8]
        i += 8
    while i < k:
        t0 += qb[i] * row[i + 1]
        i += 1
    return ((t0 + t1) + (t2 + t3)) + ((t4 + t5) + (t6 + t7))


@njit(cache=True, inline="always")
def _width(q, b):
    """The codes of block ``b`` up to its last non-zero one: how many :func:`_exact` takes."""
    k = q.shape[1]
    while k > 0 and q[b, k - 1] == 0.0:
        k -= 1
    return k


@njit(cache=True, inline="always")
def _limits(e, d):
    """``(neg_yes, neg_no, pos_yes, pos_no)`` for a bound ``e`` and margin ``d``: a value ``x`` within ``d`` of
    ``w`` has ``w < e`` for sure where ``x < neg_yes``, ``w >= e`` where ``x >= neg_no``, ``w >= -e`` where ``x >=
    pos_yes``, ``w < -e`` where ``x < pos_no``."""
    return e - d, e + d, d - e, -e - d


@njit(cache=True, nogil=True)
def _first32(t):
    """The least float32 ``c`` with ``float64(c) 2^24 >= t`` (``t`` float64; NaN where ``t`` is NaN): for a float32
    ``f``, ``float64(f) 2^24 < t`` exactly where ``f < c``, and ``>= t`` where ``f >= c``.

    Why: ``g(f) = float64(f) 2^24`` is exact (float32 to float64 is exact; a power of two, far from overflow) and
    strictly increasing over the non-NaN float32s (-inf and +inf included), so ``{f: g(f) >= t}`` is closed
    upwards: all the float32s from its least element ``c`` on (``+inf`` at least: ``g(+inf) >= t`` for every
    non-NaN ``t``), and ``g(f) < t`` is its complement, ``f < c``. ``c`` is found from the float32 nearest ``t
    2^-24``, stepped up while it fails the test and down while the one below passes it: checked against the test
    itself, it owes nothing to how the guess rounded. A NaN ``f`` fails ``f < c`` and ``f >= c``, as ``g(NaN)``
    fails both tests it replaces; a NaN ``t`` leaves ``c`` NaN, which fails every test, as ``t`` did."""
    c = np.float32(t / _SCALE)
    up, down = np.float32(np.inf), np.float32(-np.inf)
    while np.float64(c) * _SCALE < t:
        c = np.nextafter(c, up)
    while c > down and np.float64(np.nextafter(c, down)) * _SCALE >= t:
        c = np.nextafter(c, down)
    return c


@njit(cache=True, nogil=True)
def _flag_bytes(x, lim, flags):
    """Each voxel's flags told from ``x`` (4096,) float32 metres under :func:`_limits` ``lim`` (in units of
    2^-24 m): ``flags[j]`` bit 0 where ``x[j] < neg_yes`` (may be negative), bit 1 where ``x[j] >= pos_yes`` (may
    be non-negative), bit 2 where the margin leaves a sign open (NaN included: decided exactly). Compared in
    float32 against :func:`_first32` of each limit, exactly the float64 tests ``float64(x) 2^24 < t`` (and ``>=``)
    they replace, and without a branch: the loop runs on vectors (a branch per voxel did, on float64, before)."""
    c0, c1, c2, c3 = _first32(lim[0]), _first32(lim[1]), _first32(lim[2]), _first32(lim[3])
    for j in range(4096):
        f = x[j]
        neg, no_neg, pos, no_pos = f < c0, f >= c1, f >= c2, f < c3
        flags[j] = np.uint8(neg) | (np.uint8(pos) << np.uint8(1)) | (
            np.uint8(not ((neg | no_neg) & (pos | no_pos))) << np.uint8(2))


_ONES = np.uint64(0x0101010101010101)
_GATHER = np.uint64(0x0102040810204080)  # times 8 bytes of 0 or 1: byte i's bit lands on bit 56 + i, no carry
# a de Bruijn sequence: 2^i (i < 32) times it, cut to 32 bits, names i in bits 27-31 (_LOWEST: i by those bits)
_LOW32, _DE_BRUIJN = np.uint64(0xFFFFFFFF), np.uint64(0x077CB531)
_LOWEST = np.zeros(32, np.int64)
_LOWEST[((np.uint64(1) << np.arange(32, dtype=np.uint64)) * _DE_BRUIJN & _LOW32) >> np.uint64(27)] = range(32)


@njit(cache=True, inline="always")
def _row_bits(words, xy, bit):
    """Bit ``bit`` of the 16 :func:`_flag_bytes` of row ``xy`` (``words``: the flags viewed as uint64) as a uint32,
    bit ``z`` for voxel ``z``. Byte ``i`` times bit ``56 - 7 j`` of :data:`_GATHER` lands on bit ``56 + 8 i - 7 j``:
    bits 56-63 only where ``i = j``, the rest on distinct lower bits (their sum carries nothing upwards)."""
    s, top = np.uint64(bit), np.uint64(56)
    lo = (((words[2 * xy] >> s) & _ONES) * _GATHER) >> top
    hi = (((words[2 * xy + 1] >> s) & _ONES) * _GATHER) >> top
    return np.uint32(lo | (hi << np.uint64(8)))


@njit(cache=True, inline="always")
def _decided(w, e, z, nb, pb):
    """Voxel ``z``'s flags set from its exact value ``w`` against the bound ``e``."""
    bit = np.uint32(1) << np.uint32(z + 1)
    nb = (nb | bit) if w < e else (nb & ~bit)
    pb = (pb | bit) if w >= -e else (pb & ~bit)
    return nb, pb


@njit(cache=True, nogil=True)
def sign_rows(v, rows, e, d, q, basis_t, neg, pos):
    """Where the exact decode ``w`` of blocks ``b`` may be negative (``w < e[b]``: ``neg``) and non-negative (``w
    >= -e[b]``: ``pos``), as rows ``(n, 16, 16)`` uint32 with bit ``z + 1`` for voxel ``z``, told from a float
    decode in metres ``v[rows[b]]`` (``v`` ``(m, 4096)`` float32) within ``d[b]`` of ``w 2^-24`` (``e``, ``d``
    ``(n,)`` float64 integers, ``d`` may be inf): a voxel whose float decode lies within ``d[b]`` of ``e[b]`` or
    ``-e[b]`` is decided by the exact decode of its integer codes ``q`` ``(n, k)`` float64 and the basis transposed
    ``basis_t`` ``(4096, k + 1)`` float64 (:func:`_exact`). Returns the number of voxels decided exactly."""
    exact = 0
    flags = np.empty(4096, np.uint8)
    words = flags.view(np.uint64)
    for b in range(len(rows)):
        _flag_bytes(v[rows[b]], _limits(e[b], d[b]), flags)
        exact += _rows_of(flags, words, None, e[b], q, basis_t, b, _width(q, b), 0.0, 0.0, 0.0, neg, pos)
    return exact


@njit(cache=True, nogil=True)
def _rows_of(flags, words, cz, eb, q, basis_t, b, kb, step, lo, hi, neg, pos):
    """Block ``b``'s sign rows into ``neg[b]``, ``pos[b]`` from its :func:`_flag_bytes`, the voxels left open
    decided by the exact decode (clipped to ``[lo, hi]`` and refined by ``cz[j] step`` where ``cz`` is not None:
    :func:`refined_sign_rows`). Returns how many were."""
    exact = 0
    for xy in range(256):
        nb = _row_bits(words, xy, 0) << np.uint32(1)
        pb = _row_bits(words, xy, 1) << np.uint32(1)
        if (words[2 * xy] | words[2 * xy + 1]) & (_ONES << np.uint64(2)):  # open voxels are rare: a branch
            for z in range(16):
                j = xy * 16 + z
                if flags[j] & 4:
                    w = _exact(q, basis_t, b, j, kb)
                    if cz is not None:
                        w = min(max(w, lo), hi)
                        if cz[j] != 0:
                            w = min(max(w + cz[j] * step, lo), hi)
                    nb, pb = _decided(w, eb, z, nb, pb)
                    exact += 1
        neg[b, xy >> 4, xy & 15] = nb
        pos[b, xy >> 4, xy & 15] = pb
    return exact


@njit(cache=True, nogil=True)
def _select_test(kind, f, db, lo, hi, tau):
    """The tests of :func:`select_rows` on a float decode ``f`` (float32 metres), as it makes them in float64
    (kinds 2 and 3 negated: each passes from some float32 on, for a finite ``db``)."""
    x = np.float64(f) * _SCALE
    if kind == 0:
        return -tau < max(x - db, lo)
    if kind == 1:
        return max(x - db, lo) >= tau
    if kind == 2:
        return not (min(x + db, hi) < tau)
    return not (min(x + db, hi) <= -tau)


@njit(cache=True, nogil=True)
def _least_passing(kind, guess, db, lo, hi, tau):
    """``(found, c)``: ``c`` the least float32 passing :func:`_select_test` ``kind`` (-inf where all do, NaN where
    none does), looked for within four float32 of ``guess`` (``found`` False where it is not there).

    Why one compare in float32 tells the test: ``x = float64(f) 2^24`` is exact and strictly increasing over the
    non-NaN float32s (as in :func:`_first32`), and ``x - db``, ``x + db`` rounded (``db`` finite) and their
    max, min with a constant are non-decreasing in ``x``: each test passes on all the float32s from ``c`` on and
    fails below it; the test itself places ``c``. A NaN ``f`` fails the four tests of :func:`select_rows` (numba's
    ``max``, ``min`` keep a NaN first argument), and so every compare with ``c`` or :func:`_below` of it."""
    down, up = np.float32(-np.inf), np.float32(np.inf)
    if _select_test(kind, down, db, lo, hi, tau):
        return True, down
    if not _select_test(kind, up, db, lo, hi, tau):
        return True, np.float32(np.nan)
    c = guess
    for _ in range(4):
        c = np.nextafter(c, down)
    if _select_test(kind, c, db, lo, hi, tau):
        return False, c
    for _ in range(8):
        c = np.nextafter(c, up)
        if _select_test(kind, c, db, lo, hi, tau):
            return True, c
    return False, c


@njit(cache=True, nogil=True)
def _below(c):
    """The float32 ``d`` with ``f <= d`` exactly where ``f < c`` (``f`` not NaN; a NaN ``c``: none passing, as from
    :func:`_least_passing`, read as past +inf); a NaN ``f`` fails both."""
    if c != c:
        return np.float32(np.inf)
    if c == np.float32(-np.inf):
        return np.float32(np.nan)
    return np.nextafter(c, np.float32(-np.inf))


@njit(cache=True, nogil=True)
def select_rows(v, rows, tau, d, q, basis_t, lo, hi, sel):
    """A surface refinement's selected voxels (spec 6h: ``|clip(w, lo, hi)| < tau``, ``w`` the exact decode,
    ``lo``, ``hi`` the truncation times 2^24 in float64) of blocks ``b`` into ``sel`` ``(n, 4096)`` bool, told
    from the clipped float decode in metres ``v[rows[b]]`` (``v`` ``(m, 4096)`` float32) within ``d[b]`` of
    ``clip(w) 2^-24`` (``d`` ``(n,)`` float64, may be inf; ``rows[b] < 0``: not decoded): a voxel whose interval
    ``[max(x - d, lo), min(x + d, hi)]`` holds ``+-tau`` is decided by its exact decode (:func:`_exact`). Returns
    the number of voxels decided exactly."""
    exact = 0
    open_ = np.empty(4096, np.uint8)  # the voxels of a block the margin leaves open
    words = open_.view(np.uint64)
    for b in range(len(rows)):
        r = rows[b]
        db = d[b]
        kb = _width(q, b)
        if r >= 0:
            # clip(w) lies in [a, z] (within d of x and inside the truncation: a value clipped at a bound near
            # tau is decided too): -tau < a, z < tau (selected), a >= tau, z <= -tau (not), each one float32
            # compare (_least_passing) where its threshold is found, so that the loop runs on vectors
            vr, sr = v[r], sel[b]
            found = np.isfinite(db)
            if found:
                f0, c0 = _least_passing(0, np.float32((db - tau) / _SCALE), db, lo, hi, tau)
                f1, c1 = _least_passing(1, np.float32((tau + db) / _SCALE), db, lo, hi, tau)
                f2, c2 = _least_passing(2, np.float32((tau - db) / _SCALE), db, lo, hi, tau)
                f3, c3 = _least_passing(3, np.float32((-tau - db) / _SCALE), db, lo, hi, tau)
                found = f0 and f1 and f2 and f3
            if found:
                d2, d3 = _below(c2), _below(c3)
                for j in range(4096):
                    f = vr[j]
                    yes = (f >= c0) & (f <= d2)
                    sr[j] = yes
                    open_[j] = not (yes | (f >= c1) | (f <= d3))
            else:  # (an infinite margin, or no threshold near its guess: told in float64)
                for j in range(4096):
                    x = np.float64(vr[j]) * _SCALE
                    a, z = max(x - db, lo), min(x + db, hi)
                    yes = (-tau < a) & (z < tau)
                    sr[j] = yes
                    open_[j] = not (yes | (a >= tau) | (z <= -tau))
        else:
            open_[:] = 1
        for i in range(512):
            if words[i]:  # open voxels are rare: eight at a time
                for j in range(8 * i, 8 * i + 8):
                    if open_[j]:
                        w = min(max(_exact(q, basis_t, b, j, kb), lo), hi)
                        sel[b, j] = abs(w) < tau
                        exact += 1
    return exact


@njit(cache=True, nogil=True)
def refined_sign_rows(v, rows, sel, c, step, lo, hi, e, d, q, basis_t, neg, pos):
    """:func:`sign_rows` of a surface refinement's refined exact field (spec 6h) ``r = clip(clip(w) + c step)``
    (``c`` the corrections ``(m,)`` int32 of the selected voxels ``sel`` ``(n, 4096)`` bool in C order, block by
    block; 0 elsewhere; ``step`` units, ``lo``, ``hi`` the truncation times 2^24 in float64), against the bound
    ``e`` ``(n,)``. The corrections are first added to the float decode ``v[rows[b]]`` (metres, clipped), in
    place, as the reader's refined decode: ``min(max(fl32(v + c step 2^-24), lo32), hi32)`` in float32; the
    signs are then told from it within ``d[b]`` of ``r 2^-24``, the voxels within ``d[b]`` of ``+-e[b]`` (and
    every voxel of a block not decoded) by the exact ``r``. Returns the number of voxels decided exactly."""
    exact = 0
    t = 0
    step32 = np.float32(step / _SCALE)  # exact: an integer below 2^24 times a power of two
    lo32, hi32 = np.float32(lo / _SCALE), np.float32(hi / _SCALE)
    cz = np.zeros(4096, np.int64)  # a block's corrections (0 where not selected)
    last = max(len(c) - 1, 0)
    cc = c if len(c) else np.zeros(1, np.int32)
    flags = np.empty(4096, np.uint8)
    words = flags.view(np.uint64)
    for b in range(len(rows)):
        r = rows[b]
        picked = sel[b].view(np.uint64)  # a row's 16 selections in two words: about half the rows have none
        for xy in range(256):
            if picked[2 * xy] | picked[2 * xy + 1]:
                m = np.uint64(_row_bits(picked, xy, 0))
                while m:  # the selected voxels only, lowest first (C order)
                    low = m & (~m + np.uint64(1))
                    z = _LOWEST[((low * _DE_BRUIJN) & _LOW32) >> np.uint64(27)]
                    cz[xy * 16 + z] = np.int64(cc[min(t, last)])
                    t += 1
                    m ^= low
        if r >= 0:
            vr = v[r]
            for j in range(4096):
                # the reader's float32 sum (+0.0 where nothing is selected, as it adds a row of zeros)
                y = np.float32(vr[j] + np.float32(cz[j]) * step32)
                vr[j] = min(max(y, lo32), hi32)
            _flag_bytes(vr, _limits(e[b], d[b]), flags)
        else:
            flags[:] = 4
        exact += _rows_of(flags, words, cz, e[b], q, basis_t, b, _width(q, b), step, lo, hi, neg, pos)
        for xy in range(256):
            if picked[2 * xy] | picked[2 * xy + 1]:
                cz[xy * 16:xy * 16 + 16] = 0
    return exact


@njit(cache=True, nogil=True)
def set_voxels(v, rows, ids, value):
    """``v[rows[i >> 12], i & 4095] = value`` for each ``i`` of ``ids`` whose ``rows`` entry is not negative
    (``v`` ``(m, 4096)``)."""
    for t in range(len(ids)):
        r = rows[ids[t] >> 12]
        if r >= 0:
            v[r, ids[t] & 4095] = value


@njit(cache=True, inline="always")
def _padded_part(neg, pos, s, x0, x1, sx0, y0, y1, sy0, pn, pp):
    """Rows ``[x0, x1) x [y0, y1)`` of a block's padded sign rows ``pn``, ``pp`` (18 bits: z padded by one below and
    above) from the rows ``sx0 + x - x0``, ``sy0 + y - y0`` of the blocks ``s`` (table entries: below, beside,
    above; ``-2``: coded elsewhere, either sign; ``-1``: not coded, ``d_max``, non-negative only)."""
    row16 = np.uint32(0x1FFFE)
    for x in range(x0, x1):
        sx = sx0 + x - x0
        for y in range(y0, y1):
            sy = sy0 + y - y0
            # the rows along z: the block beside (or this one), then one bit from those below and above it
            if s[1] >= 0:
                rn, rp = neg[s[1], sx, sy] & row16, pos[s[1], sx, sy] & row16
            elif s[1] == -2:
                rn, rp = row16, row16
            else:
                rn, rp = np.uint32(0), row16
            if s[0] >= 0:
                rn |= (neg[s[0], sx, sy] >> np.uint32(16)) & np.uint32(1)
                rp |= (pos[s[0], sx, sy] >> np.uint32(16)) & np.uint32(1)
            elif s[0] == -2:
                rn |= np.uint32(1)
                rp |= np.uint32(1)
            else:
                rp |= np.uint32(1)
            if s[2] >= 0:
                rn |= (neg[s[2], sx, sy] & np.uint32(2)) << np.uint32(16)
                rp |= (pos[s[2], sx, sy] & np.uint32(2)) << np.uint32(16)
            elif s[2] == -2:
                rn |= np.uint32(1 << 17)
                rp |= np.uint32(1 << 17)
            else:
                rp |= np.uint32(1 << 17)
            pn[x, y] = rn
            pp[x, y] = rp


@njit(cache=True, nogil=True)
def pinned_rows(coords, neg, pos, outside, both):
    """:func:`sdfcodec.map.pinmask.pinned_rows` per block: ``(n, 16, 16)`` uint16, bit ``z`` where voxel ``(x, y,
    z)`` of block ``coords[b]`` ``(n, 3)`` lies in a relevant cell, from the sign rows ``neg``, ``pos`` ``(n, 16,
    16)`` uint32 (bit ``z + 1``); ``outside`` ``(m, 3)``: coded blocks of other chunks (either sign); blocks
    elsewhere read ``d_max`` (non-negative only). ``both``: a cell is relevant when it may be negative and may
    be non-negative (``d_max`` at or above the jump), else when it may be negative."""
    n = len(coords)
    out = np.zeros((n, 16, 16), np.uint16)
    if n == 0:
        return out
    lo = coords[0].copy()
    hi = coords[0].copy()
    for b in range(n + len(outside)):
        for a in range(3):
            c = coords[b, a] if b < n else outside[b - n, a]
            lo[a] = min(lo[a], c)
            hi[a] = max(hi[a], c)
    lo -= 1
    table = np.full((hi[0] - lo[0] + 2, hi[1] - lo[1] + 2, hi[2] - lo[2] + 2), -1, np.int64)
    for b in range(len(outside)):
        table[outside[b, 0] - lo[0], outside[b, 1] - lo[1], outside[b, 2] - lo[2]] = -2
    for b in range(n):
        table[coords[b, 0] - lo[0], coords[b, 1] - lo[1], coords[b, 2] - lo[2]] = b
    pn = np.empty((18, 18), np.uint32)
    pp = np.empty((18, 18), np.uint32)
    rel = np.empty((17, 17), np.uint32)
    for b in range(n):
        cx, cy, cz = coords[b, 0] - lo[0], coords[b, 1] - lo[1], coords[b, 2] - lo[2]
        # the padded rows in nine parts (the block's 16 x 16, four edges, four corners), each from one block
        # beside it (or this one) and those below and above that: three table look-ups per part, not per row
        for bx in range(-1, 2):
            x0, x1, sx0 = (0, 1, 15) if bx < 0 else ((17, 18, 0) if bx > 0 else (1, 17, 0))
            for by in range(-1, 2):
                y0, y1, sy0 = (0, 1, 15) if by < 0 else ((17, 18, 0) if by > 0 else (1, 17, 0))
                _padded_part(neg, pos, table[cx + bx, cy + by, cz - 1:cz + 2], x0, x1, sx0, y0, y1, sy0, pn, pp)
        for x in range(17):
            for y in range(17):
                cn = pn[x, y] | pn[x + 1, y] | pn[x, y + 1] | pn[x + 1, y + 1]
                cn |= cn >> np.uint32(1)
                if both:
                    cp = pp[x, y] | pp[x + 1, y] | pp[x, y + 1] | pp[x + 1, y + 1]
                    cn &= cp | (cp >> np.uint32(1))
                rel[x, y] = cn & np.uint32(0x1FFFF)
        for x in range(16):
            for y in range(16):
                p = rel[x, y] | rel[x + 1, y] | rel[x, y + 1] | rel[x + 1, y + 1]
                out[b, x, y] = np.uint16((p | (p >> np.uint32(1))) & np.uint32(0xFFFF))
    return out


@njit(cache=True, nogil=True)
def likelier_bits(grid, at, bounds, deltas, free, n_ctx):
    """:func:`sdfcodec.map.pinmask.cheapest_bits` in place on the layout's ``grid`` (flat uint8: 0, 1, 2 where not
    pinned): wavefront by wavefront (``at`` between ``bounds``), each voxel of ``free`` (bool, the grid's shape) set
    to the value of the larger count of its context (ties keep it), the counts those of the wavefronts before. Each
    context ``sum grid[g + deltas[q]] 3^(5 - q)`` reads earlier wavefronts only, so one voxel at a time is the same
    as numpy's whole wavefront at a time."""
    counts = np.zeros((2, n_ctx), np.int64)
    ctxs = np.empty(len(at), np.int64)
    for w in range(len(bounds) - 1):
        a, b = bounds[w], bounds[w + 1]
        for i in range(a, b):
            g = at[i]
            ctx = 0
            for q in range(len(deltas)):
                ctx = ctx * 3 + np.int64(grid[g + deltas[q]])
            ctxs[i] = ctx
            if free[g]:
                c0, c1 = counts[0, ctx], counts[1, ctx]
                if c1 > c0:
                    grid[g] = 1
                elif c0 > c1:
                    grid[g] = 0
        for i in range(a, b):
            counts[np.int64(grid[at[i]]), ctxs[i]] += 1
