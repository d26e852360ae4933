"""No silent choice (issue 44, item 3): a bound the user did not give is printed in metres, a level that drops a
map's guarantee warns, sizes that are not shipped are refused without --fit, info speaks the user's units, fuse
counts frames."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

import sdfcodec
from sdfcodec.cli import app
from sdfcodec.cli.common import human_bytes
from sdfcodec.core.sdf import Plane, Scene, Sphere, sample_volume

VS = 0.02


def run(*args, env: dict | None = None):
    return CliRunner().invoke(app, [str(a) for a in args], env=env)


@pytest.fixture(scope="module")
def volume(tmp_path_factory) -> Path:
    vol = sample_volume(Scene([Plane((0, 0, 1), 0.1), Sphere((0.5, 0.5, 0.4), 0.2)]), (64, 64, 48), VS)
    path = tmp_path_factory.mktemp("silent") / "scene.npy"
    np.save(path, vol)
    return path


def test_sz3_without_max_error_says_its_bound_and_info_shows_metres(volume, tmp_path):
    pytest.importorskip("pysz")
    r = run("encode", volume, tmp_path / "a.sdfz", "--voxel-size", VS, "--codec", "sz3")
    assert r.exit_code == 0, r.output
    # sz3's default 0.05 of the truncation range (0.14 m) is 7 mm: said, in metres' units
    assert "without --max-error: error bound 7 mm" in r.stderr, r.stderr
    r = run("encode", volume, tmp_path / "b.sdfz", "--voxel-size", VS, "--codec", "sz3", "--max-error", "0.01")
    assert r.exit_code == 0 and "without --max-error" not in r.stderr
    info = run("info", tmp_path / "b.sdfz")
    assert info.exit_code == 0, info.output
    row = next(line for line in info.stdout.splitlines() if line.startswith("error bound"))
    assert row.split("\t")[1].startswith("10 mm on every observed voxel"), row  # 0.01 m asked, not "0.0714"
    # and the bound holds: the decoded field is within 10 mm of the input where the input is inside the band
    dec = sdfcodec.open_map(tmp_path / "b.sdfz").decode_region()
    src = np.clip(np.load(volume), -0.04, 0.1)
    assert np.abs(dec - src).max() <= 0.01 + 1e-6


def test_info_of_a_lossless_map_says_it_has_no_codec_state(volume, tmp_path):
    assert run("encode", volume, tmp_path / "raw.sdfz", "--voxel-size", VS, "--codec", "raw").exit_code == 0
    r = run("info", tmp_path / "raw.sdfz")
    assert r.exit_code == 0, r.output
    assert "None" not in r.stdout
    assert "codec state\tnone (the codec learns nothing)" in r.stdout


def test_info_over_http_says_why_it_has_no_size(volume, tmp_path):
    from sdfcodec.bench.serve import FileServer

    assert run("encode", volume, tmp_path / "m.sdfz", "--voxel-size", VS).exit_code == 0
    with FileServer(tmp_path) as server:
        r = run("info", server.url("m.sdfz"))
    assert r.exit_code == 0, r.output
    assert "on disk\tnot known for a remote map" in r.stdout, r.stdout


def test_decode_at_a_level_below_a_max_error_map_warns(volume, tmp_path):
    m = tmp_path / "bound.sdfz"
    r = run("encode", volume, m, "--voxel-size", VS, "--code-size", 64, "--max-error", "0.01")
    assert r.exit_code == 0, r.output
    full = run("decode", m, tmp_path / "full.npy")
    assert full.exit_code == 0 and "warning" not in full.stderr
    low = run("decode", m, tmp_path / "low.npy", "--level", 8)
    assert low.exit_code == 0, low.output
    assert ("--level 8 decodes without the residual stage, so the 10 mm error bound of the full level (64) no "
            "longer holds; leave --level out to keep it") in " ".join(low.stderr.split()), low.stderr
    # what the warning says is so: the full level holds the bound, level 8 does not
    src = np.clip(np.load(volume), -0.04, 0.1)
    observed = src < 0.1 - 1e-6  # the band around the surfaces
    assert np.abs(np.load(tmp_path / "full.npy") - src)[observed].max() <= 0.01 + 1e-6
    assert np.abs(np.load(tmp_path / "low.npy") - src)[observed].max() > 0.01


def test_a_size_that_is_not_shipped_is_refused_without_fit(volume, tmp_path):
    r = run("encode", volume, tmp_path / "ae48.sdfz", "--voxel-size", VS, "--codec", "ae", "--code-size", 48)
    assert r.exit_code == 1 and r.stdout == ""
    assert "ships no model at code size 48" in r.stderr and "--fit" in r.stderr and r.stderr.count("\n") == 1
    assert not (tmp_path / "ae48.sdfz").exists()


def test_codecs_lists_shipped_sizes_apart_from_fittable_ones():
    r = run("codecs")
    assert r.exit_code == 0, r.output
    rows = {line.split("\t")[0]: line.split("\t") for line in r.stdout.splitlines() if not line.startswith("#")}
    assert rows["ae"][1] == "64 shipped (ae-64); 32, 128 with --fit"
    assert rows["pca"][1] == "32, 64, 128 shipped (pca-128), any prefix 1-128"
    assert rows["parallel"][1] == "64 + 64 shipped (parallel-64-64)"  # not its 129 code elements
    rows = {r["id"]: r for r in json.loads(run("codecs", "--json").stdout)}
    assert rows["ae"]["shipped_models"] == {"ae-64": [64]} and rows["ae"]["code_sizes"] == [32, 64, 128]


def test_fuse_progress_counts_frames(tmp_path):
    from sdfcodec.data.render import render_sequence
    from sdfcodec.data.sequences import Intrinsics

    seq = render_sequence(tmp_path / "seq", "fast-clean", frames=40,
                          intrinsics=Intrinsics(fx=131.25, fy=131.25, cx=79.5, cy=59.5, width=160, height=120))
    r = run("fuse", seq, tmp_path / "room.sdfz", "--voxel-size", 0.04, env={"SDFCODEC_PROGRESS_SECONDS": "0.05"})
    assert r.exit_code == 0, r.output
    lines = [line for line in r.stderr.splitlines() if line.startswith("fusing")]
    assert lines and all(" of 40 frames (" in line for line in lines if "so far" not in line), lines
    assert any(" of 40 frames (" in line for line in lines), lines
    # the summary states the grid it chose (the defaults but for --voxel-size) and what it kept beside the field
    m = sdfcodec.open_map(tmp_path / "room.sdfz")
    assert m.voxel_size == 0.04 and m.truncation == (-0.04, 0.1) and m.has_weights
    assert (f"at 0.04 m voxels, truncation [-0.04, 0.1] m; " in r.stdout
            and f"{human_bytes(m.info()['bytes_on_disk'])} with the fusion weights" in r.stdout), r.stdout


def test_encode_names_the_codec_it_chose(volume, tmp_path):
    """The walk-through's `encode` lines: a byte budget picks pca-128 prefixes and says so (it said only "codes
    quantised with step ..."), the default says pca-64 from the shipped model; info then says the codes are
    variable-rate, and a decode or compare of all a map holds says "full level", not sz3's "level 4096"."""
    r = run("encode", volume, tmp_path / "d.sdfz", "--voxel-size", VS)
    assert r.exit_code == 0 and r.stdout.startswith(f"wrote {tmp_path / 'd.sdfz'} with pca-64 (shipped model, by "
                                                    "reference): "), r.output
    r = run("encode", volume, tmp_path / "v.sdfz", "--voxel-size", VS, "--target-bytes", 128)
    assert r.exit_code == 0, r.output
    m = sdfcodec.open_map(tmp_path / "v.sdfz")
    assert m.code_size == 128 and m.header.codes.variable_rate is not None  # what the line must then say
    assert r.stdout.startswith(f"wrote {tmp_path / 'v.sdfz'} with pca-128 prefixes (shipped model, by reference): ")
    assert "target 128 B (1 pass)" in r.stdout or "target 128 B (2 passes)" in r.stdout, r.stdout
    info = run("info", tmp_path / "v.sdfz")
    row = next(line for line in info.stdout.splitlines() if line.startswith("code\t"))
    assert "variable-rate: each block keeps the prefix its rate buys" in row, row
    assert json.loads(run("info", tmp_path / "v.sdfz", "--json").stdout)["code_storage"] == "variable-rate"
    r = run("decode", tmp_path / "d.sdfz", tmp_path / "d.npy", "--level", 32)
    assert r.exit_code == 0 and "(level 32 of 64, voxel 0.02 m" in r.stdout, r.output
    r = run("decode", tmp_path / "d.sdfz", tmp_path / "f.npy")
    assert r.exit_code == 0 and "(full level, voxel 0.02 m" in r.stdout, r.output


