"""Bit-exact imports (issue 43): metric codes (spec 4f) and float32 weights keep every observed voxel of a voxblox
layer or an Open3D VoxelBlockGrid bit for bit, in metres, through import, export and import again.

The expectations come from outside the code under test: the tests' own byte-by-byte protobuf reader and writer
(tests/_voxblox_stream.py), the real voxblox layer in ../shared/data, Open3D itself
(``voxel_coordinates_and_flattened_indices``, ``VoxelBlockGrid.load``), and values the tests choose."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

import sdfcodec
from sdfcodec import errors
from sdfcodec.cli import app

from _golden_maps import check_golden_map
from _voxblox_stream import block_message, layer_bytes, layer_voxels, parse_layers
from test_import_export import REAL, _fused_grid

GOLDEN = Path(__file__).resolve().parent / "golden" / "maps" / "metric-raw"


def _bits(a) -> np.ndarray:
    """float32 values as their bit patterns: equal bits, not merely equal values (-0.0 is not 0.0)."""
    return np.ascontiguousarray(np.asarray(a, dtype=np.float32)).view(np.uint32)


def _exact_voxels(m, voxels: dict, vs: float, centre: float) -> None:
    """Every observed source voxel (global index -> (float32 distance, float32 weight)) reads back from the map at
    its own world position with the same bits, its weight exactly, and the map observes nothing else."""
    assert m.header.codes.units == "metres" and m.header.codes.dtype == "float32"
    keys = np.array(list(voxels), dtype=np.int64)
    dist = np.array([v[0] for v in voxels.values()], dtype=np.float32)
    wt = np.array([v[1] for v in voxels.values()], dtype=np.float32)
    ijk_f = ((keys + centre) * vs - np.asarray(m.origin)) / m.voxel_size
    ijk = np.round(ijk_f).astype(np.int64)
    assert np.abs(ijk_f - ijk).max() < 1e-6
    vol = m.decode_region()
    assert vol.dtype == np.float32 and np.array_equal(_bits(vol[tuple(ijk.T)]), _bits(dist))
    coords = np.argwhere(m.block_states() == 2)
    index = {tuple(c): i for i, c in enumerate(coords)}
    rows = np.array([index[tuple(b)] for b in ijk // 16])
    local = ijk % 16
    w = m.read_weights(coords)
    assert np.array_equal(_bits(w[rows, local[:, 0], local[:, 1], local[:, 2]]), _bits(wt))  # float32, exactly
    obs = m.read_observed(coords)
    assert int(obs.sum()) == len(voxels) and obs[rows, local[:, 0], local[:, 1], local[:, 2]].all()
    assert int((w > 0).sum()) == len(voxels)


def test_real_voxblox_layer_imports_bit_exact(shared_data, tmp_path):
    src = shared_data / REAL
    (header, blocks), = parse_layers(src.read_bytes())
    voxels = layer_voxels(header, blocks)
    s = sdfcodec.import_map(src, tmp_path / "real.sdfz")
    assert s["exact"] and s["observed_voxels"] == len(voxels) == 1981
    m = sdfcodec.open_map(tmp_path / "real.sdfz")
    names = {e.name: e.required for e in m.header.extensions}
    assert names["metric-codes"] is True and names["float32-fusion-weights"] is False
    _exact_voxels(m, voxels, header[1][0], 0.5)


def test_real_voxblox_round_trip_is_bit_exact(shared_data, tmp_path):
    """import -> export -> import: the export holds the source's own float32 distances and weights, and the
    second map equals the first bit for bit."""
    src = shared_data / REAL
    (header, blocks), = parse_layers(src.read_bytes())
    voxels = layer_voxels(header, blocks)
    sdfcodec.import_map(src, tmp_path / "a.sdfz")
    sdfcodec.export_map(tmp_path / "a.sdfz", tmp_path / "back.voxblox", format="voxblox", voxels_per_side=8)
    (h2, b2), = parse_layers((tmp_path / "back.voxblox").read_bytes())
    back = layer_voxels(h2, b2)
    assert set(back) == set(voxels)
    assert np.array_equal(_bits([back[k] for k in voxels]), _bits([voxels[k] for k in voxels]))
    sdfcodec.import_map(tmp_path / "back.voxblox", tmp_path / "b.sdfz")
    a, b = sdfcodec.open_map(tmp_path / "a.sdfz"), sdfcodec.open_map(tmp_path / "b.sdfz")
    assert (a.origin, a.truncation, a.shape_voxels) == (b.origin, b.truncation, b.shape_voxels)
    assert np.array_equal(_bits(a.decode_region()), _bits(b.decode_region()))
    coords = np.argwhere(a.block_states() == 2)
    assert np.array_equal(coords, np.argwhere(b.block_states() == 2))
    assert np.array_equal(_bits(a.read_weights(coords)), _bits(b.read_weights(coords)))


def _open3d_observed(g, vs: float, unit: float) -> dict:
    """Observed voxels of a VoxelBlockGrid by Open3D's own accessors: integer voxel position -> (metres as the
    source implies them, float32(float64(tsdf) x unit), and the weight)."""
    xyz, flat = g.voxel_coordinates_and_flattened_indices()
    flat = flat.numpy().reshape(-1)
    t = g.attribute("tsdf").reshape((-1,)).numpy()[flat]
    w = g.attribute("weight").reshape((-1,)).numpy()[flat]
    keys = np.round(xyz.numpy().astype(np.float64) / vs).astype(np.int64)
    seen = w > 0
    metres = (t[seen].astype(np.float32).astype(np.float64) * unit).astype(np.float32)
    return {tuple(k): (d, x) for k, d, x in zip(keys[seen], metres, w[seen])}


@pytest.mark.parametrize("res", [8, 16])
def test_open3d_grid_imports_and_round_trips_bit_exact(tmp_path, res):
    """"Exact" for Open3D (which stores tsdf = distance / truncation): the map returns, for every observed voxel,
    float32(float64(tsdf) x float64(trunc_voxel_multiplier x voxel_size)), voxel_size as Open3D keeps it
    (float32), bit for bit, and its float32 weight; an export loads in Open3D with tsdf values that give those
    metres again, and imports back to the same map."""
    o3d = pytest.importorskip("open3d")
    vs = 0.02
    vbg = _fused_grid(o3d, res, vs)
    vbg.save(str(tmp_path / "grid.npz"))
    sdfcodec.import_map(tmp_path / "grid.npz", tmp_path / "a.sdfz")
    unit = 8.0 * float(np.float32(vs))  # Open3D's default truncation: 8 voxels
    expect = _open3d_observed(vbg, float(np.float32(vs)), unit)
    assert len(expect) > 1000
    m = sdfcodec.open_map(tmp_path / "a.sdfz")
    assert m.voxel_size == float(np.float32(vs))
    _exact_voxels(m, {k: (float(d), float(w)) for k, (d, w) in expect.items()}, m.voxel_size, 0.0)
    out = sdfcodec.export_map(tmp_path / "a.sdfz", tmp_path / "back.npz", format="open3d", voxels_per_side=res)
    assert out["shift"] == [0.0, 0.0, 0.0]
    loaded = _open3d_observed(o3d.t.geometry.VoxelBlockGrid.load(str(tmp_path / "back.npz")), float(np.float32(vs)),
                              unit)
    assert set(loaded) == set(expect)
    assert np.array_equal(_bits([loaded[k] for k in expect]), _bits([expect[k] for k in expect]))
    # imported again (its bounding box may be smaller: Open3D allocates blocks it never observes), every voxel
    # reads the same metres and weight at the same place
    sdfcodec.import_map(tmp_path / "back.npz", tmp_path / "b.sdfz")
    b = sdfcodec.open_map(tmp_path / "b.sdfz")
    assert b.truncation == m.truncation
    _exact_voxels(b, {k: (float(d), float(w)) for k, (d, w) in expect.items()}, m.voxel_size, 0.0)


def test_open3d_tsdf_of_any_imported_distance_imports_back():
    """The export's tsdf: for float32 tsdf values Open3D may store, and truncations whose product rounds (not a
    power of two), the tsdf chosen for the imported metres gives those metres again. Several tsdf values round
    to one distance, so it is often not the source's own tsdf (counted here): the metres are what is kept."""
    from sdfcodec.interop.open3d_grid import metres_of, open3d_tsdf

    rng = np.random.default_rng(1)
    t = np.concatenate([rng.uniform(-1, 1, 200_000), [-1.0, 1.0, 0.0, -0.0, 1e-30]]).astype(np.float32)
    for unit in (8 * float(np.float32(0.02)), 3 * 0.05, 0.1234567):
        d = metres_of(t, unit)
        plain = (d.astype(np.float64) / unit).astype(np.float32)
        assert np.array_equal(_bits(metres_of(open3d_tsdf(d, unit), unit)), _bits(d))
        assert (plain != t).any()  # another tsdf than the source's, for the same metres


