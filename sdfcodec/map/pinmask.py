"""An observation mask coded only where it can change the surface, at voxels a reader finds itself (stream ``M2``
of the map extension ``pinned-observation-mask``, spec/map-format.md section 6g; stored by
:mod:`sdfcodec.map.pinstore`).

:mod:`sdfcodec.map.lossymask` keeps the true mask bit at the *pinned* voxels (the corners of every 2^3 cell whose
decode changes sign) and codes every voxel with :mod:`sdfcodec.map.maskcoder`. If the reader can find the pinned
voxels itself, only their bits need storing: every other voxel reads a fixed value (observed) without moving any
surface point or triangle. The reader cannot use its float decode for that: a matrix product is not bit-identical
across BLAS libraries and devices, so a cell at ``-1e-9`` on one machine and ``+1e-9`` on another would
desynchronise the stream. Here the decision is exact:

* **An exact integer decode.** A dataset-mean PCA decode in metres is ``a0 + sum_i q_i a_i`` with ``q`` the
  variable-rate integer codes. Its basis is rounded to multiples of ``2^-S`` metres (:func:`fixed_point_basis`):
  ``A = rint(2^S a)``, and ``v = A0 + q A`` is an integer product. Every partial sum is an integer below
  ``2^53`` (checked), so the float64 matrix product computes it exactly in any order, with or without FMA, on
  any machine: no compiled kernel needed and no fallback to keep identical. (A block whose bound ``T`` below is
  under ``2^24`` multiplies in float32, where the same argument holds; each block multiplies its prefix only.)
* **A proven bound.** A float decode ``x`` (metres, from float32 codes ``q step`` and float32 components, summed
  in any order) differs from ``v 2^-S`` by at most ``E 2^-S``, ``E = 1 + sum|q| + ceil(g T)`` per block, with
  ``T = max|A0| + sum_i |q_i| max|A_i|`` and ``g = (k + 4) 2^-20`` (16 times the worst-case float32 dot product
  bound ``(k + 2) 2^-24``, for the rounding of the folded decoder and of ``q step``). So ``v - E < 0`` whenever
  ``x < 0`` and ``v + E >= 0`` whenever ``x >= 0``: a cell is *relevant* when its corners may be negative and
  may be non-negative (:func:`exact_pins`); every cell whose float decode changes sign on any machine is one.
* **Chunks decode alone.** A stream covers one mask chunk. A neighbouring coded block outside it is read as
  "may be either sign", one that is not coded as ``d_max``, so a reader needs only the chunk's codes.

Which bits to store (:func:`canonical_bits`): not the truth. A voxel only matters through the relevant cells and
the sign-changing edges it belongs to: a cell is meshed only when all its corners are observed, an edge counts a
crossing only when both ends are. So the stored bit is 1 exactly at the corners of relevant cells the true mask
observes fully and at the ends of observed sign-changing edges, 0 at every other pinned voxel. Every cell and
edge that can carry a surface is then meshed or not exactly as under the true mask (a relevant cell not fully
observed keeps its unobserved corner, which is in no meshed cell and no observed edge: 0), and zeros elsewhere
are free (module :mod:`sdfcodec.map.lossymask`). This is cheaper than the truth because the meshed region is
what it spells, not the fusion's ragged borders (kitchen half at 64 B, estimated with contexts over the whole map:
14.0 against 19.9 B per block). The writer may still store 1 at any pinned voxel the canonical bits leave 0, as
long as no relevant cell becomes all 1 and no edge that may change sign gets both ends 1: :func:`chosen_bits`
picks those bits by the stream's length (kitchen half at 64 B, raw streams: 12.05 B per block canonical, 11.72
with only the truly observed ones set where the adaptive model expects a 1 (:func:`cheapest_bits`, what the
writer stores by default), 10.91; the writer runs it below 128 B per block, ``PinnedStreams.choose``).

Coding (:func:`encode_pinned`): the pinned voxels of the chunk's blocks placed in one voxel grid, wavefront by
wavefront (``x + y + z``; across block faces, so that a voxel's context sees its neighbours in the next block:
14.0 against 17.0 B per block with one wavefront order per block on the kitchen half at 64 B), each under the
context of its six neighbours before it along one or two axes, each read as 0, 1 or "not pinned" (3^6
contexts), with Krichevsky-Trofimov counts updated per wavefront (as in ``M1``); constriction's AnsCoder.
Stream: ``b"M2"``, the number of pinned voxels (uint32 LE, which the reader checks against its own count), the
AnsCoder words (uint32 LE).
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from ..core import ans
from ..core._validate import BLOCK
from ..core.surface import JUMP
from ..errors import ChecksumError, InvalidValueError
from .grouping import each_chunk
from .lossymask import neighbours, padded_blocks

__all__ = ["FRACTION_BITS", "fixed_point_basis", "exact_decode", "sign_bounds", "exact_pins", "pinned_voxels_of", "pinned_rows", "decode_bounds", "canonical_bits", "cheapest_bits", "chosen_bits", "encode_pinned",
           "decode_pinned", "unobserved_voxels", "NEIGHBOURS"]

#: Fixed-point fraction bits of the exact decode: metres in multiples of 2^-24 (6e-8 m, far below any step).
FRACTION_BITS = 24
#: Context neighbours ``(di, dj, dk)`` of a pinned voxel (all on earlier wavefronts).
NEIGHBOURS = ((-1, 0, 0), (0, -1, 0), (0, 0, -1), (-1, -1, 0), (-1, 0, -1), (0, -1, -1))
_MAGIC = b"M2"
_EXACT = 2.0 ** 53  # integers below this are exact in float64, and so is every partial sum of the product
_PAD = BLOCK + 2
_SINGLE = 2.0 ** 24  # integers below this, and every sum of them that stays below it, are exact in float32
_RUN = 16  # the exact product's column runs: blocks whose prefixes round up alike share one matrix product


def fixed_point_basis(components: np.ndarray, mean: np.ndarray, step: np.ndarray, truncation: tuple[float, float]
                      ) -> np.ndarray:
    """``(k + 1, 4096)`` float64 integers: row 0 the mean, row ``i + 1`` component ``i`` times its step, in metres
    times ``2^FRACTION_BITS``, rounded to nearest (deterministic: float64 products of the stored float32 values).

    Args:
        components: ``(k, 4096)`` float32, the dataset-mean PCA basis (normalised units).
        mean: ``(4096,)`` float32.
        step: ``(k,)`` quantisation steps of the integer codes.
        truncation: ``(d_min, d_max)`` metres; the decode ``x`` normalised is ``x (d_max - d_min) + d_min`` metres.
    """
    d_min, d_max = (float(t) for t in truncation)
    scale = 2.0 ** FRACTION_BITS
    comp = np.asarray(components, np.float32).astype(np.float64)
    step = np.asarray(step, np.float64).reshape(-1, 1)[: len(comp)]
    a0 = np.rint((np.asarray(mean, np.float32).astype(np.float64) * (d_max - d_min) + d_min) * scale)
    return np.vstack([a0[None], np.rint(comp * step * (d_max - d_min) * scale)])


def exact_decode(q: np.ndarray, basis: np.ndarray, size: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The exact decode ``(n, 4096)`` float64 integers (metres times ``2^FRACTION_BITS``) of integer codes ``q``
    ``(n, k')`` (``k' <= k``; a prefix) and its error bound ``E`` ``(n,)`` float64 integers (module docstring)
    for codes of length ``size`` (default ``k'``: the ``D`` of the bound).

    Raises:
        InvalidValueError: a partial sum could reach ``2^53`` (codes far beyond any map's), so exactness is not
            guaranteed.
    """
    q = np.asarray(q, np.float64)
    size = q.shape[1] if size is None else int(size)  # D of the bound: the codes' length, not the prefix used
    used = int(np.flatnonzero(q.any(axis=0)).max(initial=-1)) + 1  # columns past every prefix add nothing
    q = q[:, :used]
    peak, bound = decode_bounds(q, basis, size)
    return _product(q, basis[1:used + 1], basis[0], peak), bound


