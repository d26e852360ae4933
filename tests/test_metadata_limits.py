"""Metadata documents bounded by what parsing them allocates, not only by their bytes (issue 40, item 6; spec
section 9a "Untrusted maps: reader limits"): nodes and nesting depth per document, bytes and nodes of a map's
documents together. The peak memory of ``decode`` and ``verify`` on a map whose documents are padded to just
under the 16 MiB cap is measured in a child process (``RUSAGE_CHILDREN`` of a wrapper process, so that nothing
else this test process ran counts)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import sdfcodec
from sdfcodec import errors
from sdfcodec.map.io.metadata_limits import (MAX_MAP_METADATA_NODES, MAX_METADATA_DEPTH, MAX_METADATA_NODES,
                                             metadata_size)
from sdfcodec.map.io.stores import MAX_METADATA_BYTES, check_metadata_document

ROOT = Path(__file__).resolve().parents[1]
VS, TRUNC = 0.02, (-0.04, 0.1)


@pytest.fixture(scope="module")
def small_map(tmp_path_factory) -> Path:
    """A pca-8 map of 3 x 3 x 2 blocks: its metadata documents (root, codes, state, codec and its arrays)."""
    from sdfcodec.core.sdf import sample_volume
    from sdfcodec.testing import analytic_blocks, analytic_scene

    path = tmp_path_factory.mktemp("meta") / "x.sdfz"
    codec = sdfcodec.get_codec("pca", code_size=8).fit(analytic_blocks(200, seed=4))
    vol = sample_volume(analytic_scene(), (48, 48, 32), VS, truncation=TRUNC)
    # no integrity manifest: it would refuse the padded documents first (by their digests); these tests check the
    # parsing bounds under it, which maps written without one rely on
    with sdfcodec.create_map(path, codec=codec, voxel_size=VS, truncation=TRUNC, chunk_blocks=2, manifest=False) as m:
        m.write_volume(vol)
    return path


def _docs(path: Path) -> list[Path]:
    return sorted(path.rglob("zarr.json"))


def _pad(path: Path, fill) -> None:
    """Pad every metadata document of map ``path`` with attribute "pad" = the JSON text ``fill(room)``,
    ``room`` the bytes left under the 16 MiB cap (written as text: building the values takes minutes)."""
    for doc in _docs(path):
        meta = json.loads(doc.read_text())
        meta.setdefault("attributes", {})["pad"] = None
        raw = json.dumps(meta, separators=(",", ":"))
        text = fill(MAX_METADATA_BYTES - len(raw) - 64)
        raw = raw.replace('"pad":null', '"pad":' + text, 1)
        assert len(raw) < MAX_METADATA_BYTES
        doc.write_text(raw)


# -- the measure: nodes and depth from the bytes ------------------------------------------------------------

@pytest.mark.parametrize("doc", [
    {}, [], {"a": 1}, [1, [2, [3, {"b": None}]]], {"s": "a,b:[{\"\\\\", "t": ["x\\", ",", "]"]},
    {"zarr_format": 3, "node_type": "array", "shape": [3, 3, 2, 8], "attributes": {"k": ["", "\"", 1e-300]}},
])
def test_metadata_size_counts_what_the_parser_builds(doc):
    """An upper bound of the values, keys and containers the parser builds (exact, plus one per empty
    container, without whitespace), and the nesting depth, against a count over the parsed document; strings
    with separators and escapes count as one value."""
    def count(v, d=1):  # (nodes, empty containers, depth)
        if isinstance(v, (dict, list)):
            kids = [count(x, d + 1) for x in (v.values() if isinstance(v, dict) else v)]
            keys = len(v) if isinstance(v, dict) else 0
            return (1 + keys + sum(k[0] for k in kids), (not v) + sum(k[1] for k in kids),
                    max([d, *(k[2] for k in kids)]))
        return 1, 0, d - 1

    raw = json.dumps(doc, separators=(",", ":")).encode()
    nodes, empty, depth = count(doc)
    assert metadata_size(raw) == (nodes + empty, depth)


def test_deep_nesting_and_huge_arrays_are_refused_unparsed():
    deep = b"[" * MAX_METADATA_DEPTH + b"]" * MAX_METADATA_DEPTH  # inside the object: one deeper than allowed
    with pytest.raises(errors.FormatError, match=f"codes/zarr.json is nested {MAX_METADATA_DEPTH + 1} deep"):
        check_metadata_document("codes/zarr.json", b'{"a":' + deep + b"}")
    ok = b"[" * (MAX_METADATA_DEPTH - 1) + b"]" * (MAX_METADATA_DEPTH - 1)
    check_metadata_document("codes/zarr.json", b'{"a":' + ok + b"}")
    huge = b'{"a":[' + b"0," * MAX_METADATA_NODES + b"0]}"
    with pytest.raises(errors.FormatError, match=r"zarr.json holds about \d+ JSON values, more than any map"):
        check_metadata_document("zarr.json", huge)
    many_keys = b"{" + b",".join(b'"k%d":{}' % i for i in range(MAX_METADATA_NODES // 2)) + b"}"
    with pytest.raises(errors.FormatError, match="JSON values"):
        check_metadata_document("zarr.json", many_keys)
    # one long string is one value: bounded by the byte cap, not refused here
    check_metadata_document("zarr.json", b'{"a":"' + b"x," * (1 << 20) + b'"}')


def test_a_map_with_deep_or_huge_metadata_is_one_line_error(small_map, tmp_path):
    import shutil

    for name, fill in (("deep", lambda room: json.loads("[" * 200 + "]" * 200)),
                       ("huge", lambda room: [[] for _ in range(MAX_METADATA_NODES)])):
        path = tmp_path / name / "x.sdfz"
        shutil.copytree(small_map, path)
        doc = path / "codes" / "zarr.json"
        meta = json.loads(doc.read_text())
        meta["attributes"] = {"pad": fill(0)}
        doc.write_text(json.dumps(meta))
        with pytest.raises(errors.FormatError, match="codes/zarr.json .*(nested|JSON values)") as ei:
            sdfcodec.open_map(path).decode_region()
        assert "\n" not in str(ei.value)


def test_the_documents_of_a_map_are_bounded_together(small_map, tmp_path):
    """Seven documents each under the per-document limits, over the map's limit together: refused, naming the
    document that passed it; the same map unpadded reads."""
    import shutil

    path = tmp_path / "x.sdfz"
    shutil.copytree(small_map, path)
    per = MAX_MAP_METADATA_NODES // 5
    assert per < MAX_METADATA_NODES and len(_docs(path)) * per > MAX_MAP_METADATA_NODES
    _pad(path, lambda room: "[" + "0," * (per - 200) + "0]")
    with pytest.raises(errors.FormatError, match="the map's metadata documents together hold"):
        sdfcodec.open_map(path).decode_region()
    assert sdfcodec.open_map(small_map).decode_region().shape == (48, 48, 32)


_PEAK = r"""
import resource, subprocess, sys
r = subprocess.run(sys.argv[1:], capture_output=True, text=True)
print(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss * 1024, r.returncode, repr(r.stderr + r.stdout))
"""


def _peak(args: list[str], cwd: Path) -> tuple[int, int, str]:
    """Peak RSS (bytes) of ``python -m sdfcodec ARGS`` run in a fresh child, its exit status and output."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), str(ROOT / "plugins"),
                                                        os.environ.get("PYTHONPATH", "")])}
    r = subprocess.run([sys.executable, "-c", _PEAK, sys.executable, "-m", "sdfcodec", *args], capture_output=True,
                       text=True, timeout=300, env=env, cwd=cwd)
    peak, code, out = r.stdout.strip().split(" ", 2)
    return int(peak), int(code), eval(out)  # noqa: S307 - our own repr() of a string


