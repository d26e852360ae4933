"""Sub-volume sampling of dense TSDF volumes into training blocks (section IV-A of the paper).

From each dense volume, 16^3 windows are taken every ``stride`` (8) voxels along each axis, and each
window is also emitted with its index order permuted: the 6 orderings of the axes (x, y, z), i.e. the
window itself and the 5 "reflections" the paper adds (transpositions such as ``w.transpose(1, 0, 2)``).
Windows are truncated, normalised to ``[0, 1]`` (free space 1.0) and filtered: a window whose mean is
above ``max_mean`` is mostly free space and is discarded, except that each discarded window is kept with
probability ``empty_fraction`` (seeded) so the models still see some empty space.

Why *above*: the paper says windows whose mean is *below* 0.85 are discarded, but free space normalises to
1.0, so that reading would throw away exactly the surface-rich windows and keep the empty ones, and the
authors' released data (mean 0.77-0.87 per voxel) shows surface-rich windows were kept. We read it as
discarding windows whose mean is above 0.85 and keep the paper's number as the default. At the paper's
truncation (-0.04, 0.1) m and 2 cm voxels a plane lying on a window's face gives a mean of about 0.89, so
it is discarded here, but with stride 8 the same surface is deeper inside a neighbouring window, which is
kept; a plane one voxel inside gives about 0.84 and is kept. The threshold depends on the ratio of
truncation to voxel size, so revisit it when those change.

Order of the output: volumes in the order given; in each, window origins in C order of (x, y, z) start;
for each origin the kept permutations in ``itertools.permutations((0, 1, 2))`` order (identity first). Only
whole windows are taken (no padding at the far faces). The random draws depend only on ``seed`` and the
volumes, never on ``batch_size``: :func:`iter_windows` yields exactly the rows of :func:`sample_windows`.

Memory: volumes are read a tile at a time (16 x-planes and as many y-rows as fit in about 16 M voxels),
so a memory-mapped or lazily indexed volume (anything with ``shape``, ``ndim``, ``dtype`` and slicing,
e.g. ``np.load(..., mmap_mode="r")`` or a Zarr array) is never loaded whole; :func:`iter_windows` then holds
at most one tile and one batch.
"""

from __future__ import annotations

import itertools
from typing import Iterator, Sequence

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

from ..core.blocks import BLOCK, check_truncation, normalise
from ..errors import DTypeError, InvalidValueError, ShapeError

__all__ = ["PERMUTATIONS", "window_origins", "sample_windows", "iter_windows"]

#: The 6 axis orders each window is emitted in (identity first), in output order.
PERMUTATIONS: tuple[tuple[int, int, int], ...] = tuple(itertools.permutations((0, 1, 2)))

_TILE_VOXELS = 1 << 24  # voxels read and normalised at a time (64 MiB as float32)


def window_origins(shape: Sequence[int], stride: int = 8) -> np.ndarray:
    """Voxel indices of the windows' ``(x, y, z)`` origins in a volume of ``shape``, in output order.

    Along an axis of ``L`` voxels the origins are ``0, stride, 2 stride, ...`` up to ``L - 16``, i.e.
    ``(L - 16) // stride + 1`` of them (none when ``L < 16``).

    Parameters
    ----------
    shape : (int, int, int)
        Volume shape ``(X, Y, Z)`` in voxels.
    stride : int
        Step between window origins in voxels (``>= 1``).

    Returns
    -------
    np.ndarray
        ``(K, 3)`` int64 origins; ``K`` is the product of the per-axis counts.
    """
    stride = _check_stride(stride)
    if len(shape) != 3:
        raise ShapeError(f"a volume shape has 3 axes (x, y, z), got {tuple(shape)}")
    axes = [np.arange(0, int(n) - BLOCK + 1, stride, dtype=np.int64) for n in shape]
    grid = np.meshgrid(*axes, indexing="ij")
    return np.stack([g.ravel() for g in grid], axis=-1)


def sample_windows(volumes, *, stride: int = 8, truncation: tuple[float, float] = (-0.04, 0.1),
                   permute: bool = True, max_mean: float = 0.85, empty_fraction: float = 0.02,
                   seed: int = 0) -> np.ndarray:
    """All kept windows of ``volumes`` as one array (see :func:`iter_windows` for the parameters).

    Returns
    -------
    np.ndarray
        ``(N, 16, 16, 16)`` float32 normalised blocks in ``[0, 1]``, indexed (x, y, z), in the order described
        in the module docstring.
    """
    batches = list(iter_windows(volumes, stride=stride, truncation=truncation, permute=permute,
                                max_mean=max_mean, empty_fraction=empty_fraction, seed=seed))
    if not batches:
        return np.empty((0, BLOCK, BLOCK, BLOCK), dtype=np.float32)
    return batches[0] if len(batches) == 1 else np.concatenate(batches)


