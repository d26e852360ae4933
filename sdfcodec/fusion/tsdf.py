"""Projective TSDF fusion (Curless and Levoy 1996) of depth sequences into 16^3 blocks, with open3d.

:func:`fuse` integrates every posed depth frame of a sequence into an ``open3d.t.geometry.VoxelBlockGrid``
(attributes ``tsdf`` and ``weight``, 16^3-voxel blocks, allocated only around observed surfaces) and
returns the allocated blocks as :class:`FusedBlocks` in the project's conventions: distances in metres
truncated to ``[d_min, d_max]``, voxels indexed ``(x, y, z)``, unobserved voxels (weight 0) set to
``d_max`` (what unobserved voxels decode to, spec/map-format.md). :func:`mesh_from_blocks` turns blocks
(fused, or decoded from a map) back into a triangle mesh with open3d's marching cubes.

How open3d's symmetric truncation becomes the paper's asymmetric one
------------------------------------------------------------------
open3d computes, for a voxel at camera z-coordinate ``z_c`` projecting onto a pixel with depth ``D``, the
projective distance ``sdf = D - z_c``; it skips the voxel when ``sdf < -T`` and stores
``min(sdf, T) / T`` in ``[-1, 1]``, averaged over frames (weight +1 per update), with a single
``T = trunc_voxel_multiplier * voxel_size``. The paper truncates to ``[d_min, d_max]`` with
``|d_min| != d_max`` (-0.04 and 0.1 m by default). Fusing with ``T = max(|d_min|, d_max)`` and clipping
afterwards would also average in observations from ``0.04`` to ``0.1`` m *behind* surfaces (which the paper
never integrates: thin objects would lose their back side) and give those voxels weight.

Instead we shift the measurements: open3d is given ``D' = D - c`` with ``c = (d_max + d_min) / 2`` and
``T = (d_max - d_min) / 2``. Then ``sdf' = sdf - c`` and open3d's rules become exactly the paper's:
a voxel is skipped when ``sdf' < -T``, i.e. ``sdf < d_min``, and capped at ``sdf' = T``, i.e.
``sdf = d_max``. Because ``sdf`` is ``D - z_c`` (a difference of z-coordinates), the shift is exact for
every voxel, not an approximation. The stored value ``s = sdf' / T`` maps back as
``d = c + T s = d_min + (s + 1) / 2 (d_max - d_min)``, so ``(s + 1) / 2`` is already the codecs' normalised
value. Weights count the frames in which the voxel was at most ``|d_min|`` behind the observed surface
(and within an allocated block), as in the paper. Block allocation follows the same shifted band: blocks
are allocated along each pixel's ray from ``d_max`` in front of the measured surface to ``|d_min|`` behind
it. (With a symmetric truncation such as ``(-0.1, 0.1)`` the shift is 0 and this is plain open3d.)

What this means in practice: voxels more than ``|d_min|`` behind every observed surface are never
observed and read ``d_max`` (free), exactly like unobserved space; the distances are projective (along
the camera's z-axis), so at oblique views they overestimate the Euclidean distance away from the surface
(the zero crossing itself is unbiased); depth readings beyond ``depth_max`` are ignored.

Pixel centres: open3d's ``integrate`` reads the pixel ``(int(u), int(v))`` a voxel projects to, i.e. it
truncates where the pinhole convention of every calibration used here (OpenCV, TUM, 7-Scenes, our
renderer: pixel centres at integer coordinates) calls for rounding. That half-pixel slip moves slanted
surfaces by millimetres (-4 mm on a synthetic floor at 2 cm voxels, a fifth of a voxel), so :func:`fuse`
hands ``integrate`` the principal point shifted by half a pixel (``int(u + 0.5)`` is the nearest pixel);
block allocation uses the true calibration.

Voxel order: open3d stores a block's voxels with x varying fastest (``[z, y, x]`` in C order, voxel
``(x, y, z)`` of block key ``k`` at world ``voxel_size * (16 k + (x, y, z))``); :func:`fuse` transposes to
the project's ``(x, y, z)`` order. ``tests/test_render_fusion.py`` checks this against an analytic scene.
"""

from __future__ import annotations

import time
import warnings
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator

import numpy as np

