"""Light commands start light: ``sdfcodec --help``, ``codecs``, ``info`` and ``verify --decode-blocks 0`` run
without importing torch, open3d, rerun, dask, matplotlib, scikit-learn or scipy (issue 19, item 4).

Each check runs in a fresh interpreter (a subprocess): this test process has long imported torch. The map is
written here, with the shipped pca model's state embedded, so that ``info`` takes its longest path (it looks
for the shipped model whose digest the stored state has, which loads the pca plugin and its model file)."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import textwrap

import numpy as np
import pytest

HEAVY = ("torch", "open3d", "rerun", "dask", "distributed", "matplotlib", "sklearn", "scipy", "pandas")


@pytest.fixture(scope="module")
def small_map(tmp_path_factory):
    """A 3 x 2 x 2-block pca-32 map with the shipped model's state embedded: 10 coded blocks, 1 empty, 1
    never written (unobserved)."""
    import sdfcodec
    from sdfcodec.testing import analytic_blocks

    codec = sdfcodec.pretrained_codec("pca", 32)
    path = tmp_path_factory.mktemp("light") / "small.sdfz"
    coords = np.stack(np.unravel_index(np.arange(10), (3, 2, 2)), axis=1)
    with sdfcodec.create_map(path, codec=codec, voxel_size=0.02) as m:
        m.write_codes(coords, np.asarray(codec.encode(analytic_blocks(10, seed=5))))
        m.mark_empty([[2, 1, 0]])
    return path


def _fresh(code: str, *args: str) -> dict:
    """Run ``code`` in a fresh interpreter; it ends by printing the heavy modules it imported as JSON."""
    tail = f"\nimport json, sys\nprint(json.dumps(sorted({{m.split('.')[0] for m in sys.modules}} & set({HEAVY!r}))))"
    r = subprocess.run([sys.executable, "-c", textwrap.dedent(code) + tail, *args], capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 0, r.stderr
    lines = r.stdout.strip().splitlines()
    return {"heavy": json.loads(lines[-1]), "stdout": "\n".join(lines[:-1])}


def test_info_and_codecs_import_nothing_heavy(small_map):
    """The library calls behind ``info`` and ``codecs``: the map's summary (with the shipped-model lookup of its
    embedded state), every installed codec class loaded, its attributes read, and every shipped model's state
    loaded (what that lookup does for a map of any codec)."""
    r = _fresh("""
        import json, sys
        import sdfcodec
        from sdfcodec.registry import get_codec_class
        m = sdfcodec.open_map(sys.argv[1])
        info = m.info()
        classes = {e.id: get_codec_class(e.id) for e in sdfcodec.list_codecs()}
        shipped = {}
        for cid, cls in classes.items():  # info's lookup of a stored state among the shipped models, every codec
            for name, sizes in sorted((cls.shipped_models() or {}).items()):
                shipped[name] = len(cls.shipped_state(name, max(sizes)))
        print(json.dumps({"blocks": info["blocks"], "shape": info["shape_voxels"], "warning": info["state_warning"],
                          "pca": [classes["pca"].prefix_ordered, list(classes["pca"].code_sizes)[:1]],
                          "ids": sorted(classes), "shipped": shipped}))
    """, str(small_map))
    assert r["heavy"] == [], f"importing sdfcodec and reading a map's info imported {r['heavy']}"
    out = json.loads(r["stdout"])
    assert out["blocks"] == {"unobserved": 1, "empty": 1, "coded": 10}  # 12 blocks in the grid
    assert out["shape"] == [48, 32, 32]
    assert "pca-128" in out["warning"]  # the lookup of the shipped model really ran (and found it)
    assert {"pca", "ae", "raw", "parallel", "sequential"} <= set(out["ids"]) and out["pca"][0] is True
    assert {"pca-128", "ae-64", "parallel-64-64", "sequential-64-64"} <= set(out["shipped"])  # states loaded


COMMANDS = [["--help"], ["codecs", "--json"], ["info", "{map}", "--json"],
            ["verify", "{map}", "--decode-blocks", "0", "--json"]]


def _run_commands(argvs: list[list[str]], stream: str) -> list[dict]:
    """Run the command lines ``argvs`` one after the other in one fresh interpreter: for each, its exit status
    (``code``, None for a normal return), the heavy modules loaded by then and what it wrote to ``stream``
    (``out``: "stdout" or "stderr")."""
    r = _fresh(f"""
        import contextlib, io, json, sys
        from sdfcodec.cli import app
        heavy = set({HEAVY!r})
        runs = []
        for argv in json.loads(sys.argv[1]):
            buf, code = io.StringIO(), None
            with contextlib.redirect_{stream}(buf):
                try:
                    app(argv)
                except SystemExit as e:
                    code = e.code
            runs.append({{"argv": argv, "code": code, "out": buf.getvalue(),
                          "heavy": sorted({{m.split('.')[0] for m in sys.modules}} & heavy)}})
        print(json.dumps(runs))
    """, json.dumps(argvs))
    return json.loads(r["stdout"])


def test_cli_light_commands_import_nothing_heavy(small_map):
    """The commands themselves, one after the other in one fresh interpreter (each checked right after it ran)."""
    runs = _run_commands([[a.format(map=small_map) for a in argv] for argv in COMMANDS], "stdout")
    assert [x["argv"][0] for x in runs] == ["--help", "codecs", "info", "verify"]
    for x in runs:
        assert not x["code"], f"sdfcodec {' '.join(x['argv'])}: exit status {x['code']}"
        assert x["heavy"] == [], f"sdfcodec {' '.join(x['argv'])} imported {x['heavy']}"
    assert "info" in runs[0]["out"] and "bench" in runs[0]["out"]  # the help lists the commands
    assert {row["id"]: row["status"] for row in json.loads(runs[1]["out"])}["ae"] == "ok"
    info = json.loads(runs[2]["out"])
    assert info["code_size"] == 32 and info["blocks"]["coded"] == 10 and info["voxel_size"] == 0.02
    rep = json.loads(runs[3]["out"])
    assert rep["ok"] and rep["decoded_blocks"] == 0 and rep["blocks"]["coded"] == 10


def test_lazy_module_stand_in():
    from sdfcodec.plugin import is_tensor, lazy_module

    assert lazy_module("json") is sys.modules["json"]  # already imported: the module itself
    sys.modules.pop("colorsys", None)
    cs = lazy_module("colorsys")
    assert "colorsys" not in sys.modules and "not loaded" in repr(cs)
    assert cs.rgb_to_hsv(1.0, 0.0, 0.0) == (0.0, 1.0, 1.0) and "colorsys" in sys.modules
    import torch

    assert is_tensor(torch.zeros(2)) and not is_tensor(np.zeros(2))


def test_ctrl_c_during_a_lazy_import_is_raised_after_it(tmp_path):
    """A module imported on first use whose import swallows a KeyboardInterrupt raised inside it (as torch's does:
    a Ctrl-C 0.12-0.3 s into ``import torch`` was lost 2 times in 8) still interrupts: the SIGINT is held to the
    end of the import and raised there. Without that hold this child prints "imported" and exits 0."""
    (tmp_path / "swallower.py").write_text(textwrap.dedent("""
        import os, signal, time
        try:  # a SIGINT while this module loads, and a handler in it that catches everything
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(0.5)
        except BaseException:
            pass
        VALUE = 1
    """))
    code = textwrap.dedent(f"""
        import sys
        sys.path.insert(0, {str(tmp_path)!r})
        from sdfcodec.core._lazy import lazy_module
        mod = lazy_module("swallower")
        try:
            mod.VALUE
        except KeyboardInterrupt:
            print("interrupted", "swallower" in sys.modules)
        else:
            print("imported")
    """)
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0 and r.stdout.split() == ["interrupted", "True"], (r.stdout, r.stderr)


@pytest.mark.parametrize("given, numpy_first", [(None, False), ("9", False), (None, True)])
def test_the_command_line_quiets_openblas_spinning_before_numpy_loads(given, numpy_first):
    """OpenBLAS reads ``OPENBLAS_THREAD_TIMEOUT`` once, when numpy loads: importing the command line sets it to 4
    (its threads sleep after a product instead of spinning on the cores torch needs next) before anything
    imports numpy, keeps a value the user set, and sets none when numpy had loaded already (too late to act)."""
    code = textwrap.dedent(f"""
        import os, sys
        if {numpy_first}:
            import numpy
        seen = []

        class Watch:  # notes the variable at the moment numpy is first imported
            def find_spec(self, name, path=None, target=None):
                if name == "numpy" and not seen:
                    seen.append(os.environ.get("OPENBLAS_THREAD_TIMEOUT"))
                return None

        sys.meta_path.insert(0, Watch())
        import sdfcodec.cli
        print(seen, os.environ.get("OPENBLAS_THREAD_TIMEOUT"))
    """)
    env = {k: v for k, v in os.environ.items() if k != "OPENBLAS_THREAD_TIMEOUT"}
    if given is not None:
        env["OPENBLAS_THREAD_TIMEOUT"] = given
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120)
    assert r.returncode == 0, r.stderr
    want = ["[]", "None"] if numpy_first else [f"['{given or '4'}']", given or "4"]
    assert r.stdout.split() == want, r.stdout


MISTYPED = [["encode", "{npz}", "{out}", "--voxel-size", "0.02", "--truncation", "0.1,-0.04"],
            ["encode", "{npz}", "{out}", "--codec-state", "shared"],
            ["fuse", "{seq}", "{out}", "--truncation", "0.1,-0.04"],
            ["dataset", "{out}", "--synthetic", "10", "--truncation", "-0.04,nan"]]


def test_a_mistyped_flag_is_refused_before_torch_or_open3d_load(tmp_path):
    """encode, fuse and dataset check their flags first: a reversed --truncation was refused only after torch,
    Zarr (and for fuse open3d) had loaded, 3.2-3.5 s on this 2-core machine for one line of error."""
    np.savez(tmp_path / "v.npz", tsdf=np.full((16, 16, 16), 0.1, np.float32))
    (tmp_path / "seq").mkdir()
    argvs = [[a.format(npz=tmp_path / "v.npz", out=tmp_path / "out.sdfz", seq=tmp_path / "seq") for a in argv]
             for argv in MISTYPED]
    runs = _run_commands(argvs, "stderr")
    want = [r"truncation must be d_min,d_max with d_min < d_max .*got \[0\.1, -0\.04\]",
            r"--codec-state must be embedded or reference, got 'shared'",
            r"truncation must be d_min,d_max with d_min < d_max .*got \[0\.1, -0\.04\]",
            r"truncation must be d_min,d_max with d_min < d_max .*got \[-0\.04, nan\]"]
    for argv, run, pattern in zip(MISTYPED, runs, want):
        assert run["code"] == 1 and run["out"].startswith("error: "), (argv, run)
        assert re.search(pattern, " ".join(run["out"].split())), (argv, run["out"])
        assert run["heavy"] == [], f"sdfcodec {' '.join(argv)} imported {run['heavy']} before refusing the flag"
    assert not (tmp_path / "out.sdfz").exists()
