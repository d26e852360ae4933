"""Compiled rANS decoders and encoder, bit-exact with constriction 0.5.0's ``AnsCoder`` (numba; imported only by
:mod:`sdfcodec.core.ans` when numba is installed).

The coder (constriction ``src/stream/stack.rs``, ``AnsCoder<u32, u64>``, 24-bit precision): the compressed
words are a stack (the last word is read first); the state is a uint64 kept in ``[2^32, 2^64)`` while words
remain. Decoding one symbol: ``quantile = state mod 2^24``, find the symbol ``s`` with ``cdf[s] <= quantile <
cdf[s + 1]``, ``state = (state >> 24) * (cdf[s + 1] - cdf[s]) + quantile - cdf[s]``, then, if ``state < 2^32``
and a word remains, ``state = state << 32 | next word``. The models' cumulative tables are those of
``from_floating_point_probabilities_fast`` (``src/stream/model/categorical.rs``): for probabilities ``p`` ``(n,)``
float64, ``cdf[i] = trunc(P_i * (2^24 - n) / P_n) + i`` with ``P_i`` the left-to-right float64 sum of the first
``i`` entries, and ``cdf[n] = 2^24`` (what the ``Bernoulli(perfect=False)`` and ``Categorical(perfect=False)``
models, lazy or not, compute).

Module-level functions, cached on disk by numba (nested ones cannot be). Decoder state: ``st`` ``(2,)`` uint64,
the state and the number of words not read yet.
"""

from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["start", "mask_decode", "table_cdfs", "chunk_decode", "encode"]

_ONE = np.uint64(1)
_PREC = np.uint64(24)
_QMASK = np.uint64((1 << 24) - 1)
_TOTAL = 1 << 24
_LOW = np.uint64(1 << 32)
_W = np.uint64(32)


@njit(cache=True)
def start(words, st):
    """Set ``st`` to the coder constriction's ``AnsCoder(words)`` starts in; False when the last word is 0 (no
    coder writes one: constriction refuses such a stream)."""
    pos = len(words)
    if pos == 0:
        st[0], st[1] = np.uint64(0), np.uint64(0)
        return True
    first = words[pos - 1]
    if first == 0:
        return False
    pos -= 1
    s = np.uint64(first)
    while pos > 0:
        pos -= 1
        s = (s << _W) | np.uint64(words[pos])
        if s >= _LOW:
            break
    st[0], st[1] = s, np.uint64(pos)
    return True


@njit(cache=True, inline="always")
def _advance(words, st, left, right, quantile):
    s = (st[0] >> _PREC) * np.uint64(right - left) + np.uint64(quantile - left)
    if s < _LOW and st[1] > 0:
        p = st[1] - _ONE
        s = (s << _W) | np.uint64(words[p])
        st[1] = p
    st[0] = s


@njit(cache=True, inline="always")
def _bernoulli(words, st, p):
    """One bit under ``Bernoulli(perfect=False)`` with ``p = P(1)``."""
    q = np.int64(st[0] & _QMASK)
    pm = 1.0 - p
    c1 = np.int64(pm * ((_TOTAL - 2) / (pm + p))) + 1
    if q < c1:
        _advance(words, st, 0, c1, q)
        return 0
    _advance(words, st, c1, _TOTAL, q)
    return 1


@njit(cache=True, inline="always")
def _categorical3(words, st, p0, p1, p2):
    """One of three symbols under ``Categorical(perfect=False)`` with probabilities ``p0, p1, p2``."""
    q = np.int64(st[0] & _QMASK)
    scale = (_TOTAL - 3) / ((p0 + p1) + p2)
    c1 = np.int64(p0 * scale) + 1
    c2 = np.int64((p0 + p1) * scale) + 2
    if q < c1:
        _advance(words, st, 0, c1, q)
        return 0
    if q < c2:
        _advance(words, st, c1, c2, q)
        return 1
    _advance(words, st, c2, _TOTAL, q)
    return 2


@njit(cache=True, inline="always")
def _from_cdf(words, st, cdf, a, n):
    """One symbol of ``0..n-1`` under the table ``cdf[a:a + n + 1]``: a binary search."""
    q = np.int64(st[0] & _QMASK)
    lo, hi = 0, n  # cdf[a + lo] <= q < cdf[a + hi]
    while hi - lo > 1:
        mid = (lo + hi) >> 1
        if cdf[a + mid] <= q:
            lo = mid
        else:
            hi = mid
    _advance(words, st, cdf[a + lo], cdf[a + lo + 1], q)
    return lo


