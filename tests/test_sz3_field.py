"""The sz3 codec and the map extension field-compression (spec/map-format.md section 4c): conformance, the error
bound against the input (an independent expectation: |decoded - original| <= bound on every observed voxel),
the observation mask, plain zarr, refusals (unknown extension, updates, bad bounds), malformed SZ3 streams
(errors, never a crash or a hang) and a golden map decoded forever."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("pysz", reason="the sz3 codec needs pysz (pip install 'sdfcodec[sz3]')")

import sdfcodec  # noqa: E402
from sdfcodec.errors import FormatError, InvalidValueError, SDFCodecError, VersionError  # noqa: E402
from sdfcodec.map.field import chunks_of, field_of, sz3_compress, sz3_decompress  # noqa: E402
from sdfcodec.testing import analytic_blocks, parametrize_codec_checks  # noqa: E402
from sdfcodec.map.verify import verify_map  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _fused_maps import TRUNC, VS, fused_like, write_volume_map  # noqa: E402
R = TRUNC[1] - TRUNC[0]
GOLDEN = Path(__file__).parent / "golden"
BOUND_M = 0.01


@parametrize_codec_checks([sdfcodec.get_codec("sz3", max_error=0.05)], ids=["sz3-0.05"],
                          golden=[GOLDEN / "sz3-0.05"], large_batch=256)
def test_sz3_codec_conformance(codec, check, regen_golden):
    check(codec, regen_golden=regen_golden)


def test_codec_alone_keeps_its_bound_per_block():
    x = analytic_blocks(64, seed=3)
    for e in (0.01, 0.1):
        y = sdfcodec.get_codec("sz3", max_error=e).decode(sdfcodec.get_codec("sz3", max_error=e).encode(x))
        err = np.abs(np.asarray(y, np.float64) - x).max()
        assert err <= e * (1 + 1e-5), (e, err)
        assert err > e / 100  # lossy: it does use the bound
    # a block's code does not depend on its batch
    c = sdfcodec.get_codec("sz3", max_error=0.05)
    np.testing.assert_array_equal(c.encode(x[:1]), c.encode(x)[:1])


def test_field_layout_round_trips():
    a = np.random.default_rng(0).random((2, 3, 1, 4096), dtype=np.float32)
    f = field_of(a)
    assert f.shape == (32, 48, 16)
    np.testing.assert_array_equal(f[16:32, 32:48, 0:16].ravel(), a[1, 2, 0])  # block (1, 2, 0) in C order
    np.testing.assert_array_equal(chunks_of(f), a)


@pytest.fixture(scope="module")
def fused(volume):
    return fused_like(volume)


@pytest.fixture(scope="module")
def sz3_map(tmp_path_factory, fused) -> Path:
    p = tmp_path_factory.mktemp("sz3") / "room.sdfz"
    write_volume_map(p, *fused, sdfcodec.get_codec("sz3", max_error=BOUND_M / R))
    return p


def test_map_keeps_the_bound_on_observed_voxels_and_the_observation(sz3_map, fused, tmp_path):
    vol, observed = fused
    m = sdfcodec.open_map(sz3_map)
    h = m.header
    assert {e.name for e in h.extensions} == {"field-compression", "observation-mask", "integrity-manifest"}
    assert h.codes.field_compression.name == "sz3" and h.codes.chunk_blocks == 8
    dec = m.decode_region()
    err = np.abs(dec - vol)[observed]
    assert err.max() <= BOUND_M * (1 + 1e-5) + 1e-7 and err.max() > BOUND_M / 20
    assert (dec[~observed] == TRUNC[1]).all()  # unobserved voxels decode as unobserved (d_max), not a guess
    # the same blocks through iter_decoded
    for coords, blocks in m.iter_decoded():
        c = coords[0]
        np.testing.assert_array_equal(blocks[0][:min(16, vol.shape[0] - 16 * c[0]), :min(16, vol.shape[1] - 16 * c[1]),
                                                :min(16, vol.shape[2] - 16 * c[2])],
                                      dec[16 * c[0]:16 * c[0] + 16, 16 * c[1]:16 * c[1] + 16, 16 * c[2]:16 * c[2] + 16])
        break
    rep = verify_map(sz3_map)
    assert rep.ok, str(rep)
    # far smaller than the same map stored losslessly
    raw = tmp_path / "raw.sdfz"
    write_volume_map(raw, vol, observed, sdfcodec.get_codec("raw"))
    size = lambda p: sum(f.stat().st_size for f in Path(p).rglob("*") if f.is_file())  # noqa: E731
    assert size(sz3_map) < size(raw) / 4


def test_plain_zarr_reads_all_but_the_sz3_codes(sz3_map):
    """Without sdfcodec, zarr reads the header, the block states and the mask; the codes need the codec
    sdfcodec.sz3 and zarr says so by name."""
    code = f"""
