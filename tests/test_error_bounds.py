"""The residual stage of block codecs (spec/map-format.md section 6d; ``--max-error`` and ``--sign-exact``): the
bound against the input (an independent numpy check: |decoded - original| <= E on every observed voxel), the signs
at the input's crossing voxels (found here in numpy, not through sdfcodec), the surface metrics, prefix levels,
refusals (unknown extension, bad input, a lost chunk), atomic writes and a golden map decoded forever."""

from __future__ import annotations

import errno
import json
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest

import sdfcodec
from sdfcodec.errors import FormatError, InvalidValueError, VersionError, WriteFailedError
from sdfcodec.core.surface import compare_volumes
from sdfcodec.map.verify import verify_map

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
import reliability_worker as rw  # noqa: E402
from _fused_maps import TRUNC, VS, fused_like, write_volume_map  # noqa: E402
from test_writes import Faults  # noqa: E402

GOLDEN = HERE / "golden" / "maps" / "residual-pca-4"


def _crossing_voxels(vol: np.ndarray, observed: np.ndarray | None) -> np.ndarray:
    """Independent of sdfcodec: voxels of an axis-neighbour pair, both observed, with one value < 0, the other
    >= 0, differing by less than 0.1 m (the crossing definition of docs/surface.md)."""
    obs = np.ones(vol.shape, bool) if observed is None else observed
    out = np.zeros(vol.shape, bool)
    v = vol.astype(np.float64)
    for ax in range(3):
        a = [slice(None)] * 3
        b = [slice(None)] * 3
        a[ax], b[ax] = slice(0, -1), slice(1, None)
        a, b = tuple(a), tuple(b)
        e = ((v[a] < 0) != (v[b] < 0)) & (np.abs(v[a] - v[b]) < 0.1) & obs[a] & obs[b]
        out[a] |= e
        out[b] |= e
    return out


@pytest.fixture(scope="module")
def fused(volume):
    return fused_like(volume)


@pytest.fixture(scope="module")
def maps(run_shared, volume, fused, pca64) -> dict:
    """The analytic room (dense) and the fused-like room, pca-64, at several settings; written once per run
    (conftest.RunShared): tests read them, or change a copy."""
    settings = {"e10": dict(max_error=0.01), "sign": dict(sign_exact=True),
                "e10sign": dict(max_error=0.01, sign_exact=True), "plain": {}}
    rooms = {"exact": (volume, None), "fused": fused}

    def build(d: Path) -> None:
        for name, kw in settings.items():
            for kind, (vol, obs) in rooms.items():
                write_volume_map(d / f"{kind}-{name}.sdfz", vol, obs, pca64, **kw)

    d = run_shared.built("error-bounds-maps", build)
    return {(kind, name): d / f"{kind}-{name}.sdfz" for name in settings for kind in rooms}


@pytest.mark.parametrize("kind", ["exact", "fused"])
@pytest.mark.parametrize("name,bound", [("e10", 0.01), ("e10sign", 0.01)])
def test_max_error_holds_on_every_observed_voxel(maps, volume, fused, kind, name, bound):
    vol, obs = (volume, np.ones(volume.shape, bool)) if kind == "exact" else fused
    m = sdfcodec.open_map(maps[kind, name])
    dec = m.decode_region()
    err = np.abs(dec.astype(np.float64) - vol.astype(np.float64))
    assert err[obs].max() <= bound, err[obs].max()
    assert (dec[~obs] == TRUNC[1]).all()  # unobserved voxels still decode as unobserved
    plain = sdfcodec.open_map(maps[kind, "plain"]).decode_region()
    assert np.abs(plain - vol)[obs].max() > 3 * bound  # the codes alone are far off: the stage does the work
    # the streamed path applies it too: every coded block as decode_region has it
    for coords, blocks in m.iter_decoded():
        for c, b in zip(coords, blocks):
            sl = tuple(slice(16 * x, min(16 * x + 16, n)) for x, n in zip(c, vol.shape))
            np.testing.assert_array_equal(b[tuple(slice(0, s.stop - s.start) for s in sl)], dec[sl])


