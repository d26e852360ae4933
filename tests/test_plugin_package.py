"""A third-party codec plugin, installed from its own package, works through the entry point alone."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from sdfcodec.core.sdf import Plane, Scene, Sphere, sample_volume

PLUGIN = Path(__file__).resolve().parents[1] / "examples" / "sdfcodec-dct"


@pytest.fixture(scope="module")
def plugin_dir(tmp_path_factory) -> Path:
    target = tmp_path_factory.mktemp("site")
    r = subprocess.run([sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--no-build-isolation",
                        "--no-index", "--target", str(target), str(PLUGIN)], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    return target


def sdfcodec(*args, plugin: Path | None = None):
    env = dict(os.environ)
    env.pop("PYTHONPATH", None)
    if plugin is not None:
        env["PYTHONPATH"] = str(plugin)
    return subprocess.run([sys.executable, "-m", "sdfcodec.cli", *map(str, args)], capture_output=True, text=True,
                          env=env, timeout=300)


def test_installed_plugin_is_listed_used_and_missed(plugin_dir, tmp_path, monkeypatch):
    # a fresh process finds the installed package's entry point
    r = sdfcodec("codecs", "--json", plugin=plugin_dir)
    assert r.returncode == 0, r.stderr
    rows = {row["id"]: row for row in json.loads(r.stdout)}
    assert rows["dct"]["package"] == "sdfcodec-dct" and rows["dct"]["prefix_ordered"] is True

    # encode and decode through it in this process (typer's runner; the registry scans sys.path as it is now):
    # two fresh interpreters importing torch would only repeat the discovery checked above
    from typer.testing import CliRunner

    from sdfcodec.cli import app

    vol = sample_volume(Scene([Plane((0, 0, 1), 0.1), Sphere((0.4, 0.4, 0.4), 0.2)]), (48, 48, 40), 0.02)
    np.save(tmp_path / "v.npy", vol)
    with monkeypatch.context() as mp:
        mp.syspath_prepend(str(plugin_dir))
        r = CliRunner().invoke(app, ["encode", str(tmp_path / "v.npy"), str(tmp_path / "d.sdfz"), "--voxel-size",
                                     "0.02", "--codec", "dct", "--code-size", "128"])
        assert r.exit_code == 0, r.output
        r = CliRunner().invoke(app, ["decode", str(tmp_path / "d.sdfz"), str(tmp_path / "d.npy")])
        assert r.exit_code == 0, r.output
    assert np.sqrt(np.mean((np.load(tmp_path / "d.npy") - vol) ** 2)) < 0.01

    # without the plugin: the header still reads, decoding names the codec and the package to install
    assert sdfcodec("info", tmp_path / "d.sdfz").returncode == 0
    r = sdfcodec("decode", tmp_path / "d.sdfz", tmp_path / "e.npy")
    assert r.returncode == 1
    assert "'dct'" in r.stderr and "sdfcodec-dct" in r.stderr and len(r.stderr.strip().splitlines()) == 1


def _plugin_tests(plugin_dir: Path, *select: str) -> subprocess.CompletedProcess:
    """The plugin's own test suite (pytest in its folder), ``select`` passed to pytest."""
    # the plugin first, then the sdfcodec under test (a checkout's PYTHONPATH), as the suite sees it
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(p for p in [str(plugin_dir), os.environ.get("PYTHONPATH")] if p))
    r = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-p", "no:dash", *select,
                        str(PLUGIN / "tests")], capture_output=True, text=True, env=env, timeout=300, cwd=PLUGIN)
    assert r.returncode == 0, r.stdout + r.stderr
    return r


def test_plugin_passes_its_own_conformance_tests(plugin_dir):
    # its smaller codec's 17 named conformance checks (golden fixture included) and the DCT test; both codecs:
    # test_plugin_passes_all_its_tests (slow)
    r = _plugin_tests(plugin_dir, "-k", "dct-32 or scipy")
    assert "18 passed, 17 deselected" in r.stdout


@pytest.mark.slow
def test_plugin_passes_all_its_tests(plugin_dir):
    assert "35 passed" in _plugin_tests(plugin_dir).stdout  # 2 codecs x 17 named conformance checks, the DCT test
