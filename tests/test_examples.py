"""Every runnable script in examples/ runs, on small inputs, and prints what it claims (checked against
numbers computed here independently where that is cheap)."""

from __future__ import annotations

import importlib.util
import re
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import pytest

import sdfcodec

ROOT = Path(__file__).resolve().parents[1]
EXAMPLES = ROOT / "examples"
KITCHEN = ROOT.parent / "shared" / "data" / "7scenes-redkitchen"


def run_script(script: str, *args: str, timeout: float = 120) -> str:
    """Run an example as a script, in a fresh interpreter, as a user would."""
    p = subprocess.run([sys.executable, str(EXAMPLES / script), *args], capture_output=True, text=True,
                       timeout=timeout, cwd=ROOT)
    assert p.returncode == 0, f"{script} failed:\n{p.stdout}\n{p.stderr}"
    return p.stdout


def run(script: str, *args: str, capsys) -> str:
    """Run an example's ``main(argv)`` in this process (saves an interpreter start per test); its stdout."""
    spec = importlib.util.spec_from_file_location(f"example_{Path(script).stem}", EXAMPLES / script)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    capsys.readouterr()
    module.main(list(args))
    return capsys.readouterr().out


def test_quickstart(tmp_path):
    out = run_script("quickstart.py", "--out", str(tmp_path))
    tsdf = np.load(tmp_path / "room.npy")
    room = sdfcodec.open_map(tmp_path / "room.sdfz")
    assert room.code_size == 64 and room.header.codec.id == "pca"
    coded = room.count_states()["coded"]
    assert f"{coded} coded blocks, codes ({coded}, 64)" in out
    assert "coarse region (64, 64, 32)" in out
    # the reported error is the decoded map against the input, recomputed here
    full = room.decode_region()
    near = np.abs(tsdf) < 0.05
    rmse = 1000 * np.sqrt(np.mean((full[near] - tsdf[near]) ** 2))
    assert f"RMSE near surfaces: {rmse:.1f} mm" in out
    assert 1.0 < rmse < 40.0  # lossy but a room, not noise (the field spans 140 mm)


def test_fuse_and_compress(tmp_path, capsys):
    if not KITCHEN.is_dir():
        pytest.skip(f"real data not available at {KITCHEN} (the project's shared data folder)")
    out = run("fuse_and_compress.py", str(KITCHEN), "--frames", "6", "--stride", "10", "--out", str(tmp_path),
              capsys=capsys)
    assert "7scenes sequence 7scenes-redkitchen: 6 frames fused" in out
    raw, pca = sdfcodec.open_map(tmp_path / "raw.sdfz"), sdfcodec.open_map(tmp_path / "pca-64.sdfz")
    assert raw.count_states()["coded"] == pca.count_states()["coded"] > 50
    assert raw.header.codec.id == "raw" and pca.code_size == 64
    # the compressed file is smaller than the lossless one only by its codes: check the ratio printed
    info = pca.info()
    assert f"({info['ratio_dense_to_codes']:.0f}:1 against" in out
    m = re.search(r"pca-64 near surfaces: RMSE ([\d.]+) mm", out)
    assert m and 1.0 < float(m.group(1)) < 80.0


def test_search_floors(tmp_path, capsys, monkeypatch):
    pic = tmp_path / "floors.png"
    scratch = tmp_path / "tmp"
    scratch.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(scratch))  # where the example's synthetic room is written
    out = run("search_floors.py", "--size", "2", "--picture", str(pic), capsys=capsys)
    assert not list(scratch.iterdir()), "the example left its synthetic room's map behind"
    m = re.search(r"selected (\d+) blocks; decoded (\d+) of (\d+)", out)
    assert m, out
    selected, decoded, coded = (int(g) for g in m.groups())
    assert 0 < selected == decoded < coded  # only the selection is decoded
    pr = re.search(r"precision ([\d.]+), recall ([\d.]+)", out)
    assert pr and float(pr.group(1)) >= 0.5 and float(pr.group(2)) >= 0.3, out
    assert pic.is_file() and pic.stat().st_size > 10_000


