"""Trajectory metrics: TUM trajectory files, timestamp association, ATE and RPE.

This is how the paper scores ego-motion (section IV-C): the absolute trajectory error (ATE) of the tracked
camera against ground truth, plus the relative pose error (RPE) for drift. Everything is plain numpy in
float64 and follows the conventions of the TUM RGB-D benchmark and of ``evo`` (which the tests use as the
reference: same associations, same numbers to 1e-6):

- A trajectory is a list of camera-to-world poses with timestamps. Files are TUM format, one pose a line,
  ``timestamp tx ty tz qx qy qz qw`` (seconds, metres, unit quaternion with w last), ``#`` starts a comment.
- :func:`associate` pairs poses of two trajectories by nearest timestamp within ``max_diff`` seconds
  (evo's ``sync.associate_trajectories``, nearest-time method).
- :func:`ate` is the translation error ``|t_est_i - t_ref_i|`` per associated pose, optionally after the
  least-squares rigid (SE(3)) or similarity (Sim(3)) alignment of the estimate onto the reference (Horn /
  Umeyama). :func:`rpe` compares relative motions over ``delta`` frames:
  ``E_i = (Q_i^-1 Q_{i+delta})^-1 (P_i^-1 P_{i+delta})``, reporting ``|trans(E_i)|`` (metres) or the rotation
  angle of ``E_i`` (degrees).

    ref, est = associate(read_tum("groundtruth.txt"), read_tum("estimate.txt"))
    print(ate(ref, est, align=True).rmse, rpe(ref, est, relation="rotation").mean)
"""

from __future__ import annotations

import os
from pathlib import Path
from dataclasses import dataclass, field
from typing import Iterable, Literal, Union

import numpy as np

from .errors import FormatError, InvalidValueError, ShapeError

__all__ = [
    "Trajectory",
    "ErrorStatistics",
    "read_tum",
    "write_tum",
    "associate",
    "association_indices",
    "umeyama_alignment",
    "align_trajectory",
    "ate",
    "rpe",
    "quaternion_to_matrix",
    "matrix_to_quaternion",
    "rotation_angle",
    "check_pose",
]

PathLike = Union[str, "os.PathLike[str]"]
# rotation part of a pose must be orthonormal to this tolerance (7-Scenes' printed poses reach 2.4e-4)
_RIGID_TOL = 5e-3
# a TUM quaternion printed with 4 decimals has |q| within ~2e-4 of 1; more means a broken file
_QUAT_NORM_TOL = 1e-2


# ----------------------------------------------------------------------------------------------- rotations
def quaternion_to_matrix(quaternions: np.ndarray) -> np.ndarray:
    """Rotation matrices ``(..., 3, 3)`` from quaternions ``(..., 4)`` in TUM order ``(qx, qy, qz, qw)``.

    Quaternions need not be unit length: they are normalised (the same formula as evo's
    ``transformations.quaternion_matrix``; files print them with a few decimals). A zero quaternion raises
    :class:`InvalidValueError`.
    """
    q = np.asarray(quaternions, dtype=np.float64)
    if q.ndim < 1 or q.shape[-1] != 4:
        raise ShapeError(f"quaternions must have shape (..., 4) (qx, qy, qz, qw), got {q.shape}")
    n = np.einsum("...i,...i->...", q, q)
    tiny = n < np.finfo(np.float64).eps * 4.0
    if np.any(tiny):
        bad = int(np.flatnonzero(tiny.ravel())[0])
        raise InvalidValueError(f"quaternion {bad} has (nearly) zero length; a rotation needs a non-zero quaternion")
    q = q * np.sqrt(2.0 / n)[..., None]
    x, y, z, w = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    r = np.empty(q.shape[:-1] + (3, 3))
    r[..., 0, 0] = 1.0 - y * y - z * z
    r[..., 0, 1] = x * y - z * w
    r[..., 0, 2] = x * z + y * w
    r[..., 1, 0] = x * y + z * w
    r[..., 1, 1] = 1.0 - x * x - z * z
    r[..., 1, 2] = y * z - x * w
    r[..., 2, 0] = x * z - y * w
    r[..., 2, 1] = y * z + x * w
    r[..., 2, 2] = 1.0 - x * x - y * y
    return r


