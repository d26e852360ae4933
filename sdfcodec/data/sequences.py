"""Readers for RGB-D sequences: depth images, camera intrinsics and ground-truth camera poses.

Two on-disk layouts are read, and told apart automatically by :func:`open_sequence`:

``"tum"`` (the TUM RGB-D benchmark, and what :mod:`sdfcodec.data.render` writes)
    ``depth.txt`` lists ``timestamp path`` (path relative to the sequence directory, usually
    ``depth/<timestamp>.png``); the PNGs are 16-bit single-channel, 5000 units per metre, 0 = no reading.
    ``groundtruth.txt`` holds the motion-capture trajectory, one ``timestamp tx ty tz qx qy qz qw`` per
    line (camera-to-world, ``#`` comments). Depth frames get their pose from the ground truth by timestamp
    (see *Association* below).
``"7scenes"`` (Microsoft 7-Scenes, 3DMatch)
    ``frame-NNNNNN.depth.png`` 16-bit PNGs in millimetres (1000 units per metre; 0 and 65535 = no reading),
    ``frame-NNNNNN.pose.txt`` a 4x4 camera-to-world matrix, ``camera-intrinsics.txt`` a 3x3 K. Frames have
    no timestamps on disk; frame ``i`` gets ``i / frame_rate`` seconds (30 Hz, the Kinect's rate).

Conventions. Depth is float32 metres along the camera's optical axis (z-depth, not ray length), ``(H, W)``
indexed ``[row v, column u]``; missing readings are 0 (never NaN). Poses are 4x4 float64 camera-to-world
matrices (the camera frame is x right, y down, z forward, as in TUM, 7-Scenes and open3d). Pixel ``(u, v)``
looks along ``((u - cx) / fx, (v - cy) / fy, 1)``: integer pixel coordinates are pixel centres, as in the
TUM and 7-Scenes calibrations and in open3d's projection. Lens distortion is ignored (TUM recommends
exactly this for its pre-registered depth images).

Association (TUM). A depth frame at time ``t`` takes its pose from the ground truth as follows. With
``pose_lookup="interpolate"`` (the default) and ground-truth samples on both sides of ``t``, each within
``max_difference`` seconds (0.02 s, the default of TUM's ``associate.py``), the pose is interpolated
(translation linearly, rotation by spherical linear interpolation); this removes the up-to-5 ms timing
error of nearest matching against the 100 Hz motion capture. Otherwise (or with ``pose_lookup="nearest"``)
the nearest ground-truth sample is used when it is within ``max_difference``. Unlike ``associate.py``,
matches are not one-to-one: the ground truth is denser than the depth stream, and a pose may serve two
frames. Frames with no ground truth within ``max_difference`` have no pose.

Bad input never turns into a silently wrong map. Files that cannot be what they claim (a PNG that is not
16-bit single-channel, a malformed trajectory line, a missing listed file) raise
:class:`~sdfcodec.errors.FormatError`; values that cannot be right (a depth scale that puts the median
depth beyond 20 m or within 5 cm, a non-rigid ground-truth quaternion) raise
:class:`~sdfcodec.errors.InvalidValueError`, naming the file and what to do; a median depth that is
possible but unusual for an RGB-D camera (beyond 6 m or within 0.4 m: e.g. TUM's 5000 per metre read as
millimetres) gives a :class:`~sdfcodec.errors.SDFCodecWarning` naming the scale that fits. Frames without
a usable pose (none associated, missing pose file, non-finite or non-rigid matrix) are, by default, dropped, counted in
:attr:`Sequence.skipped` / :attr:`Sequence.skip_reasons` and reported once with a
:class:`~sdfcodec.errors.SDFCodecWarning`; ``missing_pose="error"`` raises instead and ``missing_pose="keep"``
keeps them with ``pose=None`` (for tracking without ground truth).

PNGs are decoded with open3d (the ``fusion`` extra); the bit depth and colour type are checked first from
the PNG header, so a wrong file gets a precise message.
"""

from __future__ import annotations

import math
import re
import struct
import warnings
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Iterator, Literal

import numpy as np

from ..errors import FormatError, InvalidValueError, MissingDependencyError, OutOfRangeError, SDFCodecWarning

