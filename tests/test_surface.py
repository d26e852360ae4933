"""Surface metrics (sdfcodec.core.surface, docs/surface.md) against independent expectations: analytic planes and
spheres, known shifts, open3d's point-cloud distances, and the dense computation for the streamed map version."""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter
from typer.testing import CliRunner

import sdfcodec
from sdfcodec.core.blocks import assemble_blocks, split_blocks
from sdfcodec.cli import app
from sdfcodec.errors import InvalidValueError, ShapeError
from sdfcodec.core.sdf import Box, Plane, Scene, Sphere, sample_volume
from sdfcodec.core.surface import SurfaceMetrics, compare_maps, compare_volumes, surface_points

VS = 0.02
TRUNC = (-0.04, 0.1)
FIELDS = ("chamfer_l1", "f_score_1", "f_score_2", "precision_1", "recall_1", "precision_2", "recall_2",
          "sign_agreement", "near_surface_rmse", "near_surface_bias")


def _assert_same(a: SurfaceMetrics, b: SurfaceMetrics, rel: float = 1e-9) -> None:
    assert (a.n_original, a.n_decoded, a.n_band) == (b.n_original, b.n_decoded, b.n_band)
    for f in FIELDS:
        assert getattr(a, f) == pytest.approx(getattr(b, f), rel=rel, abs=1e-12, nan_ok=True), f


def _write(path, vol, origin=(0.0, 0.0, 0.0), voxel_size=VS):
    with sdfcodec.create_map(path, codec=sdfcodec.get_codec("raw"), voxel_size=voxel_size, truncation=TRUNC,
                             origin=origin) as m:
        m.write_volume(vol)
    return sdfcodec.open_map(path)


# ------------------------------------------------------------------------------------------ surface points
def test_points_of_a_tilted_plane_lie_on_it():
    origin = (0.5, -0.3, 1.0)
    n = np.array([0.3, -0.2, 1.0])
    centre = np.asarray(origin) + VS * np.array([11.5, 9.5, 13.5])
    plane = Plane(n, float(n @ centre / np.linalg.norm(n)) + 0.013)
    vol = sample_volume(plane, (24, 20, 28), VS, origin, TRUNC)
    p = surface_points(vol, VS, origin)
    assert p.dtype == np.float64 and p.ndim == 2 and p.shape[1] == 3
    assert len(p) > 24 * 20  # crossings along all three axes (the normal has a component on each)
    assert np.abs(plane(p)).max() < 1e-6
    lo, hi = np.asarray(origin), np.asarray(origin) + VS * (np.array(vol.shape) - 1)
    assert np.all(p >= lo - 1e-12) and np.all(p <= hi + 1e-12)


def test_points_of_a_sphere_lie_within_the_linear_interpolation_error():
    r, centre = 0.2, (0.31, 0.33, 0.29)
    vol = sample_volume(Sphere(centre, r), (32, 32, 32), VS, truncation=TRUNC)
    p = surface_points(vol, VS)
    dist = np.linalg.norm(p - centre, axis=1) - r
    # |f| at the root of the linear interpolant is at most max|f''| h^2 / 8, and |f''| <= 1 / (r - h) there
    assert np.abs(dist).max() <= VS ** 2 / (8 * (r - VS)) + 1e-6
    # and every part of the sphere is found: a dense sample of it has a surface point within one voxel
    u = np.random.default_rng(0).normal(size=(2000, 3))
    on_sphere = np.asarray(centre) + r * u / np.linalg.norm(u, axis=1, keepdims=True)
    from scipy.spatial import cKDTree

    assert cKDTree(p).query(on_sphere)[0].max() < VS


