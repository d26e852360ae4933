"""``sdfcodec view``: the Rerun recording it writes, read back with rerun's own reader (``rerun.chunk.RrdReader``)
and checked against what the map, an independent search and the TUM files say; the command run as a user runs
it (a subprocess, output piped; the rest in process, where a fresh interpreter's imports
would cost seconds a run)."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import sdfcodec
from sdfcodec.errors import InvalidValueError, MissingDependencyError
from sdfcodec.fusion.tsdf import mesh_from_blocks
from sdfcodec.search.engine import search
from sdfcodec.view.recording import up_rotation, write_recording

pytest.importorskip("rerun", reason="rerun-sdk (the view extra) is not installed")
from rerun.chunk import RrdReader  # noqa: E402
from typer.testing import CliRunner  # noqa: E402

from sdfcodec.cli import app  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
VS = 0.02


def read_rrd(path: Path) -> dict[str, dict[str, list]]:
    """Entity path (no leading /) -> column name -> the first row's values, as Python lists."""
    got: dict[str, dict[str, list]] = {}
    for chunk in RrdReader(path).stream().to_chunks():
        batch = chunk.to_record_batch()
        row = got.setdefault(chunk.entity_path.lstrip("/"), {})
        for name in batch.schema.names:
            if not name.startswith("rerun.controls"):
                row[name] = batch.column(name)[0].as_py()
    return got


def rgb(packed: list[int]) -> np.ndarray:
    """Rerun's colours are packed 0xRRGGBBAA."""
    p = np.asarray(packed, np.uint64)
    return np.stack([(p >> 24) & 255, (p >> 16) & 255, (p >> 8) & 255], -1).astype(int)


def tum(path: Path, stamps, positions) -> Path:
    lines = ["# timestamp tx ty tz qx qy qz qw"]
    lines += [f"{t:.3f} {x:.6f} {y:.6f} {z:.6f} 0 0 0 1" for t, (x, y, z) in zip(stamps, positions)]
    path.write_text("\n".join(lines) + "\n")
    return path


@pytest.fixture(scope="module")
def small_map(tmp_path_factory, volume) -> Path:
    """The analytic scene (a floor at z = 0.1 m, a wall, a sphere, a box, a cylinder) as a pca-64 map."""
    path = tmp_path_factory.mktemp("view") / "scene.sdfz"
    with sdfcodec.create_map(path, codec=sdfcodec.pretrained_codec("pca", 64), voxel_size=VS,
                             origin=(0.0, 0.0, 0.0)) as m:
        m.write_volume(volume)
    return path


def cli(*args) -> subprocess.CompletedProcess:
    env = {"PYTHONPATH": f"{ROOT}:{ROOT / 'plugins'}", "PATH": "/usr/bin:/bin", "COLUMNS": "200"}
    return subprocess.run([sys.executable, "-m", "sdfcodec.cli", *map(str, args)], capture_output=True, text=True,
                          env=env, cwd=ROOT, timeout=120)


