"""Compiled steps of a pinned observation mask's read (numba; imported only by :mod:`sdfcodec.map.pinread` when
numba is installed): the signs of the exact decode told from the reader's float decode, and the voxels the mask's
stream reads as unobserved.

Module-level functions, cached on disk by numba.
"""

from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["sign_rows", "zero_voxels"]

_SCALE = 2.0 ** 24  # FRACTION_BITS of sdfcodec.map.pinmask: metres -> the exact decode's integers


@njit(cache=True, inline="always")
def _exact(q, basis, b, j):
    """The exact decode ``basis[0, j] + sum_i q[b, i] basis[i + 1, j]`` of voxel ``j`` of block ``b``: float64
    integers whose every partial sum stays below 2^53 (checked by the caller), so exact in this order too."""
    t = basis[0, j]
    for i in range(q.shape[1]):
        c = q[b, i]
        if c != 0.0:
            t += c * basis[i + 1, j]
    return t


@njit(cache=True)
def sign_rows(v, rows, e, d, q, basis, neg, pos):
    """Where the exact decode ``w`` of blocks ``b`` may be negative (``w < e[b]``: ``neg``) and non-negative (``w
    >= -e[b]``: ``pos``), as rows ``(n, 16, 16)`` uint32 with bit ``z + 1`` for voxel ``z``, told from a float
    decode in metres ``v[rows[b]]`` (``v`` ``(m, 4096)`` float32) within ``d[b]`` of ``w 2^-24`` (``e``, ``d``
    ``(n,)`` float64 integers, ``d`` may be inf): a voxel whose float decode lies within ``d[b]`` of ``e[b]`` or
    ``-e[b]`` is decided by the exact decode of its integer codes ``q`` ``(n, k)`` float64 and ``basis`` ``(k + 1,
    4096)`` float64 (:func:`_exact`). Returns the number of voxels decided exactly."""
    n = len(rows)
    exact = 0
    for b in range(n):
        r = rows[b]
        eb, db = e[b], d[b]
        neg_yes, neg_no = eb - db, eb + db  # x < neg_yes: w < e for sure; x >= neg_no: w >= e for sure
        pos_yes, pos_no = db - eb, -eb - db  # x >= pos_yes: w >= -e for sure; x < pos_no: w < -e for sure
        for xy in range(256):
            nb = np.uint32(0)
            pb = np.uint32(0)
            unsure = 0
            for z in range(16):
                x = np.float64(v[r, xy * 16 + z]) * _SCALE
                bit = np.uint32(1) << np.uint32(z + 1)
                if x < neg_yes:
                    nb |= bit
                if x >= pos_yes:
                    pb |= bit
                if not (x < neg_yes or x >= neg_no) or not (x >= pos_yes or x < pos_no):
                    unsure |= 1 << z
            if unsure:
                for z in range(16):
                    if unsure >> z & 1:
                        w = _exact(q, basis, b, xy * 16 + z)
                        bit = np.uint32(1) << np.uint32(z + 1)
                        nb = (nb | bit) if w < eb else (nb & ~bit)
                        pb = (pb | bit) if w >= -eb else (pb & ~bit)
                        exact += 1
            neg[b, xy >> 4, xy & 15] = nb
            pos[b, xy >> 4, xy & 15] = pb
    return exact


@njit(cache=True)
def zero_voxels(grid, at, dims, corner):
    """``(m,)`` int64 ``b * 4096 + voxel`` of the positions ``at`` of a decoded pinned mask's ``grid`` (flat uint8
    of ``dims`` ``(3,)``, blocks of 16^3 with first voxels ``corner`` ``(n, 3)``) that read 0: the voxels it
    stores as unobserved, in ``at``'s order."""
    sy, sz = dims[1] * dims[2], dims[2]
    nb = np.empty(3, np.int64)
    for a in range(3):
        nb[a] = max((dims[a] - 2) // 16, 1)
    block = np.full((nb[0], nb[1], nb[2]), -1, np.int64)
    for b in range(len(corner)):
        block[(corner[b, 0] - 1) >> 4, (corner[b, 1] - 1) >> 4, (corner[b, 2] - 1) >> 4] = b
    m = 0
    for t in range(len(at)):
        if grid[at[t]] == 0:
            m += 1
    out = np.empty(m, np.int64)
    m = 0
    for t in range(len(at)):
        g = at[t]
        if grid[g] == 0:
            i, j, k = g // sy - 1, (g // sz) % dims[1] - 1, g % sz - 1
            out[m] = block[i >> 4, j >> 4, k >> 4] * 4096 + ((i & 15) << 8) + ((j & 15) << 4) + (k & 15)
            m += 1
    return out
