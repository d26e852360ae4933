"""Trajectory metrics: known answers on constructed trajectories, and agreement with evo on real TUM files."""

from __future__ import annotations

import copy
import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from sdfcodec.core import metrics
from sdfcodec.errors import FormatError, InvalidValueError, ShapeError
from sdfcodec.core.metrics import Trajectory, associate, ate, read_tum, rpe, write_tum

STATS = ("rmse", "mean", "median", "std", "min", "max", "sse")


def _random_trajectory(rng: np.random.Generator, n: int = 50, t0: float = 100.0, dt: float = 0.033) -> Trajectory:
    """A smooth-ish random walk with random orientations."""
    pos = np.cumsum(rng.normal(scale=0.02, size=(n, 3)), axis=0)
    rots = Rotation.from_rotvec(np.cumsum(rng.normal(scale=0.05, size=(n, 3)), axis=0))
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, :3, :3] = rots.as_matrix()
    poses[:, :3, 3] = pos
    return Trajectory.from_poses(poses, t0 + dt * np.arange(n))


def _left(traj: Trajectory, transform: np.ndarray, scale: float = 1.0) -> Trajectory:
    return traj.transformed(transform, scale)


def _rigid(rotvec, t) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    m[:3, 3] = t
    return m


# ------------------------------------------------------------------------------------------------ known answers
def test_constant_offset_ate(rng):
    ref = _random_trajectory(rng)
    offset = np.array([0.03, -0.04, 0.0])  # 5 cm
    est = Trajectory(ref.timestamps, ref.positions + offset, ref.quaternions)
    res = ate(ref, est)
    assert res.unit == "m" and res.alignment is None
    for k in ("rmse", "mean", "median", "min", "max"):
        assert getattr(res, k) == pytest.approx(0.05, abs=1e-12)
    assert res.std == pytest.approx(0.0, abs=1e-12)
    assert res.sse == pytest.approx(len(ref) * 0.05 ** 2, rel=1e-12)
    aligned = ate(ref, est, align=True)
    assert aligned.rmse == pytest.approx(0.0, abs=1e-12)
    np.testing.assert_allclose(aligned.alignment[:3, 3], -offset, atol=1e-12)
    # relative motion is untouched by a constant offset
    assert rpe(ref, est).max == pytest.approx(0.0, abs=1e-12)
    assert rpe(ref, est, relation="rotation").max == pytest.approx(0.0, abs=1e-9)


def test_rigid_and_similarity_alignment(rng):
    ref = _random_trajectory(rng)
    world = _rigid([0.3, -0.2, 1.0], [1.0, 2.0, -0.5])
    moved = _left(ref, world)
    assert ate(ref, moved).rmse > 0.5
    assert ate(ref, moved, align=True).rmse == pytest.approx(0.0, abs=1e-9)
    # a rigid change of world frame leaves the RPE alone
    assert rpe(ref, moved).max == pytest.approx(0.0, abs=1e-9)
    scaled = _left(ref, world, scale=0.5)
    assert ate(ref, scaled, align=True).rmse > 1e-3  # SE(3) cannot undo a scale
    res = ate(ref, scaled, align=True, with_scale=True)
    assert res.rmse == pytest.approx(0.0, abs=1e-9)
    s = np.cbrt(np.linalg.det(res.alignment[:3, :3]))
    assert s == pytest.approx(2.0, rel=1e-9)
    # Sim(3) alignment fixes the RPE translation scale too
    assert rpe(ref, scaled, align=True, with_scale=True).max == pytest.approx(0.0, abs=1e-9)
    assert rpe(ref, scaled).max > 1e-3