# one implementation of trajectories, TUM files and rotations for the whole package: sdfcodec.core.metrics
# (re-exported here because sequences carry their ground truth as a Trajectory)
from ..core.metrics import Trajectory, check_pose, matrix_to_quaternion, quaternion_to_matrix, read_tum

__all__ = [
    "Intrinsics",
    "Frame",
    "Trajectory",
    "Sequence",
    "open_sequence",
    "read_depth_png",
    "write_depth_png",
    "read_intrinsics_file",
    "associate",
    "quaternion_to_matrix",
    "matrix_to_quaternion",
    "check_pose",
    "TUM_INTRINSICS",
    "TUM_DEPTH_SCALE",
    "SEVEN_SCENES_DEPTH_SCALE",
]

TUM_DEPTH_SCALE = 5000.0  # PNG units per metre in the TUM RGB-D benchmark
SEVEN_SCENES_DEPTH_SCALE = 1000.0  # millimetres in 7-Scenes and 3DMatch
_INVALID_RAW = 65535  # 7-Scenes marks pixels without a reading with 65535 (saturated), others with 0
_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
# median depths outside this range (metres) mean the depth scale is wrong, not an odd scene (an error) ...
_PLAUSIBLE_MEDIAN = (0.05, 20.0)
# ... and outside this one they are unusual for an RGB-D camera (a warning): TUM's 5000/m read as
# millimetres gives 5x too far (a 2.4 m median reads 12 m), millimetres read as 5000/m 5x too near (most
# pixels closer than a Kinect's 0.4-0.5 m minimum range)
_USUAL_MEDIAN = (0.4, 6.0)


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics of a depth camera: focal lengths and principal point in pixels, image size.

    Integer pixel coordinates are pixel centres: pixel ``(u, v)`` (column, row) sees the ray
    ``((u - cx) / fx, (v - cy) / fy, 1)`` in the camera frame.
    """

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    @property
    def matrix(self) -> np.ndarray:
        """The 3x3 calibration matrix K (float64)."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @classmethod
    def from_matrix(cls, k: np.ndarray, width: int, height: int) -> "Intrinsics":
        """From a 3x3 K (zero skew) and the image size in pixels."""
        k = np.asarray(k, dtype=np.float64)
        if k.shape != (3, 3) or not np.all(np.isfinite(k)):
            raise InvalidValueError(f"an intrinsics matrix must be a finite 3x3 K, got shape {k.shape}")
        if k[0, 0] <= 0 or k[1, 1] <= 0:
            raise InvalidValueError(f"focal lengths must be positive pixels, got fx={k[0, 0]}, fy={k[1, 1]}")
        return cls(float(k[0, 0]), float(k[1, 1]), float(k[0, 2]), float(k[1, 2]), int(width), int(height))

    def with_size(self, width: int, height: int) -> "Intrinsics":
        """The same calibration for an image of ``width`` x ``height`` pixels (no rescaling)."""
        return replace(self, width=int(width), height=int(height))


#: Published TUM RGB-D calibrations (fx, fy, cx, cy) for 640x480 images. ``freiburg3`` and ``default`` are
#: the ROS defaults, which TUM recommends for the pre-registered depth images of fr3.
TUM_INTRINSICS: dict[str, tuple[float, float, float, float]] = {
    "freiburg1": (517.3, 516.5, 318.6, 255.3),
    "freiburg2": (520.9, 521.0, 325.1, 249.7),
    "freiburg3": (525.0, 525.0, 319.5, 239.5),
    "default": (525.0, 525.0, 319.5, 239.5),
}
# the published 7-Scenes calibration, used when a 7-Scenes folder lacks camera-intrinsics.txt
_SEVEN_SCENES_K = (585.0, 585.0, 320.0, 240.0)


@dataclass(frozen=True)
class Frame:
    """One depth frame of a sequence.

    Attributes
    ----------
    index : int
        Position in the :class:`Sequence` (after skipped frames were dropped).
    timestamp : float
        Seconds (TUM: the recording's clock; 7-Scenes: ``frame_number / frame_rate``).
    depth : np.ndarray
        ``(H, W)`` float32 z-depth in metres, 0 where the sensor gave no reading.
    pose : np.ndarray or None
        ``(4, 4)`` float64 camera-to-world transform, or None when the sequence keeps frames without one.
    path : pathlib.Path
        The depth PNG.
    """

    index: int
    timestamp: float
    depth: np.ndarray
    pose: np.ndarray | None
    path: Path


