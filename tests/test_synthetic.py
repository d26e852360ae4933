"""Synthetic training blocks (sdfcodec.data.synthetic) and the exact primitives they use (Barrel, ConcaveCorner).

The independent expectation is brute force: the surface of each generated shape is sampled densely from its
parameters (with formulas written here, not the library's), the distance of every voxel centre is the
distance to the nearest sample, and the sign comes from an inside test written here too.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st
from scipy import stats
from scipy.spatial import cKDTree

from sdfcodec.core.blocks import denormalise, normalise
from sdfcodec.data import synthetic
from sdfcodec.data.synthetic import CATEGORIES, synthetic_blocks, synthetic_shapes
from sdfcodec.errors import InvalidValueError
from sdfcodec.core.sdf import Barrel, Box, ConcaveCorner, Cylinder, grid_points, sample_volume

H = 0.02  # default voxel size (m)
TRUNC = (-0.04, 0.1)
SPACING = 0.002  # surface sample spacing of the brute force (m); its error is below this
POINTS = grid_points((16, 16, 16), H).reshape(-1, 3)


# --- brute force ------------------------------------------------------------------------------------------------

def _grid(lo: float, hi: float, step: float) -> np.ndarray:
    """Samples of [lo, hi] with both ends and spacing <= step (empty if lo > hi)."""
    if lo > hi:
        return np.empty(0)
    return np.linspace(lo, hi, max(2, int(np.ceil((hi - lo) / step)) + 1))


def _rect(axis: int, level: float, ranges) -> np.ndarray:
    """Grid points (K, 3) on the plane coord[axis] = level over the given ranges of the other two axes."""
    a, b = [i for i in range(3) if i != axis]
    u, v = np.meshgrid(_grid(*ranges[a], SPACING), _grid(*ranges[b], SPACING), indexing="ij")
    p = np.empty(u.shape + (3,))
    p[..., axis], p[..., a], p[..., b] = level, u, v
    return p.reshape(-1, 3)


def _barrel_profile(r_mid, r_cap, h):
    """Centre offset c and radius R of the arc through (r_cap, -h), (r_mid, 0), (r_cap, h) (None if straight)."""
    if r_cap == r_mid:
        return None
    c = (r_mid ** 2 - r_cap ** 2 - h ** 2) / (2.0 * (r_mid - r_cap))  # equidistant from (r_mid,0) and (r_cap,h)
    return c, r_mid - c


def _surface_and_inside(shape, local_box):
    """Dense local-frame surface samples (K, 3) and a local inside test, from the shape's parameters."""
    sdf = shape.sdf
    (lx, hx), (ly, hy), (lz, hz) = local_box
    if shape.category == "cuboid":
        half = np.asarray(sdf.half)
        faces = []
        for ax in range(3):
            for sgn in (-1.0, 1.0):
                level = sgn * half[ax]
                if not local_box[ax][0] <= level <= local_box[ax][1]:
                    continue  # this face is farther than the truncation from every voxel
                ranges = [(max(-half[i], local_box[i][0]), min(half[i], local_box[i][1])) for i in range(3)]
                faces.append(_rect(ax, level, ranges))
        surf = np.concatenate(faces) if faces else np.empty((0, 3))
        return surf, lambda q: np.all(np.abs(q) <= half, axis=-1)
    if shape.category == "cylinder":
        r_mid, r_cap, h = sdf.radius, sdf.cap_radius, sdf.half_height
        arc = _barrel_profile(r_mid, r_cap, h)
        if arc is None:
            z = _grid(-h, h, SPACING)
            prof_r, prof_z = np.full_like(z, r_mid), z
        else:  # the meridian arc sampled by arc length
            c, big_r = arc
            alpha = np.arcsin(h / big_r)
            phi = _grid(-alpha, alpha, SPACING / big_r)
            prof_r, prof_z = c + big_r * np.cos(phi), big_r * np.sin(phi)
        # cap discs: rings of radius rr at z = +-h
        rr = _grid(0.0, r_cap, SPACING)
        prof_r = np.concatenate([prof_r, rr, rr])
        prof_z = np.concatenate([prof_z, np.full_like(rr, h), np.full_like(rr, -h)])
        keep = (prof_z >= lz) & (prof_z <= hz)
        prof_r, prof_z = prof_r[keep], prof_z[keep]
        theta = np.arange(0.0, 2 * np.pi, SPACING / max(r_mid, 1e-9))
        surf = np.stack([np.outer(prof_r, np.cos(theta)), np.outer(prof_r, np.sin(theta)),
                         np.repeat(prof_z[:, None], theta.size, axis=1)], axis=-1).reshape(-1, 3)

        def inside(q):
            rho, z = np.hypot(q[..., 0], q[..., 1]), q[..., 2]
            if arc is None:
                radius = r_mid
            else:
                c, big_r = arc
                radius = c + np.sqrt(np.maximum(big_r ** 2 - z ** 2, 0.0))
            return (np.abs(z) <= h) & (rho <= radius)
        return surf, inside
    if shape.category == "concave":
        k = sdf.planes
        pos = [(max(0.0, lo), hi) for lo, hi in local_box]  # the faces bound the free octant x, y (, z) >= 0
        if k == 2:
            pos[2] = local_box[2]
        faces = []
        for ax in range(k):
            if local_box[ax][0] <= 0.0 <= local_box[ax][1]:
                faces.append(_rect(ax, 0.0, pos))
        surf = np.concatenate(faces) if faces else np.empty((0, 3))
        return surf, lambda q: ~np.all(q[..., :k] > 0, axis=-1)
    raise AssertionError(shape.category)