import json, sys, zarr
g = zarr.open_group({str(sz3_map)!r}, mode="r")
h = g.attrs["sdfcodec"]
print(json.dumps({{"ext": [e["name"] for e in h["extensions"]], "coded": int((g["state"][:] == 2).sum()),
                  "mask": list(g["observed"].shape)}}))
try:
    g["codes"][0, 0, 0, :4]
except Exception as e:
    print("ERR", type(e).__name__, e)
assert "sdfcodec" not in sys.modules
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    first, second = out.stdout.splitlines()[:2]
    info = json.loads(first)
    assert "field-compression" in info["ext"] and info["coded"] > 0
    assert second.startswith("ERR") and "sdfcodec.sz3" in second


def test_reader_without_the_extension_refuses_by_name(sz3_map, monkeypatch):
    import sdfcodec.core.header as header

    monkeypatch.setattr(header, "KNOWN_EXTENSIONS", header.KNOWN_EXTENSIONS - {"field-compression"})
    with pytest.raises(VersionError, match="field-compression"):
        sdfcodec.open_map(sz3_map)


def test_update_is_refused_and_leaves_the_map(sz3_map):
    before = sdfcodec.open_map(sz3_map).decode_region()
    with pytest.raises(InvalidValueError, match="cannot be updated in place"):
        sdfcodec.update_map(sz3_map)
    np.testing.assert_array_equal(sdfcodec.open_map(sz3_map).decode_region(), before)


@pytest.mark.parametrize("bad", [0.0, -0.1, float("nan"), 0.9])
def test_bad_bounds_are_refused(tmp_path, bad):
    with pytest.raises(InvalidValueError, match="max_error"):
        sdfcodec.create_map(tmp_path / "x.sdfz", codec=sdfcodec.get_codec("sz3", max_error=bad), voxel_size=VS)
    assert not (tmp_path / "x.sdfz").exists()


def test_cli_max_error(tmp_path, volume):
    from typer.testing import CliRunner

    from sdfcodec.cli import app

    np.save(tmp_path / "v.npy", volume)
    run = CliRunner().invoke(app, ["encode", str(tmp_path / "v.npy"), str(tmp_path / "o.sdfz"), "--voxel-size",
                                   "0.02", "--codec", "sz3", "--max-error", "0.005"])
    assert run.exit_code == 0, run.output
    dec = sdfcodec.open_map(tmp_path / "o.sdfz").decode_region()
    assert np.abs(dec - volume).max() <= 0.005 * (1 + 1e-5) + 1e-7
    # without --codec sz3 the bound is the default pca codec's residual stage (tests/test_error_bounds.py), not SZ3
    run = CliRunner().invoke(app, ["encode", str(tmp_path / "v.npy"), str(tmp_path / "p.sdfz"), "--voxel-size",
                                   "0.02", "--max-error", "0.005"])
    assert run.exit_code == 0, run.output
    p = sdfcodec.open_map(tmp_path / "p.sdfz")
    assert p.header.codec.id == "pca" and p.header.residual.max_error == 0.005
    assert p.header.codes.field_compression is None


