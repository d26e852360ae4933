"""An observation mask that is exact only where it can change the surface (map extension
``approximate-observation-mask``, spec/map-format.md section 6f).

A reader sets the unobserved voxels of a decoded block to ``d_max`` (section 6b), so the mask changes the
decoded field only through which voxels read the codec's decode and which read ``d_max``. The surface of the
field (its zero crossings, as :func:`sdfcodec.core.surface.crossing_edges` counts them, and the marching-cubes
cells :func:`sdfcodec.fusion.tsdf.mesh_from_blocks` meshes) is decided cell by cell, a cell being 2 x 2 x 2
neighbouring voxels. Where the codec's decode ``f`` of a cell's eight corners:

* changes sign (or comes within :data:`PIN_MARGIN` of zero): the mask decides the cell, so its corners keep
  their true mask bits (they are *pinned*);
* is ``>= 0`` everywhere: every corner reads ``>= 0`` under any mask (``d_max > 0``): no crossing, no triangle;
* is ``< 0`` everywhere: a corner read as ``d_max`` makes no crossing with a negative neighbour (their
  difference exceeds ``d_max``, at least the crossing rule's ``jump``) and no triangle (marching cubes skips a
  cube with a corner at ``d_max``, above its free threshold). Only when ``d_max`` is below ``jump`` are these
  cells pinned too.

So every voxel not pinned may take either bit without moving any surface point or triangle: the F-score and
Chamfer distance against any reference are those of the exact mask, bit for bit. :func:`relax_mask` gives those
voxels bits that the context coder (:mod:`sdfcodec.map.maskcoder`) stores cheaply: the bit shared by the pinned
voxels of their 2^3 sub-cube, the true bit where those disagree, and the majority of the true bits in a
sub-cube without pinned voxels, which makes it uniform and keeps the mask's coarse shape. Measured on the kitchen
half's mask with the decode of its 128 B map (B per coded block): exact 45.8; sub-cubes without pinned voxels
set to their majority 29.6, to observed 38.8, to observed if any voxel is, 29.7, to their block's majority
29.7; then blocks whose pinned voxels are all observed made fully observed, 29.1 (three passes of a 3^3
majority filter over the sub-cubes without pinned voxels would give 28.2 more). Keeping fewer pinned voxels (one unobserved corner suffices in a cell the true mask does not mesh) pinned
29 % fewer voxels and saved nothing (38.74 against 38.79 with the fill to observed): the coder pays for the
borders, not the count. What changes: a voxel far from any surface may read the codec's decode instead of
``d_max`` (or the reverse), and its mask bit is not the fusion's.

The decode here is the writer's (the codec's float32 decode of the dequantised codes, clipped); a reader's may
differ by rounding, far below :data:`PIN_MARGIN`.
"""

from __future__ import annotations

from typing import Any, Callable, Iterator

import numpy as np

from ..core._validate import BLOCK
from ..core.surface import JUMP
from .grouping import chunk_box
from .maskcoder import encode_mask_rows

__all__ = ["PIN_MARGIN", "neighbours", "padded_blocks", "BATCH_BLOCKS", "pinned_voxels", "pinned_in_batches", "relax_mask", "MaskChunks"]

#: Metres: a decoded value within this of zero counts as either sign (the writer's decode and a reader's may
#: round differently; float32 rounding of values of 0.1 m is ~1e-8 m).
PIN_MARGIN = 1e-5
#: Blocks whose pins are worked out at a time (with their coded neighbours): ~0.1 GB of temporaries per 2048.
BATCH_BLOCKS = 2048
_NEIGHBOURS = np.array([(a, b, c) for a in (-1, 0, 1) for b in (-1, 0, 1) for c in (-1, 0, 1)
                        if (a, b, c) != (0, 0, 0)], dtype=np.int64)


def _keys(coords: np.ndarray) -> np.ndarray:
    """One int64 per block index (offset so that neighbours of index 0 stay non-negative)."""
    c = np.asarray(coords, np.int64) + 1
    return (c[:, 0] << 42) | (c[:, 1] << 21) | c[:, 2]


