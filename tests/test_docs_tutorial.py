"""Every command of docs/tutorial.md runs as written (issue 41, item 6): the quick ones for real, through the
command line's own runner in a scratch directory, on a small lossless map standing in for the one `sdfcodec fuse`
makes in step 3; the slow ones (demo, fuse, search, track, view: minutes together, and run end to end by their
own tests) are parsed by the command line, so a renamed option or command, or a wrong argument count, fails
here."""

from __future__ import annotations

import re
import shlex
from pathlib import Path

import numpy as np
import pytest
import typer
from typer.testing import CliRunner

import sdfcodec
from sdfcodec.cli import app
from sdfcodec.core.sdf import Plane, Scene, Sphere, sample_volume

ROOT = Path(__file__).resolve().parents[1]
TUTORIAL = ROOT / "docs" / "tutorial.md"
RUN = {"--version", "codecs", "info", "encode", "compare", "decode", "mesh"}


def _commands() -> list[list[str]]:
    """The `sdfcodec ...` lines of the page's bash blocks, in order, comments removed."""
    blocks = re.findall(r"```bash\n(.*?)```", TUTORIAL.read_text(encoding="utf-8"), flags=re.S)
    return [shlex.split(line, comments=True)[1:] for b in blocks for line in b.splitlines()
            if line.startswith("sdfcodec ")]


def test_the_tutorial_covers_the_first_hour():
    names = [c[0] for c in _commands()]
    for step in ("demo", "fuse", "encode", "info", "compare", "decode", "mesh", "search", "track", "view"):
        assert step in names, f"the tutorial lost its `sdfcodec {step}` step"


def test_every_tutorial_command_runs_as_written(tmp_path, monkeypatch):
    # step 3's map: lossless, as `fuse` writes it, of a small analytic room (floor, wall, a ball)
    vol = sample_volume(Scene([Plane((0, 0, 1), 0.1), Plane((0, 1, 0), 0.07), Sphere((0.7, 0.8, 0.5), 0.25)]),
                        (64, 64, 48), 0.02)
    with sdfcodec.create_map(tmp_path / "room.sdfz", codec=sdfcodec.get_codec("raw"), voxel_size=0.02) as m:
        m.write_volume(vol)
    monkeypatch.chdir(tmp_path)
    group = typer.main.get_command(app)
    runner = CliRunner()
    ran = []
    for args in _commands():
        if args[0] in RUN:
            r = runner.invoke(app, args)
            assert r.exit_code == 0, (args, r.output[-2000:])
            ran.append(args[0])
            continue
        assert args[0] in group.commands, f"no command `sdfcodec {args[0]}`"
        cmd = group.commands[args[0]]
        cmd.make_context(args[0], list(args[1:]), parent=group.make_context("sdfcodec", [args[0]]))
        if args[0] in ("fuse", "track"):  # the built-in data exists under that name
            from sdfcodec.data.render import PRESETS

            assert args[2 if args[0] == "track" else 1].split(":", 1)[1] in PRESETS
    assert set(ran) == RUN
    # what the quick steps wrote, checked against the map itself
    pca = sdfcodec.open_map("room-pca64.sdfz")
    assert pca.codec.codec_id == "pca" and pca.code_size == 64
    with np.load("room.npz") as z:
        assert any(z[k].shape == vol.shape for k in z.files), {k: z[k].shape for k in z.files}
    corner = np.load("corner.npy")
    assert corner.shape == (64, 64, 32)
    np.testing.assert_allclose(corner, pca.decode_region(((0, 64), (0, 64), (0, 32))), atol=1e-6)
    assert Path("room.ply").stat().st_size > 1000