def _brute_force(shape) -> np.ndarray:
    """Truncated signed distances (4096,) of the block's voxel centres, by nearest dense surface sample."""
    if shape.category == "plane":
        n = np.asarray(shape.sdf.normal, float)
        # an orthonormal frame with the normal as local z, built here rather than taken from the shape
        a = np.cross(n, [1.0, 0, 0] if abs(n[0]) < 0.9 else [0, 1.0, 0])
        a /= np.linalg.norm(a)
        rot = np.stack([a, np.cross(n, a), n], axis=1)
        center = n * shape.sdf.offset
        inside = lambda q: q[..., 2] <= 0  # noqa: E731
    else:
        rot = np.asarray(shape.sdf.rotation)
        center = np.asarray(shape.sdf.center)
    local = (POINTS - center) @ rot
    reach = TRUNC[1] + 2 * SPACING  # surface farther than this from every voxel cannot change a truncated value
    local_box = [(local[:, i].min() - reach, local[:, i].max() + reach) for i in range(3)]
    if shape.category == "plane":
        surf = _rect(2, 0.0, local_box)
    else:
        surf, inside = _surface_and_inside(shape, local_box)
    lo, hi = np.array(local_box).T
    surf = surf[np.all((surf >= lo) & (surf <= hi), axis=1)]
    if len(surf):
        dist, _ = cKDTree(surf).query(local, distance_upper_bound=reach)
    else:
        dist = np.full(len(local), np.inf)
    return np.clip(np.where(inside(local), -dist, dist), *TRUNC)


# --- the generator ------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("category", CATEGORIES)
def test_blocks_match_brute_force_distances(category):
    n = 8
    blocks = synthetic_blocks(n, seed=11, categories=(category,))
    shapes = synthetic_shapes(n, seed=11, categories=(category,))
    if category == "cylinder":  # the sample covers straight cylinders and bulging barrels
        assert len({s.sdf.cap_radius == s.sdf.radius for s in shapes}) == 2
    if category == "concave":  # and 2-plane edges and 3-plane corners
        assert {s.sdf.planes for s in shapes} == {2, 3}
    for block, shape in zip(blocks, shapes):
        assert shape.category == category
        expected = _brute_force(shape)
        got = denormalise(block, *TRUNC).reshape(-1).astype(np.float64)
        # nearest-sample error <= half the sample cell diagonal < SPACING; float32 rounding is far smaller
        np.testing.assert_allclose(got, expected, rtol=0, atol=SPACING + 1e-6)


def test_blocks_equal_their_shapes_sampled():
    blocks, labels = synthetic_blocks(60, seed=3, return_labels=True)
    shapes = synthetic_shapes(60, seed=3)
    assert [s.category for s in shapes] == list(labels)
    for block, shape in zip(blocks, shapes):
        again = np.clip(normalise(sample_volume(shape.sdf, (16, 16, 16), H, truncation=TRUNC), *TRUNC), 0, 1)
        np.testing.assert_allclose(block, again, rtol=0, atol=1e-6)