def neighbours(coords: np.ndarray, n: int | None = None) -> Iterator[tuple[tuple[int, int, int], np.ndarray, np.ndarray]]:
    """Per offset ``(a, b, c)`` of the 26 around a block that some block has a neighbour at: ``(offset, hit,
    source)``, the indices ``hit`` among the first ``n`` (default all) blocks ``coords`` ``(m, 3)`` whose
    neighbour there is among ``coords``, and that neighbour's index ``source``."""
    coords = np.asarray(coords, np.int64)
    n = len(coords) if n is None else n
    keys = _keys(coords)
    order = np.argsort(keys)
    sorted_keys = keys[order]
    for off in _NEIGHBOURS:
        want = _keys(coords[:n] + off)
        pos = np.clip(np.searchsorted(sorted_keys, want), 0, max(len(keys) - 1, 0))
        hit = np.flatnonzero(sorted_keys[pos] == want) if len(keys) else np.zeros(0, np.int64)
        if len(hit):
            yield tuple(int(x) for x in off), hit, order[pos[hit]]


def padded_blocks(coords: np.ndarray, dec: np.ndarray, free: float) -> np.ndarray:
    """``(n, 18, 18, 18)``: each block of ``dec`` ``(n, 16, 16, 16)`` with the one-voxel layer of its 26
    neighbours around it, ``free`` where the neighbour is not among ``coords`` (empty or unobserved blocks
    decode to ``d_max``; outside the grid nothing is meshed)."""
    n = len(dec)
    out = np.full((n, BLOCK + 2, BLOCK + 2, BLOCK + 2), free, dtype=dec.dtype)
    out[:, 1:-1, 1:-1, 1:-1] = dec
    src = {-1: slice(BLOCK - 1, BLOCK), 0: slice(0, BLOCK), 1: slice(0, 1)}  # what the neighbour lends
    dst = {-1: slice(0, 1), 0: slice(1, BLOCK + 1), 1: slice(BLOCK + 1, BLOCK + 2)}
    for (a, b, c), hit, source in neighbours(coords):
        out[(hit, dst[a], dst[b], dst[c])] = dec[(source, src[a], src[b], src[c])]
    return out


def pinned_voxels(coords: np.ndarray, dec: np.ndarray, truncation: tuple[float, float], jump: float = JUMP
                  ) -> np.ndarray:
    """``(n, 16, 16, 16)`` bool: the voxels of blocks ``coords`` ``(n, 3)`` int whose mask bit can change the
    surface, given the codec's decode ``dec`` ``(n, 16, 16, 16)`` float metres (clipped to the truncation, before
    any mask; the coded blocks of the whole map, so that cells across block faces see both sides): the corners
    of every cell where ``dec`` changes sign (module docstring)."""
    d_min, d_max = (float(t) for t in truncation)
    p = padded_blocks(np.asarray(coords, np.int64).reshape(-1, 3), np.asarray(dec, np.float32), d_max)
    neg, pos = p < PIN_MARGIN, p >= -PIN_MARGIN
    any_neg = _cells(neg, np.logical_or)
    cell = any_neg if d_max < jump else any_neg & _cells(pos, np.logical_or)  # (n, 17, 17, 17)
    return _cells(cell, np.logical_or)  # a voxel is pinned when any of its 8 cells is


def pinned_in_batches(coords: np.ndarray, decode: Callable[[np.ndarray], np.ndarray],
                      truncation: tuple[float, float], batch: int = BATCH_BLOCKS) -> np.ndarray:
    """:func:`pinned_voxels` of all blocks ``coords`` ``(n, 3)`` (ordered so that neighbours are mostly close, e.g.
    by chunk) in bounded memory: ``decode(idx)`` gives the decode ``(len(idx), 16, 16, 16)`` metres of the blocks
    ``coords[idx]``; each batch of ``batch`` blocks is decoded with its coded neighbours."""
    coords = np.asarray(coords, np.int64).reshape(-1, 3)
    keys = _keys(coords)
    order = np.argsort(keys)
    out = np.zeros((len(coords), BLOCK, BLOCK, BLOCK), bool)
    for a in range(0, len(coords), batch):
        own = np.arange(a, min(a + batch, len(coords)))
        want = _keys((coords[own][:, None, :] + _NEIGHBOURS[None]).reshape(-1, 3))
        pos = np.clip(np.searchsorted(keys, want, sorter=order), 0, len(keys) - 1)
        near = order[pos][keys[order[pos]] == want]
        idx = np.union1d(own, near)
        out[own] = pinned_voxels(coords[idx], decode(idx), truncation)[np.searchsorted(idx, own)]
    return out


