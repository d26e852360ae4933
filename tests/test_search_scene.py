"""The map-level stage of a search (sdfcodec.search.scene): what a floor, ceiling or wall query means in the map,
against analytic scenes whose floor, table top, ceiling and wall blocks are known exactly; the plane-section
truth of the labelled rooms; and the CLI's --shape-only and digest errors."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

import sdfcodec
from sdfcodec import pretrained_codec
from sdfcodec.search.engine import search
from sdfcodec.search.query import build_query
from sdfcodec.search.models import load_query, save_query
from sdfcodec.search.rooms import synthetic_room
from sdfcodec.errors import InvalidValueError
from sdfcodec.core.sdf import Box, Plane, Scene, grid_points, sample_volume

VS, TRUNC = 0.02, (-0.04, 0.1)


@pytest.fixture(scope="module")
def pca64():
    return pretrained_codec("pca", 64)


def _map(path, vol, codec):
    with sdfcodec.create_map(path, codec=codec, voxel_size=VS, truncation=TRUNC) as w:
        w.write_volume(vol)
    return sdfcodec.open_map(path)


def _near(prim, shape, min_voxels=128) -> set:
    """Blocks holding at least ``min_voxels`` voxels within 0.6 voxel of a primitive's surface."""
    d = np.abs(prim(grid_points(shape, VS)))
    idx, counts = np.unique(np.argwhere(d <= 0.6 * VS) // 16, axis=0, return_counts=True)
    return {tuple(int(v) for v in r) for r, k in zip(idx, counts) if k >= min_voxels}


def _sel(res) -> set:
    return {tuple(int(v) for v in c) for c in res.coords}


@pytest.fixture(scope="module")
def furnished(tmp_path_factory, pca64):
    """An exact room corner: a floor over solid ground, a thick shelf (its top and underside are planes), a tall
    pillar, and a wall along x = 0.45 m, no ceiling."""
    shape = (96, 96, 96)
    h = 0.171  # the floor, mid-block
    floor = Box((1.0, 1.0, h - 1.0), (3.0, 3.0, 1.0))
    table = Box((1.28, 0.96, 0.95), (0.48, 0.64, 0.1))  # a thick shelf: top at 1.05, underside at 0.85
    pillar = Box((0.2, 1.7, 1.0), (0.1, 0.1, 1.0))
    wall = Box((0.45 - 1.0, 1.0, 1.0), (1.0, 3.0, 2.0))  # solid for x < 0.45: a wall facing +x
    scene = Scene([floor, table, pillar, wall])
    m = _map(tmp_path_factory.mktemp("scene") / "room.sdfz", sample_volume(scene, shape, VS, truncation=TRUNC), pca64)
    return SimpleRoom(m, shape, h, floor, table, wall)


class SimpleRoom:
    def __init__(self, m, shape, h, floor, table, wall):
        self.m, self.shape, self.h = m, shape, h
        self.floor_blocks = _near(Plane((0, 0, 1), h), shape)
        self.top_blocks = _near(Plane((0, 0, 1), 1.05), shape) & {(x, y, z) for x in range(2, 6) for y in range(1, 5)
                                                                    for z in range(2, 5)}
        self.wall_blocks = _near(Plane((1, 0, 0), 0.45), shape)


def test_floor_is_the_lowest_level_not_the_table_top(furnished):
    room = furnished
    shape_only = _sel(search(room.m, "floor", threshold="auto", scene=False))
    assert shape_only & room.top_blocks, "the table top is floor-shaped: the shape score alone selects it"
    res = search(room.m, "floor", threshold="auto")
    got = _sel(res)
    assert not (got & room.top_blocks)
    clean = {b for b in room.floor_blocks if b[0] >= 2}  # away from the wall (x < 0.45 m holds both)
    assert len(got & clean) >= 0.9 * len(clean) and got <= room.floor_blocks
    sc = res.stats["scene"]
    assert sc["query"] == "floor" and abs(sc["height"] - room.h) < 2 * VS and "lowest" in sc["rule"]


def test_no_ceiling_in_view_selects_none(furnished):
    room = furnished
    # the table's underside is a down-facing plane: the shape score alone takes it for a ceiling
    assert len(search(room.m, "ceiling", threshold="auto", scene=False)) > 0
    res = search(room.m, "ceiling", threshold="auto")
    assert len(res) == 0 and "no ceiling in view" in res.stats["scene"]["rejected"]


def test_walls_are_large_vertical_planes(furnished):
    room = furnished
    got = _sel(search(room.m, "wall", threshold="auto"))
    shape_only = _sel(search(room.m, "wall", threshold="auto", scene=False))
    table_sides = {b for b in shape_only if b[2] in (2, 3) and b[0] >= 2}  # the shelf's sides
    assert got <= shape_only and not (got & table_sides)
    assert len(got & room.wall_blocks) >= 0.8 * len({b for b in room.wall_blocks if b[2] >= 1})


def test_scene_stage_units():
    from sdfcodec.search.scene import plane_components

    # two coplanar rows of blocks, and a third block on a plane 5 voxels off: two patches
    coords = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0]])
    normals = np.tile([0.0, 0.0, 1.0], (4, 1))
    points = (coords * 16 + 7.5) * VS
    points[3, 2] += 5 * VS
    lab = plane_components(coords, normals, points, VS)
    assert lab[0] == lab[1] == lab[2] != lab[3]