@njit(cache=True)
def mask_decode(words, n_rows, p_rows, cube_at, cube_flat, cube_bounds, cube_deltas, vox_at, vox_flat,
                vox_bounds, deltas, extra, extra_shift):
    """The observation-mask stream ``M1`` of :mod:`sdfcodec.map.maskcoder` (its words after the header).

    ``cube_at``/``cube_flat``: per sub-cube wavefront (``cube_bounds`` delimit them) the flat indices of its cells
    in the padded (10^3) and unpadded (8^3) sub-cube grid; ``vox_*`` alike for voxels (18^3, 16^3);
    ``cube_deltas`` (3,), ``deltas`` (q,) the context neighbours' flat offsets. ``extra``: ``(p_rows, 4096)``
    int64 added to each voxel's context shifted left by ``extra_shift`` (``(0, 0)`` for none: contexts of ``q``
    bits). Returns (status: 0 ok, 1 a trailing zero word; partial ``(n_rows,)`` uint8; states ``(p_rows, 512)``
    int64; padded voxels ``(p_rows, 18^3)`` uint8)."""
    partial = np.zeros(n_rows, np.uint8)
    states = np.zeros((p_rows, 512), np.int64)
    vpad = np.zeros((p_rows, 18 * 18 * 18), np.uint8)
    st = np.zeros(2, np.uint64)
    if not start(words, st):
        return 1, partial, states, vpad
    if p_rows < n_rows:
        p = p_rows / n_rows
        for i in range(n_rows):
            partial[i] = _bernoulli(words, st, p)
    else:
        partial[:] = 1
    cstride = 10 * 10 * 10
    cflat = np.full(p_rows * cstride, 3, np.int64)
    counts = np.zeros((3, 64), np.int64)
    buf_ctx = np.empty(p_rows * 64, np.int64)
    buf_sym = np.empty(p_rows * 64, np.int64)
    for w in range(len(cube_bounds) - 1):
        m = 0
        for r in range(p_rows):
            for t in range(cube_bounds[w], cube_bounds[w + 1]):
                at = r * cstride + cube_at[t]
                ctx = 0
                for qq in range(len(cube_deltas) - 1, -1, -1):
                    ctx = ctx * 4 + cflat[at + cube_deltas[qq]]
                c0, c1, c2 = counts[0, ctx] + 0.5, counts[1, ctx] + 0.5, counts[2, ctx] + 0.5
                s = (c0 + c1) + c2
                sym = _categorical3(words, st, c0 / s, c1 / s, c2 / s)
                cflat[at] = sym
                states[r, cube_flat[t]] = sym
                buf_ctx[m], buf_sym[m] = ctx, sym
                m += 1
        for i in range(m):
            counts[buf_sym[i], buf_ctx[i]] += 1
    vstride = 18 * 18 * 18
    for r in range(p_rows):  # sub-cubes all observed are known; mixed ones are decoded next
        for c in range(4096):
            if states[r, ((c >> 9) & 7) * 64 + ((c >> 5) & 7) * 8 + ((c >> 1) & 7)] == 1:
                vpad[r, (((c >> 8) + 1) * 18 + ((c >> 4) & 15) + 1) * 18 + (c & 15) + 1] = 1
    n_ctx = 1 << len(deltas)
    if extra.shape[0]:
        n_ctx += (extra.max() << extra_shift) if extra.size else 0
    vcounts = np.zeros((2, n_ctx), np.int64)
    vbuf_ctx = np.empty(p_rows * 256, np.int64)  # a wavefront of 16^3 has at most 192 cells
    vbuf_sym = np.empty(p_rows * 256, np.int64)
    flat_v = vpad.reshape(-1)
    for w in range(len(vox_bounds) - 1):
        m = 0
        for r in range(p_rows):
            for t in range(vox_bounds[w], vox_bounds[w + 1]):
                c = vox_flat[t]
                if states[r, ((c >> 9) & 7) * 64 + ((c >> 5) & 7) * 8 + ((c >> 1) & 7)] != 2:
                    continue
                at = r * vstride + vox_at[t]
                ctx = 0
                for qq in range(len(deltas)):
                    ctx |= np.int64(flat_v[at + deltas[qq]]) << qq
                if extra.shape[0]:
                    ctx += extra[r, c] << extra_shift
                n0, n1 = vcounts[0, ctx] + 0.5, vcounts[1, ctx] + 0.5
                sym = _bernoulli(words, st, n1 / (n0 + n1))
                flat_v[at] = sym
                vbuf_ctx[m], vbuf_sym[m] = ctx, sym
                m += 1
        for i in range(m):
            vcounts[vbuf_sym[i], vbuf_ctx[i]] += 1
    return 0, partial, states, vpad


