"""RGB-D sequence readers (sdfcodec.data.sequences).

Independent expectations: the real files in ../shared/data (7-Scenes redkitchen: 500 frames, fx = 585; one
TUM depth frame at 5000 per metre; TUM trajectories, cross-checked with the `evo` package), PNG pixels
decoded here with Pillow rather than open3d, poses parsed here with numpy, and hand-made sequences whose
poses and timestamps are known in closed form. Bad input must raise a clear error or be skipped, counted
and reported, never produce a wrong sequence.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from sdfcodec.data.sequences import (
    TUM_INTRINSICS,
    Intrinsics,
    associate,
    check_pose,
    matrix_to_quaternion,
    open_sequence,
    quaternion_to_matrix,
    read_depth_png,
    write_depth_png,
)
from sdfcodec.core.metrics import read_tum as read_tum_trajectory  # the one TUM reader lives in sdfcodec.core.metrics
from sdfcodec.errors import FormatError, InvalidValueError, SDFCodecError, SDFCodecWarning

KITCHEN = "7scenes-redkitchen"


def _rot_z(a: float) -> np.ndarray:
    return np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1.0]])


def _pose(t, angle: float) -> np.ndarray:
    p = np.eye(4)
    p[:3, :3] = _rot_z(angle)
    p[:3, 3] = t
    return p


def _write_gt(path: Path, stamps, poses) -> None:
    lines = ["# ground truth trajectory", "# timestamp tx ty tz qx qy qz qw"]
    for s, p in zip(stamps, poses):
        q = matrix_to_quaternion(p[:3, :3])
        lines.append(f"{s:.6f} " + " ".join(f"{v:.9f}" for v in (*p[:3, 3], *q)))
    path.write_text("\n".join(lines) + "\n")


def _make_tum(root: Path, stamps, gt_stamps=None, gt_poses=None, depth_m: float = 1.5, size=(8, 6),
              intrinsics_file: bool = True) -> Path:
    """A tiny TUM-layout sequence: constant-depth frames at ``stamps``; ground truth if given."""
    (root / "depth").mkdir(parents=True)
    lines = ["# depth maps", "# timestamp filename"]
    for s in stamps:
        name = f"depth/{s:.6f}.png"
        write_depth_png(root / name, np.full(size[::-1], depth_m), 5000)
        lines.append(f"{s:.6f} {name}")
    (root / "depth.txt").write_text("\n".join(lines) + "\n")
    if gt_stamps is not None:
        _write_gt(root / "groundtruth.txt", gt_stamps, gt_poses)
    if intrinsics_file:
        (root / "intrinsics.txt").write_text("# fx fy cx cy width height\n10 11 3.5 2.5 8 6\n")
    return root


def _make_7scenes(root: Path, n: int = 5, depth_mm: int = 1500) -> Path:
    o3d = pytest.importorskip("open3d")
    root.mkdir(parents=True)
    for i in range(n):
        o3d.io.write_image(str(root / f"frame-{i:06d}.depth.png"),
                           o3d.geometry.Image(np.full((6, 8), depth_mm, np.uint16)))
        np.savetxt(root / f"frame-{i:06d}.pose.txt", _pose((0.1 * i, 0, 0), 0.05 * i))
    np.savetxt(root / "camera-intrinsics.txt", np.array([[10, 0, 3.5], [0, 10, 2.5], [0, 0, 1.0]]))
    return root


# ----------------------------------------------------------------------------------------- real data
def test_kitchen_7scenes_layout(shared_data):
    pil = pytest.importorskip("PIL.Image")
    root = shared_data / KITCHEN
    seq = open_sequence(root)
    assert seq.layout == "7scenes" and len(seq) == 500 and seq.skipped == 0
    assert seq.depth_scale == 1000.0
    assert seq.intrinsics == Intrinsics(585.0, 585.0, 320.0, 240.0, 640, 480)  # README: fx = fy = 585
    np.testing.assert_allclose(seq.timestamps[:3], [0.0, 1 / 30, 2 / 30])
    for i in (0, 137, 499):
        frame = seq[i]
        raw = np.asarray(pil.open(root / f"frame-{i:06d}.depth.png"))  # decoded by Pillow, not open3d
        assert frame.depth.dtype == np.float32 and frame.depth.shape == (480, 640)
        np.testing.assert_allclose(frame.depth, raw.astype(np.float64) / 1000.0, rtol=1e-6)
        assert (frame.depth == 0).any()  # the kitchen has pixels with no reading, kept as 0
        np.testing.assert_array_equal(frame.pose, np.loadtxt(root / f"frame-{i:06d}.pose.txt"))
        assert frame.pose.dtype == np.float64 and frame.index == i
    assert len(seq.trajectory) == 500
    # README: the camera travels about 3.4 m over the first 450 frames
    steps = np.linalg.norm(np.diff(seq.trajectory.positions[:450], axis=0), axis=1)
    assert 3.0 < steps.sum() < 3.8


def test_kitchen_slicing_and_iteration(shared_data):
    seq = open_sequence(shared_data / KITCHEN)
    head = seq[:3]
    assert len(head) == 3 and len(seq) == 500
    assert [f.path.name for f in head] == [f"frame-{i:06d}.depth.png" for i in range(3)]
    assert seq[-1].path.name == "frame-000499.depth.png"
    assert len(seq[::100]) == 5 and seq[::100][1].path.name == "frame-000100.depth.png"
    with pytest.raises(IndexError):
        seq[500]
    assert seq.poses.shape == (500, 4, 4) and np.isfinite(seq.poses).all()


def test_kitchen_wrong_scale_suggests_millimetres(shared_data):
    with pytest.raises(InvalidValueError, match=r"depth_scale=1000 \(median 1\.\d+ m\)"):
        open_sequence(shared_data / KITCHEN, depth_scale=1.0)  # median ~1900 m
    with pytest.raises(InvalidValueError, match=r"depth_scale=1000"):
        open_sequence(shared_data / KITCHEN, depth_scale=1e6)  # median ~2 mm
    with pytest.warns(SDFCodecWarning, match=r"depth_scale=1000"):  # 0.38 m: possible, but unusual
        open_sequence(shared_data / KITCHEN, depth_scale=5000.0)


def test_tum_depth_frame_scale(shared_data, tmp_path):
    pil = pytest.importorskip("PIL.Image")
    src = shared_data / "tum-depth-frame" / "TUM_depth.png"
    root = tmp_path / "rgbd_dataset_freiburg1_demo"
    (root / "depth").mkdir(parents=True)
    shutil.copy(src, root / "depth" / "100.000000.png")
    (root / "depth.txt").write_text("# timestamp filename\n100.000000 depth/100.000000.png\n")
    _write_gt(root / "groundtruth.txt", [99.99, 100.01], [_pose((1, 2, 3), 0.0), _pose((1, 2, 3), 0.0)])
    seq = open_sequence(root)
    assert seq.layout == "tum" and seq.depth_scale == 5000.0
    # the folder name says freiburg1: TUM's published fr1 calibration
    assert (seq.intrinsics.fx, seq.intrinsics.fy, seq.intrinsics.cx, seq.intrinsics.cy) == (517.3, 516.5, 318.6, 255.3)
    assert (seq.intrinsics.width, seq.intrinsics.height) == (640, 480)
    raw = np.asarray(pil.open(src)).astype(np.float64)
    depth = seq[0].depth
    np.testing.assert_allclose(depth, raw / 5000.0, rtol=1e-6)
    assert np.median(depth[depth > 0]) == pytest.approx(2.415, abs=1e-3)  # data README: 5000 = 1 m
    # read as millimetres, the same frame would put the median at 12 m: reported with the right scale
    with pytest.warns(SDFCodecWarning, match=r"depth_scale=5000 \(median 2\.4\d m\)"):
        open_sequence(root, depth_scale=1000)


def test_tum_trajectories_match_evo(shared_data):
    file_interface = pytest.importorskip("evo.tools.file_interface")
    folder = shared_data / "tum-trajectories"
    files = sorted(folder.glob("*.txt"))
    assert len(files) >= 6
    for path in files:
        ours = read_tum_trajectory(path)
        ref = file_interface.read_tum_trajectory_file(str(path))
        np.testing.assert_allclose(ours.timestamps, ref.timestamps)
        np.testing.assert_allclose(ours.positions, ref.positions_xyz)
        np.testing.assert_allclose(ours.poses, np.stack(ref.poses_se3), atol=1e-12)
    gt = read_tum_trajectory(folder / "freiburg1_xyz-groundtruth.txt")
    assert len(gt) == 3000  # 3003 lines, 3 of them comments
    assert gt.timestamps[0] == 1305031098.6659
    np.testing.assert_allclose(gt.positions[0], [1.3563, 0.6305, 1.6380])


# ------------------------------------------------------------------------------------- poses, timing
def test_quaternions_round_trip(rng):
    from scipy.spatial.transform import Rotation

    rots = Rotation.random(50, random_state=1)
    r = rots.as_matrix()
    np.testing.assert_allclose(quaternion_to_matrix(rots.as_quat()), r, atol=1e-12)  # scipy: (x, y, z, w)
    np.testing.assert_allclose(quaternion_to_matrix(matrix_to_quaternion(r)), r, atol=1e-12)
    assert (matrix_to_quaternion(r)[:, 3] >= 0).all()


def test_check_pose():
    assert check_pose(_pose((1, 2, 3), 0.3)) is None
    assert "non-finite" in check_pose(np.full((4, 4), np.inf))
    assert "orthonormal" in check_pose(np.diag([2.0, 2.0, 2.0, 1.0]))
    assert "reflection" in check_pose(np.diag([1.0, 1.0, -1.0, 1.0]))
    bad = _pose((0, 0, 0), 0.0)
    bad[3, 0] = 1.0
    assert "bottom row" in check_pose(bad)


def test_associate_like_tums_script():
    first = np.array([0.000, 0.033, 0.066, 1.000, 2.000])
    second = np.array([0.001, 0.030, 0.070, 0.500, 2.019, 2.0195])
    # greedy by difference, one-to-one: 2.000 takes 2.019 (0.019 < 0.0195); 1.000 has nothing within 0.02
    assert associate(first, second, 0.02) == [(0, 0), (1, 1), (2, 2), (4, 4)]
    assert associate(first, second, 0.02, offset=10.0) == []
    assert associate([0.0, 0.01], [0.004], 0.02) == [(0, 0)]  # one-to-one: the closer one wins
    assert associate(first, second - 0.5, 0.02, offset=0.5) == [(0, 0), (1, 1), (2, 2), (4, 4)]


def test_tum_ground_truth_interpolated_and_nearest(tmp_path):
    # ground truth at 100 Hz of a motion known in closed form: x = 0.5 t m, yaw = 0.8 t rad
    gt_t = 10.0 + np.arange(0, 101) * 0.01
    truth = lambda t: _pose((0.5 * (t - 10), 0.2, 1.0), 0.8 * (t - 10))  # noqa: E731
    depth_t = 10.0 + np.array([0.0133, 0.3467, 0.6801])
    root = _make_tum(tmp_path / "seq", depth_t, gt_t, [truth(t) for t in gt_t])
    seq = open_sequence(root)
    assert len(seq) == 3 and seq.skipped == 0
    assert len(seq.trajectory) == 101
    for frame, t in zip(seq, depth_t):
        np.testing.assert_allclose(frame.pose, truth(t), atol=1e-7)  # lerp + slerp of a constant-rate motion
        assert frame.timestamp == pytest.approx(t)
        np.testing.assert_allclose(frame.depth, 1.5)
    near = open_sequence(root, pose_lookup="nearest")
    for frame, t in zip(near, depth_t):
        np.testing.assert_allclose(frame.pose, truth(round(t, 2)), atol=1e-7)
    assert seq.intrinsics == Intrinsics(10.0, 11.0, 3.5, 2.5, 8, 6)  # from intrinsics.txt


def test_tum_partial_association_is_counted_and_reported(tmp_path):
    gt_t = np.arange(0, 51) * 0.01  # ground truth covers 0 .. 0.5 s only
    root = _make_tum(tmp_path / "seq", np.arange(30) / 30.0, gt_t, [_pose((t, 0, 0), 0.0) for t in gt_t])
    with pytest.warns(SDFCodecWarning, match=r"skipped 14 of 30 frames.*without ground truth within 0.02 s"):
        seq = open_sequence(root)
    assert len(seq) == 16 and seq.skipped == 14
    assert seq.skip_reasons == {"without ground truth within 0.02 s": 14}
    assert seq.timestamps.max() <= 0.52
    kept = open_sequence(root, missing_pose="keep")
    assert len(kept) == 30 and kept.skipped == 0 and kept[-1].pose is None
    with pytest.raises(InvalidValueError, match=r"t=0\.533333: without ground truth.*missing_pose='skip'"):
        open_sequence(root, missing_pose="error")


def test_tum_timestamps_that_never_associate(tmp_path):
    gt_t = 500.0 + np.arange(20) * 0.01  # another clock
    root = _make_tum(tmp_path / "seq", np.arange(5) / 30.0, gt_t, [_pose((0, 0, 0), 0.0)] * 20)
    with pytest.raises(InvalidValueError, match=r"no depth frame .* within 0\.02 s: depth spans \[0\.000, 0\.133\] s, "
                                                r"groundtruth\.txt spans \[500\.000, 500\.190\] s"):
        open_sequence(root)
    assert len(open_sequence(root, max_difference=1000.0)) == 5


def test_tum_without_ground_truth(tmp_path):
    root = _make_tum(tmp_path / "seq", np.arange(4) / 30.0)
    with pytest.raises(FormatError, match="no groundtruth.txt.*missing_pose='keep'"):
        open_sequence(root)
    seq = open_sequence(root, missing_pose="keep")
    assert len(seq) == 4 and seq.trajectory is None and seq[0].pose is None


# -------------------------------------------------------------------------------------- intrinsics
@pytest.mark.parametrize("name, expected", [
    ("rgbd_dataset_freiburg1_xyz", TUM_INTRINSICS["freiburg1"]),
    ("rgbd_dataset_freiburg2_desk", TUM_INTRINSICS["freiburg2"]),
    ("fr3_office", (525.0, 525.0, 319.5, 239.5)),
])
def test_tum_intrinsics_from_folder_name(tmp_path, name, expected):
    gt_t = np.arange(10) * 0.01
    root = _make_tum(tmp_path / name, [0.0, 0.05], gt_t, [_pose((0, 0, 0), 0.0)] * 10, intrinsics_file=False)
    k = open_sequence(root).intrinsics
    assert (k.fx, k.fy, k.cx, k.cy) == expected and (k.width, k.height) == (8, 6)


def test_tum_intrinsics_explicit_file_and_default(tmp_path):
    gt_t = np.arange(10) * 0.01
    poses = [_pose((0, 0, 0), 0.0)] * 10
    root = _make_tum(tmp_path / "rgbd_dataset_freiburg1_room", [0.0], gt_t, poses)  # has intrinsics.txt
    assert open_sequence(root).intrinsics.fx == 10.0  # the file beats the folder name
    assert open_sequence(root, intrinsics="fr2").intrinsics.fx == 520.9
    k = np.array([[300.0, 0, 4], [0, 301.0, 3], [0, 0, 1]])
    assert open_sequence(root, intrinsics=k).intrinsics == Intrinsics(300.0, 301.0, 4.0, 3.0, 8, 6)
    with pytest.raises(InvalidValueError, match="unknown intrinsics preset 'kinect9'"):
        open_sequence(root, intrinsics="kinect9")
    plain = _make_tum(tmp_path / "my_camera", [0.0], gt_t, poses, intrinsics_file=False)
    with pytest.warns(SDFCodecWarning, match="names no camera.*fx=525.0"):
        assert open_sequence(plain).intrinsics.fx == 525.0
    (plain / "intrinsics.txt").write_text("1 2 3\n")
    with pytest.raises(FormatError, match="3x3 K or 'fx fy cx cy"):
        open_sequence(plain)
    (plain / "intrinsics.txt").write_text("10 10 3.5 2.5 640 480\n")
    with pytest.raises(FormatError, match="640x480 images but the depth images are 8x6"):
        open_sequence(plain)


# ------------------------------------------------------------------------------------------ bad input
def test_bad_pngs_raise_format_errors(tmp_path):
    o3d = pytest.importorskip("open3d")
    eight = tmp_path / "eight.png"
    o3d.io.write_image(str(eight), o3d.geometry.Image(np.full((6, 8), 200, np.uint8)))
    with pytest.raises(FormatError, match=r"eight\.png is 8-bit; depth must be a 16-bit PNG"):
        read_depth_png(eight, 5000)
    rgb = tmp_path / "rgb.png"
    o3d.io.write_image(str(rgb), o3d.geometry.Image(np.zeros((6, 8, 3), np.uint8)))
    with pytest.raises(FormatError, match=r"rgb\.png is a RGB PNG; depth must be a single-channel"):
        read_depth_png(rgb, 5000)
    text = tmp_path / "text.png"
    text.write_text("not an image")
    with pytest.raises(FormatError, match="not a PNG file"):
        read_depth_png(text, 5000)
    good = tmp_path / "good.png"
    write_depth_png(good, np.full((60, 80), 1.25), 5000)
    np.testing.assert_allclose(read_depth_png(good, 5000), 1.25)
    cut = tmp_path / "cut.png"
    cut.write_bytes(good.read_bytes()[:60])
    with pytest.raises(FormatError, match="could not be decoded"):
        read_depth_png(cut, 5000)
    with pytest.raises(FormatError, match="does not exist"):
        read_depth_png(tmp_path / "missing.png", 5000)


def test_7scenes_invalid_65535_is_missing(tmp_path):
    o3d = pytest.importorskip("open3d")
    path = tmp_path / "d.png"
    raw = np.array([[0, 1000, 65535, 2500]], np.uint16)
    o3d.io.write_image(str(path), o3d.geometry.Image(raw))
    np.testing.assert_allclose(read_depth_png(path, 1000), [[0.0, 1.0, 0.0, 2.5]])


def test_bad_frame_in_a_sequence(tmp_path):
    o3d = pytest.importorskip("open3d")
    gt_t = np.arange(20) * 0.01
    root = _make_tum(tmp_path / "seq", [0.0, 0.05, 0.1, 0.15], gt_t, [_pose((0, 0, 0), 0.0)] * 20)
    o3d.io.write_image(str(root / "depth/0.050000.png"), o3d.geometry.Image(np.full((6, 8), 9, np.uint8)))
    (root / "depth/0.100000.png").unlink()
    seq = open_sequence(root, check_scale=False)
    assert seq[0].depth.shape == (6, 8)
    with pytest.raises(FormatError, match="8-bit"):
        seq[1]
    with pytest.raises(FormatError, match=r"0\.100000\.png does not exist"):
        seq[2]
    write_depth_png(root / "depth/0.150000.png", np.ones((12, 16)), 5000)
    with pytest.raises(FormatError, match="is 16x12 but the sequence's images are 8x6"):
        seq[3]
    (root / "depth.txt").write_text("0.0 depth/0.000000.png extra\n")
    with pytest.raises(FormatError, match=r"depth\.txt:1: expected 'timestamp path'"):
        open_sequence(root)


def test_7scenes_missing_and_bad_poses_are_skipped_and_counted(tmp_path):
    root = _make_7scenes(tmp_path / "seq-01", n=6)
    (root / "frame-000001.pose.txt").unlink()
    np.savetxt(root / "frame-000002.pose.txt", np.full((4, 4), -np.inf))  # as failed tracking is written
    np.savetxt(root / "frame-000004.pose.txt", np.diag([2.0, 2.0, 2.0, 1.0]))  # a scaled, non-rigid matrix
    with pytest.warns(SDFCodecWarning, match=r"skipped 3 of 6 frames.*1 without a pose file.*2 with a non-finite "
                                             r"or non-rigid pose"):
        seq = open_sequence(root)
    assert len(seq) == 3 and seq.skipped == 3
    assert seq.skip_reasons == {"without a pose file": 1, "with a non-finite or non-rigid pose": 2}
    assert [f.path.name for f in seq] == ["frame-000000.depth.png", "frame-000003.depth.png", "frame-000005.depth.png"]
    np.testing.assert_allclose(seq[1].pose, _pose((0.3, 0, 0), 0.15))
    assert seq[1].timestamp == pytest.approx(3 / 30)
    with pytest.raises(InvalidValueError, match=r"frame-000001\.pose\.txt: without a pose file"):
        open_sequence(root, missing_pose="error")
    kept = open_sequence(root, missing_pose="keep")
    assert len(kept) == 6 and kept[1].pose is None and kept[2].pose is None and kept[0].pose is not None
    (root / "frame-000003.pose.txt").write_text("1 0 0\n0 1 0\n")
    with pytest.raises(FormatError, match=r"frame-000003\.pose\.txt must hold a 4x4 .*found 6"):
        open_sequence(root)


def test_7scenes_all_poses_missing(tmp_path):
    root = _make_7scenes(tmp_path / "seq", n=3)
    for p in root.glob("*.pose.txt"):
        p.unlink()
    with pytest.raises(InvalidValueError, match=r"no usable frame .*3 without a pose file"):
        open_sequence(root)


def test_bad_trajectory_files(tmp_path):
    path = tmp_path / "gt.txt"
    path.write_text("# c\n1.0 0 0 0 0 0 0 1\n2.0 0 0 0 0 0 1\n")
    with pytest.raises(FormatError, match=r"gt\.txt:3: expected 8 numbers"):
        read_tum_trajectory(path)
    path.write_text("1.0 0 0 0 0 0 0 0.5\n")
    with pytest.raises(InvalidValueError, match=r"gt\.txt:1: quaternion norm 0\.5"):
        read_tum_trajectory(path)
    path.write_text("1.0 0 nan 0 0 0 0 1\n")
    with pytest.raises(InvalidValueError, match="non-finite"):
        read_tum_trajectory(path)
    path.write_text("# only comments\n")
    with pytest.raises(FormatError, match="holds no poses"):
        read_tum_trajectory(path)
    path.write_text("2.0 0 0 0 0 0 0 1\n1.0 1 0 0 0 0 0 1\n")
    assert read_tum_trajectory(path).timestamps.tolist() == [1.0, 2.0]  # sorted by time


def test_not_a_sequence(tmp_path):
    with pytest.raises(FormatError, match="not a directory"):
        open_sequence(tmp_path / "nowhere")
    (tmp_path / "seq-01").mkdir()
    with pytest.raises(FormatError, match="seq-\\* folders: open one of them"):
        open_sequence(tmp_path)
    with pytest.raises(SDFCodecError):
        open_sequence(tmp_path, missing_pose="maybe")