def test_the_step_from_d_min_to_unobserved_d_max_is_not_a_surface():
    profile = np.array([0.1] * 5 + [0.03, 0.01, -0.01, -0.03, -0.04, -0.04] + [0.1] * 5, np.float32)
    vol = np.broadcast_to(profile, (4, 4, len(profile))).copy()
    p = surface_points(vol, VS)
    assert len(p) == 16  # one crossing per column, the front one
    assert np.allclose(p[:, 2], 6.5 * VS)
    assert len(surface_points(vol, VS, jump=0.2)) == 32  # a larger jump admits the step behind
    behind = vol.copy()
    behind[:, :, 11:] = -0.04  # the same surface, observed behind: the same points
    m = compare_volumes(vol, behind, VS)
    assert m.chamfer_l1 == 0.0 and m.f_score_1 == 1.0 and m.n_original == m.n_decoded == 16


def test_zero_counts_as_non_negative():
    vol = np.zeros((3, 3, 3), np.float32)
    vol[:, :, 0] = -0.01  # -0.01 -> 0 is a crossing at the zero voxel; 0 -> 0 is none
    p = surface_points(vol, VS)
    assert len(p) == 9 and np.allclose(p[:, 2], VS)


# --------------------------------------------------------------------------------------------------- metrics
def _plane_z(c: float, shape=(8, 8, 40)) -> np.ndarray:
    return sample_volume(Plane((0, 0, 1), c), shape, VS, truncation=TRUNC)


def test_a_volume_against_itself_is_perfect():
    vol = sample_volume(Scene([Sphere((0.3, 0.3, 0.3), 0.17), Plane((0, 1, 0), 0.111)]), (32, 32, 32), VS,
                        truncation=TRUNC)
    m = compare_volumes(vol, vol, VS)
    assert m.chamfer_l1 == 0.0 and m.f_score_1 == m.f_score_2 == 1.0
    assert m.sign_agreement == 1.0 and m.near_surface_rmse == 0.0 and m.near_surface_bias == 0.0
    assert m.n_original == m.n_decoded > 0 and m.n_band > 0


@pytest.mark.parametrize("shift, f1, f2", [(0.5 * VS, 1.0, 1.0), (1.5 * VS, 0.0, 1.0), (2.5 * VS, 0.0, 0.0)])
def test_a_shifted_plane_gives_the_shift_as_chamfer_and_f_steps_at_tau(shift, f1, f2):
    c = 0.301
    m = compare_volumes(_plane_z(c), _plane_z(c + shift), VS)
    assert m.n_original == m.n_decoded == 64
    assert m.chamfer_l1 == pytest.approx(shift, abs=1e-6)
    assert (m.f_score_1, m.precision_1, m.recall_1) == (f1, f1, f1)
    assert (m.f_score_2, m.precision_2, m.recall_2) == (f2, f2, f2)
    assert m.near_surface_bias < 0  # the decoded surface is further along +z: distances are smaller
    band = np.abs(_plane_z(c)) < 2 * VS
    assert m.n_band == band.sum()


def test_directed_distances_agree_with_open3d():
    o3d = pytest.importorskip("open3d")
    rng = np.random.default_rng(7)
    base = sample_volume(Scene([Sphere((0.32, 0.3, 0.34), 0.16), Plane((0.1, 0.2, 1), 0.12)]), (36, 32, 30), VS,
                         origin=(0.1, -0.2, 0.05), truncation=TRUNC)
    noise = gaussian_filter(rng.normal(size=base.shape), 1.5).astype(np.float32)
    dec = np.clip(base + 0.3 * VS * noise / noise.std(), *TRUNC).astype(np.float32)
    origin = (0.1, -0.2, 0.05)
    a, b = surface_points(base, VS, origin), surface_points(dec, VS, origin)

    def cloud(p):
        return o3d.geometry.PointCloud(o3d.utility.Vector3dVector(p))

    d_ab = np.asarray(cloud(a).compute_point_cloud_distance(cloud(b)))
    d_ba = np.asarray(cloud(b).compute_point_cloud_distance(cloud(a)))
    m = compare_volumes(base, dec, VS, origin=origin)
    assert (m.n_original, m.n_decoded) == (len(a), len(b))
    assert m.chamfer_l1 == pytest.approx(0.5 * (d_ab.mean() + d_ba.mean()), rel=1e-9)
    for k, (f, p, r) in {1: (m.f_score_1, m.precision_1, m.recall_1),
                         2: (m.f_score_2, m.precision_2, m.recall_2)}.items():
        p_ref, r_ref = np.mean(d_ba <= k * VS), np.mean(d_ab <= k * VS)
        assert p == pytest.approx(p_ref) and r == pytest.approx(r_ref)
        assert f == pytest.approx(2 * p_ref * r_ref / (p_ref + r_ref))
    assert 0 < m.f_score_1 < 1  # the noise moves the surface by a fraction of a voxel: not trivial
    band = np.abs(base) < 2 * VS
    e = dec[band].astype(np.float64) - base[band]
    assert m.near_surface_rmse == pytest.approx(np.sqrt(np.mean(e ** 2)))
    assert m.near_surface_bias == pytest.approx(e.mean())
    assert m.sign_agreement == pytest.approx(np.mean((dec[band] < 0) == (base[band] < 0)))


