"""Bring your own map (issue 43): voxblox TSDF layers and Open3D VoxelBlockGrids into maps and back.

The expectations come from outside the code under test: a plain byte-by-byte protobuf reader and writer of
the tests' own (tests/_voxblox_stream.py), the real voxblox layer in ../shared/data, and Open3D itself
(``voxel_coordinates_and_flattened_indices``, ``VoxelBlockGrid.load``)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

import sdfcodec
from sdfcodec.cli import app
from sdfcodec.errors import FormatError

from _voxblox_stream import block_message, layer_bytes, layer_voxels, parse_layers, synthetic_layer

REAL = "voxblox/labeltsdf_integrator_test_1.tsdf.voxblox"
ROOT = Path(__file__).resolve().parents[1]


def _tolerance(m) -> float:
    """Observed distances come back bit for bit from a map with metric codes (the raw import's default, spec 4f),
    else to float32 rounding of the map's [0, 1] normalisation (2 ulp of 1.0)."""
    if m.header.codes.units == "metres":
        return 0.0
    d_min, d_max = m.truncation
    return (d_max - d_min) * 2.0 ** -23


def _check_voxels(m, voxels: dict, vs: float, centre: float, tol: float | None = None) -> None:
    """Every observed source voxel (global index -> (distance, weight)) decodes at its own world position with its
    distance and weight, and the map observes nothing else."""
    vol = m.decode_region()
    origin = np.asarray(m.origin)
    keys = np.array(list(voxels), dtype=np.int64)
    dist = np.array([v[0] for v in voxels.values()], dtype=np.float32)
    wt = np.array([v[1] for v in voxels.values()], dtype=np.float32)
    world = (keys + centre) * vs
    ijk_f = (world - origin) / m.voxel_size
    ijk = np.round(ijk_f).astype(np.int64)
    assert np.abs(ijk_f - ijk).max() < 1e-6  # on the map's grid, at its own position
    got = vol[tuple(ijk.T)]
    assert np.abs(got - dist).max() <= (_tolerance(m) if tol is None else tol)
    states = m.block_states()
    coords = np.argwhere(states == 2)  # coded
    obs = m.read_observed(coords)
    assert int(obs.sum()) == len(voxels)
    blk = ijk // 16
    index = {tuple(c): i for i, c in enumerate(coords)}
    rows = np.array([index[tuple(b)] for b in blk])
    local = ijk - blk * 16
    assert obs[rows, local[:, 0], local[:, 1], local[:, 2]].all()
    if m.header.codec.id == "raw":  # a lossy map keeps no weights unless asked (keep_weights; spec 6a)
        w = m.read_weights(coords)[rows, local[:, 0], local[:, 1], local[:, 2]]
        # float32 weights with metric codes (exactly), else float16
        assert np.allclose(w, wt, rtol=0 if m.header.codes.units else 2.0 ** -11, atol=0)
    else:
        assert not m.has_weights


def test_real_voxblox_layer_imports_losslessly(shared_data, tmp_path):
    src = shared_data / REAL
    (header, blocks), = [layer for layer in parse_layers(src.read_bytes())]
    voxels = layer_voxels(header, blocks)
    assert len(blocks) == 13 and len(voxels) > 1000
    summary = sdfcodec.import_map(src, tmp_path / "real.sdfz")
    assert summary["format"] == "voxblox" and summary["observed_voxels"] == len(voxels)
    m = sdfcodec.open_map(tmp_path / "real.sdfz")
    assert m.header.codec.id == "raw"
    _check_voxels(m, voxels, header[1][0], 0.5)


def test_real_voxblox_exports_back(shared_data, tmp_path):
    src = shared_data / REAL
    (header, blocks), = parse_layers(src.read_bytes())
    voxels = layer_voxels(header, blocks)
    sdfcodec.import_map(src, tmp_path / "real.sdfz")
    out = sdfcodec.export_map(tmp_path / "real.sdfz", tmp_path / "back.voxblox", format="voxblox", voxels_per_side=8)
    assert out["shift"] == [0.0, 0.0, 0.0] and out["blocks"] == 13
    (h2, b2), = parse_layers((tmp_path / "back.voxblox").read_bytes())
    assert h2[3][0] == b"tsdf" and h2[2][0] == 8 and h2[1][0] == header[1][0]
    back = layer_voxels(h2, b2)
    assert set(back) == set(voxels)
    d = np.array([[voxels[k][0], back[k][0]] for k in voxels])
    w = np.array([[voxels[k][1], back[k][1]] for k in voxels])
    m = sdfcodec.open_map(tmp_path / "real.sdfz")
    assert np.abs(d[:, 0] - d[:, 1]).max() <= _tolerance(m)
    assert np.allclose(w[:, 1], w[:, 0], rtol=2.0 ** -11)
    # and our own reader: a second import of the export gives the same map values
    sdfcodec.import_map(tmp_path / "back.voxblox", tmp_path / "again.sdfz")
    a, b = sdfcodec.open_map(tmp_path / "real.sdfz"), sdfcodec.open_map(tmp_path / "again.sdfz")
    assert a.origin == b.origin and a.truncation == b.truncation
    assert np.abs(a.decode_region() - b.decode_region()).max() <= 2 * _tolerance(a)


def _random_layer(rng, vps: int, vs: float, n: int, packed_every: int = 2):
    """Blocks at random (negative too) indices with random distances, some voxels unobserved."""
    idx = rng.choice(np.arange(-6, 6), size=(n * 3, 3))
    idx = np.unique(idx, axis=0)[:n]
    msgs, voxels = [], {}
    for j, b in enumerate(idx):
        d = rng.uniform(-3 * vs, 3 * vs, size=(vps,) * 3).astype(np.float32)
        w = np.where(rng.random((vps,) * 3) < 0.6, rng.uniform(0.1, 20, size=(vps,) * 3), 0).astype(np.float32)
        msgs.append(block_message(b, vps, vs, d, w, packed=j % packed_every == 1))
        for x, y, z in np.argwhere(w > 0):
            voxels[(b[0] * vps + x, b[1] * vps + y, b[2] * vps + z)] = (float(d[x, y, z]), float(w[x, y, z]))
    return msgs, voxels


@pytest.mark.parametrize("vps,vs", [(5, 0.03), (16, 0.02), (8, 0.1)])
def test_voxblox_any_block_size_and_negative_indices(tmp_path, vps, vs):
    rng = np.random.default_rng(vps)
    msgs, voxels = _random_layer(rng, vps, vs, 20)
    src = tmp_path / "layer.tsdf"
    src.write_bytes(layer_bytes(vs, vps, msgs))
    sdfcodec.import_map(src, tmp_path / "m.sdfz", batch_blocks=1)  # many small groups: blocks cross them
    _check_voxels(sdfcodec.open_map(tmp_path / "m.sdfz"), voxels, vs, 0.5)
    if 16 % vps == 0:  # and back, at its own block size
        sdfcodec.export_map(tmp_path / "m.sdfz", tmp_path / "b.voxblox", format="voxblox", voxels_per_side=vps)
        (h, b), = parse_layers((tmp_path / "b.voxblox").read_bytes())
        back = layer_voxels(h, b)
        assert set(back) == set(voxels)


def test_export_tells_the_format_by_the_name(tmp_path):
    """`export` without --format: a voxblox suffix writes voxblox, .npz Open3D (the same bytes as with --format,
    and the content's own detector agrees); any other name is refused naming it and writes nothing."""
    from sdfcodec.interop.importer import detect_format

    raw = tmp_path / "layer.voxblox"
    synthetic_layer(str(raw), 8)
    sdfcodec.import_map(raw, tmp_path / "m.sdfz")
    runner = CliRunner()
    for name, fmt in (("a.tsdf", "voxblox"), ("b.npz", "open3d")):
        for out, extra in ((tmp_path / name, []), (tmp_path / f"explicit-{name}", ["--format", fmt])):
            r = runner.invoke(app, ["export", str(tmp_path / "m.sdfz"), str(out), "--voxels-per-side", "8", *extra])
            assert r.exit_code == 0, r.output
        assert (tmp_path / name).read_bytes() == (tmp_path / f"explicit-{name}").read_bytes()
        assert detect_format(tmp_path / name) == fmt
    r = runner.invoke(app, ["export", str(tmp_path / "m.sdfz"), str(tmp_path / "c.bin")])
    assert r.exit_code != 0 and "'c.bin'" in r.output and "--format" in r.output
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith((".c", "c."))] == []


