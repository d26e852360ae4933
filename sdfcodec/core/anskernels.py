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

__all__ = ["start", "decode_flags", "decode_cubes", "mixed_voxels", "pack_rows", "decode_bits", "wave_order",
           "wave_sizes", "wave_place", "decode_planes", "padded_states", "cube_intervals", "bit_intervals",
           "table_cdfs", "chunk_decode", "slot_table", "categorical_decode", "encode"]

_ONE = np.uint64(1)
_TWO = np.uint64(2)
_16 = np.uint64(16)
_LOW16 = np.uint64(0xFFFF)
_PREC = np.uint64(24)
_QMASK = np.uint64((1 << 24) - 1)
_FIELD = np.int64((1 << 24) - 1)  # a 24-bit field of a packed slot entry (slot_table)
_TOTAL = 1 << 24
_LOW = np.uint64(1 << 32)
_W = np.uint64(32)


@njit(cache=True, nogil=True)
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


# Per-symbol helpers: functions LLVM inlines, not numba's inline="always" (IR inlining), with which a copy of the
# corrections' loop ran 3x slower (1.6 M symbols: 24.8 vs 8.5 ms; the same instructions by kind, cause unknown).
@njit(cache=True)
def _advance(words, s, pos, left, right, quantile):
    """The state ``s`` and words left ``pos`` after decoding the symbol of ``[left, right)`` (kept in locals by
    the callers' loops, not in ``st``: stores to the output arrays would make the compiler reload it)."""
    s = (s >> _PREC) * np.uint64(right - left) + np.uint64(quantile - left)
    if s < _LOW and pos > 0:
        pos -= 1
        s = (s << _W) | np.uint64(words[pos])
    return s, pos


@njit(cache=True)
def _bernoulli(words, s, pos, p):
    """One bit under ``Bernoulli(perfect=False)`` with ``p = P(1)``."""
    q = np.int64(s & _QMASK)
    pm = 1.0 - p
    c1 = np.int64(pm * ((_TOTAL - 2) / (pm + p))) + 1
    if q < c1:
        s, pos = _advance(words, s, pos, 0, c1, q)
        return 0, s, pos
    s, pos = _advance(words, s, pos, c1, _TOTAL, q)
    return 1, s, pos


@njit(cache=True)
def _cdf3(p0, p1, p2):
    """``(cdf[1], cdf[2])`` of ``Categorical(perfect=False)`` with probabilities ``p0, p1, p2``."""
    scale = (_TOTAL - 3) / ((p0 + p1) + p2)
    return np.int64(p0 * scale) + 1, np.int64((p0 + p1) * scale) + 2


@njit(cache=True)
def _symbol3(words, s, pos, c1, c2):
    """One of three symbols under the table ``0, c1, c2, 2^24`` (selects, not branches: the symbols of a mask
    are not predictable enough for a branch predictor)."""
    q = np.int64(s & _QMASK)
    a, b = q >= c1, q >= c2
    lo = c2 if b else (c1 if a else 0)
    hi = _TOTAL if b else (c2 if a else c1)
    s, pos = _advance(words, s, pos, lo, hi, q)
    return np.int64(a) + np.int64(b), s, pos


@njit(cache=True)
def _from_slots(words, s, pos, cdf, a, slots, row, shift):
    """One symbol under the table ``cdf[a:]`` from its quantile's slot (``slots[row]``, :func:`slot_table`): one load
    where the slot lies in one symbol, else a few steps forward from its first (a binary search takes a dozen
    dependent loads). A refined map's corrections (99 % of slots in one symbol): 6.2 ns a symbol, 8.0 stepping."""
    q = np.int64(s & _QMASK)
    e = slots[row, q >> shift]
    if e >= 0:
        k = e >> 48
        left = (e >> 24) & _FIELD
        right = left + (e & _FIELD)
    else:
        k = -1 - e
        while np.int64(cdf[a + k + 1]) <= q:
            k += 1
        left, right = np.int64(cdf[a + k]), np.int64(cdf[a + k + 1])
    s, pos = _advance(words, s, pos, left, right, q)
    return k, s, pos


@njit(cache=True)
def _cube_context(cflat, at, cube_deltas):
    """The context of the sub-cube at ``at``: the states at ``cube_deltas`` as base-4 digits, first least
    significant."""
    ctx = 0
    for qq in range(len(cube_deltas) - 1, -1, -1):
        ctx = ctx * 4 + np.int64(cflat[at + cube_deltas[qq]])
    return ctx