@pytest.mark.parametrize("kind", ["exact", "fused"])
@pytest.mark.parametrize("name", ["sign", "e10sign"])
def test_sign_exact_keeps_every_crossing_sign_and_the_surface(maps, volume, fused, kind, name):
    vol, obs = (volume, None) if kind == "exact" else fused
    dec = sdfcodec.open_map(maps[kind, name]).decode_region()
    cross = _crossing_voxels(vol, obs)
    assert cross.sum() > 1000
    assert ((dec < 0) == (vol < 0))[cross].all()
    plain = sdfcodec.open_map(maps[kind, "plain"]).decode_region()
    assert not ((plain < 0) == (vol < 0))[cross].all()  # the codes alone lose some
    s = compare_volumes(vol, dec, VS, observed=obs)
    assert s.recall_1 == 1.0  # every original surface point has a decoded one within one voxel
    assert s.chamfer_l1 < VS


def test_prefix_level_decodes_without_the_residual(maps, volume):
    m = sdfcodec.open_map(maps["exact", "e10"])
    full = m.decode_region()
    low = m.decode_region(level=32)
    plain32 = sdfcodec.open_map(maps["exact", "plain"]).decode_region(level=32)
    np.testing.assert_array_equal(low, plain32)  # the same codes, no residual
    assert np.abs(low - volume).max() > 0.01 >= np.abs(full - volume).max()


def test_info_reports_the_stage_and_its_bytes(maps):
    info = sdfcodec.open_map(maps["fused", "e10sign"]).info()
    r = info["residual"]
    assert r["extension"] == "residual-bound" and r["max_error"] == 0.01 and r["sign_exact"] is True
    on_disk = sum(f.stat().st_size for f in (maps["fused", "e10sign"] / "residual").rglob("*") if f.is_file())
    assert r["bytes_on_disk"] == on_disk > 0
    assert r["bytes_per_coded_block"] == pytest.approx(on_disk / info["blocks"]["coded"])
    assert "full level" in r["holds_at"]
    assert sdfcodec.open_map(maps["fused", "plain"]).info()["residual"] is None
    from sdfcodec.map.rate import stored_bytes

    assert stored_bytes(maps["fused", "e10sign"])["residual"] == pytest.approx(r["bytes_per_coded_block"])
    assert verify_map(maps["fused", "e10sign"]).ok


def test_reader_without_the_extension_refuses_by_name(maps, monkeypatch):
    import sdfcodec.core.header as header

    monkeypatch.setattr(header, "KNOWN_EXTENSIONS", header.KNOWN_EXTENSIONS - {"residual-bound"})
    with pytest.raises(VersionError, match="residual-bound"):
        sdfcodec.open_map(maps["exact", "e10"])


def test_lost_residual_chunk_is_an_error_naming_it(maps, tmp_path):
    bad = tmp_path / "bad.sdfz"
    shutil.copytree(maps["exact", "e10"], bad)
    for f in (bad / "residual" / "c").rglob("*"):
        if f.is_file():
            f.unlink()
    with pytest.raises(FormatError, match=r"residual/c/0/0/0/0.*missing"):
        sdfcodec.open_map(bad).decode_region()


@pytest.mark.parametrize("kw,match", [
    (dict(max_error=0.0), "positive number of metres"),
    (dict(max_error=-0.01), "positive number of metres"),
    (dict(max_error=float("nan")), "positive number of metres"),
    (dict(max_error=0.14), "not below the truncation range"),
    (dict(max_error=1e-7), "finer than float32"),
])
def test_bad_bounds_are_refused(tmp_path, pca64, kw, match):
    with pytest.raises(InvalidValueError, match=match):
        sdfcodec.create_map(tmp_path / "x.sdfz", codec=pca64, voxel_size=VS, **kw)
    assert not (tmp_path / "x.sdfz").exists()


@pytest.mark.parametrize("codec,match", [
    (lambda: sdfcodec.get_codec("raw"), "lossless"),
    (lambda: sdfcodec.get_codec("gaussian-blur"), "halo"),
])
def test_codecs_that_cannot_carry_a_residual_are_refused(tmp_path, codec, match):
    with pytest.raises(InvalidValueError, match=match):
        sdfcodec.create_map(tmp_path / "x.sdfz", codec=codec(), voxel_size=VS, sign_exact=True)


