"""The SDF Tracker: camera pose from a depth image against a TSDF map (Canelhas et al., IROS 2013).

The paper scores every codec by how well this tracker follows the camera in the decoded map (section IV-C).
The tracker needs only two things from a map: the distance ``D(q)`` at world points ``q`` and its gradient
``grad D(q)``. They come through the small :class:`FieldSampler` protocol, so the same tracker runs on a
dense volume (:class:`DenseField`) or on a compressed map whose blocks are decoded lazily.

Method (one depth frame):

1. Back-project the depth pixels to camera-frame points ``p = z ((u - cx) / fx, (v - cy) / fy, 1)`` (OpenCV
   camera frame: x right, y down, z forward; ``z`` is depth along the optical axis, not range along the ray).
2. With the camera-to-world pose ``T = [R, t]``, each point lands at ``q = R p + t``. The cost is
   ``E(T) = sum_i w_i D(q_i)^2``: a point on a surface has distance zero.
3. Gauss-Newton on a twist ``xi = (v, w)`` in se(3) (``v`` metres, ``w`` a rotation vector in radians) applied
   on the right, ``T <- T exp(xi)``, i.e. an increment expressed in the camera frame. The Jacobian of
   ``D(q_i)`` is ``J_i = [g_i^T, (p_i x g_i)^T]`` with ``g_i = R^T grad D(q_i)`` (the gradient in the camera
   frame). Each step solves ``(H + lambda I) xi = -b`` with ``H = sum w J^T J / n``, ``b = sum w J^T D / n``
   (``n`` the number of inliers, so the fixed damping ``lambda`` is independent of the image size).
4. Weights ``w_i`` are Huber weights of the residual ``D(q_i)`` (1 up to ``huber_delta``, then
   ``huber_delta / |D|``) times validity: a point counts only where the field and its gradient are defined
   (inside the volume with every voxel the central differences touch, finite values), it is not on a
   truncation plateau (``d_min + margin < D < d_max - margin``: in the free-space plateau the gradient is zero
   and the distance says nothing), the gradient is not vanishing (``|grad D| >= min_gradient_norm``; a true
   distance field has ``|grad D| = 1``), and optionally ``|D| <= max_distance``.
5. Coarse to fine: pixel strides 4, 2, 1 with at most 12, 8 and 2 iterations; a level stops early when the
   update norm ``|xi|`` drops below ``1e-4``. The strides are scaled to the image (``max_pixels``): at most
   76,800 points at the finest level, so 320x240 images run 4/2/1 and 640x480 ones 8/4/2.

The field's gradient is :class:`~sdfcodec.tracking.densefield.DenseField`'s business (see that module).

Speed (CPU): points are evaluated in chunks of 32768 laid out as ``(3, n)`` rows, so every elementwise op
runs over contiguous memory and the temporaries stay below glibc's mmap threshold (fresh multi-megabyte
buffers would be page-faulted on every op); the chunks of one iteration are shared among ``threads`` Python
threads (torch releases the GIL inside its kernels) with torch's own intra-op threads set to 1 meanwhile.
torch's OpenMP threading of the same small ops degrades badly as soon as anything else wants a core (on a
busy 2-core VM: median 2.5 s against 56 ms per 640x480 frame for the chunk threads). On the CPU each chunk is
worked through in numpy (``_chunk_terms_cpu``, with DenseField's numpy lookup): numpy's calls cost about a
microsecond against torch's 5-10 (zero-copy views of the torch tensors either way); the trilinear gather is
numpy's ``take``, several times faster than ``index_select``. On CUDA the whole image is one chunk of torch ops
and everything stays on the device except the 7x7 normal equations.
Each point costs one gather (its cell's 8 corners of the field's value-and-gradient table) and a fixed
number of whole-chunk tensor ops on contiguous ``(k, n)`` rows; there is no per-point Python. The Jacobian
rows are formed in the world frame (``[grad D, (R p) x grad D]``, the cross product as two ops on shifted
row windows) and the ``(7, n) x (n, 7)`` product is rotated into the camera frame once per iteration, on the
7x7 sums, instead of rotating every point's gradient. Chunks are split evenly over the threads once each
thread gets at least 16,384 points (smaller levels stay on one thread: their ops are too short to be worth
handing the GIL back and forth). Where the time went at 640x480 (7-Scenes redkitchen,
before ``max_pixels``): the stride-1 level was two thirds of the point evaluations for under 0.3% of the ATE.

    field = DenseField(tsdf, voxel_size=0.02, origin=(0, 0, 0))
    tracker = SDFTracker(field, (585.0, 585.0, 320.0, 240.0))
    result = tracker.track(depth, initial_pose)            # depth (H, W) metres, pose (4, 4) camera-to-world
    seq = tracker.track_sequence(depth_frames, start_pose)  # seq.poses (N, 4, 4)
"""

from __future__ import annotations

import math
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager, nullcontext
from dataclasses import dataclass, field as dc_field
from typing import Any, Iterable, Protocol, runtime_checkable

import numpy as np
import torch
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from .densefield import DenseField
from ..errors import DTypeError, InvalidValueError, ShapeError
from ..core.geometry import orthonormality_error, se3_exp
from ..core.tiling import one_blas_thread