def test_import_with_another_codec(tmp_path):
    rng = np.random.default_rng(3)
    msgs, voxels = _random_layer(rng, 8, 0.02, 12)
    src = tmp_path / "layer.voxblox"
    src.write_bytes(layer_bytes(0.02, 8, msgs))
    lossless = sdfcodec.import_map(src, tmp_path / "raw.sdfz")
    codec = sdfcodec.pretrained_codec("pca", 32)
    s = sdfcodec.import_map(src, tmp_path / "pca.sdfz", codec=codec, max_error=0.004)  # encode's residual stage
    m = sdfcodec.open_map(tmp_path / "pca.sdfz")
    assert m.header.codec.id == "pca" and m.code_size == 32
    assert s["blocks"] == lossless["blocks"] and m.origin == sdfcodec.open_map(tmp_path / "raw.sdfz").origin
    _check_voxels(m, voxels, 0.02, 0.5, tol=0.004 * (1 + 1e-4))
    # weights kept when asked, as uint8 counts (spec 6a): the CLI flag, checked against the source's own weights
    out = tmp_path / "pca-w.sdfz"
    r = CliRunner().invoke(app, ["import", str(src), str(out), "--codec", "pca", "--code-size", "32", "--keep-weights"])
    assert r.exit_code == 0, r.output
    kept = sdfcodec.open_map(out)
    coords = np.argwhere(kept.block_states() == 2)
    w = kept.read_weights(coords)
    assert kept.has_weights and w.max() <= 255 and (w > 0).sum() == len(voxels)