@njit(cache=True)
def _cdf_of(table, out, o):
    """``out[o:o + n + 1]`` = the cumulative table of probabilities ``table`` ``(n,)`` float64 (the left-to-right
    sums first, in ``out`` as float64 bits: one chain of dependent adds, not two)."""
    n = len(table)
    cum = out[o:o + n + 1].view(np.float64)
    c = 0.0
    for i in range(n):
        cum[i] = c
        c += table[i]
    scale = (_TOTAL - n) / c
    for i in range(n):
        out[o + i] = np.int64(cum[i] * scale) + i
    out[o + n] = _TOTAL


@njit(cache=True)
def table_cdfs(first, decay, extent):
    """Cumulative tables, concatenated ``(len(first) + 1 + sum(2 e_j + 2),)`` int64, of ``first`` (float64) and
    of each two-sided geometric table of :meth:`sdfcodec.core.varrate.EntropyModel.table` (``e_j = max(extent_j,
    1)``; its entries ``decay_j ** |i - e_j|`` as numpy's cumprod makes them: one multiply per step), each ``n +
    1`` long. Returns (tables, where each starts ``(D + 1,)``, symbols of each ``(D + 1,)``)."""
    d = len(decay)
    sizes = np.empty(d + 1, np.int64)
    at = np.empty(d + 1, np.int64)
    sizes[0] = len(first)
    for j in range(d):
        sizes[j + 1] = 2 * max(extent[j], 1) + 1
    o = 0
    for j in range(d + 1):
        at[j] = o
        o += sizes[j] + 1
    out = np.empty(o, np.int64)
    _cdf_of(first, out, 0)
    for j in range(d):
        e = max(extent[j], 1)
        half = np.empty(e + 1)
        half[0] = 1.0
        for i in range(1, e + 1):
            half[i] = half[i - 1] * decay[j]
        table = np.empty(2 * e + 1)
        for i in range(e + 1):
            table[e - i] = half[i]
            table[e + i] = half[i]
        _cdf_of(table, out, at[j + 1])
    return out, at, sizes


@njit(cache=True)
def chunk_decode(words, n, level, cdfs, at, sizes, off):
    """The variable-rate chunk stream of :func:`sdfcodec.core.varrate.decode_chunk`: ``n`` lengths under the
    table at ``cdfs[at[0]:]`` (``sizes[0]`` symbols), then for ``j < level`` element ``j`` of every block longer
    than ``j`` under the table ``j + 1``, minus ``off[j]``. Returns (status: 0 ok, 1 a trailing zero word;
    ``(n, level)`` int32)."""
    out = np.zeros((n, level), np.int32)
    st = np.zeros(2, np.uint64)
    if not start(words, st):
        return 1, out
    k = np.empty(n, np.int64)
    for i in range(n):
        k[i] = _from_cdf(words, st, cdfs, at[0], sizes[0])
    for j in range(level):
        any_ = False
        for i in range(n):
            if k[i] > j:
                any_ = True
                out[i, j] = _from_cdf(words, st, cdfs, at[j + 1], sizes[j + 1]) - off[j]
        if not any_:
            break
    return 0, out


@njit(cache=True)
def encode(left, freq):
    """Words (uint32) of constriction's ``AnsCoder()`` after ``encode_reverse`` of symbols whose intervals
    ``[left, left + freq)`` of ``2^24`` are given in decode order (the last is pushed first)."""
    words = np.empty(len(left) + 2, np.uint32)
    m = 0
    s = np.uint64(0)
    for i in range(len(left) - 1, -1, -1):
        f = np.uint64(freq[i])
        if (s >> np.uint64(40)) >= f:
            words[m] = np.uint32(s & np.uint64(0xFFFFFFFF))
            m += 1
            s = s >> _W
        s = ((s // f) << _PREC) | (np.uint64(left[i]) + s % f)
    if s >= _LOW:
        words[m] = np.uint32(s & np.uint64(0xFFFFFFFF))
        words[m + 1] = np.uint32(s >> _W)
        m += 2
    elif s > 0:
        words[m] = np.uint32(s)
        m += 1
    return words[:m]
