"""``sdfcodec info`` reads a local map without Zarr (:func:`sdfcodec.map.summary.local_info`, issue 19 item 4):
its answer is the ordinary reader's (:meth:`sdfcodec.Map.info`) on every frozen map of the format, and wherever
it cannot be sure (links, a damaged or missing state chunk, a pipeline it does not know) it says so (None) and
the command reads the map the ordinary way, with the ordinary errors."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

import sdfcodec
from sdfcodec.cli import app
from sdfcodec.errors import SDFCodecError
from sdfcodec.map.summary import local_info
from sdfcodec.testing import analytic_blocks

GOLDEN_MAPS = sorted((Path(__file__).parent / "golden" / "maps").glob("*/map.zarr"))


@pytest.fixture(scope="module")
def long_map(tmp_path_factory) -> Path:
    """A 70 x 2 x 3-block pca-32 map: its state array has two chunks along x (the writer's are at most 64 blocks),
    the second one partial, with coded, empty and unobserved blocks in both."""
    codec = sdfcodec.pretrained_codec("pca", 32)
    path = tmp_path_factory.mktemp("summary") / "long.sdfz"
    coords = np.array([[0, 0, 0], [5, 1, 2], [63, 1, 1], [64, 0, 0], [69, 1, 2], [66, 0, 1]])
    with sdfcodec.create_map(path, codec=codec, voxel_size=0.05, shape_voxels=(70 * 16, 32, 48)) as m:
        m.write_codes(coords, np.asarray(codec.encode(analytic_blocks(len(coords), seed=7))))
        m.mark_empty([[1, 0, 0], [65, 1, 1]])
    return path


@pytest.mark.parametrize("path", GOLDEN_MAPS, ids=lambda p: p.parent.name)
def test_light_info_is_the_readers_on_every_golden_map(path):
    light = local_info(path)
    assert light is not None, f"{path.parent.name}: the light reader gave up on a map sdfcodec wrote"
    assert light == sdfcodec.open_map(path).info()


def test_light_info_reads_every_state_chunk(long_map):
    light = local_info(long_map)
    assert light == sdfcodec.open_map(long_map).info()
    assert light["blocks"] == {"unobserved": 70 * 6 - 8, "empty": 2, "coded": 6}
    assert light["grid_blocks"] == [70, 2, 3]


def _copy(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst)
    return dst


def test_a_link_inside_the_map_is_not_followed(long_map, tmp_path):
    m = _copy(long_map, tmp_path / "linked.sdfz")
    real = tmp_path / "elsewhere.json"
    os.replace(m / "state" / "zarr.json", real)
    os.symlink(real, m / "state" / "zarr.json")
    assert local_info(m) is None
    r = CliRunner().invoke(app, ["info", str(m)])  # the ordinary reader refuses the link, as before
    assert r.exit_code != 0 and "link" in r.output.lower(), r.output
    r = CliRunner().invoke(app, ["--follow-symlinks", "info", str(m), "--json"])
    assert r.exit_code == 0, r.output
    assert json.loads(r.output)["blocks"]["coded"] == 6


def test_a_damaged_state_chunk_goes_to_the_ordinary_reader(long_map, tmp_path):
    m = _copy(long_map, tmp_path / "damaged.sdfz")
    chunk = m / "state" / "c" / "1" / "0" / "0"
    data = bytearray(chunk.read_bytes())
    data[len(data) // 2] ^= 0xFF
    chunk.write_bytes(bytes(data))
    assert local_info(m) is None  # its CRC32C does not match
    with pytest.raises(SDFCodecError):
        sdfcodec.open_map(m).info()
    r = CliRunner().invoke(app, ["info", str(m)])
    assert r.exit_code != 0 and len(r.output.strip().splitlines()) == 1, r.output


def test_a_tampered_blosc_header_with_a_valid_checksum_is_never_decoded(long_map, tmp_path):
    """A frame whose header claims 1 GiB (a decompression bomb) under a recomputed, matching CRC32C: the light
    reader checks the frame's structure as the guarded store does, before Blosc sees it, and leaves the map to the
    ordinary reader, which refuses it."""
    import google_crc32c

    m = _copy(long_map, tmp_path / "bomb.sdfz")
    chunk = m / "state" / "c" / "0" / "0" / "0"
    frame = bytearray(chunk.read_bytes()[:-4])
    frame[4:8] = (1 << 30).to_bytes(4, "little")  # the uncompressed size the header claims
    chunk.write_bytes(bytes(frame) + google_crc32c.value(bytes(frame)).to_bytes(4, "little"))
    assert local_info(m) is None
    with pytest.raises(SDFCodecError):
        sdfcodec.open_map(m).info()


def test_a_missing_state_chunk_goes_to_the_ordinary_reader(long_map, tmp_path):
    m = _copy(long_map, tmp_path / "missing.sdfz")
    (m / "state" / "c" / "1" / "0" / "0").unlink()
    assert local_info(m) is None  # codes are stored under it: only the ordinary reader can say what is lost
    r = CliRunner().invoke(app, ["info", str(m)])
    assert r.exit_code != 0 and "missing" in r.output, r.output


def test_an_unknown_required_extension_is_refused_alike(long_map, tmp_path):
    m = _copy(long_map, tmp_path / "future.sdfz")
    meta = json.loads((m / "zarr.json").read_text())
    meta["attributes"]["sdfcodec"].setdefault("extensions", []).append({"name": "from-the-future", "required": True})
    (m / "zarr.json").write_text(json.dumps(meta))
    with pytest.raises(SDFCodecError) as light:
        local_info(m)
    with pytest.raises(SDFCodecError) as ordinary:
        sdfcodec.open_map(m)
    assert type(light.value) is type(ordinary.value) and "from-the-future" in str(light.value)


def test_not_a_local_directory_is_not_for_the_light_reader(long_map, tmp_path):
    assert local_info("http://127.0.0.1:9/map.sdfz") is None
    assert local_info(tmp_path / "nothing-here") is None
    (tmp_path / "file.zip").write_bytes(b"PK")
    assert local_info(tmp_path / "file.zip") is None
    os.symlink(long_map, tmp_path / "link.sdfz")
    assert local_info(tmp_path / "link.sdfz") is None


def test_info_command_imports_no_zarr(long_map):
    """The command in a fresh interpreter: it prints the same JSON as the library's Map.info(), without Zarr."""
    code = textwrap.dedent("""
        import contextlib, io, json, sys
        from sdfcodec.cli import app
        buf = io.StringIO()
        with contextlib.redirect_stdout(buf):
            try:
                app(["info", sys.argv[1], "--json"])
            except SystemExit as e:
                assert not e.code, e.code
        print(json.dumps({"zarr": "zarr" in sys.modules, "info": json.loads(buf.getvalue())}))
    """)
    r = subprocess.run([sys.executable, "-c", code, str(long_map)], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout.strip().splitlines()[-1])
    assert out["zarr"] is False
    assert out["info"] == json.loads(json.dumps(sdfcodec.open_map(long_map).info()))