@njit(cache=True, nogil=True)
def _cube_tables(counts, cdf):
    """``cdf[ctx] = (cdf[1], cdf[2])`` of each context's Krichevsky-Trofimov probabilities from ``counts``
    ``(3, n_ctx)``: the counts hold for a whole wavefront, so each context's table is made once."""
    for ctx in range(counts.shape[1]):
        c0, c1, c2 = counts[0, ctx] + 0.5, counts[1, ctx] + 0.5, counts[2, ctx] + 0.5
        t3 = (c0 + c1) + c2
        cdf[ctx, 0], cdf[ctx, 1] = _cdf3(c0 / t3, c1 / t3, c2 / t3)


@njit(cache=True, nogil=True)
def decode_flags(words, st, n, p):
    """``n`` bits ``(n,)`` uint8, each under ``Bernoulli(p, perfect=False)``."""
    out = np.empty(n, np.uint8)
    s, pos = st[0], np.int64(st[1])
    for i in range(n):
        out[i], s, pos = _bernoulli(words, s, pos, p)
    st[0], st[1] = s, np.uint64(pos)
    return out


@njit(cache=True, nogil=True)
def decode_cubes(words, st, p_rows, cube_at, cube_flat, cube_bounds, cube_deltas):
    """The sub-cube states ``(p_rows, 512)`` uint8 of the observation-mask stream ``M1``
    (:mod:`sdfcodec.map.maskcoder`): wavefront by wavefront (``cube_bounds`` delimit them in ``cube_at``, the
    padded (10^3) flat indices, and ``cube_flat``, the unpadded (8^3) ones), every row, each state (0, 1, 2)
    under ``Categorical(perfect=False)`` with Krichevsky-Trofimov probabilities of its context: the states at
    ``cube_deltas`` (3 = outside the block) as base-4 digits, the first least significant, counted over the
    wavefronts before."""
    states = np.zeros((p_rows, 512), np.uint8)
    cstride = 10 * 10 * 10
    cflat = np.full(p_rows * cstride, 3, np.uint8)  # bytes: the rows swept once per wavefront stay in cache
    n_ctx = 4 ** len(cube_deltas)
    counts = np.zeros((3, n_ctx), np.int64)
    cdf = np.empty((n_ctx, 2), np.int64)
    buf_ctx = np.empty(p_rows * 64, np.int64)  # a wavefront of 8^3 has at most 48 cells
    buf_sym = np.empty(p_rows * 64, np.int64)
    s, pos = st[0], np.int64(st[1])
    for w in range(len(cube_bounds) - 1):
        _cube_tables(counts, cdf)
        m = 0
        for r in range(p_rows):
            for t in range(cube_bounds[w], cube_bounds[w + 1]):
                at = r * cstride + cube_at[t]
                ctx = _cube_context(cflat, at, cube_deltas)
                sym, s, pos = _symbol3(words, s, pos, cdf[ctx, 0], cdf[ctx, 1])
                cflat[at] = sym
                states[r, cube_flat[t]] = sym
                buf_ctx[m], buf_sym[m] = ctx, sym
                m += 1
        for i in range(m):
            counts[buf_sym[i], buf_ctx[i]] += 1
    st[0], st[1] = s, np.uint64(pos)
    return states


@njit(cache=True, nogil=True)
def mixed_voxels(states, n_waves):
    """From sub-cube states ``(p, 512)`` (of 2^3 voxels each): the voxels padded by one ``(p, 18^3)`` uint8 (1 in
    sub-cubes all observed), and the padded flat positions (``r * 18^3 + ...``) of the voxels of mixed sub-cubes
    in decode order (wavefront ``i + j + k``, then row, then C order) with the bounds ``(n_waves + 1,)`` of each
    wavefront (a stable counting sort of the rows' C-order lists)."""
    p_rows = len(states)
    vstride = 18 * 18 * 18
    vpad = np.zeros((p_rows, vstride), np.uint8)
    n = 0
    for r in range(p_rows):
        for c in range(512):
            if states[r, c] == 2:
                n += 8
    pos = np.empty(n, np.int64)
    wave = np.empty(n, np.int64)
    bounds = np.zeros(n_waves + 1, np.int64)
    m = 0
    for r in range(p_rows):
        for i in range(16):
            for j in range(16):
                base = (i >> 1) * 64 + (j >> 1) * 8
                row0 = r * vstride + ((i + 1) * 18 + j + 1) * 18 + 1
                for kc in range(8):
                    s = states[r, base + kc]
                    if s == 1:
                        vpad[r, row0 - r * vstride + 2 * kc] = 1
                        vpad[r, row0 - r * vstride + 2 * kc + 1] = 1
                    elif s == 2:
                        for k in range(2 * kc, 2 * kc + 2):
                            pos[m] = row0 + k
                            wave[m] = i + j + k
                            bounds[i + j + k + 1] += 1
                            m += 1
    for w in range(n_waves):
        bounds[w + 1] += bounds[w]
    fill = bounds[:-1].copy()
    at = np.empty(n, np.int64)
    for t in range(n):
        at[fill[wave[t]]] = pos[t]
        fill[wave[t]] += 1
    return vpad, at, bounds