def decode_bounds(q: np.ndarray, basis: np.ndarray, size: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``(T, E)`` ``(n,)`` float64 integers of :func:`exact_decode` (module docstring) for integer codes ``q``
    ``(n, k')`` and codes of length ``size`` (default ``k'``), without the decode.

    Raises:
        InvalidValueError: a partial sum could reach ``2^53``, as :func:`exact_decode`.
    """
    q = np.asarray(q, np.float64)
    n, k = q.shape[0], q.shape[1] if size is None else int(size)
    absq = np.abs(q)
    top = _row_peaks(basis)
    peak = top[0] + absq @ top[1:q.shape[1] + 1]  # T, exact (small integers)
    if n and float(peak.max()) * 2 >= _EXACT:
        raise InvalidValueError(f"codes up to {absq.max():g} are too large for the exact decode of the pinned mask "
                                "(partial sums reach 2^52); use the exact mask (--exact-mask)")
    return peak, 1.0 + absq.sum(axis=1) + np.ceil(peak * (k + 4) / 2.0 ** 20)


_PEAKS: list = []  # (a basis, max |row| of it): a map's reads use one basis (4 MB read once, not per chunk)


def _row_peaks(basis: np.ndarray) -> np.ndarray:
    """``(k + 1,)`` float64: ``max_j |basis[i, j]|`` per row, kept for the last basis asked."""
    kept = _PEAKS[0] if _PEAKS else None  # (a local: another thread may replace the entry meanwhile)
    if kept is None or kept[0] is not basis:
        kept = (basis, np.abs(basis).max(axis=1))
        _PEAKS[:] = [kept]
    return kept[1]


def _product(q: np.ndarray, a: np.ndarray, a0: np.ndarray, peak: np.ndarray) -> np.ndarray:
    """``q @ a + a0`` (float64 integers) with each block's product cut to its prefix (rounded up to :data:`_RUN`
    columns): the columns cut are exact zeros in every term, and every partial sum is an integer below ``2^53``,
    so the result is the full product's in any order (low-rate blocks keep a few of 64-128 columns). Blocks whose
    bound ``T`` (``peak`` ``(n,)``) is below ``2^24`` multiply in float32: every term, partial sum and entry they
    use is then an integer below ``2^24``, exact in float32 too (a zero code times a rounded entry is 0)."""
    n, k = q.shape
    if not n:
        return np.zeros((0, len(a0)))
    nz = q != 0
    width = np.where(nz.any(axis=1), k - np.argmax(nz[:, ::-1], axis=1), 0)
    width = np.minimum(-(-width // _RUN) * _RUN, k)
    single = np.asarray(peak) < _SINGLE
    v = np.empty((n, len(a0)))
    a32 = (a.astype(np.float32), a0.astype(np.float32)) if single.any() else (a, a0)  # (unused then)
    for w in np.unique(width):
        for rows, (aw, b0) in ((np.flatnonzero((width == w) & single), a32),
                               (np.flatnonzero((width == w) & ~single), (a, a0))):
            if len(rows):
                v[rows] = q[rows, :w].astype(aw.dtype) @ aw[:w] + b0 if w else b0
    return v


def exact_pins(coords: np.ndarray, neg: np.ndarray, pos: np.ndarray, outside_coded: np.ndarray,
               truncation: tuple[float, float], jump: float = JUMP) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Relevant cells and pinned voxels of the blocks ``coords`` ``(n, 3)``, from where their decode may be
    negative (``neg``) and non-negative (``pos``), ``(n, 4096)`` or ``(n, 16, 16, 16)`` bool: ``v - E < 0`` and
    ``v + E >= 0`` of :func:`exact_decode` (:func:`sign_bounds`).

    ``outside_coded`` ``(m, 3)``: coded blocks that are not among ``coords`` (another chunk's): their voxels may
    take either sign; every other block around reads ``d_max``.

    Returns:
        ``(pinned (n, 16, 16, 16) bool, neg (n, 18, 18, 18) bool, pos (n, 18, 18, 18) bool)``: the voxels in a
        relevant cell, and ``neg``, ``pos`` with the one-voxel layer of the neighbours around each block.
    """
    coords = np.asarray(coords, np.int64).reshape(-1, 3)
    outside = np.asarray(outside_coded, np.int64).reshape(-1, 3)
    n, shape = len(coords), (-1, BLOCK, BLOCK, BLOCK)
    all_c = np.concatenate([coords, outside])
    either = np.ones((len(outside), BLOCK, BLOCK, BLOCK), bool)
    neg = padded_blocks(all_c, np.concatenate([np.asarray(neg, bool).reshape(shape), either]), False)[:n]
    pos = padded_blocks(all_c, np.concatenate([np.asarray(pos, bool).reshape(shape), either]), True)[:n]
    return _cells(_relevant(neg, pos, truncation, jump), np.logical_or), neg, pos


