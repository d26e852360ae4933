"""The synthetic building (sdfcodec.data.building) and online, memory-bounded fusion into a compressed map
(sdfcodec.fusion.online). CI-sized: the small building, a short fast walk at 160x120, a working set far smaller than
the map so that blocks are paged out and back in."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from scipy import ndimage
from typer.testing import CliRunner

from sdfcodec.cli import app
from sdfcodec.data.building import BUILDINGS, building_path, building_scene, building_sequence
from sdfcodec.data.render import PRESETS
from sdfcodec.errors import InvalidValueError
from sdfcodec.evaluation.tracking import resolve_sequence
from sdfcodec.fusion.tsdf import fuse
from sdfcodec.map import create_map, open_map
from sdfcodec.fusion.online import BLOCK_BYTES, fuse_to_map
from sdfcodec.registry import get_codec, pretrained_codec
from sdfcodec.core.surface import compare_maps
from sdfcodec.map.verify import verify_map

# the walk's start: corridor, into the first room and back (blocks page in); 1/64 of the pixels. 60 frames, not
# 100: the map is still over three working sets (1303 blocks against 384) and 85 blocks page back in (100 frames:
# 1617 and 828), for about half the fusion and encoding time
FRAMES, SIZE = 60, (80, 60)
BUDGET_MB = 12.0  # 384 blocks: a frame's blocks fit, the map's do not


def test_building_presets_are_registered():
    for name, (per_side, frames) in BUILDINGS.items():
        assert PRESETS[name].frames == frames and PRESETS[name].geometry == name
    assert PRESETS["building"].frames >= 5000


def test_building_rooms_connected_and_camera_in_free_space():
    scene, layout = building_scene(0, 2)
    assert len(layout.rooms) == 4
    # free space at eye height on a 10 cm grid: one connected region holding every room and the corridor,
    # enclosed by the exterior walls (nothing outside it is reachable)
    step = 0.1
    xs = np.arange(-1.0, layout.length + 1.0, step)
    ys = np.arange(-8.0, 12.0, step)
    gx, gy = np.meshgrid(xs, ys, indexing="ij")
    pts = np.stack([gx, gy, np.full_like(gx, 1.2)], -1)
    free = scene(pts) > 0.12
    lab, _ = ndimage.label(free)

    def at(x, y):
        return lab[int(round((x - xs[0]) / step)), int(round((y - ys[0]) / step))]

    corridor = at(layout.length / 2, layout.corridor_width / 2)
    assert corridor > 0
    assert all(at(*r.centre) == corridor for r in layout.rooms)
    assert at(-0.8, 0.0) != corridor and at(layout.length / 2, -7.9) != corridor  # outside the building
    # without the doors the rooms would be cut off: a door's opening is free, its lintel is not
    r = layout.rooms[0]
    assert scene(np.array([r.door_x, r.door_y + 0.1 * r.side, 1.0])) > 0.3
    assert scene(np.array([r.door_x, r.door_y + 0.1 * r.side, 2.5])) < 0.2
    # the walk: every camera centre well inside free space and inside the building, every room looped
    poses = building_path(layout, 600)
    eyes = poses[:, :3, 3]
    assert scene(eyes).min() >= 0.3
    assert all(at(x, y) == corridor for x, y, _ in eyes)
    for room in layout.rooms:
        d = np.linalg.norm(eyes[:, :2] - room.centre, axis=1)
        assert d.min() < room.loop_radius + 0.05 and np.ptp(np.arctan2(*(eyes[d < room.loop_radius + 0.1, :2]
                                                                            - room.centre).T[::-1])) > 5.0
    # a smooth walk: steps equal, turns gradual, rotations proper
    steps = np.linalg.norm(np.diff(eyes[:, :2], axis=0), axis=1)
    assert steps.min() > 0.5 * steps.mean() and steps.max() < 1.05 * steps.mean()  # hairpins at doors cut short
    rot = poses[:, :3, :3]
    cos = (np.einsum("nij,nij->n", rot[:-1], rot[1:]) - 1) / 2
    assert np.degrees(np.arccos(np.clip(cos, -1, 1))).max() < 20
    assert np.allclose(np.einsum("nji,njk->nik", rot, rot), np.eye(3), atol=1e-9)


def test_building_is_reproducible_from_its_seed():
    a, pa = building_sequence("building-small", seed=3, frames=50)
    assert np.array_equal(pa, building_sequence("building-small", seed=3)[1][:50])  # a prefix of the walk
    b, pb = building_sequence("building-small", seed=3, frames=50)
    c, _ = building_sequence("building-small", seed=4, frames=50)
    assert a.to_dict() == b.to_dict() and np.array_equal(pa, pb)
    assert a.to_dict() != c.to_dict()
    with pytest.raises(InvalidValueError):
        building_sequence("building-huge")


@pytest.fixture(scope="module")
def small_sequence(tmp_path_factory) -> Path:
    return resolve_sequence("synthetic:building-small", tmp_path_factory.mktemp("seq"), frames=FRAMES, size=SIZE)


@pytest.fixture(scope="module")
def reference(small_sequence):
    """Unbounded fusion: the whole map in open3d's grid."""
    return fuse(small_sequence, quiet=True)


