"""Descriptor search and selective expansion (sdfcodec.search), against independent expectations: analytic
floor labels of a synthetic room, brute-force distances computed with numpy from codes read with plain zarr,
prefix matching across code sizes, and the bytes a search reads."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch
import zarr

import sdfcodec
from sdfcodec.bench.search import bench_search
from sdfcodec.core.geometry import axis_rotations, rotation_to
from sdfcodec.search.engine import expand, search
from sdfcodec.search.metrics import TRUTH, evaluate_retrieval
from sdfcodec.search.query import build_query
from sdfcodec.search.models import load_query, save_query
from sdfcodec.search.rooms import LabelledRoom, synthetic_room
from sdfcodec.search.shapes import ConeRotations, cone_rotations, query_blocks
from sdfcodec.search import engine, scoring
from sdfcodec.errors import FormatError, InvalidValueError, SDFCodecWarning
from sdfcodec import pretrained_codec
from sdfcodec.view.search import format_summary, search_command

VS, TRUNC = 0.02, (-0.04, 0.1)


# ----------------------------------------------------------------------------------------------- fixtures
@pytest.fixture(scope="module")
def room() -> LabelledRoom:
    # a small furnished room with a ceiling, turned by a random yaw, its floor at a random height in its blocks
    return synthetic_room(2, size=(2.2, 2.0, 1.9))


@pytest.fixture(scope="module")
def pca128():
    return pretrained_codec("pca", 128)


@pytest.fixture(scope="module")
def maps(tmp_path_factory, room, pca128) -> dict:
    """The room as pca-128, pca-64 (the 128 basis cut to 64: the bases share their first 64 components) and
    pca-32 maps."""
    root = tmp_path_factory.mktemp("search")
    out = {}
    for k in (128, 64, 32):
        path = root / f"room-{k}.sdfz"
        with sdfcodec.create_map(path, codec=pca128.prefix(k), voxel_size=VS, truncation=TRUNC,
                                 origin=tuple(room.origin)) as w:
            w.write_volume(room.volume)
        out[k] = path
    return out


@pytest.fixture(scope="module")
def labels(room, maps) -> dict:
    res = search(sdfcodec.open_map(maps[64]), "floor", keep_scores=True)
    return {"coords": res.all_coords, **room.block_labels(res.all_coords)}


def _key(c: np.ndarray) -> set:
    return {tuple(int(v) for v in row) for row in np.asarray(c)}


def _plain_zarr_codes(path, level=None) -> tuple[np.ndarray, np.ndarray]:
    """Every coded block's code, read with plain zarr (no sdfcodec reader)."""
    g = zarr.open_group(str(path), mode="r")
    coded = np.asarray(g["state"][:]) == 2
    codes = np.asarray(g["codes"][:])
    idx = np.argwhere(coded)
    return idx, codes[coded][:, :level].astype(np.float64)


# ----------------------------------------------------------------------------------------------- query models
def test_floor_model_is_the_analytic_plane_family():
    blocks, rots, pos = query_blocks("floor", behind="solid", offsets=15)
    assert blocks.shape == (15, 16, 16, 16)
    # 15 heights evenly spanning the block's extent [-0.5, 15.5] (voxel centres 0..15), 16/15 voxels apart
    heights = pos[:, 2] + 7.5
    np.testing.assert_allclose(np.diff(heights), 16 / 15, atol=1e-5)
    np.testing.assert_allclose([heights[0], heights[-1]], [-0.5 + 8 / 15, 15.5 - 8 / 15], atol=1e-5)
    z = np.arange(16) * VS
    for b, h in zip(blocks, heights):
        expected = (np.clip(z - h * VS, *TRUNC) - TRUNC[0]) / (TRUNC[1] - TRUNC[0])  # solid below the plane
        np.testing.assert_allclose(b, np.broadcast_to(expected, (16, 16, 16)), atol=1e-6)
    # fused maps never observe more than |d_min| behind a surface: those voxels read as free space
    unobs, _, pos_u = query_blocks("floor")
    assert len(unobs) == 17 and np.allclose(np.diff(pos_u[:, 2]), 1.0)
    for b, h in zip(unobs, pos_u[:, 2] + 7.5):
        d = z - h * VS
        expected = np.where(d < TRUNC[0], 1.0, (np.clip(d, *TRUNC) - TRUNC[0]) / (TRUNC[1] - TRUNC[0]))
        np.testing.assert_allclose(b[3, 5], expected, atol=1e-6)