def _layer(rng, vps: int, vs: float, idx: np.ndarray, special: bool = False):
    msgs, voxels = [], {}
    for j, b in enumerate(idx):
        d = rng.uniform(-3 * vs, 3 * vs, size=(vps,) * 3).astype(np.float32)
        w = np.where(rng.random((vps,) * 3) < 0.6, rng.uniform(1e-9, 200, size=(vps,) * 3), 0).astype(np.float32)
        if special and j == 0:  # values a normalisation would not keep: -0.0, tiny, subnormal, weights below float16
            d.flat[:5] = [-0.0, 0.0, 1e-30, np.float32(1e-42), np.float32(-3 * vs)]
            w.flat[:5] = [1e-30, 3e-8, 65504.0 * 3, 1.0, 0.5]
        msgs.append(block_message(b, vps, vs, d, w, packed=j % 2 == 1))
        for x, y, z in np.argwhere(w > 0):
            voxels[(b[0] * vps + x, b[1] * vps + y, b[2] * vps + z)] = (d[x, y, z], w[x, y, z])
    return msgs, voxels


@pytest.mark.parametrize("vps,vs,where", [
    (4, 0.003, "mixed"), (5, 0.37, "mixed"), (16, 0.02, "mixed"), (32, 0.05, "mixed"),
    (8, 0.04, "negative"),  # 300 blocks, every index negative
])
def test_unseen_voxblox_layers_import_bit_exact(tmp_path, vps, vs, where):
    rng = np.random.default_rng(vps)
    if where == "negative":
        idx = np.unique(rng.integers(-12, 0, size=(600, 3)), axis=0)[:300]
    else:
        # 20 blocks; 6 of 32^3 voxels (each 8 map blocks, both message formats, the special values): 20 made a
        # 655k-voxel layer and a 320^3 dense decode, for no case the smaller layers and these 6 do not have
        idx = np.unique(rng.integers(-5, 5, size=(60, 3)), axis=0)[:20 if vps <= 16 else 6]
    msgs, voxels = _layer(rng, vps, vs, idx, special=True)
    src = tmp_path / "layer.tsdf"
    src.write_bytes(layer_bytes(vs, vps, msgs))
    sdfcodec.import_map(src, tmp_path / "m.sdfz", batch_blocks=7)
    m = sdfcodec.open_map(tmp_path / "m.sdfz")
    _exact_voxels(m, voxels, vs, 0.5)
    if 16 % vps == 0:  # and back at its own block size, bit for bit
        sdfcodec.export_map(tmp_path / "m.sdfz", tmp_path / "b.voxblox", format="voxblox", voxels_per_side=vps)
        (h, b), = parse_layers((tmp_path / "b.voxblox").read_bytes())
        back = layer_voxels(h, b)
        assert set(back) == set(voxels)
        assert np.array_equal(_bits([back[k] for k in voxels]), _bits([voxels[k] for k in voxels]))