from ..core._validate import BLOCK
from ..core.blocks import check_truncation, normalise
from ..errors import InvalidValueError, MissingDependencyError, SDFCodecWarning, ShapeError
from ..data.sequences import Frame, Intrinsics, Sequence, open_sequence

__all__ = ["FusedBlocks", "FrameFeed", "check_fusion_parameters", "fusion_input", "fuse", "mesh_from_blocks", "GRAVITY_FILE", "sequence_up", "prefetched_frames", "fusion_progress",
           "to_open3d_order", "open3d_module"]

#: 7-Scenes' gravity file: the gravity vector in the first camera's frame, three numbers.
GRAVITY_FILE = "gravity-direction.txt"


@dataclass
class FusedBlocks:
    """Allocated TSDF blocks of a fused sequence.

    Attributes
    ----------
    coords : np.ndarray
        ``(N, 3)`` int64 block indices, all >= 0, sorted in C order; block ``c`` covers voxels
        ``16 c .. 16 c + 15`` along each axis.
    tsdf : np.ndarray
        ``(N, 16, 16, 16)`` float32 metres in ``[d_min, d_max]``, voxels indexed ``(x, y, z)``; ``d_max``
        where unobserved.
    weights : np.ndarray
        ``(N, 16, 16, 16)`` float32 number of frames that updated each voxel (0 = unobserved).
    origin : np.ndarray
        ``(3,)`` float64 metres: world position of voxel (0, 0, 0) of block (0, 0, 0); voxel ``(i, j, k)``
        of block ``c`` is at ``origin + voxel_size * (16 c + (i, j, k))``.
    voxel_size : float
        Metres.
    truncation : tuple of float
        ``(d_min, d_max)`` metres.
    frames_integrated, frames_skipped : int
        Frames fused, and frames passed over (no pose).
    seconds : float
        Wall-clock time of the fusion loop (reading + integration).
    up : np.ndarray or None
        ``(3,)`` float64 unit vector, the world's up direction (minus gravity) when the sequence records its
        gravity (:func:`sequence_up`); None otherwise. ``sdfcodec fuse`` stores it in the map's header.
    """

    coords: np.ndarray
    tsdf: np.ndarray
    weights: np.ndarray
    origin: np.ndarray
    voxel_size: float
    truncation: tuple[float, float]
    frames_integrated: int = 0
    frames_skipped: int = 0
    seconds: float = 0.0
    up: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.coords.shape[0])

    @property
    def observed(self) -> np.ndarray:
        """``(N,)`` bool: blocks with at least one observed voxel (weight > 0)."""
        return self.weights.reshape(len(self), -1).max(axis=1) > 0 if len(self) else np.zeros(0, bool)

    @property
    def grid_shape(self) -> tuple[int, int, int]:
        """Blocks along each axis needed to hold every block, ``coords.max(0) + 1``."""
        return tuple(int(v) + 1 for v in self.coords.max(axis=0)) if len(self) else (0, 0, 0)  # type: ignore

    def normalised(self) -> np.ndarray:
        """``(N, 16, 16, 16)`` float32 ``v = (d - d_min) / (d_max - d_min)`` in ``[0, 1]`` (what codecs see)."""
        return normalise(self.tsdf, *self.truncation)

    def voxel_positions(self, index: int | slice | np.ndarray = slice(None)) -> np.ndarray:
        """World positions ``(n, 16, 16, 16, 3)`` float64 metres of the voxels of blocks ``index``."""
        c = np.asarray(self.coords[index]).reshape(-1, 3)
        local = np.stack(np.meshgrid(*[np.arange(BLOCK)] * 3, indexing="ij"), -1)
        return self.origin + self.voxel_size * (BLOCK * c[:, None, None, None, :] + local[None]).astype(np.float64)

    def select(self, mask: np.ndarray) -> "FusedBlocks":
        """The blocks where ``mask`` ``(N,)`` is true (same origin)."""
        m = np.asarray(mask)
        return FusedBlocks(self.coords[m], self.tsdf[m], self.weights[m], self.origin.copy(), self.voxel_size,
                           self.truncation, self.frames_integrated, self.frames_skipped, self.seconds)

    def to_dense(self) -> np.ndarray:
        """The blocks assembled into one ``(16 Bx, 16 By, 16 Bz)`` float32 volume (metres, ``d_max`` where no
        block), voxel ``(0, 0, 0)`` at :attr:`origin`. Memory grows with the bounding box, not the blocks."""
        gx, gy, gz = self.grid_shape
        vol = np.full((gx * BLOCK, gy * BLOCK, gz * BLOCK), self.truncation[1], dtype=np.float32)
        for (bx, by, bz), blk in zip(self.coords, self.tsdf):
            vol[bx * BLOCK:(bx + 1) * BLOCK, by * BLOCK:(by + 1) * BLOCK, bz * BLOCK:(bz + 1) * BLOCK] = blk
        return vol

    def mesh(self, weight_threshold: float = 0.0):
        """Triangle mesh of the zero level set (see :func:`mesh_from_blocks`), using the weights."""
        return mesh_from_blocks(self.coords, self.tsdf, origin=self.origin, voxel_size=self.voxel_size,
                                truncation=self.truncation, weights=self.weights, weight_threshold=weight_threshold)