def pinned_voxels_of(coords: np.ndarray, neg: np.ndarray, pos: np.ndarray, outside_coded: np.ndarray,
                     truncation: tuple[float, float], jump: float = JUMP) -> np.ndarray:
    """``(n, 16, 16, 16)`` bool: the pinned voxels of :func:`exact_pins` (its first result, the same bools),
    computed on rows of 18 bits (:func:`pinned_rows`; :func:`exact_pins` also returns the padded signs)."""
    n = len(np.asarray(coords).reshape(-1, 3))
    rows = [_rows(np.asarray(s, bool).reshape(n, BLOCK, BLOCK, BLOCK)) for s in (neg, pos)]
    return _unpack_rows(pinned_rows(coords, *rows, outside_coded, truncation, jump))


def _unpack_rows(rows: np.ndarray) -> np.ndarray:
    """``(n, 16, 16, 16)`` bool of rows ``(n, 16, 16)`` uint16 (bit ``z``: voxel ``z``)."""
    n = len(rows)
    flat = np.ascontiguousarray(rows, "<u2").reshape(-1).view(np.uint8)
    return np.unpackbits(flat, bitorder="little").view(bool).reshape(n, BLOCK, BLOCK, BLOCK)


def pinned_rows(coords: np.ndarray, neg_rows: np.ndarray, pos_rows: np.ndarray, outside_coded: np.ndarray,
                truncation: tuple[float, float], jump: float = JUMP) -> np.ndarray:
    """``(n, 16, 16)`` ``<u2``: bit ``z`` of row ``(x, y)`` set where voxel ``(x, y, z)`` of block ``coords[b]``
    ``(n, 3)`` is pinned (:func:`pinned_voxels_of`), from the signs as rows: ``neg_rows``, ``pos_rows`` ``(n, 16,
    16)`` uint32 with bit ``z + 1`` set where voxel ``z`` may be negative, non-negative (bits 0 and 17 clear).
    The neighbours' layers, the cells' OR over 2 x 2 x 2 corners and the voxels' OR over their 8 cells are a few
    whole-row operations per block instead of one per voxel."""
    coords = np.asarray(coords, np.int64).reshape(-1, 3)
    outside = np.asarray(outside_coded, np.int64).reshape(-1, 3)
    n = len(coords)
    cells = []
    for rows, free in ((neg_rows, 0), (pos_rows, _ROW18)):
        src = np.concatenate([rows, np.full((len(outside), BLOCK, BLOCK), _ROW16 << 1, np.uint32)])  # either
        cells.append(_cell_rows(_padded_rows(np.concatenate([coords, outside]), src, n, free)))
    rel = cells[0] & cells[1] if float(truncation[1]) >= jump else cells[0]
    rel &= np.uint32(_ROW18 >> 1)  # cells with lower corners 0..16
    pin = rel[:, 1:, 1:] | rel[:, :-1, 1:] | rel[:, 1:, :-1] | rel[:, :-1, :-1]  # (n, 16, 16): x, y in 1..16
    return ((pin | (pin >> 1)) & _ROW16).astype("<u2")  # voxel z in cell z (lower) or z + 1 (upper)


_ROW16, _ROW18 = np.uint32(0xFFFF), np.uint32(0x3FFFF)


def _rows(a: np.ndarray) -> np.ndarray:
    """``(n, 16, 16)`` uint32 of ``a`` ``(n, 16, 16, 16)`` bool: bit ``z + 1`` is ``a[..., z]`` (bit 0 and 17: the
    padding)."""
    packed = np.packbits(np.ascontiguousarray(a).reshape(-1), bitorder="little")  # flat: z is the fastest axis
    return packed.view("<u2").reshape(a.shape[:3]).astype(np.uint32) << np.uint32(1)


