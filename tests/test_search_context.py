"""Search that fits the map (issue 17): query models chosen from what the map records (behind, up, surface-true
encoding), the up direction in the header and from a sequence's gravity, the calibrated threshold, walls of any
yaw, and the CLI's flags and messages. Expectations are analytic: planes and rooms whose floor, wall and
ceiling blocks are known exactly."""

from __future__ import annotations

import json
import math
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

import sdfcodec
from sdfcodec import pretrained_codec
from sdfcodec.search import engine as S
from sdfcodec.errors import InvalidValueError
from sdfcodec.core.geometry import rot_x
from sdfcodec.core.sdf import Box, Plane, Scene, sample_volume
from sdfcodec.search.context import map_context
from sdfcodec.search.metrics import TRUTH

VS, TRUNC = 0.02, (-0.04, 0.1)


@pytest.fixture(scope="module")
def pca64():
    return pretrained_codec("pca", 64)


def _map(path, vol, codec, **kw):
    with sdfcodec.create_map(path, codec=codec, voxel_size=VS, truncation=TRUNC, **kw) as w:
        w.write_volume(vol)
    return sdfcodec.open_map(path)


def _plane_blocks(normal, offset, shape, origin=(0.0, 0.0, 0.0), min_voxels: int = 1) -> set:
    """Blocks of a grid holding at least ``min_voxels`` voxels within half a voxel of the plane n.p = offset
    (0.6: a plane midway between voxel layers counts on both sides; a plane crossing a whole block has about 256 such voxels, a corner sliver a few)."""
    from sdfcodec.core.sdf import grid_points

    d = np.abs(Plane(normal, offset)(grid_points(shape, VS, origin)))
    idx, counts = np.unique(np.argwhere(d <= 0.6 * VS) // 16, axis=0, return_counts=True)
    return {tuple(int(v) for v in r) for r, k in zip(idx, counts) if k >= min_voxels}


def _blocks(vol: np.ndarray, fill) -> tuple[np.ndarray, np.ndarray]:
    """Every block of a volume: ``(N, 3)`` indices and ``(N, 16, 16, 16)`` values (padded with ``fill``)."""
    from sdfcodec.core.blocks import split_blocks

    b = split_blocks(vol, fill)
    return np.argwhere(np.ones(b.shape[:3], bool)), b.reshape(-1, 16, 16, 16)


def _selected(res) -> set:
    return {tuple(int(v) for v in c) for c in res.coords}


# ------------------------------------------------------------------------------------------ header and fuse
def test_header_up_is_optional_kept_by_transcoding_and_checked(tmp_path, pca64):
    vol = sample_volume(Plane((0, 0, 1), 0.3), (32, 32, 32), VS, truncation=TRUNC)
    plain = _map(tmp_path / "plain.sdfz", vol, pca64)
    assert plain.header.up is None
    doc = json.loads((tmp_path / "plain.sdfz" / "zarr.json").read_text())["attributes"]["sdfcodec"]
    assert "up" not in doc  # an unknown up is left out, not written as null: older readers open the map
    m = _map(tmp_path / "up.sdfz", vol, pca64, up=(0.0, -2.0, 0.0))
    assert m.header.up == (0.0, -1.0, 0.0)
    with sdfcodec.create_map(tmp_path / "t.sdfz", codec=sdfcodec.get_codec("raw"), voxel_size=VS) as w:
        w.write_map(m)
    assert sdfcodec.open_map(tmp_path / "t.sdfz").header.up == (0.0, -1.0, 0.0)
    with pytest.raises(InvalidValueError, match="non-zero length"):
        sdfcodec.create_map(tmp_path / "bad.sdfz", codec=pca64, voxel_size=VS, up=(0, 0, 0))


def test_sequence_up_is_minus_gravity_in_the_world(tmp_path):
    from sdfcodec.fusion.tsdf import sequence_up

    (tmp_path / "gravity-direction.txt").write_text("0\n0\n9.81\n")  # gravity along the first camera's +z
    pose = np.eye(4)
    pose[:3, :3] = rot_x(math.pi / 2)  # camera z is world -y
    seq = SimpleNamespace(path=tmp_path, entries=[SimpleNamespace(path=Path("frame-000000.depth.png"), pose=pose)])
    np.testing.assert_allclose(sequence_up(seq), [0.0, 1.0, 0.0], atol=1e-12)
    assert sequence_up(SimpleNamespace(path=tmp_path / "none", entries=seq.entries)) is None


# ------------------------------------------------------------------------------------------------ context
def test_context_from_what_the_map_records(tmp_path, pca64):
    shape = (48, 48, 48)
    solid = sample_volume(Plane((0, 0, 1), 0.37), shape, VS, truncation=TRUNC)
    fused_style = np.where(Plane((0, 0, 1), 0.37)(sdfcodec.core.sdf.grid_points(shape, VS)) < TRUNC[0], TRUNC[1],
                           solid).astype(np.float32)
    c = map_context(_map(tmp_path / "s.sdfz", solid, pca64))
    assert c.behind == "solid" and not c.weighted and c.up == (0.0, 0.0, 1.0) and "+z" in c.up_source
    c = map_context(_map(tmp_path / "u.sdfz", fused_style, pca64))
    assert c.behind == "unobserved" and "no observation" in c.behind_source and not c.weighted
    # a map that records its observation is fused, whatever its values
    path = tmp_path / "m.sdfz"
    coords, blocks = _blocks(fused_style, TRUNC[1])
    _, obs = _blocks(Plane((0, 0, 1), 0.37)(sdfcodec.core.sdf.grid_points(shape, VS)) >= TRUNC[0], False)
    with sdfcodec.create_map(path, codec=pca64, voxel_size=VS, up=(0, 1, 1)) as w:
        w.write_blocks(coords, blocks, observed=obs)
    c = map_context(sdfcodec.open_map(path))
    assert c.behind == "unobserved" and c.weighted and "header" in c.up_source
    np.testing.assert_allclose(c.up, np.array([0, 1, 1]) / math.sqrt(2))
    c = map_context(sdfcodec.open_map(path), behind="solid", up="1,0,0")
    assert (c.behind, c.up, c.behind_source, c.up_source) == ("solid", (1.0, 0.0, 0.0), "given", "given")


# ------------------------------------------------------------------------------------------------ retrieval
def test_exact_floor_with_defaults_finds_the_floor(tmp_path, pca64):
    # the failure: an exact SDF, floor over solid ground with a box on it; main selected none
    shape = (96, 96, 48)
    h = 0.331
    scene = Scene([Box((1.0, 1.0, h - 1.0), (3.0, 3.0, 1.0)), Box((1.2, 1.1, h + 0.2), (0.15, 0.2, 0.2))])
    m = _map(tmp_path / "room.sdfz", sample_volume(scene, shape, VS, truncation=TRUNC), pca64)
    res = S.search(m, "floor", threshold="auto", keep_scores=True)
    assert res.stats["context"]["behind"] == "solid" and res.stats["threshold_info"]["method"] == "calibrated"
    truth = _plane_blocks((0, 0, 1), h, shape)
    # blocks the box's footprint or sides also reach are not clean floor
    box_blocks = {(x, y, z) for x in range(2, 6) for y in range(2, 6) for z in range(0, 3)}
    clean = {b for b in truth if b not in box_blocks}
    got = _selected(res)
    assert len(got & clean) >= 0.9 * len(clean)
    assert len(got & truth) >= 0.9 * len(got)


def test_walls_of_any_yaw_and_the_ceiling(tmp_path, pca64):
    shape = (64, 64, 64)
    yaw = math.radians(33.0)
    n = (math.cos(yaw), math.sin(yaw), 0.0)
    off = 0.62
    vol = sample_volume(Plane(n, off), shape, VS, truncation=TRUNC)  # solid behind a wall facing -n... n.p<=off
    m = _map(tmp_path / "wall.sdfz", vol, pca64)
    res = S.search(m, "wall", threshold="auto")
    truth, clean = _plane_blocks(n, off, shape), _plane_blocks(n, off, shape, min_voxels=128)
    got = _selected(res)
    assert len(got & clean) >= 0.9 * len(clean) and len(got & truth) >= 0.9 * len(got)
    assert not S.search(m, "floor", threshold="auto").coords.size  # a wall is no floor
    ceil = sample_volume(Plane((0, 0, -1), -0.55), shape, VS, truncation=TRUNC)  # solid above z = 0.55
    m = _map(tmp_path / "ceil.sdfz", ceil, pca64)
    got = _selected(S.search(m, "ceiling", threshold="auto"))
    truth = _plane_blocks((0, 0, -1), -0.55, shape)
    assert len(got & truth) >= 0.9 * len(truth) and len(got & truth) >= 0.9 * len(got)


def test_fused_style_map_with_mask_is_searched_surface_true(tmp_path, pca64):
    # a fused-style field (unobserved beyond |d_min| behind surfaces) with its observation mask: a floor slab
    # and a box on it; the query is encoded surface-true, partly observed blocks are scored where observed
    from sdfcodec.core.sdf import grid_points

    shape, h = (96, 96, 48), 0.171  # mid-block: the blocks above and below hold no surface within a voxel
    scene = Scene([Box((1.0, 1.0, h - 0.5), (3.0, 3.0, 0.5)), Box((1.25, 1.2, h + 0.25), (0.2, 0.25, 0.25))])
    raw = scene(grid_points(shape, VS))
    vol = np.where(raw < TRUNC[0], TRUNC[1], np.clip(raw, *TRUNC)).astype(np.float32)
    coords, blocks = _blocks(vol, TRUNC[1])
    _, seen = _blocks(raw >= TRUNC[0], False)
    path = tmp_path / "fused.sdfz"
    with sdfcodec.create_map(path, codec=pca64, voxel_size=VS, up=(0, 0, 1)) as w:
        w.write_blocks(coords, blocks, observed=seen)
    res = S.search(sdfcodec.open_map(path), "floor", threshold="auto")
    assert res.stats["context"]["weighted_encoding"] and res.stats["observed_scoring"]
    assert res.stats["context"]["behind"] == "unobserved"
    truth = _plane_blocks((0, 0, 1), h, shape)
    box = {(x, y, z) for x in range(3, 6) for y in range(3, 6) for z in range(0, 3)}  # the box's footprint
    clean = _plane_blocks((0, 0, 1), h, shape, min_voxels=128) - box
    got = _selected(res)
    assert len(got & clean) >= 0.9 * len(clean) and len(got & truth) >= 0.9 * len(got)


# --------------------------------------------------------------------------------------------------- CLI
def test_cli_flags_messages_and_hint(tmp_path, pca64):
    from typer.testing import CliRunner

    from sdfcodec.cli import app

    vol = sample_volume(Plane((0, 0, 1), 0.3), (32, 32, 32), VS, truncation=TRUNC)
    _map(tmp_path / "p.sdfz", vol, pca64)
    run = CliRunner().invoke
    r = run(app, ["search", str(tmp_path / "p.sdfz"), "--json"])
    s = json.loads(r.stdout)
    assert r.exit_code == 0 and s["selected"] >= 1 and s["threshold_info"]["method"] == "calibrated"
    assert s["context"]["behind"] == "solid"
    r = run(app, ["search", str(tmp_path / "p.sdfz"), "--threshold", "0"])
    assert r.exit_code == 0 and "nothing selected" in r.stdout and "--top" in r.stdout
    r = run(app, ["search", str(tmp_path / "p.sdfz"), "--up", "0,0,0"])
    assert r.exit_code != 0 and "zero length" in r.stderr and len(r.stderr.strip().splitlines()) == 1
    r = run(app, ["search", str(tmp_path / "p.sdfz"), "--behind", "wet"])
    assert r.exit_code != 0 and "unobserved, solid" in r.stderr
    r = run(app, ["search", str(tmp_path / "p.sdfz"), "--level", "65"])
    assert r.exit_code != 0 and "1..64" in r.stderr


def test_up_is_estimated_from_a_tilted_map_and_a_given_up_wins(tmp_path, pca64):
    # an exact floor tilted 7 degrees about x over a 96 x 96 footprint: no up in the header
    n = np.array([0.0, -math.sin(math.radians(7.0)), math.cos(math.radians(7.0))])
    vol = sample_volume(Plane(n, 0.45), (96, 96, 64), VS, truncation=TRUNC)
    m = _map(tmp_path / "tilted.sdfz", vol, pca64)
    c = map_context(m)
    assert "estimated" in c.up_source
    assert math.degrees(math.acos(min(1.0, float(np.dot(c.up, n))))) < 1.5
    assert map_context(m, up=(0, 0, 1)).up == (0.0, 0.0, 1.0)


def test_pole_and_blocks_like_these(tmp_path, pca64):
    from sdfcodec.core.sdf import Cylinder, grid_points

    shape = (64, 64, 64)
    floor_h = 0.13
    scene = Scene([Box((0.64, 0.64, floor_h - 1.0), (2.0, 2.0, 1.0)), Cylinder((0.3, 0.3, 0.64), 0.07, 1.0)])
    m = _map(tmp_path / "pole.sdfz", sample_volume(scene, shape, VS, truncation=TRUNC), pca64)
    d_pole = np.abs(Cylinder((0.3, 0.3, 0.64), 0.07, 1.0)(grid_points(shape, VS)))
    near = np.argwhere(d_pole <= 0.6 * VS) // 16
    pole_blocks = {tuple(int(v) for v in r) for r in np.unique(near, axis=0) if r[2] >= 1}  # above the floor's
    floor_blocks = _plane_blocks((0, 0, 1), floor_h, shape) - {(0, 0, 0)}  # the pole stands on (0, 0, 0)
    got = _selected(S.search(m, "pole", threshold="auto"))
    assert pole_blocks <= got and not (got & floor_blocks)
    # blocks like a floor block: its own code is the descriptor (score 0); the other pure floor blocks of this
    # exact map are the same block, so they tie with it, and the pole's floor block comes after them
    res = S.search(m, "like:2,2,0", top=len(floor_blocks))
    # 0 up to the float32 rounding of |a|^2 + |b|^2 - 2 a.b (the scoring kernel's product form)
    assert res.scores[0] <= 1e-3 and (2, 2, 0) in _selected(res)
    assert _selected(res) == floor_blocks
    with pytest.raises(InvalidValueError, match="coded block"):
        S.search(m, "like:3,3,3", top=3)
