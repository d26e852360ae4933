"""A synthetic office floor plate of any size, as a lazily computed TSDF: the volume behind maps of a million
blocks and more (``docs/scale.md``), generated from its parameters alone, chunk by chunk,
so that no part of it needs to fit in memory and nothing is downloaded.

The building is a lattice of rooms ``cell`` metres apart (``rooms`` per axis, the z axis being storeys):
walls and floor slabs ``wall`` metres thick on the lattice planes, a door in every wall (0.9 x 2.1 m, centred
in the wall), and in every room one box of furniture whose size and place come from the room's index and the
seed (numpy's ``default_rng(seed)``, drawn once for all rooms). Distances are those of :mod:`sdfcodec.core.sdf`'s
primitives, combined as a union (minimum) and a door cut (maximum with the door's negated distance): exact
outside the solid wherever one primitive is nearest, a lower bound of the true distance elsewhere, truncated
to ``[d_min, d_max]`` like any fused map.

:class:`OfficeVolume` is a picklable, sliceable array (``shape``, ``dtype``, ``volume[x0:x1, y0:y1, z0:z1]``), so
``dask.array.from_array`` and :func:`sdfcodec.map.scale.as_dask_volume` read it chunk by chunk on any worker.
"""

from __future__ import annotations

from typing import Any, Sequence

import numpy as np

from ..errors import InvalidValueError

__all__ = ["OfficeVolume"]

_DOOR_HALF_WIDTH, _DOOR_HEIGHT = 0.45, 2.1


