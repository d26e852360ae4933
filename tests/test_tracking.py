"""The SDF Tracker against an analytic scene: a room corner with boxes and a sphere, sampled at 2 cm, and depth
images rendered from the same exact distance function by sphere tracing."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest
import torch
from scipy.linalg import expm
from scipy.spatial.transform import Rotation

from sdfcodec.core import metrics
from sdfcodec.errors import DTypeError, InvalidValueError, ShapeError
from sdfcodec.core.sdf import Box, Plane, Scene, Sphere, sample_volume
from sdfcodec.tracking.tracker import (CameraIntrinsics, DenseField, FieldSampler, SDFTracker, TrackerConfig, backproject,
                                       se3_exp)

VOXEL = 0.02
ORIGIN = (-0.2, -0.2, -0.2)
SHAPE = (110, 110, 90)  # covers -0.2 .. 1.98 m in x and y, -0.2 .. 1.58 m in z
W, H = 160, 120
K = (131.25, 131.25, 79.5, 59.5)  # a Kinect's 525 px focal length at a quarter of 640x480


def room() -> Scene:
    """Floor z = 0 and walls x = 0 and y = 0 (a concave corner), two boxes and a ball on the floor."""
    return Scene([
        Box((1.0, 1.0, -0.5), (1.6, 1.6, 0.5)),
        Box((-0.5, 1.0, 1.0), (0.5, 1.6, 1.6)),
        Box((1.0, -0.5, 1.0), (1.6, 0.5, 1.6)),
        Box((0.7, 0.45, 0.15), (0.15, 0.2, 0.15), Rotation.from_euler("z", 20, degrees=True).as_matrix()),
        Sphere((0.45, 1.1, 0.25), 0.25),
        Box((1.2, 0.3, 0.35), (0.1, 0.1, 0.35)),
    ])


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """Camera-to-world pose (OpenCV camera: x right, y down, z forward) at ``eye`` looking at ``target``."""
    eye, target, up = (np.asarray(v, dtype=np.float64) for v in (eye, target, up))
    z = target - eye
    z /= np.linalg.norm(z)
    y = -(up - (up @ z) * z)
    y /= np.linalg.norm(y)
    pose = np.eye(4)
    pose[:3, 0], pose[:3, 1], pose[:3, 2], pose[:3, 3] = np.cross(y, z), y, z, eye
    return pose


def render_depth(sdf, pose: np.ndarray, intrinsics=K, height: int = H, width: int = W,
                 max_range: float = 8.0, steps: int = 300) -> np.ndarray:
    """Depth (H, W) float32 metres (z along the optical axis, 0 = no hit) by sphere tracing the exact SDF."""
    fx, fy, cx, cy = intrinsics
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    rays = np.stack([(u - cx) / fx, (v - cy) / fy, np.ones_like(u)], -1).reshape(-1, 3)
    norm = np.linalg.norm(rays, axis=1)
    dirs = (rays / norm[:, None]) @ pose[:3, :3].T
    origin = pose[:3, 3]
    s = np.zeros(len(dirs))
    active = np.ones(len(dirs), dtype=bool)
    hit = np.zeros(len(dirs), dtype=bool)
    for _ in range(steps):
        idx = np.flatnonzero(active)
        if not len(idx):
            break
        d = sdf(origin + s[idx, None] * dirs[idx])
        s[idx] += d
        done = np.abs(d) < 1e-6
        hit[idx[done]] = True
        active[idx[done | (s[idx] > max_range)]] = False
    return np.where(hit, s / norm, 0.0).reshape(height, width).astype(np.float32)


def pose_error(estimate, truth) -> tuple[float, float]:
    """(translation metres, rotation degrees) of ``truth^-1 estimate``."""
    e = np.linalg.inv(truth) @ np.asarray(estimate, dtype=np.float64)
    return float(np.linalg.norm(e[:3, 3])), float(metrics.rotation_angle(e[None, :3, :3], degrees=True)[0])


def perturb(pose: np.ndarray, rng: np.random.Generator, metres: float, degrees: float) -> np.ndarray:
    t = rng.normal(size=3)
    w = rng.normal(size=3)
    xi = np.concatenate([metres * t / np.linalg.norm(t), math.radians(degrees) * w / np.linalg.norm(w)])
    return pose @ se3_exp(xi)


TRUE_POSE = look_at((1.7, 1.5, 1.2), (0.4, 0.4, 0.2))


@pytest.fixture(scope="module")
def scene():
    return room()


@pytest.fixture(scope="module")
def volume(scene):
    return sample_volume(scene, SHAPE, VOXEL, ORIGIN)


@pytest.fixture(scope="module")
def field(volume):
    return DenseField(volume, VOXEL, ORIGIN)


@pytest.fixture(scope="module")
def depth(scene):
    d = render_depth(scene, TRUE_POSE)
    assert (d > 0).mean() > 0.99
    return d


# ----------------------------------------------------------------------------------------------- the field
def test_plane_gradient_is_exact():
    normal = np.array([0.3, -0.5, 0.8])
    normal /= np.linalg.norm(normal)
    plane = Plane(normal, offset=0.35)
    shape, origin = (30, 32, 34), (0.0, 0.05, -0.1)
    vol = sample_volume(plane, shape, VOXEL, origin, truncation=None)  # raw distances: a linear field
    rng = np.random.default_rng(0)
    pts = rng.uniform(np.array(origin) + 1.0 * VOXEL, np.array(origin) + (np.array(shape) - 2.0) * VOXEL,
                      size=(2000, 3))
    t = torch.as_tensor(pts, dtype=torch.float32)
    for kwargs in ({}, {"precompute_gradient": False}, {"backend": "grid_sample"}):
        f = DenseField(vol, VOXEL, origin, truncation=(-2.0, 2.0), **kwargs)
        d, g, valid = f.sample_with_gradient(t)
        assert valid.all()
        # trilinear interpolation and central differences are exact on a linear function
        np.testing.assert_allclose(d.numpy(), plane(pts), atol=2e-6)
        np.testing.assert_allclose(g.numpy(), np.broadcast_to(normal, (len(pts), 3)), atol=2e-4)
        d2, valid2 = f.sample(t)
        np.testing.assert_allclose(d2.numpy(), d.numpy(), atol=1e-6)


def test_gradient_variants_agree_and_bounds(volume):
    rng = np.random.default_rng(1)
    lo = np.array(ORIGIN) - 0.1
    hi = np.array(ORIGIN) + np.array(SHAPE) * VOXEL + 0.1
    pts = torch.as_tensor(rng.uniform(lo, hi, size=(5000, 3)), dtype=torch.float32)
    results = [DenseField(volume, VOXEL, ORIGIN, **kw).sample_with_gradient(pts)
               for kw in ({}, {"precompute_gradient": False}, {"backend": "grid_sample"})]
    ref_d, ref_g, ref_v = results[0]
    u = (pts.numpy().astype(np.float64) - ORIGIN) / VOXEL
    inside = np.all((u >= 1) & (u < np.array(SHAPE) - 2), axis=1)
    np.testing.assert_array_equal(ref_v.numpy(), inside)
    assert 0 < inside.sum() < len(pts)
    for d, g, v in results[1:]:
        np.testing.assert_array_equal(v.numpy(), ref_v.numpy())
        np.testing.assert_allclose(d[v].numpy(), ref_d[v].numpy(), atol=1e-6)
        np.testing.assert_allclose(g[v].numpy(), ref_g[v].numpy(), atol=1e-4)
    # the (N, 3) input may be a transposed (3, N) view (what the tracker passes)
    d2, g2, v2 = DenseField(volume, VOXEL, ORIGIN).sample_with_gradient(pts.t().contiguous().t())
    assert torch.equal(d2, ref_d) and torch.equal(g2, ref_g) and torch.equal(v2, ref_v)


def test_sampler_matches_an_independent_trilinear_reference(volume):
    """Value and gradient at scattered points against a float64 reference written from the definition: the
    trilinear interpolation of the voxels and of their central differences (d[i+1] - d[i-1]) / 2h, taken
    straight from the volume (not from the field's precomputed 4-channel table)."""
    rng = np.random.default_rng(11)
    u = rng.uniform(1.0, np.array(SHAPE) - 2.0 - 1e-3, size=(3000, 3))  # continuous voxel coordinates, valid
    pts = np.array(ORIGIN) + u * VOXEL
    v = volume.astype(np.float64)
    i0 = np.floor(u).astype(int)
    f = u - i0
    ref = np.zeros((len(u), 4))
    for corner in np.ndindex(2, 2, 2):
        c = i0 + corner
        w = np.prod(np.where(corner, f, 1 - f), axis=1)
        at = lambda dx, dy, dz: v[c[:, 0] + dx, c[:, 1] + dy, c[:, 2] + dz]  # noqa: E731
        grad = [(at(1, 0, 0) - at(-1, 0, 0)), (at(0, 1, 0) - at(0, -1, 0)), (at(0, 0, 1) - at(0, 0, -1))]
        ref += w[:, None] * np.stack([at(0, 0, 0)] + [g / (2 * VOXEL) for g in grad], 1)
    d, g, valid = DenseField(volume, VOXEL, ORIGIN).sample_with_gradient(torch.as_tensor(pts, dtype=torch.float32))
    assert valid.all()
    np.testing.assert_allclose(d.numpy(), ref[:, 0], atol=2e-6)
    np.testing.assert_allclose(g.numpy(), ref[:, 1:], atol=2e-4)


def test_cpu_paths_match_the_torch_ops_a_device_runs(volume, depth):
    """On the CPU the field's lookup and the tracker's sums run in numpy, in cache-sized pieces
    (``DenseField._lookup_rows``, ``SDFTracker._chunk_terms_cpu``); on a device, torch's ops do the same work.
    Both are run here on the CPU, on more points than one piece, and must agree."""
    cpu = DenseField(volume, VOXEL, ORIGIN)
    ops = DenseField(volume, VOXEL, ORIGIN)
    ops._rows = False  # the torch ops a CUDA device runs
    rng = np.random.default_rng(5)
    lo = np.array(ORIGIN) - 0.1
    hi = np.array(ORIGIN) + np.array(SHAPE) * VOXEL + 0.1
    pts = torch.as_tensor(rng.uniform(lo, hi, size=(40000, 3)), dtype=torch.float32)  # two lookup pieces
    pts[::97] = float("nan")
    (d1, g1, v1), (d2, g2, v2) = cpu.sample_with_gradient(pts), ops.sample_with_gradient(pts)
    np.testing.assert_array_equal(v1.numpy(), v2.numpy())
    assert 0 < int(v1.sum()) < len(pts) and bool(torch.isfinite(d1).all() and torch.isfinite(g1).all())
    np.testing.assert_allclose(d1[v1].numpy(), d2[v2].numpy(), atol=1e-6)
    np.testing.assert_allclose(g1[v1].numpy(), g2[v2].numpy(), atol=1e-5)
    np.testing.assert_array_equal(cpu.sample(pts)[0].numpy(), d1.numpy())

    tracker = SDFTracker(cpu, K)
    pose = perturb(TRUE_POSE, np.random.default_rng(8), 0.01, 1.0)
    p = backproject(torch.from_numpy(depth), K).t().contiguous()
    chunks = [p[:, :7000], p[:, 7000:]]
    r5 = torch.as_tensor(pose[[0, 1, 2, 0, 1], :3], dtype=torch.float32)
    t = torch.as_tensor(pose[:3, 3], dtype=torch.float32).reshape(3, 1)
    numpy_sums = tracker._chunk_terms_cpu(chunks, r5, t).numpy()
    torch_sums = tracker._chunk_terms(chunks, r5, t).double().numpy()
    assert numpy_sums[8, 0] > 0.5 * p.shape[1]  # most points are inliers: the sums are not trivially equal
    np.testing.assert_allclose(numpy_sums, torch_sums, rtol=1e-4, atol=1e-6 * np.abs(torch_sums).max())


def test_sphere_value_and_gradient_against_the_analytic_sdf():
    """On a sphere (curved: trilinear interpolation is not exact) the value is within the interpolation error
    of the true distance and the gradient within a degree of the true normal."""
    centre, radius = np.array([0.36, 0.35, 0.37]), 0.2
    sphere = Sphere(tuple(centre), radius)
    shape = (36, 35, 37)
    vol = sample_volume(sphere, shape, VOXEL, (0.0, 0.0, 0.0), truncation=None)
    rng = np.random.default_rng(12)
    dirs = rng.normal(size=(2000, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    pts = centre + dirs * rng.uniform(radius - 0.05, radius + 0.08, size=(2000, 1))  # the truncation band
    d, g, valid = DenseField(vol, VOXEL, truncation=(-1.0, 1.0)).sample_with_gradient(
        torch.as_tensor(pts, dtype=torch.float32))
    assert valid.all()
    # trilinear error <= h^2 / 8 * sum |second derivatives|, with |d2/dx2 (|x| - r)| <= 1 / |x| <= 1 / 0.15
    assert np.abs(d.numpy() - sphere(pts)).max() < VOXEL ** 2 / 8 * 3 / 0.15
    cosine = np.sum(g.numpy() * dirs, axis=1) / np.linalg.norm(g.numpy(), axis=1)
    assert np.degrees(np.arccos(np.clip(cosine, -1, 1))).max() < 1.0
    assert np.abs(np.linalg.norm(g.numpy(), axis=1) - 1).max() < 0.02


def test_dense_field_nan_voxels_are_unknown(volume):
    vol = volume.copy()
    vol[50:60, 50:60, 10:20] = np.nan
    f = DenseField(torch.from_numpy(vol), VOXEL, ORIGIN)
    p = torch.tensor([[ORIGIN[0] + 55 * VOXEL, ORIGIN[1] + 55 * VOXEL, ORIGIN[2] + 15 * VOXEL],
                      [ORIGIN[0] + 20 * VOXEL, ORIGIN[1] + 20 * VOXEL, ORIGIN[2] + 15 * VOXEL]])
    d, g, valid = f.sample_with_gradient(p)
    assert valid.tolist() == [False, True]
    assert torch.isfinite(d).all() and torch.isfinite(g).all()
    # NaN or infinite query points are simply not valid, for every backend
    bad = torch.tensor([[float("nan"), 0.5, 0.5], [float("inf"), 0.5, 0.5], [0.5, 0.5, 0.5]])
    for kw in ({}, {"precompute_gradient": False}, {"backend": "grid_sample"}):
        d, g, valid = DenseField(volume, VOXEL, ORIGIN, **kw).sample_with_gradient(bad)
        assert valid.tolist() == [False, False, True]
        assert torch.isfinite(d).all() and torch.isfinite(g).all()


def test_dense_field_input_errors(volume):
    with pytest.raises(ShapeError, match=r"\(X, Y, Z\)"):
        DenseField(volume[0], VOXEL)
    with pytest.raises(ShapeError, match="at least 4"):
        DenseField(volume[:3], VOXEL)
    with pytest.raises(DTypeError):
        DenseField(volume.astype(np.int16), VOXEL)
    with pytest.raises(InvalidValueError, match="voxel_size"):
        DenseField(volume, -0.02)
    with pytest.raises(InvalidValueError, match="truncation"):
        DenseField(volume, VOXEL, truncation=(0.1, -0.04))
    with pytest.raises(ShapeError, match="origin"):
        DenseField(volume, VOXEL, origin=(0.0, 0.0))
    with pytest.raises(ShapeError, match=r"\(N, 3\)"):
        DenseField(volume, VOXEL).sample(torch.zeros(5, 2))
    assert isinstance(DenseField(volume, VOXEL), FieldSampler)


# ------------------------------------------------------------------------------------------------ geometry
def test_se3_exp_matches_matrix_exponential():
    rng = np.random.default_rng(2)
    for scale in (1e-10, 1e-3, 0.5, 2.0):
        xi = rng.normal(size=6) * scale
        twist = np.zeros((4, 4))
        twist[:3, :3] = np.array([[0, -xi[5], xi[4]], [xi[5], 0, -xi[3]], [-xi[4], xi[3], 0]])
        twist[:3, 3] = xi[:3]
        np.testing.assert_allclose(se3_exp(xi), expm(twist), atol=1e-12)


def test_moved_names_keep_their_tracking_import_path():
    """se3_exp lives in sdfcodec.core.geometry and DenseField in sdfcodec.tracking.densefield; sdfcodec.tracking.tracker re-exports
    the same objects."""
    from sdfcodec.tracking import densefield, tracker as tracking
    from sdfcodec.core import geometry

    assert tracking.se3_exp is geometry.se3_exp and tracking.DenseField is densefield.DenseField
    assert isinstance(densefield.DenseField(np.zeros((4, 4, 4)), 0.02), FieldSampler)


def test_backproject_pixels():
    depth = torch.zeros(6, 8)
    depth[2, 5] = 2.0
    depth[4, 0] = 1.0
    depth[0, 0] = float("nan")
    k = CameraIntrinsics(100.0, 50.0, 4.0, 3.0)
    pts = backproject(depth, k)
    assert pts.shape == (2, 3)
    np.testing.assert_allclose(pts.numpy(), [[(5 - 4) / 100 * 2, (2 - 3) / 50 * 2, 2.0],
                                             [(0 - 4) / 100 * 1, (4 - 3) / 50 * 1, 1.0]])
    assert backproject(depth, k, stride=2).shape == (1, 3)  # rows 0, 2, 4 x columns 0, 2, 4, 6: only (4, 0)
    assert CameraIntrinsics.coerce(np.array([[100, 0, 4], [0, 50, 3], [0, 0, 1.0]])) == k


# ------------------------------------------------------------------------------------------------ tracking
def test_converges_from_perturbed_poses(field, depth):
    tracker = SDFTracker(field, K)
    rng = np.random.default_rng(5)
    for _ in range(3):
        start = perturb(TRUE_POSE, rng, 0.03, 3.0)
        res = tracker.track(depth, start)
        assert res.success, res.message
        trans, rot = pose_error(res.pose, TRUE_POSE)
        assert trans < 0.005 and rot < 0.5, (trans, rot, res.message)
        assert res.inlier_ratio > 0.9 and res.residual < 0.002
        assert len(res.iterations_per_level) == 3 and res.iterations == sum(res.iterations_per_level)
        assert isinstance(res.pose, np.ndarray) and res.pose.dtype == np.float64


def test_true_pose_is_a_fixed_point(field, depth):
    res = SDFTracker(field, K).track(depth, TRUE_POSE)
    trans, rot = pose_error(res.pose, TRUE_POSE)
    assert trans < 0.001 and rot < 0.05


def test_pose_type_follows_input_and_threads_agree(field, depth):
    start = perturb(TRUE_POSE, np.random.default_rng(6), 0.02, 2.0)
    one = SDFTracker(field, K, TrackerConfig(threads=1)).track(depth, start)
    two = SDFTracker(field, K, {"threads": 2, "chunk_size": 4096}).track(torch.from_numpy(depth),
                                                                        torch.as_tensor(start, dtype=torch.float32))
    assert isinstance(two.pose, torch.Tensor) and two.pose.dtype == torch.float32
    np.testing.assert_allclose(two.pose.numpy(), one.pose, atol=1e-4)


def test_numpy_blas_is_held_at_one_thread_while_tracking_and_restored(field, depth):
    """The chunks' small numpy products run on one BLAS thread during ``track`` (OpenBLAS's own threads spin
    after each call, on the core the tracker's other thread needs) and numpy gets its threads back after."""
    from threadpoolctl import threadpool_info

    def blas_threads() -> list[int]:
        return [lib["num_threads"] for lib in threadpool_info() if lib["user_api"] == "blas"
                and "numpy" in lib["filepath"]]

    before = blas_threads()
    if not before:
        pytest.skip("threadpoolctl finds no BLAS library of numpy's here")
    seen: list[list[int]] = []

    class Watching:  # a FieldSampler that notes numpy's BLAS threads while the tracker calls it
        device, truncation = field.device, field.truncation

        def sample(self, points):
            return field.sample(points)

        def sample_with_gradient(self, points):
            seen.append(blas_threads())
            return field.sample_with_gradient(points)

    res = SDFTracker(Watching(), K).track(depth, TRUE_POSE)
    assert res.success and seen and all(t == [1] * len(before) for t in seen), seen
    assert blas_threads() == before


def _reference_step(field, depth, pose, cfg):
    """One Gauss-Newton step as the module docstring writes it, in float64 numpy with every point's Jacobian
    formed in the camera frame (``g = R^T grad D``, ``J = [g, p x g]``): (pose, inliers, residual)."""
    pts = backproject(torch.from_numpy(depth), K, 1, cfg.min_depth, cfg.max_depth).numpy().astype(np.float64)
    r, t = pose[:3, :3], pose[:3, 3]
    d, g, valid = (x.numpy().astype(np.float64) if x.dtype != torch.bool else x.numpy()
                   for x in field.sample_with_gradient(torch.from_numpy(pts @ r.T + t).float()))
    gc = g @ r  # row i: R^T g_i
    jac = np.hstack([gc, np.cross(pts, gc)])
    d_min, d_max = field.truncation
    mask = (valid & (d > d_min + cfg.plateau_margin) & (d < d_max - cfg.plateau_margin)
            & ((gc * gc).sum(1) >= cfg.min_gradient_norm ** 2))
    w = np.where(mask, cfg.huber_delta / np.maximum(np.abs(d), cfg.huber_delta), 0.0)
    n = int(mask.sum())
    h = (jac * w[:, None]).T @ jac / n
    b = (jac * w[:, None]).T @ d / n
    xi = -np.linalg.solve(h + cfg.damping * np.eye(6), b)
    return pose @ se3_exp(xi), n, math.sqrt(float((d[mask] ** 2).sum()) / n)


@pytest.mark.parametrize("threads, chunk", [(1, None), (2, 4096)])
def test_one_step_matches_a_float64_camera_frame_reference(field, depth, threads, chunk):
    """The tracker forms its Jacobian rows in the world frame and rotates the 7x7 sums (float32, chunked, on
    threads); one step must equal the textbook float64 step with per-point camera-frame Jacobians."""
    cfg = TrackerConfig(strides=(1,), iterations=(1,), max_pixels=None, min_update=0.0, max_final_update=None,
                        threads=threads, chunk_size=chunk)
    start = perturb(TRUE_POSE, np.random.default_rng(11), 0.02, 2.0)
    res = SDFTracker(field, K, cfg).track(depth, start)
    pose, inliers, residual = _reference_step(field, depth, start, cfg)
    assert res.success and res.iterations == 1, res.message
    moved = np.abs(pose - start).max()
    assert moved > 1e-3  # a real step, not a fixed point
    np.testing.assert_allclose(res.pose, pose, atol=2e-4 * moved)
    assert abs(res.inliers - inliers) <= 2 and res.inliers > 0.5 * res.points
    assert res.residual == pytest.approx(residual, rel=1e-3)


def test_custom_field_sampler(scene, depth):
    """Any object with device, truncation and the two sample methods plugs in: here the exact analytic SDF."""

    class AnalyticField:
        device = torch.device("cpu")
        truncation = (-0.04, 0.1)

        def _d(self, p):
            return np.clip(scene(p), *self.truncation)

        def sample(self, points):
            p = points.double().numpy()
            return torch.from_numpy(self._d(p)).float(), torch.ones(len(p), dtype=torch.bool)

        def sample_with_gradient(self, points):
            p = points.double().numpy()
            h = 1e-3
            g = np.stack([(self._d(p + h * e) - self._d(p - h * e)) / (2 * h) for e in np.eye(3)], axis=1)
            return (torch.from_numpy(self._d(p)).float(), torch.from_numpy(g).float(),
                    torch.ones(len(p), dtype=torch.bool))

    start = perturb(TRUE_POSE, np.random.default_rng(8), 0.02, 2.0)
    res = SDFTracker(AnalyticField(), K, TrackerConfig(strides=(8, 4), iterations=(12, 6))).track(depth, start)
    assert res.success, res.message
    trans, rot = pose_error(res.pose, TRUE_POSE)
    assert trans < 0.003 and rot < 0.3


def test_misbehaving_field_sampler_is_reported(depth):
    class NaNField:
        device = torch.device("cpu")
        truncation = (-0.04, 0.1)

        def sample(self, points):
            return torch.full((len(points),), float("nan")), torch.ones(len(points), dtype=torch.bool)

        def sample_with_gradient(self, points):
            n = len(points)
            return torch.full((n,), float("nan")), torch.zeros(n, 3), torch.ones(n, dtype=torch.bool)

    res = SDFTracker(NaNField(), K).track(depth, TRUE_POSE)
    assert not res.success and "non-finite" in res.message
    np.testing.assert_array_equal(res.pose, TRUE_POSE)


def test_track_sequence(scene, field):
    # the camera slides sideways and pans: about 1 cm and 1 degree a frame
    poses = [look_at((1.7 - 0.01 * i, 1.5 + 0.005 * i, 1.2), (0.4 + 0.02 * i, 0.4, 0.2)) for i in range(6)]
    frames = [render_depth(scene, p) for p in poses]
    frames[3][::3] = np.nan  # missing readings are ignored
    tracker = SDFTracker(field, K, TrackerConfig(constant_velocity=True))
    seq = tracker.track_sequence(frames, poses[0])
    assert seq.poses.shape == (6, 4, 4) and not seq.failures
    truth = metrics.Trajectory.from_poses(np.stack(poses))
    result = metrics.ate(truth, seq.to_trajectory())
    assert result.max < 0.005, result.as_dict()
    assert metrics.rpe(truth, seq.to_trajectory(), relation="rotation").max < 0.5
    untracked_first = tracker.track_sequence(iter(frames[:2]), poses[0], track_first=False)
    assert untracked_first.results[0] is None and np.array_equal(untracked_first.poses[0], poses[0])


def test_failures_are_reported_not_nan(field, depth):
    tracker = SDFTracker(field, K)
    far = TRUE_POSE.copy()
    far[:3, 3] += [10.0, 0.0, 0.0]  # the map is nowhere near
    res = tracker.track(depth, far)
    assert not res.success
    assert "fall where the map is usable" in res.message and "far off the map" in res.message
    np.testing.assert_array_equal(res.pose, far)
    assert res.inliers == 0 and math.isinf(res.residual) and res.inlier_ratio == 0.0
    # inside the map but 30 cm off along the optical axis: most points sit in the free-space plateau and
    # Gauss-Newton wanders off; that is reported, not returned as a pose
    behind = TRUE_POSE.copy()
    behind[:3, 3] -= 0.3 * TRUE_POSE[:3, 2]
    lost = tracker.track(depth, behind)
    assert not lost.success and "did not converge" in lost.message
    np.testing.assert_array_equal(lost.pose, behind)
    assert lost.update_norm > 0.01 and np.isfinite(lost.residual)
    empty = tracker.track(np.zeros_like(depth), TRUE_POSE)
    assert not empty.success and "valid depth readings" in empty.message
    assert np.isfinite(empty.pose).all()
    mm = tracker.track(depth * 1000.0, TRUE_POSE)  # millimetres by mistake: beyond max_depth
    assert not mm.success and "metres" in mm.message
    seq = tracker.track_sequence([depth, np.zeros_like(depth), depth], TRUE_POSE)
    assert seq.failures == [1] and np.isfinite(seq.poses).all()
    stopped = tracker.track_sequence([depth, np.zeros_like(depth), depth], TRUE_POSE, stop_on_failure=True)
    assert len(stopped.poses) == 2


def test_input_errors(field, depth):
    tracker = SDFTracker(field, K)
    with pytest.raises(ShapeError, match=r"\(H, W\)"):
        tracker.track(depth[..., None], TRUE_POSE)
    with pytest.raises(DTypeError, match="metres"):
        tracker.track((depth * 1000).astype(np.uint16), TRUE_POSE)
    with pytest.raises(ShapeError, match=r"\(4, 4\)"):
        tracker.track(depth, TRUE_POSE[:3])
    bad = TRUE_POSE.copy()
    bad[0, 0] = np.nan
    with pytest.raises(InvalidValueError, match="NaN"):
        tracker.track(depth, bad)
    bad = TRUE_POSE.copy()
    bad[:3, :3] *= 2.0
    with pytest.raises(InvalidValueError, match="rotation"):
        tracker.track(depth, bad)
    with pytest.raises(InvalidValueError, match="same length"):
        TrackerConfig(strides=(4, 2), iterations=(3,))
    with pytest.raises(InvalidValueError, match="huber_delta"):
        TrackerConfig(huber_delta=-1.0)
    with pytest.raises(InvalidValueError, match="no field 'huber'.*huber_delta"):
        SDFTracker(field, K, {"huber": 0.1})
    with pytest.raises(InvalidValueError, match="FieldSampler"):
        SDFTracker(object(), K)
    with pytest.raises(ShapeError, match="intrinsics"):
        SDFTracker(field, (1.0, 2.0))
    with pytest.raises(InvalidValueError, match="focal"):
        CameraIntrinsics(-1.0, 1.0, 0.0, 0.0)


def test_pyramid_scales_to_the_image_size():
    """max_pixels: the finest level of a 640x480 frame is strided by 2 (76,800 points), a 160x120 frame keeps
    stride 1, and max_pixels=None runs the strides as given."""
    plane = Plane((0.0, 0.0, -1.0), offset=-1.0)  # the wall z = 1 m, free space towards the camera at the origin
    origin = (-0.8, -0.7, 0.8)
    field = DenseField(sample_volume(plane, (82, 72, 22), VOXEL, origin), VOXEL, origin)
    cfg = {"max_final_update": None}
    for (w, h), max_pixels, finest in (((640, 480), 76800, 2), ((640, 480), None, 1), ((160, 120), 76800, 1),
                                       ((640, 480), 20000, 4)):
        k = (525.0 * w / 640, 525.0 * w / 640, (w - 1) / 2, (h - 1) / 2)
        res = SDFTracker(field, k, {**cfg, "max_pixels": max_pixels}).track(np.ones((h, w), np.float32), np.eye(4))
        assert res.success, res.message
        assert res.points == -(-w // finest) * -(-h // finest), (w, max_pixels, res.points)
        assert res.residual < 1e-4 and len(res.iterations_per_level) == 3


def test_config_defaults_are_the_original_trackers():
    cfg = TrackerConfig()
    assert cfg.strides == (4, 2, 1) and cfg.iterations == (12, 8, 2) and cfg.min_update == 1e-4
    assert cfg.max_pixels == 320 * 240  # 640x480 images run 8/4/2 (test_pyramid_scales_to_the_image_size)
    assert TrackerConfig(**cfg.model_dump()) == cfg
    assert "huber_delta" in TrackerConfig.model_json_schema()["properties"]


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_tracks_on_gpu(volume, depth):
    field = DenseField(torch.from_numpy(volume).cuda(), VOXEL, ORIGIN)
    start = perturb(TRUE_POSE, np.random.default_rng(9), 0.03, 3.0)
    res = SDFTracker(field, K).track(torch.from_numpy(depth).cuda(), torch.as_tensor(start, device="cuda"))
    assert res.success and res.pose.device.type == "cuda"
    trans, rot = pose_error(res.pose.cpu().numpy(), TRUE_POSE)
    assert trans < 0.005 and rot < 0.5


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_gpu_sampler_and_tracker_match_the_cpu(volume, depth):
    """The same code on the device: the sampler agrees with the CPU's to float rounding, the pose to 0.1 mm."""
    cpu, gpu = DenseField(volume, VOXEL, ORIGIN), DenseField(torch.from_numpy(volume).cuda(), VOXEL, ORIGIN)
    pts = torch.as_tensor(np.random.default_rng(13).uniform(0.0, 1.5, size=(20000, 3)), dtype=torch.float32)
    for a, b in zip(cpu.sample_with_gradient(pts), gpu.sample_with_gradient(pts.cuda())):
        np.testing.assert_allclose(b.cpu().numpy(), a.numpy(), atol=1e-5)
    start = perturb(TRUE_POSE, np.random.default_rng(14), 0.02, 2.0)
    one = SDFTracker(cpu, K).track(depth, start)
    two = SDFTracker(gpu, K).track(torch.from_numpy(depth).cuda(), start)
    assert one.success and two.success and isinstance(two.pose, np.ndarray)
    np.testing.assert_allclose(two.pose, one.pose, atol=1e-4)


@pytest.mark.bench
def test_benchmark_vga_frames_per_second(scene, field):
    """Frames per second at 640x480 with the default stride pyramid (run: pytest -m bench -s)."""
    k = (525.0, 525.0, 319.5, 239.5)
    depth = render_depth(scene, TRUE_POSE, k, 480, 640)
    tracker = SDFTracker(field, k)
    rng = np.random.default_rng(10)
    starts = [perturb(TRUE_POSE, rng, 0.01, 1.0) for _ in range(30)]  # a typical frame-to-frame motion
    tracker.track(depth, starts[0])  # warm up
    times = []
    for start in starts:
        t0 = time.perf_counter()
        res = tracker.track(depth, start)
        times.append(time.perf_counter() - t0)
        assert res.success and pose_error(res.pose, TRUE_POSE)[0] < 0.002
    print(f"\nSDF tracker 640x480, strides {tracker.config.strides}, torch threads {torch.get_num_threads()}: "
          f"median {1e3 * np.median(times):.1f} ms ({1 / np.median(times):.1f} frames/s), best "
          f"{1e3 * min(times):.1f} ms ({1 / min(times):.1f} frames/s); iterations {res.iterations_per_level}")


# ------------------------------------------------------------------------------- MapField: lazily decoded maps
@pytest.fixture(scope="module")
def raw_map(volume, tmp_path_factory):
    from sdfcodec import create_map, get_codec, open_map

    path = tmp_path_factory.mktemp("mapfield") / "room.sdfz"
    with create_map(path, codec=get_codec("raw"), voxel_size=VOXEL, origin=ORIGIN) as m:
        m.write_volume(volume)
    return open_map(path)


def test_map_field_matches_dense_decode(raw_map, depth):
    from sdfcodec.tracking.mapfield import MapField

    dense = DenseField(raw_map.decode_region(), VOXEL, ORIGIN, raw_map.truncation)
    lazy = MapField(raw_map)
    assert isinstance(lazy, FieldSampler)
    rng = np.random.default_rng(3)
    # points all over the map and beyond it, plus the surface points a camera sees
    pts = rng.uniform(-0.4, 2.2, size=(20000, 3)).astype(np.float32)
    d0, g0, v0 = dense.sample_with_gradient(torch.from_numpy(pts))
    d1, g1, v1 = lazy.sample_with_gradient(torch.from_numpy(pts))
    d_max = raw_map.truncation[1]
    # every point DenseField can use is valid here too, with the same numbers; the others read d_max / invalid
    informative = v0 & (d0 < d_max - 1e-6)
    assert torch.equal(v1 & informative, informative)
    assert torch.allclose(d1[v1], d0[v1], atol=1e-6) and torch.allclose(g1[v1], g0[v1], atol=1e-6)
    assert not v1[~v0].any()
    assert torch.all(d1[~v1] == d_max) and torch.all(g1[~v1] == 0)
    s = lazy.stats()
    # misses count every block given a slot (coded ones and the empty neighbours of coded ones); each coded
    # block is decoded once
    assert s["misses"] > 0 and s["blocks_decoded"] > 0 and s["evictions"] == 0
    # the same tracked pose
    start = perturb(TRUE_POSE, np.random.default_rng(8), 0.02, 2.0)
    a = SDFTracker(dense, K).track(depth, start)
    b = SDFTracker(MapField(raw_map), K).track(depth, start)
    np.testing.assert_allclose(b.pose, a.pose, atol=1e-5)
    assert a.iterations == b.iterations


def test_map_field_cpu_path_matches_the_torch_ops_a_device_runs(raw_map):
    """On the CPU MapField's lookup runs in numpy (``MapField._lookup_cpu``); on a device, torch's ops do the same
    work. Both are run here on the CPU and must agree, on points in and out of the map, NaN and infinite ones
    included, and load and hit the same blocks."""
    from sdfcodec.tracking.mapfield import MapField

    cpu, ops = MapField(raw_map), MapField(raw_map)
    ops._pool_np = None  # the torch ops a CUDA device runs
    rng = np.random.default_rng(21)
    pts = torch.from_numpy(rng.uniform(-0.4, 2.2, size=(20000, 3)).astype(np.float32))
    pts[::97] = float("nan")
    pts[5::101, 1] = float("inf")
    (d1, g1, v1), (d2, g2, v2) = cpu.sample_with_gradient(pts), ops.sample_with_gradient(pts)
    assert torch.equal(v1, v2) and 0 < int(v1.sum()) < len(pts)
    assert torch.allclose(d1, d2, atol=1e-6) and torch.allclose(g1, g2, atol=1e-5)
    assert torch.all(d1[~v1] == raw_map.truncation[1]) and torch.all(g1[~v1] == 0)
    assert cpu.stats() == ops.stats()


def test_map_field_partial_view_and_cache_bound(raw_map, depth):
    from sdfcodec.tracking.mapfield import MapField, _SLOT_BYTES

    start = perturb(TRUE_POSE, np.random.default_rng(9), 0.02, 2.0)
    lazy = MapField(raw_map)
    res = SDFTracker(lazy, K).track(depth, start)
    trans, rot = pose_error(res.pose, TRUE_POSE)
    assert res.success and trans < 0.005 and rot < 0.5
    s = lazy.stats()
    assert 0 < s["misses"] < lazy.n_coded  # a partial view decodes only part of the map
    assert s["hits"] > s["misses"]  # later iterations find their blocks cached
    # a tight bound: two halves of the map in turn, each fitting the cache but not both; blocks are evicted,
    # the bound holds and the samples stay exact
    dense = DenseField(raw_map.decode_region(), VOXEL, ORIGIN, raw_map.truncation)
    budget = 40 * _SLOT_BYTES
    small = MapField(raw_map, cache_bytes=budget)
    rng = np.random.default_rng(10)
    for lo, hi in [((0.0, 0.0, 0.0), (0.6, 0.6, 0.6)), ((1.0, 1.0, 0.6), (1.6, 1.6, 1.2)),
                   ((0.0, 0.0, 0.0), (0.6, 0.6, 0.6))]:
        pts = torch.from_numpy(rng.uniform(lo, hi, size=(3000, 3)).astype(np.float32))
        d0, _, _ = dense.sample_with_gradient(pts)
        d1, _, v1 = small.sample_with_gradient(pts)
        assert v1.any() and torch.allclose(d1[v1], d0[v1], atol=1e-6)
        s2 = small.stats()
        assert s2["resident_bytes"] <= budget and s2["pool_bytes"] <= budget
    assert small.stats()["evictions"] > 0
    with pytest.raises(InvalidValueError, match="raise cache_bytes"):  # one lookup that cannot fit
        MapField(raw_map, cache_bytes=4 * _SLOT_BYTES).sample(torch.from_numpy(
            rng.uniform(0.0, 1.6, size=(3000, 3)).astype(np.float32)))
    with pytest.raises(InvalidValueError, match="cache_bytes"):
        MapField(raw_map, cache_bytes=1000)


def test_map_field_halo_codec_has_no_seams(volume, tmp_path):
    from sdfcodec import create_map, get_codec, open_map
    from sdfcodec.tracking.mapfield import MapField

    path = tmp_path / "blur.sdfz"
    with create_map(path, codec=get_codec("gaussian-blur"), voxel_size=VOXEL, origin=ORIGIN) as m:
        m.write_volume(volume)
    blur = open_map(path)
    dense = DenseField(blur.decode_region(), VOXEL, ORIGIN, blur.truncation)
    lazy = MapField(blur)
    pts = torch.from_numpy(np.random.default_rng(4).uniform(0.0, 1.8, size=(5000, 3)).astype(np.float32))
    d0, g0, v0 = dense.sample_with_gradient(pts)
    d1, g1, v1 = lazy.sample_with_gradient(pts)
    assert torch.allclose(d1[v1], d0[v1], atol=1e-5) and torch.allclose(g1[v1], g0[v1], atol=1e-4)