def test_observed_mask_and_band_width_select_the_band():
    vol = _plane_z(0.301)
    dec = _plane_z(0.311)
    observed = np.ones(vol.shape, bool)
    observed[:4] = False
    full, half = compare_volumes(vol, dec, VS), compare_volumes(vol, dec, VS, observed=observed)
    assert half.n_band * 2 == full.n_band and half.chamfer_l1 == full.chamfer_l1
    assert compare_volumes(vol, dec, VS, band=VS).n_band == (np.abs(vol) < VS).sum()


def test_empty_surfaces_give_defined_results_without_warnings(tmp_path):
    free = np.full((8, 8, 8), TRUNC[1], np.float32)
    with sdfcodec.create_map(tmp_path / "e.sdfz", codec=sdfcodec.get_codec("raw"), voxel_size=VS) as m:
        pass  # a map with nothing written: extent (0, 0, 0), no slab to decode
    empty = sdfcodec.open_map(tmp_path / "e.sdfz")
    plane = _plane_z(0.071, (8, 8, 8))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for a, b in [(free, free), (plane, free), (free, plane)]:
            m = compare_volumes(a, b, VS)
            assert m.chamfer_l1 == np.inf and m.f_score_1 == m.f_score_2 == 0.0
            assert m.precision_1 == m.recall_1 == 0.0
        both = compare_volumes(free, free, VS)
        _assert_same(compare_maps(empty, empty), both)
        assert np.isnan(both.near_surface_rmse) and np.isnan(both.sign_agreement) and both.n_band == 0
    d = both.to_dict()
    assert d["chamfer_l1"] is None and d["near_surface_rmse"] is None and d["n_original"] == 0
    json.dumps(d, allow_nan=False)


def test_bad_inputs_are_clear_errors():
    vol = _plane_z(0.3, (8, 8, 8))
    with pytest.raises(ShapeError, match="differ in shape"):
        compare_volumes(vol, vol[:4], VS)
    with pytest.raises(ShapeError, match="3-D"):
        surface_points(vol[0], VS)
    bad = vol.copy()
    bad[0, 0, 0] = np.nan
    with pytest.raises(InvalidValueError, match="NaN"):
        compare_volumes(vol, bad, VS)
    with pytest.raises(InvalidValueError, match="voxel_size"):
        surface_points(vol, 0.0)


# ------------------------------------------------------------------------------------------------------ maps
def _border_scene(shift: float = 0.0) -> np.ndarray:
    # a wall whose face lies across the slab border between x = 127 and 128, and a sphere centred on the border
    # (crossings along y and z in the layers on both sides of it). No chunk of codes is entirely solid: a raw
    # code chunk of all d_min is all zeros, which the map writer does not store (see the report of this branch)
    scene = Scene([Box((130.4 * VS + shift, 0.0, 16 * VS), (3 * VS, 5 * VS, 20 * VS)),
                   Sphere((128 * VS, 16 * VS + shift, 16 * VS), 9 * VS)])
    return sample_volume(scene, (150, 32, 32), VS, origin=(0, 0, 0), truncation=TRUNC)