def test_rotation_sampling():
    rots = axis_rotations()
    assert rots.shape == (24, 3, 3)
    np.testing.assert_allclose(np.linalg.det(rots), 1.0)
    assert len({r.tobytes() for r in rots.round(6)}) == 24
    # the floor under the 24 cube rotations: 6 plane directions at 15 offsets each, duplicates removed
    assert query_blocks("floor", rotations="axis", offsets=15, behind="solid")[0].shape[0] == 90
    cone = cone_rotations(10.0, 32, seed=3)
    np.testing.assert_allclose(cone[0], np.eye(3))
    tilt = np.degrees(np.arccos(np.clip(cone[:, 2, 2], -1, 1)))
    assert tilt.max() <= 10.0 + 1e-6 and tilt.max() > 5.0
    # tilted floors: every plane normal of the model lies within the cone about up
    _, r, _ = query_blocks("floor", rotations=ConeRotations(10.0, 8))
    assert np.all(np.degrees(np.arccos(np.clip(r[:, 2, 2], -1, 1))) <= 10.0 + 1e-4)
    # the built-in families: ceilings are floors upside down; edges: a room's three concave edges (wall-wall,
    # floor-wall, ceiling-wall) at 12 yaws and 5 x 5 places, each holding two perpendicular faces (its
    # voxels' free side is a quarter space: free where both faces' distances are positive)
    floor, ceiling = query_blocks("floor")[0], query_blocks("ceiling")[0]
    np.testing.assert_allclose(ceiling, floor[..., ::-1], atol=1e-6)
    edges, er, ep = query_blocks("edge")
    assert edges.shape[0] == 3 * 12 * 25
    yaws = np.degrees(np.arctan2(er[:, 1, 0], er[:, 0, 0])) % 30.0  # the shape's x axis turned about up
    np.testing.assert_allclose(np.minimum(yaws, 30.0 - yaws), 0.0, atol=1e-4)  # every 30 degrees
    # an up direction other than +z rotates the whole model onto it
    _, r, _ = query_blocks("floor", up=(0.0, 1.0, 1.0))
    np.testing.assert_allclose(r[:, :, 2], np.broadcast_to([0, 2 ** -0.5, 2 ** -0.5], (len(r), 3)), atol=1e-6)


def test_query_model_save_load_roundtrip(tmp_path, pca128):
    model = build_query("wall", codec=pca128.prefix(64), rotations="cone:5:3")
    path = save_query(model, tmp_path / "wall.npz")
    with np.load(path, allow_pickle=False) as z:  # plain arrays only: this would raise on an object array
        assert {"descriptors", "blocks", "__sdfcodec_query__"} <= set(z.files)
    back = load_query(path)
    np.testing.assert_array_equal(back.descriptors, model.descriptors)
    np.testing.assert_array_equal(back.blocks, model.blocks)
    assert back.spec == model.spec and back.codec_config == model.codec_config
    assert back.codec_state_sha256 == model.codec_state_sha256 and back.truncation == model.truncation
    (tmp_path / "bad.npz").write_bytes(b"not a zip")
    with pytest.raises(FormatError):
        load_query(tmp_path / "bad.npz")
    np.savez(tmp_path / "other.npz", x=np.zeros(3))
    with pytest.raises(FormatError, match="not an sdfcodec query model"):
        load_query(tmp_path / "other.npz")


# ----------------------------------------------------------------------------------------------- searching
def test_floor_retrieval_matches_analytic_labels(maps, labels):
    res = search(sdfcodec.open_map(maps[64]), "floor", threshold="auto", keep_scores=True)
    pos, neg = TRUTH["floor-vs-none"](labels)
    assert pos.sum() >= 20
    selected = np.isin(np.arange(len(labels["coords"])),
                       [i for i, c in enumerate(map(tuple, labels["coords"])) if c in _key(res.coords)])
    tp, fp, fn = (selected & pos).sum(), (selected & neg).sum(), (~selected & pos).sum()
    assert tp / (tp + fp) >= 0.9 and tp / (tp + fn) >= 0.9, (tp, fp, fn)
    # nothing selected is a wall or ceiling: every selected block holds floor or an upward-facing surface
    assert np.all((labels["floor"] > 0) | (labels["up"] > 0.5) | ~selected)
    assert res.stats["blocks_scored"] == len(labels["coords"]) and res.stats["selected"] == len(res)