def test_metadata_just_under_the_byte_cap_keeps_peak_memory_bounded(small_map, tmp_path):
    """Every metadata document padded to just under 16 MiB with empty lists (5.6 million values each): on
    main ``decode`` peaked at 2.33 GB and ``verify`` at 2.95 GB (0.27 GB untampered). Now each is refused
    before it is parsed, in one line, and the peak stays within 150 MB of the untampered map's."""
    import shutil

    bad = tmp_path / "bad.sdfz"
    shutil.copytree(small_map, bad)
    _pad(bad, lambda room: "[" + "[]," * (room // 3 - 1) + "[]]")
    assert len(_docs(bad)) >= 5
    for cmd in (["decode", "{m}", "{out}"], ["verify", "{m}"]):
        base = _peak([a.format(m=small_map, out=tmp_path / "a.npy") for a in cmd], tmp_path)
        got = _peak([a.format(m=bad, out=tmp_path / "b.npy") for a in cmd], tmp_path)
        assert base[1] == 0, base
        assert got[1] != 0 and "Traceback" not in got[2], got
        assert "JSON values" in got[2], got
        assert got[0] <= base[0] + (150 << 20), f"{cmd[0]}: peak {got[0] / 1e9:.2f} GB vs {base[0] / 1e9:.2f} GB"