@pytest.mark.parametrize("up", [(0.0, 0.0, 1.0), (0.1, -0.2, 0.97), (-0.17, 0.05, 0.98)])
def test_blocks_of_neighbouring_wall_yaws_join_one_patch(up):
    """The wall model's neighbouring yaws are PLANE_ANGLE_DEG (15 degrees) apart, so two blocks of one wall whose
    nearest descriptors are neighbouring yaws agree: one patch, for every pair of them and any up. The rotations
    are float32 (15 degrees give or take 1e-4): an exact comparison let rounding split some pairs (the kitchen's
    side wall, between two yaws, stayed patches of 3 blocks that no wall was made of)."""
    from sdfcodec.search.scene import PLANE_ANGLE_DEG, plane_components
    from sdfcodec.search.shapes import WALL_YAWS, query_blocks

    rots = query_blocks("wall", up=up)[1]
    normals = np.unique(np.asarray(rots, np.float64)[:, :, 2], axis=0)
    assert len(normals) == WALL_YAWS
    u = np.asarray(up) / np.linalg.norm(up)
    pairs = [(i, j) for i in range(WALL_YAWS) for j in range(i + 1, WALL_YAWS)
             if abs(math.degrees(math.acos(np.clip(normals[i] @ normals[j], -1, 1))) - PLANE_ANGLE_DEG) < 0.01]
    assert len(pairs) == WALL_YAWS  # each yaw and the next, around the circle
    centre = np.array([7.5, 7.5, 7.5]) * VS
    for i, j in pairs:
        # two blocks one above the other on one wall through both planes' line along up: no distance between them
        lab = plane_components(np.array([[0, 0, 0], [0, 0, 1]]), normals[[i, j]],
                               np.stack([centre, centre + 16 * VS * u]), VS)
        assert lab[0] == lab[1], (i, j, math.degrees(math.acos(min(1.0, normals[i] @ normals[j]))))