def test_codes_and_dask_writes_are_refused(tmp_path, pca64, volume):
    with sdfcodec.create_map(tmp_path / "x.sdfz", codec=pca64, voxel_size=VS, max_error=0.01) as m:
        with pytest.raises(InvalidValueError, match="write blocks or volumes"):
            m.write_codes([[0, 0, 0]], np.zeros((1, 64), np.float32))
        da = pytest.importorskip("dask.array")
        with pytest.raises(InvalidValueError, match="dask"):
            m.write_volume(da.from_array(np.asarray(volume), chunks=32))
        m.write_volume(volume)
    assert np.abs(sdfcodec.open_map(tmp_path / "x.sdfz").decode_region() - volume).max() <= 0.01


def test_quantised_codes_and_updates_keep_the_bound(tmp_path, pca64, volume):
    """int8 and int16 codes: the residual is measured against the dequantised codes a reader decodes; an update
    writes the residual of the blocks it replaces."""
    for kw in (dict(code_dtype="int8"), dict(code_dtype="int16", code_step=0.5)):
        p = tmp_path / f"{kw['code_dtype']}.sdfz"
        with sdfcodec.create_map(p, codec=pca64, voxel_size=VS, max_error=0.005, **kw) as m:
            m.write_volume(volume)
        assert np.abs(sdfcodec.open_map(p).decode_region() - volume).max() <= 0.005
    shifted = np.clip(volume - 0.01, *TRUNC).astype(np.float32)
    with sdfcodec.update_map(p) as m:
        m.write_blocks([[1, 1, 1]], shifted[16:32, 16:32, 16:32][None])
    dec = sdfcodec.open_map(p).decode_region()
    assert np.abs(dec[16:32, 16:32, 16:32] - shifted[16:32, 16:32, 16:32]).max() <= 0.005
    assert sdfcodec.open_map(p).header.residual.max_error == 0.005


def test_failed_write_leaves_the_old_map_readable(tmp_path, pca64, volume, monkeypatch):
    """Every data write of a residual map's replacement failing in turn: WriteFailedError, and the map there is
    byte for byte as before and decodes as before, with nothing hidden left."""
    p, part = tmp_path / "a.sdfz", volume[:48, :48, :32]
    with sdfcodec.create_map(p, codec=pca64, voxel_size=VS, max_error=0.01) as m:
        m.write_volume(part)
    before = rw.snapshot(p)
    with monkeypatch.context() as mp:  # how many data writes a replacement makes
        count = Faults(mp, "write")
        with sdfcodec.create_map(tmp_path / "count.sdfz", codec=pca64, voxel_size=VS, max_error=0.004) as m:
            m.write_volume(part)
    assert count.count > 3
    for k in range(1, count.count + 1):
        with monkeypatch.context() as mp:
            Faults(mp, "write", k, errno.ENOSPC)
            with pytest.raises(WriteFailedError):
                with sdfcodec.create_map(p, codec=pca64, voxel_size=VS, max_error=0.004, overwrite=True) as m:
                    m.write_volume(part)
        after = rw.snapshot(p)
        assert after[0] == before[0] and rw.hidden_left(tmp_path) == [], k
        np.testing.assert_array_equal(after[1], before[1])


def test_cli_encode_and_info(tmp_path, volume):
    from typer.testing import CliRunner

    from sdfcodec.cli import app

    np.save(tmp_path / "v.npy", volume)
    run = CliRunner().invoke(app, ["encode", str(tmp_path / "v.npy"), str(tmp_path / "o.sdfz"), "--voxel-size",
                                   "0.02", "--codec", "pca", "--code-size", "64", "--sign-exact", "--max-error",
                                   "0.01", "--json"])
    assert run.exit_code == 0, run.output
    summary = json.loads(run.stdout)
    assert summary["residual"]["max_error"] == 0.01 and summary["residual"]["sign_exact"]
    dec = sdfcodec.open_map(tmp_path / "o.sdfz").decode_region()
    assert np.abs(dec - volume).max() <= 0.01
    run = CliRunner().invoke(app, ["info", str(tmp_path / "o.sdfz")])
    assert run.exit_code == 0 and "residual-bound" in run.output and "full level" in run.output
    for flags, match in ((["--max-error", "0"], "--max-error must be a positive"),
                         (["--max-error", "0.2"], "not below the truncation range"),
                         (["--codec", "raw", "--sign-exact"], "lossless"),
                         (["--codec", "sz3", "--sign-exact", "--max-error", "0.01"], "field compressor")):
        if "sz3" in flags:
            pytest.importorskip("pysz")
        run = CliRunner().invoke(app, ["encode", str(tmp_path / "v.npy"), str(tmp_path / "x.sdfz"),
                                       "--voxel-size", "0.02", *flags])
        assert run.exit_code == 1 and match in run.output, (flags, run.output)
        assert len(run.output.strip().splitlines()) == 1
        assert not (tmp_path / "x.sdfz").exists()