def test_layers_that_are_not_tsdf_are_named(tmp_path):
    vs, vps = 0.05, 8
    d = np.zeros((vps,) * 3, np.float32)
    blk = block_message((0, 0, 0), vps, vs, d, np.ones_like(d))
    p = tmp_path / "esdf_and_occupancy.voxblox"
    p.write_bytes(layer_bytes(vs, vps, [blk], layer_type="esdf") + layer_bytes(vs, vps, [blk], layer_type="occupancy"))
    r = CliRunner().invoke(app, ["import", str(p), str(tmp_path / "o.sdfz")])
    assert r.exit_code == 1 and "esdf, occupancy" in r.output and "no TSDF layer" in r.output
    assert not (tmp_path / "o.sdfz").exists()


def test_normalised_import_and_old_readers(shared_data, tmp_path, monkeypatch):
    """--no-exact writes the raw map every reader opens (to (d_max - d_min) x 2^-24, weights float16); a reader
    without the extension refuses the exact one by name instead of misreading it."""
    src = shared_data / REAL
    r = CliRunner().invoke(app, ["import", str(src), str(tmp_path / "n.sdfz"), "--no-exact", "--json"])
    assert r.exit_code == 0, r.output
    assert json.loads(r.output)["exact"] is False
    sdfcodec.import_map(src, tmp_path / "e.sdfz")
    n, e = sdfcodec.open_map(tmp_path / "n.sdfz"), sdfcodec.open_map(tmp_path / "e.sdfz")
    assert n.header.codes.units is None and not {x.name for x in n.header.extensions} & {
        "metric-codes", "float32-fusion-weights"}
    assert "units" not in json.loads((tmp_path / "n.sdfz" / "zarr.json").read_text())["attributes"]["sdfcodec"][
        "codes"]
    d_min, d_max = n.truncation
    diff = np.abs(n.decode_region() - e.decode_region())
    assert diff.max() <= (d_max - d_min) * 2.0 ** -23
    # the codes the codec sees are the same normalised values (search, transcoding)
    (cn, zn), (ce, ze) = n.read_codes(), e.read_codes()
    assert np.array_equal(cn, ce) and np.abs(zn - ze).max() <= 2.0 ** -22
    assert np.array_equal(np.concatenate([z for _, z in e.iter_codes()]), ze)
    import sdfcodec.core.header as header

    monkeypatch.setattr(header, "KNOWN_EXTENSIONS", header.KNOWN_EXTENSIONS - {"metric-codes"})
    with pytest.raises(errors.VersionError, match="metric-codes"):
        sdfcodec.open_map(tmp_path / "e.sdfz")
    sdfcodec.open_map(tmp_path / "n.sdfz")