@njit(cache=True, nogil=True)
def pack_rows(vpad, states):
    """Decoded voxels padded by one ``(p, 18^3)`` uint8 -> (packed mask rows ``(p, 512)`` uint8, C order, most
    significant bit first as numpy's packbits; whether every mixed sub-cube of ``states`` ``(p, 512)`` decoded
    both values, as a sound stream does)."""
    p_rows = len(vpad)
    out = np.empty((p_rows, 512), np.uint8)
    ok = True
    for r in range(p_rows):
        v = vpad[r]
        for i in range(16):
            for j in range(16):
                base = ((i + 1) * 18 + j + 1) * 18 + 1
                for h in range(2):  # a line of 16 voxels is two bytes
                    byte = 0
                    for k in range(8 * h, 8 * h + 8):
                        byte = (byte << 1) | v[base + k]
                    out[r, (i * 16 + j) * 2 + h] = byte
        for t in range(512):
            if states[r, t] == 2:
                i0, j0, k0 = 2 * (t >> 6), 2 * ((t >> 3) & 7), 2 * (t & 7)
                n = 0
                for di in range(2):
                    for dj in range(2):
                        at = ((i0 + di + 1) * 18 + j0 + dj + 1) * 18 + k0 + 1
                        n += v[at] + v[at + 1]
                if n == 0 or n == 8:
                    ok = False
    return out, ok


@njit(cache=True)
def _context(grid, g, deltas, weights, extra, i, has_extra):
    """The context of the ``i``-th bit, at ``grid[g]``: its neighbours ``grid[g + deltas]`` weighted, plus
    ``extra[i]`` where given (the decoder and the encoder must compute it alike)."""
    ctx = 0
    for q in range(len(deltas)):
        ctx += np.int64(grid[g + deltas[q]]) * weights[q]
    if has_extra:
        ctx += extra[i]
    return ctx


@njit(cache=True)
def _kt_split(c0, c1):
    """The ``cdf[1]`` of ``Bernoulli(perfect=False)`` under Krichevsky-Trofimov counts ``c0``, ``c1``: ``p = (c1 +
    1/2) / (c0 + c1 + 1)`` as :func:`_bernoulli` quantises it (the decoder and the encoder must compute it alike)."""
    n0, n1 = c0 + 0.5, c1 + 0.5
    p = n1 / (n0 + n1)
    pm = 1.0 - p
    return np.int64(pm * ((_TOTAL - 2) / (pm + p))) + 1


@njit(cache=True, nogil=True)
def decode_bits(words, st, grid, at, bounds, deltas, weights, extra, n_ctx):
    """Bits at the flat positions ``at`` of ``grid`` (written there as decoded), wavefront by wavefront
    (``bounds`` delimit them in ``at``), each under ``Bernoulli(p, perfect=False)`` with the Krichevsky-Trofimov
    ``p = (n1 + 1/2) / (n0 + n1 + 1)`` of its context, counted over the wavefronts before. The context of
    ``at[i]``: ``sum_q grid[at[i] + deltas[q]] * weights[q]``, plus ``extra[i]`` when ``extra`` is not empty
    (a caller's own small integers, already scaled), below ``n_ctx``. Returns False when a context reaches
    ``n_ctx`` (then the grid holds what was decoded so far). Each context's quantised split is kept and worked
    out again only when a wavefront changed its counts (no division per bit: 7.6 -> 5.6 ms a kitchen chunk)."""
    counts = np.zeros((2, n_ctx), np.int64)
    split = np.full(n_ctx, _kt_split(0, 0), np.int64)
    widest = 0
    for w in range(len(bounds) - 1):
        widest = max(widest, bounds[w + 1] - bounds[w])
    buf_ctx = np.empty(widest, np.int64)
    has_extra = len(extra) > 0
    s, pos = st[0], np.int64(st[1])
    for w in range(len(bounds) - 1):
        a, b = bounds[w], bounds[w + 1]
        for i in range(a, b):
            g = at[i]
            ctx = _context(grid, g, deltas, weights, extra, i, has_extra)
            if ctx < 0 or ctx >= n_ctx:
                st[0], st[1] = s, np.uint64(pos)
                return False
            c1 = split[ctx]
            q = np.int64(s & _QMASK)
            if q < c1:
                s, pos = _advance(words, s, pos, 0, c1, q)
                grid[g] = 0
            else:
                s, pos = _advance(words, s, pos, c1, _TOTAL, q)
                grid[g] = 1
            buf_ctx[i - a] = ctx
        for i in range(a, b):
            counts[np.int64(grid[at[i]]), buf_ctx[i - a]] += 1
        for i in range(a, b):
            ctx = buf_ctx[i - a]
            split[ctx] = _kt_split(counts[0, ctx], counts[1, ctx])
    st[0], st[1] = s, np.uint64(pos)
    return True


