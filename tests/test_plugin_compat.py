"""Third-party codec plugins keep working and are held to the contract (issue 40, items 3 and 8).

- A codec package written from our earlier docs, which defines ``--regen-golden`` in its own conftest.py, runs
  its tests with sdfcodec's auto-loaded pytest plugin installed (it failed at start with ``option names
  {'--regen-golden'} already added``): a frozen copy under tests/plugin_packages/oldstyle is run by pytest in a
  subprocess, with and without the flag.
- ``check_codec`` catches learned state kept outside ``state_dict`` (on the class: a rebuild in the same process
  shared it and matched).
- A plugin whose decode raises, returns the wrong shape, an integer type or NaN is refused on every decode path
  (the map reader, the public decode, ``verify``, the CLI) with one line naming the codec and its module; an
  int32 decode was accepted before, centimetres off, and an exception ended ``decode`` in a traceback.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

import sdfcodec
from sdfcodec.cli import app
from sdfcodec.errors import PluginError, SDFCodecError
from sdfcodec.testing import analytic_blocks, run_codec_checks

ROOT = Path(__file__).resolve().parents[1]
OLDSTYLE = ROOT / "tests" / "plugin_packages" / "oldstyle"
VS, TRUNC = 0.02, (-0.04, 0.1)


@pytest.mark.parametrize("regen", [False, True], ids=["plain", "regen-golden"])
def test_oldstyle_plugin_package_runs_its_tests(regen):
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), str(ROOT / "plugins"), str(OLDSTYLE)]),
               EXPECT_REGEN_GOLDEN="1" if regen else "0")
    env.pop("PYTEST_ADDOPTS", None)
    # with the flag, only the test that reads it: the package's conformance checks have no golden fixture, the one
    # check the flag changes (sdfcodec.testing), so under it they would repeat the plain run's checks exactly; a
    # clash of the two --regen-golden options would fail at start-up, before any test
    cmd = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-n", "0",
           *(["--regen-golden", "-k", "test_flag_reaches_the_tests"] * regen)]
    r = subprocess.run(cmd, cwd=OLDSTYLE, env=env, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0 and "already added" not in r.stdout + r.stderr, r.stdout[-3000:] + r.stderr[-3000:]
    summary = r"^1 passed, 16 deselected in " if regen else r"^17 passed in "
    assert re.search(summary, r.stdout, re.M) and "failed" not in r.stdout, r.stdout[-2000:]


class _Leaky(sdfcodec.Codec):
    """Learns a scale in ``fit`` but keeps it on the class, outside ``state_dict``: a map of it decodes right in
    the process that wrote it and wrong anywhere else."""

    codec_id = "test-leaky-state"
    code_sizes = (4096,)
    code_size = 4096
    prefix_ordered = False
    requires_fit = True
    _scale = 1.0

    def __init__(self):
        pass

    def _fit(self, blocks):
        self.mean_ = blocks.mean(axis=0).astype(np.float32)
        type(self)._scale = float(blocks.std() + 0.5)

    def state_dict(self):
        return {"mean": self.mean_} if hasattr(self, "mean_") else {}

    def load_state_dict(self, state):
        self.mean_ = np.asarray(state["mean"], np.float32)
        return self

    def _encode(self, b):
        return ((b - torch.from_numpy(self.mean_).to(b.device)) / self._scale).reshape(len(b), -1)

    def _decode(self, c):
        return c.reshape(len(c), 16, 16, 16) * self._scale + torch.from_numpy(self.mean_).to(c.device)


def test_check_codec_catches_state_outside_state_dict():
    sdfcodec.register_codec(_Leaky, replace=True)
    # 32 blocks and a 64-block large batch: the leak shows on any input (the defaults, 256 and 4096, took seconds)
    rep = run_codec_checks(_Leaky(), blocks=analytic_blocks(32, seed=0), large_batch=64)
    failed = {r.name: r.message for r in rep.results if not r.passed}
    assert "state_round_trip" in failed and "outside state_dict" in failed["state_round_trip"], failed


class _Good(sdfcodec.Codec):
    """The block's voxels are its code; the subclasses below break the decode one way each."""

    codec_id = "test-plugin-decode"
    code_sizes = (4096,)
    code_size = 4096
    prefix_ordered = False
    requires_fit = False

    def __init__(self):
        pass

    def _encode(self, b):
        return b.reshape(len(b), 4096).clone()

    def _decode(self, c):
        return c.reshape(len(c), 16, 16, 16).clone()