def matrix_to_quaternion(rotations: np.ndarray) -> np.ndarray:
    """Unit quaternions ``(..., 4)`` in TUM order ``(qx, qy, qz, qw)`` with ``qw >= 0`` from rotation matrices
    ``(..., 3, 3)`` (the nearest rotation is used when a matrix is not exactly orthonormal)."""
    from scipy.spatial.transform import Rotation

    r = np.asarray(rotations, dtype=np.float64)
    if r.ndim < 2 or r.shape[-2:] != (3, 3):
        raise ShapeError(f"rotations must have shape (..., 3, 3), got {r.shape}")
    if r.size == 0:
        return np.zeros(r.shape[:-2] + (4,))
    q = Rotation.from_matrix(r.reshape(-1, 3, 3)).as_quat()  # scalar last
    q = np.where(q[:, 3:4] < 0, -q, q)
    return q.reshape(r.shape[:-2] + (4,))


def rotation_angle(rotations: np.ndarray, degrees: bool = False) -> np.ndarray:
    """Rotation angles ``(N,)`` in ``[0, pi]`` (radians, or degrees) of rotation matrices ``(N, 3, 3)``.

    Uses ``atan2(|axis part|, cos part)``, accurate for tiny and for near-half-turn angles alike (``arccos`` of
    the trace loses half the digits near zero).
    """
    r = np.asarray(rotations, dtype=np.float64)
    if r.ndim != 3 or r.shape[1:] != (3, 3):
        raise ShapeError(f"rotations must have shape (N, 3, 3), got {r.shape}")
    s = 0.5 * np.sqrt((r[:, 2, 1] - r[:, 1, 2]) ** 2 + (r[:, 0, 2] - r[:, 2, 0]) ** 2 + (r[:, 1, 0] - r[:, 0, 1]) ** 2)
    c = 0.5 * (r[:, 0, 0] + r[:, 1, 1] + r[:, 2, 2] - 1.0)
    angle = np.arctan2(s, c)
    return np.degrees(angle) if degrees else angle


def _inverse_se3(poses: np.ndarray) -> np.ndarray:
    """Inverse of rigid transforms ``(N, 4, 4)``: ``[R^T, -R^T t]``."""
    inv = np.zeros_like(poses)
    rt = np.swapaxes(poses[:, :3, :3], 1, 2)
    inv[:, :3, :3] = rt
    inv[:, :3, 3] = -np.einsum("nij,nj->ni", rt, poses[:, :3, 3])
    inv[:, 3, 3] = 1.0
    return inv


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


def _as_trajectory(x, name: str) -> Trajectory:
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
    traj = _as_trajectory(trajectory, "trajectory")
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
    out = Path(path)
    out.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return out


def check_pose(pose: np.ndarray, tol: float = _RIGID_TOL) -> str | None:
    """Why ``pose`` is not a usable 4x4 rigid transform, or ``None`` when it is.

    Checks shape, finiteness, the bottom row ``(0, 0, 0, 1)``, orthonormality of the rotation part
    (``max |R^T R - I| <= tol``, default 5e-3: 7-Scenes' printed poses reach 2.4e-4) and ``det R > 0``
    (no reflection).
    """
    p = np.asarray(pose)
    if p.shape != (4, 4):
        return f"shape {p.shape} is not 4x4"
    if not np.all(np.isfinite(p)):
        return "non-finite values"
    if np.abs(p[3] - (0.0, 0.0, 0.0, 1.0)).max() > tol:
        return f"bottom row {p[3].tolist()} is not (0, 0, 0, 1)"
    r = p[:3, :3]
    err = float(np.abs(r.T @ r - np.eye(3)).max())
    if err > tol:
        return f"rotation is not orthonormal (|R^T R - I| = {err:.3g})"
    if np.linalg.det(r) <= 0:
        return "rotation is a reflection (det < 0)"
    return None


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
    ref = _as_trajectory(reference, "reference")
    est = _as_trajectory(estimate, "estimate")
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
def umeyama_alignment(source: np.ndarray, target: np.ndarray, with_scale: bool = False
                      ) -> tuple[np.ndarray, np.ndarray, float]:
    """Least-squares similarity ``target ~ s R source + t`` (Umeyama 1991; Horn's closed form).

    Args:
        source: ``(N, 3)`` points (e.g. estimated positions).
        target: ``(N, 3)`` points (e.g. reference positions).
        with_scale: also estimate the scale ``s`` (Sim(3)); else ``s = 1`` (SE(3)).

    Returns:
        ``(R (3, 3), t (3,), s)``.

    Raises:
        ShapeError: mismatched shapes. InvalidValueError: degenerate points (fewer than 2 distinct directions
        of spread, e.g. all collinear), where the rotation is not determined.
    """
    x = np.asarray(source, dtype=np.float64)
    y = np.asarray(target, dtype=np.float64)
    if x.shape != y.shape or x.ndim != 2 or x.shape[1] != 3:
        raise ShapeError(f"source and target must both have shape (N, 3), got {x.shape} and {y.shape}")
    n = len(x)
    if n == 0:
        raise InvalidValueError("cannot align empty point sets")
    mx, my = x.mean(axis=0), y.mean(axis=0)
    xc, yc = x - mx, y - my
    sigma_x = np.sum(xc * xc) / n
    cov = yc.T @ xc / n
    u, d, vt = np.linalg.svd(cov)
    # evo's test (fewer than 2 singular values above eps), made relative so collinear points are caught at
    # any scale
    if d[1] <= max(np.finfo(d.dtype).eps, 1e-12 * d[0]):
        raise InvalidValueError(f"degenerate point sets ({n} points, covariance rank < 2): the alignment "
                                "rotation is not determined; use more poses or align=False")
    s_mat = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0.0:
        s_mat[2, 2] = -1.0
    r = u @ s_mat @ vt
    c = float(np.trace(np.diag(d) @ s_mat) / sigma_x) if with_scale else 1.0
    t = my - c * (r @ mx)
    return r, t, c