def test_view_command_records_mesh_search_and_trajectory(small_map, tmp_path):
    # a camera circling the room at 1 m, and an estimate off by (3, 0, 4) cm: an ATE of exactly 5 cm
    stamps = np.arange(15) * 0.1
    a = np.linspace(0, 2 * np.pi, 15)
    gt_pos = np.stack([0.9 + 0.5 * np.cos(a), 0.7 + 0.4 * np.sin(a), np.full(15, 1.0)], -1)
    gt = tum(tmp_path / "gt.txt", stamps, gt_pos)
    est = tum(tmp_path / "est.txt", stamps[:12], gt_pos[:12] + [0.03, 0.0, 0.04])
    out = tmp_path / "view.rrd"
    # in process (the imports of a fresh interpreter cost seconds); the subprocess run is the next test's
    r = CliRunner().invoke(app, ["view", str(small_map), "--query", "floor", "--top", "7", "--trajectory", str(est),
                                 "--groundtruth", str(gt), "-o", str(out), "--json"])
    assert r.exit_code == 0, r.output
    summary = json.loads(r.stdout)
    assert not (tmp_path / ".tmp-view.rrd").exists()  # written beside and renamed
    rec = read_rrd(out)

    m = sdfcodec.open_map(small_map)
    coords, blocks = zip(*m.iter_blocks())
    mesh = mesh_from_blocks(np.concatenate(coords), np.concatenate(blocks), origin=m.origin, voxel_size=VS,
                            truncation=m.truncation)
    got_v = np.asarray(rec["world/map/mesh"]["Mesh3D:vertex_positions"])
    assert got_v.shape == (len(mesh.vertices), 3) and len(mesh.vertices) > 1000
    # open3d's marching cubes numbers vertices in no fixed order (threads): compare the triangles' corners
    def corners(v, t):
        tri = np.sort(np.round(np.asarray(v)[np.asarray(t)], 5).view([("", float)] * 3).reshape(-1, 3), axis=1)
        return np.sort(tri.view(float).reshape(len(tri), 9), axis=0)
    np.testing.assert_array_equal(corners(got_v, rec["world/map/mesh"]["Mesh3D:triangle_indices"]),
                                  corners(mesh.vertices, mesh.triangles))
    assert len(rec["world/map/mesh"]["Mesh3D:vertex_colors"]) == len(mesh.vertices)  # coloured by score

    # one point, one colour and one score per coded block; the scores are the search's
    res = search(m, "floor", top=7, keep_scores=True, device="cpu")
    coded = m.count_states()["coded"]
    sc = rec["world/map/search/scores"]
    assert len(sc["Points3D:positions"]) == len(sc["Points3D:colors"]) == len(sc["score"]) == coded
    np.testing.assert_allclose(sorted(sc["score"]), np.sort(res.all_scores), rtol=1e-5)
    colours = rgb(sc["Points3D:colors"])
    assert np.array_equal(colours[int(np.argmin(sc["score"]))], [253, 231, 37])  # the closest block is brightest
    assert np.array_equal(colours[int(np.argmax(sc["score"]))], [68, 1, 84])
    # the seven selected blocks as boxes over their extent: centre origin + (16 c + 7.5) voxels, half 8 voxels
    box = rec["world/map/search/selected"]
    want = {tuple(np.round(VS * (16 * np.asarray(c) + 7.5), 5)) for c in res.coords}
    assert {tuple(np.round(c, 5)) for c in box["Boxes3D:centers"]} == want and len(want) == 7
    np.testing.assert_allclose(box["Boxes3D:half_sizes"], np.full((7, 3), 8 * VS), rtol=1e-6)

    # trajectories: one point per pose of each file, at the file's positions; an error segment per pair
    e, g = rec["world/map/trajectory/estimate"], rec["world/map/trajectory/groundtruth"]
    np.testing.assert_allclose(e["Points3D:positions"], gt_pos[:12] + [0.03, 0, 0.04], atol=1e-6)
    np.testing.assert_allclose(g["Points3D:positions"], gt_pos, atol=1e-6)
    assert len(e["LineStrips3D:strips"][0]) == 12 and len(g["LineStrips3D:strips"][0]) == 15
    segs = np.asarray(rec["world/map/trajectory/errors"]["LineStrips3D:strips"])
    assert segs.shape == (12, 2, 3)
    np.testing.assert_allclose(np.linalg.norm(segs[:, 0] - segs[:, 1], axis=1), 0.05, atol=1e-6)
    assert summary["trajectory"]["ate_rmse"] == pytest.approx(0.05, abs=1e-9)
    assert summary["trajectory"]["associated"] == 12 and summary["search"]["selected"] == 7

    # metres in the map's frame, +z up: no up in the header, so no rotation
    # rerun's ViewDir codes: Up = 1, Right = 3, Forward = 5: x right, y forward, z up
    assert rec["world"]["ViewCoordinates:xyz"] == [[3, 5, 1]]
    np.testing.assert_allclose(np.asarray(rec["world/map"]["Transform3D:mat3x3"]).reshape(3, 3), np.eye(3), atol=1e-7)
    assert "ATE RMSE 50.0 mm" in rec["summary"]["TextDocument:text"][0]


