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

from ..core._lazy import lazy_module
from ..core._validate import BLOCK, empty
from ..errors import InvalidValueError

torch = lazy_module("torch")  # imported on first use: reading a header never needs it

__all__ = ["BufferRing", "RingPool", "BlockPlacer", "Placement"]


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
    its time on 2 cores. :meth:`clear` lets them go."""

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
            view[rel[:, 0], rel[:, 1], rel[:, 2]] = src
        else:
            r = torch.from_numpy(rel).to(self.vol.device)
            view[r[:, 0], r[:, 1], r[:, 2]] = src

    def plan(self, coords: np.ndarray) -> "Placement":
        """How blocks ``coords`` ``(n, 3)`` (each touching ``[lo, hi)``) are copied in: worked out once for a
        group, then :meth:`Placement.place` copies any range of its rows (a tile) with no further index work."""
        return Placement(self, coords)

    def place(self, coords: np.ndarray, blocks: torch.Tensor) -> None:
        """Copy ``blocks`` ``(n, 16, 16, 16)`` (on ``vol``'s device), the decodes of blocks ``coords`` ``(n, 3)``
        (map block indices, each touching ``[lo, hi)``), into ``vol``."""
        if not len(coords):
            return
        if self.np_vol is not None:
            self.plan(coords).place(0, len(coords), blocks)
            return
        # on a GPU one advanced-index assignment per segment class (a copy per run would be a kernel per run)
        for segs, idx in self._classes(coords):
            view, b0 = self._view(*segs)
            inner = tuple(slice(s[2], s[3]) for s in segs)
            sel = slice(None) if idx is None else torch.from_numpy(idx).to(blocks.device)
            rel = coords if idx is None else coords[idx]
            self._assign(view, rel - np.asarray(b0), blocks[(sel, *inner)])

    def fill(self, coords: np.ndarray, value: float) -> None:
        """Set the voxels of blocks ``coords`` ``(n, 3)`` (each touching ``[lo, hi)``) to ``value``."""
        if not len(coords):
            return
        for segs, idx in self._classes(coords):
            view, b0 = self._view(*segs)
            self._assign(view, (coords if idx is None else coords[idx]) - np.asarray(b0), value)


class Placement:
    """The copies of one group of blocks into a CPU volume, as *runs*: rows ``[r0, r1)`` of the group whose
    blocks are consecutive along z in one segment class, each run one slice assignment into the class's strided
    view (numpy copies those as runs of contiguous voxels, 2-3x faster than its advanced-index assignment, which
    goes voxel by voxel). A group in the volume's C order (a reader's group of whole chunk columns, sorted) has
    one run per row of blocks along z. Made by :meth:`BlockPlacer.plan`; :meth:`place` may run from several
    threads at once for disjoint rows."""

    def __init__(self, placer: BlockPlacer, coords: np.ndarray):
        ids = [np.searchsorted(st, coords[:, a], side="right") - 1 for a, st in enumerate(placer.starts)]
        dims = [len(s) for s in placer.segments]
        cls = (ids[0] * dims[1] + ids[1]) * dims[2] + ids[2]
        # block coordinates relative to their class's first block
        first = np.stack([np.array([seg[0] for seg in placer.segments[a]], dtype=np.int64)[ids[a]] for a in range(3)],
                         axis=1)
        rel = coords - first
        step = np.diff(rel, axis=0)
        brk = np.flatnonzero((np.diff(cls) != 0) | (step[:, 2] != 1) | (step[:, 1] != 0) | (step[:, 0] != 0))
        self.starts = np.r_[0, brk + 1].astype(np.int64)
        self.ends = np.r_[brk + 1, len(coords)].astype(np.int64)
        self.rel = rel[self.starts].tolist()
        self.cls = cls[self.starts].tolist()
        self.views: dict[int, tuple[object, tuple[slice, ...]]] = {}
        for c in set(self.cls):
            triple = (c // (dims[1] * dims[2]), c // dims[2] % dims[1], c % dims[2])
            segs = [placer.segments[a][i] for a, i in enumerate(triple)]
            self.views[c] = (placer._view(*segs)[0], tuple(slice(sg[2], sg[3]) for sg in segs))

    def place(self, a: int, b: int, blocks: torch.Tensor | np.ndarray) -> None:
        """Copy ``blocks`` ``(b - a, 16, 16, 16)``, the decodes of the group's rows ``[a, b)``, into the volume."""
        src = blocks.numpy() if isinstance(blocks, torch.Tensor) else blocks
        first = int(np.searchsorted(self.ends, a, side="right"))
        last = int(np.searchsorted(self.starts, b, side="left"))
        for r in range(first, last):
            r0, r1 = max(int(self.starts[r]), a), min(int(self.ends[r]), b)
            (i, j, k), (view, inner) = self.rel[r], self.views[self.cls[r]]
            k += r0 - int(self.starts[r])
            view[i, j, k:k + r1 - r0] = src[(slice(r0 - a, r1 - a), *inner)]