def test_search_scores_an_exact_map_as_its_normalised_twin(shared_data, tmp_path):
    """Descriptor search sees the codes as the codec encodes them (normalised), whatever the storage."""
    from sdfcodec.search import engine as S

    sdfcodec.import_map(shared_data / REAL, tmp_path / "e.sdfz")
    sdfcodec.import_map(shared_data / REAL, tmp_path / "n.sdfz", exact=False)
    a, b = (S.search(tmp_path / f"{k}.sdfz", "floor", keep_scores=True, threshold=1e9, scene=False) for k in "en")
    assert np.array_equal(a.all_coords, b.all_coords) and len(a.all_scores) == 4
    np.testing.assert_allclose(a.all_scores, b.all_scores, rtol=1e-5)


def test_commands_on_an_exact_map(shared_data, tmp_path):
    """decode, a region, mesh, compare, verify, info and a remote read all see the exact metres."""
    from sdfcodec.bench.serve import FileServer
    from sdfcodec.map.verify import verify_map

    sdfcodec.import_map(shared_data / REAL, tmp_path / "www" / "e.sdfz")
    path = tmp_path / "www" / "e.sdfz"
    m = sdfcodec.open_map(path)
    full = m.decode_region()
    run = CliRunner().invoke
    assert run(app, ["decode", str(path), str(tmp_path / "d.npy")]).exit_code == 0
    assert np.array_equal(_bits(np.load(tmp_path / "d.npy")), _bits(full))
    part = m.decode_region(((3, 29), (2, 16), (5, 20)))
    assert np.array_equal(_bits(part), _bits(full[3:29, 2:16, 5:20]))
    for coords, blocks in m.iter_decoded():
        for c, b in zip(coords, blocks):
            assert np.array_equal(_bits(b), _bits(full[tuple(slice(16 * v, 16 * v + 16) for v in c)]))
    r = run(app, ["mesh", str(path), str(tmp_path / "m.ply"), "--region", "0:32,0:16,0:16"])
    assert r.exit_code == 0, r.output
    sdfcodec.import_map(shared_data / REAL, tmp_path / "n.sdfz", exact=False)
    r = run(app, ["compare", str(path), str(tmp_path / "n.sdfz"), "--json"])
    c = json.loads(r.output)
    assert r.exit_code == 0 and c["chamfer_l1"] < 1e-7 and c["n_band"] == 1981 and c["near_surface_rmse"] < 1e-7
    assert verify_map(path).ok
    # an export of a region: its voxels bit for bit, nothing outside it
    sdfcodec.export_map(path, tmp_path / "part.voxblox", format="voxblox", voxels_per_side=8,
                        region=((0, 16), (0, 16), (8, 32)))
    (h, b), = parse_layers((tmp_path / "part.voxblox").read_bytes())
    part_voxels = layer_voxels(h, b)
    (h0, b0), = parse_layers((shared_data / REAL).read_bytes())
    source = layer_voxels(h0, b0)
    g0 = np.round(np.asarray(m.origin) / m.voxel_size - 0.5).astype(np.int64)
    inside = {k: v for k, v in source.items() if all(lo <= k[i] - g0[i] < hi for i, (lo, hi) in
                                                      enumerate(((0, 16), (0, 16), (8, 32))))}
    assert set(part_voxels) == set(inside) and 0 < len(inside) < len(source)
    assert np.array_equal(_bits([part_voxels[k] for k in inside]), _bits([inside[k] for k in inside]))
    r = run(app, ["info", str(path)])
    assert r.exit_code == 0 and "metres as written (metric-codes)" in r.output
    with pytest.raises(errors.SDFCodecError, match="level"):
        m.decode_region(level=64)  # raw is not prefix-ordered: one level
    with FileServer(tmp_path / "www") as srv:
        remote = sdfcodec.open_map(srv.url("e.sdfz"))
        assert remote.header.codes.units == "metres"
        assert np.array_equal(_bits(remote.decode_region()), _bits(full))
        coords = np.argwhere(remote.block_states() == 2)
        assert np.array_equal(_bits(remote.read_weights(coords)), _bits(m.read_weights(coords)))


