"""A first search says what it is doing (issue 44, item 1): building and calibrating the query is announced on
stderr once, with where it is cached; the summary is one line (selected blocks, code bytes read, time, end-to-end
blocks/s), the details come with --verbose; a second search builds nothing."""

from __future__ import annotations

import json

import pytest
from typer.testing import CliRunner

import sdfcodec
from sdfcodec import pretrained_codec
from sdfcodec.cli import app
from sdfcodec.core.sdf import Plane, sample_volume
from sdfcodec.search.cache import announce_builds, cache_key, cached_threshold, clear_memory_cache

VS, TRUNC = 0.02, (-0.04, 0.1)


@pytest.fixture(scope="module")
def floor_map(tmp_path_factory):
    path = tmp_path_factory.mktemp("first") / "floor.sdfz"
    vol = sample_volume(Plane((0, 0, 1), 0.3), (48, 48, 48), VS, truncation=TRUNC)
    with sdfcodec.create_map(path, codec=pretrained_codec("pca", 64), voxel_size=VS, truncation=TRUNC) as w:
        w.write_volume(vol)
    return path


def test_announce_builds_tells_only_of_work_not_cached(tmp_path, monkeypatch):
    monkeypatch.setenv("SDFCODEC_CACHE_DIR", str(tmp_path))
    clear_memory_cache()
    heard: list[str] = []
    key = cache_key("threshold", test="announce")
    with announce_builds(heard.append):
        assert cached_threshold(key, lambda: (1.5, {}), what="calibrating x") == (1.5, {})
        assert cached_threshold(key, lambda: (9.0, {}), what="calibrating x") == (1.5, {})  # cached: not told
    clear_memory_cache()
    assert cached_threshold(key, lambda: (9.0, {}), what="calibrating x") == (1.5, {})  # from disk, no listener
    assert heard == ["calibrating x"]


def test_first_search_says_what_it_builds_and_prints_one_line(floor_map, tmp_path, monkeypatch):
    cache = tmp_path / "cache"
    monkeypatch.setenv("SDFCODEC_CACHE_DIR", str(cache))
    clear_memory_cache()
    r = CliRunner().invoke(app, ["search", str(floor_map), "--query", "floor"])
    assert r.exit_code == 0, r.output
    lines = r.stdout.splitlines()
    assert len(lines) == 1, lines
    assert lines[0].startswith("selected ") and "of codes read" in lines[0] and "blocks/s end to end" in lines[0]
    told = [line for line in r.stderr.splitlines() if "(once; cached in" in line]
    assert any(line.startswith("building the floor query for pca-64") for line in told), r.stderr
    assert any(line.startswith("calibrating the floor threshold for pca-64") for line in told), r.stderr
    assert all(str(cache) in line for line in told)
    # the same figures as --json, and the cache is what a second search uses: nothing is built again
    clear_memory_cache()
    again = CliRunner().invoke(app, ["search", str(floor_map), "--query", "floor", "--verbose"])
    assert again.exit_code == 0 and "(once;" not in again.stderr
    assert "building and calibrating the query included" in lines[0]
    assert "building and calibrating" not in again.stdout  # nothing was built the second time
    detail = again.stdout.splitlines()
    assert len(detail) > 2 and detail[-1].split(", in ")[0] == lines[0].split(", in ")[0]
    assert any(line.startswith("behind=") for line in detail) and any("threshold" in line for line in detail[:-1])
    s = json.loads(CliRunner().invoke(app, ["search", str(floor_map), "--query", "floor", "--json"]).stdout)
    assert lines[0].startswith(f"selected {s['selected']} of {s['coded_blocks']} coded blocks")


def test_bad_input_is_one_line_before_any_build(floor_map, tmp_path, monkeypatch):
    """A bad --level or an --out through a file is refused before the query is built: one line, no notes."""
    monkeypatch.setenv("SDFCODEC_CACHE_DIR", str(tmp_path / "cold"))
    clear_memory_cache()
    (tmp_path / "afile").write_text("x")
    for args, says in ((["--level", "65"], "1..64"), (["--out", str(tmp_path / "afile" / "sub")], "Not a directory")):
        r = CliRunner().invoke(app, ["search", str(floor_map), *args])
        assert r.exit_code == 1 and r.stderr.startswith("error: ") and says in r.stderr, r.stderr
        assert r.stderr.count("\n") == 1, r.stderr
    assert not (tmp_path / "cold").exists()  # nothing was built


_ENDS = """
import atexit, sys
from sdfcodec.cli import main

class Teardown:  # a module global: deleted only by Python's teardown of its modules
    def __del__(self):
        sys.stderr.write("teardown ran\\n")

keep = Teardown()
atexit.register(lambda: sys.stderr.write("atexit ran\\n"))
sys.argv = ["sdfcodec", *sys.argv[1:]]
main()
"""


def test_a_search_that_finished_ends_its_process_without_pythons_teardown(floor_map, tmp_path):
    """The command (sdfcodec.cli.main) ends a search that printed its answer and closed its files right away: the
    atexit handlers run (readers' pins, remote sessions), the teardown of its modules does not (0.2-0.9 s of a
    wall search's process on two loaded cores). Its output is whole; a search that fails exits as before."""
    import subprocess
    import sys

    env = {**__import__("os").environ, "SDFCODEC_CACHE_DIR": str(tmp_path / "cache")}
    out = tmp_path / "out"
    r = subprocess.run([sys.executable, "-c", _ENDS, "search", str(floor_map), "--query", "floor", "--json",
                        "--out", str(out)], capture_output=True, text=True, timeout=300, env=env)
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["selected"] > 0
    assert "atexit ran" in r.stderr and "teardown ran" not in r.stderr, r.stderr
    assert (out / "search.png").stat().st_size > 0 and (out / "expanded.ply").read_bytes().startswith(b"ply")
    bad = subprocess.run([sys.executable, "-c", _ENDS, "search", str(tmp_path / "none.sdfz")], capture_output=True,
                         text=True, timeout=300, env=env)
    assert bad.returncode == 1 and bad.stderr.startswith("error: ")
    assert "atexit ran" in bad.stderr and "teardown ran" in bad.stderr, bad.stderr