__all__ = [
    "FieldSampler",
    "DenseField",
    "CameraIntrinsics",
    "TrackerConfig",
    "TrackingResult",
    "TrackedSequence",
    "SDFTracker",
    "backproject",
    "se3_exp",
]


# ---------------------------------------------------------------------------------------------- the map side
@runtime_checkable
class FieldSampler(Protocol):
    """What the tracker needs from a map: a truncated signed distance field it can sample at world points.

    Implementations: :class:`~sdfcodec.tracking.densefield.DenseField` (a dense voxel volume) and
    :class:`~sdfcodec.tracking.mapfield.MapField` (a compressed map decoding blocks lazily into an LRU cache of decoded
    blocks) implement the same four members. The tracker calls
    :meth:`sample_with_gradient` once per chunk of at most ``TrackerConfig.chunk_size`` points per
    Gauss-Newton iteration, possibly from several threads at once (``TrackerConfig.threads``), with points
    that may be a non-contiguous view (a transposed ``(3, N)`` tensor): implementations must accept any
    strides and be thread-safe, or the tracker must be run with ``threads=1``.

    Attributes:
        device: where :meth:`sample_with_gradient` wants its points and returns its results.
        truncation: ``(d_min, d_max)`` metres; values at ``d_max`` (``d_min``) are the free-space (solid)
            plateau where the field carries no gradient.
    """

    @property
    def device(self) -> torch.device: ...

    @property
    def truncation(self) -> tuple[float, float]: ...

    def sample(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Distances at world points.

        Args:
            points: ``(N, 3)`` float32 world coordinates in metres, on :attr:`device`.

        Returns:
            ``(values (N,) float32 metres, valid (N,) bool)``; ``values`` is arbitrary (but finite) where not
            ``valid`` (outside the map, unobserved).
        """
        ...

    def sample_with_gradient(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Distances and their gradients at world points.

        Args:
            points: ``(N, 3)`` float32 world coordinates in metres, on :attr:`device`.

        Returns:
            ``(values (N,) metres, gradients (N, 3) world frame, dimensionless (metres per metre),
            valid (N,) bool)``; ``valid`` says both the value and the gradient are defined; values and
            gradients are finite everywhere (zero where not valid is fine).
        """
        ...


# ------------------------------------------------------------------------------------------- camera, config
@dataclass(frozen=True)
class CameraIntrinsics:
    """Pinhole intrinsics in pixels: ``u = fx x / z + cx``, ``v = fy y / z + cy`` (pixel ``(u, v)`` is column
    ``u``, row ``v``; pixel centres at integer coordinates)."""

    fx: float
    fy: float
    cx: float
    cy: float

    def __post_init__(self) -> None:
        vals = (self.fx, self.fy, self.cx, self.cy)
        if not all(isinstance(v, (int, float, np.floating)) and math.isfinite(v) for v in vals):
            raise InvalidValueError(f"intrinsics must be finite numbers, got {vals}")
        if self.fx <= 0 or self.fy <= 0:
            raise InvalidValueError(f"focal lengths fx, fy must be positive pixels, got {self.fx}, {self.fy}")

    @classmethod
    def coerce(cls, intrinsics: Any) -> "CameraIntrinsics":
        """From a :class:`CameraIntrinsics`, a ``(fx, fy, cx, cy)`` sequence or a 3x3 matrix ``K``."""
        if isinstance(intrinsics, CameraIntrinsics):
            return intrinsics
        if isinstance(intrinsics, torch.Tensor):
            intrinsics = intrinsics.detach().cpu().numpy()
        a = np.asarray(intrinsics, dtype=np.float64)
        if a.shape == (3, 3):
            return cls(float(a[0, 0]), float(a[1, 1]), float(a[0, 2]), float(a[1, 2]))
        if a.shape == (4,):
            return cls(*(float(v) for v in a))
        raise ShapeError(f"intrinsics must be (fx, fy, cx, cy) or a 3x3 matrix K, got shape {a.shape}")


class TrackerConfig(BaseModel):
    """Every parameter of :class:`SDFTracker` with its default. ``strides``, ``iterations`` and ``min_update``
    are the original SDF Tracker's (``max_pixels=None`` runs its strides on any image size); the others are
    this implementation's choices, described per field.
    Invalid values raise :class:`~sdfcodec.errors.InvalidValueError`; JSON round trip with ``model_dump()`` /
    ``TrackerConfig(**d)``."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    strides: tuple[int, ...] = Field((4, 2, 1), description="pixel strides of the coarse-to-fine levels "
                                     "(every stride-th row and column of the depth image is used)")
    iterations: tuple[int, ...] = Field((12, 8, 2), description="maximum Gauss-Newton iterations per level")
    max_pixels: int | None = Field(76800, ge=1, description="the strides are multiplied by the smallest integer "
                                   "that leaves at most this many pixels (of the strided grid) at the finest level: "
                                   "the pyramid follows the number of points rather than the pixels, so 320x240 "
                                   "images run the original strides 4/2/1 and 640x480 ones 8/4/2 (on 7-Scenes at "
                                   "640x480 the stride-1 level took two thirds of the time and changed the ATE by "
                                   "under 0.3%). None: the strides as given")
    min_update: float = Field(1e-4, ge=0, description="a level stops when the twist update norm |xi| "
                              "(metres and radians together) falls below this")
    damping: float = Field(1e-4, ge=0, description="fixed Levenberg damping lambda added to the diagonal of the "
                           "normal equations, which are averaged over inliers (units of J^T J: 1 for translation)")
    huber_delta: float = Field(0.02, gt=0, description="Huber threshold on the residual D in metres: weight 1 "
                               "below it, huber_delta / |D| above")
    min_depth: float = Field(0.1, ge=0, description="depth readings below this many metres are ignored")
    max_depth: float = Field(6.0, gt=0, description="depth readings above this many metres are ignored")
    plateau_margin: float = Field(0.002, ge=0, description="metres: points with D >= d_max - margin or "
                                  "D <= d_min + margin are on (or touching) a truncation plateau and ignored")
    min_gradient_norm: float = Field(0.2, ge=0, description="points where |grad D| is below this are ignored "
                                     "(a true distance field has |grad D| = 1; 0 on the plateaus)")
    max_distance: float | None = Field(None, gt=0, description="optional cap: points with |D| above this many "
                                       "metres are ignored (None: only the plateau test)")
    max_final_update: float | None = Field(0.01, gt=0, description="a frame whose last update |xi| is still "
                                           "above this (metres and radians) has not converged: it fails, "
                                           "with a diagnostic (None: never)")
    min_inliers: int = Field(30, ge=6, description="fewer usable points than this at any iteration fails the "
                             "frame (the initial pose is returned with a diagnostic)")
    chunk_size: int | None = Field(None, ge=1024, description="points evaluated per batch: bounds the "
                                   "temporary memory (a few hundred bytes a point); None: 32768 on CPU (cache "
                                   "friendly, and below glibc's mmap threshold so buffers are reused instead "
                                   "of page-faulted afresh), 4M on GPU")
    threads: int | None = Field(None, ge=1, description="CPU only: threads that evaluate point chunks in "
                                "parallel (this one plus threads - 1 workers); while they run, torch's "
                                "intra-op threads are set to 1 and restored afterwards, so the two never "
                                "oversubscribe the cores. None: torch.get_num_threads(). 1: no workers "
                                "(torch's own intra-op parallelism as configured)")
    constant_velocity: bool = Field(False, description="track_sequence: predict each frame's initial pose by "
                                    "repeating the previous frame-to-frame motion, instead of the previous pose")

    def __init__(self, **data: Any) -> None:
        try:
            super().__init__(**data)
        except ValidationError as e:
            first = e.errors()[0]
            loc = ".".join(str(p) for p in first["loc"]) or "(config)"
            if first["type"] == "extra_forbidden":
                raise InvalidValueError(f"TrackerConfig has no field {loc!r}; the fields are "
                                        f"{', '.join(type(self).model_fields)}") from e
            raise InvalidValueError(f"invalid TrackerConfig field {loc}: {first['msg']} "
                                    f"({e.error_count()} problem(s) in all)") from e

    @model_validator(mode="after")
    def _consistent(self) -> "TrackerConfig":
        if not self.strides or len(self.strides) != len(self.iterations):
            raise ValueError(f"strides {self.strides} and iterations {self.iterations} must be non-empty and of "
                             "the same length (one entry per level)")
        if any(s < 1 for s in self.strides) or any(i < 0 for i in self.iterations):
            raise ValueError("strides must be >= 1 and iterations >= 0")
        if not self.min_depth < self.max_depth:
            raise ValueError(f"min_depth ({self.min_depth}) must be below max_depth ({self.max_depth})")
        return self


@dataclass(frozen=True)
class TrackingResult:
    """The outcome of :meth:`SDFTracker.track`.

    Attributes:
        pose: ``(4, 4)`` camera-to-world estimate; same type as the initial pose (numpy float64, or a tensor
            with the initial pose's dtype and device). On failure: the initial pose, unchanged.
        success: False when the frame could not be tracked (too few usable points, a non-finite solve, or
            no convergence: the last update above ``max_final_update``).
        message: what happened, in words (why it failed, or a convergence summary).
        iterations: Gauss-Newton iterations run, all levels together.
        iterations_per_level: iterations run at each level (coarse to fine).
        residual: RMS of ``D`` (metres) over the inliers at the last evaluation (the pose before the last,
            small, update); ``inf`` if no point was usable.
        inliers: usable points at the last evaluation.
        points: back-projected depth points (valid readings) at the last level evaluated.
        update_norm: ``|xi|`` of the last update.
        conditioning: smallest / largest eigenvalue of the last (undamped) ``H``; near 0 means the geometry
            leaves some motion unconstrained (e.g. only one plane in view).
    """

    pose: Any
    success: bool
    message: str
    iterations: int
    iterations_per_level: tuple[int, ...]
    residual: float
    inliers: int
    points: int
    update_norm: float
    conditioning: float

    @property
    def inlier_ratio(self) -> float:
        """``inliers / points`` (0 when there were no points)."""
        return self.inliers / self.points if self.points else 0.0


@dataclass
class TrackedSequence:
    """The outcome of :meth:`SDFTracker.track_sequence`.

    Attributes:
        poses: ``(N, 4, 4)`` float64 numpy camera-to-world poses, one per frame.
        results: the per-frame :class:`TrackingResult` (``None`` for an untracked first frame).
    """

    poses: np.ndarray
    results: list = dc_field(default_factory=list)

    @property
    def failures(self) -> list[int]:
        """Indices of the frames that failed to track."""
        return [i for i, r in enumerate(self.results) if r is not None and not r.success]

    def to_trajectory(self, timestamps: Any = None):
        """The poses as a :class:`sdfcodec.core.trajectory.Trajectory` (timestamps ``(N,)`` seconds; default
        ``0, 1, 2, ...``), ready for :func:`sdfcodec.core.metrics.ate`."""
        from ..core.trajectory import Trajectory

        return Trajectory.from_poses(self.poses, timestamps)


# ------------------------------------------------------------------------------------------ back-projection
def backproject(depth: torch.Tensor, intrinsics: Any, stride: int = 1, min_depth: float = 0.0,
                max_depth: float = math.inf) -> torch.Tensor:
    """Camera-frame points ``(N, 3)`` metres of the valid pixels of ``depth`` ``(H, W)`` metres, every
    ``stride``-th row and column starting at pixel (0, 0) (OpenCV frame: x right, y down, z forward), in
    row-major pixel order. Readings that are not finite or outside ``(min_depth, max_depth)`` are dropped.
    Device follows ``depth``; float32. The result is a transposed view of a contiguous ``(3, N)`` tensor."""
    k = CameraIntrinsics.coerce(intrinsics)
    if not isinstance(depth, torch.Tensor):
        depth = torch.as_tensor(np.asarray(depth, dtype=np.float32))
    if depth.ndim != 2:
        raise ShapeError(f"depth must have shape (H, W) in metres, got {tuple(depth.shape)}")
    if not (isinstance(stride, int) and stride >= 1):
        raise InvalidValueError(f"stride must be an integer >= 1, got {stride!r}")
    return _backproject(depth.to(torch.float32), k, stride, min_depth, max_depth, {}).t()


def _ray_factors(k: CameraIntrinsics, h: int, w: int, stride: int, device: torch.device, cache: dict
                 ) -> tuple[torch.Tensor, torch.Tensor]:
    """Per pixel of the strided grid (h * w,), row-major: ``(u - cx) / fx`` and ``(v - cy) / fy``."""
    key = (h, w, stride, device)
    if key not in cache:
        u = (np.arange(w, dtype=np.float64) * stride - k.cx) / k.fx
        v = (np.arange(h, dtype=np.float64) * stride - k.cy) / k.fy
        rx = torch.from_numpy(np.tile(u, h).astype(np.float32)).to(device)
        ry = torch.from_numpy(np.repeat(v, w).astype(np.float32)).to(device)
        cache[key] = (rx, ry)
    return cache[key]


def _backproject(depth: torch.Tensor, k: CameraIntrinsics, stride: int, min_depth: float, max_depth: float,
                 cache: dict) -> torch.Tensor:
    """``(3, N)`` contiguous float32 camera-frame points of the valid strided pixels of ``depth`` (H, W)."""
    z = depth[::stride, ::stride]
    h, w = z.shape
    rx, ry = _ray_factors(k, h, w, stride, depth.device, cache)
    if depth.device.type == "cpu":  # numpy's flatnonzero / take are several times faster here
        zn = np.ascontiguousarray(z.numpy()).reshape(-1)
        with np.errstate(invalid="ignore"):
            idx = np.flatnonzero((zn > min_depth) & (zn < max_depth))  # NaN compares False
        out = np.empty((3, len(idx)), dtype=np.float32)
        np.take(zn, idx, out=out[2])
        np.multiply(np.take(rx.numpy(), idx), out[2], out=out[0])
        np.multiply(np.take(ry.numpy(), idx), out[2], out=out[1])
        return torch.from_numpy(out)
    zf = z.reshape(-1)
    idx = ((zf > min_depth) & (zf < max_depth)).nonzero().squeeze(1)
    zz = zf[idx]
    return torch.stack([rx[idx] * zz, ry[idx] * zz, zz])


# --------------------------------------------------------------------------------------------------- tracker
#: a level is shared among the threads only when each gets at least this many points: below it the ~50 torch
#: calls a chunk are short and the threads spend their time handing the GIL to each other (2 threads on
#: 100 kitchen frames: 37.5 ms of CPU a frame with this bound against 43.8 ms with 1,024; one thread: 34.4)
_MIN_POINTS_PER_THREAD = 16384


def _split(pts: torch.Tensor, chunk: int, workers: int) -> list[torch.Tensor]:
    """``pts`` (3, N) as column slices (rows stay contiguous) of at most ``chunk`` points, their number a
    multiple of ``workers`` and their sizes equal to within one, so that every worker gets the same share
    (a level smaller than one chunk still runs on every core) once each worker gets at least
    ``_MIN_POINTS_PER_THREAD`` points; smaller levels stay in as few chunks as ``chunk`` allows."""
    npts = pts.shape[1]
    n = max(1, -(-npts // chunk))
    n = -(-n // workers) * workers if npts >= _MIN_POINTS_PER_THREAD * workers else n
    size = -(-npts // n) if npts else 1
    return [pts[:, i:i + size] for i in range(0, max(npts, 1), size)]


def _stride_scale(shape: tuple[int, int], finest: int, max_pixels: int | None) -> int:
    """The smallest integer ``s >= 1`` with at most ``max_pixels`` pixels on the ``(H, W)`` grid strided by
    ``finest * s`` (1 when ``max_pixels`` is None)."""
    if max_pixels is None:
        return 1
    h, w = shape
    s = 1
    while -(-h // (finest * s)) * -(-w // (finest * s)) > max_pixels:
        s += 1
    return s


def _conditioning(h: np.ndarray | None) -> float:
    """Smallest over largest eigenvalue of the (undamped) normal matrix ``h`` (0 when there is none)."""
    if h is None:
        return 0.0
    ev = np.linalg.eigvalsh(h)
    return float(ev[0] / ev[-1]) if ev[-1] > 0 else 0.0


@contextmanager
def _intra_op_threads(n: int | None):
    """Temporarily set torch's intra-op thread count (None: leave it)."""
    if n is None:
        yield
        return
    prev = torch.get_num_threads()
    if prev != n:
        torch.set_num_threads(n)
    try:
        yield
    finally:
        if prev != n:
            torch.set_num_threads(prev)


class SDFTracker:
    """Track depth frames against a :class:`FieldSampler` (see the module docstring for the method).

    Args:
        field: the map, e.g. a :class:`DenseField`; computation runs on ``field.device``.
        intrinsics: :class:`CameraIntrinsics`, ``(fx, fy, cx, cy)`` or a 3x3 ``K`` (pixels) of the depth
            images.
        config: :class:`TrackerConfig` (default: the original tracker's settings), or a dict of its fields.
    """

    def __init__(self, field: FieldSampler, intrinsics: Any, config: TrackerConfig | dict | None = None) -> None:
        if not isinstance(field, FieldSampler):
            raise InvalidValueError(f"field must implement FieldSampler (device, truncation, sample, "
                                    f"sample_with_gradient), got {type(field).__name__}")
        self.field = field
        self.intrinsics = CameraIntrinsics.coerce(intrinsics)
        if config is None:
            config = TrackerConfig()
        elif isinstance(config, dict):
            config = TrackerConfig(**config)
        elif not isinstance(config, TrackerConfig):
            raise InvalidValueError(f"config must be a TrackerConfig or a dict of its fields, got "
                                    f"{type(config).__name__}")
        self.config = config
        self._pool: ThreadPoolExecutor | None = None
        self._rays: dict = {}  # cached per-pixel ray factors, by image size and stride
        self._pool_size = 0

    # -- inputs
    def _depth(self, depth: Any) -> torch.Tensor:
        dev = self.field.device
        if isinstance(depth, torch.Tensor):
            if not depth.is_floating_point():
                raise DTypeError(f"depth must be floating point metres, got {depth.dtype}; convert raw sensor "
                                 "units first (e.g. depth_mm.float() / 1000)")
            d = depth.detach().to(device=dev, dtype=torch.float32)
        else:
            a = np.asarray(depth)
            if a.dtype.kind != "f":
                raise DTypeError(f"depth must be floating point metres, got dtype {a.dtype}; convert raw sensor "
                                 "units first (e.g. depth_mm / 1000.0)")
            d = torch.from_numpy(np.ascontiguousarray(a, dtype=np.float32)).to(dev)
        if d.ndim != 2:
            raise ShapeError(f"depth must have shape (H, W) in metres, got {tuple(d.shape)}")
        return d

    @staticmethod
    def _pose(pose: Any, name: str = "initial_pose") -> np.ndarray:
        if isinstance(pose, torch.Tensor):
            pose = pose.detach().cpu().numpy()
        p = np.asarray(pose, dtype=np.float64)
        if p.shape != (4, 4):
            raise ShapeError(f"{name} must be a (4, 4) camera-to-world matrix, got shape {p.shape}")
        if not np.all(np.isfinite(p)):
            raise InvalidValueError(f"{name} holds NaN or infinite values")
        r = p[:3, :3]
        if orthonormality_error(r) > 1e-3 or np.linalg.det(r) < 0:
            raise InvalidValueError(f"{name}'s rotation part is not a rotation (R^T R != I or det < 0)")
        return p

    @staticmethod
    def _like(pose: np.ndarray, template: Any) -> Any:
        if isinstance(template, torch.Tensor):
            dt = template.dtype if template.is_floating_point() else torch.float64
            return torch.as_tensor(pose, dtype=dt, device=template.device)
        return pose.copy()

    # -- one evaluation of the normal equations
    def _chunk_terms(self, chunks: list[torch.Tensor], r5: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        """Sums over the points of ``chunks`` (each (3, n) camera frame) as one (9, 8) matrix
        ``[w J; m D; m] @ [1, J]^T`` with the world-frame rows ``J = [(R p) x grad D (3), D, grad D (3)]``,
        Huber weights ``w`` and the inlier mask ``m``: ``[:7, 1:]`` is ``sum w J J^T``, ``[7, 4]`` the sum of
        ``D^2`` over the inliers and ``[8, 0]`` their number. One product gives all three (fewer ops a chunk:
        the coarse levels' few thousand points are dominated by the per-op cost). ``r5`` is R's rows
        0, 1, 2, 0, 1 (so ``r5 @ p`` holds the shifted rows the cross product needs).
        :meth:`_normal_equations` turns the world-frame rows into the camera frame's Jacobian afterwards
        (``[R^T g, p x R^T g] = diag(R^T, R^T) [g, R p x g]``), on the sums instead of on every point."""
        cfg = self.config
        dev = r5.device
        d_min, d_max = self.field.truncation
        lo, hi = d_min + cfg.plateau_margin, d_max - cfg.plateau_margin
        g2 = cfg.min_gradient_norm ** 2
        r = r5[:3]
        acc = None
        for p in chunks:  # p: (3, n) camera-frame points, each row contiguous
            n = p.shape[1]
            q = torch.addmm(t, r, p)  # (3, n) world points; q.t() is the (N, 3) the protocol asks for
            d, g, valid = self.field.sample_with_gradient(q.t())
            # every op below runs on whole contiguous rows (DenseField hands g out as a view of (3, n) rows).
            # a: [1, (R p) x g (3), D, g (3), g_x, g_y]; the repeated g_x, g_y make the cross product two ops
            # on shifted 3-row windows
            a = torch.empty((10, n), dtype=torch.float32, device=dev)
            a[0].fill_(1.0)
            a[4].copy_(d)
            a[5:8].copy_(g.t())
            a[8:10].copy_(a[5:7])
            rp = torch.mm(r5, p)  # R p, rows x, y, z, x, y: the lever arm in the world frame
            torch.mul(rp[1:4], a[7:10], out=a[1:4]).addcmul_(rp[2:5], a[6:9], value=-1.0)  # (R p) x g
            gsq = torch.mul(a[5], a[5]).addcmul_(a[6], a[6]).addcmul_(a[7], a[7])  # |g|^2
            mask = (d < hi) & (d > lo)
            mask &= valid
            mask &= gsq >= g2
            ad = d.abs()
            if cfg.max_distance is not None:
                mask &= ad <= cfg.max_distance
            left = torch.empty((9, n), dtype=torch.float32, device=dev)
            m = left[8]
            m.copy_(mask)
            torch.mul(m, d, out=left[7])
            # Huber weight: 1 up to delta, delta / |D| beyond; 0 for unusable points
            w = torch.div(m, ad.clamp_min_(cfg.huber_delta)).mul_(cfg.huber_delta)
            torch.mul(a[1:8], w, out=left[:7])
            part = torch.mm(left, a[:8].t())
            acc = part if acc is None else acc.add_(part)
        return acc

    def _chunk_terms_cpu(self, chunks: list[torch.Tensor], r5: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        """:meth:`_chunk_terms` on the CPU, in numpy: the same sums, added up in float64 over the chunks.
        numpy's calls cost about a microsecond against torch's 5-10, and the coarse levels' few thousand points
        a chunk are dominated by the per-call cost. Whole chunks, not cache-sized pieces of them: pieces of
        4,096 points measured 0.86x of the torch ops on kitchen frames (more short calls, whose Python part
        holds the GIL the other thread waits for), whole chunks 1.2-1.3x (2-core AMD EPYC)."""
        cfg = self.config
        d_min, d_max = self.field.truncation
        lo, hi = d_min + cfg.plateau_margin, d_max - cfg.plateau_margin
        g2 = cfg.min_gradient_norm ** 2
        r5n, tn = r5.numpy(), t.numpy()
        acc = np.zeros((9, 8))
        for chunk in chunks:
            p = chunk.numpy()
            n = p.shape[1]
            rp = r5n @ p  # R p, rows x, y, z, x, y: the lever arm in the world frame
            q = rp[:3] + tn  # (3, n) world points
            # any FieldSampler's tensors (CPU, any float dtype) as numpy arrays; DenseField's are views already
            d, g, valid = (x.detach().numpy() for x in self.field.sample_with_gradient(torch.from_numpy(q).t()))
            a = np.empty((10, n), dtype=np.float32)  # as in _chunk_terms: [1, (R p) x g, D, g, g_x, g_y]
            a[0] = 1.0
            a[4] = d
            a[5:8] = g.T
            a[8:10] = a[5:7]
            np.multiply(rp[1:4], a[7:10], out=a[1:4])
            a[1:4] -= rp[2:5] * a[6:9]
            gsq = a[5] * a[5]
            gsq += a[6] * a[6]
            gsq += a[7] * a[7]
            mask = d < hi
            mask &= d > lo
            mask &= valid
            mask &= gsq >= g2
            ad = np.abs(d)
            if cfg.max_distance is not None:
                mask &= ad <= cfg.max_distance
            left = np.empty((9, n), dtype=np.float32)
            left[8] = mask
            np.multiply(left[8], d, out=left[7])
            w = np.maximum(ad, cfg.huber_delta, out=ad)  # Huber weight: delta / max(|D|, delta), 0 where unusable
            np.divide(left[8], w, out=w)
            w *= cfg.huber_delta
            np.multiply(a[1:8], w, out=left[:7])
            acc += left @ a[:8].T
        return torch.from_numpy(acc)

    def _normal_equations(self, chunks: list[torch.Tensor], pose: np.ndarray, workers: int
                          ) -> tuple[np.ndarray, np.ndarray, int, float]:
        """``(H (6, 6), b (6,), inliers, sum of D^2 over inliers)`` at ``pose``, summed over all chunks, with
        ``J = [g, p x g]`` in the camera frame (``g = R^T grad D``)."""
        dev = chunks[0].device
        r5 = torch.as_tensor(pose[[0, 1, 2, 0, 1], :3], dtype=torch.float32, device=dev)
        t = torch.as_tensor(pose[:3, 3], dtype=torch.float32, device=dev).reshape(3, 1)
        terms = self._chunk_terms_cpu if dev.type == "cpu" else self._chunk_terms
        if workers > 1 and len(chunks) > 1:
            pool = self._get_pool(workers)
            parts = [chunks[i::workers] for i in range(workers)]
            futures = [pool.submit(terms, part, r5, t) for part in parts[1:] if part]
            acc = terms(parts[0], r5, t)  # this thread takes a share too
            for fut in futures:
                acc = acc + fut.result()
        else:
            acc = terms(chunks, r5, t)
        sums = acc.to(torch.float64).cpu().numpy()
        full = sums[:7, 1:]  # rows/columns: (R p) x g_world (3), D, g_world (3)
        rot = np.zeros((6, 7))  # the camera frame's J = [R^T g, R^T ((R p) x g)] from the world-frame rows
        rot[0:3, 4:7] = rot[3:6, 0:3] = pose[:3, :3].T
        return rot @ full @ rot.T, rot @ full[:, 3], int(round(sums[8, 0])), float(sums[7, 4])

    def _get_pool(self, workers: int) -> ThreadPoolExecutor:
        if self._pool is None or self._pool_size != workers - 1:
            if self._pool is not None:
                self._pool.shutdown(wait=False)
            self._pool = ThreadPoolExecutor(max_workers=workers - 1, thread_name_prefix="sdf-tracker")
            self._pool_size = workers - 1
        return self._pool

    def __enter__(self) -> "SDFTracker":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def close(self) -> None:
        """Stop the worker threads (if ``config.threads > 1`` started any); the tracker stays usable."""
        if self._pool is not None:
            self._pool.shutdown(wait=True)
            self._pool = None

    # -- public
    def track(self, depth: Any, initial_pose: Any) -> TrackingResult:
        """Estimate the camera-to-world pose of one depth frame.

        Args:
            depth: ``(H, W)`` depth in metres (numpy or torch, any device; moved to the field's device);
                0, negative, NaN or out-of-range readings are ignored.
            initial_pose: ``(4, 4)`` camera-to-world starting guess (numpy or torch).

        Returns:
            :class:`TrackingResult`; ``result.pose`` has the type, dtype and device of ``initial_pose``. A frame
            that cannot be tracked returns ``success=False`` with the initial pose and a message, never NaN.

        Raises:
            ShapeError, DTypeError, InvalidValueError: malformed inputs (wrong shapes, integer depth, a
            non-finite or non-rigid pose).
        """
        d = self._depth(depth)
        pose0 = self._pose(initial_pose)
        workers = self._workers(d.device)
        # on the CPU numpy's BLAS (the chunks' small products) stays on one thread too: OpenBLAS's own threads
        # spin after each call, on the core the other chunk thread (or the next op) needs
        blas = one_blas_thread() if d.device.type == "cpu" else nullcontext()
        with _intra_op_threads(1 if workers > 1 else None), blas:
            return self._track(d, pose0, initial_pose, workers)

    def _workers(self, device: torch.device) -> int:
        if device.type != "cpu":
            return 1
        n = self.config.threads
        return torch.get_num_threads() if n is None else n

    def _track(self, d: torch.Tensor, pose0: np.ndarray, initial_pose: Any, workers: int) -> TrackingResult:
        cfg = self.config
        pose = pose0.copy()
        per_level: list[int] = []
        total = 0
        residual, inliers, npts, unorm = math.inf, 0, 0, 0.0
        eye6 = np.eye(6)
        chunk = cfg.chunk_size or (32768 if d.device.type == "cpu" else 1 << 22)
        h_last = None  # the last finite, normalised H: its conditioning is reported (computed once, at the end)
        scale = _stride_scale(d.shape, cfg.strides[-1], cfg.max_pixels)
        for stride, iters in zip((s * scale for s in cfg.strides), cfg.iterations):
            pts = _backproject(d, self.intrinsics, stride, cfg.min_depth, cfg.max_depth, self._rays)  # (3, N)
            npts = pts.shape[1]
            chunks = _split(pts, chunk, workers)
            done = 0
            for _ in range(iters):
                if npts < cfg.min_inliers:
                    return self._fail(initial_pose, per_level + [done], total, residual, 0, npts, unorm, h_last,
                                      f"only {npts} valid depth readings at stride {stride} (need "
                                      f"{cfg.min_inliers}); is the depth in metres and within "
                                      f"({cfg.min_depth}, {cfg.max_depth}) m?")
                h, b, inliers, sq = self._normal_equations(chunks, pose, workers)
                if not (np.all(np.isfinite(h)) and np.all(np.isfinite(b)) and math.isfinite(sq)):
                    return self._fail(initial_pose, per_level + [done], total, residual, inliers, npts, unorm,
                                      h_last, "the map returned non-finite distances or gradients (FieldSampler "
                                      "outputs must be finite everywhere, also where not valid)")
                if inliers < cfg.min_inliers:
                    return self._fail(initial_pose, per_level + [done], total, residual, inliers, npts, unorm,
                                      h_last, f"only {inliers} of {npts} depth points at stride {stride} fall where "
                                      f"the map is usable (inside the volume, off the truncation plateaus, "
                                      f"need {cfg.min_inliers}); the pose is probably far off the map or lost")
                residual = math.sqrt(sq / inliers)
                h /= inliers
                b /= inliers
                h_last = h
                try:
                    xi = -np.linalg.solve(h + cfg.damping * eye6, b)
                except np.linalg.LinAlgError:
                    xi = np.full(6, np.nan)
                if not np.all(np.isfinite(xi)):
                    return self._fail(initial_pose, per_level + [done], total, residual, inliers, npts, unorm,
                                      h_last, "the Gauss-Newton step is not finite (singular normal equations); "
                                      "raise damping or check the map for NaN")
                pose = pose @ se3_exp(xi)
                unorm = float(np.linalg.norm(xi))
                done += 1
                total += 1
                if unorm < cfg.min_update:
                    break
            per_level.append(done)
        if cfg.max_final_update is not None and unorm > cfg.max_final_update:
            return self._fail(initial_pose, per_level, total, residual, inliers, npts, unorm, h_last,
                              f"did not converge: the last update was |xi| = {unorm:.3g} (> max_final_update "
                              f"{cfg.max_final_update}), residual {residual * 1000:.1f} mm, {inliers}/{npts} "
                              "inliers; the initial pose is probably too far from the truth for the "
                              "truncation distance")
        # re-orthonormalise the rotation against drift from many compositions
        u, _, vt = np.linalg.svd(pose[:3, :3])
        pose[:3, :3] = u @ vt
        cond = _conditioning(h_last)
        msg = (f"tracked: {total} iterations {tuple(per_level)}, {inliers}/{npts} inliers, "
               f"residual {residual * 1000:.2f} mm, last update {unorm:.2e}")
        return TrackingResult(self._like(pose, initial_pose), True, msg, total, tuple(per_level), residual,
                              inliers, npts, unorm, cond)

    def _fail(self, initial_pose, per_level, total, residual, inliers, npts, unorm, h_last, msg) -> TrackingResult:
        cond = _conditioning(h_last)
        pose0 = self._pose(initial_pose)
        return TrackingResult(self._like(pose0, initial_pose), False, msg, total, tuple(per_level), residual,
                              inliers, npts, unorm, cond)

    def track_sequence(self, depths: Iterable[Any], start_pose: Any, *, track_first: bool = True,
                       constant_velocity: bool | None = None, stop_on_failure: bool = False) -> TrackedSequence:
        """Track a sequence of depth frames, each initialised from the previous estimate.

        Args:
            depths: iterable of ``(H, W)`` depth images in metres (a list, a generator, an ``(N, H, W)``
                array...).
            start_pose: ``(4, 4)`` camera-to-world pose of the first frame (e.g. from ground truth).
            track_first: refine the first frame from ``start_pose`` (default) or take ``start_pose`` as is.
            constant_velocity: predict each frame by repeating the last frame-to-frame motion (default:
                ``config.constant_velocity``).
            stop_on_failure: stop at the first frame that fails; otherwise a failed frame keeps its
                initial (predicted) pose and tracking goes on from there.

        Returns:
            :class:`TrackedSequence` with ``poses`` ``(N, 4, 4)`` float64 and the per-frame results.
        """
        cv = self.config.constant_velocity if constant_velocity is None else bool(constant_velocity)
        start = self._pose(start_pose, "start_pose")
        poses: list[np.ndarray] = []
        results: list = []
        for i, depth in enumerate(depths):
            if i == 0:
                guess = start
            elif cv and len(poses) >= 2:
                guess = poses[-1] @ (np.linalg.inv(poses[-2]) @ poses[-1])
            else:
                guess = poses[-1]
            if i == 0 and not track_first:
                self._depth(depth)  # still validate the frame
                poses.append(start.copy())
                results.append(None)
                continue
            res = self.track(depth, guess)
            poses.append(np.asarray(res.pose, dtype=np.float64))
            results.append(res)
            if stop_on_failure and not res.success:
                break
        out = np.stack(poses) if poses else np.zeros((0, 4, 4))
        return TrackedSequence(out, results)
