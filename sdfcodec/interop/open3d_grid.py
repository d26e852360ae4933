"""Open3D ``VoxelBlockGrid`` files (``VoxelBlockGrid.save``, an ``.npz``): reading and writing.

What ``save`` writes (Open3D 0.17-0.20, seen in the files it makes): ``key`` ``(N, 3)`` int32, the block
indices; ``value_000``, ``value_001``... ``(N, r, r, r, C)``, one per attribute, voxels of a block in
``[z, y, x]`` order (x fastest); ``attr_name_<name>`` ``(1,)`` int64 holding the number of that attribute's
``value_`` array; ``block_resolution`` ``(1,)`` and ``voxel_size`` ``(1,)``; and an array named after the
device (``CPU:0``). No pickles: every array is plain. Voxel ``(i, j, k)`` of block ``key`` lies at
``voxel_size x (key x r + (i, j, k))`` metres. The ``tsdf`` attribute is the distance divided by Open3D's
truncation, ``trunc_voxel_multiplier x voxel_size`` (8 voxels by default: the multiplier is not in the
file, so callers say it); ``weight`` 0 means never observed.

The arrays are read without loading them when the archive stores them uncompressed, as ``save`` does
(memory-mapped from inside the zip file), so an import reads only the blocks it is placing; a compressed
archive (``np.savez_compressed``) is loaded array by array.
"""

from __future__ import annotations

import os
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import FormatError, InputNotFoundError

__all__ = ["Open3DGrid", "open_open3d_grid", "looks_like_open3d_grid", "write_open3d_grid",
           "DEFAULT_TRUNC_VOXEL_MULTIPLIER", "metres_of", "open3d_tsdf"]

#: Open3D's default truncation of ``integrate``, in voxels.
DEFAULT_TRUNC_VOXEL_MULTIPLIER = 8.0
#: A block resolution above this is absurd (2^30 voxels a block); refused before anything is allocated.
MAX_RESOLUTION = 1024


@dataclass
class Open3DGrid:
    """A saved grid: ``keys`` ``(N, 3)`` int64 block indices, ``tsdf`` and ``weight`` ``(N, r, r, r, 1)`` arrays
    (memory-mapped or loaded), block resolution ``r``, ``voxel_size`` metres (float32 as Open3D keeps it)."""

    path: Path
    keys: np.ndarray
    tsdf: Any
    weight: Any
    resolution: int
    voxel_size: float

    def read_blocks(self, ids: np.ndarray, unit: float) -> tuple[np.ndarray, np.ndarray]:
        """Distances (metres: stored value x ``unit``) and weights ``(len(ids), r, r, r)`` float32 of blocks
        ``ids``, voxels indexed ``(x, y, z)``."""
        order = np.argsort(ids, kind="stable")  # rising offsets into the file
        s = np.empty((len(ids),) + self.tsdf.shape[1:4], dtype=np.float32)
        w = np.empty_like(s)
        s[order] = np.asarray(self.tsdf[ids[order], ..., 0], dtype=np.float32)
        w[order] = np.asarray(self.weight[ids[order], ..., 0], dtype=np.float32)
        return metres_of(s, unit).transpose(0, 3, 2, 1), w.transpose(0, 3, 2, 1)


def metres_of(tsdf: np.ndarray, unit: float) -> np.ndarray:
    """Open3D's stored ``tsdf`` (float32, distance / truncation) as float32 metres: ``float32(float64(tsdf) x
    unit)``, ``unit`` the truncation ``trunc_voxel_multiplier x voxel_size`` in float64; what an import stores, bit
    for bit (docs/how-to/import-open3d.md)."""
    return (np.asarray(tsdf, dtype=np.float32).astype(np.float64) * unit).astype(np.float32)


def open3d_tsdf(d: np.ndarray, unit: float) -> np.ndarray:
    """float32 ``tsdf`` of metres ``d`` (any shape, float32) that :func:`metres_of` turns back into ``d`` exactly
    wherever a float32 does (every distance an import from Open3D gave): the float32 nearest ``d / unit``, or
    the neighbour of it that does (the two roundings can miss by one unit in the last place)."""
    d = np.asarray(d, dtype=np.float32)
    t = (d.astype(np.float64) / unit).astype(np.float32)
    for towards in (np.float32(np.inf), np.float32(-np.inf)):
        miss = metres_of(t, unit) != d
        if not miss.any():
            break
        alt = np.nextafter(t, towards)
        t = np.where(miss & (metres_of(alt, unit) == d), alt, t)
    return t


def looks_like_open3d_grid(path: Path) -> bool:
    """Whether ``path`` is a zip archive holding the arrays ``VoxelBlockGrid.save`` writes."""
    try:
        with zipfile.ZipFile(path) as z:
            names = set(z.namelist())
    except (OSError, zipfile.BadZipFile):
        return False
    return {"key.npy", "block_resolution.npy", "voxel_size.npy"} <= names