# --------------------------------------------------------------------------------------------------- poses
def _slerp_pose(p0: np.ndarray, p1: np.ndarray, a: float) -> np.ndarray:
    """Pose a fraction ``a`` in [0, 1] of the way from ``p0`` to ``p1`` (lerp translation, slerp rotation)."""
    q0, q1 = matrix_to_quaternion(p0[:3, :3]), matrix_to_quaternion(p1[:3, :3])
    dot = float(q0 @ q1)
    if dot < 0:  # take the short way round
        q1, dot = -q1, -dot
    if dot > 0.9995:  # nearly equal: normalised lerp is exact enough and avoids dividing by sin(~0)
        q = q0 + a * (q1 - q0)
    else:
        th = math.acos(dot)
        q = (math.sin((1 - a) * th) * q0 + math.sin(a * th) * q1) / math.sin(th)
    out = np.eye(4)
    out[:3, :3] = quaternion_to_matrix(q)
    out[:3, 3] = (1 - a) * p0[:3, 3] + a * p1[:3, 3]
    return out


# ---------------------------------------------------------------------------------------- text files
def _numeric_rows(path: Path, what: str) -> list[tuple[int, list[str]]]:
    """Non-comment, non-empty lines of a text file as ``(line_number, fields)``."""
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise FormatError(f"{what} {path} does not exist") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise FormatError(f"cannot read {what} {path}: {exc}") from exc
    rows = []
    for n, line in enumerate(text.splitlines(), start=1):
        s = line.strip()
        if s and not s.startswith("#"):
            rows.append((n, s.replace(",", " ").split()))
    return rows


def read_intrinsics_file(path: str | Path, width: int, height: int) -> Intrinsics:
    """Read intrinsics: a 3x3 K (``camera-intrinsics.txt`` of 7-Scenes/3DMatch), or one line of
    ``fx fy cx cy`` or ``fx fy cx cy width height`` (``#`` comments allowed).

    ``width`` and ``height`` (pixels, from the depth images) are used unless the file gives them; a file
    that gives a different size is an error.
    """
    path = Path(path)
    values = [v for _, fields in _numeric_rows(path, "intrinsics file") for v in fields]
    try:
        nums = [float(v) for v in values]
    except ValueError:
        raise FormatError(f"intrinsics file {path} holds non-numbers: {' '.join(values)!r}") from None
    if len(nums) == 9:
        return Intrinsics.from_matrix(np.array(nums).reshape(3, 3), width, height)
    if len(nums) in (4, 6):
        intr = Intrinsics.from_matrix(np.array([[nums[0], 0, nums[2]], [0, nums[1], nums[3]], [0, 0, 1]]),
                                      width, height)
        if len(nums) == 6 and (int(nums[4]), int(nums[5])) != (width, height):
            raise FormatError(f"intrinsics file {path} is for {int(nums[4])}x{int(nums[5])} images but the depth "
                              f"images are {width}x{height}")
        return intr
    raise FormatError(f"intrinsics file {path} must hold a 3x3 K or 'fx fy cx cy [width height]', "
                      f"found {len(nums)} numbers")


# ------------------------------------------------------------------------------------------- depth PNGs
def _png_header(path: Path) -> tuple[int, int, int, int]:
    """``(width, height, bit_depth, colour_type)`` from a PNG's IHDR chunk, or FormatError."""
    try:
        with open(path, "rb") as f:
            head = f.read(26)
    except FileNotFoundError:
        raise FormatError(f"depth image {path} does not exist (listed by the sequence but missing)") from None
    except OSError as exc:
        raise FormatError(f"cannot read depth image {path}: {exc}") from exc
    if len(head) < 26 or head[:8] != _PNG_SIGNATURE or head[12:16] != b"IHDR":
        raise FormatError(f"depth image {path} is not a PNG file (bad signature); depth must be 16-bit PNG")
    width, height = struct.unpack(">II", head[16:24])
    return width, height, head[24], head[25]


