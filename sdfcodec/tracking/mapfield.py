"""Track against a map without decoding all of it: :class:`MapField`, a :class:`~sdfcodec.tracking.tracker.FieldSampler`
over a map file whose blocks are decoded on demand and kept in an LRU cache bounded in bytes.

How a lookup works (CPU or CUDA, float32):

1. World points -> continuous voxel coordinates ``u = (p - origin) / voxel_size`` -> the lower corner of the
   trilinear cell ``c = floor(u)`` -> its block ``c // 16`` and local voxel ``c mod 16``.
2. Blocks not in the cache are decoded in one batch per call (grouped into boxes of at most 8^3 blocks),
   and each becomes a *slot*: a ``(17, 17, 17, 4)`` table of value and central-difference gradient over the
   block's voxels 0..16 per axis (voxel 16 is the first voxel of the next block, and the gradients at the
   borders use the neighbours' voxels). With that apron every trilinear cell of a block lies inside its own
   slot, so a lookup is one 8-corner gather from one slot, exactly as :class:`~sdfcodec.tracking.tracker.DenseField`
   does on a dense volume, and gives the same numbers as DenseField on the map's dense decode.
3. Neighbour values come from slots already cached (their voxels 0..15) or are decoded with the batch; codecs
   with a decode halo (``gaussian-blur``) decode the whole box with neighbour context through the map's own
   region decoder, so there are no seams either.

The cache holds at most ``cache_bytes // (17^3 * 16)`` slots (78.6 KB each: 256 MiB holds 3413 blocks, a
5 x 5 x 2.5 m room at 2 cm); the least recently used slot is evicted first. Blocks that are not coded and have
no coded neighbour (unobserved or empty space, and everything outside the map) read as ``d_max`` with a zero
gradient and are *not valid*, like the free-space plateau; points whose cell or central differences leave
the map's voxel extent are not valid either (the same rule as DenseField).

    field = MapField(open_map("room.sdfz"), cache_bytes=64 << 20)
    tracker = SDFTracker(field, intrinsics)
    ...
    field.stats()   # {'hits': ..., 'misses': ..., 'blocks_decoded': ..., 'resident_blocks': ..., ...}
"""

from __future__ import annotations

import os
import threading
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from ..core._validate import BLOCK, check_device
from .densefield import cell_rows, trilinear, trilinear_rows
from ..errors import InvalidValueError, ShapeError
from ..core.header import BlockState

if TYPE_CHECKING:
    from ..map.facade import Map

__all__ = ["MapField", "DEFAULT_CACHE_BYTES"]

#: default bound on the decoded-block cache (bytes)
DEFAULT_CACHE_BYTES = 256 << 20
_E = BLOCK + 1  # slot edge: the block's 16 voxels + the first voxel of the next block
_E3 = _E ** 3
_SLOT_BYTES = _E3 * 4 * 4  # float32 value + 3 gradient channels
_GROUP = 8  # blocks per axis decoded into one canvas at most (bounds the temporary memory: 160^3 * 20 B)