def _member(z: zipfile.ZipFile, path: Path, name: str) -> Any:
    """Array ``name`` of the archive: memory-mapped when stored uncompressed, else loaded (never unpickled)."""
    try:
        info = z.getinfo(name + ".npy")
    except KeyError:
        raise FormatError(f"{path} is not an Open3D VoxelBlockGrid file: it has no array {name!r}") from None
    with z.open(info) as f:
        try:
            version = np.lib.format.read_magic(f)
            read = (np.lib.format.read_array_header_1_0 if version == (1, 0)
                    else np.lib.format.read_array_header_2_0)
            shape, fortran, dtype = read(f)
        except ValueError as e:
            raise FormatError(f"{path}: array {name!r} is not a plain .npy array ({e})") from None
        if dtype.hasobject:
            raise FormatError(f"{path}: array {name!r} holds Python objects, which would need unpickling; sdfcodec "
                              "never unpickles: save the grid with Open3D's VoxelBlockGrid.save")
        count = int(np.prod(shape, dtype=np.int64)) * dtype.itemsize
        if count > info.file_size:
            raise FormatError(f"{path}: array {name!r} claims {shape} {dtype} but its member holds "
                              f"{info.file_size} bytes (a truncated file)")
        header_len = f.tell()
    if info.compress_type == zipfile.ZIP_STORED and not fortran and count:
        # the member's data starts after its local header (30 bytes, then name and extra field)
        with open(path, "rb") as raw:
            raw.seek(info.header_offset)
            local = raw.read(30)
            if len(local) < 30 or local[:4] != b"PK\x03\x04":
                raise FormatError(f"{path}: the zip entry of {name!r} is damaged")
            start = info.header_offset + 30 + int.from_bytes(local[26:28], "little") + int.from_bytes(
                local[28:30], "little")
        if start + header_len + count > os.path.getsize(path):
            raise FormatError(f"{path}: truncated stream: array {name!r} runs past the end of the file")
        return np.memmap(path, dtype=dtype, mode="r", offset=start + header_len, shape=shape)
    with z.open(info) as f:
        try:
            return np.load(f, allow_pickle=False)
        except ValueError as e:
            raise FormatError(f"{path}: array {name!r} cannot be read without unpickling ({e})") from None


def open_open3d_grid(path: str | os.PathLike) -> Open3DGrid:
    """Open a grid file written by ``VoxelBlockGrid.save``, checking the arrays it needs (module docstring).

    Raises:
        InputNotFoundError: no such file. FormatError: not such a file, no ``tsdf`` or ``weight`` attribute,
            shapes that disagree, absurd resolution, a truncated archive.
    """
    p = Path(path)
    if not p.is_file():
        raise InputNotFoundError(f"no Open3D grid file at {p}")
    try:
        z = zipfile.ZipFile(p)
    except (OSError, zipfile.BadZipFile) as e:
        raise FormatError(f"{p} is not an Open3D VoxelBlockGrid file (not a zip/npz archive: {e})") from None
    with z:
        names = {n[:-4] for n in z.namelist() if n.endswith(".npy")}
        res = np.asarray(_member(z, p, "block_resolution")).reshape(-1)
        vs = np.asarray(_member(z, p, "voxel_size")).reshape(-1)
        if len(res) != 1 or len(vs) != 1:
            raise FormatError(f"{p}: block_resolution and voxel_size must hold one number each")
        r, vsz = int(res[0]), float(vs[0])
        if not 0 < r <= MAX_RESOLUTION:
            raise FormatError(f"{p}: block resolution {r} is absurd (1 to {MAX_RESOLUTION})")
        if not (np.isfinite(vsz) and vsz > 0):
            raise FormatError(f"{p}: voxel size {vsz} is not a positive number of metres")
        attrs = {n[len("attr_name_"):] for n in names if n.startswith("attr_name_")}
        missing = [a for a in ("tsdf", "weight") if a not in attrs]
        if missing:
            raise FormatError(f"{p}: the grid has no {' or '.join(missing)} attribute (its attributes: "
                              f"{', '.join(sorted(attrs)) or 'none'}); only TSDF grids (tsdf and weight) import")
        arrays = {}
        for a in ("tsdf", "weight"):
            num = int(np.asarray(_member(z, p, f"attr_name_{a}")).reshape(-1)[0])
            arrays[a] = _member(z, p, f"value_{num:03d}")
        keys = np.asarray(_member(z, p, "key"))
    n = len(keys)
    if keys.ndim != 2 or keys.shape[1] != 3:
        raise FormatError(f"{p}: key must be (N, 3) block indices, got shape {keys.shape}")
    for a, arr in arrays.items():
        if arr.shape[:4] != (n, r, r, r) or arr.ndim != 5 or arr.shape[4] != 1:
            raise FormatError(f"{p}: {a} has shape {arr.shape}, the grid needs ({n}, {r}, {r}, {r}, 1): voxel count "
                              "mismatch")
    keys = keys.astype(np.int64)
    if n and len(np.unique(keys, axis=0)) != n:
        raise FormatError(f"{p}: the grid holds the same block twice (a corrupt file)")
    return Open3DGrid(path=p, keys=keys, tsdf=arrays["tsdf"], weight=arrays["weight"], resolution=r, voxel_size=vsz)


def write_open3d_grid(out: Any, keys: np.ndarray, tsdf: np.ndarray, weight: np.ndarray,
                      voxel_size: float) -> None:
    """Write the arrays ``VoxelBlockGrid.load`` reads: block ``keys`` ``(N, 3)``, ``tsdf`` (Open3D's units) and
    ``weight`` ``(N, r, r, r)`` float32 indexed ``(x, y, z)`` (stored ``[z, y, x]``, with the channel axis)."""
    r = tsdf.shape[1]

    def o3d_order(a: np.ndarray) -> np.ndarray:
        return np.ascontiguousarray(np.asarray(a, dtype=np.float32).transpose(0, 3, 2, 1)[..., None])

    arrays = {"value_000": o3d_order(tsdf), "value_001": o3d_order(weight),
              "key": np.asarray(keys, dtype=np.int32).reshape(-1, 3),
              "attr_name_tsdf": np.array([0], dtype=np.int32), "attr_name_weight": np.array([1], dtype=np.int32),
              "CPU:0": np.array(0, dtype=np.uint8), "block_resolution": np.array([r], dtype=np.int64),
              "voxel_size": np.array([voxel_size], dtype=np.float32)}
    np.savez(out, **arrays)  # ``out``: a path or an open binary file