def test_shape_dtype_range_and_zero_crossing():
    blocks, labels = synthetic_blocks(400, seed=5, return_labels=True)
    assert blocks.shape == (400, 16, 16, 16) and blocks.dtype == np.float32 and blocks.flags.c_contiguous
    assert labels.shape == (400,) and set(labels) == set(CATEGORIES)
    assert blocks.min() == 0.0 and blocks.max() == 1.0 and np.all((blocks >= 0) & (blocks <= 1))
    zero = normalise(np.float32(0.0), *TRUNC)
    flat = blocks.reshape(len(blocks), -1)
    assert np.all(flat.min(axis=1) < zero) and np.all(flat.max(axis=1) > zero)  # every block has both signs


def test_anchor_on_surface_in_central_region():
    centre = np.full(3, 7.5 * H)
    for s in synthetic_shapes(200, seed=8):
        assert abs(float(s.sdf(s.anchor))) < 1e-12
        assert np.all(np.abs(s.anchor - centre) <= 4 * H + 1e-12)


def test_rotations_uniform_over_so3():
    shapes = synthetic_shapes(1500, seed=21)
    rots = np.stack([s.rotation for s in shapes])
    assert np.allclose(rots @ rots.transpose(0, 2, 1), np.eye(3), atol=1e-12)
    assert np.allclose(np.linalg.det(rots), 1.0)
    # Haar measure: E[R] = 0, and each column is uniform on the sphere, so every coordinate of it is U(-1, 1)
    assert np.all(np.abs(rots.mean(axis=0)) < 4 * np.sqrt(1 / 3 / len(rots)))
    for col in range(3):
        for coord in range(3):
            assert stats.kstest(rots[:, coord, col], stats.uniform(-1, 2).cdf).pvalue > 1e-3
    normals = np.stack([s.sdf.normal for s in shapes if s.category == "plane"])
    assert stats.kstest(normals[:, 2], stats.uniform(-1, 2).cdf).pvalue > 1e-3


def test_deterministic_by_seed():
    a = synthetic_blocks(70, seed=4)
    b = synthetic_blocks(70, seed=4)
    c = synthetic_blocks(70, seed=5)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)


def test_categories_and_weights():
    _, labels = synthetic_blocks(30, seed=0, categories=("plane",), return_labels=True)
    assert set(labels) == {"plane"}
    _, labels = synthetic_blocks(600, seed=0, categories=("cuboid", "concave"), weights=(3, 1), return_labels=True)
    frac = np.mean(labels == "cuboid")
    assert abs(frac - 0.75) < 5 * np.sqrt(0.75 * 0.25 / 600)
    _, labels = synthetic_blocks(40, seed=0, weights=(0, 1, 0, 0), return_labels=True)
    assert set(labels) == {"cylinder"}
    _, labels = synthetic_blocks(5, categories="concave", return_labels=True)  # one name alone
    assert labels.tolist() == ["concave"] * 5
    assert synthetic_blocks(0, return_labels=True)[1].shape == (0,)
    cylinders = synthetic_shapes(200, seed=2, categories=("cylinder",))
    straight = np.array([s.sdf.cap_radius == s.sdf.radius for s in cylinders])
    assert 0.3 < straight.mean() < 0.7  # both straight cylinders and bulging barrels are drawn
    planes = np.array([s.sdf.planes for s in synthetic_shapes(200, seed=2, categories=("concave",))])
    assert set(planes) == {2, 3}


def test_voxel_size_and_truncation():
    trunc = (-0.02, 0.05)
    blocks = synthetic_blocks(20, seed=6, voxel_size=0.01, truncation=trunc)
    shapes = synthetic_shapes(20, seed=6, voxel_size=0.01)
    for block, shape in zip(blocks, shapes):
        d = sample_volume(shape.sdf, (16, 16, 16), 0.01, truncation=trunc)
        np.testing.assert_allclose(denormalise(block, *trunc), d, rtol=0, atol=1e-6)
    assert synthetic_blocks(0).shape == (0, 16, 16, 16)


def test_redrawn_until_both_signs(monkeypatch):
    # demand both signs by 3 voxels: many draws fail, so the redraw loop runs; it must keep the promise
    monkeypatch.setattr(synthetic, "_CROSSING_MARGIN", 3.0)
    calls = []
    draw = synthetic._draw
    monkeypatch.setattr(synthetic, "_draw", lambda name, m, *a: calls.append(m) or draw(name, m, *a))
    shapes = synthetic_shapes(64, seed=1)
    assert sum(calls) > 64  # some were drawn again
    for s in shapes:
        d = s.sdf(POINTS)
        assert d.min() < -3 * H and d.max() > 3 * H


