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


def test_installed_plugin_is_listed_used_and_missed(plugin_dir, tmp_path):
    r = sdfcodec("codecs", "--json", plugin=plugin_dir)
    assert r.returncode == 0, r.stderr
    rows = {row["id"]: row for row in json.loads(r.stdout)}
    assert rows["dct"]["package"] == "sdfcodec-dct" and rows["dct"]["prefix_ordered"] is True

    vol = sample_volume(Scene([Plane((0, 0, 1), 0.1), Sphere((0.4, 0.4, 0.4), 0.2)]), (48, 48, 40), 0.02)
    np.save(tmp_path / "v.npy", vol)
    r = sdfcodec("encode", tmp_path / "v.npy", tmp_path / "d.sdfz", "--voxel-size", 0.02, "--codec", "dct",
                 "--code-size", 128, plugin=plugin_dir)
    assert r.returncode == 0, r.stderr
    r = sdfcodec("decode", tmp_path / "d.sdfz", tmp_path / "d.npy", plugin=plugin_dir)
    assert r.returncode == 0, r.stderr
    assert np.sqrt(np.mean((np.load(tmp_path / "d.npy") - vol) ** 2)) < 0.01

    # without the plugin: the header still reads, decoding names the codec and the package to install
    assert sdfcodec("info", tmp_path / "d.sdfz").returncode == 0
    r = sdfcodec("decode", tmp_path / "d.sdfz", tmp_path / "e.npy")
    assert r.returncode == 1
    assert "'dct'" in r.stderr and "sdfcodec-dct" in r.stderr and len(r.stderr.strip().splitlines()) == 1


def test_plugin_passes_its_own_conformance_tests(plugin_dir):
    # the plugin first, then the sdfcodec under test (a checkout's PYTHONPATH), as the suite sees it
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(p for p in [str(plugin_dir), os.environ.get("PYTHONPATH")] if p))
    r = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-p", "no:dash",
                        str(PLUGIN / "tests")], capture_output=True, text=True, env=env, timeout=300, cwd=PLUGIN)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "35 passed" in r.stdout  # 2 codecs x 17 named conformance checks, and the DCT test