def iter_windows(volumes, *, stride: int = 8, truncation: tuple[float, float] = (-0.04, 0.1),
                 permute: bool = True, max_mean: float = 0.85, empty_fraction: float = 0.02, seed: int = 0,
                 batch_size: int = 4096) -> Iterator[np.ndarray]:
    """Yield the kept windows of ``volumes`` in batches, holding at most one volume tile and one batch.

    Parameters
    ----------
    volumes : array ``(X, Y, Z)`` or sequence of such arrays
        Dense TSDF volume(s) in metres, indexed (x, y, z), floating point, finite (give unobserved voxels
        the value ``d_max``). Distances outside ``truncation`` are clipped to it. A 4-axis array is taken as a
        stack of volumes.
    stride : int
        Step between window origins in voxels (the paper: 8).
    truncation : (float, float)
        ``(d_min, d_max)`` in metres; values are mapped to ``[0, 1]`` with :func:`sdfcodec.core.blocks.normalise`.
    permute : bool
        Also emit the 5 axis permutations of each window (the paper's "reflections"); False gives only the
        windows as they are.
    max_mean : float
        Windows whose normalised mean is above this are mostly free space and are discarded (see the module
        docstring for why "above" and why 0.85).
    empty_fraction : float
        Probability in ``[0, 1]`` with which each discarded window (each permutation separately) is kept
        anyway, so a small share of empty space stays in the data.
    seed : int
        Seed of the generator that picks the kept empty windows.
    batch_size : int
        Windows per yielded batch; every batch but the last has exactly this many.

    Yields
    ------
    np.ndarray
        ``(B, 16, 16, 16)`` float32 normalised blocks, ``1 <= B <= batch_size``.

    Raises
    ------
    ShapeError
        A volume does not have 3 axes.
    DTypeError
        A volume is not floating point.
    InvalidValueError
        A parameter is out of range, or a volume holds NaN or infinite values.
    """
    stride = _check_stride(stride)
    try:
        d_min, d_max = (float(t) for t in truncation)
    except (TypeError, ValueError) as exc:
        raise InvalidValueError(f"truncation must be a pair (d_min, d_max) of metres, got {truncation!r}") from exc
    check_truncation(d_min, d_max)
    if not (isinstance(max_mean, (int, float, np.floating)) and np.isfinite(max_mean)):
        raise InvalidValueError(f"max_mean must be a finite number (a normalised mean, e.g. 0.85), got {max_mean!r}")
    if not (0.0 <= empty_fraction <= 1.0):
        raise InvalidValueError(f"empty_fraction must be a probability in [0, 1], got {empty_fraction!r}")
    if isinstance(batch_size, bool) or not isinstance(batch_size, (int, np.integer)) or batch_size < 1:
        raise InvalidValueError(f"batch_size must be a positive integer, got {batch_size!r}")
    return _iterate(_as_volume_list(volumes), stride, d_min, d_max, permute, float(max_mean),
                    float(empty_fraction), np.random.default_rng(seed), int(batch_size))


# --------------------------------------------------------------------------------------------------------------


def _check_stride(stride) -> int:
    if isinstance(stride, bool) or not isinstance(stride, (int, np.integer)) or stride < 1:
        raise InvalidValueError(f"stride must be a positive integer number of voxels, got {stride!r}")
    return int(stride)


def _as_volume_list(volumes) -> list:
    # one volume is anything with 3 axes (ndarray, memmap, zarr array...); otherwise a sequence of volumes
    ndim = getattr(volumes, "ndim", None)
    if ndim is not None and ndim not in (3, 4):
        raise ShapeError(f"expected a volume (X, Y, Z), a stack (N, X, Y, Z) or a sequence of volumes, got an "
                         f"array of shape {tuple(volumes.shape)}")
    if ndim is None and not hasattr(volumes, "__iter__"):
        raise ShapeError(f"expected a volume (X, Y, Z) or a sequence of volumes, got {type(volumes).__name__}")
    vols = [volumes] if ndim == 3 else list(volumes)
    for i, v in enumerate(vols):
        ndim = getattr(v, "ndim", None)
        if ndim is None:
            v = vols[i] = np.asarray(v)
            ndim = v.ndim
        if ndim != 3:
            raise ShapeError(f"volume {i} must have 3 axes (x, y, z), got shape {tuple(np.shape(v))}")
        if np.dtype(v.dtype).kind != "f":
            raise DTypeError(f"volume {i} must hold floating-point distances in metres, got dtype {v.dtype}; "
                             "convert with .astype(np.float32)")
    return vols