class _Raises(_Good):
    def _decode(self, c):
        raise KeyError("weights")


class _WrongShape(_Good):
    def _decode(self, c):
        return c.reshape(len(c), 16, 16, 16)[:, :8].clone()


class _Int32(_Good):
    def _decode(self, c):
        return (c.reshape(len(c), 16, 16, 16) * 10).to(torch.int32)


class _NaN(_Good):
    def _decode(self, c):
        out = c.reshape(len(c), 16, 16, 16).clone()
        out[:, 3, 3, 3] = float("nan")
        return out


BROKEN = [(_Raises, r"failed while decoding: KeyError"), (_WrongShape, r"returned shape \(\d+, 8, 16, 16\)"),
          (_Int32, r"returned int32 values"), (_NaN, r"NaN/Inf")]


@pytest.fixture(scope="module")
def plugin_map(tmp_path_factory):
    from sdfcodec.core.sdf import sample_volume
    from sdfcodec.testing import analytic_scene

    path = tmp_path_factory.mktemp("plugin-decode") / "m.sdfz"
    sdfcodec.register_codec(_Good, replace=True)
    v = sample_volume(analytic_scene(), (32, 32, 32), VS, truncation=TRUNC).astype(np.float32)
    with sdfcodec.create_map(path, codec=_Good(), voxel_size=VS, truncation=TRUNC) as m:
        m.write_volume(v)
    return path


@pytest.mark.parametrize("broken", BROKEN, ids=[b[0].__name__.strip("_") for b in BROKEN])
def test_broken_plugin_decode_is_one_line_everywhere(broken, plugin_map, tmp_path):
    from sdfcodec.map.verify import verify_map

    cls, expect = broken
    sdfcodec.register_codec(cls, replace=True)  # the installed plugin now decodes badly
    try:
        with pytest.raises(SDFCodecError, match=expect) as e:
            sdfcodec.open_map(plugin_map).decode_region()
        assert "test-plugin-decode" in str(e.value) and "\n" not in str(e.value)
        with pytest.raises(SDFCodecError, match=expect):
            sum(len(c) for c, _ in sdfcodec.open_map(plugin_map).iter_blocks())
        with pytest.raises(PluginError, match=expect):  # the public decode too
            cls().decode(np.zeros((2, 4096), np.float32) + 0.5)
        rep = verify_map(plugin_map)
        assert not rep.ok and any("test-plugin-decode" in str(p) for p in rep.problems), rep.problems
        out = tmp_path / "d.npy"
        r = CliRunner().invoke(app, ["decode", str(plugin_map), str(out)])
        lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
        assert r.exit_code == 1 and isinstance(r.exception, SystemExit), (r.exception, r.stderr)
        assert len(lines) == 1 and "test-plugin-decode" in lines[0] and "Traceback" not in r.stderr, r.stderr
        assert not out.exists() and not [p for p in os.listdir(tmp_path) if p.startswith(".d.npy")]
    finally:
        sdfcodec.register_codec(_Good, replace=True)
    assert np.isfinite(sdfcodec.open_map(plugin_map).decode_region()).all()  # the good plugin reads it again


def test_float64_decode_is_converted():
    """A plugin decoding to float64 (numpy's default) keeps working: its blocks are converted to float32."""
    class F64(_Good):
        def _decode(self, c):
            return c.reshape(len(c), 16, 16, 16).double()

    x = analytic_blocks(3)
    out = F64().decode(F64().encode(x))
    assert out.dtype == np.float32 and np.array_equal(out, x)
