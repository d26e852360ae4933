"""A dense TSDF volume as a :class:`~sdfcodec.tracking.tracker.FieldSampler`: :class:`DenseField` (trilinear
interpolation, central-difference gradient), what the SDF Tracker samples on a fully decoded map.

Gradient: central differences with a step of one voxel of the trilinearly interpolated field. Trilinear
interpolation is linear in the voxel values, so this is *exactly* the trilinear interpolation of the voxels'
central differences ``(d[i+1] - d[i-1]) / 2h``; :class:`DenseField` precomputes those (4 channels: value and
gradient, interpolated in one gather) unless told to save the memory and evaluate them on the fly.

A map too large to decode whole is sampled through :class:`~sdfcodec.tracking.mapfield.MapField` instead (blocks decoded
lazily into a bounded cache), which follows the same conventions.
"""

from __future__ import annotations

import math
import mmap
from typing import Any, Literal, Sequence

import numpy as np
import torch

from ..errors import DTypeError, InvalidValueError, ShapeError

__all__ = ["DenseField"]


#: The most points a CPU lookup takes at a time: it bounds the temporaries (about 200 bytes a point) of a large
#: call; the tracker's chunks (32,768 points) go whole, which measured faster than cache-sized pieces (see
#: :meth:`DenseField._lookup_rows`).
_CPU_POINTS = 32768


def _as_vec3(x: Any, name: str) -> tuple[float, float, float]:
    a = np.asarray(x, dtype=np.float64).reshape(-1)
    if a.shape != (3,):
        raise ShapeError(f"{name} must have 3 components (x, y, z), got shape {np.shape(x)}")
    if not np.all(np.isfinite(a)):
        raise InvalidValueError(f"{name} must be finite, got {a.tolist()}")
    return float(a[0]), float(a[1]), float(a[2])


def trilinear(corners: torch.Tensor, frac: torch.Tensor, channel_major: bool = False,
              in_place: bool = False) -> torch.Tensor:
    """Trilinear interpolation of gathered cell corners: ``corners`` (8 * N, C) or (8, N, C), corner-major
    (corner ``(a, b, c)`` of the cell at index ``4a + 2b + c``, i.e. x-major), ``frac`` (N, 3) the points'
    fractions in their cells (any strides; a ``(3, N)`` tensor's transpose is cheapest) -> (N, C), or with
    ``channel_major`` a contiguous (C, N).

    The fractions are expanded to the C channels first (a copy of 3 N C floats) so that every lerp runs over
    two contiguous slabs of N * C values: measured 1.1x faster than broadcasting them as (N, 1) and 1.4x
    faster than expanding them by a gather, for 4 channels on a 2-core CPU. ``channel_major`` has the last
    lerp write its (C, N) result directly (what the tracker's row-wise arithmetic wants) instead of
    transposing a copy afterwards. ``in_place`` lets the first two lerps write over ``corners`` (a
    contiguous scratch gather) instead of fresh buffers: 1.15x faster for 25,600 points of 4 channels."""
    n = frac.shape[0]
    ch = corners.shape[-1]
    c = corners.reshape(2, 2, 2, n * ch)
    w = frac.t()[:, :, None].expand(3, n, ch).reshape(3, n * ch) if ch > 1 else frac.t()
    for k in range(2):
        c = torch.lerp(c[0], c[1], w[k], out=c[0]) if in_place else torch.lerp(c[0], c[1], w[k])
    if not channel_major:
        return torch.lerp(c[0], c[1], w[2]).reshape(n, ch)
    out = torch.empty((ch, n), dtype=c.dtype, device=c.device)
    cm = c.reshape(2, n, ch).transpose(1, 2)  # (2, C, N) views
    return torch.lerp(cm[0], cm[1], w[2].reshape(n, ch).t(), out=out)