class OfficeVolume:
    """``rooms`` ``(nx, ny, nz)`` rooms of ``cell`` ``(lx, ly, lz)`` metres at ``voxel_size`` metres, truncated
    to ``truncation``; voxel ``(i, j, k)`` lies at ``voxel_size * (i, j, k)`` (the first walls sit on the planes
    ``x = wall / 2`` etc., so the building starts inside the volume). float32 metres, computed on slicing."""

    def __init__(self, rooms: Sequence[int] = (8, 8, 1), *, cell: Sequence[float] = (4.0, 3.2, 2.8),
                 wall: float = 0.2, voxel_size: float = 0.02, truncation: tuple[float, float] = (-0.04, 0.1),
                 seed: int = 0):
        self.rooms = tuple(int(n) for n in rooms)
        self.cell = np.asarray(cell, dtype=np.float64)
        if len(self.rooms) != 3 or min(self.rooms) < 1 or self.cell.shape != (3,) or not (self.cell > 1.0).all():
            raise InvalidValueError(f"rooms must be three counts >= 1 and cell three sizes > 1 m, got {rooms!r}, "
                                    f"{cell!r}")
        if not 0 < wall < 0.5 or not voxel_size > 0:
            raise InvalidValueError(f"wall must be in (0, 0.5) m and voxel_size > 0, got {wall!r}, {voxel_size!r}")
        self.wall, self.voxel_size, self.truncation, self.seed = float(wall), float(voxel_size), truncation, seed
        extent = self.cell * np.asarray(self.rooms) + self.wall  # the last walls' outer faces
        self.shape = tuple(int(np.ceil(e / self.voxel_size)) for e in extent)
        self.dtype, self.ndim = np.dtype(np.float32), 3
        rng = np.random.default_rng(seed)
        n = self.rooms
        # furniture: half sizes 0.3-0.9 m across, 0.35-0.6 m up (desks, cabinets), resting on the floor, its
        # centre placed so that it keeps 0.25 m from the walls and never blocks the doors' middle
        half = np.stack([rng.uniform(0.3, 0.9, n), rng.uniform(0.3, 0.9, n), rng.uniform(0.35, 0.6, n)], axis=-1)
        room_half = (self.cell - self.wall) / 2
        free = np.maximum(room_half[:2] - half[..., :2] - 0.25, 0.0)
        centre_xy = rng.uniform(-1.0, 1.0, (*n, 2)) * free
        self.box_centre = np.concatenate([centre_xy, half[..., 2:] - room_half[2]], axis=-1).astype(np.float32)
        self.box_half = half.astype(np.float32)

    def __getstate__(self) -> dict:
        return dict(self.__dict__)

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)

    def __dask_tokenize__(self):
        return ("sdfcodec-offices", self.rooms, tuple(self.cell), self.wall, self.voxel_size,
                tuple(self.truncation), self.seed)

    def __getitem__(self, sel: Any) -> np.ndarray:
        if not isinstance(sel, tuple) or len(sel) != 3 or not all(isinstance(s, slice) for s in sel):
            raise InvalidValueError(f"an OfficeVolume is read by three slices, got {sel!r}")
        axes = [np.arange(*s.indices(n), dtype=np.float32) * np.float32(self.voxel_size)
                for s, n in zip(sel, self.shape)]
        return self.sample(*axes)

    def sample(self, x: np.ndarray, y: np.ndarray, z: np.ndarray) -> np.ndarray:
        """Truncated distances (float32 metres) on the grid of world positions ``x`` x ``y`` x ``z`` (1-D)."""
        cell, w2 = self.cell.astype(np.float32), np.float32(self.wall / 2)
        local, index = [], []
        for a, p, n in zip(range(3), (x, y, z), self.rooms):
            q = p - w2  # the lattice planes at wall / 2 + k * cell
            k = np.clip(np.floor(q / cell[a]).astype(np.int64), 0, n - 1)
            u = q - (k + np.float32(0.5)) * cell[a]  # relative to the room's centre, in [-cell / 2, cell / 2)
            local.append(u.astype(np.float32))
            index.append(k)
        ux, uy, uz = (v.reshape(sh) for v, sh in zip(local, ((-1, 1, 1), (1, -1, 1), (1, 1, -1))))
        slab = [np.abs(np.abs(v) - cell[a] / 2) - w2 for a, v in enumerate((ux, uy, uz))]  # wall distance per axis
        # doors: the x walls (planes of constant x) open around the room's y centre, the y walls around x
        z_door = np.maximum(-(uz + cell[2] / 2 - w2), uz + cell[2] / 2 - w2 - _DOOR_HEIGHT)  # <0 inside door height
        door_x = np.maximum(np.abs(uy) - _DOOR_HALF_WIDTH, z_door)
        door_y = np.maximum(np.abs(ux) - _DOOR_HALF_WIDTH, z_door)
        d = np.minimum(np.maximum(slab[0], -door_x), np.maximum(slab[1], -door_y))
        d = np.minimum(d, slab[2])
        # furniture, room by room over the runs of voxels each axis has in one room (a chunk spans a few rooms)
        runs = [np.flatnonzero(np.diff(k, prepend=-1)).tolist() + [len(k)] for k in index]
        for ax0, ax1 in zip(runs[0][:-1], runs[0][1:]):
            for ay0, ay1 in zip(runs[1][:-1], runs[1][1:]):
                for az0, az1 in zip(runs[2][:-1], runs[2][1:]):
                    room = (index[0][ax0], index[1][ay0], index[2][az0])
                    c, h = self.box_centre[room], self.box_half[room]
                    q = [np.abs(v - c[a]) - h[a] for a, v in enumerate((ux[ax0:ax1], uy[:, ay0:ay1],
                                                                          uz[:, :, az0:az1]))]
                    box = (np.sqrt(np.maximum(q[0], 0) ** 2 + np.maximum(q[1], 0) ** 2 + np.maximum(q[2], 0) ** 2)
                           + np.minimum(np.maximum(np.maximum(q[0], q[1]), q[2]), 0))
                    sub = d[ax0:ax1, ay0:ay1, az0:az1]
                    np.minimum(sub, box, out=sub)
        return np.clip(d, *self.truncation).astype(np.float32, copy=False)