def _bad(tmp_path, data: bytes) -> str:
    p = tmp_path / "bad.voxblox"
    p.write_bytes(data)
    with pytest.raises(FormatError) as e:
        sdfcodec.import_map(p, tmp_path / "out.sdfz")
    assert not (tmp_path / "out.sdfz").exists()
    return str(e.value)


def test_voxblox_bad_inputs_refused_with_one_line(tmp_path):
    vs, vps = 0.05, 8
    d = np.zeros((vps,) * 3, np.float32)
    w = np.ones_like(d)
    good = layer_bytes(vs, vps, [block_message((0, 0, 0), vps, vs, d, w), block_message((1, 0, 0), vps, vs, d, w)])
    assert "truncated stream" in _bad(tmp_path, good[:-100])
    assert "voxel count mismatch" in _bad(tmp_path, layer_bytes(vs, vps, [
        block_message((0, 0, 0), vps, vs, d, w, n_words=3 * vps ** 3 - 3)]))
    for kind in ("esdf", "occupancy", "intensity"):
        msg = _bad(tmp_path, layer_bytes(vs, vps, [block_message((0, 0, 0), vps, vs, d, w)], layer_type=kind))
        assert f"its layers: {kind}" in msg and "no TSDF layer" in msg
    assert "absurd" in _bad(tmp_path, layer_bytes(vs, 100000, []) + b"\x00")
    # a message count far beyond what the file can hold is refused before anything is read or allocated
    assert "claims 4000000000 messages" in _bad(tmp_path, b"\x80\xd0\xac\xf3\x0e" + good[1:])
    assert "not on its layer's block lattice" in _bad(tmp_path, layer_bytes(vs, vps, [
        block_message((0.5, 0, 0), vps, vs, d, w)]))
    # two blocks 10^5 blocks apart on every axis: a state grid of 10^14 bytes, refused before it is allocated
    assert "block-state grid" in _bad(tmp_path, layer_bytes(vs, vps, [
        block_message((0, 0, 0), vps, vs, d, w), block_message((10 ** 5,) * 3, vps, vs, d, w)]))
    # the CLI: one line on stderr, exit status 1, no traceback
    p = tmp_path / "cut.voxblox"
    p.write_bytes(good[:-100])
    r = CliRunner().invoke(app, ["import", str(p), str(tmp_path / "o.sdfz")])  # in process: the same code
    assert r.exit_code == 1 and isinstance(r.exception, SystemExit), r.exception
    assert r.stderr.strip().count("\n") == 0 and "truncated stream" in r.stderr