def trilinear_rows(corners: np.ndarray, frac: np.ndarray, out: np.ndarray) -> np.ndarray:
    """CPU trilinear interpolation in numpy: ``corners`` (8 * n, C) float32 gathered cell corners, corner-major
    as for :func:`trilinear` (overwritten: it is the scratch of the lerps), ``frac`` (3, n) the fractions,
    ``out`` (C, n) (any strides) receives the result, which is returned.

    Each lerp is ``a += w (b - a)`` in place over two contiguous slabs of n * C values, the fractions repeated to
    the C channels (:func:`_repeat4` for 4, else ``np.repeat``): numpy's calls cost about a microsecond against
    torch's 5-10 and its expanded copy of the fractions (a stride-0 inner dimension) ran at 0.7 GB/s on a 2-core
    AMD EPYC; with ``np.repeat`` this measured 1.3-1.6x faster than :func:`trilinear` for 4,800-19,200 points of
    4 channels, one thread."""
    n = frac.shape[1]
    ch = corners.shape[-1]
    c = corners.reshape(2, 2, 2, n * ch)
    w = _repeat4(frac) if ch == 4 else np.repeat(frac, ch, axis=1) if ch > 1 else frac
    for k in range(2):
        a, b = c[0], c[1]
        b -= a
        b *= w[k]
        a += b
        c = a
    a, b = c[0].reshape(n, ch), c[1].reshape(n, ch)
    b -= a
    b *= w[2].reshape(n, ch)
    return np.add(a.T, b.T, out=out)


