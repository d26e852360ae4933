"""``--target-error E``: the surface error of variable-rate codes on a sample of a map's blocks, and the coarsest
step that keeps it within a target (the variable-rate writer's rate control by error,
:class:`~sdfcodec.map.varrate.VariableRateWriter`).

The surface error is measured where the surface is placed: at the observed voxels that touch a crossing of the
input's zero level, inside their block or across a block's face (:func:`~sdfcodec.map.residual.crossing_voxels`),
each voxel's decode (refined, where the map carries a surface refinement, spec section 6h) against its input value.
Faces count because blocks decode worst at their edges: measured inside blocks only, a synthetic room's 50 mm map
met its target (49.7 mm) and missed it with the faces (56.8 mm). The target holds for :data:`ERROR_QUANTILE` of
them. Why a quantile and not the largest: on real fused maps a few crossing voxels lie on surfaces thinner than
the codes can hold, which every lossy code here erases. Measured on the kitchen half (frames of a real RGB-D
kitchen fused at 2 cm, 196 coded blocks, 36,988 crossing voxels), the largest error is 134-140 mm for the
fixed-length pca-64 map and for variable-rate maps from 64 to 512 B per coded block, while 99 % lie within 77.6 /
59.4 / 23.4 / 0.8 mm at 64 / 128 / 256 / 512 B: a bound on the largest refused every target below 134.75 mm. A
bound on every voxel is the residual stage's (``--max-error``, fixed-rate maps).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Callable

import numpy as np

from ..core import refine as cr
from ..core._lazy import lazy_module
from ..core._validate import BLOCK
from ..errors import InvalidValueError

if TYPE_CHECKING:
    from ..codec import Codec
    from .refine import TrueValues

torch = lazy_module("torch")

__all__ = ["ERROR_QUANTILE", "CONFIDENCE_Z", "REFINE_FACTORS", "REFINE_RANGE", "REFINE_TRIES", "CODE_HALVINGS",
           "LOG2_CODE_STEPS", "surface_error", "coarsest_step", "ErrorSample", "refine_steps", "unreachable"]

#: The share of a sample's crossing voxels whose decode a target error bounds.
ERROR_QUANTILE = 0.99
#: Where the sample holds some of a map's blocks, the share beyond the target is estimated with this many standard
#: errors to spare (one-sided 95 % were it normal; 91 % of 200 samples held on a population whose errors cluster by
#: block, tests/test_variable_rate.py): the map, not the sample, is what must hold it. Without: the two random rooms
#: (2,345 blocks, 2,048 sampled) measured 5.24 mm at a 5 mm target.
CONFIDENCE_Z = 1.645
#: Refinement steps tried for a target error ``E``, as multiples of ``E`` (a corrected voxel lies within half a
#: step of its input), coarsest first, a quarter octave apart. Finer steps than the target needs are tried too: a
#: finer step refines a wider band around the decoded surface (:func:`~sdfcodec.map.refine.tau_for_step`), which
#: reaches the crossing voxels coarser codes decode far off. The band widens in steps as fine as that: on the
#: kitchen half a 10 mm target took 450.5 B per coded block with steps an octave apart (refinement 1.87 mm), 386.1 B
#: half an octave apart (2.65 mm), 336.9 B a quarter apart (3.15 mm), the crossings inside blocks measured.
REFINE_FACTORS = tuple(1.5 * 2.0 ** (-k / 4) for k in range(21))
#: The refinement steps whose maps are measured: the coarsest that meets the target on the sample and the next
#: finer ones that do, this many in all (finer steps cost more bytes of corrections, unless the coarsest needs much
#: finer codes).
REFINE_TRIES = 3
#: The refinement steps rate control tries, metres (a byte target's bisection, an error target's ladder).
REFINE_RANGE = (2e-4, 5e-2)
#: Beside each refinement step, the codes' steps tried: the coarsest that reaches the target and this many
#: halvings of it (the error only falls with them; the bytes the map measures decide).
CODE_HALVINGS = 3
#: log2 of the codes' steps rate control searches, a byte target and an error target alike: 1e-3 .. 16
#: normalised units.
LOG2_CODE_STEPS = (-10.0, 4.0)


def refine_steps(target: float) -> list[float]:
    """The refinement steps (metres) tried for a target error: :data:`REFINE_FACTORS` times it, within
    :data:`REFINE_RANGE`; for a target below every one of them, the finest step of the range (which may still meet
    it: a corrected voxel lies within half a step; else the refusal names the error it reaches)."""
    steps = [f * target for f in REFINE_FACTORS if REFINE_RANGE[0] <= f * target <= REFINE_RANGE[1]]
    return steps or ([REFINE_RANGE[0]] if max(REFINE_FACTORS) * target < REFINE_RANGE[0] else [])


def unreachable(target: float, reached: float, refined: bool) -> InvalidValueError:
    """The refusal of an error ``target`` (metres) that the codes at their finest step (beside a surface refinement:
    ``refined``) miss, reaching ``reached``: what to do instead."""
    return InvalidValueError(
        f"a target error of {target * 1000:g} mm is below what this codec reaches on this map: {reached * 1000:.2f} "
        f"mm at its finest step{' with a surface refinement' if refined else ''} ({ERROR_QUANTILE:.0%} of the voxels "
        "that place the surface, on a sample); use --max-error (a residual stage) for a bound on every voxel")


def _apart(n: int) -> np.ndarray:
    """``(n, 3)`` block indices no two of which are neighbours: crossings inside each block only."""
    return np.arange(n)[:, None] * np.array([[3, 0, 0]])


def _crossings(coords: np.ndarray, v: np.ndarray, observed: np.ndarray | None, truncation: tuple[float, float],
               face_weight: float = 1.0) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """``(input metres (n, 4096) float64, its crossing voxels (n, 4096) bool, their weights or None: all 1)`` of
    normalised ``v``, blocks ``coords`` ``(n, 3)``: crossings inside a block and across the face of two of these
    blocks. A voxel whose only crossings lie across faces weighs ``face_weight``: for a uniform sample of blocks,
    how many of its neighbours the sample lacks for each it holds (a face's two blocks are both in a sample of k of
    N blocks with odds (k - 1) / (N - 1) once one is)."""
    from .residual import crossing_voxels

    d_min, d_max = truncation
    x = (v * (d_max - d_min) + d_min).reshape(len(v), -1).astype(np.float64)
    cross = crossing_voxels(coords, x.reshape(v.shape), observed).reshape(len(v), -1)
    if face_weight == 1.0:
        return x, cross, None
    inside = crossing_voxels(_apart(len(v)), x.reshape(v.shape), observed).reshape(len(v), -1)[cross]
    return x, cross, np.where(inside, 1.0, face_weight)


def _face_crossings(truth: TrueValues, coords: np.ndarray, x: np.ndarray, observed: np.ndarray | None
                    ) -> np.ndarray:
    """``(n, 4096)`` bool: the voxels of blocks ``coords`` ``(n, 3)`` (input metres ``x`` ``(n, 4096)``, mask
    ``observed`` ``(n, 16, 16, 16)`` or None) touching a crossing across a face with a neighbour ``truth`` (a
    :class:`~sdfcodec.map.refine.TrueValues` of every block the writer saw) holds: its facing layer read there."""
    from ..core.surface import crossing_edges

    n = len(coords)
    own_v = x.reshape(n, BLOCK, BLOCK, BLOCK)
    own_o = np.ones(own_v.shape, bool) if observed is None else np.asarray(observed, bool).reshape(own_v.shape)
    out = np.zeros(own_v.shape, bool)
    for ax in range(3):
        for side in (-1, 1):
            rows = truth.rows_of(coords + side * np.eye(3, dtype=np.int64)[ax], partial=True)
            i = np.flatnonzero(rows >= 0)
            if not len(i):
                continue
            mine, theirs = (BLOCK - 1, 0) if side > 0 else (0, BLOCK - 1)  # the two layers facing each other
            nb = np.take(np.asarray(truth.values[rows[i]]).reshape(-1, BLOCK, BLOCK, BLOCK), theirs, axis=ax + 1)
            nb_o = (np.ones(nb.shape, bool) if truth.observed is None else np.take(np.unpackbits(
                np.asarray(truth.observed[rows[i]]), axis=1).reshape(-1, BLOCK, BLOCK, BLOCK).astype(bool),
                theirs, axis=ax + 1))
            own = np.take(own_v[i], mine, axis=ax + 1)
            e = crossing_edges(own, nb) & np.take(own_o[i], mine, axis=ax + 1) & nb_o
            view = np.moveaxis(out, ax + 1, 1)  # (n, layer along ax, ...): the layer facing the neighbour
            view[i, mine] |= e
    return out.reshape(n, -1)


def surface_error(codec: Codec, v: np.ndarray, observed: np.ndarray | None, codes: np.ndarray,
                  truncation: tuple[float, float], refinement: tuple[float, float] | None = None,
                  quantile: float = ERROR_QUANTILE, crossings: tuple | None = None,
                  coords: np.ndarray | None = None, sampled: tuple[int, int] | None = None) -> float:
    """The surface error (metres) of decoding ``codes`` ``(n, D)`` against normalised blocks ``v``
    ``(n, 16, 16, 16)`` at block indices ``coords`` ``(n, 3)`` (None: no two of them neighbours): the ``quantile`` of
    ``|decoded - input|`` over the observed voxels that touch a surface crossing of the input, inside their block
    or across the face of two of these blocks (``observed`` ``(n, 16, 16, 16)`` bool, None: all). With
    ``refinement`` ``(step, band)`` metres, the decode is refined first as a map's surface refinement refines it
    (:mod:`sdfcodec.core.refine`, here in float metres rather than the reader's exact units: the rate control's
    estimate). 0 when there are no such voxels. ``crossings``: ``_crossings`` of these blocks (its weights make
    the quantile a weighted one), where the caller keeps them. ``sampled`` ``(k, N)``: these blocks are a uniform
    sample of k of a map's N; where ``k < N`` the error is the one the map's share of voxels beyond it stays under
    ``1 - quantile`` for, :data:`CONFIDENCE_Z` standard errors included (:func:`_bounded_quantile`)."""
    d_min, d_max = truncation
    n = len(v)
    if crossings is None:
        crossings = _crossings(_apart(n) if coords is None else coords, v, observed, truncation)
    x, cross, weights = crossings
    if not cross.any():
        return 0.0
    dec = codec.decode(torch.from_numpy(np.asarray(codes, np.float32))).numpy().reshape(n, -1)
    dec = cr.clip_units(dec.astype(np.float64) * (d_max - d_min) + d_min, truncation, 1.0)
    if refinement is not None:
        step, band = refinement
        sel = cr.select(dec, band)
        obs = None if observed is None else np.asarray(observed, bool).reshape(n, -1)
        dec = cr.refine(dec, sel, cr.corrections(x, obs, dec, sel, step), step, truncation, 1.0)
    err = np.abs(dec - x)[cross]
    if sampled is not None and sampled[0] < sampled[1]:
        return _bounded_quantile(err, np.nonzero(cross)[0], n, weights, quantile, *sampled)
    if weights is None:
        return float(np.quantile(err, quantile))
    return float(np.quantile(err, quantile, weights=weights, method="inverted_cdf"))


def _bounded_quantile(err: np.ndarray, block: np.ndarray, n: int, weights: np.ndarray | None, quantile: float,
                      k: int, total: int) -> float:
    """The smallest error ``t`` whose share of exceedances over the map is within ``1 - quantile`` with
    :data:`CONFIDENCE_Z` standard errors to spare, estimated from the ``n`` sampled blocks (``k`` of ``total``
    blocks, drawn uniformly): ``err`` the errors of their crossing voxels, ``block`` each one's block (0..n-1),
    ``weights`` theirs (or None). The share is a ratio estimate over blocks (exceeding weight / crossing weight),
    its variance the sampled blocks' (a block's voxels are not independent draws: its code sets them all) with the
    finite population correction ``1 - k / total``."""
    w = np.ones(len(err)) if weights is None else weights
    per_block = np.bincount(block, w, minlength=n)
    order = np.argsort(err)
    err, block, w = err[order], block[order], w[order]
    scale = np.sqrt((1.0 - k / total) / k) / per_block.mean()

    def excess(i: int) -> float:  # the bound on the share above err[i] (the voxels after it in the order)
        above = np.bincount(block[i + 1:], w[i + 1:], minlength=n)
        share = above.sum() / per_block.sum()
        return share + CONFIDENCE_Z * scale * float(np.std(above - share * per_block, ddof=1))

    # below the plain quantile the share above alone exceeds 1 - quantile: the search starts there, in the tail
    lo = max(int(np.searchsorted(np.cumsum(w) / w.sum(), quantile)) - 1, 0)
    hi = len(err) - 1  # the last voxel has nothing above it: always within
    while lo < hi:  # the bound falls as t rises (fewer voxels above it)
        mid = (lo + hi) // 2
        if excess(mid) <= 1.0 - quantile:
            hi = mid
        else:
            lo = mid + 1
    return float(err[lo])


def coarsest_step(error: Callable[[float], float], target: float) -> tuple[float | None, float]:
    """``(step, error there)``: the coarsest step (the smallest codes) whose ``error(step)`` stays within
    ``target``, bisection on log2(step), or ``(None, error at the finest step)`` when even that misses."""
    lo, hi = LOG2_CODE_STEPS
    floor = error(2 ** lo)
    if floor > target:
        return None, floor
    top = error(2 ** hi)
    if top <= target:
        return 2 ** hi, top
    got = floor
    for _ in range(16):
        mid = (lo + hi) / 2
        e = error(2 ** mid)
        if e <= target:
            lo, got = mid, e
        else:
            hi = mid
    return 2 ** lo, got


class ErrorSample:
    """A uniform sample of up to ``size`` of the blocks a writer encodes (a reservoir: the blocks of the ``size``
    smallest random priorities, ``seed``), kept to measure the surface error of their codes at a step.

    :meth:`add` blocks as they are encoded: their indices ``coords`` ``(n, 3)``, normalised ``v`` ``(n, 16, 16,
    16)``, ``observed`` (same shape, or None), float ``codes`` ``(n, D)`` and the gains ``(n, D)`` the step's prefix
    lengths are chosen by; :meth:`coarsest_step` the coarsest step that keeps their :func:`surface_error` within a
    target. The crossings across a kept block's faces read the neighbour's input from ``truth`` (:meth:`add`) where
    the writer keeps one (:func:`_face_crossings`); else only those between two kept blocks count, the voxels whose
    only crossings lie across faces weighing as many as the sample lacks of them (:func:`_crossings`; 1 where every
    block is kept). On a map larger than the sample the error is bounded with :data:`CONFIDENCE_Z` to spare."""

    def __init__(self, codec: Codec, size: int, seed: int = 0):
        self.codec, self.size = codec, int(size)
        self._rng = np.random.default_rng(seed)
        self._kept: list[tuple] = []  # (priority, coords, v, observed, codes, gains) per kept block
        self._seen = 0  # blocks added
        self._truth: TrueValues | None = None  # every block's input, where the writer keeps it: the faces' other side
        self._arrays: tuple | None = None  # (truncation, the kept blocks' arrays and crossings): coarsest_step

    def add(self, coords: np.ndarray, v: np.ndarray, observed: np.ndarray | None, codes: np.ndarray,
            gains: np.ndarray, truth: TrueValues | None = None) -> None:
        """Blocks ``coords`` ``(n, 3)`` as above; ``truth``: a :class:`~sdfcodec.map.refine.TrueValues` the writer
        keeps every block's input in (these included), where the neighbours across a kept block's faces are read."""
        self._truth = truth
        pr = self._rng.random(len(v))
        for i in np.argsort(pr)[:self.size]:
            self._kept.append((pr[i], np.asarray(coords[i], np.int64), v[i], None if observed is None else observed[i],
                               codes[i], gains[i]))
        self._kept.sort(key=lambda t: t[0])
        del self._kept[self.size:]
        self._seen += len(v)
        self._arrays = None

    def coarsest_step(self, target: float, truncation: tuple[float, float],
                      quantised: Callable[[np.ndarray, np.ndarray, float], np.ndarray],
                      refinement: tuple[float, float] | None = None) -> tuple[float | None, float]:
        """:func:`coarsest_step` of the sample's :func:`surface_error` (with ``refinement``, ``(step, band)``
        metres, or None), its codes at step ``s`` being ``quantised(codes, gains, s)`` (``(n, D)``, dequantised)."""
        if self._arrays is None or self._arrays[0] != truncation:  # stacked once for every step tried
            c, v = np.stack([t[1] for t in self._kept]), np.stack([t[2] for t in self._kept])
            obs = None if self._kept[0][3] is None else np.stack([t[3] for t in self._kept])
            z, g = (np.stack([t[i] for t in self._kept]).astype(np.float64) for i in (4, 5))
            k, truth = len(self._kept), self._truth
            if truth is not None and truth.n:  # every face of every kept block, its neighbour read from the input
                x, cross, _ = _crossings(_apart(k), v, obs, truncation)  # inside blocks; the faces from the copy
                cross = (cross | _face_crossings(truth, c, x, obs), None)
            else:  # the faces between kept blocks, each weighing what the sample lacks
                face = 1.0 if k >= self._seen or k < 2 else (self._seen - 1) / (k - 1)
                x, *cross = _crossings(c, v, obs, truncation, face)
            self._arrays = (truncation, v, obs, z, g, (x, *cross))
        _, v, obs, z, g, cross = self._arrays
        sampled = (len(self._kept), self._seen)
        return coarsest_step(lambda s: surface_error(self.codec, v, obs, quantised(z, g, s), truncation, refinement,
                                                     crossings=cross, sampled=sampled), target)