def _fused_grid(o3d, res: int, vs: float):
    """A small VoxelBlockGrid fused by Open3D itself from two depth images of a tilted plane and a box."""
    vbg = o3d.t.geometry.VoxelBlockGrid(("tsdf", "weight"), (o3d.core.float32, o3d.core.float32), ((1,), (1,)),
                                        vs, res, 20000)
    h, w = 60, 80
    u, v = np.meshgrid(np.arange(w), np.arange(h))
    K = o3d.core.Tensor(np.array([[60.0, 0, w / 2], [0, 60.0, h / 2], [0, 0, 1]]))
    for k, shift in enumerate((0.0, 0.05)):
        depth = 0.8 + 0.004 * u + 0.002 * v + shift
        depth[20:35, 30:50] -= 0.15  # a box in front of the plane
        img = o3d.t.geometry.Image(o3d.core.Tensor((depth * 1000).astype(np.uint16)))
        ext = np.eye(4)
        ext[0, 3] = -0.3 * k
        ext = o3d.core.Tensor(ext)
        coords = vbg.compute_unique_block_coordinates(img, K, ext, 1000.0, 3.0)
        vbg.integrate(coords, img, K, ext, 1000.0, 3.0)
    return vbg


@pytest.mark.parametrize("res", [8, 16])
def test_open3d_grid_imports_losslessly(tmp_path, res):
    o3d = pytest.importorskip("open3d")
    vs = 0.02
    vbg = _fused_grid(o3d, res, vs)
    vbg.save(str(tmp_path / "grid.npz"))
    sdfcodec.import_map(tmp_path / "grid.npz", tmp_path / "g.sdfz")  # format from the content
    xyz, flat = vbg.voxel_coordinates_and_flattened_indices()
    xyz, flat = xyz.numpy().astype(np.float64), flat.numpy().reshape(-1)
    tsdf = vbg.attribute("tsdf").reshape((-1,)).numpy()[flat]
    weight = vbg.attribute("weight").reshape((-1,)).numpy()[flat]
    seen = weight > 0
    assert seen.sum() > 1000
    m = sdfcodec.open_map(tmp_path / "g.sdfz")
    vol = m.decode_region()
    ijk_f = (xyz[seen] - np.asarray(m.origin)) / m.voxel_size
    ijk = np.round(ijk_f).astype(np.int64)
    assert np.abs(ijk_f - ijk).max() < 1e-3  # Open3D's coordinates are float32
    metres = (tsdf[seen].astype(np.float64) * 8 * np.float32(vs)).astype(np.float32)  # Open3D's default truncation
    assert np.abs(vol[tuple(ijk.T)] - metres).max() <= _tolerance(m)
    coords = np.argwhere(m.block_states() == 2)
    assert int(m.read_observed(coords).sum()) == int(seen.sum())


def test_open3d_export_loads_in_open3d(tmp_path):
    o3d = pytest.importorskip("open3d")
    vs = 0.02
    vbg = _fused_grid(o3d, 8, vs)
    vbg.save(str(tmp_path / "grid.npz"))
    sdfcodec.import_map(tmp_path / "grid.npz", tmp_path / "g.sdfz")
    out = sdfcodec.export_map(tmp_path / "g.sdfz", tmp_path / "back.npz", format="open3d", voxels_per_side=8)
    assert out["shift"] == [0.0, 0.0, 0.0]
    back = o3d.t.geometry.VoxelBlockGrid.load(str(tmp_path / "back.npz"))

    def observed(g):
        xyz, flat = g.voxel_coordinates_and_flattened_indices()
        flat = flat.numpy().reshape(-1)
        t = g.attribute("tsdf").reshape((-1,)).numpy()[flat]
        w = g.attribute("weight").reshape((-1,)).numpy()[flat]
        keys = np.round(xyz.numpy() / vs).astype(np.int64)[w > 0]
        return {tuple(k): (a, b) for k, a, b in zip(keys, t[w > 0], w[w > 0])}

    a, b = observed(vbg), observed(back)
    assert set(a) == set(b)
    t = np.array([[a[k][0], b[k][0]] for k in a])
    w = np.array([[a[k][1], b[k][1]] for k in a])
    assert np.abs(t[:, 0] - t[:, 1]).max() < 1e-6  # Open3D units: 1e-6 of its truncation
    assert np.allclose(w[:, 1], w[:, 0], rtol=2.0 ** -11)