def test_oblique_wall_blocks_are_clean_in_the_section_truth():
    from sdfcodec.data.render import RoomScene
    from sdfcodec.search.rooms import LabelledRoom
    from sdfcodec.core.geometry import rot_z
    from sdfcodec.search.metrics import TRUTH

    yaw = math.radians(35.0)
    n = np.array([math.cos(yaw), math.sin(yaw), 0.0])
    wall = Box(tuple(n * (0.8 - 0.5) + np.array([0.0, 0.0, 0.64])), (0.5, 3.0, 1.0), rot_z(yaw))  # face n.p = 0.8
    floor = Box((0.64, 0.64, -0.5 + 0.1), (3.0, 3.0, 0.5))
    scene = RoomScene([floor, wall], ["floor", "wall"], (1.28, 1.28, 1.28), 0, "poor")
    shape = (80, 80, 64)
    vol = np.clip(scene(grid_points(shape, VS)), *TRUNC).astype(np.float32)
    room = LabelledRoom(volume=vol, origin=np.zeros(3), voxel_size=VS, truncation=TRUNC, scene=scene, rotation=np.eye(3),
                        size=(1.28, 1.28, 1.28), up=np.array([0.0, 0.0, 1.0]), behind="solid")
    coords = np.argwhere(np.ones((5, 5, 4), bool))
    lab = room.block_labels(coords)
    pos, neg = TRUTH["wall"](lab)
    # blocks well above the floor that the oblique wall crosses near their centre: whole sections, clean
    c = (coords * 16 + 7.5) * VS
    dist = np.abs(c @ n - 0.8) / VS
    crossing = (dist <= 4.0) & (coords[:, 2] >= 1)
    assert crossing.sum() >= 4 and pos[crossing].all()
    assert (lab["wall_section_cover"][crossing] >= 0.9).all()
    assert not pos[dist > 14.0].any()  # no wall in them


@pytest.mark.parametrize("tilt_deg,height", [(6.0, 15.0), (6.0, 15.5), (8.0, 15.3), (10.0, 15.6)])
def test_a_tilted_floor_alone_in_a_block_is_clean_or_a_sliver_in_the_section_truth(tilt_deg, height):
    """A tilted floor alone in a block covers all of its section there: the block is a clean floor block, or a
    sliver left out of the truth, never a negative. The
    section was measured on a plane through the surface voxels' centres, up to a voxel off the surface where the
    floor passes a block's face (measured: 11 of the 17 "false positives" of a tilted exact room, seed 9301,
    were blocks holding nothing but floor, "covering" 0.56-0.84 of their section)."""
    from sdfcodec.data.render import RoomScene
    from sdfcodec.search.rooms import LabelledRoom
    from sdfcodec.search.metrics import SLIVER_SECTION, TRUTH

    tilt = math.radians(tilt_deg)
    rot = np.array([[math.cos(tilt), 0.0, math.sin(tilt)], [0.0, 1.0, 0.0], [-math.sin(tilt), 0.0, math.cos(tilt)]])
    up = rot[:, 2]
    # a point of the floor's top face: `height` voxels up at the middle of the third column of blocks, where the
    # floor leaves the bottom blocks through their top face
    top = np.array([39.5, 32.0, height]) * VS
    # the floor's slab ends inside the fifth column of blocks (along the room's x); those blocks are not checked
    end = 1.43
    floor = Box(tuple(top - 0.5 * up + rot[:, 0] * (end - 3.0 - top @ rot[:, 0])), (3.0, 3.0, 0.5), rot)
    scene = RoomScene([floor], ["floor"], (1.6, 1.28, 0.96), 0, "poor")
    shape = (96, 64, 48)
    vol = np.clip(scene(grid_points(shape, VS)), *TRUNC).astype(np.float32)
    room = LabelledRoom(volume=vol, origin=np.zeros(3), voxel_size=VS, truncation=TRUNC, scene=scene, rotation=rot,
                        size=(1.6, 1.28, 0.96), up=up, behind="solid")
    coords = np.argwhere(np.ones((6, 4, 3), bool))
    lab = room.block_labels(coords)
    pos, neg = TRUTH["floor"](lab)
    # each block's share of its cross-section over which the analytic plane passes among its voxel centres
    g = np.stack(np.meshgrid(*[np.linspace(0.0, 15.0, 61)] * 2, indexing="ij"), -1).reshape(-1, 2)
    share = []
    for c in coords:
        x, y = (16 * c[0] + g[:, 0]) * VS, (16 * c[1] + g[:, 1]) * VS
        z = (top[2] - (up[0] * (x - top[0]) + up[1] * (y - top[1])) / up[2]) / VS - 16 * c[2]  # voxels, this block
        share.append(((z >= 0.0) & (z <= 15.0)).mean())
    share = np.asarray(share)
    x_room = (coords * 16 + 7.5) * VS @ rot[:, 0]
    alone = x_room + 0.5 * 16 * VS < end  # the floor does not end in these blocks
    assert not neg[alone & (lab["surface_voxels"] > 0)].any(), (
        coords[alone & neg].tolist(), lab["floor_section_cover"][alone & neg], lab["floor_section"][alone & neg])
    # blocks the floor crosses over more than a sliver's area among their voxel centres: clean
    strip = alone & (share * 256 >= 1.5 * SLIVER_SECTION)
    assert strip.sum() >= 8 and pos[strip].all(), coords[strip & ~pos].tolist()