def read_depth_png(path: str | Path, depth_scale: float) -> np.ndarray:
    """Read a 16-bit depth PNG as float32 metres.

    Parameters
    ----------
    path : str or Path
        A 16-bit single-channel (greyscale) PNG.
    depth_scale : float
        PNG units per metre (TUM 5000, 7-Scenes 1000).

    Returns
    -------
    np.ndarray
        ``(H, W)`` float32 metres; 0 where there is no reading (raw 0, or 65535 as 7-Scenes writes).

    Raises
    ------
    FormatError
        Missing file, not a PNG, not 16-bit, more than one channel, or undecodable data.
    """
    path = Path(path)
    width, height, bits, colour = _png_header(path)
    if colour != 0:
        kinds = {2: "RGB", 3: "palette", 4: "grey+alpha", 6: "RGBA"}
        raise FormatError(f"depth image {path} is a {kinds.get(colour, f'type-{colour}')} PNG; depth must be a "
                          "single-channel (greyscale) 16-bit PNG")
    if bits != 16:
        raise FormatError(f"depth image {path} is {bits}-bit; depth must be a 16-bit PNG (an {bits}-bit image "
                          "is usually a visualisation or a colour frame, not the sensor's depth)")
    o3d = _open3d()
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        img = o3d.io.read_image(str(path))
    raw = np.asarray(img)
    if img.is_empty() or raw.shape != (height, width) or raw.dtype != np.uint16:
        raise FormatError(f"depth image {path} could not be decoded as a {width}x{height} 16-bit PNG (corrupt "
                          "or truncated file)")
    depth = raw.astype(np.float32)
    depth[raw == _INVALID_RAW] = 0.0
    depth *= np.float32(1.0 / depth_scale)
    return depth


def write_depth_png(path: str | Path, depth: np.ndarray, depth_scale: float) -> Path:
    """Write ``(H, W)`` metres (0 or NaN = no reading) as a 16-bit PNG with ``depth_scale`` units per metre.

    Values are rounded to the nearest unit; depths that do not fit in 16 bits (>= 65535 units, e.g. 13.1 m
    at scale 5000) become 0 (no reading), as a real sensor beyond its range.
    """
    d = np.asarray(depth, dtype=np.float64)
    if d.ndim != 2:
        raise InvalidValueError(f"a depth image must have shape (H, W), got {d.shape}")
    raw = np.rint(np.nan_to_num(d, nan=0.0) * depth_scale)
    raw[(raw < 0) | (raw >= _INVALID_RAW)] = 0
    o3d = _open3d()
    img = o3d.geometry.Image(np.ascontiguousarray(raw.astype(np.uint16)))
    if not o3d.io.write_image(str(path), img):
        raise FormatError(f"could not write depth image {path}")
    return Path(path)


def _open3d():
    try:
        import open3d as o3d
    except ImportError as exc:  # only the optional 'fusion' extra brings open3d
        raise MissingDependencyError("reading and writing depth images needs open3d: pip install 'sdfcodec[fusion]'") \
            from exc
    return o3d


# --------------------------------------------------------------------------------------------- association
def associate(first: np.ndarray, second: np.ndarray, max_difference: float = 0.02, offset: float = 0.0
              ) -> list[tuple[int, int]]:
    """One-to-one timestamp matching, as TUM's ``associate.py``.

    Candidate pairs ``(i, j)`` with ``|first[i] - (second[j] + offset)| < max_difference`` are taken
    greedily in order of increasing difference, each index at most once.

    Returns
    -------
    list of (int, int)
        Index pairs sorted by ``i``.
    """
    a = np.asarray(first, dtype=np.float64)
    b = np.asarray(second, dtype=np.float64) + offset
    order = np.argsort(b, kind="stable")
    bs = b[order]
    cands = []
    for i, t in enumerate(a):
        lo, hi = np.searchsorted(bs, [t - max_difference, t + max_difference])
        for k in range(lo, hi):
            diff = abs(t - bs[k])
            if diff < max_difference:
                cands.append((diff, i, int(order[k])))
    cands.sort()
    used_a, used_b, out = set(), set(), []
    for _, i, j in cands:
        if i not in used_a and j not in used_b:
            used_a.add(i)
            used_b.add(j)
            out.append((i, j))
    return sorted(out)


