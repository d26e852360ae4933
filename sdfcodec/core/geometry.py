"""Rotations and rigid transforms in one place (in the style of evo's ``lie_algebra``), plain numpy float64.

Everything that turns, composes or aligns poses uses these: the trajectory metrics
(:mod:`sdfcodec.core.metrics`), trajectories and TUM files (:mod:`sdfcodec.core.trajectory`), the SDF Tracker
(:mod:`sdfcodec.tracking.tracker`) and the query shapes of descriptor search (:mod:`sdfcodec.search`).

Conventions: rotation matrices act on column vectors (``p' = R p``); a rigid transform is a ``(4, 4)``
matrix ``[R, t; 0, 1]``; quaternions are in TUM order ``(qx, qy, qz, qw)`` (scalar last); a twist is
``xi = (v, w)`` ``(6,)`` with ``v`` in metres and ``w`` a rotation vector in radians.
"""

from __future__ import annotations

import math
from typing import Any, Sequence

import numpy as np

from ..errors import InvalidValueError, ShapeError

__all__ = [
    "RIGID_TOL",
    "rot_x",
    "rot_y",
    "rot_z",
    "hat",
    "axis_rotations",
    "rotation_to",
    "quaternion_to_matrix",
    "matrix_to_quaternion",
    "rotation_angle",
    "se3_exp",
    "se3_inverse",
    "se3_compose",
    "orthonormality_error",
    "check_pose",
    "umeyama_alignment",
]

#: Default tolerance of :func:`check_pose`: the rotation part of a pose must be orthonormal to this
#: (7-Scenes' printed poses reach 2.4e-4).
RIGID_TOL = 5e-3


# ----------------------------------------------------------------------------------------------- rotations
def rot_x(a: float) -> np.ndarray:
    """Rotation by ``a`` radians about ``+x``: ``(3, 3)`` float64."""
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0, 0], [0, c, -s], [0, s, c]])


def rot_y(a: float) -> np.ndarray:
    """Rotation by ``a`` radians about ``+y``: ``(3, 3)`` float64."""
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0, s], [0, 1.0, 0], [-s, 0, c]])


def rot_z(a: float) -> np.ndarray:
    """Rotation by ``a`` radians about ``+z``: ``(3, 3)`` float64."""
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def hat(w: np.ndarray) -> np.ndarray:
    """The skew-symmetric matrix ``[w]x`` ``(3, 3)`` float64 of a vector ``w`` ``(3,)``: ``[w]x p = w x p``."""
    return np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


def axis_rotations() -> np.ndarray:
    """The 24 proper rotations of the cube (signed permutation matrices with determinant +1).

    Returns
    -------
    np.ndarray
        ``(24, 3, 3)`` float64, the identity first.
    """
    out = []
    for perm in ((0, 1, 2), (0, 2, 1), (1, 0, 2), (1, 2, 0), (2, 0, 1), (2, 1, 0)):
        for signs in np.ndindex(2, 2, 2):
            r = np.zeros((3, 3))
            for row, (col, s) in enumerate(zip(perm, signs)):
                r[row, col] = -1.0 if s else 1.0
            if np.linalg.det(r) > 0:
                out.append(r)
    return np.stack(out)


def rotation_to(direction: Sequence[float]) -> np.ndarray:
    """The smallest rotation taking ``+z`` onto ``direction`` (normalised on use).

    Returns
    -------
    np.ndarray
        ``(3, 3)`` float64; ``R @ (0, 0, 1)`` is the unit ``direction``.
    """
    d = np.asarray(direction, dtype=np.float64).reshape(3)
    n = np.linalg.norm(d)
    if not np.isfinite(n) or n < 1e-12:
        raise InvalidValueError(f"a direction needs a finite, non-zero vector, got {list(d)}")
    d = d / n
    z = np.array([0.0, 0.0, 1.0])
    c = float(z @ d)
    if c < -1 + 1e-12:  # opposite: half a turn about x
        return np.diag([1.0, -1.0, -1.0])
    vx = hat(np.cross(z, d))
    return np.eye(3) + vx + vx @ vx / (1.0 + c)


# --------------------------------------------------------------------------------------------- quaternions
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


# -------------------------------------------------------------------------------------------------- SE(3)
def se3_exp(xi: Any) -> np.ndarray:
    """The exponential map of a twist ``xi = (v, w)`` ``(6,)`` (``v`` metres, ``w`` rotation vector in
    radians) to a rigid transform ``(4, 4)`` float64: ``R = exp([w]x)``, ``t = V v`` with
    ``V = I + (1 - cos a) / a^2 [w]x + (a - sin a) / a^3 [w]x^2``, ``a = |w|``."""
    xi = np.asarray(xi, dtype=np.float64).reshape(-1)
    if xi.shape != (6,):
        raise ShapeError(f"a twist has 6 components (vx, vy, vz, wx, wy, wz), got shape {xi.shape}")
    v, w = xi[:3], xi[3:]
    a2 = float(w @ w)
    a = math.sqrt(a2)
    k = hat(w)
    k2 = k @ k
    if a < 1e-8:  # Taylor expansions
        s1, s2, s3 = 1.0 - a2 / 6.0, 0.5 - a2 / 24.0, 1.0 / 6.0 - a2 / 120.0
    else:
        s1, s2, s3 = math.sin(a) / a, (1.0 - math.cos(a)) / a2, (a - math.sin(a)) / (a2 * a)
    out = np.eye(4)
    out[:3, :3] = np.eye(3) + s1 * k + s2 * k2
    out[:3, 3] = (np.eye(3) + s2 * k + s3 * k2) @ v
    return out


def se3_inverse(poses: np.ndarray) -> np.ndarray:
    """Inverse of rigid transforms ``(N, 4, 4)`` float64: ``[R^T, -R^T t]`` (exact for rigid input, no
    general matrix inverse)."""
    inv = np.zeros_like(poses)
    rt = np.swapaxes(poses[:, :3, :3], 1, 2)
    inv[:, :3, :3] = rt
    inv[:, :3, 3] = -np.einsum("nij,nj->ni", rt, poses[:, :3, 3])
    inv[:, 3, 3] = 1.0
    return inv


def se3_compose(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Pairwise products ``a_i @ b_i`` of transforms ``(N, 4, 4)`` -> ``(N, 4, 4)`` float64."""
    return np.einsum("nij,njk->nik", a, b)


def orthonormality_error(rotation: np.ndarray) -> float:
    """``max |R^T R - I|`` of a ``(3, 3)`` matrix: 0 for a rotation (or a reflection; check ``det R`` too).
    Callers choose their own tolerance (:func:`check_pose` 5e-3 for printed poses, the tracker 1e-3)."""
    r = np.asarray(rotation)
    return float(np.abs(r.T @ r - np.eye(3)).max())


def check_pose(pose: np.ndarray, tol: float = RIGID_TOL) -> str | None:
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
    err = orthonormality_error(r)
    if err > tol:
        return f"rotation is not orthonormal (|R^T R - I| = {err:.3g})"
    if np.linalg.det(r) <= 0:
        return "rotation is a reflection (det < 0)"
    return None


# ---------------------------------------------------------------------------------------------- alignment
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