@pytest.mark.parametrize("kwargs", [
    dict(n=-1), dict(n=2.5), dict(voxel_size=0.0), dict(categories=("sphere",)), dict(categories=()),
    dict(categories=("plane", "plane")), dict(weights=(1, 1)), dict(weights=(1, -1, 1, 1)), dict(weights=(0, 0, 0, 0)),
    dict(weights=("a", "b", "c", "d")),
    dict(truncation=(0.1, -0.04)), dict(truncation=(0.01, 0.1)), dict(truncation=(-0.04,)),
])
def test_bad_arguments(kwargs):
    kwargs = {"n": 3, **kwargs}
    with pytest.raises(InvalidValueError):
        synthetic_blocks(kwargs.pop("n"), **kwargs)


# --- the new primitives -------------------------------------------------------------------------------------------

def test_straight_barrel_is_the_cylinder(rng):
    pts = rng.normal(scale=0.5, size=(5000, 3))
    rot = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    rot *= np.linalg.det(rot)
    got = Barrel((0.1, -0.2, 0.3), 0.3, 0.3, 0.2, rot)(pts)
    np.testing.assert_allclose(got, Cylinder((0.1, -0.2, 0.3), 0.3, 0.2, rot)(pts), rtol=0, atol=1e-12)
    # a barrel that bulges by a hair is continuous with it (no blow-up of the arc radius)
    close = Barrel((0.1, -0.2, 0.3), 0.3, 0.3 * (1 - 1e-10), 0.2, rot)(pts)
    np.testing.assert_allclose(close, got, rtol=0, atol=1e-9)


@settings(max_examples=30, deadline=None)
@given(r_mid=st.floats(0.05, 0.5), share=st.floats(0.0, 0.99), h=st.floats(0.05, 0.5), seed=st.integers(0, 2 ** 16))
@example(r_mid=0.4375, share=2.220446049250313e-16, h=0.5, seed=0)  # bulges by one ulp: R ~ 1e15 (found by a full run)
def test_barrel_matches_dense_meridian_samples(r_mid, share, h, seed):
    r_cap = r_mid - share * min(r_mid, h)  # every allowed bulge, up to a half-circle profile
    rng = np.random.default_rng(seed)
    # query points around the barrel, in 3D with random azimuth
    q = rng.uniform(-1.0, 1.0, size=(400, 3)) * [r_mid + 0.15, r_mid + 0.15, h + 0.15]
    got = Barrel((0, 0, 0), r_mid, r_cap, h)(q)
    arc = _barrel_profile(r_mid, r_cap, h)
    step = 2e-4
    if arc is None:
        seg_r, seg_z = np.full(int(2 * h / step) + 2, r_mid), np.linspace(-h, h, int(2 * h / step) + 2)
    else:
        c, big_r = arc
        alpha = np.arcsin(h / big_r)
        phi = np.linspace(-alpha, alpha, int(2 * alpha * big_r / step) + 2)
        # r_mid - R (1 - cos phi), not c + R cos phi: for a barrel that bulges by a hair, c ~ -R ~ -1e15 and the
        # difference of the two would lose everything below R's last bit (0.125 at 1e15)
        seg_r, seg_z = r_mid - 2 * big_r * np.sin(phi / 2) ** 2, big_r * np.sin(phi)
    rr = np.linspace(0, r_cap, int(r_cap / step) + 2)
    prof = np.concatenate([np.stack([seg_r, seg_z], 1), np.stack([rr, np.full_like(rr, h)], 1),
                           np.stack([rr, np.full_like(rr, -h)], 1)])
    rho, z = np.hypot(q[:, 0], q[:, 1]), q[:, 2]
    dist, _ = cKDTree(prof).query(np.stack([rho, z], 1))
    # the arc's radius at height z, r_mid - z^2 / (R + sqrt(R^2 - z^2)): the same value as c + sqrt(R^2 - z^2), stable
    radius = r_mid if arc is None else r_mid - z ** 2 / (arc[1] + np.sqrt(np.maximum(arc[1] ** 2 - z ** 2, 0)))
    inside = (np.abs(z) <= h) & (rho <= radius)
    np.testing.assert_allclose(got, np.where(inside, -dist, dist), rtol=0, atol=step)