@pytest.fixture(scope="module")
def border_maps(tmp_path_factory):
    d = tmp_path_factory.mktemp("surface")
    origin = (-1.0, 0.5, 0.25)
    a = _write(d / "a.sdfz", _border_scene(), origin)
    b = _write(d / "b.sdfz", _border_scene(0.3 * VS), origin)
    return a, b, origin


def test_compare_maps_equals_compare_volumes_across_slab_borders(border_maps):
    a, b, origin = border_maps
    assert a.shape_voxels[0] > 128  # the default slab border at x = 128 lies inside
    dense = compare_volumes(a.decode_region(), b.decode_region(), VS, origin=origin)
    assert dense.n_original > 0 and 0 < dense.chamfer_l1 < VS
    x = (surface_points(a.decode_region(), VS, origin)[:, 0] - origin[0]) / VS
    on = np.isclose(x, np.round(x), atol=1e-6)
    # crossings across the border (x between 127 and 128) and along y/z in the layers on both sides of it
    assert np.any((x > 127.1) & (x < 127.9)) and np.any(on & (np.round(x) == 127)) and np.any(on & (np.round(x) == 128))
    done = []
    _assert_same(compare_maps(a, b, progress=done.append), dense)
    assert sum(done) == a.shape_voxels[0] and len(done) == 2
    for slab in (16, 37, 1000):
        _assert_same(compare_maps(a, b, slab=slab), dense)
    _assert_same(compare_maps(a, a), compare_volumes(a.decode_region(), a.decode_region(), VS, origin=origin))


def test_compare_maps_leaves_weight_zero_voxels_out_of_the_band(tmp_path):
    vol = sample_volume(Sphere((0.5, 0.3, 0.3), 0.2), (48, 32, 32), VS, truncation=TRUNC)
    dec = np.clip(vol + 0.005, *TRUNC).astype(np.float32)
    weights = np.ones(vol.shape, np.float32)
    weights[20:30] = 0.0
    blocks, wblocks = split_blocks(vol, TRUNC[1]), split_blocks(weights, 0.0)
    coords = np.argwhere(np.ones(blocks.shape[:3], bool))
    with sdfcodec.create_map(tmp_path / "w.sdfz", codec=sdfcodec.get_codec("raw"), voxel_size=VS,
                             truncation=TRUNC) as m:
        m.write_blocks(coords, blocks[tuple(coords.T)], weights=wblocks[tuple(coords.T)])
    a, b = sdfcodec.open_map(tmp_path / "w.sdfz"), _write(tmp_path / "d.sdfz", dec)
    assert a.has_weights and np.array_equal(assemble_blocks(split_blocks(weights, 0.0)), weights)
    # weight-0 voxels are unobserved: the map decodes them to d_max (spec 6b), and they are out of the band
    assert (a.decode_region()[20:30] == TRUNC[1]).all()
    dense = compare_volumes(a.decode_region(), b.decode_region(), VS, observed=weights > 0)
    full = compare_volumes(vol, b.decode_region(), VS)
    assert 0 < dense.n_band < full.n_band
    _assert_same(compare_maps(a, b, slab=16), dense)


def test_mismatched_maps_are_clear_errors(tmp_path):
    vol = _plane_z(0.1, (16, 16, 16))
    a = _write(tmp_path / "a.sdfz", vol)
    with pytest.raises(InvalidValueError, match="voxel sizes differ.*0.02.*0.03"):
        compare_maps(a, _write(tmp_path / "v.sdfz", vol, voxel_size=0.03))
    with pytest.raises(InvalidValueError, match="origins differ"):
        compare_maps(a, _write(tmp_path / "o.sdfz", vol, origin=(0.0, 0.0, 0.32)))
    with pytest.raises(ShapeError, match=r"extents differ.*\(16, 16, 16\).*\(32, 16, 16\)"):
        compare_maps(a, _write(tmp_path / "e.sdfz", np.concatenate([vol, vol])))