def test_open3d_grid_without_tsdf_refused(tmp_path):
    o3d = pytest.importorskip("open3d")
    vbg = o3d.t.geometry.VoxelBlockGrid(("weight", "color"), (o3d.core.float32, o3d.core.float32), ((1,), (3,)),
                                        0.05, 8, 10)
    vbg.hashmap().activate(o3d.core.Tensor(np.zeros((1, 3), np.int32)))
    vbg.save(str(tmp_path / "c.npz"))
    with pytest.raises(FormatError, match="no tsdf attribute"):
        sdfcodec.import_map(tmp_path / "c.npz", tmp_path / "o.sdfz", format="open3d")


_RSS = """
import json, resource, sys
import sdfcodec
s = sdfcodec.import_map(sys.argv[1], sys.argv[2], batch_blocks=128)
print(json.dumps({"rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, "coded": s["blocks"]["coded"]}))
"""


def _import_rss(tmp_path, n: int) -> dict:
    src = tmp_path / f"s{n}.voxblox"
    synthetic_layer(str(src), n)
    r = subprocess.run([sys.executable, "-c", _RSS, str(src), str(tmp_path / f"s{n}.sdfz")], capture_output=True,
                       text=True, cwd=ROOT, check=True)
    out = json.loads(r.stdout.strip().splitlines()[-1])
    out["bytes"] = src.stat().st_size
    return out


def test_import_memory_is_bounded_by_the_working_set(tmp_path):
    """Five times the blocks (8^3 voxels, observed in part) take no more memory: peak RSS is the process's
    base plus one group of map blocks, not the source (10,000 blocks: 70 MB of file, 40 MB of voxels)."""
    small, big = _import_rss(tmp_path, 2000), _import_rss(tmp_path, 10000)
    assert big["coded"] > 4 * small["coded"]
    assert big["bytes"] > 60e6
    assert big["rss_mib"] - small["rss_mib"] < 25, (small, big)


def test_trajectory_of_7scenes_poses(shared_data, tmp_path):
    from sdfcodec.data.sequences import open_sequence
    from sdfcodec.core.trajectory import read_tum

    seq_dir = shared_data / "7scenes-redkitchen"
    r = CliRunner().invoke(app, ["trajectory", str(seq_dir), "-o", str(tmp_path / "gt.txt")])
    assert r.exit_code == 0, r.output
    gt = read_tum(tmp_path / "gt.txt")
    assert len(gt) == 500
    pose = np.loadtxt(seq_dir / "frame-000123.pose.txt")
    # the pose file's rotation through a TUM quaternion: exactly orthonormal (the file's text is not, to 1e-4)
    assert np.allclose(gt.poses[123], pose, atol=1e-3) and np.array_equal(gt.poses[123][:3, 3], pose[:3, 3])
    assert np.isclose(gt.timestamps[123], 123 / 30)
    seq = open_sequence(seq_dir)
    assert np.allclose(gt.timestamps, seq.trajectory.timestamps) and np.allclose(gt.poses, seq.trajectory.poses, atol=1e-3)


def test_mesh_region(shared_data, tmp_path):
    sdfcodec.import_map(shared_data / REAL, tmp_path / "real.sdfz")
    runs = {}
    for name, region in (("all", None), ("part", "0:8,0:16,0:32")):
        # in process (CliRunner): the same command's code without two fresh interpreters importing torch
        args = ["mesh", str(tmp_path / "real.sdfz"), str(tmp_path / f"{name}.ply"), "--json"]
        r = CliRunner().invoke(app, args + (["--region", region] if region else []))
        assert r.exit_code == 0, r.output
        runs[name] = json.loads(r.stdout[r.stdout.index("{"):])
    assert 0 < runs["part"]["triangles"] < runs["all"]["triangles"]