@pytest.mark.parametrize("planes", [2, 3])
def test_concave_corner_is_minus_the_octant(rng, planes):
    # the free space is the octant (or quadrant wedge); near the corner it is a huge box's corner region,
    # so the corner's distance is minus the box's (exact, from the existing Box primitive)
    big = 100.0
    rot = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    rot *= np.linalg.det(rot)
    center = np.array([0.2, -0.1, 0.4])
    box_center = np.array([big, big, big if planes == 3 else 0.0])
    octant = Box(center + rot @ box_center, (big, big, big), rot)
    pts = center + rng.normal(scale=0.3, size=(5000, 3))
    got = ConcaveCorner(center, rot, planes)(pts)
    np.testing.assert_allclose(got, -octant(pts), rtol=0, atol=1e-10)


def test_primitive_parameter_errors():
    with pytest.raises(ValueError):
        Barrel((0, 0, 0), 0.1, 0.2, 0.1)(np.zeros((1, 3)))  # caps wider than the middle
    with pytest.raises(ValueError):
        Barrel((0, 0, 0), 0.5, 0.2, 0.1)(np.zeros((1, 3)))  # bulge 0.3 > half height 0.1
    with pytest.raises(ValueError):
        ConcaveCorner((0, 0, 0), None, 4)(np.zeros((1, 3)))


def test_primitives_broadcast_stacked_parameters(rng):
    # what the generator relies on: (N, 1) parameters and (N, 3, 3) rotations against (N, M, 3) points
    n, m = 5, 200
    pts = rng.normal(scale=0.3, size=(n, m, 3))
    rots = np.stack([np.linalg.qr(rng.normal(size=(3, 3)))[0] for _ in range(n)])
    rots *= np.linalg.det(rots)[:, None, None]
    centers = rng.normal(scale=0.1, size=(n, 1, 3))
    radius = rng.uniform(0.1, 0.3, n)
    cap = radius - rng.uniform(0, 0.05, n) * (np.arange(n) % 2)  # straight and bulging mixed
    half_height = rng.uniform(0.05, 0.3, n)
    planes = np.array([2, 3, 3, 2, 3])
    barrels = Barrel(centers, radius[:, None], cap[:, None], half_height[:, None], rots)(pts)
    corners = ConcaveCorner(centers, rots, planes[:, None])(pts)
    for i in range(n):
        one = Barrel(centers[i, 0], radius[i], cap[i], half_height[i], rots[i])(pts[i])
        np.testing.assert_allclose(barrels[i], one, rtol=0, atol=1e-12)
        np.testing.assert_allclose(corners[i], ConcaveCorner(centers[i, 0], rots[i], int(planes[i]))(pts[i]),
                                   rtol=0, atol=1e-12)


def test_box_sphere_cylinder_distances_are_numpys_formulas_bit_for_bit(rng):
    """The closed forms of Box, Sphere and Cylinder, written here with numpy's reductions (np.linalg.norm and
    max over the last axis): the primitives give the same bits (they sum and compare the components one at a
    time, which is faster), NaN where a point is NaN."""
    from sdfcodec.core.sdf import Sphere

    pts = rng.normal(scale=1.5, size=(3000, 3)) * rng.choice([1e-4, 1.0, 1e3], size=(3000, 1))
    pts[:5] = np.nan
    rot = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    c = np.array([0.1, -0.2, 0.3])
    np.testing.assert_array_equal(Sphere(c, 0.7)(pts), np.linalg.norm(pts - c, axis=-1) - 0.7)
    for r in (None, rot):
        q = np.abs(pts - c if r is None else (pts - c) @ r) - np.array([0.5, 0.2, 1.0])
        want = np.linalg.norm(np.maximum(q, 0.0), axis=-1) + np.minimum(q.max(axis=-1), 0.0)
        np.testing.assert_array_equal(Box(c, (0.5, 0.2, 1.0), r)(pts), want)
        p = pts - c if r is None else (pts - c) @ r
        d = np.stack([np.linalg.norm(p[..., :2], axis=-1) - 0.4, np.abs(p[..., 2]) - 0.8], -1)
        want = np.minimum(d.max(axis=-1), 0.0) + np.linalg.norm(np.maximum(d, 0.0), axis=-1)
        np.testing.assert_array_equal(Cylinder(c, 0.4, 0.8, r)(pts), want)