FUZZ = r"""
import sys, numpy as np
from sdfcodec.errors import SDFCodecError
from sdfcodec.map.field import sz3_compress, sz3_decompress
rng = np.random.default_rng(int(sys.argv[1]))
x = np.clip(np.sin(np.linspace(0, 60, 24 ** 3)).reshape(24, 24, 24) + 0.5, 0, 1).astype(np.float32)
s = np.frombuffer(sz3_compress(x, 0.01), np.uint8)
errors = ok = 0
for _ in range(int(sys.argv[2])):
    y = s.copy()
    k = rng.integers(0, 4)
    if k == 0:
        for _ in range(rng.integers(1, 5)):
            y[rng.integers(0, len(y))] ^= np.uint8(1 << rng.integers(0, 8))
    elif k == 1:
        y = y[:rng.integers(0, len(y))]
    elif k == 2:
        i = rng.integers(0, len(y)); y[i:i + 8] = rng.integers(0, 256, len(y[i:i + 8]), dtype=np.uint8)
    else:
        y = np.concatenate([y, rng.integers(0, 256, rng.integers(1, 64), dtype=np.uint8)])
    try:
        out = sz3_decompress(y, (24, 24, 24))
        assert out.shape == (24, 24, 24) and np.isfinite(out).all()
        ok += 1
    except SDFCodecError:
        errors += 1
print(errors, ok)
"""


def test_malformed_sz3_streams_are_errors_not_crashes():
    """Mutated, truncated and extended SZ3 streams: each decodes to finite values of the right shape or raises
    an SDFCodecError; the process neither dies (a C-level crash) nor hangs (timeout)."""
    out = subprocess.run([sys.executable, "-c", FUZZ, "7", "400"], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    errors, ok = map(int, out.stdout.split())
    assert errors + ok == 400 and errors > 50


def test_malformed_chunk_in_a_map_is_an_error_naming_it(sz3_map, tmp_path):
    """An SZ3 chunk altered with a valid checksum (the damage the CRC cannot see) is refused naming the chunk."""
    import google_crc32c  # zarr's crc32c implementation

    bad = tmp_path / "bad.sdfz"
    shutil.copytree(sz3_map, bad)
    chunk = next(p for p in (bad / "codes" / "c").rglob("*") if p.is_file())
    data = bytearray(chunk.read_bytes()[:-4])
    rng = np.random.default_rng(5)
    for i in rng.integers(16, len(data), 6):
        data[i] ^= 0xFF
    data = bytes(data[: len(data) // 2])  # and truncated
    chunk.write_bytes(data + np.array([google_crc32c.value(data)], "<u4").tobytes())
    with pytest.raises(SDFCodecError, match="chunk c/0/0/0/0 of array .codes."):
        sdfcodec.open_map(bad).decode_region()
    assert not verify_map(bad).ok


def test_golden_sz3_map_decodes_forever(regen_golden, fused):
    """A small sz3 map written once (regenerate only with --regen-golden, for a format change): today's reader
    opens it, verifies it and decodes it to the frozen values."""
    g = GOLDEN / "maps" / "sz3-field"
    if regen_golden:
        shutil.rmtree(g, ignore_errors=True)
        g.mkdir(parents=True)
        vol, obs = fused
        write_volume_map(g / "map.zarr", vol[:40, :36, :20], obs[:40, :36, :20], sdfcodec.get_codec("sz3", max_error=0.05))
        np.save(g / "decoded.npy", sdfcodec.open_map(g / "map.zarr").decode_region())
    assert (g / "map.zarr" / "zarr.json").is_file(), "golden map missing: run pytest --regen-golden once"
    m = sdfcodec.open_map(g / "map.zarr")
    assert m.header.codes.field_compression.max_error == 0.05
    assert verify_map(g / "map.zarr").ok
    np.testing.assert_array_equal(m.decode_region(), np.load(g / "decoded.npy"))


def test_sz3_functions_refuse_bad_input():
    with pytest.raises(InvalidValueError):
        sz3_compress(np.full((8, 8, 8), np.nan, np.float32), 0.01)
    with pytest.raises(FormatError):
        sz3_decompress(b"not an sz3 stream at all", (8, 8, 8))
    s = sz3_compress(np.zeros((8, 8, 8), np.float32), 0.01)
    with pytest.raises(FormatError, match="holds"):
        sz3_decompress(s, (8, 8, 4))