def _cells(a: np.ndarray, op: Any) -> np.ndarray:
    """Reduce ``a`` ``(n, m, m, m)`` over 2 x 2 x 2 windows with ``op``: ``(n, m-1, m-1, m-1)``."""
    a = op(a[:, 1:], a[:, :-1])
    a = op(a[:, :, 1:], a[:, :, :-1])
    return op(a[:, :, :, 1:], a[:, :, :, :-1])


def relax_mask(observed: np.ndarray, pinned: np.ndarray) -> np.ndarray:
    """``(n, 16, 16, 16)`` bool: ``observed`` where ``pinned``; elsewhere the bit of the pinned voxels of the
    voxel's 2^3 sub-cube when they agree, the true bit when they disagree (the sub-cube is coded voxel by voxel
    anyway, and the truth is smooth), and in a sub-cube without pinned voxels the majority of its true bits
    (observed at a tie); a block none of whose pinned voxels is unobserved is observed everywhere."""
    obs, pin = np.asarray(observed, bool), np.asarray(pinned, bool)
    n, h = len(obs), BLOCK // 2
    corners = [(a, b, c) for a in (0, 1) for b in (0, 1) for c in (0, 1)]

    def per_cube(x: np.ndarray) -> np.ndarray:  # (n, 8, 8, 8) uint8 counts: 8 strided adds, no 7-D reduction
        return sum(x[:, a::2, b::2, c::2].view(np.uint8) for a, b, c in corners)

    n_pin, n_on, n_obs = per_cube(pin), per_cube(pin & obs), per_cube(obs)
    # 2: keep the truth (pinned bits disagree); else the bit the sub-cube takes
    fill = np.where(n_pin == 0, n_obs >= 4, np.where(n_on == n_pin, 1, np.where(n_on == 0, 0, 2))).astype(np.uint8)
    f = np.broadcast_to(fill.reshape(n, h, 1, h, 1, h, 1), (n, h, 2, h, 2, h, 2)).reshape(obs.shape)
    out = np.where(pin | (f == 2), obs, f == 1)
    out[~(pin & ~obs).reshape(n, -1).any(axis=1)] = True  # no pinned voxel unobserved: a full row, one flag
    return out


class MaskChunks:
    """The coded mask chunks of a map being written, for rate control: ``bytes(rows)`` is what the ``observed``
    array's chunks take once the coded blocks' rows are ``rows``, ``write(rows)`` stores them.

    Args:
        arr: the writer's ``observed`` Zarr array (chunks of ``c`` ^ 3 blocks, chain ``sdfcodec.mask-ans``).
        coords: ``(n, 3)`` the coded blocks, grouped by chunk.
    """

    def __init__(self, arr: Any, coords: np.ndarray):
        self.arr, self.coords = arr, np.asarray(coords, np.int64).reshape(-1, 3)
        c = int(arr.chunks[0])
        keys = self.coords // c
        self.chunks, inverse = np.unique(keys, axis=0, return_inverse=True)
        self.inverse = inverse.reshape(-1)
        self.local = self.coords - keys * c
        self.c = c
        # the rows of each chunk's other blocks (empty, unobserved, beyond the grid: the fill), read once
        self.base = []
        for key in self.chunks:
            box = self._box(key)
            full = np.full((c, c, c, arr.shape[3]), 255, np.uint8)
            got = np.asarray(arr[box])
            full[tuple(slice(0, s) for s in got.shape[:3])] = got
            self.base.append(full)

    def _box(self, key: np.ndarray) -> tuple[slice, ...]:
        return chunk_box(key, self.c, self.arr.shape)

    def _chunk(self, i: int, rows: np.ndarray) -> np.ndarray:
        full = self.base[i].copy()
        sel = np.flatnonzero(self.inverse == i)
        loc = self.local[sel]
        full[loc[:, 0], loc[:, 1], loc[:, 2]] = rows[sel]
        return full

    def bytes(self, rows: np.ndarray) -> int:
        """Bytes of every chunk holding coded blocks with these rows ``(n, 512)`` uint8 (stream + CRC32C)."""
        return sum(len(encode_mask_rows(self._chunk(i, rows).reshape(-1, self.arr.shape[3]))) + 4
                   for i in range(len(self.chunks)))

    def write(self, rows: np.ndarray) -> None:
        for i, key in enumerate(self.chunks):
            box = self._box(key)
            self.arr[box] = self._chunk(i, rows)[tuple(slice(0, s.stop - s.start) for s in box[:3])]