def test_encode_exact_and_what_it_refuses(tmp_path):
    rng = np.random.default_rng(4)
    vol = rng.uniform(-0.04, 0.1, (40, 20, 18)).astype(np.float32)
    vol[0, 0, :3] = [-0.0, np.float32(-0.04), np.float32(0.1)]
    np.save(tmp_path / "v.npy", vol)
    run = CliRunner().invoke
    r = run(app, ["encode", str(tmp_path / "v.npy"), str(tmp_path / "e.sdfz"), "--codec", "raw", "--exact",
                  "--voxel-size", "0.02", "--truncation", "-0.04,0.1"])
    assert r.exit_code == 0, r.output
    e = sdfcodec.open_map(tmp_path / "e.sdfz")
    assert np.array_equal(_bits(e.decode_region()), _bits(vol))
    # transcoding keeps it: exact to exact through the blocks, bit for bit
    r = run(app, ["encode", str(tmp_path / "e.sdfz"), str(tmp_path / "t.sdfz"), "--codec", "raw", "--exact"])
    assert r.exit_code == 0, r.output
    assert np.array_equal(_bits(sdfcodec.open_map(tmp_path / "t.sdfz").decode_region()), _bits(vol))
    for extra in (["--codec", "pca"], ["--codec", "raw", "--code-dtype", "float16"]):
        r = run(app, ["encode", str(tmp_path / "v.npy"), str(tmp_path / "x.sdfz"), "--exact", "--voxel-size", "0.02",
                      *extra])
        assert r.exit_code == 1 and "exact storage" in r.output and not (tmp_path / "x.sdfz").exists()
    with pytest.raises(errors.InvalidValueError, match="write blocks"):
        with sdfcodec.create_map(tmp_path / "w.sdfz", codec=sdfcodec.get_codec("raw"), voxel_size=0.02,
                                 exact=True) as m:
            m.write_codes(np.zeros((1, 3), np.int64), np.zeros((1, 4096), np.float32))
    assert not (tmp_path / "w.sdfz").exists()
    da = pytest.importorskip("dask.array")
    with pytest.raises(errors.InvalidValueError, match="dask"):  # its tasks would store normalised codes
        with sdfcodec.create_map(tmp_path / "k.sdfz", codec=sdfcodec.get_codec("raw"), voxel_size=0.02,
                                 truncation=(-0.04, 0.1), exact=True) as m:
            m.write_volume(da.from_array(vol, chunks=16))
    assert not (tmp_path / "k.sdfz").exists()