@njit(cache=True, nogil=True)
def _wave_slots(sizes):
    """From the sizes of the wavefronts ``(W0,)``: (each one's first slot in the order ``(W0,)``, the bounds of the
    non-empty ones ``(W + 1,)``, their wavefronts ``(W,)``)."""
    n_waves = len(sizes)
    nxt = np.zeros(n_waves, np.int64)
    w_used = 0
    for w in range(n_waves):
        if w:
            nxt[w] = nxt[w - 1] + sizes[w - 1]
        if sizes[w]:
            w_used += 1
    bounds = np.zeros(w_used + 1, np.int64)
    waves = np.zeros(w_used, np.int64)
    u = 0
    for w in range(n_waves):
        if sizes[w]:
            waves[u] = w
            u += 1
            bounds[u] = bounds[u - 1] + sizes[w]
    return nxt, bounds, waves


@njit(cache=True, nogil=True)
def _block_table(dims, corner):
    """``(Bx, By, Bz)`` int64: the index of the block of 16^3 at each block position of a grid of ``dims`` (one
    voxel of padding around) whose blocks start at ``corner`` ``(n, 3)``; -1 where none."""
    nb = np.empty(3, np.int64)
    for d in range(3):
        nb[d] = max((dims[d] - 2) // 16, 1)
    occ = np.full((nb[0], nb[1], nb[2]), -1, np.int64)
    for b in range(len(corner)):
        occ[(corner[b, 0] - 1) >> 4, (corner[b, 1] - 1) >> 4, (corner[b, 2] - 1) >> 4] = b
    return occ


@njit(cache=True, nogil=True)
def wave_order(grid, dims, corner, pinned):
    """The positions :func:`decode_bits` takes for the pinned voxels of blocks of 16^3 placed in one grid:
    ``grid`` flat uint8 of ``dims`` ``(3,)`` (C order) holding 2 where nothing is pinned (left so), ``corner``
    ``(n, 3)`` each block's first voxel, ``pinned`` ``(n, 4096)`` bool (C order in the block). Returns (flat
    positions ``(m,)`` int64 wavefront by wavefront, ``x + y + z`` rising, C order within one; the bounds of the
    non-empty wavefronts ``(W + 1,)``): a counting sort by wavefront, then one scan of the grid in C order."""
    sy, sz = dims[1] * dims[2], dims[2]
    n_waves = dims[0] + dims[1] + dims[2]
    sizes = np.zeros(n_waves, np.int64)
    m = 0
    for b in range(len(corner)):
        x0, y0, z0 = corner[b, 0], corner[b, 1], corner[b, 2]
        for v in range(4096):
            if pinned[b, v]:
                i, j, k = x0 + (v >> 8), y0 + ((v >> 4) & 15), z0 + (v & 15)
                grid[i * sy + j * sz + k] = 0
                sizes[i + j + k] += 1
                m += 1
    nxt, bounds, _ = _wave_slots(sizes)
    at = np.empty(m, np.int64)
    # the scan visits the blocks' voxels only (C order: x, y, then the blocks along z), not the whole box
    nb = np.empty(3, np.int64)
    for d in range(3):
        nb[d] = max((dims[d] - 2) // 16, 1)
    occ = np.zeros((nb[0], nb[1], nb[2]), np.bool_)
    for b in range(len(corner)):
        occ[(corner[b, 0] - 1) >> 4, (corner[b, 1] - 1) >> 4, (corner[b, 2] - 1) >> 4] = True
    for i in range(1, dims[0] - 1):
        for j in range(1, dims[1] - 1):
            base = i * sy + j * sz
            for bz in range(nb[2]):
                if not occ[(i - 1) >> 4, (j - 1) >> 4, bz]:
                    continue
                for k in range(bz * 16 + 1, bz * 16 + 17):
                    if grid[base + k] == 0:
                        w = i + j + k
                        at[nxt[w]] = base + k
                        nxt[w] += 1
                        grid[base + k] = 2
    return at, bounds


#: The index of a power of two below 2^16 from its product with the de Bruijn sequence 0x09AF (its top four
#: bits, all distinct): a set bit's position without a loop over the bits below it (a table by the remainder
#: modulo 37 measured 0.15 ms more on the kitchen's 592k pins).
_LOW_BIT = np.zeros(16, np.int64)
for _k in range(16):
    _LOW_BIT[(((1 << _k) * 0x09AF) >> 12) & 15] = _k
#: A byte's eight bits spread over the eight bytes of a uint64 (bit k to byte k): sixteen rows summed as bytes.
_SPREAD = np.array([sum(((v >> k) & 1) << (8 * k) for k in range(8)) for v in range(256)], np.uint64)


@njit(cache=True, nogil=True)
def wave_sizes(dims, corner, rows):
    """The pinned voxels of each wavefront ``(S, dims[0] + dims[1] + dims[2])`` int64 per slab of blocks along
    the first axis (``S = (dims[0] - 2) // 16``, the slab of a block ``(corner[b, 0] - 1) >> 4``): pins as rows
    ``(n, 16, 16)`` uint16 (bit ``z``: voxel ``z``) of blocks with first voxels ``corner`` ``(n, 3)``. A row's
    bits are spread over bytes and summed along each anti-diagonal ``x + y`` of the block (at most 16 rows: no
    byte overflows), then added per wavefront: 0.23 ms for the kitchen's 592k pins, one count a bit 1.24."""
    n_waves = dims[0] + dims[1] + dims[2]
    sizes = np.zeros((max((dims[0] - 2) // 16, 1), n_waves), np.int64)
    diag = np.zeros((31, 2), np.uint64)
    for b in range(len(corner)):
        slab = (corner[b, 0] - 1) >> 4
        base = corner[b, 0] + corner[b, 1] + corner[b, 2]
        diag[:] = 0
        for x in range(16):
            for y in range(16):
                r = rows[b, x, y]
                diag[x + y, 0] += _SPREAD[r & 0xFF]
                diag[x + y, 1] += _SPREAD[r >> 8]
        for d in range(31):
            for h in range(2):
                v = diag[d, h]
                for k in range(8):
                    sizes[slab, base + d + 8 * h + k] += np.int64((v >> np.uint64(8 * k)) & np.uint64(0xFF))
    return sizes


@njit(cache=True, nogil=True)
def wave_place(dims, corner, rows, nxt, slabs, out):
    """Place the pinned voxels of the blocks of slabs ``slabs`` ``(2,)`` (``[first, end)``, :func:`wave_sizes`)
    in ``out`` ``(m,)`` int64, the next free slot of each wavefront ``w`` ``nxt[w]`` (advanced), C order
    (``i``, then ``j``) within a wavefront: ``(b * 4096 + voxel) << 32 | i << 16 | j`` for grid position ``(i,
    j, w - i - j)``, voxel ``voxel`` of block ``b``. Slabs placed apart (on threads) fill ``out`` alike, given
    the slots of the slabs before them."""
    occ = _block_table(dims, corner)
    for i in range(slabs[0] * 16 + 1, min(slabs[1] * 16 + 1, dims[0] - 1)):
        for j in range(1, dims[1] - 1):
            for bz in range(occ.shape[2]):
                b = occ[(i - 1) >> 4, (j - 1) >> 4, bz]
                if b < 0:
                    continue
                r = np.int64(rows[b, (i - 1) & 15, (j - 1) & 15])
                w0 = np.uint64(i + j + bz * 16 + 1)  # indices as uint64: no test for a negative one
                v = ((b * 4096 + (((i - 1) & 15) << 8) + (((j - 1) & 15) << 4)) << 32) | (i << 16) | j
                while r:
                    k = _LOW_BIT[np.uint64((((r & -r) * 0x09AF) >> 12) & 15)]
                    at = w0 + np.uint64(k)
                    out[np.uint64(nxt[at])] = v + (k << 32)
                    nxt[at] += 1
                    r &= r - 1


@njit(cache=True, nogil=True)
def decode_planes(words, st, dims, ij, waves, bounds, nbr, weights, n_ctx):
    """:func:`decode_bits` of the positions ``ij`` of :func:`wave_place`, the same bits from the same words,
    without the grid: a context reads its neighbours ``nbr`` ``(q, 3)`` rows ``(dw, di, dj)`` (``dw < 0``: in an
    earlier wavefront) from the last three wavefronts kept as planes of ``dims[0] x dims[1]`` (2: not pinned),
    which stay in cache where a grid of the chunk's voxels did not. Returns (ok, the ``b * 4096 + voxel`` of
    the positions whose bit is 0 ``(z,)`` int64, in decode order), written over the start of ``ij``: a fresh
    array of the positions' size measured 1 ms more of the kitchen's 592k, the page faults of its first writes.

    One pass per wavefront for its contexts (they read earlier wavefronts only) and their plane slots, one
    for its bits, counting them as they come and listing the contexts whose split must be worked out again
    (the counts of a wavefront change its splits only after it: three passes measured 1.2x the time). Each
    bit's voxel is stored whether or not it is 0, the next slot taken only after a 0: no branch on the bit
    (a pass over the bits after this one measured 2.5 ms for 592k of them, this 0.35 ms more here)."""
    s0, s1 = dims[0], dims[1]
    plane = np.full((3, s0, s1), 2, np.uint8)
    owner = np.full(3, -1, np.int64)  # the wavefront each plane holds
    counts = np.zeros(2 * n_ctx, np.int64)  # (context, bit) interleaved: one cache line holds both
    split = np.full(n_ctx, _kt_split(0, 0), np.int64)
    stamp = np.full(n_ctx, -1, np.int64)  # the wavefront whose counts changed a context's split
    changed = np.empty(n_ctx, np.int64)  # those contexts, listed once each
    top = 0
    for q in range(len(weights)):
        top += 2 * weights[q]
    bounded = top < n_ctx  # the planes hold 0, 1, 2 only: no context can reach n_ctx, none is checked
    nz = np.uint64(0)  # the zeros found: never past the position at hand, nor those of the wavefronts to come
    widest = 0
    for u in range(len(bounds) - 1):
        widest = max(widest, bounds[u + 1] - bounds[u])
    buf_ctx = np.empty(widest, np.int64)
    held = np.empty((3, max(widest, 1)), np.int64)  # each plane's bits' slots in flat, beside their contexts,
    n_held = np.zeros(3, np.int64)  # kept to clear the plane (ij is overwritten by then)
    flat = plane.reshape(-1)
    off = np.empty(len(weights), np.int64)  # each neighbour's offset in flat, for the wavefront at hand
    s, pos = st[0], np.int64(st[1])
    us1 = np.uint64(s1)
    for u in range(len(waves)):
        w = waves[u]
        for q in range(len(weights)):  # (no division per bit: the planes' slots worked out once a wavefront)
            off[q] = ((w + nbr[q, 0]) % 3) * s0 * s1 + nbr[q, 1] * s1 + nbr[q, 2]
        for back in range(3):  # the planes of w - 2, w - 1, w: cleared unless they hold those wavefronts
            wb = w - back
            slot = wb % 3
            if owner[slot] != wb:
                for t in range(n_held[slot]):
                    flat[np.uint64(held[slot, t])] = 2
                owner[slot], n_held[slot] = wb, 0
        a, b = bounds[u], bounds[u + 1]
        me = w % 3
        n_held[me] = b - a
        buf_at = held[me]
        mine = me * s0 * s1
        if len(weights) == 6 and bounded:  # M2's six neighbours, unrolled (a loop measured 1.2x the time)
            o0, o1, o2, o3, o4, o5 = (np.uint64(off[0]), np.uint64(off[1]), np.uint64(off[2]), np.uint64(off[3]),
                                      np.uint64(off[4]), np.uint64(off[5]))  # negative ones wrap, as the sums do
            w0, w1, w2, w3, w4, w5 = weights[0], weights[1], weights[2], weights[3], weights[4], weights[5]
            for t in range(a, b):
                v = np.uint64(ij[t])
                at = ((v >> _16) & _LOW16) * us1 + (v & _LOW16)
                buf_at[t - a] = np.int64(at) + mine
                buf_ctx[t - a] = (np.int64(flat[at + o0]) * w0 + np.int64(flat[at + o1]) * w1
                                  + np.int64(flat[at + o2]) * w2 + np.int64(flat[at + o3]) * w3
                                  + np.int64(flat[at + o4]) * w4 + np.int64(flat[at + o5]) * w5)
        else:
            for t in range(a, b):
                at = ((ij[t] >> 16) & 0xFFFF) * s1 + (ij[t] & 0xFFFF)
                ctx = 0
                for q in range(len(weights)):
                    ctx += np.int64(flat[at + off[q]]) * weights[q]
                if ctx >= n_ctx:
                    st[0], st[1] = s, np.uint64(pos)
                    return False, ij[:0]
                buf_at[t - a] = at + mine
                buf_ctx[t - a] = ctx
        nc = 0
        for t in range(a, b):  # indices as uint64 here and above: no test for a negative one (5.8 -> 3.9 ms)
            r = np.uint64(t - a)
            ctx = np.uint64(buf_ctx[r])
            c1 = split[ctx]
            qv = np.int64(s & _QMASK)
            up = qv >= c1  # selects, not a branch: the bits of a mask are not predictable
            lo, fr = (c1, _TOTAL - c1) if up else (0, c1)
            s = (s >> _PREC) * np.uint64(fr) + np.uint64(qv - lo)  # _advance's step, the width not a difference
            if s < _LOW and pos > 0:
                pos -= 1
                s = (s << _W) | np.uint64(words[pos])
            flat[np.uint64(buf_at[r])] = np.uint8(up)
            ij[nz] = ij[np.uint64(t)] >> 32
            nz += _ONE - np.uint64(up)
            counts[_TWO * ctx + np.uint64(up)] += 1
            if stamp[ctx] != u:
                stamp[ctx] = u
                changed[nc] = ctx
                nc += 1
        for k in range(nc):  # each context's split once a wavefront (two divisions), not once a bit
            ctx = changed[k]
            split[ctx] = _kt_split(counts[2 * ctx], counts[2 * ctx + 1])
    st[0], st[1] = s, np.uint64(pos)
    return True, ij[:nz]


@njit(cache=True, nogil=True)
def padded_states(bits):
    """Voxel bits ``(p, 4096)`` uint8 (0/1, C order) -> (the voxels padded by one with zeros ``(p * 18^3,)``
    uint8, the sub-cube states ``(p, 512)`` int64: 0 none observed, 1 all, 2 mixed)."""
    p_rows = len(bits)
    vpad = np.zeros(p_rows * 18 * 18 * 18, np.uint8)
    sums = np.zeros((p_rows, 512), np.int64)
    for r in range(p_rows):
        for c in range(4096):
            b = bits[r, c]
            vpad[r * 5832 + (((c >> 8) + 1) * 18 + ((c >> 4) & 15) + 1) * 18 + (c & 15) + 1] = b
            sums[r, ((c >> 9) & 7) * 64 + ((c >> 5) & 7) * 8 + ((c >> 1) & 7)] += b
    states = np.where(sums == 0, 0, np.where(sums == 8, 1, 2))
    return vpad, states


@njit(cache=True, nogil=True)
def cube_intervals(states, cube_at, cube_flat, cube_bounds, cube_deltas, left, freq, m):
    """The encoder's side of :func:`decode_cubes`: the intervals of the known states ``(p, 512)`` written to
    ``left``/``freq`` from ``m`` on, in decode order; returns the next free index."""
    p_rows = len(states)
    cstride = 10 * 10 * 10
    cflat = np.full(p_rows * cstride, 3, np.uint8)
    for r in range(p_rows):
        for t in range(len(cube_at)):
            cflat[r * cstride + cube_at[t]] = states[r, cube_flat[t]]
    n_ctx = 4 ** len(cube_deltas)
    counts = np.zeros((3, n_ctx), np.int64)
    cdf = np.empty((n_ctx, 2), np.int64)
    buf_ctx = np.empty(p_rows * 64, np.int64)  # a wavefront of 8^3 has at most 48 cells
    buf_sym = np.empty(p_rows * 64, np.int64)
    for w in range(len(cube_bounds) - 1):
        _cube_tables(counts, cdf)
        a = m
        for r in range(p_rows):
            for t in range(cube_bounds[w], cube_bounds[w + 1]):
                at = r * cstride + cube_at[t]
                ctx = _cube_context(cflat, at, cube_deltas)
                sym = np.int64(cflat[at])
                lo = 0 if sym == 0 else cdf[ctx, sym - 1]
                hi = _TOTAL if sym == 2 else cdf[ctx, sym]
                left[m], freq[m] = lo, hi - lo
                buf_ctx[m - a], buf_sym[m - a] = ctx, sym
                m += 1
        for i in range(m - a):
            counts[buf_sym[i], buf_ctx[i]] += 1
    return m


@njit(cache=True, nogil=True)
def bit_intervals(grid, at, bounds, deltas, weights, extra, n_ctx, left, freq, m):
    """The encoder's side of :func:`decode_bits`: the intervals of the known bits ``grid[at]``, from ``m`` on;
    returns the next free index, or -1 when a context reaches ``n_ctx``."""
    counts = np.zeros((2, n_ctx), np.int64)
    ctxs = np.empty(len(at), np.int64)
    has_extra = len(extra) > 0
    for w in range(len(bounds) - 1):
        a, b = bounds[w], bounds[w + 1]
        for i in range(a, b):
            pos = at[i]
            ctx = _context(grid, pos, deltas, weights, extra, i, has_extra)
            if ctx < 0 or ctx >= n_ctx:
                return -1
            ctxs[i] = ctx
            c1 = _kt_split(counts[0, ctx], counts[1, ctx])
            if grid[pos]:
                left[m], freq[m] = c1, _TOTAL - c1
            else:
                left[m], freq[m] = 0, c1
            m += 1
        for i in range(a, b):
            counts[np.int64(grid[at[i]]), ctxs[i]] += 1
    return m


@njit(cache=True, nogil=True)
def _cdf_of(table, out, o, cum):
    """``out[o:o + n + 1]`` = the cumulative table of probabilities ``table`` ``(n,)`` float64 (the left-to-right
    sums first, into the scratch ``cum``: one chain of dependent adds, not two)."""
    n = len(table)
    c = 0.0
    for i in range(n):
        cum[i] = c
        c += table[i]
    scale = (_TOTAL - n) / c
    for i in range(n):
        out[o + i] = np.uint32(np.int64(cum[i] * scale) + i)
    out[o + n] = _TOTAL


@njit(cache=True, nogil=True)
def table_cdfs(first, decay, extent):
    """Cumulative tables, concatenated ``(len(first) + 1 + sum(2 e_j + 2),)`` uint32, of ``first`` (float64) and
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
    out = np.empty(o, np.uint32)  # 2^24 fits: half the bytes a decode walks through
    cum = np.empty(max(sizes.max(), 1))
    _cdf_of(first, out, 0, cum)
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
        _cdf_of(table, out, at[j + 1], cum)
    return out, at, sizes


@njit(cache=True, nogil=True)
def chunk_decode(words, n, level, cdfs, at, slots, shift, off):
    """The variable-rate chunk stream of :func:`sdfcodec.core.varrate.decode_chunk`: ``n`` lengths under the
    table at ``cdfs[at[0]:]``, then for ``j < level`` element ``j`` of every block longer than ``j`` under the
    table ``j + 1``, minus ``off[j]`` (``slots`` ``(D + 1, 2^(24 - shift))``: :func:`slot_table` of each table).
    Returns (status: 0 ok, 1 a trailing zero word; ``(n, level)`` int32)."""
    out = np.zeros((n, level), np.int32)
    st = np.zeros(2, np.uint64)
    if not start(words, st):
        return 1, out
    k = np.empty(n, np.int64)
    s, pos = st[0], np.int64(st[1])
    for i in range(n):
        k[i], s, pos = _from_slots(words, s, pos, cdfs, at[0], slots, 0, shift)
    for j in range(level):
        any_ = False
        for i in range(n):
            if k[i] > j:
                any_ = True
                v, s, pos = _from_slots(words, s, pos, cdfs, at[j + 1], slots, j + 1, shift)
                out[i, j] = v - off[j]
        if not any_:
            break
    return 0, out


@njit(cache=True, nogil=True)
def slot_table(cdfs, at, shift):
    """``(len(at), 2^(24 - shift))`` int64: for each table ``j`` of ``cdfs`` (starting at ``at[j]``, as
    :func:`table_cdfs` gives them) and each slot ``t`` of the quantiles ``[t 2^shift, (t + 1) 2^shift)``, where a
    decode of a symbol starts: ``k << 48 | cdf[k] << 24 | (cdf[k + 1] - cdf[k])`` when the whole slot lies in
    symbol ``k`` (below 2^15), else ``-1 - s`` for the symbol ``s`` with ``cdf[s] <= t 2^shift < cdf[s + 1]``."""
    out = np.empty((len(at), 1 << (24 - shift)), np.int64)
    for j in range(len(at)):
        k = 0
        for t in range(out.shape[1]):
            while np.int64(cdfs[at[j] + k + 1]) <= (t << shift):
                k += 1
            left, right = np.int64(cdfs[at[j] + k]), np.int64(cdfs[at[j] + k + 1])
            if right >= (t + 1) << shift and k < 1 << 15:  # (15 bits keep the entry positive)
                out[j, t] = (k << 48) | (left << 24) | (right - left)
            else:
                out[j, t] = -1 - k
    return out


@njit(cache=True, nogil=True)
def categorical_decode(words, st, n, cdf, slots, shift):
    """``n`` symbols ``(n,)`` int32, each under the one table ``cdf`` (``m + 1`` entries, :func:`table_cdfs`;
    ``slots`` ``(1, 2^(24 - shift))``: its :func:`slot_table`), from the decoder state ``st`` (left where the
    last symbol leaves it)."""
    out = np.empty(n, np.int32)
    s, pos = st[0], np.int64(st[1])
    for i in range(n):
        out[i], s, pos = _from_slots(words, s, pos, cdf, 0, slots, 0, shift)
    st[0], st[1] = s, np.uint64(pos)
    return out


#: The flag :func:`categorical_ahead` sets on a symbol after which the state is 0 (symbols are below 2^16).
AHEAD_EMPTY = np.int32(1 << 30)


@njit(cache=True, nogil=True)
def categorical_ahead(words, st, cap, cdf, slots, shift):
    """:func:`categorical_decode` of a stream whose length is not known yet: symbols ``(m',)`` int32 until the
    coder is empty for good (state 0 and every word read: each further symbol is then the table's first, the state
    staying 0) or ``cap`` symbols, each flagged with :data:`AHEAD_EMPTY` where the state is 0 after it (what
    ``is_empty`` tells after that many symbols)."""
    out = np.empty(cap, np.int32)
    s, pos = st[0], np.int64(st[1])
    n = 0
    while n < cap and not (s == 0 and pos == 0):
        k, s, pos = _from_slots(words, s, pos, cdf, 0, slots, 0, shift)
        out[n] = k | AHEAD_EMPTY if s == 0 else k
        n += 1
    st[0], st[1] = s, np.uint64(pos)
    return out[:n].copy()


@njit(cache=True, nogil=True)
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