def test_scores_equal_brute_force_numpy(maps):
    m = sdfcodec.open_map(maps[64])
    model = build_query("floor", map=m)
    # the descriptors are the map codec's encoding of the analytic planes
    blocks, _, _ = query_blocks("floor", voxel_size=VS, truncation=TRUNC)
    np.testing.assert_allclose(model.descriptors, m.codec.encode(blocks), rtol=1e-5, atol=1e-4)
    idx, codes = _plain_zarr_codes(maps[64])
    q = model.descriptors.astype(np.float64)
    d = ((codes[:, None, :] - q[None]) ** 2).sum(-1)
    expected = d.min(1)
    res = search(m, model, keep_scores=True)
    order = {tuple(c): i for i, c in enumerate(res.all_coords)}
    got = res.all_scores[[order[tuple(c)] for c in idx]]
    np.testing.assert_allclose(got, expected, rtol=1e-4, atol=2e-3)
    # selection by threshold and by top-k, with nearest descriptors, from the same brute force
    srt = np.sort(expected)
    k = next(i for i in range(len(srt) // 10, len(srt) - 1) if srt[i + 1] - srt[i] > 0.05)
    t = float(srt[k] + srt[k + 1]) / 2  # a threshold in a gap: no float ties at the boundary
    sel = search(m, model, threshold=t, scene=False)  # the shape score alone (the scene stage is tested apart)
    assert _key(sel.coords) == _key(idx[expected <= t])
    assert np.all(np.diff(sel.scores) >= 0)
    row = {tuple(c): i for i, c in enumerate(idx)}
    for c, s, n in zip(sel.coords, sel.scores, sel.nearest):
        i = row[tuple(c)]
        assert abs(s - expected[i]) <= 2e-3 + 1e-4 * expected[i]
        assert abs(d[i, n] - expected[i]) <= 2e-3 + 1e-4 * expected[i]  # the reported descriptor is a nearest one
    top = search(m, model, top=7, scene=False)
    np.testing.assert_allclose(top.scores, np.sort(expected)[:7], rtol=1e-4, atol=2e-3)
    both = search(m, model, threshold=t, top=5, scene=False)
    assert len(both) == 5 and _key(both.coords) <= _key(sel.coords)


@pytest.mark.parametrize("n_desc", [15, 300])
def test_scorer_in_tiles_equals_brute_force(n_desc):
    """The CPU scorer's products of a few hundred codes (few descriptors) and its row tiles (many) give the
    float64 brute-force minimum distances and a nearest descriptor. Bounded (a search's call): every code within
    the bound gets its score and nearest descriptor; the others a lower bound over the bound, from the first
    PRUNE_PREFIX elements where most codes are far, the full score where most are near (the probe)."""
    rng = np.random.default_rng(n_desc)
    spread = np.linspace(3.0, 0.2, 64).astype(np.float32)  # decreasing, as the components of a pca code
    q = rng.standard_normal((n_desc, 64)).astype(np.float32) * spread
    near_codes = q[rng.integers(0, n_desc, 600)] + 0.1 * rng.standard_normal((600, 64)).astype(np.float32)
    far_codes = rng.standard_normal((1900, 64)).astype(np.float32) * spread * 3 + 8.0 * spread
    codes = np.concatenate([near_codes, far_codes])[rng.permutation(2500)]
    scorer = scoring.Scorer(q, torch.device("cpu"))
    # products of a few hundred codes on the calling thread where one would be threaded (few descriptors); a large
    # model's products in row tiles on every core (rows None)
    assert (scorer.rows is not None and scorer.rows < len(codes)) == (n_desc == 15)
    s, idx = scorer(codes)
    d = ((codes[:, None, :].astype(np.float64) - q[None]) ** 2).sum(-1)
    np.testing.assert_allclose(s, d.min(1), rtol=1e-4, atol=1e-3)
    np.testing.assert_allclose(d[np.arange(len(codes)), idx], d.min(1), rtol=1e-4, atol=1e-3)
    for t, pruned in ((float(np.quantile(s, 0.2)), True), (float(np.quantile(s, 0.7)), False)):
        sb, ib = scorer(codes, t)
        near = s <= t
        assert 0 < near.sum() < len(s)
        np.testing.assert_array_equal(sb <= t, near)
        np.testing.assert_allclose(sb[near], s[near], rtol=1e-4, atol=1e-3)  # float32 rounding of |c|^2 - 2c.q + |q|^2
        np.testing.assert_array_equal(ib[near], idx[near])
        assert np.all(ib[~near] == -1)
        rounding = 1e-5 * ((codes[~near] ** 2).sum(1) + (q ** 2).sum(1).max())  # of |c|^2 - 2c.q + |q|^2
        assert np.all(sb[~near] <= s[~near] + rounding)  # a lower bound of the score
        # pruned: the far codes' bounds are their first components' distance, well under their scores; else the
        # probe saw most codes near the shape and every score is whole
        assert (np.mean(sb[~near] < 0.99 * s[~near]) > 0.5) == pruned


def test_prefix_matching_across_code_sizes(maps, pca128):
    r128 = search(sdfcodec.open_map(maps[128]), "floor", level=32, keep_scores=True)
    r64 = search(sdfcodec.open_map(maps[64]), "floor", level=32, keep_scores=True)
    r32 = search(sdfcodec.open_map(maps[32]), "floor", keep_scores=True)
    for r in (r64, r32):
        assert r.level == 32
        np.testing.assert_array_equal(r.all_coords, r128.all_coords)
        np.testing.assert_allclose(r.all_scores, r128.all_scores, rtol=1e-5, atol=1e-3)
    # the level-32 scores are distances between the first 32 elements of the 128-element codes
    idx, codes = _plain_zarr_codes(maps[128], level=32)
    q = build_query("floor", codec=pca128).descriptors[:, :32].astype(np.float64)
    expected = ((codes[:, None] - q[None]) ** 2).sum(-1).min(1)
    order = {tuple(c): i for i, c in enumerate(r128.all_coords)}
    np.testing.assert_allclose(r128.all_scores[[order[tuple(c)] for c in idx]], expected, rtol=1e-4, atol=2e-3)
    # a 32-element descriptors-only model made with the pca-32 codec matches the first 32 of a 128 map's codes
    small = build_query("floor", codec=pca128.prefix(32), keep_blocks=False)
    r = search(sdfcodec.open_map(maps[128]), small, keep_scores=True)
    assert r.level == 32
    np.testing.assert_allclose(r.all_scores, r128.all_scores, rtol=1e-5, atol=1e-3)
    with pytest.raises(InvalidValueError, match="exceeds the query"):
        search(sdfcodec.open_map(maps[128]), small, level=64)


def test_descriptors_from_another_basis_are_refused(maps):
    from sdfcodec.testing import analytic_blocks

    other = sdfcodec.get_codec("pca", code_size=32).fit(analytic_blocks(300, seed=4))
    model = build_query("floor", codec=other, keep_blocks=False)
    with pytest.raises(InvalidValueError, match="different codec or basis"):
        search(sdfcodec.open_map(maps[64]), model)
    # with its blocks kept, the same model is re-encoded with the map's codec and works
    res = search(sdfcodec.open_map(maps[64]), build_query("floor", codec=other), top=3)
    ref = search(sdfcodec.open_map(maps[64]), "floor", top=3)
    np.testing.assert_allclose(res.scores, ref.scores, rtol=1e-5, atol=1e-3)


def test_non_prefix_codec_refuses_a_prefix_level(tmp_path, room):
    path = tmp_path / "raw.sdfz"
    vol = room.volume[:64, :64, :48]
    with sdfcodec.create_map(path, codec=sdfcodec.get_codec("raw"), voxel_size=VS, truncation=TRUNC) as w:
        w.write_volume(vol)
    m = sdfcodec.open_map(path)
    assert not m.header.codes.prefix_ordered
    with pytest.raises(InvalidValueError, match="not prefix-ordered"):
        search(m, "floor", level=32)
    with pytest.raises(InvalidValueError, match="not prefix-ordered"):
        search(m, build_query("floor", codec=pretrained_codec("pca", 64), keep_blocks=False))
    # at full size, raw codes are the normalised voxels: scores are exact squared voxel distances
    res = search(m, "floor", keep_scores=True)
    blocks, _, _ = query_blocks("floor")
    q = blocks.reshape(len(blocks), -1).astype(np.float64)
    for c, s in zip(res.all_coords[:20], res.all_scores[:20]):
        v = (vol[tuple(slice(16 * a, 16 * a + 16) for a in c)] - TRUNC[0]) / (TRUNC[1] - TRUNC[0])
        # the kernel's expanded form |c|^2 - 2 c.q + |q|^2 is float32: its rounding scales with the squared
        # norms (thousands for raw blocks), not with the score (0.035 off a score of 224 in this room)
        scale = float((v.astype(np.float64) ** 2).sum() + (q ** 2).sum(1).max())
        assert math.isclose(s, ((v.reshape(-1) - q) ** 2).sum(1).min(), rel_tol=1e-4, abs_tol=2e-5 * scale)


class _Counting(zarr.storage.WrapperStore):
    def __init__(self, store):
        super().__init__(store)
        self.keys = []

    async def get(self, key, prototype, byte_range=None):
        self.keys.append(key)
        return await self._store.get(key, prototype, byte_range)


def test_level32_reads_a_quarter_of_the_code_bytes(maps, monkeypatch, tmp_path):
    m = sdfcodec.open_map(maps[128])
    # the shape score alone: the scene stage may re-read the chunks of blocks beyond a level (solid or surface?)
    full = search(m, "floor", top=5, scene=False)
    low = search(m, "floor", level=32, top=5, scene=False)
    assert full.stats["code_bytes_read"] == full.stats["code_bytes_full"] > 0
    assert low.stats["code_bytes_read"] == low.stats["code_bytes_level"]
    # the code chunks are 32 elements wide: level 32 reads only the first one along the code axis
    ratio = low.stats["code_bytes_read"] / full.stats["code_bytes_read"]
    assert 0.15 < ratio < 0.35, ratio
    # independently of the search's own counter: which chunk keys the store is asked for
    store = _Counting(zarr.storage.LocalStore(maps[128], read_only=True))
    search(sdfcodec.open_map(store), "floor", level=32, top=5, scene=False)
    keys = [k for k in store.keys if k.startswith("codes/c/")]
    assert keys and all(k.endswith("/0") for k in keys)
    # bounded memory: codes are scored a batch of chunks at a time, never the whole map at once
    sizes = []
    real = scoring.Scorer.__call__

    def spy(self, codes, bound=None):
        sizes.append(len(codes))
        return real(self, codes, bound)

    monkeypatch.setattr(scoring.Scorer, "__call__", spy)
    small = tmp_path / "small-chunks.sdfz"  # the room spans one default (16^3-block) chunk: use 4^3 ones
    with sdfcodec.create_map(small, codec=m.codec, voxel_size=VS, truncation=TRUNC, chunk_blocks=4) as w:
        w.write_codes(*m.read_codes())
    ms = sdfcodec.open_map(small)
    res = search(ms, "floor", level=32, chunks_per_batch=1, behind="unobserved", up=(0, 0, 1),
                   scene=False)  # no estimates
    assert max(sizes) <= 4 ** 3 and sum(sizes) == res.stats["blocks_scored"] == m.count_states()["coded"]
    assert len(sizes) > 1


def test_bad_arguments(maps):
    m = sdfcodec.open_map(maps[64])
    with pytest.raises(InvalidValueError, match="floor, ceiling, wall, edge, corner"):
        search(m, "sofa")
    with pytest.raises(InvalidValueError, match="threshold"):
        search(m, "floor", threshold=-1.0)
    with pytest.raises(InvalidValueError, match="top"):
        search(m, "floor", top=0)
    with pytest.raises(InvalidValueError, match="level"):
        search(m, "floor", level=65)
    # one user block: its threshold comes from copies of it shifted by up to half a voxel (a constant block is
    # its own shifted copy, so only blocks coded like it are selected)
    res = search(m, np.full((1, 16, 16, 16), TRUNC[1] / 2, np.float32), threshold="auto")
    assert res.stats["threshold_info"]["method"] == "calibrated on shifted copies" and res.threshold < 1e-2


def test_query_for_another_geometry_is_rebuilt_or_warned(maps, pca128):
    m = sdfcodec.open_map(maps[64])
    coarse = build_query("floor", codec=pca128.prefix(64), voxel_size=0.05)
    res = search(m, coarse, top=3)  # named query: rebuilt for the map's 2 cm voxels
    assert res.query.voxel_size == VS
    np.testing.assert_allclose(res.scores, search(m, "floor", top=3).scores, rtol=1e-5)
    user = build_query(np.full((2, 16, 16, 16), 0.05, np.float32) + np.arange(2)[:, None, None, None] * 0.01,
                         codec=pca128.prefix(64), voxel_size=0.05)
    with pytest.warns(SDFCodecWarning, match="voxel size"):
        search(m, user, top=1)


# ----------------------------------------------------------------------------------------------- expanding
def test_expand_decodes_only_the_selection(maps, room):
    m = sdfcodec.open_map(maps[64])
    res = search(m, "floor", threshold="auto")
    assert len(res) > 0
    exp = expand(m, res, as_="dense")
    full = m.decode_region()
    for c, b in zip(exp.coords, exp.blocks):
        box = tuple(slice(16 * a, min(16 * a + 16, n)) for a, n in zip(c, full.shape))
        np.testing.assert_allclose(b[tuple(slice(0, s.stop - s.start) for s in box)], full[box], atol=1e-5)
    lo = exp.dense_offset
    for c, b in zip(exp.coords, exp.blocks):
        rel = c * 16 - lo
        np.testing.assert_array_equal(exp.dense[rel[0]:rel[0] + 16, rel[1]:rel[1] + 16, rel[2]:rel[2] + 16], b)
    st = exp.stats
    assert st["blocks_decoded"] == len(res) < st["coded_blocks"]
    assert 0 < st["code_bytes_read"] <= st["code_bytes_full"]
    mesh = expand(m, res, as_="mesh").mesh
    v = np.asarray(mesh.vertices)
    assert len(mesh.triangles) > 100
    # the floor of the (yawed, untilted) room is the plane z = 0: the expanded surface lies on it
    assert np.median(np.abs(v[:, 2])) < 0.01
    with pytest.raises(InvalidValueError, match="not coded"):
        expand(m, np.zeros((1, 3), np.int64))


# ----------------------------------------------------------------------------------------------- CLI backend
def test_search_command(tmp_path, maps):
    out = tmp_path / "out"
    summary = search_command(maps[128], "floor", 32, None, None, out, True, "cpu")
    json.dumps(summary)  # JSON-able as it is
    assert summary["level"] == 32 and summary["threshold_mode"] == "auto"
    assert summary["selected"] == len(summary["blocks"]) > 0
    for b in summary["blocks"]:
        assert isinstance(b["coords"], list) and len(b["coords"]) == 3 and all(type(v) is int for v in b["coords"])
    # the floor's plane check (sdfcodec.search.plane_check) made the selection: the blocks its plane accepted, and
    # those observed too little to check that the map-level stage kept
    pc = summary["scene"]["plane_check"]
    assert len(pc["planes"]) == 1 and pc["planes"][0]["checked"] >= summary["selected"]
    assert pc["planes"][0]["accepted"] + pc["kept_unchecked"] == pc["selected"] == summary["selected"]
    assert "plane check:" in format_summary(summary)
    assert (out / "search.png").stat().st_size > 10_000 and (out / "expanded.ply").stat().st_size > 1000
    assert summary["expanded"]["blocks_decoded"] == summary["selected"]
    assert "selected" in format_summary(summary)
    with pytest.raises(sdfcodec.errors.MapExistsError):
        search_command(maps[128], "floor", None, None, 3, out, False, "cpu")
    top = search_command(maps[128], "floor", None, None, 3, None, False, "cpu")
    assert top["selected"] == 3 and "blocks" not in top and top["threshold_mode"] == "none"


def test_cli_search_json(tmp_path, maps, pca128):
    """`sdfcodec search MAP --json` through the real command line: every selected block as a list of three ints
    with its score, equal to a brute-force numpy search of the codes read with plain zarr."""
    from typer.testing import CliRunner

    from sdfcodec.cli import app

    runner = CliRunner()
    # --shape-only: the code-space score, which the brute force computes (the scene stage is tested apart)
    r = runner.invoke(app, ["search", str(maps[128]), "--query", "floor", "--level", "32", "--top", "6", "--json",
                            "--shape-only"])
    assert r.exit_code == 0, r.output
    out = json.loads(r.stdout)
    assert out["level"] == 32 and out["code_size"] == 128 and out["selected"] == 6 and len(out["blocks"]) == 6
    for b in out["blocks"]:
        assert set(b) == {"coords", "score"}
        assert isinstance(b["coords"], list) and len(b["coords"]) == 3 and all(type(v) is int for v in b["coords"])
        assert type(b["score"]) is float
    idx, codes = _plain_zarr_codes(maps[128], level=32)
    q = query_blocks("floor", voxel_size=VS, truncation=TRUNC)[0]
    q = pca128.encode(q)[:, :32].astype(np.float64)
    expected = ((codes[:, None] - q[None]) ** 2).sum(-1).min(1)
    order = np.argsort(expected, kind="stable")
    np.testing.assert_allclose([b["score"] for b in out["blocks"]], expected[order[:6]], rtol=1e-4, atol=2e-3)
    # the blocks named are the brute force's best six (ties aside: compare the scores at the reported coords)
    row = {tuple(int(v) for v in c): i for i, c in enumerate(idx)}
    for b in out["blocks"]:
        assert abs(expected[row[tuple(b["coords"])]] - b["score"]) <= 2e-3 + 1e-4 * b["score"]
    # a threshold selects every block under it, best first (a threshold in a gap of the scores: many blocks of
    # exact floor tie, and float32 scores differ from float64 ones in the last digits)
    srt = expected[order]
    k = next(i for i in range(20, len(srt) - 1) if srt[i + 1] - srt[i] > 0.05)
    t = float(srt[k] + srt[k + 1]) / 2
    r = runner.invoke(app, ["search", str(maps[128]), "--level", "32", "--threshold", f"{t!r}", "--json",
                            "--shape-only"])
    assert r.exit_code == 0, r.output
    out = json.loads(r.stdout)
    assert out["threshold_mode"] == "given" and out["selected"] == int((expected <= t).sum())
    assert {tuple(b["coords"]) for b in out["blocks"]} == _key(idx[expected <= t])
    assert [b["score"] for b in out["blocks"]] == sorted(b["score"] for b in out["blocks"])
    # without --json: the human summary, no block list
    r = runner.invoke(app, ["search", str(maps[128]), "--top", "3"])
    assert r.exit_code == 0 and "selected 3 of" in r.stdout and "coords" not in r.stdout


def test_cli_search_errors_are_one_line(tmp_path, room):
    from typer.testing import CliRunner

    from sdfcodec.cli import app

    path = tmp_path / "raw.sdfz"
    with sdfcodec.create_map(path, codec=sdfcodec.get_codec("raw"), voxel_size=VS, truncation=TRUNC) as w:
        w.write_volume(room.volume[:32, :32, :32])
    runner = CliRunner()
    r = runner.invoke(app, ["search", str(path), "--level", "32", "--json"])
    assert r.exit_code != 0 and "not prefix-ordered" in r.stderr and r.stdout.strip() == ""
    assert len(r.stderr.strip().splitlines()) == 1, r.stderr
    r = runner.invoke(app, ["search", str(path), "--query", "sofa"])
    assert r.exit_code != 0 and "floor, ceiling, wall, edge, corner" in r.stderr


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_gpu_scores_equal_cpu(maps):
    m = sdfcodec.open_map(maps[128])
    cpu = search(m, "floor", keep_scores=True, device="cpu")
    gpu = search(m, "floor", keep_scores=True, device="cuda")
    np.testing.assert_allclose(gpu.all_scores, cpu.all_scores, rtol=1e-4, atol=1e-2)


@pytest.mark.slow
def test_floor_precision_recall_target():
    """Paper-scale check (minutes): precision >= 0.9 at recall >= 0.9 for clean floor blocks at pca-64."""
    rooms = [synthetic_room(s, geometry="normal" if s % 2 == 0 else "rich") for s in range(4)]
    rec = evaluate_retrieval(rooms, {"pca-64": pretrained_codec("pca", 64)}, truths=("floor-vs-none",),
                               keep_curves=False)[0]
    assert rec["precision_at_recall"] >= 0.9, rec


def test_repeated_searches_reuse_the_counting_view_and_count_alone(maps):
    """A second search of an open map reads through the view the first opened (no array metadata again) and
    reports its own bytes only; a view held by an unfinished search is not shared."""
    from sdfcodec.search.counting import counting_view, release_view

    m = sdfcodec.open_map(maps[64])
    first = search(m, "floor", threshold=1.0, scene=False).stats
    second = search(m, "floor", threshold=1.0, scene=False).stats
    assert first["code_bytes_read"] == second["code_bytes_read"] == first["code_bytes_full"] > 0
    assert "meta" in first["bytes_read"] and "meta" not in second["bytes_read"]
    assert second["code_bytes_level"] == first["code_bytes_level"]
    view, store = counting_view(m)  # held, as by a search in another thread
    other_view, other_store = counting_view(m)
    assert other_store is not store and other_view is not view
    release_view(store)
    assert counting_view(m)[1] is store and store.bytes == {}
