"""The first hour of a user at the command line (issue 20, items 2-6): every command run as a user runs it, in a
subprocess with stdout and stderr piped (not a terminal), its output read as a script would read it."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

import sdfcodec
from sdfcodec.core.sdf import Plane, Scene, Sphere, sample_volume

VS = 0.02
ROOT = Path(__file__).resolve().parents[1]


def sdfcodec_cli(*args, env: dict | None = None, timeout: float = 120, python_flags: tuple = ()
                 ) -> subprocess.CompletedProcess:
    """``python -m sdfcodec.cli ARGS`` with stdout and stderr piped, as a script runs it."""
    return subprocess.run([sys.executable, *python_flags, "-m", "sdfcodec.cli", *map(str, args)],
                          capture_output=True, text=True, timeout=timeout, env=_env(env))


def sdfcodec_in_process(*args) -> subprocess.CompletedProcess:
    """The same command run in this process (typer's runner: stdout and stderr are not a terminal either), for the
    checks of what a command says and writes: a fresh interpreter would add seconds of imports and check nothing
    more. What is about the process itself (start-up imports, a pipe, a signal) runs in :func:`sdfcodec_cli`."""
    from typer.testing import CliRunner

    from sdfcodec.cli import app

    r = CliRunner().invoke(app, [str(a) for a in args], env={"FORCE_COLOR": None, "TTY_COMPATIBLE": None})
    if r.exception is not None and not isinstance(r.exception, SystemExit):
        raise r.exception  # a traceback the command would have printed: the test fails with it
    return subprocess.CompletedProcess(args, r.exit_code, r.stdout, r.stderr)


def _env(extra: dict | None = None) -> dict:
    env = dict(os.environ)
    env.pop("FORCE_COLOR", None)
    env.pop("TTY_COMPATIBLE", None)
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), str(ROOT / "plugins"), env.get("PYTHONPATH", "")])
    env.update(extra or {})
    return env


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> tuple[Path, Path, np.ndarray]:
    """A 120 x 100 x 60 volume (.npy) and its pca-64 map (the shipped eigenshapes), encoded in-process."""
    vol = sample_volume(Scene([Plane((0, 0, 1), 0.1), Plane((0, 1, 0), 0.07), Sphere((0.7, 0.8, 0.5), 0.25)]),
                        (120, 100, 60), VS)
    d = tmp_path_factory.mktemp("first-hour")
    np.save(d / "scene.npy", vol)
    with sdfcodec.create_map(d / "scene.sdfz", codec=sdfcodec.pretrained_codec("pca", 64), voxel_size=VS) as m:
        m.write_volume(vol)
    return d / "scene.npy", d / "scene.sdfz", vol


def test_help_and_version_are_quick_and_never_import_torch():
    """Item 2 and start-up: `--version` prints the version and exits 0 (was "Missing command.", 2); neither it
    nor `--help` imports torch or open3d (was 2.4 s of torch for `--help`)."""
    r = sdfcodec_cli("--version", python_flags=("-X", "importtime"))
    assert r.returncode == 0 and r.stdout == f"sdfcodec {sdfcodec.__version__}\n", (r.stdout, r.stderr[-500:])
    modules = {line.rsplit("|", 1)[-1].strip() for line in r.stderr.splitlines() if line.startswith("import time")}
    assert "numpy" in modules  # the import log is read correctly
    assert not {m for m in modules if m.split(".")[0] in ("torch", "open3d", "zarr")}, sorted(modules)[:20]
    r = sdfcodec_cli("--help", python_flags=("-X", "importtime"))
    assert r.returncode == 0 and "encode" in r.stdout and "--version" in r.stdout
    # `python -m sdfcodec` is the command too (an environment whose scripts are not on PATH)
    r = subprocess.run([sys.executable, "-m", "sdfcodec", "--version"], capture_output=True, text=True, timeout=120,
                       env=_env())
    assert r.returncode == 0 and r.stdout == f"sdfcodec {sdfcodec.__version__}\n", (r.stdout, r.stderr[-500:])
    assert not any(re.search(r"\|\s*(torch|open3d)$", line) for line in r.stderr.splitlines())


def test_code_size_zero_or_negative_is_an_error(scene, tmp_path):
    """Item 2: `--code-size 0` (or -1, or a size a fixed-size codec cannot make) is one line and status 1, and
    writes nothing (it used to encode at 64)."""
    src, _, _ = scene
    for args, words in ((("--code-size", "0"), "positive"), (("--code-size", "-1"), "positive"),
                        (("--codec", "raw", "--code-size", "64"), "4096")):
        r = sdfcodec_in_process("encode", src, tmp_path / "m.sdfz", "--voxel-size", VS, *args)
        assert r.returncode == 1 and r.stderr.startswith("error: --code-size") is (words == "positive"), r.stderr
        assert words in r.stderr and r.stderr.count("\n") == 1 and r.stdout == ""
        assert not (tmp_path / "m.sdfz").exists()


def test_piped_tables_are_tab_separated_and_never_cut(scene):
    """Item 3: on a pipe, `codecs` and `info` are tab-separated lines, no id cut to "gaussian-b…", no line
    wrapped at 80 columns; `| tail -1` is the last row."""
    r = sdfcodec_cli("codecs")
    assert r.returncode == 0, r.stderr
    lines = r.stdout.splitlines()
    assert "…" not in r.stdout and lines[0] == "# installed sdfcodec codecs"
    assert lines[1].split("\t") == ["id", "code sizes", "prefix-ordered", "needs fitting", "package", "status"]
    rows = {ln.split("\t")[0]: ln.split("\t") for ln in lines[2:]}
    # the installed codecs (entry points): other tests in this process may have registered codecs at run time
    assert set(rows) == {e.id for e in sdfcodec.list_codecs() if e.package} and all(len(r_) == 6 for r_ in rows.values())
    assert rows["gaussian-blur"][1] == "4096" and rows["pca"][2] == "yes"

    _, map_path, vol = scene
    r = sdfcodec_cli("info", map_path)
    assert r.returncode == 0, r.stderr
    info = dict(ln.split("\t") for ln in r.stdout.splitlines() if not ln.startswith("#"))
    assert info["extent"].startswith(str(list(vol.shape))) and info["voxel size"] == f"{VS} m"
    assert info["codec"].startswith('{"id": "pca", "code_size": 64') and len(info["codec"]) > 80  # not wrapped


def test_encode_summary_is_one_line_on_a_pipe(scene, tmp_path):
    """Item 3: a summary longer than 80 columns stays one line on a pipe (rich wrapped it at 80)."""
    src, _, _ = scene
    out = tmp_path / ("a-rather-long-directory-name-" * 3) / "scene-encoded-with-the-shipped-eigenshapes.sdfz"
    out.parent.mkdir()
    r = sdfcodec_cli("encode", src, out, "--voxel-size", VS)
    assert r.returncode == 0, r.stderr
    assert r.stdout.count("\n") == 1 and len(r.stdout) > 120 and r.stdout.startswith(f"wrote {out} with pca-64 (shipped model, by reference): ")
    assert f"{sdfcodec.open_map(out).count_states()['coded']} coded blocks" in r.stdout


def test_interrupt_says_what_became_of_the_output(tmp_path):
    """Item 6: Ctrl-C (SIGINT) in the middle of an encode exits 130 with one line saying that OUTPUT was not
    created (and leaves nothing there); before it, the piped progress lines report the encode (item 3)."""
    rng = np.random.default_rng(0)
    vol = rng.uniform(-0.04, 0.1, (256, 256, 256)).astype(np.float32)  # 64 MiB of raw codes: seconds of work
    np.save(tmp_path / "big.npy", vol)
    del vol
    out = tmp_path / "big.sdfz"
    proc = subprocess.Popen([sys.executable, "-m", "sdfcodec.cli", "encode", str(tmp_path / "big.npy"), str(out),
                             "--voxel-size", "0.02", "--codec", "raw"], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=_env({"SDFCODEC_PROGRESS_SECONDS": "0.3"}))
    first = proc.stderr.readline()  # a progress line: the encode is under way
    time.sleep(0.2)
    proc.send_signal(signal.SIGINT)
    stdout, rest = proc.communicate(timeout=60)
    # the writer reports whole batches of 16,384 blocks: this one is still in its first
    assert re.fullmatch(r"encoding: \d+ s so far\n", first), first + rest
    assert proc.returncode == 130, (first, rest)
    assert rest.splitlines()[-1] == f"error: interrupted: {out} was not created", rest
    assert stdout == "" and not out.exists()
    assert [p.name for p in tmp_path.iterdir()] == ["big.npy"]  # no temporary map left beside it


def test_progress_lines_without_a_terminal(monkeypatch, capsys):
    """The rule behind them: one line per unfinished task every interval, nothing once it is complete."""
    from sdfcodec.cli.common import LineProgress

    with LineProgress("frames", every=0.05) as prog:
        task = prog.add_task("tracking", total=10)
        prog.advance(task, 4)
        time.sleep(0.18)
        prog.update(task, advance=6)
        time.sleep(0.12)
    lines = capsys.readouterr().err.splitlines()
    assert 2 <= len(lines) <= 4 and all(re.fullmatch(r"tracking: 4 of 10 frames \(40%\), [\d.]+ frames/s, 0 s, "
                                                     r"about \d+ s left", ln) for ln in lines), lines


def test_live_bars_on_a_terminal_show_the_rate(monkeypatch):
    """On a terminal progress_bar is rich's live bar (imported on first use); its last column shows the caller's
    ``rate`` field when set, else the measured speed in the unit."""
    import io

    from rich.console import Console

    from sdfcodec.cli import common

    term = Console(file=io.StringIO(), force_terminal=True, width=120)
    monkeypatch.setattr(common, "err", term)
    with common.progress_bar("frames") as prog:
        done = prog.add_task("tracking", total=10)
        given = prog.add_task("fusing", total=10, rate="3 frames/s")
        prog.advance(done, 4)
        time.sleep(0.05)
        prog.advance(done, 4)
        column = prog.columns[-1]
        assert str(column.render(prog.tasks[given])) == "3 frames/s"
        speed = str(column.render(prog.tasks[done]))
        assert re.fullmatch(r"[\d,]+\.\d frames/s", speed), speed


def test_metre_regions_are_half_open_and_decodes_truncated(scene, tmp_path):
    """Item 5: `--region 0:1,0:1,0:0.5 --units m` at 2 cm is 50 x 50 x 25 voxels (was 51 x 51 x 26: the upper
    ends were included), the same voxels as the voxel range 0:50,0:50,0:25; decoded values lie in the truncation
    (a lossy decode overshot d_max)."""
    _, map_path, _ = scene
    r = sdfcodec_in_process("decode", map_path, tmp_path / "m.npy", "--region", "0:1,0:1,0:0.5", "--units", "m")
    assert r.returncode == 0, r.stderr
    assert "50 x 50 x 25 voxels" in r.stdout and r.stdout.count("\n") == 1
    part = np.load(tmp_path / "m.npy")
    full = sdfcodec.open_map(map_path).decode_region()
    # equal to float32 rounding: BLAS (AMD's at least) sums in another order for another number of blocks
    assert part.shape == (50, 50, 25)
    np.testing.assert_allclose(part, full[:50, :50, :25], rtol=0, atol=1e-6)
    assert full.min() >= -0.04 and full.max() <= 0.1
    r = sdfcodec_in_process("decode", map_path, tmp_path / "e.npy", "--region", "0:1,0:1,0.5:0.5", "--units", "m")
    assert r.returncode == 1 and "holds no voxel on axis z" in r.stderr and "half-open" in r.stderr


def test_decode_npz_round_trips_without_flags_and_reversed_truncation_first(scene, tmp_path):
    """Item 6: `decode OUT.npz` records voxel size, origin and truncation, so `encode OUT.npz` needs no flag (and
    a region keeps its own origin); a reversed `--truncation` is refused before any clipping warning."""
    src, map_path, _ = scene
    r = sdfcodec_in_process("decode", map_path, tmp_path / "part.npz", "--region", "10:40,20:60,0:30")
    assert r.returncode == 0, r.stderr
    with np.load(tmp_path / "part.npz") as z:
        assert z["tsdf"].shape == (30, 40, 30) and float(z["voxel_size"]) == VS
        assert np.allclose(z["origin"], [10 * VS, 20 * VS, 0]) and np.allclose(z["truncation"], [-0.04, 0.1])
    r = sdfcodec_in_process("encode", tmp_path / "part.npz", tmp_path / "back.sdfz", "--codec", "raw")
    assert r.returncode == 0, r.stderr
    back = sdfcodec.open_map(tmp_path / "back.sdfz")
    assert back.voxel_size == VS and np.allclose(back.origin, [10 * VS, 20 * VS, 0])
    assert back.truncation == (-0.04, 0.1)
    r = sdfcodec_in_process("encode", src, tmp_path / "rev.sdfz", "--voxel-size", VS, "--truncation", "0.1,-0.04")
    assert r.returncode == 1 and r.stderr.count("\n") == 1 and "warning" not in r.stderr, r.stderr
    assert r.stderr.startswith("error: truncation must be d_min,d_max with d_min < d_max")


def test_track_prints_one_sentence_with_its_ate(tmp_path):
    """Item 4: `track` prints one sentence: frames, ATE and RPE against the ground truth, frames/s, the file (it
    printed a dict dump without the ATE); the ATE is the one of the written trajectory."""
    from sdfcodec.data.render import render_sequence
    from sdfcodec.data.sequences import Intrinsics
    from sdfcodec.fusion.tsdf import fuse
    from sdfcodec.core.metrics import ate, read_tum

    seq = render_sequence(tmp_path / "seq", "slow-clean", frames=6,
                          intrinsics=Intrinsics(fx=131.25, fy=131.25, cx=79.5, cy=59.5, width=160, height=120))
    fused = fuse(seq, voxel_size=0.02, quiet=True)
    with sdfcodec.create_map(tmp_path / "raw.sdfz", codec=sdfcodec.get_codec("raw"), voxel_size=0.02,
                             origin=tuple(fused.origin)) as m:
        m.write_blocks(fused.coords, fused.tsdf)
    r = sdfcodec_in_process("track", tmp_path / "raw.sdfz", seq, "-o", tmp_path / "t.txt")
    assert r.returncode == 0, r.stderr
    assert r.stdout.count("\n") == 1 and "{" not in r.stdout and "frames_per_s" not in r.stdout
    rmse = 1000 * ate(read_tum(seq / "groundtruth.txt"), read_tum(tmp_path / "t.txt")).rmse
    assert re.fullmatch(rf"tracked 6 frames of {re.escape(str(seq))} in {re.escape(str(tmp_path / 'raw.sdfz'))} "
                        rf"\([\d.]+ frames/s, [\d.]+ s, from the ground-truth first pose\): ATE RMSE {rmse:.1f} mm \(max [\d.]+ mm\), "
                        rf"RPE [\d.]+ mm/frame against the ground truth; wrote {re.escape(str(tmp_path / 't.txt'))}\n",
                        r.stdout), r.stdout