def test_view_command_line_piped(small_map, tmp_path, monkeypatch):
    out = tmp_path / "v.rrd"
    r = cli("view", small_map, "-o", out)
    assert r.returncode == 0, r.stderr
    assert r.stdout.startswith(f"wrote {out}: mesh ") and f"rerun {out}" in r.stdout
    assert set(read_rrd(out)) == {"__properties", "world", "world/map", "world/map/mesh", "summary"}
    # the refusals, in process (the same command; a subprocess each would cost seconds of imports)
    runner = CliRunner()
    before = out.stat().st_mtime_ns
    r = runner.invoke(app, ["view", str(small_map), "-o", str(out)])  # kept without --overwrite
    assert r.exit_code == 1 and "--overwrite" in r.output and out.stat().st_mtime_ns == before
    assert len(r.output.strip().splitlines()) == 1
    r = runner.invoke(app, ["view", str(small_map), "--groundtruth", str(tmp_path / "gt.txt"), "-o", str(tmp_path / "w.rrd")])
    assert r.exit_code == 1 and "--groundtruth needs --trajectory" in r.output
    r = runner.invoke(app, ["view", str(small_map), "--trajectory", str(tmp_path / "nosuch.txt"), "-o", str(tmp_path / "w.rrd")])
    assert r.exit_code == 1 and "nosuch.txt" in r.output
    r = runner.invoke(app, ["view", str(small_map), "-o", str(tmp_path / "no" / "w.rrd")])
    assert r.exit_code == 1 and "w.rrd" in r.output and len(r.output.strip().splitlines()) == 1
    r = runner.invoke(app, ["view", str(small_map), "-o", str(tmp_path / "w.ply")])
    assert r.exit_code == 1 and ".rrd" in r.output
    # the help's words, whatever width rich wrapped them at (an earlier test in the process may have fixed it)
    words = re.sub(r"[│\s]+", " ", runner.invoke(app, ["view", "--help"], terminal_width=200).output)
    assert "pip install 'sdfcodec[view]'" in words
    # rerun hidden from the import system, as on an install without the extra
    monkeypatch.setitem(sys.modules, "rerun", None)
    r = runner.invoke(app, ["view", str(small_map), "-o", str(tmp_path / "w.rrd")])
    assert r.exit_code == 1 and "pip install 'sdfcodec[view]'" in r.output
    assert len(r.output.strip().splitlines()) == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["v.rrd"]  # nothing else written, no temporary left


def test_up_from_the_header_is_shown_up(volume, tmp_path, monkeypatch):
    up = np.array([0.0, -0.6, 0.8])
    path = tmp_path / "tilted.sdfz"
    with sdfcodec.create_map(path, codec=sdfcodec.pretrained_codec("pca", 32), voxel_size=VS, up=tuple(up)) as m:
        m.write_volume(volume[:32, :32, :32])
    s = write_recording(path, tmp_path / "t.rrd")
    assert s["up_source"] == "header"
    rot = np.asarray(read_rrd(tmp_path / "t.rrd")["world/map"]["Transform3D:mat3x3"])
    # rerun stores the matrix column-major; either way it must be a rotation taking the map's up to +z
    rot = rot.reshape(3, 3).T
    np.testing.assert_allclose(rot @ up, [0, 0, 1], atol=1e-6)
    np.testing.assert_allclose(rot @ rot.T, np.eye(3), atol=1e-6)
    assert np.linalg.det(rot) == pytest.approx(1.0)
    for u in ([0, 0, 1], [0, 0, -1], [1, 0, 0], [0.3, 0.4, -0.866]):
        u = np.asarray(u, float) / np.linalg.norm(u)
        R = up_rotation(u)
        np.testing.assert_allclose(R @ u, [0, 0, 1], atol=1e-9)
        assert np.linalg.det(R) == pytest.approx(1.0)
    with pytest.raises(InvalidValueError, match="trajectory"):
        write_recording(path, tmp_path / "u.rrd", groundtruth=np.tile(np.eye(4), (3, 1, 1)))
    monkeypatch.setitem(sys.modules, "rerun", None)
    with pytest.raises(MissingDependencyError, match=r"sdfcodec\[view\]"):
        write_recording(path, tmp_path / "u.rrd")
    assert not (tmp_path / "u.rrd").exists()