def _padded_rows(coords: np.ndarray, rows: np.ndarray, n: int, free: np.uint32) -> np.ndarray:
    """``(n, 18, 18)`` uint32: the first ``n`` blocks' rows (:func:`_rows`) with the one-voxel layer of their 26
    neighbours among ``coords`` ``(m, 3)`` (rows ``(m, 16, 16)``), ``free`` (0 or all 18 bits) elsewhere."""
    out = np.full((n, _PAD, _PAD), free, np.uint32)
    out[:, 1:-1, 1:-1] = rows[:n] | (free & np.uint32(0x20001))  # z padding: free until a neighbour lends it
    src = {-1: slice(BLOCK - 1, BLOCK), 0: slice(0, BLOCK), 1: slice(0, 1)}  # the rows the neighbour lends
    dst = {-1: slice(0, 1), 0: slice(1, BLOCK + 1), 1: slice(BLOCK + 1, BLOCK + 2)}
    for (a, b, c), hit, source in neighbours(coords, n):
        lent = rows[source, src[a], src[b]]
        if c == 0:  # the neighbour beside it in x or y: its whole rows, padding bits kept
            keep, got = _ROW18 & ~np.uint32(0x1FFFE), lent & np.uint32(0x1FFFE)
        elif c < 0:  # below in z: its voxel z = 15 (bit 16) becomes this block's padding bit 0
            keep, got = _ROW18 & ~np.uint32(1), (lent >> np.uint32(16)) & np.uint32(1)
        else:  # above in z: its voxel z = 0 (bit 1) becomes padding bit 17
            keep, got = _ROW18 & ~np.uint32(1 << 17), (lent & np.uint32(2)) << np.uint32(16)
        view = out[hit, dst[a], dst[b]]
        out[hit, dst[a], dst[b]] = (view & keep) | got
    return out


def _cell_rows(p: np.ndarray) -> np.ndarray:
    """``(n, 17, 17)`` uint32 of padded rows ``(n, 18, 18)``: bit ``z`` set when a corner of the cell with lower
    corner ``(x, y, z)`` has its bit."""
    a = p[:, 1:, 1:] | p[:, :-1, 1:] | p[:, 1:, :-1] | p[:, :-1, :-1]
    return a | (a >> np.uint32(1))