def _lookup_poses(stamps: np.ndarray, gt: Trajectory, max_difference: float, mode: str) -> list[np.ndarray | None]:
    """Pose of each depth timestamp from the ground truth (see the module docstring), None if none."""
    ts = gt.timestamps
    out: list[np.ndarray | None] = []
    for t in stamps:
        j = int(np.searchsorted(ts, t))  # ts[j-1] < t <= ts[j]
        before = j - 1 if j > 0 else None
        after = j if j < len(ts) else None
        d_before = t - ts[before] if before is not None else math.inf
        d_after = ts[after] - t if after is not None else math.inf
        if min(d_before, d_after) > max_difference:
            out.append(None)
            continue
        if d_after == 0.0:
            out.append(gt.poses[after].copy())
        elif mode == "interpolate" and d_before <= max_difference and d_after <= max_difference:
            a = d_before / (d_before + d_after)
            out.append(_slerp_pose(gt.poses[before], gt.poses[after], a))
        else:
            out.append(gt.poses[before if d_before <= d_after else after].copy())
    return out


# ------------------------------------------------------------------------------------------------ sequence
@dataclass
class _Entry:
    timestamp: float
    path: Path
    pose: np.ndarray | None


@dataclass
class Sequence:
    """An RGB-D sequence's depth frames with intrinsics and poses; build it with :func:`open_sequence`.

    ``len(seq)``, ``seq[i]`` (a :class:`Frame`, read from disk on access), ``seq[a:b:c]`` (a sub-sequence
    sharing the same files) and iteration work as for a list of frames.

    Attributes
    ----------
    path : Path
        The sequence directory.
    layout : str
        ``"tum"`` or ``"7scenes"``.
    intrinsics : Intrinsics
        The depth camera's calibration, with the depth images' size.
    depth_scale : float
        PNG units per metre.
    trajectory : Trajectory or None
        The ground truth as stored (TUM: every motion-capture sample; 7-Scenes: one pose per usable frame).
    skipped : int
        Frames dropped when the sequence was opened (no usable pose); the reasons are in ``skip_reasons``.
    skip_reasons : dict
        ``reason -> count``.
    """

    path: Path
    layout: str
    intrinsics: Intrinsics
    depth_scale: float
    trajectory: Trajectory | None
    entries: list[_Entry] = field(repr=False)
    skipped: int = 0
    skip_reasons: dict[str, int] = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.entries)

    def __iter__(self) -> Iterator[Frame]:
        for i in range(len(self)):
            yield self[i]

    def __getitem__(self, index):
        if isinstance(index, slice):
            return replace(self, entries=self.entries[index])
        i = int(index)
        if i < 0:
            i += len(self)
        if not 0 <= i < len(self):
            raise OutOfRangeError(f"frame {index} out of range for a sequence of {len(self)} frames")
        return self.read_frame(i)

    def read_frame(self, i: int) -> Frame:
        """Frame ``i`` with its depth read from disk (``FormatError`` for a bad PNG)."""
        e = self.entries[i]
        depth = read_depth_png(e.path, self.depth_scale)
        if depth.shape != (self.intrinsics.height, self.intrinsics.width):
            raise FormatError(f"depth image {e.path} is {depth.shape[1]}x{depth.shape[0]} but the sequence's images "
                              f"are {self.intrinsics.width}x{self.intrinsics.height}; one sequence has one image size")
        return Frame(index=i, timestamp=e.timestamp, depth=depth,
                     pose=None if e.pose is None else e.pose.copy(), path=e.path)

    @property
    def timestamps(self) -> np.ndarray:
        """``(N,)`` float64 seconds of the frames."""
        return np.array([e.timestamp for e in self.entries], dtype=np.float64)

    @property
    def poses(self) -> np.ndarray:
        """``(N, 4, 4)`` float64 camera-to-world poses of the frames (all-NaN for a frame without one)."""
        out = np.full((len(self), 4, 4), np.nan)
        for i, e in enumerate(self.entries):
            if e.pose is not None:
                out[i] = e.pose
        return out

    @property
    def frame_paths(self) -> list[Path]:
        """The depth PNG of each frame."""
        return [e.path for e in self.entries]


MissingPose = Literal["skip", "error", "keep"]