def test_cli_shape_only_and_summary(tmp_path, furnished):
    from typer.testing import CliRunner

    from sdfcodec.cli import app

    path = str(furnished.m.location)
    r = CliRunner().invoke(app, ["search", path, "--json"])
    s = json.loads(r.stdout)
    assert r.exit_code == 0 and s["scene"]["query"] == "floor" and s["scene"]["kept"] == s["selected"]
    r = CliRunner().invoke(app, ["search", path, "--shape-only", "--json"])
    s2 = json.loads(r.stdout)
    assert r.exit_code == 0 and s2["scene"] is None and s2["selected"] > s["selected"]
    r = CliRunner().invoke(app, ["search", path, "--query", "ceiling"])
    assert r.exit_code == 0 and "map-level stage" in r.stdout and "--shape-only" in r.stdout


def test_saved_model_of_another_basis_is_one_line_naming_both_digests(tmp_path, furnished):
    from typer.testing import CliRunner

    from sdfcodec.cli import app
    from sdfcodec.testing import analytic_blocks

    other = sdfcodec.get_codec("pca", code_size=64).fit(analytic_blocks(300, seed=4))
    model = build_query("floor", codec=other, keep_blocks=False)
    save_query(model, tmp_path / "other.npz")
    r = CliRunner().invoke(app, ["search", str(furnished.m.location), "--query", str(tmp_path / "other.npz")])
    line = r.stderr.strip()
    assert r.exit_code != 0 and len(line.splitlines()) == 1
    assert model.codec_state_sha256[:16] in line and furnished.m.header.codec.state_sha256[:16] in line
    with pytest.raises(InvalidValueError, match="different codec or basis"):
        search(furnished.m, load_query(tmp_path / "other.npz"))


def test_a_floor_over_the_threshold_everywhere_is_found_among_the_weak_candidates(furnished):
    """A threshold under every block's score but within WEAK_FACTOR of the best: what the automatic threshold meets
    when a level floor lies at the one offset the model's lattice fits worst (every block of it just over the
    threshold; fused-style rooms of seed 8201 lost their whole floor so). No level is anchored by a block under
    the threshold, so the floor is looked for among the weak candidates under the same rules (the lowest large
    level, not the table top) and the search says so. With no candidate within WEAK_FACTOR of the threshold it
    still selects nothing (this once raised a numpy error on the empty list of levels)."""
    from sdfcodec.search.scene import WEAK_FACTOR

    room = furnished
    best = float(np.min(search(room.m, "floor", threshold="auto", scene=False, keep_scores=True).scores))
    assert best > 0
    res = search(room.m, "floor", threshold=best / (0.5 + WEAK_FACTOR / 2))
    got = _sel(res)
    clean = {b for b in room.floor_blocks if b[0] >= 2}  # away from the wall (x < 0.45 m holds both)
    assert not (got & room.top_blocks) and got <= room.floor_blocks and len(got & clean) >= 0.9 * len(clean)
    sc = res.stats["scene"]
    assert sc["under_threshold"] == 0 and "weak" in sc["anchored_by"] and abs(sc["height"] - room.h) < 2 * VS
    none = search(room.m, "floor", threshold=best / (2 * WEAK_FACTOR))
    assert len(none.coords) == 0


