"""Trajectories in the style of evo's ``trajectory`` and ``file_interface``: timestamped camera-to-world poses,
TUM trajectory files, association by timestamp and alignment, plain numpy float64.

- A trajectory is a list of camera-to-world poses with timestamps. Files are TUM format, one pose a line,
  ``timestamp tx ty tz qx qy qz qw`` (seconds, metres, unit quaternion with w last), ``#`` starts a comment.
- :func:`associate` pairs poses of two trajectories by nearest timestamp within ``max_diff`` seconds
  (evo's ``sync.associate_trajectories``, nearest-time method).
- :func:`align_trajectory` aligns an associated estimate onto a reference (Horn / Umeyama,
  :func:`sdfcodec.core.geometry.umeyama_alignment`).

The metrics on trajectories (ATE, RPE) are in :mod:`sdfcodec.core.metrics`; rotations and rigid transforms in
:mod:`sdfcodec.core.geometry`.

    ref, est = associate(read_tum("groundtruth.txt"), read_tum("estimate.txt"))
    aligned, sim = align_trajectory(est, ref)
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable, Union

import numpy as np

from ..errors import FormatError, InvalidValueError, ShapeError
from .geometry import check_pose, matrix_to_quaternion, quaternion_to_matrix, umeyama_alignment

__all__ = [
    "Trajectory",
    "as_trajectory",
    "check_associated",
    "read_tum",
    "write_tum",
    "associate",
    "association_indices",
    "align_trajectory",
]

PathLike = Union[str, "os.PathLike[str]"]
# a TUM quaternion printed with 4 decimals has |q| within ~2e-4 of 1; more means a broken file
_QUAT_NORM_TOL = 1e-2


# ---------------------------------------------------------------------------------------------- trajectory
@dataclass(frozen=True, eq=False)
class Trajectory:
    """Timestamped camera-to-world poses (float64).

    Attributes:
        timestamps: ``(N,)`` seconds.
        positions: ``(N, 3)`` metres, the camera centre in the world frame.
        quaternions: ``(N, 4)`` ``(qx, qy, qz, qw)``, camera-to-world rotation (normalised on use).
    """

    timestamps: np.ndarray
    positions: np.ndarray
    quaternions: np.ndarray
    _poses: np.ndarray | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        t = np.asarray(self.timestamps, dtype=np.float64)
        p = np.asarray(self.positions, dtype=np.float64)
        q = np.asarray(self.quaternions, dtype=np.float64)
        if t.ndim != 1:
            raise ShapeError(f"timestamps must have shape (N,), got {t.shape}")
        n = len(t)
        if p.shape != (n, 3):
            raise ShapeError(f"positions must have shape (N, 3) = ({n}, 3) to match the timestamps, got {p.shape}")
        if q.shape != (n, 4):
            raise ShapeError(f"quaternions must have shape (N, 4) = ({n}, 4) (qx, qy, qz, qw), got {q.shape}")
        for name, a in (("timestamps", t), ("positions", p), ("quaternions", q)):
            if not np.all(np.isfinite(a)):
                raise InvalidValueError(f"trajectory {name} hold NaN or infinite values")
        object.__setattr__(self, "timestamps", t)
        object.__setattr__(self, "positions", p)
        object.__setattr__(self, "quaternions", q)
        if self._poses is None and n:
            quaternion_to_matrix(q)  # rejects zero quaternions early

    @classmethod
    def from_poses(cls, poses: np.ndarray, timestamps: np.ndarray | None = None) -> "Trajectory":
        """Build from camera-to-world matrices ``(N, 4, 4)`` (numpy or torch) and timestamps ``(N,)`` seconds
        (default ``0, 1, 2, ...``). The matrices are kept as given (so metrics see exactly them)."""
        if hasattr(poses, "detach"):
            poses = poses.detach().cpu().numpy()
        m = np.asarray(poses, dtype=np.float64)
        if m.ndim != 3 or m.shape[1:] != (4, 4):
            raise ShapeError(f"poses must have shape (N, 4, 4), got {m.shape}")
        if not np.all(np.isfinite(m)):
            raise InvalidValueError("poses hold NaN or infinite values")
        t = np.arange(len(m), dtype=np.float64) if timestamps is None else np.asarray(timestamps, np.float64)
        return cls(t, m[:, :3, 3].copy(), matrix_to_quaternion(m[:, :3, :3]) if len(m) else np.zeros((0, 4)),
                   m.copy())

    def __len__(self) -> int:
        return len(self.timestamps)

    @property
    def poses(self) -> np.ndarray:
        """Camera-to-world matrices ``(N, 4, 4)`` float64."""
        if self._poses is not None:
            return self._poses
        m = np.zeros((len(self), 4, 4))
        if len(self):
            m[:, :3, :3] = quaternion_to_matrix(self.quaternions)
        m[:, :3, 3] = self.positions
        m[:, 3, 3] = 1.0
        object.__setattr__(self, "_poses", m)
        return m

    def subset(self, indices: Iterable[int] | np.ndarray) -> "Trajectory":
        """The poses at ``indices`` (in that order; repeats allowed)."""
        idx = np.asarray(list(indices) if not isinstance(indices, np.ndarray) else indices, dtype=np.int64)
        return Trajectory(self.timestamps[idx], self.positions[idx], self.quaternions[idx],
                          None if self._poses is None else self._poses[idx])

    def transformed(self, transform: np.ndarray, scale: float = 1.0) -> "Trajectory":
        """Poses ``T @ [R_i, s * t_i]`` for a rigid ``transform`` ``(4, 4)`` applied on the left (world frame)
        after scaling the positions by ``scale`` (how a Sim(3) alignment acts on a trajectory)."""
        t = np.asarray(transform, dtype=np.float64)
        if t.shape != (4, 4):
            raise ShapeError(f"transform must have shape (4, 4), got {t.shape}")
        p = self.poses.copy()
        p[:, :3, 3] *= scale
        out = np.einsum("ij,njk->nik", t, p)
        return Trajectory.from_poses(out, self.timestamps)


def as_trajectory(x, name: str) -> Trajectory:
    """``x`` as a :class:`Trajectory`: a trajectory as it is, or camera-to-world poses ``(N, 4, 4)`` (numpy or
    torch) with timestamps ``0, 1, 2, ...``; ``name`` goes into the error message."""
    if isinstance(x, Trajectory):
        return x
    if hasattr(x, "detach"):
        x = x.detach().cpu().numpy()
    a = np.asarray(x, dtype=np.float64)
    if a.ndim == 3 and a.shape[1:] == (4, 4):
        return Trajectory.from_poses(a)
    raise ShapeError(f"{name} must be a Trajectory or poses of shape (N, 4, 4), got {a.shape}")


# ----------------------------------------------------------------------------------------------------- I/O
def read_tum(path: PathLike) -> Trajectory:
    """Read a TUM trajectory file (a TUM ``groundtruth.txt`` or an estimate in the same format).

    One pose a line, ``timestamp tx ty tz qx qy qz qw`` (camera-to-world); ``#`` comment lines and blank
    lines are skipped; fields are separated by spaces, tabs or commas. The poses are returned sorted by
    timestamp (stable, so an already sorted file is read exactly as written).

    Parameters
    ----------
    path : str or os.PathLike
        The text file.

    Returns
    -------
    Trajectory
        ``N`` poses, float64, timestamps non-decreasing.

    Raises
    ------
    FileNotFoundError
        No such file.
    FormatError
        A line without 8 numeric fields (the message gives the line number), no poses at all, or a zero
        quaternion.
    InvalidValueError
        Non-finite values, or a quaternion whose norm is far from 1 (more than 1e-2: not a rotation, e.g.
        columns in the wrong order); the message gives the line.
    """
    rows: list[list[float]] = []
    linenos: list[int] = []
    with open(path, encoding="utf-8-sig") as f:
        for lineno, line in enumerate(f, 1):
            s = line.strip()
            if not s or s.startswith("#"):
                continue
            parts = s.replace(",", " ").split()
            if len(parts) != 8:
                raise FormatError(f"{path}:{lineno}: expected 8 numbers (a TUM trajectory line has 8 fields: "
                                  f"timestamp tx ty tz qx qy qz qw), got {len(parts)}: {s[:80]!r}")
            try:
                rows.append([float(v) for v in parts])
            except ValueError as exc:
                raise FormatError(f"{path}:{lineno}: non-numeric field (not a number) in TUM trajectory line "
                                  f"{s[:80]!r}") from exc
            linenos.append(lineno)
    if not rows:
        raise FormatError(f"trajectory file {path} holds no poses (only comments or blank lines; expected lines "
                          "'timestamp tx ty tz qx qy qz qw')")
    m = np.asarray(rows, dtype=np.float64)
    bad = ~np.all(np.isfinite(m), axis=1)
    if bad.any():
        raise InvalidValueError(f"{path}:{linenos[int(np.argmax(bad))]}: non-finite value in a pose; remove the "
                                "line or fix the file")
    norms = np.linalg.norm(m[:, 4:8], axis=1)
    if np.any(norms < 1e-8):
        i = int(np.argmax(norms < 1e-8))
        raise FormatError(f"{path}:{linenos[i]}: quaternion has zero length; a rotation needs a non-zero quaternion")
    bad = np.abs(norms - 1.0) > _QUAT_NORM_TOL
    if bad.any():
        i = int(np.argmax(bad))
        raise InvalidValueError(f"{path}:{linenos[i]}: quaternion norm {norms[i]:.4g} is not 1, so the pose is not "
                                "a rotation; the columns must be 'timestamp tx ty tz qx qy qz qw'")
    m = m[np.argsort(m[:, 0], kind="stable")]
    try:
        return Trajectory(m[:, 0], m[:, 1:4], m[:, 4:8])
    except (InvalidValueError, ShapeError) as exc:
        raise FormatError(f"{path}: {exc}") from exc


def write_tum(path: PathLike, trajectory: Trajectory, header: str | None = None) -> Path:
    """Write a trajectory as a TUM file, ``timestamp tx ty tz qx qy qz qw`` per line.

    Values are written as shortest round-trip float text, so reading the file back gives exactly the same
    timestamps, positions and quaternions.

    Parameters
    ----------
    path : str or os.PathLike
        Output file (overwritten).
    trajectory : Trajectory or array
        The poses, or camera-to-world matrices ``(N, 4, 4)``.
    header : str, optional
        Lines written first as ``#`` comments; a ``# timestamp tx ty tz qx qy qz qw`` column line follows
        unless the header already names the columns.

    Returns
    -------
    pathlib.Path
        ``path``.

    Raises
    ------
    InvalidValueError
        A pose matrix that is not rigid (checked when the trajectory was built from matrices).
    """
    traj = as_trajectory(trajectory, "trajectory")
    if traj._poses is not None:
        for i, p in enumerate(traj._poses):
            why = check_pose(p)
            if why:
                raise InvalidValueError(f"pose {i} of the trajectory to write is not rigid: {why}")
    columns = "timestamp tx ty tz qx qy qz qw"
    lines = [f"# {h}" for h in (header.splitlines() if header else [])]
    if not header or columns not in header:
        lines.append(f"# {columns}")
    for t, p, q in zip(traj.timestamps, traj.positions, traj.quaternions):
        lines.append(" ".join(repr(float(v)) for v in (t, *p, *q)))
    from ._atomic import write_file

    text = "\n".join(lines) + "\n"
    return write_file(path, lambda tmp: tmp.write_text(text, encoding="utf-8"), "writing the trajectory")


# ------------------------------------------------------------------------------------------- association
def association_indices(stamps_1: np.ndarray, stamps_2: np.ndarray, max_diff: float = 0.01,
                        offset_2: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """For each stamp in ``stamps_1`` ``(N,)``, the nearest stamp of ``stamps_2 + offset_2`` ``(M,)`` if it is
    within ``max_diff`` seconds; returns the index arrays ``(K,)`` of the matched pairs.

    Same rule as evo's ``sync.matching_time_indices``: on a tie the earlier stamp of ``stamps_2`` wins; a stamp
    of ``stamps_2`` may be matched more than once; unsorted ``stamps_2`` fall back to a brute-force search.
    """
    s1 = np.asarray(stamps_1, dtype=np.float64)
    s2 = np.array(stamps_2, dtype=np.float64, copy=True)
    if s1.ndim != 1 or s2.ndim != 1:
        raise ShapeError(f"timestamps must be 1-D, got {s1.shape} and {s2.shape}")
    if max_diff < 0:
        raise InvalidValueError(f"max_diff must be >= 0 seconds, got {max_diff}")
    if len(s1) == 0 or len(s2) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    s2 += offset_2
    if not np.all(np.diff(s2) >= 0):
        best = np.empty(len(s1), np.int64)
        for start in range(0, len(s1), 1024):  # bounded memory: 1024 x M differences at a time
            best[start:start + 1024] = np.argmin(np.abs(s2[None, :] - s1[start:start + 1024, None]), axis=1)
        ok = np.abs(s2[best] - s1) <= max_diff
        return np.flatnonzero(ok), best[ok]
    in_range = (s1 >= s2[0] - max_diff) & (s1 <= s2[-1] + max_diff)
    idx = np.minimum(np.searchsorted(s2, s1, side="right"), len(s2) - 1)
    diff_ub = s2[idx] - s1
    diff_lb = np.where(idx > 0, s1 - s2[np.maximum(idx - 1, 0)], np.inf)
    take_ub = (diff_ub <= max_diff) & (diff_ub < diff_lb)
    take_lb = ~take_ub & (diff_lb <= max_diff) & (diff_lb <= diff_ub)
    ok = in_range & (take_ub | take_lb)
    best = np.where(take_ub, idx, idx - 1)
    return np.flatnonzero(ok), best[ok].astype(np.int64)


def associate(reference: Trajectory, estimate: Trajectory, max_diff: float = 0.01,
              offset: float = 0.0) -> tuple[Trajectory, Trajectory]:
    """Synchronise two trajectories by timestamp: returns ``(reference', estimate')`` with the same number of
    poses, pose ``i`` of one matched to pose ``i`` of the other.

    Exactly evo's ``sync.associate_trajectories(ref, est, max_diff, offset_2=offset)`` (nearest time): the
    trajectory with fewer poses (the estimate when equal) is walked in order and each of its poses is paired
    with the nearest pose of the other within ``max_diff`` seconds; ``offset`` (seconds) is added to the
    estimate's timestamps for the matching only.

    Raises:
        InvalidValueError: no pair of timestamps within ``max_diff`` (the message gives both time ranges).
    """
    ref = as_trajectory(reference, "reference")
    est = as_trajectory(estimate, "estimate")
    second_longer = len(est) > len(ref)
    short, long_ = (ref, est) if second_longer else (est, ref)
    i_short, i_long = association_indices(short.timestamps, long_.timestamps, max_diff,
                                          offset if second_longer else -offset)
    if len(i_short) == 0:
        raise InvalidValueError(
            f"no matching timestamps between the reference ({ref.timestamps.min():.6f}..{ref.timestamps.max():.6f} s)"
            f" and the estimate ({est.timestamps.min():.6f}..{est.timestamps.max():.6f} s) with max_diff "
            f"{max_diff} s and offset {offset} s; check the files' clocks or raise max_diff")
    short, long_ = short.subset(i_short), long_.subset(i_long)
    return (short, long_) if second_longer else (long_, short)


# ------------------------------------------------------------------------------------------------ alignment
def check_associated(reference: Trajectory, estimate: Trajectory) -> None:
    """Raise unless the two trajectories are associated: the same, non-zero number of poses (pose ``i`` of
    one matched to pose ``i`` of the other, as :func:`associate` returns them)."""
    if len(reference) != len(estimate):
        raise ShapeError(f"reference and estimate must have the same number of poses, got {len(reference)} and "
                         f"{len(estimate)}; associate them first: ref, est = associate(ref, est)")
    if len(reference) == 0:
        raise InvalidValueError("empty trajectories")


def align_trajectory(estimate: Trajectory, reference: Trajectory, with_scale: bool = False
                     ) -> tuple[Trajectory, np.ndarray]:
    """Align associated ``estimate`` onto ``reference`` by :func:`umeyama_alignment` of their positions.

    Returns:
        ``(aligned estimate, S)`` where ``S`` ``(4, 4)`` is the similarity ``[s R, t; 0, 1]`` mapping estimate
        positions to the reference frame (the aligned poses are ``[R R_i, s R t_i + t]``).
    """
    est = as_trajectory(estimate, "estimate")
    ref = as_trajectory(reference, "reference")
    check_associated(ref, est)
    r, t, s = umeyama_alignment(est.positions, ref.positions, with_scale)
    rigid = np.eye(4)
    rigid[:3, :3], rigid[:3, 3] = r, t
    sim = rigid.copy()
    sim[:3, :3] *= s
    return est.transformed(rigid, scale=s), sim
