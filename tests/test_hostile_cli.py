"""Hostile command lines (issue 40, items 4 and 7): inputs numpy cannot or must not read (object arrays, pickles,
truncated or lying ``.npy`` headers, metadata of the wrong type), values that broke a command's arithmetic or
torch (``--chunk-blocks 0``, ``--device foo``, a CUDA device on a CPU-only torch, ``--frames -1``,
``--cache-mb nan``, ``--query like:1,2``, a voxel size of 5e-324 under ``--region --units m``), and outputs that
would lose data (a file replaced without ``--overwrite``, a file written inside a map, ``.`` as a map, a file
onto a directory). Every case must end with exit status 1, one line on stderr starting ``error:`` that names
the input and matches what is wrong, no traceback, and nothing left behind: no temporary, no output, every file
that was there unchanged (compared byte for byte).
"""

from __future__ import annotations

import hashlib
import json
import os
import pickle
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

import sdfcodec
from sdfcodec.cli import app

VS, TRUNC = 0.02, (-0.04, 0.1)


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    """A valid volume, a map encoded from it, and the hostile input files, in one folder the cases copy."""
    from sdfcodec.core.sdf import sample_volume
    from sdfcodec.testing import analytic_blocks, analytic_scene

    d = tmp_path_factory.mktemp("hostile-cli")
    v = sample_volume(analytic_scene(), (48, 40, 36), VS, truncation=TRUNC).astype(np.float32)
    np.save(d / "v.npy", v)
    codec = sdfcodec.get_codec("pca", code_size=16).fit(analytic_blocks(100, seed=3))
    with sdfcodec.create_map(d / "m.sdfz", codec=codec, voxel_size=VS, truncation=TRUNC, chunk_blocks=2) as m:
        m.write_volume(v)
    np.save(d / "object.npy", np.array([{"a": 1}] * 4, dtype=object), allow_pickle=True)
    np.savez(d / "object.npz", tsdf=np.array([None] * 3, dtype=object), voxel_size=VS)
    with open(d / "pickle.npy", "wb") as f:  # a pickle where a .npy belongs: never unpickled
        pickle.dump(v, f)
    raw = (d / "v.npy").read_bytes()
    (d / "truncated.npy").write_bytes(raw[: len(raw) // 2])
    (d / "truncated-header.npy").write_bytes(raw[:40])
    head = raw[:128]
    assert b"(48, 40, 36)" in head
    (d / "lying.npy").write_bytes(head.replace(b"(48, 40, 36)", b"(96, 40, 36)") + raw[128:])
    np.savez(d / "strmeta.npz", tsdf=v, voxel_size="abc", origin="x", truncation="y")
    np.savez(d / "strmeta-array.npz", tsdf=v, voxel_size=np.array(["0.02"]))
    np.save(d / "strings.npy", np.array([["a"] * 3] * 3))
    # a map whose header says voxel size 5e-324 (finite, positive, valid JSON)
    shutil.copytree(d / "m.sdfz", d / "tiny-voxels.sdfz")
    doc = json.loads((d / "tiny-voxels.sdfz" / "zarr.json").read_text())
    doc["attributes"]["sdfcodec"]["voxel_size"] = 5e-324
    (d / "tiny-voxels.sdfz" / "zarr.json").write_text(json.dumps(doc))
    (d / "existing.txt").write_text("a trajectory someone wanted to keep\n")
    (d / "a-directory.npy").mkdir()
    (d / "eval-out").mkdir()
    (d / "eval-out" / "eval.json").write_text("{}\n")
    (d / "bench.json").write_text("{}\n")
    return d


def _tree(root: Path) -> dict[str, str]:
    """Every file under ``root`` (hidden ones too) -> its digest; directories -> 'dir'."""
    out = {}
    for dirpath, dirnames, filenames in os.walk(root):
        for n in dirnames:
            out[os.path.relpath(os.path.join(dirpath, n), root)] = "dir"
        for n in filenames:
            p = os.path.join(dirpath, n)
            out[os.path.relpath(p, root)] = hashlib.sha256(Path(p).read_bytes()).hexdigest()
    return out


NO_CUDA = pytest.mark.skipif(torch.cuda.is_available(), reason="the machine has CUDA: --device cuda is valid")
SEQ = "no-sequence-read"  # track refuses its flags before it reads the sequence
# (id, arguments ({d}: the case's folder), what the one error line must match (the input named))
CASES = [
    ("encode-object-npy", "encode {d}/object.npy {d}/o.sdfz --voxel-size 0.02", r"object\.npy.*Python objects"),
    ("encode-object-npz", "encode {d}/object.npz {d}/o.sdfz", r"object\.npz.*Python objects"),
    ("encode-pickle-as-npy", "encode {d}/pickle.npy {d}/o.sdfz --voxel-size 0.02", r"pickle\.npy.*pickle"),
    ("encode-truncated-npy", "encode {d}/truncated.npy {d}/o.sdfz --voxel-size 0.02", r"truncated\.npy.*shorter"),
    ("encode-truncated-npy-header", "encode {d}/truncated-header.npy {d}/o.sdfz --voxel-size 0.02",
     r"truncated-header\.npy.*shorter"),
    ("encode-lying-npy-header", "encode {d}/lying.npy {d}/o.sdfz --voxel-size 0.02", r"lying\.npy.*shorter"),
    ("encode-string-metadata-npz", "encode {d}/strmeta.npz {d}/o.sdfz", r"strmeta\.npz: array 'voxel_size'"),
    ("encode-string-metadata-array-npz", "encode {d}/strmeta-array.npz {d}/o.sdfz --voxel-size 0.02",
     r"strmeta-array\.npz: array 'voxel_size'"),
    ("encode-string-volume", "encode {d}/strings.npy {d}/o.sdfz --voxel-size 0.02", r"strings\.npy.*not numbers"),
    ("compare-string-metadata-npz", "compare {d}/strmeta.npz {d}/m.sdfz", r"strmeta\.npz: array 'voxel_size'"),
    ("compare-object-npy", "compare {d}/object.npy {d}/m.sdfz", r"object\.npy.*Python objects"),
    ("compare-truncated-npy", "compare {d}/truncated.npy {d}/m.sdfz", r"truncated\.npy.*shorter"),
    ("dataset-volume-pickle", "dataset {d}/ds --volume {d}/pickle.npy", r"pickle\.npy.*pickle"),
    ("encode-chunk-blocks-0", "encode {d}/v.npy {d}/o.sdfz --voxel-size 0.02 --chunk-blocks 0",
     r"--chunk-blocks.*got 0"),
    ("encode-device-foo", "encode {d}/v.npy {d}/o.sdfz --voxel-size 0.02 --device foo", r"'foo' is not a torch"),
    ("encode-device-cuda-cpu-only-torch", "encode {d}/v.npy {d}/o.sdfz --voxel-size 0.02 --device cuda",
     r"'cuda'.*(CPU-only|no CUDA)"),
    ("decode-device-foo", "decode {d}/m.sdfz {d}/o.npy --device foo", r"'foo' is not a torch"),
    ("decode-device-cuda-cpu-only-torch", "decode {d}/m.sdfz {d}/o.npy --device cuda",
     r"'cuda'.*(CPU-only|no CUDA)"),
    ("decode-region-m-voxel-size-5e-324", "decode {d}/tiny-voxels.sdfz {d}/o.npy --region 0:0.1,0:0.1,0:0.1 "
     "--units m", r"tiny-voxels\.sdfz.*voxel_size 5e-324"),
    ("search-like-two-numbers", "search {d}/m.sdfz --query like:1,2 --no-mesh", r"like:.*'1,2'"),
    ("track-cache-mb-nan", "track {d}/m.sdfz " + SEQ + " -o {d}/t.txt --cache-mb nan", r"--cache-mb.*nan"),
    ("track-frames-0", "track {d}/m.sdfz " + SEQ + " -o {d}/t.txt --frames 0", r"frames.*got 0"),
    ("track-frames-negative", "track {d}/m.sdfz " + SEQ + " -o {d}/t.txt --frames -1", r"frames.*got -1"),
    ("track-device-foo", "track {d}/m.sdfz " + SEQ + " -o {d}/t.txt --device foo", r"'foo' is not a torch"),
    # outputs that lost data
    ("encode-output-dot", "encode {d}/v.npy . --voxel-size 0.02 --overwrite", r"'\.' names a directory"),
    ("track-output-exists", "track {d}/m.sdfz " + SEQ + " -o {d}/existing.txt", r"existing\.txt exists.*--overwrite"),
    ("track-output-inside-map", "track {d}/m.sdfz " + SEQ + " -o {d}/m.sdfz/zarr.json --overwrite",
     r"m\.sdfz/zarr\.json lies inside .*m\.sdfz, a Zarr store"),
    ("track-output-is-map", "track {d}/m.sdfz " + SEQ + " -o {d}/m.sdfz --overwrite", r"m\.sdfz is a directory"),
    ("decode-output-is-directory", "decode {d}/m.sdfz {d}/a-directory.npy --overwrite",
     r"a-directory\.npy is a directory"),
    ("decode-output-inside-map", "decode {d}/m.sdfz {d}/m.sdfz/codes/x.npy", r"lies inside .*m\.sdfz, a Zarr store"),
    ("encode-output-inside-map", "encode {d}/v.npy {d}/m.sdfz/inner.sdfz --voxel-size 0.02",
     r"inner\.sdfz lies inside"),
    ("mesh-output-inside-map", "mesh {d}/m.sdfz {d}/m.sdfz/mesh.ply", r"mesh\.ply lies inside"),
    ("search-out-inside-map", "search {d}/m.sdfz --out {d}/m.sdfz/pictures", r"pictures lies inside"),
    ("train-output-inside-map", "train {d}/m.sdfz -o {d}/m.sdfz/model.npz", r"model\.npz lies inside"),
    ("dataset-output-inside-map", "dataset {d}/m.sdfz/ds --synthetic 10", r"ds lies inside"),
    ("fuse-output-inside-map", "fuse " + SEQ + " {d}/m.sdfz/fused.sdfz", r"fused\.sdfz lies inside"),
    ("bench-out-exists", "bench --quick --out {d}/bench.json", r"bench\.json exists.*--overwrite"),
    ("eval-out-has-results", "eval synthetic:fast-clean -o {d}/eval-out", r"eval\.json exists.*--overwrite"),
]


@pytest.mark.parametrize("case", [pytest.param(c, id=c[0], marks=NO_CUDA if "cuda" in c[0] else ()) for c in CASES])
def test_hostile_cli_case(case, inputs, tmp_path, monkeypatch):
    name, argv, expect = case
    d = tmp_path / "in"
    shutil.copytree(inputs, d, symlinks=True)
    work = tmp_path / "cwd"
    work.mkdir()
    monkeypatch.chdir(work)  # `.` as an output is this empty folder
    before, before_cwd = _tree(d), _tree(work)
    r = CliRunner().invoke(app, argv.format(d=d).split())
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert r.exit_code == 1, (name, r.exit_code, r.stdout, r.stderr, r.exception)
    assert isinstance(r.exception, SystemExit), f"{name}: {type(r.exception).__name__}: {r.exception}"
    assert "Traceback" not in r.stderr and len(lines) == 1 and lines[0].startswith("error: "), (name, r.stderr)
    assert re.search(expect, lines[0]), f"{name}: {lines[0]!r} does not match {expect!r}"
    # nothing left behind: no output, no temporary, every input file unchanged
    assert _tree(d) == before, f"{name}: files changed: {sorted(set(_tree(d).items()) ^ set(before.items()))}"
    assert _tree(work) == before_cwd


def test_case_count():
    """docs/reliability.md quotes this count."""
    assert len(CASES) >= 38


def test_decode_write_failure_leaves_no_temporary(inputs, tmp_path, monkeypatch):
    """A decode whose write fails after the data were written (the rename over the output refused: here the
    output turned into a directory while the command ran) leaves no hidden temporary, and says so truthfully;
    before, a full-size ``.x.npy.tmp`` stayed while the message said none was left."""
    from sdfcodec.core import _atomic

    d = tmp_path / "in"
    shutil.copytree(inputs, d, symlinks=True)
    out = d / "x.npy"
    real = os.replace

    def replace(src, dst):
        if Path(dst) == out:
            out.mkdir()  # the output became a directory between the check and the rename
        return real(src, dst)

    monkeypatch.setattr(_atomic.os, "replace", replace)
    r = CliRunner().invoke(app, ["decode", str(d / "m.sdfz"), str(out)])
    assert r.exit_code == 1 and "no temporary file is left" in r.stderr, r.stderr
    assert not [p for p in os.listdir(d) if p.startswith(".x.npy")], os.listdir(d)


def test_overwrite_replaces_and_reports(inputs, tmp_path):
    """With ``--overwrite`` the same outputs are written: track replaces an existing trajectory file (and the
    report names it), decode replaces an existing array."""
    d = tmp_path / "in"
    shutil.copytree(inputs, d, symlinks=True)
    r = CliRunner().invoke(app, ["decode", str(d / "m.sdfz"), str(d / "v.npy"), "--overwrite"])
    assert r.exit_code == 0 and f"wrote {d / 'v.npy'}" in r.stdout, r.stderr
    assert np.array_equal(np.load(d / "v.npy"), sdfcodec.open_map(d / "m.sdfz").decode_region())


def test_commit_reports_the_version_it_wrote(inputs, tmp_path, monkeypatch):
    """A map committed while another writer replaces it at once: the writer's map object (and so ``encode``'s
    report) describes the version it wrote, not the one now at the path."""
    from sdfcodec.core import _atomic
    from sdfcodec.testing import analytic_blocks

    path = tmp_path / "race.sdfz"
    codec = sdfcodec.get_codec("pca", code_size=16).fit(analytic_blocks(100, seed=3))
    other = np.full((16, 16, 16), TRUNC[1], np.float32)
    other[:, :, :3] = -0.02  # one coded block
    real, raced, calls = _atomic.collect, [], []

    def collect(final):  # called as a writer starts, then right after its swap: race the second call
        if Path(final) != path:  # another map's collection: a map of an earlier test closed by the garbage collector
            return real(final)
        calls.append(final)
        if len(calls) == 2 and not raced:
            raced.append(True)
            with sdfcodec.create_map(final, codec=codec, voxel_size=VS, truncation=TRUNC, overwrite=True) as o:
                o.write_volume(other)
        return real(final)

    monkeypatch.setattr(_atomic, "collect", collect)
    with sdfcodec.create_map(path, codec=codec, voxel_size=VS, truncation=TRUNC) as m:
        m.write_volume(np.load(inputs / "v.npy"))
    monkeypatch.setattr(_atomic, "collect", real)
    assert raced
    assert sdfcodec.open_map(path).info()["blocks"]["coded"] == 1  # the other writer's map is at the path
    info = m.info()
    assert info["blocks"]["coded"] == sdfcodec.open_map(inputs / "m.sdfz").info()["blocks"]["coded"] > 1
    assert m.decode_region().shape == (48, 40, 36)
