"""Step-quantised int16 codes (map extension ``quantised-codes``, spec section 4b): the quantiser's bound, maps
through every writer and reader, plain Zarr, refusal by readers without the extension, bad input, the rate
model and ``encode --step`` / ``--target-bytes`` (through a subprocess once), and a golden map decoded forever."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

import sdfcodec
from _golden_maps import check_golden_map
from sdfcodec import errors
from sdfcodec.cli import app
from sdfcodec.core.quantize import (QMAX16, check_quantisable, check_step, dequantise_step, fit_rate_model,
                                    quantise_step, step_for_bytes)
from sdfcodec.core.sdf import sample_volume
from sdfcodec.testing import analytic_blocks, analytic_scene
from sdfcodec.map.verify import verify_map

VS, TRUNC = 0.02, (-0.04, 0.1)
STEP = 0.05
GOLDEN = Path(__file__).parent / "golden" / "maps" / "int16-pca-4"


@pytest.fixture(scope="module")
def maps(tmp_path_factory, volume, pca64) -> dict[str, Path]:
    out = {}
    for name, kw in (("float32", {}), ("int16", {"code_dtype": "int16", "code_step": STEP})):
        out[name] = tmp_path_factory.mktemp("maps") / f"{name}.sdfz"
        with sdfcodec.create_map(out[name], codec=pca64, voxel_size=VS, truncation=TRUNC, **kw) as m:
            m.write_volume(volume)
    return out


# -- the quantiser ------------------------------------------------------------------------------------------

def test_step_quantiser_is_within_half_a_step_per_element(rng):
    z = rng.standard_normal((400, 24)) * np.logspace(1, -2, 24)
    step = np.linspace(0.01, 0.3, 24)
    offset = rng.standard_normal(24)
    q = quantise_step(z, step, offset)
    assert q.dtype == np.int16
    np.testing.assert_array_equal(q, np.rint((z - offset) / step))  # numpy's own rounding, independently
    back = dequantise_step(q, step, offset)
    assert back.dtype == np.float32
    assert np.all(np.abs(back - z) <= step / 2 + 1e-6 * (1 + np.abs(z)))
    # a prefix dequantises alone with the first steps
    np.testing.assert_array_equal(dequantise_step(q[:, :8], step, offset), back[:, :8])


def test_step_quantiser_refuses_codes_beyond_int16_naming_the_step():
    z = np.array([[100.0, 0.0]])
    with pytest.raises(errors.InvalidValueError, match=r"code element 0 .* step of at least 0\.00305"):
        quantise_step(z, [0.001, 0.001], [0.0, 0.0])
    q = quantise_step(z, [100.0 / QMAX16, 1.0], [0.0, 0.0])  # exactly at the range: stored
    assert int(q[0, 0]) == QMAX16


@pytest.mark.parametrize("bad", [0, -0.1, float("nan"), float("inf"), [0.1, 0.0, 0.1]])
def test_check_step_refuses_zero_negative_and_nan(bad):
    with pytest.raises(errors.InvalidValueError, match="finite and > 0"):
        check_step(bad, 3)


def test_check_step_shapes():
    np.testing.assert_array_equal(check_step(0.5, 3), [0.5, 0.5, 0.5])
    with pytest.raises(errors.ShapeError, match="one number or 3"):
        check_step([0.1, 0.2], 3)


def test_only_orthonormal_codecs_take_a_step():
    check_quantisable(sdfcodec.get_codec("raw"))
    check_quantisable(sdfcodec.get_codec("pca", code_size=8))
    with pytest.raises(errors.InvalidValueError, match="'ae' cannot store step-quantised"):
        check_quantisable(sdfcodec.get_codec("ae", code_size=8))


def test_rate_model_inverts_measured_bytes(rng):
    import numcodecs

    z = rng.standard_normal((2000, 16)) * np.logspace(0.5, -1.5, 16)
    blosc = numcodecs.Blosc("zstd", 5, numcodecs.Blosc.BITSHUFFLE)
    compress = lambda q: len(blosc.encode(np.ascontiguousarray(q)))  # noqa: E731
    model = fit_rate_model(z, compress)
    byts = [b for _, b in model.points]
    assert byts[0] == max(byts) and model.floor < min(byts)  # the finest step costs most, all zeros least
    for want in (6.0, 12.0, 20.0):
        s = step_for_bytes(model, want)
        got = compress(np.rint(z / s).astype(np.int16)) / len(z)
        assert abs(got - want) < 0.1 * want, (want, s, got)
    with pytest.raises(errors.InvalidValueError, match=r"at least \d"):
        step_for_bytes(model, model.floor * 0.5, 40.0)
    with pytest.raises(errors.InvalidValueError, match="above what int16 codes take"):
        step_for_bytes(model, 1e6)


# -- maps ---------------------------------------------------------------------------------------------------

def test_int16_map_round_trips_within_half_a_step(maps, volume, pca64):
    m16, m32 = sdfcodec.open_map(maps["int16"]), sdfcodec.open_map(maps["float32"])
    h = m16.header
    assert h.codes.dtype == "int16" and h.codes.quantisation.step == [STEP] * 64
    assert [e.model_dump() for e in h.extensions if e.name != "integrity-manifest"] == [
        {"name": "quantised-codes", "required": True}]
    (c16, z16), (c32, z32) = m16.read_codes(), m32.read_codes()
    assert np.array_equal(c16, c32)
    assert np.abs(z16 - z32).max() <= STEP / 2 + 1e-5
    np.testing.assert_allclose(z16, np.rint(z32 / STEP) * STEP, atol=1e-5)
    # prefix levels: a level reads the first elements and dequantises them alone
    _, z16_32 = m16.read_codes(level=32)
    np.testing.assert_array_equal(z16_32, z16[:, :32])
    # the reader truncates decoded distances to [d_min, d_max] (a TSDF holds no others)
    ref = np.clip(pca64.decode(z16) * (TRUNC[1] - TRUNC[0]) + TRUNC[0], *TRUNC)
    blocks = dict((tuple(c), b) for cs, bs in m16.iter_decoded(batch_blocks=7) for c, b in zip(cs, bs))
    for c, r in zip(c16, ref):
        np.testing.assert_allclose(blocks[tuple(c)], r, atol=1e-5)
    extra = np.sqrt(np.mean((m16.decode_region() - m32.decode_region()) ** 2))
    own = np.sqrt(np.mean((m32.decode_region() - volume) ** 2))
    assert 0 < extra < 0.5 * own
    info16, info32 = m16.info(), m32.info()
    assert info16["code_bytes_raw"] == len(c16) * 64 * 2
    assert info16["bytes_on_disk"] - info16["codec_state_bytes"] < 0.7 * (info32["bytes_on_disk"] -
                                                                          info32["codec_state_bytes"])
    assert verify_map(maps["int16"]).ok


def test_plain_zarr_reads_the_integers(maps):
    import zarr

    g = zarr.open_group(str(maps["int16"]), mode="r")
    header = g.attrs["sdfcodec"]
    coded = g["state"][:] == 2
    q = g["codes"][:][coded]
    assert q.dtype == np.int16
    _, z32 = sdfcodec.open_map(maps["float32"]).read_codes()  # blocks in the same (C) order
    np.testing.assert_array_equal(q, np.rint(z32 / STEP))
    step = np.asarray(header["codes"]["quantisation"]["step"])
    offset = np.asarray(header["codes"]["quantisation"]["offset"])
    np.testing.assert_allclose(offset + step * q, z32, atol=STEP / 2 + 1e-6)


def _edit_header(path: Path, fn) -> None:
    meta = path / "zarr.json"
    doc = json.loads(meta.read_text())
    fn(doc["attributes"]["sdfcodec"])
    meta.write_text(json.dumps(doc))


def _codes(h: dict, **kw) -> None:
    h["codes"]["quantisation"].update(kw)


def test_readers_without_the_extension_refuse_and_bad_headers_are_named(maps, tmp_path, monkeypatch):
    import sdfcodec.core.header as header

    # a reader that predates quantised-codes refuses by the extension it does not know, naming it
    monkeypatch.setattr(header, "KNOWN_EXTENSIONS", header.KNOWN_EXTENSIONS - {"quantised-codes"})
    with pytest.raises(errors.VersionError, match="extension 'quantised-codes'"):
        sdfcodec.open_map(maps["int16"])
    monkeypatch.undo()
    edits = {
        "no extension": (lambda h: h.update(extensions=[]), "quantised-codes"),
        "optional": (lambda h: h.update(extensions=[{"name": "quantised-codes", "required": False}]), "quantised"),
        "no quantisation": (lambda h: h["codes"].pop("quantisation"), "quantisation is required"),
        "step 0": (lambda h: _codes(h, step=[0.0] * 64), "greater than 0"),
        "negative step": (lambda h: _codes(h, step=[-0.05] * 64), "greater than 0"),
        "short step": (lambda h: _codes(h, step=[0.05] * 3), "64 steps"),
        "string step": (lambda h: _codes(h, step=["0.05"] * 64), "JSON number"),
        "float32 with a step": (lambda h: h["codes"].update(dtype="float32"), "quantis"),
    }
    for name, (edit, msg) in edits.items():
        p = tmp_path / f"{name.replace(' ', '-')}.sdfz"
        shutil.copytree(maps["int16"], p)
        _edit_header(p, edit)
        with pytest.raises(errors.FormatError, match=msg):
            sdfcodec.open_map(p)
        rep = verify_map(p)  # verify names the step fields too
        assert not rep.ok and rep.problems[0].where == "header", name


def test_create_map_bad_input(tmp_path, pca64):
    kw = dict(codec=pca64, voxel_size=VS, truncation=TRUNC)
    for step, msg in ((0.0, "finite and > 0"), (-1.0, "finite and > 0"), (float("nan"), "finite and > 0"),
                      (None, "need a quantisation step")):
        with pytest.raises(errors.InvalidValueError, match=msg):
            sdfcodec.create_map(tmp_path / "a.sdfz", code_dtype="int16", code_step=step, **kw)
    with pytest.raises(errors.InvalidValueError, match="int16 codes only"):
        sdfcodec.create_map(tmp_path / "a.sdfz", code_step=0.1, **kw)
    assert not any(tmp_path.iterdir())  # nothing left behind


def test_update_and_dask_writers_keep_the_step(maps, tmp_path, volume, pca64):
    import dask.array as da

    p = tmp_path / "upd.sdfz"
    shutil.copytree(maps["int16"], p)
    with sdfcodec.update_map(p) as m:
        m.write_volume(np.array(volume[:32, :32, :32]), offset=(96, 0, 0))
    m = sdfcodec.open_map(p)
    assert m.header.codes.quantisation.step == [STEP] * 64 and verify_map(p).ok
    np.testing.assert_allclose(m.decode_region()[96:128, :32, :32],
                               sdfcodec.open_map(maps["int16"]).decode_region()[:32, :32, :32], atol=1e-5)
    q = tmp_path / "dask.sdfz"
    with sdfcodec.create_map(q, codec=pca64, voxel_size=VS, truncation=TRUNC, code_dtype="int16",
                             code_step=STEP) as m:
        m.write_volume(da.from_array(volume, chunks=(64, 64, 45)))
    (ca, za), (cb, zb) = sdfcodec.open_map(q).read_codes(), sdfcodec.open_map(maps["int16"]).read_codes()
    assert np.array_equal(ca, cb)
    assert np.abs(za - zb).max() <= STEP + 1e-6  # one step apart at most (float32 rounding of batched products)


# -- the command line ---------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def room_file(tmp_path_factory) -> Path:
    vol = sample_volume(analytic_scene(), (160, 128, 64), VS, truncation=TRUNC)
    path = tmp_path_factory.mktemp("cli") / "room.npy"
    np.save(path, vol)
    return path


def test_encode_target_bytes_from_the_command_line(room_file, tmp_path):
    # in process (typer's runner): a fresh interpreter would add only its start-up; the console entry point on a
    # pipe is tests/test_cli_first_hour.py's
    out = tmp_path / "room.sdfz"
    r = CliRunner().invoke(app, ["encode", str(room_file), str(out), "--voxel-size", str(VS), "--target-bytes", "80",
                                 "--code-dtype", "int16", "--json"])
    assert r.exit_code == 0, r.output
    q = json.loads(r.stdout[r.stdout.index("{"):])["quantisation"]
    # independently of the summary: the files of the map, codec state left out, per coded block
    m = sdfcodec.open_map(out)
    files = [f for f in out.rglob("*") if f.is_file() and "codec" not in f.relative_to(out).parts[:1]]
    per_block = sum(f.stat().st_size for f in files) / m.count_states()["coded"]
    assert abs(per_block - 80) <= 0.1 * 80, q
    assert q["bytes_per_coded_block"] == pytest.approx(per_block)
    assert m.header.codes.dtype == "int16" and m.header.codes.quantisation.step == [q["step"]] * 64
    r = CliRunner().invoke(app, ["encode", str(room_file), str(tmp_path / "x.sdfz"), "--voxel-size", str(VS),
                                 "--target-bytes", "3", "--code-dtype", "int16"])
    assert r.exit_code == 1 and "below what this codec can reach on this map: at least" in r.output, r.output
    assert not (tmp_path / "x.sdfz").exists()


def test_encode_step_and_bad_input(room_file, tmp_path):
    runner = CliRunner()
    out = tmp_path / "s.sdfz"
    r = runner.invoke(app, ["encode", str(room_file), str(out), "--voxel-size", str(VS), "--step", "0.1", "--json"])
    assert r.exit_code == 0, r.output
    q = json.loads(r.stdout[r.stdout.index("{"):])["quantisation"]
    assert q["step"] == 0.1 and sdfcodec.open_map(out).header.codes.quantisation.step == [0.1] * 64
    for args, msg in ((["--step", "0"], "finite and > 0"), (["--step", "nan"], "finite and > 0"),
                      (["--step", "-2"], "finite and > 0"), (["--target-bytes", "0"], "finite and > 0"),
                      (["--step", "0.1", "--target-bytes", "50"], "pass one of them"),
                      (["--step", "0.1", "--code-dtype", "int8"], "contradicts"),
                      (["--step", "0.1", "--codec", "ae", "--code-size", "64"], "cannot store step-quantised")):
        r = runner.invoke(app, ["encode", str(room_file), str(tmp_path / "bad.sdfz"), "--voxel-size", str(VS),
                                *args])
        assert r.exit_code == 1 and msg in r.output, (args, r.output)
        assert not (tmp_path / "bad.sdfz").exists()


# -- golden -------------------------------------------------------------------------------------------------

def _golden_map(path: Path) -> None:
    codec = sdfcodec.get_codec("pca", code_size=4).fit(analytic_blocks(64, seed=5))
    vol = sample_volume(analytic_scene(), (40, 24, 20), VS, truncation=TRUNC)
    with sdfcodec.create_map(path, codec=codec, voxel_size=VS, truncation=TRUNC, code_dtype="int16",
                             code_step=[0.02, 0.05, 0.1, 0.2], code_offset=[0.5, 0.0, 0.0, -0.25], chunk_blocks=2,
                             tool="tests/test_quantised_codes.py golden") as m:
        m.write_volume(vol)


def test_golden_int16_map_decodes_forever(regen_golden):
    """A small int16 map written once (regenerate only with --regen-golden, for a format change): today's
    reader must open it, verify it and decode it to the frozen values."""
    m = check_golden_map(GOLDEN, _golden_map, regen_golden)
    q = m.header.codes.quantisation
    assert m.header.codes.dtype == "int16" and q.step == [0.02, 0.05, 0.1, 0.2] and q.offset == [0.5, 0, 0, -0.25]