def sign_bounds(v: np.ndarray, bound: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(neg, pos)`` ``(n, 16, 16, 16)`` bool from :func:`exact_decode`'s ``(v, E)``: where a float decode may be
    negative, and where it may be non-negative."""
    e = np.asarray(bound, np.float64).reshape(-1, 1)
    # v - e < 0 and v + e >= 0 compared without forming them (integers: the same answers, no temporaries)
    return (v < e).reshape(-1, BLOCK, BLOCK, BLOCK), (v >= -e).reshape(-1, BLOCK, BLOCK, BLOCK)


def _relevant(neg: np.ndarray, pos: np.ndarray, truncation: tuple[float, float], jump: float) -> np.ndarray:
    """``(n, 17, 17, 17)`` bool: the cells of padded blocks whose decode may change sign (below ``jump``, any cell
    that may be negative: module lossymask)."""
    cell = _cells(neg, np.logical_or)
    return cell & _cells(pos, np.logical_or) if float(truncation[1]) >= jump else cell


def canonical_bits(coords: np.ndarray, observed: np.ndarray, neg: np.ndarray, pos: np.ndarray,
                   truncation: tuple[float, float], jump: float = JUMP) -> np.ndarray:
    """``(n, 16, 16, 16)`` bool: the bits to store (module docstring) of the coded blocks ``coords`` ``(n, 3)``
    (the whole map's, or a chunk with its coded neighbours: only blocks whose neighbours are all given are
    exact) with true mask ``observed`` ``(n, 16, 16, 16)`` and decode signs ``neg``, ``pos`` (:func:`sign_bounds`):
    1 at the corners of relevant cells that ``observed`` sees fully and at both ends of observed edges that may
    change sign; 0 elsewhere."""
    coords = np.asarray(coords, np.int64).reshape(-1, 3)
    _, neg, pos = exact_pins(coords, neg, pos, np.zeros((0, 3), np.int64), truncation, jump)
    obs = padded_blocks(coords, np.asarray(observed, bool), False)  # blocks not coded read d_max: never meshed
    meshed = _relevant(neg, pos, truncation, jump) & _cells(obs, np.logical_and)
    out = _cells(np.pad(meshed, ((0, 0), (1, 1), (1, 1), (1, 1))), np.logical_or)  # (n, 18, 18, 18)
    for ax in (1, 2, 3):
        a = tuple(slice(0, -1) if d == ax else slice(None) for d in range(4))
        b = tuple(slice(1, None) if d == ax else slice(None) for d in range(4))
        may = (neg[a] & pos[b]) | (pos[a] & neg[b]) if float(truncation[1]) >= jump else neg[a] | neg[b]
        edge = may & obs[a] & obs[b]
        out[a] |= edge
        out[b] |= edge
    return out[:, 1:-1, 1:-1, 1:-1] & np.asarray(observed, bool)


def cheapest_bits(coords: np.ndarray, bits: np.ndarray, free: np.ndarray, pinned: np.ndarray) -> np.ndarray:
    """``bits`` ``(n, 16, 16, 16)`` bool with each voxel of ``free`` (a subset of ``pinned``) set to the value
    :func:`encode_pinned`'s adaptive model finds more probable when it reaches it (ties keep ``bits``), wavefront
    by wavefront as the coder goes: the stream of the result is shorter (the model sharpens on the values it is
    given). Where every free voxel is truly observed and not in ``bits``, any choice keeps the guarantee of
    :func:`canonical_bits` (a relevant cell or edge the true mask does not observe keeps its unobserved corner
    at 0), so the writer may store either; it starts :func:`chosen_bits` from the result."""
    lay, pinned = _Layout.holding(coords, bits, pinned)
    is_free = np.zeros(lay.grid.shape, bool)
    is_free[lay.flat[np.asarray(free, bool).reshape(lay.flat.shape) & pinned]] = True
    if ans.available():  # compiled: one voxel at a time, no Python loop per wavefront (the same choices)
        from ..core import pinkernels

        pinkernels.likelier_bits(lay.grid, lay.at, np.asarray(lay.bounds, np.int64), lay.deltas, is_free, lay.N_CTX)
        return lay.blocks() == 1
    counts = np.zeros((2, lay.N_CTX), np.int64)
    for a, b in zip(lay.bounds[:-1], lay.bounds[1:]):
        sl = lay.at[a:b]
        ctx = lay.context(sl)
        f = is_free[sl]
        if f.any():
            c = counts[:, ctx[f]]
            sym = lay.grid[sl[f]]
            lay.grid[sl[f]] = np.where(c[1] > c[0], 1, np.where(c[0] > c[1], 0, sym))
        counts += _tally(lay.grid[sl].astype(np.int64), ctx)
    return lay.blocks() == 1


#: Sweeps of :func:`chosen_bits` at most (kitchen half at 64 B from cheapest_bits' choice, raw streams in B per
#: block: 1 sweep 10.95, 2 10.85, 6 10.83; each sweep costs about what cheapest_bits does).
SWEEPS = 3


def chosen_bits(coords: np.ndarray, bits: np.ndarray, pinned: np.ndarray, neg: np.ndarray, pos: np.ndarray,
                outside_coded: np.ndarray, truncation: tuple[float, float], jump: float = JUMP,
                sweeps: int = SWEEPS, start: np.ndarray | None = None) -> np.ndarray:
    """``bits`` ``(n, 16, 16, 16)`` bool (:func:`canonical_bits` of a chunk's coded blocks ``coords`` ``(n, 3)``)
    with the pinned voxels it leaves 0, truly observed or not, set to whichever value codes the chunk's ``M2``
    stream shorter, wherever a 1 cannot mesh what the true mask leaves unmeshed.

    ``pinned`` ``(n, 16, 16, 16)`` bool; ``neg``, ``pos`` ``(n, 18, 18, 18)`` bool: where the decode may be
    negative / non-negative, with each block's one-voxel layer of neighbours (:func:`exact_pins`'s padded signs
    from the neighbours' true codes). ``outside_coded`` ``(m, 3)``: the coded blocks of other chunks around them
    (every other block is not coded: it reads ``d_max``, unobserved, never meshed).

    Why the surface stays the true mask's: the canonical bits mesh exactly the relevant cells and count exactly
    the sign-changing edges the true mask does, and bits here only go 0 -> 1 from them, so it is enough that no
    relevant cell becomes all 1 and no edge that may change sign gets both ends 1 (below ``jump`` no voxel on
    such an edge is set: an unobserved end reading ``d_max`` beside a negative one is a crossing there). A
    corner in another chunk's block counts as 1 (that chunk chooses its own bits, so a cell across chunks keeps
    a 0 on each side); one in a block that is not coded as 0.

    How: iterated conditional modes. A sweep visits the free voxels in the 8 classes of ``(x, y, z) mod 2``
    (two voxels of a class share no cell, no edge and no context, so a class moves at once): each takes the
    value with the shorter code of itself and of the 6 voxels whose context it is in, under a static model
    (the counts of every context of the chunk at the sweep's start), a 1 only where the check above allows it.
    Up to ``sweeps`` sweeps, until none changes a bit, from ``start`` (same shape as ``bits``: a choice that
    meets the rule, such as :func:`cheapest_bits`'; default ``bits``). Raw streams in B per block at 64 B per
    block, canonical / cheapest_bits / from the canonical bits / from cheapest_bits': kitchen half 12.05 /
    11.72 / 10.91 / 10.83, the posed rooms of examples/peers_study.py 0.83 / 0.67 / 0.73 / 0.66."""
    lay, pinned = _Layout.holding(coords, bits, pinned)
    size = lay.grid.size
    sy, sz = lay.shape[1] * lay.shape[2], lay.shape[2]
    flat = lay.flat
    coords = np.asarray(coords, np.int64).reshape(-1, 3)
    lo = coords.min(axis=0)
    coded = np.zeros(tuple((int(x) - 2) // BLOCK + 2 for x in lay.shape), bool)  # the box's blocks grown by one
    near = np.concatenate([coords, np.asarray(outside_coded, np.int64).reshape(-1, 3)]) - lo + 1
    near = near[((near >= 0) & (near < np.asarray(coded.shape))).all(axis=1)]
    coded[tuple(near.T)] = True
    # grid voxel g lies in box block (g - 1) // 16, grown-box block (g + 15) // 16 (padding voxel 0: the block before)
    never = ~coded[np.ix_(*[(np.arange(n) + BLOCK - 1) // BLOCK for n in lay.shape])].reshape(-1)
    free = flat[pinned & ~np.asarray(bits, bool).reshape(flat.shape)]
    # relevant cells by their lower corner's grid position, edges that may change sign by their lower end
    base = flat[:, :1, :1, :1] - (sy + sz + 1)  # grid position of padded voxel (0, 0, 0) of each block
    r = np.arange(BLOCK + 2)
    pad_pos = base + (r[:, None, None] * sy + r[None, :, None] * sz + r[None, None, :])[None]  # (n, 18, 18, 18)
    rel_at = np.zeros(size, bool)
    rel_at[pad_pos[:, :-1, :-1, :-1][_relevant(neg, pos, truncation, jump)]] = True
    small = float(truncation[1]) < jump
    edges = []
    for ax, step in zip((1, 2, 3), (sy, sz, 1)):
        a = tuple(slice(0, -1) if d == ax else slice(None) for d in range(4))
        b = tuple(slice(1, None) if d == ax else slice(None) for d in range(4))
        may = neg[a] | neg[b] if small else (neg[a] & pos[b]) | (pos[a] & neg[b])
        e = np.zeros(size, bool)
        e[pad_pos[a][may]] = True
        edges.append((e, step))
    if start is not None:  # a choice that meets the rule: its bits at the free voxels
        lay.grid[free] = np.asarray(start, bool).reshape(flat.shape)[pinned & ~np.asarray(bits, bool).reshape(flat.shape)]
    check = _Check(lay.grid, never, rel_at, edges, small, (sy, sz))
    for _ in range(sweeps):
        if not _sweep(lay, free, check):
            break
    return lay.blocks() == 1


class _Check:
    """Where a voxel of the grid may read 1 (:func:`chosen_bits`): each of its relevant cells keeps another corner
    at 0, each edge at it that may change sign its other end at 0."""

    def __init__(self, grid, never, rel_at, edges, small, strides):
        self.grid, self.never, self.rel_at, self.edges, self.small = grid, never, rel_at, edges, small
        sy, sz = strides
        self.unit = [a * sy + b * sz + c for a in (0, 1) for b in (0, 1) for c in (0, 1)]

    def zero(self, w: np.ndarray) -> np.ndarray:
        return (self.grid[w] == 0) | self.never[w]

    def allows(self, u: np.ndarray) -> np.ndarray:
        ok = np.ones(len(u), bool)
        for e, st in self.edges:
            if self.small:
                ok &= ~e[u - st] & ~e[u]
            else:
                ok &= (~e[u - st] | self.zero(u - st)) & (~e[u] | self.zero(u + st))
        for lo in self.unit:
            cell = u - lo
            held = np.zeros(len(u), bool)
            for hi in self.unit:
                if hi != lo:  # the other corners
                    held |= self.zero(cell + hi)
            ok &= ~self.rel_at[cell] | held
        return ok


def _sweep(lay: "_Layout", free: np.ndarray, check: _Check) -> bool:
    """One sweep of :func:`chosen_bits` over the free voxels ``free`` (flat grid positions); True when a bit
    changed."""
    sy, sz = lay.shape[1] * lay.shape[2], lay.shape[2]
    x, rest = np.divmod(free, sy)
    y, z = np.divmod(rest, sz)
    cls = (x % 2) * 4 + (y % 2) * 2 + z % 2
    c = _tally(lay.grid[lay.at].astype(np.int64), lay.context(lay.at)) + 0.5
    p1 = c[1] / (c[0] + c[1])
    cost = np.stack([-np.log2(1 - p1), -np.log2(p1), np.zeros_like(p1)])  # bits by symbol; 2 (not pinned): none
    moved = False
    for k in range(8):
        u = free[cls == k]
        v = lay.grid[u].astype(np.int64)
        nv = 1 - v
        cu = lay.context(u)
        delta = cost[nv, cu] - cost[v, cu]
        for weight, d in zip(lay.WEIGHTS, lay.deltas):
            w = u - d  # u is w's neighbour of this weight
            sw, cw = lay.grid[w].astype(np.int64), lay.context(w)
            delta += cost[sw, cw + (nv - v) * weight] - cost[sw, cw]
        go = delta < -1e-9
        up = np.flatnonzero(go & (nv == 1))
        go[up[~check.allows(u[up])]] = False
        lay.grid[u[go]] = nv[go]
        moved |= bool(go.any())
    return moved


def _cells(a: np.ndarray, op) -> np.ndarray:
    """Reduce ``a`` ``(n, m, m, m)`` over 2 x 2 x 2 windows with ``op``: ``(n, m-1, m-1, m-1)``."""
    a = op(a[:, 1:], a[:, :-1])
    a = op(a[:, :, 1:], a[:, :, :-1])
    return op(a[:, :, :, 1:], a[:, :, :, :-1])


class _Layout:
    """The chunk's coded blocks ``coords`` ``(n, 3)`` placed in one voxel grid (their bounding box, padded by one
    voxel of "not pinned"): flat positions of the pinned voxels in decode order, the wavefront bounds, the grid
    (uint8: 0, 1, or 2 where not pinned) and the context offsets."""

    def __init__(self, coords: np.ndarray, pinned: np.ndarray):
        coords = np.asarray(coords, np.int64).reshape(-1, 3)
        pinned = np.asarray(pinned)
        if pinned.dtype == np.uint16:  # (n, 16, 16) rows of bits (pinned_rows)
            pinned = _unpack_rows(pinned)
        pinned = pinned.astype(bool).reshape(-1, BLOCK, BLOCK, BLOCK)
        if len(coords) != len(pinned):
            raise InvalidValueError(f"{len(coords)} block coordinates for {len(pinned)} blocks of pins")
        lo = coords.min(axis=0) if len(coords) else np.zeros(3, np.int64)
        span = (coords.max(axis=0) - lo + 1) * BLOCK if len(coords) else np.zeros(3, np.int64)
        self.shape = tuple(int(x) + 2 for x in span)
        self.corner = (coords - lo) * BLOCK + 1  # each block's first voxel in the padded grid
        sy, sz = self.shape[1] * self.shape[2], self.shape[2]
        self.grid = np.full(int(np.prod(self.shape)), 2, np.uint8)
        self.deltas = np.array([a * sy + b * sz + c for a, b, c in NEIGHBOURS], np.int64)
        if ans.available():  # compiled: a counting sort and one scan of the grid
            self.at, self.bounds = ans.wave_order(self.grid, self.shape, self.corner, pinned)
            return
        self.grid[self.flat[pinned]] = 0
        at = np.flatnonzero(self.grid == 0)  # C order of the grid, without a comparison sort
        x, rest = np.divmod(at, sy)
        y, z = np.divmod(rest, sz)
        wave = x + y + z
        # wavefront by wavefront, C order within one: a stable sort of small integers is numpy's radix sort
        order = np.argsort(wave.astype(np.uint16) if sum(self.shape) < 2 ** 16 else wave, kind="stable")
        self.at = at[order]
        sizes = np.bincount(wave, minlength=1)
        self.bounds = np.r_[0, np.cumsum(sizes[sizes > 0])]
        self.grid[at] = 2

    @classmethod
    def holding(cls, coords: np.ndarray, bits: np.ndarray, pinned: np.ndarray) -> tuple["_Layout", np.ndarray]:
        """The layout of ``pinned`` ``(n, 16, 16, 16)`` bool with ``bits`` (same shape) placed in its grid at the
        pinned voxels, and ``pinned`` as bool in the shape of :attr:`flat`."""
        lay = cls(coords, pinned)
        flat = lay.flat
        pinned = np.asarray(pinned, bool).reshape(flat.shape)
        lay.grid[flat[pinned]] = np.asarray(bits, bool).reshape(flat.shape)[pinned]
        return lay, pinned

    @property
    def flat(self) -> np.ndarray:
        """``(n, 16, 16, 16)`` int64: the flat position of every voxel of the blocks in the grid."""
        sy, sz = self.shape[1] * self.shape[2], self.shape[2]
        i, j, k = (np.arange(BLOCK)[:, None, None], np.arange(BLOCK)[None, :, None], np.arange(BLOCK)[None, None, :])
        first = self.corner @ np.array([sy, sz, 1])
        return first[:, None, None, None] + (i * sy + j * sz + k)[None]

    def blocks(self) -> np.ndarray:
        """``(n, 16, 16, 16)`` uint8: the grid's values over the blocks (gathered through a window view of the
        grid, without the flat positions)."""
        win = np.lib.stride_tricks.sliding_window_view(self.grid.reshape(self.shape), (BLOCK,) * 3)
        return win[tuple(self.corner.T)]

    #: Each neighbour's weight in the context number (the first neighbour most significant), as ans takes them.
    WEIGHTS = 3 ** np.arange(len(NEIGHBOURS), dtype=np.int64)[::-1]
    N_CTX = 3 ** len(NEIGHBOURS)

    def context(self, at: np.ndarray) -> np.ndarray:
        ctx = np.zeros(len(at), np.int64)
        for d in self.deltas:
            ctx *= 3
            ctx += self.grid[at + d]
        return ctx


def _stream():
    import constriction  # a core dependency, imported on first use

    return constriction.stream


def encode_pinned(coords: np.ndarray, bits: np.ndarray, pinned: np.ndarray) -> bytes:
    """The ``M2`` stream of ``bits`` ``(n, 16, 16, 16)`` bool at the voxels ``pinned`` (same shape) of a chunk's
    coded blocks ``coords`` ``(n, 3)`` (bits elsewhere are not stored)."""
    lay, _ = _Layout.holding(coords, bits, pinned)
    head = _MAGIC + np.uint32(len(lay.at)).astype("<u4").tobytes()
    if ans.available():  # the compiled encoder: constriction's words, without a Python loop per wavefront
        words = ans.encode_bits(lay.grid, lay.at, lay.bounds, lay.deltas, lay.WEIGHTS, lay.N_CTX)
        return head + np.asarray(words, "<u4").tobytes()
    st = _stream()
    bern, coder = st.model.Bernoulli(perfect=False), st.stack.AnsCoder()
    counts = np.zeros((2, 3 ** len(NEIGHBOURS)), np.int64)
    parts = []
    for a, b in zip(lay.bounds[:-1], lay.bounds[1:]):
        sl = lay.at[a:b]
        ctx, sym = lay.context(sl), lay.grid[sl].astype(np.int64)
        parts.append((sym.astype(np.int32), _p1(counts, ctx)))
        counts += _tally(sym, ctx)
    for sym, p in reversed(parts):
        coder.encode_reverse(sym, bern, p)
    return head + np.asarray(coder.get_compressed(), dtype="<u4").tobytes()


def _tally(sym: np.ndarray, ctx: np.ndarray) -> np.ndarray:
    """``(2, 3^6)`` counts of symbols ``sym`` in contexts ``ctx``."""
    n = 3 ** len(NEIGHBOURS)
    return np.bincount(sym * n + ctx, minlength=2 * n).reshape(2, n)


def _p1(counts: np.ndarray, ctx: np.ndarray) -> np.ndarray:
    c = counts[:, ctx] + 0.5  # exact in float64: integer counts plus a half
    return c[1] / (c[0] + c[1])


def decode_pinned(stream: bytes | np.ndarray, coords: np.ndarray, pinned: np.ndarray,
                  where: str = "a pinned mask chunk") -> np.ndarray:
    """Inverse of :func:`encode_pinned`: ``(n, 16, 16, 16)`` bool, the stored bits at ``pinned`` and 1 (observed)
    elsewhere.

    Raises:
        ChecksumError: the stream is not one :func:`encode_pinned` wrote for these pinned voxels, named by
            ``where``.
    """
    return _decoded(stream, coords, pinned, where).blocks() != 0  # pinned: the bit read; elsewhere 2, observed


def unobserved_voxels(stream: bytes | np.ndarray, coords: np.ndarray, pinned: np.ndarray,
                      where: str = "a pinned mask chunk", *, threads: int = 1) -> np.ndarray:
    """What :func:`decode_pinned` reads as 0, as ``(m,)`` int64 ``b * 4096 + voxel`` (block ``b`` of ``coords``,
    the voxel's C-order index in it; ascending within a block is not promised): without the ``(n, 4096)`` mask,
    for a reader that sets those voxels of its decode to free space. ``pinned``: ``(n, 16, 16, 16)`` bool, or
    rows ``(n, 16, 16)`` uint16 (:func:`pinned_rows`; compiled, the order of the decode laid out on up to
    ``threads`` threads, the decode itself on one: each bit's context is its decoded neighbours).

    Raises:
        ChecksumError: as :func:`decode_pinned`.
    """
    pinned = np.asarray(pinned)
    if ans.available() and pinned.dtype == np.uint16:
        return _plane_zeros(stream, coords, pinned, where, threads=threads)
    return np.flatnonzero(_decoded(stream, coords, pinned, where).blocks().reshape(-1) == 0)


#: NEIGHBOURS as (wavefront step, di, dj): what the compiled decoder of wavefront planes reads.
_PLANE_NEIGHBOURS = np.array([(a + b + c, a, b) for a, b, c in NEIGHBOURS], np.int64)


def _plane_zeros(stream: bytes | np.ndarray, coords: np.ndarray, rows: np.ndarray, where: str, *,
                 threads: int = 1) -> np.ndarray:
    """:func:`unobserved_voxels` of pins as rows, compiled, without a grid of the chunk's voxels: the bits
    decoded wavefront plane by plane (:func:`sdfcodec.core.ans.decode_planes`), the same words read alike."""
    buf = _checked(stream, where)
    coords = np.asarray(coords, np.int64).reshape(-1, 3)
    lo = coords.min(axis=0) if len(coords) else np.zeros(3, np.int64)
    shape = tuple(int(x) + 2 for x in ((coords.max(axis=0) - lo + 1) * BLOCK if len(coords) else np.zeros(3)))
    corner = (coords - lo) * BLOCK + 1
    order = ans.wave_order_planes(shape, corner, rows, threads, lambda job, runs: each_chunk(job, runs, threads))
    _check_count(buf, len(order[0]), where)
    if not len(order[0]):
        return np.zeros(0, np.int64)
    try:
        coder = ans.Decoder(np.ascontiguousarray(buf[6:].view("<u4"), dtype=np.uint32))
        zeros = ans.decode_planes(coder, shape, order, _PLANE_NEIGHBOURS, _Layout.WEIGHTS, _Layout.N_CTX)
    except ValueError as e:  # a last word of 0, as constriction refuses it
        raise ChecksumError(f"{where} is not a sound M2 stream (ValueError: {e})") from e
    if not coder.is_empty():
        raise ChecksumError(f"{where} has words left after its {len(order[0])} pinned voxels; it is corrupted")
    return zeros


def _checked(stream: bytes | np.ndarray, where: str) -> np.ndarray:
    buf = np.frombuffer(bytes(stream), dtype=np.uint8)
    if len(buf) < 6 or bytes(buf[:2]) != _MAGIC or (len(buf) - 6) % 4:
        raise ChecksumError(f"{where} is not an M2 stream (bad header or length {len(buf)})")
    return buf


def _check_count(buf: np.ndarray, pins: int, where: str) -> None:
    count = int(buf[2:6].view("<u4")[0])
    if count != pins:
        raise ChecksumError(f"{where} codes {count} pinned voxels, its blocks' decode pins {pins}; the codes "
                            "or the mask are corrupted")


def _decoded(stream: bytes | np.ndarray, coords: np.ndarray, pinned: np.ndarray, where: str) -> _Layout:
    """The layout of :func:`decode_pinned` with the stream's bits decoded into its grid."""
    buf = _checked(stream, where)
    lay = _Layout(coords, pinned)
    _check_count(buf, len(lay.at), where)
    count = len(lay.at)
    if len(lay.at):
        words = np.ascontiguousarray(buf[6:].view("<u4"), dtype=np.uint32)
        if ans.available():  # compiled, the same words read as constriction reads them (tests/test_pinned_mask.py)
            try:
                coder = ans.Decoder(words)
                coder.bits(lay.grid, lay.at, lay.bounds, lay.deltas, lay.WEIGHTS, lay.N_CTX)
            except ValueError as e:  # a last word of 0, as constriction refuses it
                raise ChecksumError(f"{where} is not a sound M2 stream (ValueError: {e})") from e
        else:
            coder = _constriction_decode(words, lay, where)
        if not coder.is_empty():
            raise ChecksumError(f"{where} has words left after its {count} pinned voxels; it is corrupted")
    return lay


def _constriction_decode(words: np.ndarray, lay: _Layout, where: str):
    """The fallback of :func:`decode_pinned` without numba: the bits into ``lay.grid``; returns the coder."""
    st = _stream()
    try:
        coder = st.stack.AnsCoder(words) if len(words) else st.stack.AnsCoder()
        bern = st.model.Bernoulli(perfect=False)
        counts = np.zeros((2, lay.N_CTX), np.int64)
        for a, b in zip(lay.bounds[:-1], lay.bounds[1:]):
            sl = lay.at[a:b]
            ctx = lay.context(sl)
            sym = np.asarray(coder.decode(bern, _p1(counts, ctx)), np.int64)
            lay.grid[sl] = sym
            counts += _tally(sym, ctx)
    except Exception as e:  # noqa: BLE001 - constriction raises on an exhausted or inconsistent stream
        raise ChecksumError(f"{where} is not a sound M2 stream ({type(e).__name__}: {e})") from e
    return coder