def open_sequence(path: str | Path, *, layout: str | None = None,
                  intrinsics: Intrinsics | str | np.ndarray | None = None, depth_scale: float | None = None,
                  max_difference: float = 0.02, pose_lookup: Literal["interpolate", "nearest"] = "interpolate",
                  missing_pose: MissingPose = "skip", frame_rate: float = 30.0, check_scale: bool = True) -> Sequence:
    """Open an RGB-D sequence directory, detecting its layout.

    Parameters
    ----------
    path : str or Path
        The sequence directory (TUM: the folder with ``depth.txt``; 7-Scenes/3DMatch: the folder with the
        ``frame-NNNNNN.*`` files).
    layout : {"tum", "7scenes"}, optional
        Force a layout instead of detecting it.
    intrinsics : Intrinsics, str or array, optional
        Override the calibration: an :class:`Intrinsics`, a 3x3 K, or a TUM preset name (``"freiburg1"``,
        ``"fr2"``, ``"default"``...). Otherwise: an intrinsics file in the folder or its parent
        (``intrinsics.txt`` or ``camera-intrinsics.txt``), else for TUM the preset named by the folder
        (``...freiburg1...`` or ``fr1``), else the layout's default with a warning.
    depth_scale : float, optional
        PNG units per metre; default 5000 (TUM) or 1000 (7-Scenes).
    max_difference : float
        Seconds; a TUM depth frame needs ground truth this close (TUM's ``associate.py`` default 0.02).
    pose_lookup : {"interpolate", "nearest"}
        How TUM ground truth is turned into a pose at a depth timestamp (module docstring).
    missing_pose : {"skip", "error", "keep"}
        What to do with a frame without a usable pose: drop it (counted in ``skipped``, one warning), raise
        :class:`~sdfcodec.errors.InvalidValueError`, or keep it with ``pose=None``.
    frame_rate : float
        Hz; gives 7-Scenes frames their timestamps.
    check_scale : bool
        Read up to 5 frames spread over the sequence and raise when their median depth is beyond 20 m or
        within 5 cm (a wrong ``depth_scale``), or warn when it is beyond 6 m or within 0.4 m (unusual for
        an RGB-D camera: e.g. TUM's 5000 per metre read as millimetres), naming the scale that would fit.

    Returns
    -------
    Sequence

    Raises
    ------
    FormatError
        Unrecognised layout, missing or malformed list/trajectory files, bad PNGs.
    InvalidValueError
        Implausible depth scale; a frame without a usable pose when ``missing_pose="error"``; no frame left.
    """
    root = Path(path)
    if not root.is_dir():
        raise FormatError(f"sequence path {root} is not a directory")
    if missing_pose not in ("skip", "error", "keep"):
        raise InvalidValueError(f"missing_pose must be 'skip', 'error' or 'keep', got {missing_pose!r}")
    if pose_lookup not in ("interpolate", "nearest"):
        raise InvalidValueError(f"pose_lookup must be 'interpolate' or 'nearest', got {pose_lookup!r}")
    if not (max_difference > 0):
        raise InvalidValueError(f"max_difference must be positive seconds, got {max_difference}")
    if depth_scale is not None and not (np.isfinite(depth_scale) and depth_scale > 0):
        raise InvalidValueError(f"depth_scale must be positive units per metre, got {depth_scale}")
    layout = layout or _detect_layout(root)
    reasons: dict[str, int] = {}
    examples: dict[str, str] = {}

    def reject(reason: str, example: str) -> None:
        if missing_pose == "error":
            raise InvalidValueError(f"{example}: {reason}; pass missing_pose='skip' to drop such frames or "
                                    "missing_pose='keep' to read them without a pose")
        reasons[reason] = reasons.get(reason, 0) + 1
        examples.setdefault(reason, example)

    if layout == "tum":
        scale = TUM_DEPTH_SCALE if depth_scale is None else float(depth_scale)
        entries, trajectory = _read_tum(root, max_difference, pose_lookup, missing_pose, reject)
    elif layout == "7scenes":
        scale = SEVEN_SCENES_DEPTH_SCALE if depth_scale is None else float(depth_scale)
        entries, trajectory = _read_7scenes(root, frame_rate, reject)
    else:
        raise InvalidValueError(f"layout must be 'tum' or '7scenes', got {layout!r}")

    n_total = len(entries)
    if missing_pose == "skip":
        entries = [e for e in entries if e.pose is not None]
    skipped = sum(reasons.values()) if missing_pose == "skip" else 0
    if not entries:
        detail = "; ".join(f"{n} {r} (e.g. {examples[r]})" for r, n in reasons.items())
        raise InvalidValueError(f"no usable frame in {root} ({n_total} listed): {detail or 'no depth frames'}")
    if skipped:
        detail = "; ".join(f"{n} {r} (e.g. {examples[r]})" for r, n in reasons.items())
        warnings.warn(f"skipped {skipped} of {n_total} frames of {root}: {detail}; see Sequence.skip_reasons",
                      SDFCodecWarning, stacklevel=2)

    w, h, _, _ = _png_header(entries[0].path)
    intr = _resolve_intrinsics(root, layout, intrinsics, w, h)
    seq = Sequence(path=root, layout=layout, intrinsics=intr, depth_scale=scale, trajectory=trajectory,
                   entries=entries, skipped=skipped, skip_reasons=dict(reasons) if skipped else {})
    if check_scale:
        _check_depth_scale(seq)
    return seq