# ------------------------------------------------------------------------------------------------------- CLI
def test_cli_compare_prints_the_table_and_json(border_maps):
    a, b, _ = border_maps
    runner = CliRunner()
    r = runner.invoke(app, ["compare", a.location, b.location, "--json"])
    assert r.exit_code == 0, r.output
    summary = json.loads(r.stdout)
    expected = compare_maps(a, b).to_dict()
    assert {k: summary[k] for k in expected} == pytest.approx(expected, rel=1e-9)
    assert summary["level"] == b.code_size and summary["voxel_size"] == VS
    r = runner.invoke(app, ["compare", a.location, b.location])
    assert r.exit_code == 0, r.output
    for label in ("Chamfer-L1 (mm)", "F-score @ 1 voxel", "F-score @ 2 voxels", "sign agreement",
                  "near-surface RMSE (mm)", "near-surface bias (mm)", "surface points (original)"):
        assert label in r.stdout
    assert f"{1000 * expected['chamfer_l1']:.3f}" in r.stdout


def test_cli_compare_against_the_volume_the_map_was_encoded_from(border_maps, tmp_path):
    """An .npy/.npz ORIGINAL is the volume on DECODED's grid, truncated as the writer truncated it (the volume
    here holds distances beyond the truncation)."""
    a, b, origin = border_maps
    raw = sample_volume(Scene([Box((130.4 * VS, 0.0, 16 * VS), (3 * VS, 5 * VS, 20 * VS)),
                               Sphere((128 * VS, 16 * VS, 16 * VS), 9 * VS)]), (150, 32, 32), VS)  # untruncated
    assert np.array_equal(np.clip(raw, *TRUNC), _border_scene())
    # not compare_maps(a, b): the lossless map's float32 round trip moves voxels of this scene that lie exactly
    # a jump (0.1 m) apart across it, and 88 of 2094 surface points with them
    expected = compare_volumes(_border_scene(), b.decode_region(), VS, origin=origin).to_dict()
    np.save(tmp_path / "v.npy", raw)
    np.savez(tmp_path / "v.npz", tsdf=raw, voxel_size=VS, origin=np.array(origin))
    for path in ("v.npy", "v.npz"):
        r = CliRunner().invoke(app, ["compare", str(tmp_path / path), b.location, "--json"])
        assert r.exit_code == 0, r.output
        summary = json.loads(r.stdout)
        assert {k: summary[k] for k in expected} == pytest.approx(expected, rel=1e-9)
    np.savez(tmp_path / "o.npz", tsdf=raw, voxel_size=VS, origin=np.zeros(3))
    for args, what in [(["o.npz"], "origins differ"), (["v.npy", "--key", "tsdf"], "--key names an array")]:
        r = CliRunner().invoke(app, ["compare", str(tmp_path / args[0]), b.location, *args[1:]])
        assert r.exit_code == 1 and what in r.stderr and "Traceback" not in r.output
    np.save(tmp_path / "short.npy", raw[:100])
    r = CliRunner().invoke(app, ["compare", str(tmp_path / "short.npy"), b.location])
    assert r.exit_code == 1 and "(100, 32, 32) voxels, the map (150, 32, 32)" in r.stderr


def test_cli_compare_errors_are_one_line(border_maps, tmp_path):
    a, _, _ = border_maps
    other = _write(tmp_path / "small.sdfz", _plane_z(0.1, (16, 16, 16)))
    r = CliRunner().invoke(app, ["compare", a.location, other.location])
    assert r.exit_code == 1
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "differ" in lines[0]
    r = CliRunner().invoke(app, ["compare", a.location, str(tmp_path / "missing.sdfz")])
    assert r.exit_code == 1 and "Traceback" not in r.output