@pytest.fixture(scope="module")
def online(small_sequence, reference, tmp_path_factory):
    out = tmp_path_factory.mktemp("online") / "online.sdfz"
    # the reference's (tight) origin, so that both maps have one lattice and extent
    # keep_weights: the weights (uint8 counts, exact below 256 frames) are compared with the reference's below
    report = fuse_to_map(small_sequence, out, codec=pretrained_codec("pca", 64), working_set_mb=BUDGET_MB,
                         origin=reference.origin, quiet=True, keep_weights=True)
    return out, report


def test_online_fusion_pages_out_and_in_within_its_budget(online):
    out, rep = online
    budget = int(BUDGET_MB * 2**20 // BLOCK_BYTES)
    assert rep["budget_blocks"] == budget == 384
    assert rep["frames_integrated"] == FRAMES
    # the map is several working sets big, so blocks left it, and the walk's return from the room into the
    # corridor brought some back
    assert rep["allocated_blocks"] > 3 * budget
    assert rep["blocks_paged_out"] >= rep["allocated_blocks"] - budget
    assert rep["blocks_paged_in"] > 0
    assert 0 < rep["peak_working_set_blocks"] <= budget
    assert rep["peak_working_set_mib"] <= BUDGET_MB
    m = open_map(out)
    assert m.has_weights and m.records_observation and rep["stores"] == "weights"
    assert m.reader.weights_array.dtype == np.uint8  # kept in a lossy map: uint8 counts (spec 6a)
    assert sum(m.count_states()[k] for k in ("coded", "empty")) == rep["allocated_blocks"]
    assert verify_map(out).ok


def test_online_map_equals_fuse_then_encode(online, reference, tmp_path):
    out, rep = online
    fused = reference
    assert len(fused) == rep["allocated_blocks"]  # the same blocks, on the same lattice
    raw_path, enc_path = tmp_path / "raw.sdfz", tmp_path / "enc.sdfz"
    with create_map(raw_path, codec=get_codec("raw"), voxel_size=0.02, origin=tuple(fused.origin)) as m:
        m.write_blocks(fused.coords, fused.tsdf, weights=fused.weights)
    raw = open_map(raw_path)
    with create_map(enc_path, codec=pretrained_codec("pca", 64), voxel_size=0.02, origin=raw.origin,
                    shape_voxels=raw.shape_voxels) as m:
        m.write_map(raw)  # what `sdfcodec encode` does
    enc, on = open_map(enc_path), open_map(out)
    assert on.shape_voxels == enc.shape_voxels
    # the weights survive paging (float16 counts are exact, and so are the uint8 counts kept): they are what the unbounded grid holds, but for a
    # few voxels on the edge of the band (measured with 100 frames: 77 of 9.4 million), where the two runs'
    # extrinsics differ in the last bits (the reference fuses at the world lattice, the online run relative to its
    # origin)
    diff = np.abs(on.read_weights(fused.coords) - fused.weights)
    assert diff.max() <= 1 and np.count_nonzero(diff) <= 1e-4 * diff.size
    between = compare_maps(enc, on)
    codec_error = compare_maps(raw, enc)
    assert between.chamfer_l1 * 1000 <= 2.0, between.to_dict()
    # and paging costs little beside the codec itself (measured: docs/scale.md)
    assert compare_maps(raw, on).chamfer_l1 <= codec_error.chamfer_l1 + 0.002


def test_online_fusion_refuses_a_working_set_smaller_than_a_frame(small_sequence, tmp_path):
    with pytest.raises(InvalidValueError, match="working-set-mb of at least"):
        fuse_to_map(small_sequence, tmp_path / "x.sdfz", codec=get_codec("raw"), working_set_mb=0.5, quiet=True)
    assert not (tmp_path / "x.sdfz").exists()  # nothing half-written at the path


def test_cli_fuse_online_json(tmp_path):
    # a synthetic: sequence straight from the command line, rendered tiny; the JSON report on a pipe
    out = tmp_path / "cli.sdfz"
    seq = resolve_sequence("synthetic:building-small", tmp_path / "seq", frames=40, size=(80, 60))
    # in process (typer's runner; its output is not a terminal either): a fresh interpreter would add only the
    # start-up of torch and open3d
    r = CliRunner().invoke(app, ["fuse", str(seq), str(out), "--codec", "pca", "--code-size", "64",
                                 "--working-set-mb", "12", "--json"])
    assert r.exit_code == 0, r.output
    rep = json.loads(r.stdout)
    assert rep["budget_blocks"] == 384 and 0 < rep["peak_working_set_blocks"] <= 384
    assert rep["blocks_paged_out"] > 0 and rep["allocated_blocks"] > 384
    assert rep["peak_rss_mib"] > 0 and rep["frames_per_s"] > 0 and rep["frames_integrated"] == 40
    m = open_map(out)
    assert rep["codec"]["id"] == "pca" and m.code_size == 64
    assert m.count_states()["coded"] == rep["blocks"]["coded"] > 0
    # a lossy map keeps its observation mask, not the weights it fused with (sdfcodec.map.weights)
    assert rep["stores"] == "observation mask" and not m.has_weights and m.records_observation