def align_trajectory(estimate: Trajectory, reference: Trajectory, with_scale: bool = False
                     ) -> tuple[Trajectory, np.ndarray]:
    """Align associated ``estimate`` onto ``reference`` by :func:`umeyama_alignment` of their positions.

    Returns:
        ``(aligned estimate, S)`` where ``S`` ``(4, 4)`` is the similarity ``[s R, t; 0, 1]`` mapping estimate
        positions to the reference frame (the aligned poses are ``[R R_i, s R t_i + t]``).
    """
    est = _as_trajectory(estimate, "estimate")
    ref = _as_trajectory(reference, "reference")
    _check_same_length(ref, est)
    r, t, s = umeyama_alignment(est.positions, ref.positions, with_scale)
    rigid = np.eye(4)
    rigid[:3, :3], rigid[:3, 3] = r, t
    sim = rigid.copy()
    sim[:3, :3] *= s
    return est.transformed(rigid, scale=s), sim


def _check_same_length(ref: Trajectory, est: Trajectory) -> None:
    if len(ref) != len(est):
        raise ShapeError(f"reference and estimate must have the same number of poses, got {len(ref)} and "
                         f"{len(est)}; associate them first: ref, est = associate(ref, est)")
    if len(ref) == 0:
        raise InvalidValueError("empty trajectories")


# -------------------------------------------------------------------------------------------------- metrics
@dataclass(frozen=True)
class ErrorStatistics:
    """Per-pose (or per-pair) errors and their statistics (evo's names and definitions: ``std`` is the
    population standard deviation, ``sse`` the sum of squared errors).

    Attributes:
        errors: ``(K,)`` float64 errors in ``unit``.
        unit: ``"m"`` or ``"deg"``.
        alignment: ``(4, 4)`` similarity ``[s R, t; 0, 1]`` applied to the estimate before comparing; ``None``
            when not aligned.
        pairs: ``(K, 2)`` the index pairs compared (RPE only; ``None`` for ATE).
    """

    errors: np.ndarray
    unit: str
    rmse: float
    mean: float
    median: float
    std: float
    min: float
    max: float
    sse: float
    alignment: np.ndarray | None = None
    pairs: np.ndarray | None = None

    @classmethod
    def from_errors(cls, errors: np.ndarray, unit: str, alignment: np.ndarray | None = None,
                    pairs: np.ndarray | None = None) -> "ErrorStatistics":
        e = np.asarray(errors, dtype=np.float64)
        sq = e * e
        return cls(errors=e, unit=unit, rmse=float(np.sqrt(np.mean(sq))), mean=float(np.mean(e)),
                   median=float(np.median(e)), std=float(np.std(e)), min=float(np.min(e)), max=float(np.max(e)),
                   sse=float(np.sum(sq)), alignment=alignment, pairs=pairs)

    def as_dict(self) -> dict[str, float]:
        """``{"rmse", "mean", "median", "std", "min", "max", "sse"}`` as floats."""
        return {k: getattr(self, k) for k in ("rmse", "mean", "median", "std", "min", "max", "sse")}


