"""Where decoded blocks go: a small ring of reusable output buffers (:class:`BufferRing`, what
``iter_decoded(copy=False)`` and ``decode_region`` decode into) and the placing of decoded blocks into a dense
volume (:class:`BlockPlacer`, what ``decode_region`` fills), both without a per-block Python loop.

Placing is vectorised per *segment class*: along each axis the blocks touching a voxel range ``[lo, hi)`` fall
into at most three segments (a partial first block, the whole blocks, a partial last block), each copying the
same slice of every block. The blocks of one class (one segment per axis, at most 27 classes) are copied with
one advanced-index assignment into a strided view of the volume shaped ``(bx, by, bz, wx, wy, wz)``; in the
common case (whole blocks only) that is one assignment per decoded group.
"""

from __future__ import annotations

import threading
from typing import Sequence

import numpy as np

from .._lazy import lazy_module
from .._validate import BLOCK, empty
from ..errors import InvalidValueError

torch = lazy_module("torch")  # imported on first use: reading a header never needs it

__all__ = ["BufferRing", "RingPool", "BlockPlacer"]


class BufferRing:
    """``size`` reusable float32 buffers ``(n, 16, 16, 16)`` on ``device``, handed out in turn by :meth:`take`:
    the buffer handed out now is handed out again ``size`` takes later, so what was decoded into it is valid
    until then. Each buffer grows to the largest batch asked of it (a reader's groups are about equal)."""

    def __init__(self, size: int, device: torch.device):
        self.device = torch.device(device)
        self.buffers: list[torch.Tensor | None] = [None] * int(size)
        self.turn = 0

    def take(self, n: int) -> torch.Tensor:
        """The next buffer, as a contiguous ``(n, 16, 16, 16)`` view (its contents undefined)."""
        slot = self.turn % len(self.buffers)
        self.turn += 1
        buf = self.buffers[slot]
        if buf is None or len(buf) < n:
            self.buffers[slot] = None  # let the smaller one go before the larger one is allocated
            buf = self.buffers[slot] = empty((n, BLOCK, BLOCK, BLOCK), self.device)
        return buf[:n]


class RingPool:
    """The rings of one reader, kept between its iterations: :meth:`borrow` lends a ring to one iteration at a
    time (a second iteration running meanwhile gets a ring of its own), :meth:`give_back` keeps it for the next.
    A kept ring's buffers are already faulted in: a fresh 2 x 128 MiB ring per whole-map read cost 15-20 % of
    its time on 2 cores (docs/results.md, issue 19). :meth:`clear` lets them go."""

    def __init__(self, size: int):
        self.size = int(size)
        self.free: dict = {}
        self.lock = threading.Lock()

    def borrow(self, device: torch.device) -> BufferRing:
        with self.lock:
            ring = self.free.pop(torch.device(device), None)
        return ring if ring is not None else BufferRing(self.size, device)

    def give_back(self, ring: BufferRing) -> None:
        with self.lock:
            self.free[ring.device] = ring

    def clear(self) -> None:
        with self.lock:
            self.free.clear()


def _axis_segments(lo: int, hi: int, base: int) -> list[tuple[int, int, int, int, int]]:
    """The segments of the blocks touching voxels ``[lo, hi)`` along one axis: ``(b0, b1, s0, s1, d0)`` = blocks
    ``b0 <= b < b1`` copy their voxels ``[s0, s1)`` to ``d0 + (b - b0) * 16`` (relative to voxel ``base``); a
    segment of several blocks always copies whole blocks."""
    first, last = lo // BLOCK, (hi - 1) // BLOCK
    if first == last:
        return [(first, first + 1, lo - first * BLOCK, hi - first * BLOCK, lo - base)]
    segs = []
    whole0, whole1 = first, last + 1
    if lo % BLOCK:
        segs.append((first, first + 1, lo % BLOCK, BLOCK, lo - base))
        whole0 = first + 1
    if hi % BLOCK:
        whole1 = last
    if whole1 > whole0:
        segs.append((whole0, whole1, 0, BLOCK, whole0 * BLOCK - base))
    if hi % BLOCK:
        segs.append((last, last + 1, 0, hi - last * BLOCK, last * BLOCK - base))
    return segs