def test_levels_of_one_wall_seen_in_pieces_merge():
    """A wall turned 10 degrees from the model's nearest yaw, seen as three patches along it: each block's plane
    point lies on the wall but carries the model's normal, so the largest patch (a column of blocks, too narrow
    for a fit) gives its level the model's normal, and the far patches miss it by 8-11 voxels. The levels merge
    through the plane fitted to all three (before: three levels of 4, 3 and 3 blocks)."""
    from sdfcodec.search.scene import plane_levels

    true_n = np.array([math.cos(math.radians(10)), math.sin(math.radians(10)), 0.0])
    along = np.array([-true_n[1], true_n[0], 0.0])
    model_n = np.array([1.0, 0.0, 0.0])
    pts, comp = [], []
    for k, (start, count) in enumerate(((0.0, 4), (3.5, 3), (-3.5, 3))):  # blocks along the wall, then up it
        for j in range(count):
            pts.append(16 * VS * (start * along + np.array([0.0, 0.0, j])))
            comp.append(k)
    pts, comp = np.asarray(pts), np.asarray(comp)
    normals = np.tile(model_n, (len(pts), 1))
    level, levels = plane_levels(comp, normals, pts, np.ones(3, bool), VS)
    assert len(levels) == 1 and levels[0]["blocks"] == 10 and (level == 0).all()
    assert float(levels[0]["normal"] @ true_n) > math.cos(math.radians(2))
    # a parallel plane 8 voxels behind it stays a level of its own
    pts2 = np.concatenate([pts, pts[comp == 1] - 8 * VS * true_n])
    comp2 = np.concatenate([comp, np.full(3, 3)])
    level2, levels2 = plane_levels(comp2, np.tile(model_n, (len(pts2), 1)), pts2, np.ones(4, bool), VS)
    assert len(levels2) == 2 and level2[3] != level2[0]


@pytest.mark.parametrize("geometry", ["poor", "rich"])
def test_a_fused_style_floor_on_a_layer_of_voxel_centres_is_found(tmp_path, pca64, geometry):
    """The fused-style room of seed 8201 has its floor exactly on a layer of voxel centres, the offset the floor
    model's lattice fits worst: every floor block scores just over the automatic threshold (the rich room's table
    top, one block, under it). The whole floor was lost (0 of 125 and 0 of 83 floor blocks); found among the weak
    candidates it is selected as the room's truth says (sdfcodec.search.metrics.TRUTH)."""
    from sdfcodec.search.metrics import TRUTH

    room = synthetic_room(8201, geometry=geometry, behind="unobserved")
    rel = (0.0 - room.origin[2]) / room.voxel_size  # the floor's top is at z = 0 in this room
    assert abs(rel - round(rel)) < 1e-2  # on a layer of voxel centres (the premise)
    with sdfcodec.create_map(tmp_path / "room.sdfz", codec=pca64, voxel_size=room.voxel_size,
                             truncation=room.truncation, origin=tuple(room.origin)) as w:
        w.write_volume(room.volume)
    with sdfcodec.open_map(tmp_path / "room.sdfz") as m:
        res = search(m, "floor", threshold="auto", keep_scores=True)
        pos, neg = TRUTH["floor"](room.block_labels(res.all_coords))
        chosen = {tuple(c) for c in res.coords.tolist()}
        sel = np.array([tuple(c) in chosen for c in res.all_coords.tolist()])
        counted = pos | neg
        tp = int((sel & pos)[counted].sum())
        assert tp >= 0.9 * int(pos[counted].sum()) and tp >= 0.9 * int(sel[counted].sum())
        assert res.stats["scene"]["under_threshold"] <= 1 and "weak" in res.stats["scene"]["anchored_by"]


