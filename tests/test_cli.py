"""The command line: encode -> info -> decode round trip, JSON output, one-line errors."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

import sdfcodec
from sdfcodec.cli import app
from sdfcodec.core.sdf import Box, Plane, Scene, Sphere, sample_volume

runner = CliRunner()
VS = 0.02


@pytest.fixture(scope="module")
def volume_file(tmp_path_factory) -> tuple[Path, np.ndarray]:
    scene = Scene([Plane((0, 0, 1), 0.1), Plane((0, 1, 0), 0.07), Sphere((0.7, 0.8, 0.5), 0.25),
                   Box((1.5, 0.5, 0.4), (0.2, 0.15, 0.25))])
    vol = sample_volume(scene, (120, 100, 60), VS)
    path = tmp_path_factory.mktemp("cli") / "scene.npy"
    np.save(path, vol)
    return path, vol


def run(*args: str):
    return runner.invoke(app, [str(a) for a in args])


def test_encode_info_decode_round_trip(volume_file, tmp_path):
    src, vol = volume_file
    out_map = tmp_path / "scene.sdfz"
    r = run("encode", src, out_map, "--voxel-size", VS, "--code-size", 64, "--json")
    assert r.exit_code == 0, r.output
    summary = json.loads(r.stdout[r.stdout.index("{"):])
    assert summary["codec"]["code_size"] == 64 and summary["blocks"]["coded"] > 64

    r = run("info", out_map, "--json")
    assert r.exit_code == 0, r.output
    info = json.loads(r.stdout)
    assert info["shape_voxels"] == [120, 100, 60] and info["levels"] == [32, 64]
    assert info["ratio_dense_to_disk"] > 1
    r = run("info", out_map)
    assert r.exit_code == 0 and "coded" in r.stdout

    dense = tmp_path / "dense.npy"
    r = run("decode", out_map, dense)
    assert r.exit_code == 0, r.output
    dec = np.load(dense)
    assert dec.shape == vol.shape
    assert np.array_equal(dec, sdfcodec.open_map(out_map).decode_region())
    assert np.sqrt(np.mean((dec - vol) ** 2)) < 0.01

    part = tmp_path / "part.npy"
    r = run("decode", out_map, part, "--level", 32, "--region", "0:40,10:20,5:6", "--json")
    assert r.exit_code == 0, r.output
    assert np.load(part).shape == (40, 10, 1)


def test_transcode_map_to_raw_float16(volume_file, tmp_path):
    src, vol = volume_file
    a, b = tmp_path / "a.sdfz", tmp_path / "b.sdfz"
    assert run("encode", src, a, "--voxel-size", VS, "--codec", "raw").exit_code == 0
    r = run("encode", a, b, "--codec", "raw", "--code-dtype", "float16")
    assert r.exit_code == 0, r.output
    mb = sdfcodec.open_map(b)
    assert mb.header.codes.dtype == "float16" and mb.shape_voxels == vol.shape
    assert np.abs(mb.decode_region() - vol).max() < 1e-4  # float16 steps of ~0.14 mm near d_max
    # int8 raw codes: each block's 4096 values in 255 steps of its own range (at most 0.14 m / 254 apart)
    c = tmp_path / "c.sdfz"
    r = run("encode", a, c, "--codec", "raw", "--code-dtype", "int8")
    assert r.exit_code == 0, r.output
    mc = sdfcodec.open_map(c)
    assert mc.header.codes.dtype == "int8" and run("info", c).output.count("int8") >= 1
    err = np.abs(mc.decode_region() - vol).max()
    assert 0 < err <= (0.1 + 0.04) / 254 / 2 * 1.001


def test_model_option(volume_file, tmp_path):
    src, _ = volume_file
    from sdfcodec.testing import analytic_blocks

    model = sdfcodec.save_model(sdfcodec.get_codec("pca", code_size=32).fit(analytic_blocks(300)),
                                tmp_path / "pca32.npz")
    r = run("encode", src, tmp_path / "m.sdfz", "--voxel-size", VS, "--model", model)
    assert r.exit_code == 0, r.output
    m = sdfcodec.open_map(tmp_path / "m.sdfz")
    assert m.code_size == 32
    assert np.array_equal(m.codec.components_, sdfcodec.load_model(model).components_)
    r = run("encode", src, tmp_path / "n.sdfz", "--voxel-size", VS, "--model", model, "--code-size", 64)
    assert r.exit_code == 1 and "contradicts the model" in r.stderr


def one_line_error(r, *needles: str) -> None:
    assert r.exit_code == 1, r.output
    lines = [ln for ln in r.stderr.strip().splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error:"), r.stderr
    for n in needles:
        assert n in lines[0], lines[0]


def test_errors_are_one_line(volume_file, tmp_path):
    src, vol = volume_file
    out_map = tmp_path / "x.sdfz"
    one_line_error(run("encode", src, out_map), "--voxel-size")
    one_line_error(run("encode", tmp_path / "missing.npy", out_map, "--voxel-size", VS), "missing.npy")
    one_line_error(run("encode", src, out_map, "--voxel-size", VS, "--codec", "zzz"), "'zzz' is not installed")
    assert run("encode", src, out_map, "--voxel-size", VS, "--codec", "raw").exit_code == 0
    one_line_error(run("encode", src, out_map, "--voxel-size", VS, "--codec", "raw"), "exists", "--overwrite")
    one_line_error(run("decode", out_map, tmp_path / "d.npy", "--level", 3), "not prefix-ordered")
    one_line_error(run("decode", out_map, tmp_path / "d.npy", "--region", "0:10,0:10"), "--region")
    one_line_error(run("decode", out_map, tmp_path / "d.npy", "--region", "0:500,0:10,0:10"), "outside the map")
    one_line_error(run("info", tmp_path / "nowhere.sdfz"), "no map at")
    nan = vol.copy()
    nan[3, 3, 3] = np.nan
    np.save(tmp_path / "nan.npy", nan)
    one_line_error(run("encode", tmp_path / "nan.npy", tmp_path / "y.sdfz", "--voxel-size", VS), "NaN")
    assert not (tmp_path / "y.sdfz").exists()


def test_codecs_listing():
    r = run("codecs", "--json")
    assert r.exit_code == 0
    rows = {row["id"]: row for row in json.loads(r.stdout)}
    assert rows["pca"]["prefix_ordered"] is True and rows["pca"]["code_sizes"] == [32, 64, 128]
    assert rows["raw"]["requires_fit"] is False and rows["pca"]["package"] == "sdfcodec"


def test_bench_json_records(bench_run):
    # `sdfcodec bench --quick --sizes 32 --batches 1,64 --read 300 --repeats 2 --json` (conftest.BENCH_ARGS)
    assert bench_run["exit_code"] == 0, bench_run["output"]
    recs = json.loads(bench_run["stdout"])
    (start,) = [x for x in recs if x["operation"] == "info-startup"]  # `sdfcodec info` in fresh processes
    assert start["seconds_best"] > start["baseline_seconds_best"] > 0  # a command costs more than no command
    assert start["meets_target"] == (start["seconds_median"] <= start["target_seconds"] == 0.5)
    assert len(start["seconds_rounds"]) == 2
    recs = [x for x in recs if x is not start]
    assert {(x["operation"], x["batch"]) for x in recs} == {
        ("encode", 1), ("decode", 1), ("encode", 64), ("decode", 64), ("decode-on-read", 300),
        ("decode-on-read-http", 300), ("search", 8192), ("encode-weighted", 1), ("encode-weighted", 64),
        ("encode-masked", 1), ("encode-masked", 64), ("decode-on-read-into", 300), ("decode-on-read-fresh", 300), ("decode-region", 300),
        ("decode-region-into", 300), ("decode-into", 300)}
    into = [x for x in recs if x["operation"] in ("decode-on-read-into", "decode-on-read-fresh", "decode-region",
                                                  "decode-region-into", "decode-into")]
    for x in into:  # decoding into place: interleaved with the preallocated product, best and median rounds
        assert x["ratio_to_baseline"] == pytest.approx(x["blocks_per_s"] / x["baseline_blocks_per_s"])
        assert x["ratio_of_bests"] == pytest.approx(x["blocks_per_s_best"] / x["baseline_blocks_per_s_best"])
        assert x["blocks_per_s_best"] >= x["blocks_per_s"] > 0 and x["repeats"] == 2 and x["map_blocks"] == 300
    for x in (x for x in recs if x["operation"] in ("encode-weighted", "encode-masked")):  # beside the plain encode
        # timed again in the same rounds (encode_blocks_per_s), the ratio paired round by round: a weighted fit of
        # 32 numbers (Gram matrices of 528 columns) costs more than the plain projection
        assert x["encode_blocks_per_s"] > 0 and 0 < x["ratio_to_encode"] < 1
        assert x["roofline_shapes"] == [[4096, 32], [4096, 32 * 33 // 2], [4096, 32]]
    assert all(x["blocks_per_s"] > 0 and x["baseline_blocks_per_s"] > 0 for x in recs)
    for x in recs:  # the paper's 405-645 us per block against ours
        assert x["speedup_vs_paper"] == pytest.approx([405 / x["us_per_block"], 645 / x["us_per_block"]])
    for op in ("decode-on-read", "decode-on-read-http"):  # the memory-copy roofline: 16 KiB per decoded block
        x = next(x for x in recs if x["operation"] == op)
        assert x["memcpy_blocks_per_s"] == pytest.approx(x["memcpy_bytes_per_s"] / 16384)
        assert x["ratio_to_memcpy"] > 0  # paired round by round with the copy (sdfcodec.bench.harness.paired)
    # --read 0 --no-search works (two rounds, as above: what is checked is the path, not the figures), and its table
    # says each speed-up against the paper's 405 us/block to two figures (a slow encode read "0x" before)
    r = run("bench", "--quick", "--sizes", "32", "--batches", "1", "--read", "0", "--no-search", "--repeats", "2")
    assert r.exit_code == 0, r.output
    rows = [line.split("\t") for line in r.stdout.splitlines() if line.startswith("32\t")]
    assert rows and any(line.startswith("code\t") and line.endswith("\tvs paper's 405 us/block")
                        for line in r.stdout.splitlines()), r.stdout
    for row in rows:
        want = 405 / float(row[-2])
        assert row[-1] != "0x" and float(row[-1].rstrip("x").replace(",", "")) == pytest.approx(want, rel=0.06), row
    read = next(x for x in recs if x["operation"] == "decode-on-read")
    # 300 pca-32 codes of float32 were really stored and read: at least their compressed bytes (4 B x 32 each,
    # Blosc-compressible, so bounded below loosely) and at most their raw size plus chunk overhead
    assert 300 * 32 * 4 / 20 < read["code_bytes_on_disk"] < 300 * 32 * 4 * 2 + 4096
    assert read["in_memory_decode_blocks_per_s"] > 0
    assert read["ratio_to_in_memory_decode"] > 0
    assert run("bench", "--quick", "--read", "-1").exit_code != 0


def test_encode_uses_shipped_model_by_default(volume_file, tmp_path):
    from sdfcodec.map import state_digest

    src, _ = volume_file
    r = run("encode", src, tmp_path / "d.sdfz", "--voxel-size", VS, "--code-size", 32)
    assert r.exit_code == 0, r.output
    m = sdfcodec.open_map(tmp_path / "d.sdfz")
    assert m.header.codec.state_sha256 == state_digest(sdfcodec.pretrained_codec("pca", 32).state_dict())
    r = run("encode", src, tmp_path / "f.sdfz", "--voxel-size", VS, "--code-size", 32, "--fit")
    assert r.exit_code == 0 and "fitting" in r.stderr
    assert sdfcodec.open_map(tmp_path / "f.sdfz").header.codec.state_sha256 != m.header.codec.state_sha256


def test_dataset_and_train(volume_file, tmp_path):
    src, _ = volume_file
    ds = tmp_path / "ds.zarr"
    r = run("dataset", ds, "--synthetic", 1500, "--volume", src, "--json")
    assert r.exit_code == 0, r.output
    meta = json.loads(r.stdout)
    assert meta["sources"]["synthetic"] == 1500 and sum(meta["splits"].values()) % 500 == 0
    nb = sum(meta["splits"].values()) // 500  # whole batches, split 300 : 50 : 50 (at least one each)
    assert meta["splits"]["validation"] == meta["splits"]["test"] == 500 * max(1, round(nb / 8))
    reports = []
    for extra in ([], ["--max-memory-gb", "0.001"]):  # in memory (sklearn), then streamed covariance
        r = run("train", ds, "--code-size", 16, "-o", tmp_path / "m.npz", "--overwrite", "--json", *extra)
        assert r.exit_code == 0, r.output
        reports.append(json.loads(r.stdout))
    assert reports[0]["validation"]["mse_voxel"] == pytest.approx(reports[1]["validation"]["mse_voxel"], rel=1e-4)
    m = sdfcodec.load_model(tmp_path / "m.npz")
    assert m.code_size == 16
    one_line_error(run("train", ds, "-o", tmp_path / "m.npz"), "exists")


def test_fuse_and_mesh_a_rendered_sequence(tmp_path):
    """`sdfcodec fuse` writes a lossless raw map whose field matches the fusion, `mesh` extracts its surface."""
    from sdfcodec.data.render import render_sequence
    from sdfcodec.data.sequences import Intrinsics
    from sdfcodec.fusion.tsdf import fuse

    seq = render_sequence(tmp_path / "seq", "fast-clean", frames=12,
                          intrinsics=Intrinsics(fx=131.25, fy=131.25, cx=79.5, cy=59.5, width=160, height=120))
    out_map = tmp_path / "room.sdfz"
    r = run("fuse", seq, out_map, "--voxel-size", 0.04, "--weights", "--json")
    assert r.exit_code == 0, r.output
    summary = json.loads(r.stdout)
    assert summary["frames_integrated"] == 12 and summary["allocated_blocks"] > 10
    m = sdfcodec.open_map(out_map)
    ref = fuse(seq, voxel_size=0.04, quiet=True)
    assert m.origin == tuple(ref.origin) and m.has_weights
    coords, blocks = zip(*m.iter_blocks())
    coords, blocks = np.concatenate(coords), np.concatenate(blocks)
    order = {tuple(c): i for i, c in enumerate(ref.coords)}
    idx = [order[tuple(c)] for c in coords]
    assert np.allclose(blocks, ref.tsdf[idx], atol=1e-6)
    assert np.array_equal(m.read_weights(coords), ref.weights[idx])
    r = run("mesh", out_map, tmp_path / "room.ply", "--json")
    assert r.exit_code == 0, r.output
    assert json.loads(r.stdout)["triangles"] > 1000
    one_line_error(run("fuse", tmp_path / "nothing", tmp_path / "x.sdfz"), "nothing")


def test_track_cli_against_a_compressed_map(tmp_path):
    from sdfcodec.data.render import render_sequence
    from sdfcodec.data.sequences import Intrinsics
    from sdfcodec.core.metrics import ate, read_tum

    seq = render_sequence(tmp_path / "seq", "slow-clean", frames=8,
                          intrinsics=Intrinsics(fx=131.25, fy=131.25, cx=79.5, cy=59.5, width=160, height=120))
    assert run("fuse", seq, tmp_path / "raw.sdfz").exit_code == 0
    assert run("encode", tmp_path / "raw.sdfz", tmp_path / "pca.sdfz", "--code-size", 64).exit_code == 0
    r = run("track", tmp_path / "pca.sdfz", seq, "-o", tmp_path / "traj.txt", "--json")
    assert r.exit_code == 0, r.output
    est, gt = read_tum(tmp_path / "traj.txt"), read_tum(seq / "groundtruth.txt")
    assert len(est) == 8
    assert ate(gt, est).mean < 0.05  # started from ground truth, an 8-frame slow pan stays within centimetres


def test_file_system_failures_are_one_line(tmp_path):
    """An output the file system refuses, in a command without a dedicated write path (here: search --out under
    a plain file), is one line on stderr and exit status 1, never a traceback."""
    vol = tmp_path / "v.npy"
    np.save(vol, np.full((32, 32, 32), 0.1, np.float32) - np.linspace(0, 0.14, 32, dtype=np.float32)[None, None, :])
    r = run("encode", str(vol), str(tmp_path / "m.sdfz"), "--codec", "raw", "--voxel-size", "0.02")
    assert r.exit_code == 0, r.output
    (tmp_path / "afile").write_text("not a directory")
    r = run("search", str(tmp_path / "m.sdfz"), "--query", "floor", "--out", str(tmp_path / "afile" / "sub"))
    assert r.exit_code == 1 and "Traceback" not in r.output, r.output
    assert r.output.startswith("error: ") and "afile" in r.output and r.output.count("\n") == 1, r.output