def open3d_module():
    try:
        import open3d as o3d
    except ImportError as exc:  # open3d comes with the optional 'fusion' extra
        raise MissingDependencyError("TSDF fusion needs open3d: pip install 'sdfcodec[fusion]'") from exc
    return o3d


def prefetched_frames(seq: Sequence, ahead: int = 6) -> Iterator[Frame]:
    """Frames of ``seq`` in order, decoded by a worker thread ``ahead`` frames in advance (PNG decoding
    releases the GIL, so it overlaps with integration)."""
    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="sdfcodec-read") as pool:
        pending: deque = deque()
        nxt = 0
        try:
            while nxt < len(seq) or pending:
                while nxt < len(seq) and len(pending) < ahead:
                    pending.append(pool.submit(seq.read_frame, nxt))
                    nxt += 1
                yield pending.popleft().result()
        finally:
            for f in pending:
                f.cancel()


def fusion_progress(total: int | None):
    """A rich progress bar on stderr showing frames done and frames per second."""
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, ProgressColumn, TextColumn, TimeRemainingColumn
    from rich.text import Text

    class Rate(ProgressColumn):  # rich's speed columns are for bytes
        def render(self, task):
            speed = task.finished_speed or task.speed
            return Text("" if speed is None else f"{speed:5.1f} frames/s", style="progress.data.speed")

    progress = Progress(TextColumn("fusing"), BarColumn(), MofNCompleteColumn(), Rate(), TimeRemainingColumn(),
                        console=Console(stderr=True))
    return progress, progress.add_task("fuse", total=total)


def sequence_up(sequence: Sequence) -> np.ndarray | None:
    """The world's up direction of a sequence that records its gravity, else None.

    7-Scenes sequences may hold :data:`GRAVITY_FILE`, the gravity vector in the first frame's camera axes; with
    the first frame's camera-to-world pose ``R`` it is ``up = -R g / |g|`` in world axes (the map's grid axes:
    fusion only shifts the origin). TUM sequences record no gravity here (their accelerometer samples are not
    read), nor do frames without a file: None.

    Raises
    ------
    FormatError
        The gravity file exists but does not hold three finite numbers of non-zero length.
    """
    from ..errors import FormatError

    path = Path(sequence.path) / GRAVITY_FILE
    if not path.is_file():
        return None
    try:
        g = np.loadtxt(path, dtype=np.float64).reshape(-1)
    except ValueError as e:
        raise FormatError(f"{path}: not three numbers ({e})") from e
    if g.shape != (3,) or not np.all(np.isfinite(g)) or np.linalg.norm(g) < 1e-9:
        raise FormatError(f"{path}: gravity must be three finite numbers of non-zero length, got {g.tolist()}")
    # the gravity file is in the sequence's first camera (frame-000000), whichever frames this Sequence holds
    first = [e.pose for e in sequence.entries if Path(e.path).name.startswith("frame-000000.")]
    pose = first[0] if first else None
    if pose is None:
        return None
    up = -(np.asarray(pose, dtype=np.float64)[:3, :3] @ g)
    return up / np.linalg.norm(up)