class BlockPlacer:
    """Copies decoded blocks into ``vol``, the dense voxels ``[base, base + vol.shape)`` of a map (a contiguous
    float32 tensor on any device; on the CPU the copies run in numpy, whose advanced-index assignment is the
    faster here); only the voxels of each block inside ``[lo, hi)`` (within ``vol``) are written."""

    def __init__(self, vol: torch.Tensor, base: Sequence[int], lo: Sequence[int], hi: Sequence[int]):
        if not vol.is_contiguous():
            raise InvalidValueError("BlockPlacer needs a contiguous volume (torch.empty(...))")
        self.vol = vol
        self.np_vol = vol.numpy() if vol.device.type == "cpu" else None
        self.segments = [_axis_segments(int(a), int(b), int(o)) for a, b, o in zip(lo, hi, base)]
        # block index -> segment of each axis, through the segments' first blocks (searchsorted)
        self.starts = [np.array([s[0] for s in segs], dtype=np.int64) for segs in self.segments]

    def _view(self, sx, sy, sz) -> tuple[object, tuple[int, ...]]:
        """The strided view ``(bx, by, bz, wx, wy, wz)`` of ``vol`` that segment class ``(sx, sy, sz)`` writes,
        and the block offsets ``b0`` to subtract from block coordinates."""
        segs = (sx, sy, sz)
        shape = tuple(s[1] - s[0] for s in segs) + tuple(s[3] - s[2] for s in segs)
        if self.np_vol is not None:
            st = self.np_vol.strides
            sub = self.np_vol[segs[0][4]:, segs[1][4]:, segs[2][4]:]
            view = np.lib.stride_tricks.as_strided(sub, shape, tuple(BLOCK * s for s in st) + st, writeable=True)
        else:
            st = self.vol.stride()
            sub = self.vol[segs[0][4]:, segs[1][4]:, segs[2][4]:]
            view = sub.as_strided(shape, tuple(BLOCK * s for s in st) + st, sub.storage_offset())
        return view, tuple(s[0] for s in segs)

    def _classes(self, coords: np.ndarray) -> list[tuple[list[tuple[int, ...]], np.ndarray | None]]:
        """The segment classes present among blocks ``coords`` ``(n, 3)``: ``(segments per axis, indices of its
        blocks)`` each, the indices None when the class holds every block (no gather needed)."""
        ids = [np.searchsorted(st, coords[:, a], side="right") - 1 for a, st in enumerate(self.starts)]
        dims = [len(s) for s in self.segments]
        cls = (ids[0] * dims[1] + ids[1]) * dims[2] + ids[2]
        present = np.unique(cls)
        out = []
        for c in present.tolist():
            triple = (c // (dims[1] * dims[2]), c // dims[2] % dims[1], c % dims[2])
            segs = [self.segments[a][i] for a, i in enumerate(triple)]
            out.append((segs, None if len(present) == 1 else np.flatnonzero(cls == c)))
        return out

    def _assign(self, view: object, rel: np.ndarray, src: object) -> None:
        if self.np_vol is not None:
            if np.ndim(src) == 0:
                view[rel[:, 0], rel[:, 1], rel[:, 2]] = src
                return
            # runs of blocks consecutive along z (a reader's groups come in chunk order, C order inside a chunk)
            # are one slice assignment each: numpy copies those in runs of contiguous voxels, 2-3x faster than
            # its advanced-index assignment, which goes voxel by voxel (measured on 24^3 blocks here)
            brk = np.flatnonzero((np.diff(rel[:, 2]) != 1) | (np.diff(rel[:, 1]) != 0) | (np.diff(rel[:, 0]) != 0))
            starts, ends = np.r_[0, brk + 1].tolist(), np.r_[brk + 1, len(rel)].tolist()
            for a, b, (i, j, k) in zip(starts, ends, rel[starts].tolist()):
                view[i, j, k:k + b - a] = src[a:b]
        else:
            r = torch.from_numpy(rel).to(self.vol.device)
            view[r[:, 0], r[:, 1], r[:, 2]] = src

    def place(self, coords: np.ndarray, blocks: torch.Tensor) -> None:
        """Copy ``blocks`` ``(n, 16, 16, 16)`` (on ``vol``'s device), the decodes of blocks ``coords`` ``(n, 3)``
        (map block indices, each touching ``[lo, hi)``), into ``vol``."""
        if not len(coords):
            return
        src_all = blocks.numpy() if self.np_vol is not None else blocks
        for segs, idx in self._classes(coords):
            view, b0 = self._view(*segs)
            inner = tuple(slice(s[2], s[3]) for s in segs)
            if idx is None:  # every block of the group
                self._assign(view, coords - np.asarray(b0), src_all[(slice(None), *inner)])
            else:
                sel = idx if self.np_vol is not None else torch.from_numpy(idx).to(blocks.device)
                self._assign(view, coords[idx] - np.asarray(b0), src_all[(sel, *inner)])

    def fill(self, coords: np.ndarray, value: float) -> None:
        """Set the voxels of blocks ``coords`` ``(n, 3)`` (each touching ``[lo, hi)``) to ``value``."""
        if not len(coords):
            return
        for segs, idx in self._classes(coords):
            view, b0 = self._view(*segs)
            self._assign(view, (coords if idx is None else coords[idx]) - np.asarray(b0), value)