def _merge_every_pair_each_pass(level, levels, comp, normals, points, voxel_size):
    """The levels' merge as it was written first (every pair tried again in every pass), and without the check of
    the two levels' normals that spares the fit of pairs that cannot merge: the reference."""
    from sdfcodec.search.scene import ANGLE_SLACK_DEG, PLANE_ANGLE_DEG, PLANE_TOL_VOXELS, _fit_plane

    cos_a, tol = math.cos(math.radians(PLANE_ANGLE_DEG + ANGLE_SLACK_DEG)), PLANE_TOL_VOXELS * voxel_size
    of, owner, merged = level[comp], list(range(len(levels))), len(levels) >= 2
    while merged:
        merged = False
        alive = sorted({owner[j] for j in range(len(levels))}, key=lambda j: -levels[j]["blocks"])
        for a in alive:
            for b in alive:
                if b == a or levels[b]["blocks"] > levels[a]["blocks"] or owner[b] != b or owner[a] != a:
                    continue
                la, lb = levels[a], levels[b]  # no pre-check of their normals: the merge's is a filter only
                ia = np.flatnonzero(np.isin(of, [j for j in range(len(levels)) if owner[j] == a]))
                ib = np.flatnonzero(np.isin(of, [j for j in range(len(levels)) if owner[j] == b]))
                n, d = _fit_plane(normals[np.r_[ia, ib]], points[np.r_[ia, ib]], voxel_size)
                if (n @ la["normal"] < cos_a or n @ lb["normal"] < cos_a
                        or np.median(np.abs(points[ia] @ n - d)) > tol or np.median(np.abs(points[ib] @ n - d)) > tol):
                    continue
                la.update(normal=n, d=d, blocks=la["blocks"] + lb["blocks"])
                owner = [a if o == b else o for o in owner]
                merged = True
    keep = sorted({owner[j] for j in range(len(levels))})
    remap = np.array([keep.index(owner[j]) for j in range(len(levels))], np.int64)
    return np.where(level >= 0, remap[np.maximum(level, 0)], -1), [levels[j] for j in keep]


def test_levels_merge_as_when_every_pair_is_tried_in_every_pass(monkeypatch):
    """The merge of levels that are one plane tries again only the pairs a merge changed: on walls seen in patches
    a few degrees and centimetres off (so they start as separate levels) it merges exactly what trying every pair
    in every pass merges, into the same planes. Seed 152 holds a pair that does not merge until one of its levels
    has merged with a third (a merge remembered by level alone, not by what the level holds, misses it)."""
    import copy

    import sdfcodec.search.scene as scene

    merges = 0
    for seed in range(140, 160):
        rng = np.random.default_rng(seed)
        comp, normals, points, patch = [], [], [], 0
        for _ in range(int(rng.integers(1, 3))):
            yaw = rng.uniform(0, 2 * math.pi)
            n0 = np.array([math.cos(yaw), math.sin(yaw), 0.0])
            along, d0 = np.cross(n0, [0.0, 0.0, 1.0]), rng.uniform(-1, 1)
            for _ in range(int(rng.integers(3, 8))):  # patches along the wall, each tilted and moved on its own
                t = math.radians(rng.uniform(-10, 10))
                nk = math.cos(t) * n0 + math.sin(t) * along
                centre = (d0 + rng.uniform(-0.06, 0.06)) * n0 + rng.uniform(-2, 2) * along
                for _ in range(int(rng.integers(1, 9))):
                    comp.append(patch)
                    normals.append(nk)
                    up = rng.uniform(-0.5, 0.5) * np.array([0, 0, 1.0])
                    points.append(centre + rng.uniform(-0.3, 0.3) * along + up)
                patch += 1
        comp, normals, points = np.asarray(comp, np.int64), np.asarray(normals), np.asarray(points)
        captured = {}
        real = scene._merge_levels

        def spy(level, levels, *rest):
            captured["args"] = (level.copy(), copy.deepcopy(levels), *rest)
            return real(level, levels, *rest)

        monkeypatch.setattr(scene, "_merge_levels", spy)
        got_level, got = scene.plane_levels(comp, normals, points, np.ones(patch, bool), 0.02)
        monkeypatch.undo()
        level0, levels0, *rest = captured["args"]
        want_level, want = _merge_every_pair_each_pass(level0, levels0, *rest)
        merges += len(levels0) - len(want)
        assert np.array_equal(got_level, want_level)
        assert [(lv["blocks"], lv["d"], *lv["normal"]) for lv in got] == [(lv["blocks"], lv["d"], *lv["normal"])
                                                                         for lv in want]
    assert merges >= 10  # the scenarios do merge levels