def fusion_input(sequence: Sequence | str | Path | Iterable[Frame], intrinsics: Intrinsics | None
                 ) -> tuple[Sequence | None, Iterable[Frame], Intrinsics, int | None, np.ndarray | None]:
    """What a fusion run reads: ``(sequence or None, frames, intrinsics, frame count or None, up or None)``. A
    path is opened; a :class:`Sequence` gives its own intrinsics and gravity and is read ahead
    (:func:`prefetched_frames`); an iterable of frames needs ``intrinsics`` (InvalidValueError otherwise)."""
    if isinstance(sequence, (str, Path)):
        sequence = open_sequence(sequence)
    if isinstance(sequence, Sequence):
        return sequence, prefetched_frames(sequence), sequence.intrinsics, len(sequence), sequence_up(sequence)
    if intrinsics is None:
        raise InvalidValueError("fusing an iterable of frames needs intrinsics=Intrinsics(...)")
    total = len(sequence) if hasattr(sequence, "__len__") else None  # type: ignore[arg-type]
    return None, sequence, intrinsics, total, None


def check_fusion_parameters(truncation: Sequence | tuple, voxel_size: float, depth_max: float | None
                            ) -> tuple[float, float]:
    """``(d_min, d_max)`` of a fusion run, after checking its truncation (d_min < 0 < d_max, so that surfaces
    have both signs), voxel size and depth limit; InvalidValueError otherwise."""
    d_min, d_max = (float(v) for v in truncation)
    check_truncation(d_min, d_max)
    if not (d_min < 0.0 < d_max):
        raise InvalidValueError(f"truncation must satisfy d_min < 0 < d_max so surfaces have both signs, got "
                                f"[{d_min}, {d_max}]")
    if not (np.isfinite(voxel_size) and voxel_size > 0):
        raise InvalidValueError(f"voxel_size must be positive metres, got {voxel_size}")
    if depth_max is not None and not (depth_max > 0):
        raise InvalidValueError(f"depth_max must be positive metres or None, got {depth_max}")
    return d_min, d_max


class FrameFeed:
    """The posed frames of a fusion run as open3d's inputs, and the integration parameters, shared by
    :func:`fuse` and the online fusion (:mod:`sdfcodec.fusion.online`): each frame's depth shifted by ``shift`` metres
    (open3d truncates symmetrically; the project's range is not) as an image on ``dev``, and its extrinsic
    (world to camera, open3d's world starting at ``anchor``). Frames without a pose are counted and passed over;
    the progress bar (``total`` frames; none when ``quiet``) advances per frame. The caller counts what it
    integrated in ``integrated``."""

    def __init__(self, intrinsics: Any, truncation: tuple[float, float], voxel_size: float, depth_max: float | None,
                 anchor: np.ndarray, dev: Any, total: int | None, quiet: bool):
        o3d = open3d_module()
        d_min, d_max = truncation
        # the shift that turns open3d's symmetric band [-T, T] into [d_min, d_max] (module docstring)
        self.half = 0.5 * (d_max - d_min)
        self.shift = np.float32(0.5 * (d_max + d_min))
        self.intrinsics, self.dev, self.total, self.quiet = intrinsics, dev, total, quiet
        self.k = o3d.core.Tensor(intrinsics.matrix, o3d.core.float64, dev)
        # open3d's integrate looks up the pixel int(u), int(v) (truncation, not rounding) of a voxel's projection,
        # while calibrations (OpenCV, TUM, 7-Scenes, our renderer) put pixel centres at integer coordinates.
        # Shifting the principal point by half a pixel makes int(u + 0.5) the nearest pixel; without it, surfaces
        # come out about a quarter voxel off on slanted views (measured: -4 mm on the synthetic floor at 2 cm).
        self.k_lookup = o3d.core.Tensor(intrinsics.matrix + np.array([[0, 0, 0.5], [0, 0, 0.5], [0, 0, 0]]),
                                        o3d.core.float64, dev)
        # open3d's world is ours minus the anchor, so its block lattice starts at the anchor
        self.to_o3d = np.eye(4)
        self.to_o3d[:3, 3] = anchor
        self.mult = self.half / voxel_size
        self.dmax_shifted = (1e6 if depth_max is None else float(depth_max)) - float(self.shift)
        self.integrated = self.skipped = 0
        self.on_frame: Callable[[int | None], None] | None = None  # called per frame with ``total`` (fuse's progress)

    def touched(self, vbg: Any, img: Any, extrinsic: Any) -> Any:
        """The block keys (open3d tensor) a frame's band reaches."""
        return vbg.compute_unique_block_coordinates(img, self.k, extrinsic, 1.0, self.dmax_shifted, self.mult)

    def integrate(self, vbg: Any, keys: Any, img: Any, extrinsic: Any) -> None:
        """Fuse a frame into the blocks ``keys`` of ``vbg`` (they must be allocated)."""
        vbg.integrate(keys, img, self.k_lookup, extrinsic, 1.0, self.dmax_shifted, self.mult)

    def inputs(self, frames: Iterable[Frame]) -> Iterator[tuple[Frame, Any, Any]]:
        """``(frame, image, extrinsic)`` for each posed frame. Raises ShapeError for a depth image whose shape
        is not the intrinsics'."""
        o3d = open3d_module()
        progress, task = fusion_progress(self.total) if not self.quiet else (None, None)
        h, w = self.intrinsics.height, self.intrinsics.width
        try:
            if progress is not None:
                progress.start()
            for frame in frames:
                if progress is not None:
                    progress.advance(task)
                if self.on_frame is not None:
                    self.on_frame(self.total)
                if frame.pose is None:
                    self.skipped += 1
                    continue
                depth = np.asarray(frame.depth, dtype=np.float32)
                if depth.shape != (h, w):
                    raise ShapeError(f"depth image of frame {frame.index} is {depth.shape} but the intrinsics are "
                                     f"for (H, W) = ({h}, {w})")
                # NaN > 0 is false, so missing readings (0 or NaN) become 0 - shift <= 0, which open3d skips
                shifted = np.where(depth > 0, depth - self.shift, np.float32(0.0))
                img = o3d.t.geometry.Image(o3d.core.Tensor.from_numpy(np.ascontiguousarray(shifted))).to(self.dev)
                extrinsic = o3d.core.Tensor(np.linalg.inv(np.asarray(frame.pose, dtype=np.float64)) @ self.to_o3d,
                                            o3d.core.float64, self.dev)
                yield frame, img, extrinsic
        finally:
            if progress is not None:
                progress.stop()

    def check(self) -> None:
        """After the frames: a warning if some had no pose; InvalidValueError if none was integrated."""
        if self.skipped:
            warnings.warn(f"fusion passed over {self.skipped} frame(s) without a pose; {self.integrated} were "
                          "integrated", SDFCodecWarning, stacklevel=3)
        if self.integrated == 0:
            raise InvalidValueError("no frame with a pose to fuse; open the sequence with its ground truth")