def _detect_layout(root: Path) -> str:
    if (root / "depth.txt").is_file():
        return "tum"
    if next(root.glob("frame-*.depth.png"), None) is not None:
        return "7scenes"
    hint = ""
    if next(root.glob("seq-*"), None) is not None:
        hint = " (it holds seq-* folders: open one of them)"
    elif (root / "depth").is_dir():
        hint = " (it has depth/ but no depth.txt listing the frames with their timestamps)"
    raise FormatError(f"{root} is not an RGB-D sequence{hint}: expected a TUM folder with depth.txt (+ "
                      "groundtruth.txt) or a 7-Scenes/3DMatch folder of frame-NNNNNN.depth.png + .pose.txt")


def _read_tum(root: Path, max_difference: float, pose_lookup: str, missing_pose: str, reject
              ) -> tuple[list[_Entry], Trajectory | None]:
    listing = root / "depth.txt"
    entries = []
    for n, fields in _numeric_rows(listing, "depth list"):
        if len(fields) != 2:
            raise FormatError(f"{listing}:{n}: expected 'timestamp path', got {' '.join(fields)!r}")
        try:
            stamp = float(fields[0])
        except ValueError:
            raise FormatError(f"{listing}:{n}: timestamp {fields[0]!r} is not a number") from None
        if not np.isfinite(stamp):
            raise FormatError(f"{listing}:{n}: timestamp {fields[0]!r} is not finite")
        entries.append(_Entry(stamp, root / fields[1], None))
    if not entries:
        raise FormatError(f"{listing} lists no depth frames")
    entries.sort(key=lambda e: e.timestamp)
    gt_path = root / "groundtruth.txt"
    if not gt_path.is_file():
        if missing_pose == "keep":
            return entries, None
        raise FormatError(f"{root} has no groundtruth.txt, so its frames have no poses; fusion needs them. Pass "
                          "missing_pose='keep' to read the depth frames without poses")
    gt = read_tum(gt_path)  # sorted by timestamp
    poses = _lookup_poses(np.array([e.timestamp for e in entries]), gt, max_difference, pose_lookup)
    if all(p is None for p in poses) and missing_pose != "keep":
        raise InvalidValueError(
            f"no depth frame of {root} has ground truth within {max_difference} s: depth spans "
            f"[{entries[0].timestamp:.3f}, {entries[-1].timestamp:.3f}] s, groundtruth.txt spans "
            f"[{gt.timestamps[0]:.3f}, {gt.timestamps[-1]:.3f}] s. Check that both files belong to the same "
            "recording (same clock), or raise max_difference")
    for e, p in zip(entries, poses):
        if p is None:
            reject(f"without ground truth within {max_difference} s", f"depth frame at t={e.timestamp:.6f}")
        e.pose = p
    return entries, gt


_FRAME_RE = re.compile(r"^frame-(\d+)\.depth\.png$")


def _read_7scenes(root: Path, frame_rate: float, reject) -> tuple[list[_Entry], Trajectory | None]:
    frames = []
    for p in root.iterdir():
        m = _FRAME_RE.match(p.name)
        if m:
            frames.append((int(m.group(1)), p))
    frames.sort()
    entries = []
    for number, p in frames:
        pose_path = p.with_name(f"frame-{p.name[6:-10]}.pose.txt")
        pose = None
        if not pose_path.is_file():
            reject("without a pose file", pose_path.name)
        else:
            try:  # plain split is 10x faster than np.loadtxt, which matters for 3DMatch's thousands of frames
                values = np.array(pose_path.read_text().split(), dtype=np.float64)
            except (ValueError, OSError, UnicodeDecodeError) as exc:
                raise FormatError(f"pose file {pose_path} is not a 4x4 matrix of numbers: {exc}") from exc
            if values.size != 16:
                raise FormatError(f"pose file {pose_path} must hold a 4x4 camera-to-world matrix (16 numbers), "
                                  f"found {values.size}")
            pose = values.reshape(4, 4)
            why = check_pose(pose)
            if why is not None:
                reject("with a non-finite or non-rigid pose", f"{pose_path.name}: {why}")
                pose = None
        entries.append(_Entry(number / frame_rate, p, pose))
    good = [e for e in entries if e.pose is not None]
    traj = None
    if good:
        traj = Trajectory.from_poses(np.stack([e.pose for e in good]), np.array([e.timestamp for e in good]))
    return entries, traj