class MapField:
    """A map file as a :class:`~sdfcodec.tracking.tracker.FieldSampler`, decoding blocks lazily into an LRU cache.

    Parameters
    ----------
    map : Map or str or os.PathLike
        An open map (:func:`sdfcodec.open_map`) or its path/URL. Any codec; its plugin must be installed.
    level : int, optional
        Decode only the first ``level`` code elements (prefix-ordered codecs; default: all).
    device : str or torch.device, optional
        Where the cache lives and lookups run (default CPU).
    cache_bytes : int
        Bound on the decoded-block cache in bytes (each cached block costs 17^3 * 16 = 78,608 bytes). One
        lookup call must fit: the blocks touched by one ``sample_with_gradient`` call (a chunk of the
        tracker's points) must all be resident at once, else :class:`InvalidValueError` asks for more.

    Attributes
    ----------
    hits, misses : int
        Per lookup call, each distinct cached block it touched counts a hit, each block it had to load a miss.
    blocks_decoded : int
        Blocks run through the codec's decoder (misses plus the neighbours their borders needed; for halo
        codecs every coded block of the decoded boxes).
    evictions : int
        Slots reused for other blocks.

    Notes
    -----
    Thread-safe: slot bookkeeping and the gather run under a lock (the tracker may call from several threads),
    the interpolation arithmetic outside it.
    """

    def __init__(self, map: Map, level: int | None = None, device: str | torch.device | None = None,
                 cache_bytes: int = DEFAULT_CACHE_BYTES) -> None:
        from ..map import Map, open_map

        if not isinstance(map, Map):
            if not isinstance(map, (str, os.PathLike)):
                raise InvalidValueError(f"map must be a Map or a path, got {type(map).__name__}")
            map = open_map(map)
        self.map = map
        self.level = map.reader.level(level)
        self.codec = map.codec
        self._halo = int(self.codec.halo)
        self._device = check_device(device) if device is not None else torch.device("cpu")
        self.voxel_size = float(map.voxel_size)
        self.origin = tuple(float(o) for o in map.origin)
        self._truncation = tuple(float(t) for t in map.truncation)
        states = map.block_states()
        self._states = states
        self.grid = tuple(int(g) for g in states.shape)
        coded = states == BlockState.CODED
        # blocks whose voxels can differ from d_max: coded ones and their 26 neighbours (a neighbour's border
        # cells interpolate into the coded block)
        active = _dilate(coded)
        self.n_coded = int(coded.sum())
        self.n_active = int(active.sum())
        if not (isinstance(cache_bytes, (int, np.integer)) and cache_bytes >= _SLOT_BYTES):
            raise InvalidValueError(f"cache_bytes must be an int >= {_SLOT_BYTES} (one decoded block), got {cache_bytes!r}")
        self.cache_bytes = int(cache_bytes)
        self.capacity = max(1, min(self.cache_bytes // _SLOT_BYTES, self.n_active))
        # slot of each block (flat x-major index): >= 0 cached, -1 active but not cached, -2 inactive (d_max)
        self._slot_of = np.where(active, -1, -2).astype(np.int64).ravel()
        self._pool = torch.zeros((self.capacity * _E3, 4), dtype=torch.float32, device=self._device)
        self._pool_np = self._pool.numpy() if self._device.type == "cpu" else None
        self._slot_block = np.full(self.capacity, -1, np.int64)
        self._last_used = np.zeros(self.capacity, np.int64)
        self._n_used = 0
        self._tick = 0
        self.hits = self.misses = self.blocks_decoded = self.evictions = 0
        self._lock = threading.Lock()
        nvox = np.asarray(map.shape_voxels, dtype=np.float32)
        dev = self._device
        # valid cells: lower corner in [1, n - 3] per axis (DenseField's rule on the map's dense decode)
        self._lo = torch.ones(3, device=dev)
        self._hi = torch.tensor(nvox - 3.0, device=dev)
        self._origin_t = torch.tensor(self.origin, dtype=torch.float32, device=dev)
        # the CPU lookup's (3, 1) columns (numpy)
        self._origin_np = np.asarray(self.origin, dtype=np.float32).reshape(3, 1)
        self._lo_np = np.ones((3, 1), dtype=np.float32)
        self._hi_np = (nvox - 3.0).reshape(3, 1)
        self._inv = np.float32(1.0 / self.voxel_size)
        off = np.array([[a, b, c] for a in (0, 1) for b in (0, 1) for c in (0, 1)])
        self._corner_np = (off @ np.array([_E * _E, _E, 1])).astype(np.int64)
        self._corner = torch.from_numpy(self._corner_np).to(dev)
        self._bstrides = (self.grid[1] * self.grid[2], self.grid[2], 1)

    # -- FieldSampler
    @property
    def device(self) -> torch.device:
        return self._device

    @property
    def truncation(self) -> tuple[float, float]:
        return self._truncation  # type: ignore[return-value]

    def stats(self) -> dict[str, Any]:
        """Cache statistics: hits, misses, blocks_decoded, evictions, resident_blocks, capacity_blocks,
        resident_bytes, cache_bytes (the bound), coded_blocks (in the map), hit_rate."""
        total = self.hits + self.misses
        return {"hits": self.hits, "misses": self.misses, "blocks_decoded": self.blocks_decoded,
                "evictions": self.evictions, "resident_blocks": self._n_used, "capacity_blocks": self.capacity,
                "resident_bytes": self._n_used * _SLOT_BYTES, "cache_bytes": self.cache_bytes,
                "pool_bytes": self.capacity * _SLOT_BYTES, "coded_blocks": self.n_coded,
                "hit_rate": self.hits / total if total else 0.0}

    def reset_stats(self) -> None:
        """Zero the counters (the cache keeps its blocks)."""
        self.hits = self.misses = self.blocks_decoded = self.evictions = 0

    def sample(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Distances ``(N,)`` metres and validity ``(N,)`` at world points ``(N, 3)`` metres."""
        d, _, valid = self.sample_with_gradient(points)
        return d, valid

    def sample_with_gradient(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Distances ``(N,)`` metres, gradients ``(N, 3)`` (world frame, per metre) and validity ``(N,)`` at
        world points ``(N, 3)`` float32 metres (any strides). Invalid points get ``d_max`` and a zero gradient."""
        if not isinstance(points, torch.Tensor):
            points = torch.as_tensor(np.asarray(points, dtype=np.float32))
        if points.ndim != 2 or points.shape[1] != 3:
            raise ShapeError(f"points must have shape (N, 3) (world x, y, z in metres), got {tuple(points.shape)}")
        p = points.to(device=self._device, dtype=torch.float32)
        if self._pool_np is not None:
            return self._lookup_cpu(p)
        u = (p - self._origin_t) * (1.0 / self.voxel_size)
        i0f = torch.floor(u)
        c = torch.clamp(i0f, self._lo, self._hi).nan_to_num_(nan=1.0)
        ok = c == i0f
        in_range = ok[:, 0] & ok[:, 1] & ok[:, 2]
        frac = (u - c).nan_to_num_(nan=0.0, posinf=0.0, neginf=0.0)
        ci = c.to(torch.int64)
        b = torch.div(ci, BLOCK, rounding_mode="floor")
        loc = ci - b * BLOCK
        bflat = b[:, 0] * self._bstrides[0] + b[:, 1] * self._bstrides[1] + b[:, 2]
        local = loc[:, 0] * (_E * _E) + loc[:, 1] * _E + loc[:, 2]
        with self._lock:
            active, s = self._slots(bflat.cpu().numpy(), in_range.cpu().numpy())
            idx = torch.from_numpy(s).to(self._device) * _E3 + local
            idx = (self._corner[:, None] + idx[None, :]).reshape(-1)
            corners = self._pool.index_select(0, idx)
        valid = torch.from_numpy(active).to(self._device)
        vals = trilinear(corners, frac, in_place=True)  # (N, 4); corners is a scratch gather
        d_max = self._truncation[1]
        d = torch.where(valid, vals[:, 0], d_max)
        g = torch.where(valid[:, None], vals[:, 1:], 0.0)
        return d, g, valid

    def _lookup_cpu(self, p: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """:meth:`sample_with_gradient` on the CPU, in numpy, as DenseField's CPU lookup (numpy's calls cost about
        a microsecond, torch's 5-10, and the arithmetic runs on contiguous (3, N) rows). Only the slot lookup and
        the gather hold the lock, so that the tracker's two threads interpolate at the same time: 1.35x on warm
        kitchen maps against torch's ops under the lock (2-core AMD EPYC)."""
        q = p.detach().numpy().T  # (3, N); a (3, N).t() view is read without a copy
        n = q.shape[1]
        in_range = np.empty(n, dtype=bool)
        c, frac = cell_rows(q, self._origin_np, self._inv, self._lo_np, self._hi_np, in_range)
        blk, loc = np.divmod(c.astype(np.intp), BLOCK)
        bflat = blk[0] * self._bstrides[0]
        bflat += blk[1] * self._bstrides[1]
        bflat += blk[2]
        local = loc[0] * (_E * _E)
        local += loc[1] * _E
        local += loc[2]
        with self._lock:
            active, s = self._slots(bflat, in_range)
            local += s * _E3
            corners = np.take(self._pool_np, np.add.outer(self._corner_np, local).reshape(-1), axis=0)
        vals = trilinear_rows(corners, frac, np.empty((4, n), dtype=np.float32))
        if not active.all():  # not valid: d_max and a zero gradient
            off = ~active
            vals[0, off] = self._truncation[1]
            vals[1:, off] = 0.0
        return torch.from_numpy(vals[0]), torch.from_numpy(vals[1:]).t(), torch.from_numpy(active)

    def _slots(self, bf: np.ndarray, inr: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(Under the lock.) The cache slots of the blocks ``bf`` (N,) flat indices of the points in range ``inr``
        (N,): ``(active, slot)``, the points that read a decoded block and their slots (0 for the rest), loading
        the blocks not cached yet."""
        slots = self._slot_of[bf]
        self._tick += 1
        resident = inr & (slots >= 0)
        # distinct cached slots this call touches (a mark array: O(N + capacity), cheaper than a sort)
        mark = np.zeros(self.capacity, dtype=bool)
        mark[slots[resident]] = True
        touched = np.flatnonzero(mark)
        self._last_used[touched] = self._tick  # protects them from eviction by this call's loads
        missing = inr & (slots == -1)
        if missing.any():
            need = np.unique(bf[missing])
            self._load(need)
            slots = self._slot_of[bf]
        self.hits += len(touched)
        active = inr & (slots >= 0)
        return active, np.where(active, slots, 0)

    # -- cache management (called under the lock)
    def _alloc(self) -> int:
        if self._n_used < self.capacity:
            self._n_used += 1
            return self._n_used - 1
        # the least recently used slot; slots touched by the current call carry the current tick
        slot = int(np.argmin(self._last_used))
        if self._last_used[slot] >= self._tick:
            raise InvalidValueError(
                f"the decoded-block cache ({self.capacity} blocks, {self.cache_bytes} bytes) cannot hold the "
                "blocks one lookup touches; raise cache_bytes (or lower TrackerConfig.chunk_size)")
        old = self._slot_block[slot]
        if old >= 0:
            self._slot_of[old] = -1
            self.evictions += 1
        return slot

    def _load(self, need: np.ndarray) -> None:
        """Decode the active blocks with flat indices ``need`` (M,) into slots."""
        coords = np.stack(np.unravel_index(need, self.grid), axis=1).astype(np.int64)
        groups = coords // _GROUP
        keys, inv = np.unique(groups, axis=0, return_inverse=True)
        inv = inv.reshape(-1)
        for gi in range(len(keys)):
            self._load_group(coords[inv == gi])

    def _load_group(self, coords: np.ndarray) -> None:
        d_min, d_max = self._truncation
        b0 = coords.min(axis=0) - 1
        b1 = coords.max(axis=0) + 2  # exclusive; one block of apron each side
        nb = b1 - b0
        dev = self._device
        if self._halo:
            canvas = self.map.reader.decode_voxels(b0 * BLOCK, b1 * BLOCK, self.level, dev)
            cl, ch = np.maximum(b0, 0), np.minimum(b1, self.grid)
            self.blocks_decoded += int((self._states[cl[0]:ch[0], cl[1]:ch[1], cl[2]:ch[2]] == BlockState.CODED).sum())
        else:
            canvas = torch.full(tuple(int(v) * BLOCK for v in nb), d_max, dtype=torch.float32, device=dev)
            view = canvas.view(int(nb[0]), BLOCK, int(nb[1]), BLOCK, int(nb[2]), BLOCK).permute(0, 2, 4, 1, 3, 5)
            cl, ch = np.maximum(b0, 0), np.minimum(b1, self.grid)
            sub = self._states[cl[0]:ch[0], cl[1]:ch[1], cl[2]:ch[2]]
            in_box = np.argwhere(sub == BlockState.CODED) + cl
            if len(in_box):
                flat = (in_box * np.array(self._bstrides)).sum(1)
                slot = self._slot_of[flat]
                cached = slot >= 0
                if cached.any():  # neighbours already decoded: their voxels 0..15 from the slots
                    rel = torch.from_numpy(in_box[cached] - b0).to(dev)
                    vals = self._pool.view(self.capacity, _E, _E, _E, 4)[torch.from_numpy(slot[cached]).to(dev), :BLOCK,
                                                                          :BLOCK, :BLOCK, 0]
                    view[rel[:, 0], rel[:, 1], rel[:, 2]] = vals
                todo = in_box[~cached]
                if len(todo):
                    box = tuple(slice(int(a), int(b)) for a, b in zip(cl, ch))
                    all_c, all_z = self.map.reader.codes_in(box, self.level, self._states)
                    strides = np.array(self._bstrides)
                    pick = np.isin(all_c @ strides, todo @ strides)
                    cc, zz = all_c[pick], all_z[pick]
                    # the map readers' decode step: NaN/Inf refused, then the same float ops as decode_region
                    dec = self.map.reader.decode_codes(torch.from_numpy(zz).to(dev), metres=True, coords=cc)
                    rel = torch.from_numpy(cc - b0).to(dev)
                    view[rel[:, 0], rel[:, 1], rel[:, 2]] = dec
                    self.blocks_decoded += len(cc)
        # value + central differences (DenseField's formula) over the canvas
        table = torch.zeros(canvas.shape + (4,), dtype=torch.float32, device=dev)
        table[..., 0] = canvas
        inv2h = 1.0 / (2.0 * self.voxel_size)
        table[1:-1, :, :, 1] = (canvas[2:] - canvas[:-2]) * inv2h
        table[:, 1:-1, :, 2] = (canvas[:, 2:] - canvas[:, :-2]) * inv2h
        table[:, :, 1:-1, 3] = (canvas[:, :, 2:] - canvas[:, :, :-2]) * inv2h
        pool = self._pool.view(self.capacity, _E, _E, _E, 4)
        for blk in coords:
            r = (blk - b0) * BLOCK
            slot = self._alloc()
            pool[slot] = table[r[0]:r[0] + _E, r[1]:r[1] + _E, r[2]:r[2] + _E]
            flat = int((blk * np.array(self._bstrides)).sum())
            self._slot_of[flat] = slot
            self._slot_block[slot] = flat
            self._last_used[slot] = self._tick
            self.misses += 1


def _dilate(mask: np.ndarray) -> np.ndarray:
    """26-neighbourhood dilation of a 3-D bool array (no wrap-around)."""
    out = mask.copy()
    if not mask.any():
        return out
    p = np.pad(mask, 1)
    X, Y, Z = mask.shape
    for dx in (0, 1, 2):
        for dy in (0, 1, 2):
            for dz in (0, 1, 2):
                out |= p[dx:dx + X, dy:dy + Y, dz:dz + Z]
    return out