def test_golden_residual_map_decodes_forever(regen_golden, fused):
    """A small residual map (pca-4, 1 cm and sign-exact, with an observation mask) written once (regenerate only
    with --regen-golden, for a format change): today's reader opens it, verifies it, decodes it to the frozen
    values, and they keep the bound against the input."""
    vol, obs = (a[:40, :36, :20] for a in fused)
    if regen_golden:
        from sdfcodec.testing import analytic_blocks

        shutil.rmtree(GOLDEN, ignore_errors=True)
        GOLDEN.mkdir(parents=True)
        codec = sdfcodec.get_codec("pca", code_size=4).fit(analytic_blocks(200, seed=5))
        write_volume_map(GOLDEN / "map.zarr", vol, obs, codec, max_error=0.01, sign_exact=True)
        np.save(GOLDEN / "decoded.npy", sdfcodec.open_map(GOLDEN / "map.zarr").decode_region())
    assert (GOLDEN / "map.zarr" / "zarr.json").is_file(), "golden map missing: run pytest --regen-golden once"
    m = sdfcodec.open_map(GOLDEN / "map.zarr")
    assert m.header.residual.max_error == 0.01 and m.header.residual.sign_exact
    assert verify_map(GOLDEN / "map.zarr").ok
    dec = m.decode_region()
    np.testing.assert_array_equal(dec, np.load(GOLDEN / "decoded.npy"))
    assert np.abs(dec - vol)[obs].max() <= 0.01
    assert ((dec < 0) == (vol < 0))[_crossing_voxels(vol, obs)].all()


def test_bound_holds_across_devices(maps, volume, pca64, tmp_path):
    """Written on one device, decoded on another: the writer's margin covers the decode's float32 differences."""
    torch = pytest.importorskip("torch")
    if not torch.cuda.is_available():
        pytest.skip("needs CUDA")
    dec = sdfcodec.open_map(maps["exact", "e10sign"]).decode_region(device="cuda").cpu().numpy()
    assert np.abs(dec.astype(np.float64) - volume).max() <= 0.01
    assert ((dec < 0) == (volume < 0))[_crossing_voxels(volume, None)].all()
    p = tmp_path / "gpu.sdfz"
    with sdfcodec.create_map(p, codec=pca64, voxel_size=VS, max_error=0.004, sign_exact=True, device="cuda") as m:
        m.write_volume(volume)
    dec = sdfcodec.open_map(p).decode_region()
    assert np.abs(dec.astype(np.float64) - volume).max() <= 0.004
    assert ((dec < 0) == (volume < 0))[_crossing_voxels(volume, None)].all()


def test_transcoding_a_map_keeps_the_bound(tmp_path, fused, pca64):
    """A lossless fused map transcoded with a residual (Map.write_map: decoded and encoded, never the codes
    copied): the bound holds against the source on its observed voxels, which stay unobserved."""
    vol, obs = (a[:48, :48, :32] for a in fused)
    src = tmp_path / "raw.sdfz"
    write_volume_map(src, vol, obs, sdfcodec.get_codec("raw"))
    with sdfcodec.create_map(tmp_path / "t.sdfz", codec=pca64, voxel_size=VS, max_error=0.005, sign_exact=True) as m:
        m.write_map(sdfcodec.open_map(src))
    t = sdfcodec.open_map(tmp_path / "t.sdfz")
    dec = t.decode_region()
    # the input of the transcode is the source's decode: raw float32 round trips move the analytic room's exact
    # zeros (walls on voxel centres) to +-1e-8, across zero either way
    ref = sdfcodec.open_map(src).decode_region()
    assert np.abs(dec - ref)[obs].max() <= 0.005 and (dec[~obs] == TRUNC[1]).all()
    assert ((dec < 0) == (ref < 0))[_crossing_voxels(ref, obs)].all()
    assert {e.name for e in t.header.extensions} == {"residual-bound", "observation-mask", "integrity-manifest"}