def cell_rows(q: np.ndarray, origin: np.ndarray, inv: np.float32, lo: np.ndarray, hi: np.ndarray,
              valid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The CPU cell arithmetic of a trilinear lookup, in numpy: for world points ``q`` (3, n) float32 metres (any
    strides), the lower corners of their cells clamped to ``[lo, hi]`` and the fractions, both (3, n) float32;
    validity (the clamp moved nothing) is written into ``valid`` (n,) bool. ``origin``, ``lo``, ``hi``: (3, 1)
    float32; ``inv``: 1 / voxel size.

    Points that are not valid (outside the bounds, NaN, infinite) get the cell ``lo`` and fractions 0, so that every
    index is in the table. The clamp is one ``clip`` of the block, and the fractions need none: ``u - floor(u)`` is
    in [0, 1) wherever the point is valid (the subtraction is exact); the invalid are fixed only when there are any
    (fmin/fmax row by row and a clamp of the fractions took 0.11 ms of a 17,000-point lookup on a 2-core AMD
    EPYC; this takes about 0.04)."""
    u = np.subtract(q, origin)
    u *= inv
    cell = np.floor(u)
    c = np.clip(cell, lo, hi)  # NaN stays NaN here: fixed below with the other invalid points
    ok = cell == c  # never true for NaN
    np.logical_and(ok[0], ok[1], out=valid)
    valid &= ok[2]
    u -= c
    if not valid.all():
        bad = ~valid
        np.copyto(c, lo, where=bad)
        np.copyto(u, 0.0, where=bad)
    return c, u


def _repeat4(frac: np.ndarray) -> np.ndarray:
    """``np.repeat(frac, 4, axis=1)`` for a (3, n) float32 ``frac``, by integer moves: each value's 4 bytes
    doubled into an 8-byte word (``x | x << 32``), written twice. ``np.repeat`` copies 4-byte elements one at a
    time: 0.12 ms for 17,000 points here against 0.06 ms this way (2-core AMD EPYC)."""
    x = np.ascontiguousarray(frac, dtype=np.float32).view(np.uint32).astype(np.uint64)
    x |= x << np.uint64(32)
    w = np.empty((*x.shape, 2), dtype=np.uint64)
    w[..., 0] = x
    w[..., 1] = x
    return w.reshape(x.shape[0], -1).view(np.float32)


def _zeros_on_huge_pages(shape: tuple[int, ...]) -> torch.Tensor:
    """A zeroed CPU float32 tensor in anonymous memory advised for transparent huge pages (Linux), else
    ``torch.zeros``. The tracker's gather reads 8 scattered rows a point from the value-and-gradient table;
    with 4 KiB pages nearly every row is a TLB miss (the x neighbours are a whole y-z slab apart): on 2 MiB
    pages numpy's ``take`` of a 640x480 frame's points measured 1.2-1.6x faster (7-Scenes redkitchen)."""
    nbytes = math.prod(shape) * 4
    huge = 2 << 20
    if not hasattr(mmap, "MADV_HUGEPAGE") or nbytes < huge:
        return torch.zeros(shape, dtype=torch.float32)
    try:
        mem = mmap.mmap(-1, nbytes + huge, flags=mmap.MAP_PRIVATE | mmap.MAP_ANONYMOUS)
        mem.madvise(mmap.MADV_HUGEPAGE)
    except (OSError, ValueError):
        return torch.zeros(shape, dtype=torch.float32)
    buf = np.frombuffer(mem, dtype=np.uint8)  # anonymous memory is zero; it lives as long as the tensor does
    start = -buf.ctypes.data % huge  # the table starts on a huge-page boundary
    return torch.from_numpy(buf[start:start + nbytes].view(np.float32).reshape(shape))


class DenseField:
    """A dense TSDF volume as a :class:`~sdfcodec.tracking.tracker.FieldSampler` (trilinear interpolation,
    central-difference gradient).

    Voxel ``(i, j, k)`` holds the distance at world position ``origin + voxel_size * (i, j, k)`` (the project's
    convention).
    A point is valid when every voxel its interpolation and central differences touch lies in the volume
    (continuous voxel coordinates ``u = (p - origin) / voxel_size`` in ``[1, n - 2)`` on each axis) and is
    finite; NaN points are not valid. NaN voxels are allowed and mean "unknown": points that touch one are
    not valid (the project's convention is to store unobserved space as ``d_max``, which the tracker's
    plateau test drops as well).

    Args:
        volume: ``(X, Y, Z)`` distances in metres, numpy or torch (any float dtype; stored as float32). Each
            axis needs at least 4 voxels.
        voxel_size: edge of a voxel in metres.
        origin: world position ``(3,)`` of voxel ``(0, 0, 0)`` in metres.
        truncation: ``(d_min, d_max)`` metres the volume was truncated to.
        device: where to keep the volume and compute; default: the tensor's device (CPU for numpy).
        precompute_gradient: keep a ``(X, Y, Z, 4)`` table of value and central differences (4x the memory of
            the volume; one 8-corner gather per point) instead of 7 trilinear lookups of the values per point
            (the same numbers up to float rounding, about 5x slower).
        backend: ``"gather"`` (hand-written trilinear gather; about 15% faster than grid_sample on a 2-core
            CPU for scattered points) or ``"grid_sample"`` (``torch.nn.functional.grid_sample``; needs
            ``precompute_gradient``).

    Memory: ``precompute_gradient`` keeps 16 bytes a voxel (a 5 x 5 x 3 m room at 2 cm: 150 MB). For maps too
    large for that, implement :class:`~sdfcodec.tracking.tracker.FieldSampler` over decoded blocks instead.
    """

    def __init__(self, volume: Any, voxel_size: float, origin: Sequence[float] = (0.0, 0.0, 0.0),
                 truncation: tuple[float, float] = (-0.04, 0.1), *, device: str | torch.device | None = None,
                 precompute_gradient: bool = True, backend: Literal["gather", "grid_sample"] = "gather") -> None:
        if isinstance(volume, torch.Tensor):
            if not volume.is_floating_point():
                raise DTypeError(f"volume must be floating point, got {volume.dtype}; convert with .float()")
            vol = volume.detach().to(device=device if device is not None else volume.device, dtype=torch.float32)
        else:
            arr = np.asarray(volume)
            if arr.dtype.kind != "f":
                raise DTypeError(f"volume must be floating point (distances in metres), got dtype {arr.dtype}")
            vol = torch.from_numpy(np.ascontiguousarray(arr, dtype=np.float32))
            if device is not None:
                vol = vol.to(device)
        if vol.ndim != 3:
            raise ShapeError(f"volume must have shape (X, Y, Z), got {tuple(vol.shape)}")
        if min(vol.shape) < 4:
            raise ShapeError(f"volume needs at least 4 voxels along each axis for trilinear interpolation and "
                             f"central differences, got {tuple(vol.shape)}")
        if not (isinstance(voxel_size, (int, float)) and math.isfinite(voxel_size) and voxel_size > 0):
            raise InvalidValueError(f"voxel_size must be a positive number of metres, got {voxel_size!r}")
        d_min, d_max = (float(v) for v in truncation)
        if not d_min < d_max:
            raise InvalidValueError(f"truncation must be (d_min, d_max) with d_min < d_max, got {truncation}")
        if backend not in ("gather", "grid_sample"):
            raise InvalidValueError(f"backend must be 'gather' or 'grid_sample', got {backend!r}")
        if backend == "grid_sample" and not precompute_gradient:
            raise InvalidValueError("backend='grid_sample' needs precompute_gradient=True")
        self.voxel_size = float(voxel_size)
        self.origin = _as_vec3(origin, "origin")
        self._truncation = (d_min, d_max)
        self.shape = tuple(int(s) for s in vol.shape)
        self.precompute_gradient = bool(precompute_gradient)
        self.backend = backend
        self._device = vol.device
        X, Y, Z = self.shape
        self._strides = (Y * Z, Z, 1)
        # a point is valid when the lower corner of its cell, floor(u) (u = continuous voxel coordinate), is in
        # [1, n - 3] on each axis: its 8 corners and their central differences then stay inside the volume
        dev = vol.device
        # (3, 1) columns: the cell arithmetic runs on (3, N) rows, each contiguous
        self._lo, self._hi = (1.0, 1.0, 1.0), (X - 3.0, Y - 3.0, Z - 3.0)
        self._lo0, self._hi0 = (0.0, 0.0, 0.0), (X - 2.0, Y - 2.0, Z - 2.0)
        self._origin_t = torch.tensor(self.origin, dtype=torch.float32, device=dev).reshape(3, 1)
        self._lo_t = torch.tensor(self._lo, device=dev)  # for grid_sample's (N, 3) points
        self._hi_t = torch.tensor(self._hi, device=dev)
        self._ones_row = torch.ones((1, 3), dtype=torch.float32, device=dev)
        # the flat cell index as one (1, 3) x (3, N) product of the cell corners: exact in float32 while every
        # index is below 2^24 (a 256^3 volume); larger volumes take the integer arithmetic
        self._strides_row = torch.tensor([self._strides], dtype=torch.float32, device=dev)
        self._float_index = X * Y * Z <= 2**24
        # int64 on the CPU (numpy's take wants intp); int32 on accelerators unless the volume passes 2^31 voxels
        small = X * Y * Z < 2**31 - 1
        self._index_dtype = torch.int32 if small and dev.type != "cpu" else torch.int64
        off = torch.tensor([[a, b, c] for a in (0, 1) for b in (0, 1) for c in (0, 1)], device=dev)
        self._corner_offsets = (off * torch.tensor(self._strides, device=dev)).sum(1).to(self._index_dtype)  # (8,)
        self._has_nan = not bool(torch.isfinite(vol).all())  # NaN/inf voxels: unknown
        if precompute_gradient:
            table = (_zeros_on_huge_pages((X, Y, Z, 4)) if vol.device.type == "cpu"
                     else torch.zeros((X, Y, Z, 4), dtype=torch.float32, device=vol.device))
            table[..., 0] = vol
            inv2h = 1.0 / (2.0 * self.voxel_size)
            table[1:-1, :, :, 1] = (vol[2:] - vol[:-2]) * inv2h
            table[:, 1:-1, :, 2] = (vol[:, 2:] - vol[:, :-2]) * inv2h
            table[:, :, 1:-1, 3] = (vol[:, :, 2:] - vol[:, :, :-2]) * inv2h
            self._table = table.reshape(-1, 4)
            if backend == "grid_sample":
                self._grid_volume = table.permute(3, 0, 1, 2).unsqueeze(0).contiguous()  # (1, 4, X, Y, Z)
                self._grid_scale = torch.tensor([2.0 / (Z - 1), 2.0 / (Y - 1), 2.0 / (X - 1)],
                                                dtype=torch.float32, device=vol.device)
        else:
            self._table = vol.reshape(-1, 1)
        self._volume = vol
        # the CPU lookup of the value-and-gradient table runs in numpy (_lookup_rows); elsewhere torch's ops
        self._rows = dev.type == "cpu" and precompute_gradient and backend == "gather"
        if self._rows:
            self._np = (self._table.numpy(), self._corner_offsets.numpy(),
                        np.asarray(self.origin, dtype=np.float32).reshape(3, 1),
                        np.asarray(self._strides, dtype=np.float32 if self._float_index else np.float64),
                        np.asarray(self._lo, dtype=np.float32).reshape(3, 1),
                        np.asarray(self._hi, dtype=np.float32).reshape(3, 1))

    # -- FieldSampler
    @property
    def device(self) -> torch.device:
        return self._device

    @property
    def truncation(self) -> tuple[float, float]:
        return self._truncation

    @property
    def volume(self) -> torch.Tensor:
        """The distances ``(X, Y, Z)`` float32 metres on :attr:`device`."""
        return self._volume

    def _check_points(self, points: torch.Tensor) -> torch.Tensor:
        if not isinstance(points, torch.Tensor):
            points = torch.as_tensor(np.asarray(points, dtype=np.float32))
        if points.ndim != 2 or points.shape[1] != 3:
            raise ShapeError(f"points must have shape (N, 3) (world x, y, z in metres), got {tuple(points.shape)}")
        return points.to(device=self._device, dtype=torch.float32)

    def _cells(self, points: torch.Tensor, lo: torch.Tensor, hi: torch.Tensor
               ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Lower cell corners clamped to ``[lo, hi]`` (3, 1): flat voxel index (N,), fractions (N, 3) (a view
        of a contiguous (3, N)), in_range (N,).

        The arithmetic runs on (3, N) rows: every op then reads and writes contiguous memory with per-row
        scalars (on (N, 3) points it was 2-10x slower per op: tiny inner dimensions, reductions over 3).
        A ``(3, N).t()`` view (what the tracker passes) is read without a copy."""
        n = points.shape[0]
        u = torch.empty((3, n), dtype=torch.float32, device=points.device)
        torch.sub(points.t(), self._origin_t, out=u).mul_(1.0 / self.voxel_size)
        i0f = torch.floor(u)
        c = torch.empty_like(i0f)
        for k in range(3):  # a scalar clamp per row: 6x faster than one clamp against (3, 1) bounds
            torch.clamp(i0f[k], float(lo[k]), float(hi[k]), out=c[k])
        c.nan_to_num_(nan=1.0)  # NaN points: any in-range cell, flagged below
        # in range where the clamp moved nothing; summed by a product (comparisons and reductions over
        # (3, N) booleans measured 6x slower)
        in_range = torch.mm(self._ones_row, (i0f - c).abs_())[0] == 0
        frac = u.sub_(c).nan_to_num_(nan=0.0, posinf=0.0, neginf=0.0)  # [0, 1) in range; finite elsewhere
        if self._float_index:
            base = torch.mm(self._strides_row, c)[0].to(self._index_dtype)
        else:
            ci = c.to(self._index_dtype)
            base = ci[0] * self._strides[0] + ci[1] * self._strides[1] + ci[2]
        return base, frac.t(), in_range

    def _interp(self, base: torch.Tensor, frac: torch.Tensor, table: torch.Tensor,
                channel_major: bool = False) -> torch.Tensor:
        """Trilinear interpolation of ``table`` rows (X*Y*Z, C) over the cells at ``base`` (N,) with fractions
        ``frac`` (N, 3) -> (N, C), or a contiguous (C, N) with ``channel_major``.

        One gather per point: its 8 corners' rows (value and gradient together), gathered corner-major as
        (8, N, C); on the CPU the gather and the corner indices are numpy's (``take`` is about 4x faster than
        ``index_select`` for rows this short, the broadcast add 2.5x faster than torch's; zero-copy either
        way)."""
        if table.device.type == "cpu":
            idx = np.add.outer(self._corner_offsets.numpy(), base.numpy()).reshape(-1)
            c = torch.from_numpy(np.take(table.numpy(), idx, axis=0))
        else:
            idx = (self._corner_offsets[:, None] + base[None, :]).reshape(-1)  # x-major, then y, then z
            c = table.index_select(0, idx)
        return trilinear(c, frac, channel_major, in_place=True)

    def _lookup_rows(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The CPU lookup: value and gradient rows ``(4, N)`` and validity ``(N,)`` at ``points`` ``(N, 3)``
        (a ``(3, N).t()`` view is read without a copy), in numpy, :data:`_CPU_POINTS` points at a time.

        Why numpy: the work per point is a gather of 8 scattered table rows and ~20 passes of arithmetic over its
        values, and torch's CPU ops cost 5-10 microseconds a call (a coarse pyramid level has 4,000 points),
        numpy's about one. Pieces of 4,096 points (to keep the gathered corners in a 512 KiB L2) measured slower
        in the tracker than 32,768: more calls, and two tracker threads wait for each other's GIL between them
        (kitchen frames, 2-core AMD EPYC). Cells and fractions: :func:`cell_rows`."""
        table, offsets, origin, strides, lo, hi = self._np
        q = points.detach().numpy().T  # (3, N)
        n = q.shape[1]
        vals = np.empty((4, n), dtype=np.float32)
        valid = np.empty(n, dtype=bool)
        inv = np.float32(1.0 / self.voxel_size)
        for a in range(0, n, _CPU_POINTS):
            b = min(n, a + _CPU_POINTS)
            c, u = cell_rows(q[:, a:b], origin, inv, lo, hi, valid[a:b])
            # exact in float32 while every index is below 2^24 (a 256^3 volume), float64 beyond
            base = (strides @ c).astype(np.intp)
            corners = np.take(table, np.add.outer(offsets, base).reshape(-1), axis=0)
            trilinear_rows(corners, u, vals[:, a:b])
        if self._has_nan:
            valid &= np.isfinite(vals).all(axis=0)
            vals[:, ~valid] = 0.0
        return torch.from_numpy(vals), torch.from_numpy(valid)

    def sample(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Distances ``(N,)`` metres and validity ``(N,)`` at world points ``(N, 3)`` metres (see
        :class:`~sdfcodec.tracking.tracker.FieldSampler`); validity uses the same bounds as :meth:`sample_with_gradient`."""
        p = self._check_points(points)
        if self._rows:
            vals, valid = self._lookup_rows(p)
            return vals[0], valid
        base, frac, valid = self._cells(p, self._lo, self._hi)
        d = self._interp(base, frac, self._table)[:, 0]
        if self._has_nan:
            valid = valid & torch.isfinite(d)
            d = torch.where(valid, d, torch.zeros_like(d))
        return d, valid

    def sample_with_gradient(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Distances ``(N,)``, gradients ``(N, 3)`` (world frame, per metre) and validity ``(N,)`` at world
        points ``(N, 3)`` metres (see :class:`~sdfcodec.tracking.tracker.FieldSampler`). Where not valid the outputs are
        finite but meaningless."""
        p = self._check_points(points)
        if self.backend == "grid_sample":
            u = (p - self._origin_t.t()) * (1.0 / self.voxel_size)
            i0f = torch.floor(u)
            ok = torch.clamp(i0f, self._lo_t, self._hi_t) == i0f
            valid = ok[:, 0] & ok[:, 1] & ok[:, 2]
            # grid_sample's last grid axis indexes the input's last dimension: (z, y, x) order, in [-1, 1]
            g = (u.flip(1) * self._grid_scale - 1.0).reshape(1, 1, 1, -1, 3)
            out = torch.nn.functional.grid_sample(self._grid_volume, g, mode="bilinear", padding_mode="border",
                                                  align_corners=True)
            vals = torch.where(valid, out.reshape(4, -1), 0.0)
        elif self._rows:
            vals, valid = self._lookup_rows(p)
            return vals[0], vals[1:].t(), valid
        elif self.precompute_gradient:
            base, frac, valid = self._cells(p, self._lo, self._hi)
            vals = self._interp(base, frac, self._table, channel_major=True)  # (4, N)
        else:
            # central differences of the trilinear field, one voxel each way: 7 lookups of the values
            _, _, valid = self._cells(p, self._lo, self._hi)
            h = self.voxel_size
            shifts = torch.tensor([[0, 0, 0], [h, 0, 0], [-h, 0, 0], [0, h, 0], [0, -h, 0], [0, 0, h], [0, 0, -h]],
                                  dtype=p.dtype, device=p.device)
            stacked = (p[None] + shifts[:, None]).reshape(-1, 3)
            # the +-1 voxel lookups may use the border voxels: clamp to the whole volume there
            base, frac, _ = self._cells(stacked, self._lo0, self._hi0)
            v = self._interp(base, frac, self._table)[:, 0].reshape(7, -1)
            inv2h = 1.0 / (2.0 * h)
            vals = torch.stack([v[0], (v[1] - v[2]) * inv2h, (v[3] - v[4]) * inv2h, (v[5] - v[6]) * inv2h])
        if self._has_nan:
            valid = valid & torch.isfinite(vals).all(dim=0)
            vals = torch.where(valid, vals, torch.zeros_like(vals))
        # (4, N) rows: the gradient goes out as an (N, 3) view whose transpose is contiguous
        return vals[0], vals[1:].t(), valid