def test_info_shows_no_codec_state_size_when_none_is_stored(volume, tmp_path):
    """A map referencing the shipped model stores no state: `info` showed "on disk ... (codec state 37 B)" (the
    codec group's metadata) beside "by reference", and a second ratio "without codec state" that differed by 0.1."""
    assert run("encode", volume, tmp_path / "p.sdfz", "--voxel-size", VS).exit_code == 0
    r = run("info", tmp_path / "p.sdfz")
    rows = dict(line.split("\t", 1) for line in r.stdout.splitlines() if "\t" in line)
    assert "codec state" not in rows["on disk"] and "ratio dense : disk without codec state" not in rows
    assert rows["codec state"].startswith("not stored: the shipped model pca-128 at code size 64, by reference")
    r = run("encode", volume, tmp_path / "fit.sdfz", "--voxel-size", VS, "--fit", "--code-size", 8)
    assert r.exit_code == 0 and " with pca-8 (fitted on " in r.stdout, r.output
    rows = dict(line.split("\t", 1) for line in run("info", tmp_path / "fit.sdfz").stdout.splitlines() if "\t" in line)
    state = sdfcodec.open_map(tmp_path / "fit.sdfz").info()["codec_state_bytes"]
    assert rows["on disk"].endswith(f"(codec state {human_bytes(state)})"), rows["on disk"]
    assert "ratio dense : disk without codec state" in rows