@pytest.mark.bench
def test_million_block_import(tmp_path):
    """The issue's figure: a synthetic voxblox layer of SDFCODEC_IMPORT_BLOCKS blocks (default 10^6, 8^3 voxels,
    about 8.5 GB) imported in a fresh process: its peak RSS, wall time and the machine's load, printed."""
    import os
    import time

    n = int(os.environ.get("SDFCODEC_IMPORT_BLOCKS", 10 ** 6))
    src = tmp_path / "big.voxblox"
    synthetic_layer(str(src), n)
    load0 = os.getloadavg()
    t0 = time.perf_counter()
    r = subprocess.run([sys.executable, "-c", _RSS.replace("batch_blocks=128", "batch_blocks=1024"), str(src),
                        str(tmp_path / "big.sdfz")], capture_output=True, text=True, cwd=ROOT, check=True)
    out = json.loads(r.stdout.strip().splitlines()[-1])
    print(json.dumps({"blocks": n, "file_bytes": src.stat().st_size, "seconds": time.perf_counter() - t0,
                      "load_before": load0, "load_after": os.getloadavg(), **out}))
    assert out["rss_mib"] < 2048


def test_view_takes_a_7scenes_folder_as_ground_truth(shared_data, tmp_path):
    pytest.importorskip("rerun")
    from sdfcodec.core.trajectory import write_tum
    from sdfcodec.data.sequences import open_sequence

    seq_dir = shared_data / "7scenes-redkitchen"
    sdfcodec.import_map(shared_data / REAL, tmp_path / "real.sdfz")
    # the folder's poses in process: `sdfcodec trajectory` writing them is test_trajectory_of_7scenes_poses's
    gt = open_sequence(seq_dir).trajectory
    est = gt.subset(range(100)).poses.copy()
    est[:, :3, 3] += [0.03, 0.0, 0.04]  # 5 cm off: the ATE against the folder's poses must say so
    write_tum(tmp_path / "est.txt", type(gt).from_poses(est, gt.timestamps[:100]))
    # in process (typer's runner): what is checked is the command's reading of the folder, not its start-up
    r = CliRunner().invoke(app, ["view", str(tmp_path / "real.sdfz"), "--trajectory", str(tmp_path / "est.txt"),
                                 "--groundtruth", str(seq_dir), "-o", str(tmp_path / "v.rrd"), "--json"])
    assert r.exit_code == 0, r.output
    t = json.loads(r.stdout)["trajectory"]
    assert t["groundtruth_poses"] == 500 and t["associated"] == 100
    assert abs(t["ate_rmse"] - 0.05) < 1e-6


def test_open3d_archive_needing_pickle_refused(tmp_path):
    # a look-alike archive whose keys are Python objects: reading them would unpickle, which sdfcodec never does
    p = tmp_path / "evil.npz"
    np.savez(p, key=np.array([object()], dtype=object), block_resolution=np.array([8]),
             voxel_size=np.array([0.05], np.float32), attr_name_tsdf=np.array([0]), attr_name_weight=np.array([1]),
             value_000=np.zeros((1, 8, 8, 8, 1), np.float32), value_001=np.zeros((1, 8, 8, 8, 1), np.float32))
    with pytest.raises(FormatError, match="never unpickles"):
        sdfcodec.import_map(p, tmp_path / "o.sdfz")
    assert not (tmp_path / "o.sdfz").exists()


def test_voxblox_file_of_several_layers_imports_its_tsdf_layer(tmp_path):
    # voxblox's SaveLayer may append layers to one file: an ESDF layer first (2 words a voxel), then the TSDF
    rng = np.random.default_rng(7)
    msgs, voxels = _random_layer(rng, 8, 0.05, 6)
    esdf = [block_message((9, 9, 9), 8, 0.05, np.zeros((8,) * 3), np.ones((8,) * 3), n_words=2 * 8 ** 3)]
    src = tmp_path / "two.voxblox"
    src.write_bytes(layer_bytes(0.05, 8, esdf, layer_type="esdf") + layer_bytes(0.05, 8, msgs))
    sdfcodec.import_map(src, tmp_path / "m.sdfz")
    _check_voxels(sdfcodec.open_map(tmp_path / "m.sdfz"), voxels, 0.05, 0.5)