def fuse(sequence: Sequence | str | Path | Iterable[Frame], voxel_size: float = 0.02,
         truncation: tuple[float, float] = (-0.04, 0.1), *, depth_max: float | None = 4.0,
         origin: np.ndarray | None = None, intrinsics: Intrinsics | None = None, device: str = "CPU:0",
         block_count: int = 4096, quiet: bool = False,
         progress: Callable[[int | None], None] | None = None) -> FusedBlocks:
    """Fuse a posed depth sequence into a block TSDF with open3d's VoxelBlockGrid.

    Parameters
    ----------
    sequence : Sequence, path or iterable of Frame
        A :class:`~sdfcodec.data.sequences.Sequence` (read ahead in a thread), a sequence folder (opened
        with :func:`~sdfcodec.data.sequences.open_sequence`), or frames (then give ``intrinsics``). Frames
        carry ``(H, W)`` float32 z-depth metres (0 or NaN = no reading) and a 4x4 camera-to-world pose.
    voxel_size : float
        Metres per voxel (blocks are 16 voxels on a side).
    truncation : tuple of float
        ``(d_min, d_max)`` metres, ``d_min < 0 < d_max`` (the module docstring explains how the asymmetric
        band is fused exactly).
    depth_max : float or None
        Metres; readings farther than this are ignored (Kinect-class noise grows as z^2). None = no limit.
    origin : array-like, optional
        ``(3,)`` metres: put voxel (0, 0, 0) of block (0, 0, 0) here, so that several fusions share one
        lattice; every allocated block must then lie at non-negative indices (else InvalidValueError).
        By default the lattice is aligned to world multiples of ``16 voxel_size`` and the origin is the
        corner of the lowest allocated block.
    intrinsics : Intrinsics, optional
        Needed only when ``sequence`` is an iterable of frames.
    device : str
        open3d device, ``"CPU:0"`` or ``"CUDA:0"``.
    block_count : int
        Initial capacity of open3d's block hash map (it grows as needed; each block costs 32 KiB).
    quiet : bool
        No progress bar (otherwise a rich bar on stderr shows frames and frames/s).
    progress : callable, optional
        Called once per frame read with the number of frames in the sequence (None when unknown): a caller's own
        progress report (``sdfcodec fuse`` without a terminal).

    Returns
    -------
    FusedBlocks
        Every allocated block, including blocks with no observed voxel (see :attr:`FusedBlocks.observed`).

    Raises
    ------
    InvalidValueError
        Bad voxel size, truncation or origin; no frame with a pose.
    ShapeError
        A depth image that does not match the intrinsics.
    """
    o3d = open3d_module()
    d_min, d_max = check_fusion_parameters(truncation, voxel_size, depth_max)
    sequence, frames, intrinsics, total, up = fusion_input(sequence, intrinsics)
    anchor = np.zeros(3) if origin is None else np.asarray(origin, dtype=np.float64).reshape(3)
    if not np.all(np.isfinite(anchor)):
        raise InvalidValueError(f"origin must be 3 finite metres, got {origin}")

    dev = o3d.core.Device(device)
    vbg = o3d.t.geometry.VoxelBlockGrid(("tsdf", "weight"), (o3d.core.float32, o3d.core.float32), ((1,), (1,)),
                                        float(voxel_size), BLOCK, int(block_count), dev)
    feed = FrameFeed(intrinsics, (d_min, d_max), voxel_size, depth_max, anchor, dev, total, quiet)
    feed.on_frame = progress
    half, shift = feed.half, feed.shift
    t0 = time.perf_counter()
    for _, img, extrinsic in feed.inputs(frames):
        feed.integrate(vbg, feed.touched(vbg, img, extrinsic), img, extrinsic)
        feed.integrated += 1
    seconds = time.perf_counter() - t0
    feed.check()
    integrated, skipped = feed.integrated, feed.skipped

    hm = vbg.hashmap()
    idx = hm.active_buf_indices().to(o3d.core.int64)
    keys = hm.key_tensor()[idx].cpu().numpy().astype(np.int64)
    # open3d keeps a block's voxels as [z, y, x] (x fastest); the project indexes (x, y, z)
    s = vbg.attribute("tsdf")[idx].cpu().numpy()[..., 0].transpose(0, 3, 2, 1)
    w = vbg.attribute("weight")[idx].cpu().numpy()[..., 0].transpose(0, 3, 2, 1)
    tsdf = np.clip(s * np.float32(half) + shift, d_min, d_max).astype(np.float32)
    tsdf[w <= 0] = np.float32(d_max)
    order = np.lexsort((keys[:, 2], keys[:, 1], keys[:, 0]))
    keys, tsdf, w = keys[order], np.ascontiguousarray(tsdf[order]), np.ascontiguousarray(w[order], dtype=np.float32)
    if origin is None:
        low = keys.min(axis=0) if len(keys) else np.zeros(3, np.int64)
        coords = keys - low
        out_origin = anchor + low * BLOCK * float(voxel_size)
    else:
        coords = keys
        if len(keys) and keys.min() < 0:
            lowest = anchor + keys.min(axis=0) * BLOCK * float(voxel_size)
            raise InvalidValueError(f"the fused surface reaches below origin={anchor.tolist()} (down to "
                                    f"{lowest.tolist()} m); pass a lower origin or origin=None")
        out_origin = anchor
    return FusedBlocks(coords=coords, tsdf=tsdf, weights=w, origin=np.asarray(out_origin, dtype=np.float64),
                       voxel_size=float(voxel_size), truncation=(d_min, d_max), frames_integrated=integrated,
                       frames_skipped=skipped, seconds=seconds, up=up)