def test_rpe_known_drift():
    n = 20
    ref_poses = np.tile(np.eye(4), (n, 1, 1))
    ref_poses[:, 0, 3] = 0.1 * np.arange(n)  # 10 cm a frame along x
    est_poses = ref_poses.copy()
    est_poses[:, 0, 3] = 0.11 * np.arange(n)  # 1 cm a frame too far
    yaw = np.radians(0.5) * np.arange(n)  # and 0.5 degree a frame of spurious yaw (about the camera z axis)
    est_poses[:, :3, :3] = Rotation.from_euler("z", yaw[:, None]).as_matrix()
    ref, est = Trajectory.from_poses(ref_poses), Trajectory.from_poses(est_poses)
    rot = rpe(ref, est, relation="rotation")
    assert rot.unit == "deg"
    np.testing.assert_allclose(rot.errors, 0.5, atol=1e-9)
    rot5 = rpe(ref, est, relation="rotation", delta=5)
    np.testing.assert_allclose(rot5.errors, 2.5, atol=1e-9)
    assert len(rot5.errors) == n - 5 and rot5.pairs[0].tolist() == [0, 5]
    consecutive = rpe(ref, est, relation="rotation", delta=5, all_pairs=False)
    assert consecutive.pairs.tolist() == [[0, 5], [5, 10], [10, 15]]
    # translation: without the yaw, E = Q_rel^-1 P_rel is a pure 1 cm step per frame
    est_poses[:, :3, :3] = np.eye(3)
    trans = rpe(ref, Trajectory.from_poses(est_poses))
    assert trans.unit == "m"
    np.testing.assert_allclose(trans.errors, 0.01, atol=1e-12)
    np.testing.assert_allclose(rpe(ref, Trajectory.from_poses(est_poses), delta=4).errors, 0.04, atol=1e-12)


def test_stats_definitions():
    errors = np.array([1.0, 2.0, 4.0, 7.0])
    s = metrics.ErrorStatistics.from_errors(errors, "m")
    assert s.rmse == pytest.approx(math.sqrt(np.mean(errors ** 2)))
    assert s.mean == 3.5 and s.median == 3.0 and s.min == 1.0 and s.max == 7.0
    assert s.std == pytest.approx(np.std(errors)) and s.sse == 70.0
    assert set(s.as_dict()) == set(STATS)