def _maybe_align(ref: Trajectory, est: Trajectory, align: bool, with_scale: bool
                 ) -> tuple[Trajectory, np.ndarray | None]:
    if not (align or with_scale):
        return est, None
    if with_scale and not align:
        # scale only (evo's correct_scale without align): the scale of the Sim(3) fit, no rotation/translation
        _, _, s = umeyama_alignment(est.positions, ref.positions, True)
        sim = np.diag([s, s, s, 1.0])
        return est.transformed(np.eye(4), scale=s), sim
    aligned, sim = align_trajectory(est, ref, with_scale)
    return aligned, sim


def ate(reference: Trajectory, estimate: Trajectory, *, align: bool = False, with_scale: bool = False
        ) -> ErrorStatistics:
    """Absolute trajectory error (translation part, metres) of associated trajectories.

    Per pose ``|t_est_i - t_ref_i|`` (evo ``APE`` with ``PoseRelation.translation_part``).

    Args:
        reference, estimate: associated trajectories (same length, pose ``i`` matched to pose ``i``; see
            :func:`associate`), or camera-to-world poses ``(N, 4, 4)``.
        align: first align the estimate onto the reference with the least-squares rigid transform (SE(3),
            Horn/Umeyama), as ``evo_ape --align``.
        with_scale: also fit a scale (Sim(3), ``evo_ape --align --correct_scale``); alone (``align=False``)
            only the scale is corrected, as ``evo_ape --correct_scale``.
    """
    ref = _as_trajectory(reference, "reference")
    est = _as_trajectory(estimate, "estimate")
    _check_same_length(ref, est)
    est, sim = _maybe_align(ref, est, align, with_scale)
    return ErrorStatistics.from_errors(np.linalg.norm(est.positions - ref.positions, axis=1), "m", sim)


def rpe(reference: Trajectory, estimate: Trajectory, *, delta: int = 1,
        relation: Literal["translation", "rotation"] = "translation", all_pairs: bool = True,
        align: bool = False, with_scale: bool = False) -> ErrorStatistics:
    """Relative pose error over ``delta`` frames of associated trajectories.

    For each pair ``(i, j = i + delta)``: ``E = (Q_i^-1 Q_j)^-1 (P_i^-1 P_j)`` with reference poses ``Q`` and
    estimated poses ``P``; the error is ``|translation(E)|`` in metres (``relation="translation"``) or the
    rotation angle of ``E`` in degrees (``relation="rotation"``). Same as evo's ``main_rpe.rpe`` with
    ``PoseRelation.translation_part`` / ``rotation_angle_deg``, ``delta_unit=frames``.

    Args:
        reference, estimate: associated trajectories or poses ``(N, 4, 4)``.
        delta: frame offset, an integer >= 1.
        relation: ``"translation"`` (metres) or ``"rotation"`` (degrees).
        all_pairs: every ``i`` with ``i + delta < N`` (default, as the TUM benchmark and ``evo_rpe --all_pairs``);
            ``False`` takes consecutive, non-overlapping pairs ``(0, delta), (delta, 2 delta), ...`` (evo's
            default).
        align, with_scale: as for :func:`ate` (a rigid alignment leaves the RPE unchanged; a scale does not).
    """
    ref = _as_trajectory(reference, "reference")
    est = _as_trajectory(estimate, "estimate")
    _check_same_length(ref, est)
    if isinstance(delta, bool) or not float(delta).is_integer() or int(delta) < 1:
        raise InvalidValueError(f"delta is a number of frames, an integer >= 1; got {delta!r}")
    delta = int(delta)
    if relation not in ("translation", "rotation"):
        raise InvalidValueError(f"relation must be 'translation' or 'rotation', got {relation!r}")
    est, sim = _maybe_align(ref, est, align, with_scale)
    n = len(ref)
    if all_pairs:
        i = np.arange(0, max(n - delta, 0))
        j = i + delta
    else:
        ids = np.arange(0, n, delta)
        i, j = ids[:-1], ids[1:]
    if len(i) == 0:
        raise InvalidValueError(f"delta = {delta} frames leaves no pose pairs in {n} poses; use a smaller delta")
    q, p = ref.poses, est.poses
    q_rel = np.einsum("nij,njk->nik", _inverse_se3(q[i]), q[j])
    p_rel = np.einsum("nij,njk->nik", _inverse_se3(p[i]), p[j])
    e = np.einsum("nij,njk->nik", _inverse_se3(q_rel), p_rel)
    if relation == "translation":
        err, unit = np.linalg.norm(e[:, :3, 3], axis=1), "m"
    else:
        err, unit = rotation_angle(e[:, :3, :3], degrees=True), "deg"
    return ErrorStatistics.from_errors(err, unit, sim, np.stack([i, j], axis=1))
