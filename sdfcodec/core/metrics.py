"""Trajectory metrics: ATE and RPE (evo's ``metrics``), on the trajectories of :mod:`sdfcodec.core.trajectory`.

This is how the paper scores ego-motion (section IV-C): the absolute trajectory error (ATE) of the tracked
camera against ground truth, plus the relative pose error (RPE) for drift. Everything is plain numpy in
float64 and follows the conventions of the TUM RGB-D benchmark and of ``evo`` (which the tests use as the
reference: same associations, same numbers to 1e-6):

- :func:`ate` is the translation error ``|t_est_i - t_ref_i|`` per associated pose, optionally after the
  least-squares rigid (SE(3)) or similarity (Sim(3)) alignment of the estimate onto the reference (Horn /
  Umeyama). :func:`rpe` compares relative motions over ``delta`` frames:
  ``E_i = (Q_i^-1 Q_{i+delta})^-1 (P_i^-1 P_{i+delta})``, reporting ``|trans(E_i)|`` (metres) or the rotation
  angle of ``E_i`` (degrees).

Trajectories, TUM files and association live in :mod:`sdfcodec.core.trajectory`, rotations, rigid transforms and
the Umeyama alignment in :mod:`sdfcodec.core.geometry`; their names are re-exported here, where they used to be
defined, so ``from sdfcodec.core.metrics import read_tum`` keeps working.

    ref, est = associate(read_tum("groundtruth.txt"), read_tum("estimate.txt"))
    print(ate(ref, est, align=True).rmse, rpe(ref, est, relation="rotation").mean)
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from ..errors import InvalidValueError
from .geometry import (check_pose, matrix_to_quaternion, quaternion_to_matrix, rotation_angle, se3_compose,
                       se3_inverse, umeyama_alignment)
from .trajectory import (Trajectory, align_trajectory, as_trajectory, associate, association_indices,
                         check_associated, read_tum, write_tum)

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
    ref = as_trajectory(reference, "reference")
    est = as_trajectory(estimate, "estimate")
    check_associated(ref, est)
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
    ref = as_trajectory(reference, "reference")
    est = as_trajectory(estimate, "estimate")
    check_associated(ref, est)
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
    q_rel = se3_compose(se3_inverse(q[i]), q[j])
    p_rel = se3_compose(se3_inverse(p[i]), p[j])
    e = se3_compose(se3_inverse(q_rel), p_rel)
    if relation == "translation":
        err, unit = np.linalg.norm(e[:, :3, 3], axis=1), "m"
    else:
        err, unit = rotation_angle(e[:, :3, :3], degrees=True), "deg"
    return ErrorStatistics.from_errors(err, unit, sim, np.stack([i, j], axis=1))