def test_rotation_angle_accuracy():
    rng = np.random.default_rng(7)
    axes = rng.normal(size=(200, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    angles = np.concatenate([10.0 ** rng.uniform(-9, 0, 100), math.pi - 10.0 ** rng.uniform(-6, 0, 100)])
    mats = Rotation.from_rotvec(axes * angles[:, None]).as_matrix()
    np.testing.assert_allclose(metrics.rotation_angle(mats), angles, rtol=1e-7, atol=1e-12)
    np.testing.assert_allclose(metrics.rotation_angle(mats, degrees=True), np.degrees(angles), rtol=1e-7, atol=1e-10)


def test_quaternion_round_trip():
    rng = np.random.default_rng(3)
    q = rng.normal(size=(30, 4))
    r = metrics.quaternion_to_matrix(q)  # not unit: normalised
    np.testing.assert_allclose(r, Rotation.from_quat(q).as_matrix(), atol=1e-12)
    q2 = metrics.matrix_to_quaternion(r)
    assert np.all(q2[:, 3] >= 0)
    np.testing.assert_allclose(metrics.quaternion_to_matrix(q2), r, atol=1e-12)
    with pytest.raises(InvalidValueError, match="zero length"):
        metrics.quaternion_to_matrix(np.zeros((1, 4)))


def test_umeyama_recovers_similarity(rng):
    x = rng.normal(size=(40, 3))
    r = Rotation.from_rotvec([0.4, -1.2, 2.0]).as_matrix()
    t = np.array([0.5, -2.0, 3.0])
    y = 1.7 * x @ r.T + t
    r2, t2, s2 = metrics.umeyama_alignment(x, y, with_scale=True)
    np.testing.assert_allclose(r2, r, atol=1e-10)
    np.testing.assert_allclose(t2, t, atol=1e-10)
    assert s2 == pytest.approx(1.7, rel=1e-12)
    r3, _, s3 = metrics.umeyama_alignment(x, x @ r.T, with_scale=False)
    np.testing.assert_allclose(r3, r, atol=1e-10)
    assert s3 == 1.0
    line = np.outer(np.arange(10.0), [1.0, 2.0, 3.0])
    with pytest.raises(InvalidValueError, match="degenerate"):
        metrics.umeyama_alignment(line, line)
    with pytest.raises(ShapeError):
        metrics.umeyama_alignment(x, y[:-1])


# ----------------------------------------------------------------------------------------------- association
def test_association_rules():
    ref = np.array([0.0, 1.0, 2.0, 3.0, 4.0])
    # 1.02 is too far; 3.0 is exactly 1/128 s from both 2.9921875 and 3.0078125 (a tie: the earlier wins)
    est = np.array([0.005, 1.02, 2.0, 2.9921875, 3.0078125, 4.0])
    i1, i2 = metrics.association_indices(ref, est, max_diff=0.01)
    assert i1.tolist() == [0, 2, 3, 4] and i2.tolist() == [0, 2, 3, 5]
    i1, i2 = metrics.association_indices(est, ref, max_diff=0.01)
    assert i1.tolist() == [0, 2, 3, 4, 5] and i2.tolist() == [0, 2, 3, 3, 4]  # a stamp may be matched twice
    # offset is added to the second list
    i1, i2 = metrics.association_indices(ref, ref - 0.5, max_diff=0.01, offset_2=0.5)
    assert i1.tolist() == i2.tolist() == [0, 1, 2, 3, 4]
    # unsorted second list: brute force, same answer
    perm = np.array([3, 0, 4, 1, 2])
    i1, i2 = metrics.association_indices(ref, ref[perm] + 0.001, max_diff=0.01)
    assert i1.tolist() == [0, 1, 2, 3, 4] and perm[i2].tolist() == [0, 1, 2, 3, 4]


def test_associate_trajectories(rng):
    ref = _random_trajectory(rng, n=60)
    est = ref.subset(range(0, 60, 2))
    est = Trajectory(est.timestamps + 0.004, est.positions, est.quaternions)
    r, e = associate(ref, est)
    assert len(r) == len(e) == 30
    np.testing.assert_allclose(r.timestamps, ref.timestamps[::2])
    with pytest.raises(InvalidValueError, match="no matching timestamps"):
        associate(ref, Trajectory(est.timestamps + 100.0, est.positions, est.quaternions))
    with pytest.raises(ShapeError, match="associate"):
        ate(ref, est)


def test_association_matches_evo_on_random_stamps():
    evo_sync = pytest.importorskip("evo.core.sync")
    rng = np.random.default_rng(11)
    for _ in range(20):
        s1 = np.sort(rng.uniform(0, 10, rng.integers(5, 80)))
        s2 = np.sort(rng.uniform(0, 10, rng.integers(5, 80)))
        s2[::7] = np.round(s2[::7], 2)  # some exact and near ties
        s1[::5] = np.round(s1[::5], 2)
        for max_diff, offset in ((0.01, 0.0), (0.05, 0.02), (0.2, -0.1)):
            ours = metrics.association_indices(s1, s2, max_diff, offset)
            theirs = evo_sync.matching_time_indices(s1, s2, max_diff, offset)
            assert ours[0].tolist() == theirs[0] and ours[1].tolist() == theirs[1]


# ---------------------------------------------------------------------------------------------------- files
def test_tum_round_trip(tmp_path, rng):
    traj = _random_trajectory(rng, n=25, t0=1305031102.160407)
    path = tmp_path / "traj.txt"
    write_tum(path, traj, header="estimated by a test\ntimestamp tx ty tz qx qy qz qw")
    text = path.read_text()
    assert text.startswith("# estimated by a test\n# timestamp")
    back = read_tum(path)
    assert np.array_equal(back.timestamps, traj.timestamps)
    assert np.array_equal(back.positions, traj.positions)
    assert np.array_equal(back.quaternions, traj.quaternions)
    np.testing.assert_allclose(back.poses, traj.poses, atol=1e-12)


def test_tum_reader_errors(tmp_path):
    good = tmp_path / "good.txt"
    good.write_text("# comment\n\n1.0 0 0 0 0 0 0 1\n2.0,1,0,0,0,0,0,1\n")
    t = read_tum(good)
    assert len(t) == 2 and t.positions[1, 0] == 1.0
    bad = tmp_path / "bad.txt"
    bad.write_text("1.0 0 0 0 0 0 0 1\n2.0 0 0 0 0 0 1\n")
    with pytest.raises(FormatError, match=r"bad.txt:2: .*8 fields"):
        read_tum(bad)
    words = tmp_path / "words.txt"
    words.write_text("1.0 0 0 0 0 0 0 one\n")
    with pytest.raises(FormatError, match="non-numeric"):
        read_tum(words)
    empty = tmp_path / "empty.txt"
    empty.write_text("# nothing\n")
    with pytest.raises(FormatError, match="no poses"):
        read_tum(empty)
    zero = tmp_path / "zero.txt"
    zero.write_text("1.0 0 0 0 0 0 0 0\n")
    with pytest.raises(FormatError, match="zero length"):
        read_tum(zero)
    with pytest.raises(FileNotFoundError):
        read_tum(tmp_path / "missing.txt")


def test_input_checks(rng):
    ref = _random_trajectory(rng, n=10)
    with pytest.raises(InvalidValueError, match="delta"):
        rpe(ref, ref, delta=0)
    with pytest.raises(InvalidValueError, match="delta"):
        rpe(ref, ref, delta=1.5)
    with pytest.raises(InvalidValueError, match="no pose pairs"):
        rpe(ref, ref, delta=10)
    with pytest.raises(InvalidValueError, match="relation"):
        rpe(ref, ref, relation="full")
    with pytest.raises(ShapeError):
        Trajectory(np.zeros(3), np.zeros((2, 3)), np.zeros((3, 4)))
    with pytest.raises(InvalidValueError, match="NaN"):
        Trajectory(np.array([np.nan]), np.zeros((1, 3)), np.array([[0, 0, 0, 1.0]]))
    # poses (N, 4, 4), numpy or torch, are accepted wherever a Trajectory is
    torch = pytest.importorskip("torch")
    poses = torch.as_tensor(ref.poses)
    assert ate(poses, ref.poses).rmse == pytest.approx(0.0, abs=1e-12)


# ------------------------------------------------------------------------------------- agreement with evo
PAIRS = [
    ("freiburg1_xyz-groundtruth.txt", "freiburg1_xyz-rgbdslam.txt"),
    ("freiburg1_xyz-groundtruth.txt", "freiburg1_xyz-rgbdslam_drift.txt"),
    ("freiburg1_xyz-groundtruth.txt", "freiburg1_xyz-ORB_kf_mono.txt"),
    ("fr2_desk_groundtruth.txt", "fr2_desk_ORB.txt"),
    ("fr2_desk_groundtruth.txt", "fr2_desk_ORB_kf_mono.txt"),
    ("freiburg1_xyz-rgbdslam.txt", "freiburg1_xyz-rgbdslam_drift_short.txt"),
]


@pytest.mark.parametrize("ref_name,est_name", PAIRS)
def test_agrees_with_evo(shared_data, ref_name, est_name):
    file_interface = pytest.importorskip("evo.tools.file_interface")
    from evo import main_ape, main_rpe
    from evo.core import metrics as evo_metrics
    from evo.core import sync

    folder = shared_data / "tum-trajectories"
    evo_ref = file_interface.read_tum_trajectory_file(str(folder / ref_name))
    evo_est = file_interface.read_tum_trajectory_file(str(folder / est_name))
    evo_ref, evo_est = sync.associate_trajectories(evo_ref, evo_est, max_diff=0.01)
    ref, est = associate(read_tum(folder / ref_name), read_tum(folder / est_name), max_diff=0.01)
    # same association, pose by pose
    assert np.array_equal(ref.timestamps, evo_ref.timestamps)
    assert np.array_equal(est.timestamps, evo_est.timestamps)

    worst = 0.0
    for align, scale in ((False, False), (True, False), (True, True), (False, True)):
        theirs = main_ape.ape(copy.deepcopy(evo_ref), copy.deepcopy(evo_est),
                              evo_metrics.PoseRelation.translation_part, align=align, correct_scale=scale).stats
        ours = ate(ref, est, align=align, with_scale=scale)
        for k in STATS:
            tol = 1e-6 * max(1.0, abs(theirs[k])) if k == "sse" else 1e-6  # sse is a sum over ~2000 poses
            assert abs(getattr(ours, k) - theirs[k]) <= tol, (align, scale, k)
            worst = max(worst, abs(getattr(ours, k) - theirs[k]) if k != "sse" else 0.0)

    relations = (("translation", evo_metrics.PoseRelation.translation_part),
                 ("rotation", evo_metrics.PoseRelation.rotation_angle_deg))
    for ours_rel, evo_rel in relations:
        for delta, all_pairs, align, scale in ((1, True, False, False), (10, True, False, False),
                                               (5, False, False, False), (3, True, True, True)):
            theirs = main_rpe.rpe(copy.deepcopy(evo_ref), copy.deepcopy(evo_est), evo_rel, delta=delta,
                                  delta_unit=evo_metrics.Unit.frames, all_pairs=all_pairs, align=align,
                                  correct_scale=scale).stats
            ours = rpe(ref, est, delta=delta, relation=ours_rel, all_pairs=all_pairs, align=align, with_scale=scale)
            for k in STATS:
                tol = 1e-6 * max(1.0, abs(theirs[k])) if k == "sse" else 1e-6
                assert abs(getattr(ours, k) - theirs[k]) <= tol, (ours_rel, delta, all_pairs, align, k)
    assert worst < 1e-6


def test_old_import_paths_are_the_moved_objects():
    """Trajectories live in sdfcodec.core.trajectory and rotations in sdfcodec.core.geometry; sdfcodec.core.metrics re-exports
    the very same objects (no copies that could drift apart)."""
    from sdfcodec.core import geometry, trajectory

    for name in ("Trajectory", "read_tum", "write_tum", "associate", "association_indices", "align_trajectory"):
        assert getattr(metrics, name) is getattr(trajectory, name), name
    for name in ("umeyama_alignment", "quaternion_to_matrix", "matrix_to_quaternion", "rotation_angle",
                 "check_pose"):
        assert getattr(metrics, name) is getattr(geometry, name), name
    assert set(metrics.__all__) <= set(dir(metrics))


def test_se3_helpers(rng):
    from sdfcodec.core import geometry

    poses = np.stack([geometry.se3_exp(rng.normal(scale=0.5, size=6)) for _ in range(5)])
    np.testing.assert_allclose(geometry.se3_compose(geometry.se3_inverse(poses), poses), np.tile(np.eye(4), (5, 1, 1)),
                               atol=1e-12)
    np.testing.assert_allclose(geometry.se3_compose(poses, poses[::-1]), poses @ poses[::-1], atol=1e-12)
    assert all(geometry.check_pose(p) is None for p in poses)
    assert "reflection" in geometry.check_pose(np.diag([1.0, 1.0, -1.0, 1.0]))
    for r in (geometry.rot_x(0.3), geometry.rot_y(-1.2), geometry.rot_z(2.0), geometry.rotation_to((1, -2, 0.5))):
        np.testing.assert_allclose(r.T @ r, np.eye(3), atol=1e-12)
        assert np.linalg.det(r) == pytest.approx(1.0)
    w = rng.normal(size=3)
    np.testing.assert_allclose(geometry.hat(w) @ np.array([1.0, 2.0, 3.0]), np.cross(w, [1.0, 2.0, 3.0]))
