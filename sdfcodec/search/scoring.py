"""The scoring kernel of a search: :class:`Scorer` (the minimum squared distance of codes to a query's
descriptors, with a bound that lets it skip the codes whose first elements are already too far) and
:class:`ObservedScorer` (partly observed blocks, compared where they were observed). See :mod:`sdfcodec.search`
for the conventions and units.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from ..codec import Codec
from ..core._lazy import lazy_module
from ..core.tiling import run_tiles
from .arrays import decode_array

if TYPE_CHECKING:
    from ..map.facade import Map

torch = lazy_module("torch")  # for scoring on a GPU only: a search on the CPU never imports it

__all__ = ["MIN_OBSERVED_SURFACE", "ObservedScorer", "PRUNE_PREFIX", "Scorer", "score_codes", "scored_voxels"]


#: :class:`Scorer`'s bounded call (a search's) compares the first this many code elements first: the distance over
#: a prefix is a lower bound of the whole distance, so a code whose prefix is already farther than the bound is not
#: scored in full. Descriptors of ``2 * PRUNE_PREFIX`` elements or more only. 8, not 16: in the streaming search
#: the products' cost follows their depth (pca-64, 65,536 codes against 15 floor descriptors on 2 cores: the search
#: ran at 0.93-0.94 of reading the codes with 8, 0.89 with 16, 0.82 with no pruning), and a code far from a shape
#: is far in its first components already.
PRUNE_PREFIX = 8
#: The rounding margin of that lower bound, relative to ``bound + max |q|^2``: float32 sums of 8-64 products err by
#: a few 1e-6 of ``|c|^2 + |q|^2``, and a code within the bound has ``|c|^2 <= 2 |q|^2 + 2 bound``; so no code
#: whose full score is within the bound is ever dropped.
PRUNE_MARGIN = 1e-4
#: Pruning costs a pass more where most codes are near the shape (a floor search's loose first stage over a
#: room's surface blocks kept 4-86 % of them in synthetic rooms): the first ``PRUNE_PROBE`` codes of a batch are
#: tried first, and when more than ``PRUNE_MAX_SHARE`` of them survive the prefix, the batch is scored in full.
PRUNE_PROBE = 1024
PRUNE_MAX_SHARE = 0.5


def _min_products(c: np.ndarray, qt: np.ndarray, qq: np.ndarray, rows: int | None) -> np.ndarray:
    """``min_m (qq_m + c . qt[:, m])`` ``(n,)`` and the products ``(M, n)``, in products of ``rows`` codes (None:
    :data:`_LARGE_MODEL_ROWS` at a time on every core)."""
    gt = np.empty((qt.shape[1], len(c)), np.float32)

    def work(a: int, b: int) -> None:
        # written transposed, (M, n): the minimum over the descriptors is then M - 1 elementwise minima along
        # contiguous rows, where numpy's argmin along 15 columns and the gather of its values cost half as much as
        # the products themselves
        np.matmul(c[a:b], qt, out=gt[:, a:b].T)

    if rows is None:  # a large model: row tiles on every core, one BLAS thread each
        run_tiles(len(c), work, rows=_LARGE_MODEL_ROWS)
    else:
        for a in range(0, len(c), rows):
            work(a, a + rows)
    gt += qq[:, None]
    return np.minimum.reduce(gt, axis=0), gt


def _single_thread_rows(m: int, l: int) -> int | None:
    # codes per product on the CPU: OpenBLAS runs a product of 2^18 multiply-adds or more on every core, and a
    # skinny one (a few descriptors) then waits on threads busy elsewhere (the reader's decoders, other
    # processes): 4-8 ms for 16,384 codes against 15 descriptors on a loaded 2-core machine, 0.4 ms in
    # 256-code products (one core each, cache-sized). Large models (None): row tiles on every core.
    tile = ((1 << 18) - 1) // max(1, m * l)
    return tile if tile >= 128 else None


class Scorer:
    """Minimum squared distance of codes to descriptors: ``min_m |c|^2 - 2 c.q_m + |q_m|^2``, one matrix
    product per batch. numpy's BLAS on the CPU, torch on other devices.

    ``descriptors``: ``(M, L)`` float32 (cast), the query's first ``L`` elements; ``device``: where to score
    (``"cpu"`` or a :class:`torch.device`).
    The kernel of :func:`search`, and what ``sdfcodec.bench.bench_search`` times."""

    def __init__(self, descriptors: np.ndarray, device: Any):
        q = np.ascontiguousarray(descriptors, dtype=np.float32)
        self.device = device
        self.qq = np.einsum("ij,ij->i", q, q)
        self.qt = np.ascontiguousarray(-2.0 * q.T)  # (L, M): the -2 folded into the product
        self.rows = _single_thread_rows(*q.shape)
        self.prefix = PRUNE_PREFIX if q.shape[1] >= 2 * PRUNE_PREFIX else None
        if self.prefix is not None:
            self.qq_prefix = np.einsum("ij,ij->i", q[:, :self.prefix], q[:, :self.prefix])
            self.qt_prefix = np.ascontiguousarray(self.qt[:self.prefix])
            self.rows_prefix = _single_thread_rows(q.shape[0], self.prefix)
            self.margin = PRUNE_MARGIN * float(self.qq.max(initial=0.0))
        self.on_cpu = str(device).split(":")[0] == "cpu"
        if not self.on_cpu:
            self.tqt = torch.from_numpy(self.qt).to(device)
            self.tqq = torch.from_numpy(self.qq).to(device)

    def __call__(self, codes: Any, bound: float | None = None) -> tuple[np.ndarray, np.ndarray]:
        """``(n, L)`` float32 codes -> scores ``(n,)`` float32 and nearest index ``(n,)`` int64 (numpy).

        With ``bound`` (a search's call, on the CPU), only the codes scoring ``<= bound`` are scored in full:
        their scores are those of the unbounded call (to float32 rounding) and their nearest index is given; the
        others get a lower bound of their score (to float32 rounding) that is ``> bound``: the distance over the
        first :data:`PRUNE_PREFIX` elements, for descriptors of twice as many elements or more; and index -1."""
        if self.on_cpu:
            c = np.asarray(codes, dtype=np.float32)
            if bound is not None:
                return self._bounded(c, bound)
            s, gt = self._whole(c)
            return s, gt.argmin(axis=0)
        c = (codes if isinstance(codes, torch.Tensor) else torch.from_numpy(np.asarray(codes))).to(self.device)
        g = torch.addmm(self.tqq, c, self.tqt)
        s, idx = g.min(dim=1)
        s = (s + (c * c).sum(dim=1)).clamp_(min=0.0)
        return s.cpu().numpy(), idx.cpu().numpy()

    def _whole(self, c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Whole scores ``(n,)`` of codes ``c`` on the CPU and the products plus ``|q|^2``, ``(M, n)``."""
        s, gt = _min_products(c, self.qt, self.qq, self.rows)
        s += np.einsum("ij,ij->i", c, c)
        np.maximum(s, 0.0, out=s)  # rounding can take an exact match a hair below zero
        return s, gt

    def _bounded_full(self, c: np.ndarray, bound: float) -> tuple[np.ndarray, np.ndarray]:
        s, gt = self._whole(c)
        idx = np.full(len(c), -1, np.int64)
        near = np.flatnonzero(s <= bound)
        if len(near):  # a search needs the nearest index only of the few codes it selects
            idx[near] = gt[:, near].argmin(axis=0)
        return s, idx

    def _prefix_bound(self, c: np.ndarray) -> np.ndarray:
        """The squared distance over the first :data:`PRUNE_PREFIX` elements ``(n,)``: a lower bound of the score."""
        head = c[:, :self.prefix]
        s, _ = _min_products(head, self.qt_prefix, self.qq_prefix, self.rows_prefix)
        s += np.einsum("ij,ij->i", head, head)
        return s

    def _bounded(self, c: np.ndarray, bound: float) -> tuple[np.ndarray, np.ndarray]:
        if self.prefix is None:
            return self._bounded_full(c, bound)
        idx = np.full(len(c), -1, np.int64)
        cut = bound + PRUNE_MARGIN * bound + self.margin  # the codes whose prefix is farther: score > bound
        probe = self._prefix_bound(c[:PRUNE_PROBE])
        if np.count_nonzero(probe <= cut) > PRUNE_MAX_SHARE * len(probe):
            return self._bounded_full(c, bound)
        s = np.concatenate([probe, self._prefix_bound(c[PRUNE_PROBE:])]) if len(c) > PRUNE_PROBE else probe
        cand = np.flatnonzero(s <= cut)
        if len(cand):
            full, near_idx = self(c[cand])
            s[cand] = full
            inside = full <= bound
            idx[cand[inside]] = near_idx[inside]
        return s, idx


#: Partly observed blocks with fewer observed voxels near a surface than this (a 4 x 4 patch) keep their code
#: score: no surface of theirs was seen to compare with a shape.
MIN_OBSERVED_SURFACE = 16
#: Codes per product of a large model's scores (:func:`_min_products`; 256 x 64 x 2,856 for the wall model).
_LARGE_MODEL_ROWS = 256
#: Blocks per product of :class:`ObservedScorer` (a tile of the wall's 2,856 descriptors: 1.4 MiB of scores).
_OBSERVED_ROWS = 128


class ObservedScorer:
    """Scores of partly observed blocks (maps with an observation mask), compared where they were observed.

    A masked map encodes a block by weighted least squares with weight 0 on its unobserved voxels, so what its
    code decodes to there is an extrapolation, and two codes of the same observed surface can be far apart.
    For such blocks the score is ``min_m 4096 / n_obs * sum_j o_j (x_j - q_mj)^2``: the squared distance
    between the block's reconstruction ``x`` and each descriptor's reconstruction ``q_m`` (both truncated to the
    normalised ``[0, 1]``, as a reader truncates) over the block's
    ``n_obs`` observed voxels ``o``, scaled to a whole block (so it is on the scale of code scores: for a fully
    observed block of an orthonormal codec such as pca it equals the code score). Two matrix products per batch
    after decoding the partial blocks. Blocks with fewer than :data:`MIN_OBSERVED_SURFACE` observed voxels near
    a surface keep their code score."""

    def __init__(self, descriptors: np.ndarray, codec: Codec, truncation: tuple[float, float], voxel_size: float):
        from ..map.observed import SURFACE_BAND_VOXELS

        self.codec = codec
        q = self._decode(np.asarray(descriptors, np.float32))
        # transposed views: BLAS reads them as they are (copies of the wall's 2,856 x 4,096 were a second of a
        # search's start on two cores)
        self.qt = q.T
        self.qq = np.square(q, out=np.empty_like(q)).T
        d_min, d_max = truncation
        self.v0 = -d_min / (d_max - d_min)
        self.half = SURFACE_BAND_VOXELS * voxel_size / (d_max - d_min)

    def _decode(self, codes: np.ndarray) -> np.ndarray:
        k = self.codec.code_size
        if codes.shape[1] < k and not self.codec.prefix_ordered:
            codes = np.pad(codes, ((0, 0), (0, k - codes.shape[1])))
        out = decode_array(self.codec, codes)
        # what a reader sees: truncated to [d_min, d_max] (normalised [0, 1]); a masked map's writer fits its codes
        # to that (docs/surface.md), leaving arbitrary values past the bounds where truncation makes them exact
        out = np.asarray(out, dtype=np.float32).reshape(len(codes), -1)
        return np.clip(out, 0.0, 1.0, out=out)  # in place: decode_array's output is ours

    def __call__(self, codes: np.ndarray, observed: np.ndarray, fallback: np.ndarray, fallback_idx: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray]:
        """``(n, L)`` codes, ``(n, 16, 16, 16)`` bool observed voxels, and their code scores and nearest
        indices -> masked scores ``(n,)`` float32 and nearest indices ``(n,)`` int64."""
        x = self._decode(codes)
        seen = observed.reshape(len(codes), -1)
        s = np.asarray(fallback, np.float32).copy()
        idx = np.asarray(fallback_idx, np.int64).copy()
        # the products only for blocks with a surface observed: the others keep their code score (a fused map's
        # blocks seen through a few voxels: a fifth of the kitchen's partly observed blocks)
        ok = np.flatnonzero(((np.abs(x - self.v0) < self.half) & seen).sum(axis=1) >= MIN_OBSERVED_SURFACE)
        if not len(ok):
            return s, idx
        x, o = x[ok], seen[ok].astype(np.float32)
        ox = o * x
        sxx = (ox * x).sum(axis=1)
        d = np.empty((len(ok), self.qt.shape[1]), np.float32)

        def work(a: int, b: int) -> None:
            # (n, 4096) x (4096, M) twice, in row tiles on every core with one BLAS thread each: a search holds
            # numpy's BLAS at one thread (sdfcodec.search.engine), and its threaded products of a few rows, waiting
            # on cores busy elsewhere, cost more than they won
            part = d[a:b]
            np.matmul(ox[a:b], self.qt, out=part)
            part *= np.float32(2.0)
            np.subtract(sxx[a:b, None], part, out=part)
            part += o[a:b] @ self.qq

        run_tiles(len(ok), work, rows=_OBSERVED_ROWS)
        best = d.argmin(axis=1)
        n_obs = np.maximum(o.sum(axis=1), 1.0)
        s[ok] = np.maximum(np.take_along_axis(d, best[:, None], axis=1)[:, 0], 0.0) * (x.shape[1] / n_obs)
        idx[ok] = best
        return s, idx


def scored_voxels(m: "Map", coords: np.ndarray) -> np.ndarray:
    """``(n, 16, 16, 16)`` bool: the voxels of blocks ``coords`` ``(n, 3)`` of map ``m`` that an observed score
    (and the plane check) compares: those :meth:`~sdfcodec.Map.read_observed` gives as observed, and in a block
    where the map's mask is stored only at some voxels (:func:`~sdfcodec.map.observed.read_observation`: a
    pinned mask, the default of variable-rate maps) and says one of them is unobserved, only those it stores.

    Why: a pinned mask reads every voxel but its pinned ones (the corners of the cells whose decode may change
    sign) as observed, behind a surface too, where the cameras saw nothing and the codec's guess decodes (often
    free space below a floor); compared there, the whole kitchen's floor blocks scored 104 (median) on its
    128 B map against 23 with the exact mask, and a floor search found half of them. An unobserved pinned voxel
    shows the block has such space; a block whose pins are all observed reads as the mask says (an observation
    that is whole near its surfaces), as a map with an exact mask would. A block with too few scored voxels near
    its surface keeps its code score (:data:`MIN_OBSERVED_SURFACE`)."""
    from ..map.format import check_coords
    from ..map.observed import read_observation

    obs, known = read_observation(m.reader, check_coords(coords, grid=m.grid_blocks))
    if known is None:
        return obs
    hidden = (known & ~obs).reshape(len(obs), -1).any(axis=1)
    obs[hidden] &= known[hidden]
    return obs


def score_codes(scorer: "Scorer", observed_scorer: ObservedScorer | None, codes: np.ndarray,
                observed: np.ndarray | None, bound: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Scores and nearest descriptors of codes ``(n, L)``: the code scores of ``scorer``, replaced for partly
    observed blocks (``observed`` ``(n, 16, 16, 16)`` bool, None: all observed) by ``observed_scorer``'s.
    ``bound``: only the scores ``<= bound`` and their nearest descriptors are needed, the others may be lower
    bounds over it (:meth:`Scorer.__call__`; a partly observed block keeps its code score and index only where
    that score is its score)."""
    s, idx = scorer(codes, bound)
    if observed_scorer is not None and observed is not None:
        partial = ~observed.reshape(len(observed), -1).all(axis=1)
        if partial.any():
            s[partial], idx[partial] = observed_scorer(np.asarray(codes)[partial], observed[partial], s[partial],
                                                       idx[partial])
    return s, idx