def test_update_of_an_exact_map_stays_exact(tmp_path):
    """Blocks written by an update (the map's weights array new then) read back bit for bit beside the old ones."""
    rng = np.random.default_rng(9)
    b = rng.uniform(-0.05, 0.2, (2, 16, 16, 16)).astype(np.float32)
    w = rng.uniform(1e-9, 1e5, b.shape).astype(np.float32)
    with sdfcodec.create_map(tmp_path / "u.sdfz", codec=sdfcodec.get_codec("raw"), voxel_size=0.02,
                             truncation=(-0.05, 0.2), exact=True) as m:
        m.write_blocks(np.array([[0, 0, 0]]), b[:1])
    with sdfcodec.update_map(tmp_path / "u.sdfz") as m:
        m.write_blocks(np.array([[2, 1, 0]]), b[1:], weights=w[1:])
    m = sdfcodec.open_map(tmp_path / "u.sdfz")
    assert m.header.codes.units == "metres" and m.has_weights
    vol = m.decode_region()
    assert np.array_equal(_bits(vol[:16, :16, :16]), _bits(b[0])) and np.array_equal(_bits(vol[32:, 16:, :16]),
                                                                                       _bits(b[1]))
    assert np.array_equal(_bits(m.read_weights(np.array([[2, 1, 0]]))), _bits(w[1:]))


def _golden_inputs():
    """The golden map's blocks, weights and the values they must decode to (chosen here, not read back)."""
    rng = np.random.default_rng(43)
    d_min, d_max = -0.1, 0.3
    blocks = rng.uniform(d_min, d_max, (3, 16, 16, 16)).astype(np.float32)
    blocks[0].flat[:4] = [-0.0, np.float32(d_min), np.float32(d_max), np.float32(1e-42)]
    blocks[2] = np.float32(d_max)  # exactly free space: stored empty
    weights = rng.uniform(0, 40, blocks.shape).astype(np.float32)
    weights[1, :4] = 0  # unobserved: decodes to d_max
    weights[0].flat[:2] = [3e-9, 70000.0]  # beyond float16 on both sides
    coords = np.array([[0, 0, 0], [1, 0, 1], [0, 1, 0]])
    return (d_min, d_max), coords, blocks, weights


def _golden_map(path):
    trunc, coords, blocks, weights = _golden_inputs()
    with sdfcodec.create_map(path, codec=sdfcodec.get_codec("raw"), voxel_size=0.05, truncation=trunc, exact=True,
                             tool="tests/test_exact_import.py golden") as m:
        m.write_blocks(coords, blocks, weights=weights)


def test_golden_metric_map_decodes_forever(regen_golden):
    """A small map with metric codes and float32 weights written once (regenerate only with --regen-golden, for a
    format change): today's reader opens it, verifies it and returns the values written, bit for bit."""
    m = check_golden_map(GOLDEN, _golden_map, regen_golden)
    (d_min, d_max), coords, blocks, weights = _golden_inputs()
    assert m.header.codes.units == "metres" and m.truncation == (d_min, d_max)
    assert m.block_states()[0, 1, 0] == 1  # empty
    expect = np.where(weights > 0, blocks, np.float32(d_max))
    vol = m.decode_region()
    for c, b in zip(coords, expect):
        assert np.array_equal(_bits(vol[tuple(slice(16 * v, 16 * v + 16) for v in c)]), _bits(b))
    got = m.read_weights(coords[:2])
    assert np.array_equal(_bits(got), _bits(weights[:2]))
    raw = json.loads((GOLDEN / "map.zarr" / "zarr.json").read_text())["attributes"]["sdfcodec"]
    assert raw["codes"]["units"] == "metres"
    assert {"name": "metric-codes", "required": True} in raw["extensions"]
    assert {"name": "float32-fusion-weights", "required": False} in raw["extensions"]


@pytest.mark.parametrize("mutate,says", [
    (lambda h: h["extensions"].remove({"name": "metric-codes", "required": True}), "metric-codes"),
    (lambda h: h["codes"].pop("units"), "metric-codes"),
    (lambda h: h["extensions"][h["extensions"].index({"name": "metric-codes", "required": True})].update(
        required=False), "metric-codes"),
    (lambda h: h["codes"].update(dtype="float16"), "units"),
    (lambda h: h["codes"].update(units="millimetres"), "units"),
    (lambda h: (h["codec"].update(id="gaussian-blur"), h["codec"]["config"].update(id="gaussian-blur")), "raw"),
])
def test_inconsistent_metric_headers_are_refused(mutate, says):
    """The field and the required extension go together, on raw float32 codes only (spec 4f)."""
    from sdfcodec.core.header import parse_header

    raw = json.loads((GOLDEN / "map.zarr" / "zarr.json").read_text())["attributes"]["sdfcodec"]
    parse_header(raw)
    mutate(raw)
    with pytest.raises(errors.FormatError, match=says):
        parse_header(raw, "golden")