def mesh_from_blocks(coords: np.ndarray, tsdf: np.ndarray, *, origin, voxel_size: float,
                     truncation: tuple[float, float] = (-0.04, 0.1), weights: np.ndarray | None = None,
                     weight_threshold: float = 0.0, free_threshold: float | None = None):
    """Marching-cubes mesh of the zero level set of blocks, with open3d.

    Parameters
    ----------
    coords : np.ndarray
        ``(N, 3)`` int block indices.
    tsdf : np.ndarray
        ``(N, 16, 16, 16)`` metres, voxels ``(x, y, z)`` (fused, or decoded from a map and denormalised).
    origin : array-like
        ``(3,)`` metres, world position of voxel (0, 0, 0) of block (0, 0, 0).
    voxel_size : float
        Metres.
    truncation : tuple of float
        ``(d_min, d_max)`` metres.
    weights : np.ndarray, optional
        ``(N, 16, 16, 16)`` observation counts; a marching cube is used only when all 8 corners have weight
        above ``weight_threshold``. Without weights (a decoded map), voxels at or above ``free_threshold``
        (default ``d_max - 0.1 (d_max - d_min)``, i.e. free or unobserved space) count as unobserved: a
        cube can only hold a real surface when all its corners are within its diagonal (``sqrt(3)`` voxels)
        of it, so this removes the false surfaces where unobserved ``d_max`` meets the ``d_min`` band
        behind a wall, and no real one (unless the voxel size exceeds about a third of ``d_max``).

    Returns
    -------
    open3d.geometry.TriangleMesh
        Legacy mesh, vertices in world metres, with vertex normals.
    """
    o3d = open3d_module()
    d_min, d_max = (float(v) for v in truncation)
    check_truncation(d_min, d_max)
    coords = np.asarray(coords, dtype=np.int64).reshape(-1, 3)
    tsdf = np.asarray(tsdf, dtype=np.float32)
    if tsdf.shape != (len(coords), BLOCK, BLOCK, BLOCK):
        raise ShapeError(f"tsdf must have shape ({len(coords)}, 16, 16, 16) to match coords, got {tsdf.shape}")
    if weights is None:
        free = d_max - 0.1 * (d_max - d_min) if free_threshold is None else float(free_threshold)
        w = (tsdf < free).astype(np.float32)
        weight_threshold = 0.0
    else:
        w = np.asarray(weights, dtype=np.float32)
        if w.shape != tsdf.shape:
            raise ShapeError(f"weights must have the shape of tsdf {tsdf.shape}, got {w.shape}")
    vbg = o3d.t.geometry.VoxelBlockGrid(("tsdf", "weight"), (o3d.core.float32, o3d.core.float32), ((1,), (1,)),
                                        float(voxel_size), BLOCK, max(len(coords), 1))
    if len(coords):
        buf, _ = vbg.hashmap().activate(o3d.core.Tensor(coords.astype(np.int32)))
        buf = buf.to(o3d.core.int64)
        # marching cubes interpolates the zero crossing linearly, so any positive scale of metres works;
        # dividing by the larger truncation keeps values in open3d's usual [-1, 1]
        scale = np.float32(max(-d_min, d_max))
        # back to open3d's [z, y, x] voxel order inside a block
        vbg.attribute("tsdf")[buf] = o3d.core.Tensor(to_open3d_order(tsdf / scale))
        vbg.attribute("weight")[buf] = o3d.core.Tensor(to_open3d_order(w))
    try:
        mesh = vbg.extract_triangle_mesh(float(weight_threshold)).to_legacy()
    except RuntimeError:
        # open3d 0.20 fails on setting the colours of an empty result instead of returning an empty mesh
        if _has_crossing(tsdf, w, weight_threshold):
            raise
        return o3d.geometry.TriangleMesh()
    mesh.translate(np.asarray(origin, dtype=np.float64).reshape(3))
    if len(mesh.triangles):
        mesh.compute_vertex_normals()
    return mesh


def _has_crossing(tsdf: np.ndarray, w: np.ndarray, weight_threshold: float) -> bool:
    """Whether any two x-, y- or z-adjacent usable voxels inside a block differ in sign (a cheap
    necessary-enough check that marching cubes has something to extract)."""
    neg = (tsdf < 0) & (w > weight_threshold)
    pos = (tsdf >= 0) & (w > weight_threshold)
    for axis in (1, 2, 3):
        a = [slice(None)] * 4
        b = [slice(None)] * 4
        a[axis], b[axis] = slice(1, None), slice(None, -1)
        if np.any(neg[tuple(a)] & pos[tuple(b)]) or np.any(pos[tuple(a)] & neg[tuple(b)]):
            return True
    return False


def to_open3d_order(blocks: np.ndarray) -> np.ndarray:
    """``(N, 16, 16, 16)`` voxels ``(x, y, z)`` -> open3d's ``(N, 16, 16, 16, 1)`` ``[z, y, x]`` float32."""
    return np.ascontiguousarray(blocks.transpose(0, 3, 2, 1)[..., None], dtype=np.float32)