def test_search_floors_on_a_given_map_with_top(tmp_path, capsys):
    from sdfcodec.core.sdf import Plane, sample_volume

    # a map of a single horizontal plane at z = 0.5 m: every coded block is floor, so top-k selects k of them
    vol = sample_volume(Plane((0, 0, 1), 0.5), (64, 64, 64), 0.02)
    path = tmp_path / "plane.sdfz"
    with sdfcodec.create_map(path, codec=sdfcodec.pretrained_codec("pca", 32), voxel_size=0.02) as mp:
        mp.write_volume(vol)
    coded = sdfcodec.open_map(path).count_states()["coded"]
    out = run("search_floors.py", str(path), "--top", "5", capsys=capsys)
    assert f"{coded} coded blocks scored at level 32" in out
    assert f"selected 5 blocks; decoded 5 of {coded}" in out


def test_track_compressed(tmp_path, capsys):
    out = run("track_compressed.py", "--frames", "6", "--out", str(tmp_path), capsys=capsys)
    rows = dict(re.findall(r"(original|pca-64): 6 frames, ATE RMSE ([\d.]+) mm", out))
    assert set(rows) == {"original", "pca-64"}, out
    for v in rows.values():
        assert float(v) < 100.0  # tracked, not lost (a lost camera is metres off)
    assert (tmp_path / "sequence" / "groundtruth.txt").is_file()
    assert sdfcodec.open_map(tmp_path / "pca-64.sdfz").code_size == 64


def test_read_over_http(capsys):
    out = run("read_over_http.py", "--region", "0:64,0:64,0:64", capsys=capsys)
    assert "-> (64, 64, 64), identical to the local read: True" in out
    m = re.search(r"in (\d+) requests: codes ([\d.]+) KiB of ([\d.]+) KiB", out)
    assert m, out
    requests, fetched, codes = int(m.group(1)), float(m.group(2)), float(m.group(3))
    assert requests >= 3
    # a 64^3-voxel corner needs one chunk of blocks (8^3 blocks = 128^3 voxels) of a map 200 voxels long
    assert 0 < fetched < 0.6 * codes


def test_cited_documents_exist():
    """Code and docs cite documents of this repository only: every spec/... or docs/... path they name exists,
    and nothing cites a design page that lives outside it (DESIGN.md)."""
    cite = re.compile(r"(?<![\w/.])((?:spec|docs)/[\w./-]+\.(?:md|json|py|png))")
    files = [ROOT / "README.md", *[p for d in ("sdfcodec", "plugins", "docs", "spec", "examples")
                                   for p in (ROOT / d).rglob("*") if p.suffix in (".py", ".md")]]
    missing, outside = [], []
    for f in files:
        text = f.read_text(errors="replace")
        for n, line in enumerate(text.splitlines(), 1):
            where = f"{f.relative_to(ROOT)}:{n}"
            missing += [f"{where}: {c}" for c in cite.findall(line) if not (ROOT / c.rstrip(".")).exists()]
            if "DESIGN.md" in line:
                outside.append(where)
    assert not missing, "cited documents that are not in the repository:\n" + "\n".join(missing)
    assert not outside, "DESIGN.md is not in the repository; cite spec/ or docs/ instead:\n" + "\n".join(outside)


def test_side_information(tmp_path, capsys):
    """The per-array table adds up to the map's files (counted here), and the mask study's context-model bounds
    never rise as the context grows (nested contexts: conditioning never raises an empirical entropy)."""
    from _fused_maps import fused_like, write_volume_map
    from sdfcodec.core.sdf import Sphere, sample_volume

    vol, observed = fused_like(sample_volume(Sphere((0.32, 0.32, 0.32), 0.2), (48, 48, 48), 0.02,
                                             truncation=(-0.04, 0.1)))
    path = tmp_path / "m.sdfz"
    write_volume_map(path, vol, observed, sdfcodec.pretrained_codec("pca", 32))
    out = run("side_information.py", str(path), capsys=capsys)
    coded = sdfcodec.open_map(path).count_states()["coded"]
    files = [f for f in path.rglob("*") if f.is_file() and f.relative_to(path).parts[0] != "codec"]
    total = sum(f.stat().st_size for f in files) / coded
    assert f"| **total (no codec/)** | **{total:.1f}** |" in out and f"| coded blocks | {coded} |" in out
    out = run("side_information.py", "--mask-study", str(path), capsys=capsys)
    rows = dict(re.findall(r"^\| ([^|]+?) \| ([\d.]+) \|", out, re.M))
    assert float(rows["plain"]) > 0
    bounds = [float(rows[f"entropy, {k} causal neighbours"]) for k in (3, 6, 9)]
    assert bounds[0] >= bounds[1] >= bounds[2] >= 0