def _tum_preset(name: str) -> tuple[float, float, float, float] | None:
    key = name.lower()
    if key in TUM_INTRINSICS:
        return TUM_INTRINSICS[key]
    m = re.search(r"(?:freiburg|fr)([123])(?!\d)", key)
    return TUM_INTRINSICS[f"freiburg{m.group(1)}"] if m else None


def _resolve_intrinsics(root: Path, layout: str, given, width: int, height: int) -> Intrinsics:
    if isinstance(given, Intrinsics):
        return given.with_size(width, height)
    if isinstance(given, str):
        preset = _tum_preset(given)
        if preset is None:
            raise InvalidValueError(f"unknown intrinsics preset {given!r}; use one of {sorted(TUM_INTRINSICS)} "
                                    "(or 'fr1'/'fr2'/'fr3'), an Intrinsics or a 3x3 K")
        return Intrinsics(*preset, width, height)
    if given is not None:
        return Intrinsics.from_matrix(np.asarray(given), width, height)
    for folder in (root, root.parent):
        for name in ("intrinsics.txt", "camera-intrinsics.txt"):
            if (folder / name).is_file():
                return read_intrinsics_file(folder / name, width, height)
    if layout == "tum":
        preset = _tum_preset(root.resolve().name)
        if preset is not None:
            return Intrinsics(*preset, width, height)
        default = TUM_INTRINSICS["default"]
    else:
        default = _SEVEN_SCENES_K
    warnings.warn(f"{root} names no camera (no intrinsics.txt / camera-intrinsics.txt and no freiburg1/2/3 in its "
                  f"name): using fx={default[0]}, fy={default[1]}, cx={default[2]}, cy={default[3]}. Pass "
                  "intrinsics= if this is another camera", SDFCodecWarning, stacklevel=3)
    return Intrinsics(*default, width, height)


def _check_depth_scale(seq: Sequence) -> None:
    """Raise when the median depth of a few frames is implausible for an RGB-D camera (wrong scale)."""
    n = len(seq)
    picks = sorted({int(round(x)) for x in np.linspace(0, n - 1, min(5, n))})
    valid = []
    for i in picks:
        d = read_depth_png(seq.entries[i].path, seq.depth_scale)
        valid.append(d[d > 0])
    values = np.concatenate(valid)
    if values.size == 0:
        return  # nothing to judge by (blank frames); fusion will simply integrate nothing
    median = float(np.median(values))
    if _USUAL_MEDIAN[0] <= median <= _USUAL_MEDIAN[1]:
        return
    raw = median * seq.depth_scale
    fits = [s for s in (SEVEN_SCENES_DEPTH_SCALE, TUM_DEPTH_SCALE)
            if s != seq.depth_scale and _USUAL_MEDIAN[0] <= raw / s <= _USUAL_MEDIAN[1]]
    suggestion = (f"depth_scale={fits[0]:g} (median {raw / fits[0]:.2f} m)" if fits
                  else f"a depth_scale near {raw / 2.0:.4g} (for a median of about 2 m)")
    lo, hi = _PLAUSIBLE_MEDIAN
    if not lo <= median <= hi:
        raise InvalidValueError(f"median depth of {seq.path} is {median:.4g} m at depth_scale={seq.depth_scale:g}, "
                                f"which no RGB-D camera gives; the scale is probably wrong: try {suggestion}")
    warnings.warn(f"median depth of {seq.path} is {median:.3g} m at depth_scale={seq.depth_scale:g}, unusual for an "
                  f"RGB-D camera; if the scale is wrong try {suggestion} (check_scale=False silences this)",
                  SDFCodecWarning, stacklevel=3)