def _iterate(vols, stride, d_min, d_max, permute, max_mean, empty_fraction, rng, batch_size):
    perms = PERMUTATIONS if permute else PERMUTATIONS[:1]
    pending: list[np.ndarray] = []
    n_pending = 0
    for vi, vol in enumerate(vols):
        for chunk in _volume_windows(vol, vi, stride, d_min, d_max, perms, max_mean, empty_fraction, rng, batch_size):
            pending.append(chunk)
            n_pending += len(chunk)
            while n_pending >= batch_size:
                joined = pending[0] if len(pending) == 1 else np.concatenate(pending)
                yield joined[:batch_size]
                rest = joined[batch_size:]
                pending, n_pending = ([rest], len(rest)) if len(rest) else ([], 0)
    if n_pending:
        yield pending[0] if len(pending) == 1 else np.concatenate(pending)


def _volume_windows(vol, vi, stride, d_min, d_max, perms, max_mean, empty_fraction, rng, batch_size):
    """Kept windows of one volume, in output order, in chunks of at most ``batch_size``."""
    sx, sy, sz = (int(n) for n in vol.shape)
    nx, ny, nz = (max(0, (n - BLOCK) // stride + 1) for n in (sx, sy, sz))
    if nx == 0 or ny == 0 or nz == 0:
        return
    # rows of windows (y origins) per tile: the tile covers 16 x-planes, all of z, and enough y for `rows`
    rows = max(1, min(ny, (_TILE_VOXELS // (BLOCK * sz) - BLOCK) // stride + 1))
    n_perm = len(perms)
    for ix in range(nx):
        x0 = ix * stride
        for iy0 in range(0, ny, rows):
            iy1 = min(ny, iy0 + rows)
            y0, y1 = iy0 * stride, (iy1 - 1) * stride + BLOCK
            tile = np.asarray(vol[x0:x0 + BLOCK, y0:y1, :])
            if not np.all(np.isfinite(tile)):
                raise InvalidValueError(
                    f"volume {vi} holds NaN or infinite values near voxel ({x0}, {y0}, 0); sdfcodec needs finite "
                    f"distances (give unobserved voxels the truncation distance d_max = {d_max})")
            # truncate in metres, then clip again after normalising so float32 rounding stays in [0, 1]
            tile = normalise(np.clip(tile, d_min, d_max), d_min, d_max)
            np.clip(tile, 0.0, 1.0, out=tile)
            means = _window_means(tile, stride)[: iy1 - iy0, :nz]  # (rows, nz)
            # one uniform draw per window and permutation, in output order, whether or not it is needed:
            # the stream then does not depend on how volumes are tiled or batched
            u = rng.random((iy1 - iy0, nz, n_perm))
            keep = (means[..., None] <= max_mean) | (u < empty_fraction)
            jy, kz, pp = np.nonzero(keep)  # C order = output order
            if jy.size == 0:
                continue
            view = sliding_window_view(tile, (BLOCK, BLOCK, BLOCK))[0, ::stride, ::stride]  # (rows', nz', 16,16,16)
            for s in range(0, jy.size, batch_size):
                j, k, p = jy[s:s + batch_size], kz[s:s + batch_size], pp[s:s + batch_size]
                windows = view[j, k]  # fancy indexing copies only the kept windows
                if n_perm > 1:
                    for q in range(1, n_perm):
                        sel = p == q
                        if sel.any():
                            windows[sel] = windows[sel].transpose(0, *(1 + np.asarray(perms[q])))
                yield windows


def _window_means(tile: np.ndarray, stride: int) -> np.ndarray:
    """Means ``(ny, nz)`` of the 16^3 windows of a ``(16, Y, Z)`` tile at origins ``stride`` apart in y and z."""
    plane = tile.sum(axis=0, dtype=np.float64)  # (Y, Z): the window spans all 16 x-planes of the tile
    # summed-area table with a zero border: any 16 x 16 window sum is 4 lookups
    sat = np.zeros((plane.shape[0] + 1, plane.shape[1] + 1))
    np.cumsum(np.cumsum(plane, axis=0), axis=1, out=sat[1:, 1:])
    y = np.arange(0, plane.shape[0] - BLOCK + 1, stride)
    z = np.arange(0, plane.shape[1] - BLOCK + 1, stride)
    total = (sat[np.ix_(y + BLOCK, z + BLOCK)] - sat[np.ix_(y, z + BLOCK)]
             - sat[np.ix_(y + BLOCK, z)] + sat[np.ix_(y, z)])
    return total / BLOCK ** 3
