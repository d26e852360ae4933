"""int8 code storage (map extension ``int8-codes``, spec section 4a): the quantiser's error bound, maps that
round-trip through every reader and writer, refusal by readers that lack the extension, verify, and a golden
map written once and decoded forever."""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import numpy as np
import pytest

import sdfcodec
from _golden_maps import check_golden_map
from sdfcodec import errors
from sdfcodec.core.quantize import dequantize_codes, quantize_codes
from sdfcodec.core.sdf import sample_volume
from sdfcodec.testing import analytic_blocks, analytic_scene
from sdfcodec.map.verify import verify_map

VS, TRUNC = 0.02, (-0.04, 0.1)
GOLDEN = Path(__file__).parent / "golden" / "maps" / "int8-pca-4"


@pytest.fixture(scope="module")
def maps(tmp_path_factory, volume, pca64) -> dict[str, Path]:
    out = {}
    for dtype in ("float32", "int8"):
        out[dtype] = tmp_path_factory.mktemp("maps") / f"{dtype}.sdfz"
        # no integrity manifest: tests below tamper with these maps to test the checks under it
        with sdfcodec.create_map(out[dtype], codec=pca64, voxel_size=VS, truncation=TRUNC, code_dtype=dtype,
                                 manifest=False) as m:
            m.write_volume(volume)
    return out


# -- the quantiser ------------------------------------------------------------------------------------------

@pytest.mark.parametrize("per", ["block", "component"])
def test_quantiser_error_is_within_half_a_step(per, rng):
    z = rng.standard_normal((300, 48)) * np.logspace(1, -3, 48)  # decaying, as PCA codes
    z[0] = 2.5  # a constant code vector: scale 0, stored exactly
    q, params = quantize_codes(z, per=per)
    assert q.dtype == np.int8 and np.abs(q.astype(int)).max() <= 127
    back = dequantize_codes(q, params, per=per)
    axis = 1 if per == "block" else 0
    step = (z.max(axis=axis, keepdims=True) - z.min(axis=axis, keepdims=True)) / 254  # independent of params
    assert np.all(np.abs(back - z) <= step / 2 * (1 + 1e-5) + 1e-6 * np.abs(z))
    if per == "block":
        assert back[0].tolist() == [2.5] * 48
        # the extremes of every block land on +-127
        assert (np.abs(q[1:].astype(int)).max(axis=1) == 127).all()


def test_quantiser_refuses_bad_input():
    with pytest.raises(errors.InvalidValueError, match="NaN"):
        quantize_codes(np.array([[0.0, np.nan]]))
    with pytest.raises(errors.InvalidValueError, match="per must be"):
        quantize_codes(np.zeros((2, 3)), per="chunk")
    with pytest.raises(errors.ShapeError, match=r"\(N, k\)"):
        quantize_codes(np.zeros(3))


# -- maps ---------------------------------------------------------------------------------------------------

def test_int8_map_round_trips_within_the_quantisation_bound(maps, volume, pca64):
    m8, m32 = sdfcodec.open_map(maps["int8"]), sdfcodec.open_map(maps["float32"])
    assert m8.header.codes.dtype == "int8"
    assert [e.model_dump() for e in m8.header.extensions] == [{"name": "int8-codes", "required": True}]
    c8, z8 = m8.read_codes()
    c32, z32 = m32.read_codes()
    assert np.array_equal(c8, c32)
    step = (z32.max(axis=1) - z32.min(axis=1)) / 254
    assert np.all(np.abs(z8 - z32).max(axis=1) <= step / 2 * (1 + 1e-5) + 1e-6)
    # decoded: the extra error is small against the codec's own
    d8, d32 = m8.decode_region(), m32.decode_region()
    extra, own = np.sqrt(np.mean((d8 - d32) ** 2)), np.sqrt(np.mean((d32 - volume) ** 2))
    assert 0 < extra < 0.2 * own
    # every reader goes through the same dequantisation
    blocks = dict((tuple(c), b) for cs, bs in m8.iter_decoded(batch_blocks=5) for c, b in zip(cs, bs))
    assert len(blocks) == len(c8)
    # the reader truncates decoded distances to [d_min, d_max] (a TSDF holds no others)
    ref = np.clip(pca64.decode(z8) * (TRUNC[1] - TRUNC[0]) + TRUNC[0], *TRUNC)
    for c, r in zip(c8, ref):
        np.testing.assert_allclose(blocks[tuple(c)], r, atol=1e-5)
    # a prefix level dequantises alone (the per-block scale covers every element)
    _, z8_16 = m8.read_codes(level=32)
    np.testing.assert_array_equal(z8_16, z8[:, :32])
    # a quarter of float32's code bytes, plus 8 bytes of offset and scale per block
    info8, info32 = m8.info(), m32.info()
    assert info8["code_bytes_raw"] == len(c8) * (64 + 8)
    without_state = [i["bytes_on_disk"] - i["codec_state_bytes"] for i in (info8, info32)]
    assert without_state[0] < 0.5 * without_state[1]


def test_int8_map_verifies_and_names_a_broken_scale(maps, tmp_path):
    rep = verify_map(maps["int8"])
    assert rep.ok, rep.problems
    assert rep.chunks_checked.get("code_scale", 0) >= 1
    broken = tmp_path / "broken.sdfz"
    shutil.copytree(maps["int8"], broken)
    chunk = next(p for p in sorted((broken / "code_scale" / "c").rglob("*")) if p.is_file())
    chunk.unlink()
    rep = verify_map(broken)
    assert not rep.ok and any(p.where.startswith("code_scale/") and "missing" in p.message for p in rep.problems)


def test_scale_rows_holding_nan_are_refused_naming_a_block(maps, tmp_path):
    import zarr

    bad = tmp_path / "nan.sdfz"
    shutil.copytree(maps["int8"], bad)
    m = sdfcodec.open_map(bad)
    coords, _ = m.read_codes()
    m.close()
    arr = zarr.open_array(str(bad / "code_scale"), mode="r+")
    arr[tuple(coords[0])] = [np.nan, 1.0]
    with pytest.raises(errors.FormatError, match=re.escape(f"block {tuple(int(v) for v in coords[0])}")):
        sdfcodec.open_map(bad).decode_region()


def _edit_header(path: Path, fn) -> None:
    meta = path / "zarr.json"
    doc = json.loads(meta.read_text())
    fn(doc["attributes"]["sdfcodec"])
    meta.write_text(json.dumps(doc))


def test_readers_without_the_extension_refuse_int8_maps(maps, tmp_path, monkeypatch):
    import sdfcodec.core.header as header

    # a reader that does not implement int8-codes (as sdfcodec 0.1) refuses by the extension, naming it
    monkeypatch.setattr(header, "KNOWN_EXTENSIONS", frozenset({"fusion-weights"}))
    with pytest.raises(errors.VersionError, match="extension 'int8-codes'"):
        sdfcodec.open_map(maps["int8"])
    monkeypatch.undo()
    # int8 codes without the extension (or with it optional) is an invalid header, not a guess
    for edit in (lambda h: h.update(extensions=[]),
                 lambda h: h.update(extensions=[{"name": "int8-codes", "required": False}])):
        p = tmp_path / f"edited-{len(list(tmp_path.iterdir()))}.sdfz"
        shutil.copytree(maps["int8"], p)
        _edit_header(p, edit)
        with pytest.raises(errors.FormatError, match="int8"):
            sdfcodec.open_map(p)
    # and a map whose code_scale array is gone is incomplete
    p = tmp_path / "no-scale.sdfz"
    shutil.copytree(maps["int8"], p)
    shutil.rmtree(p / "code_scale")
    with pytest.raises(errors.FormatError, match="lacks array 'code_scale'"):
        sdfcodec.open_map(p)


def test_update_and_dask_writers_keep_int8(maps, tmp_path, volume, pca64):
    import dask.array as da

    p = tmp_path / "upd.sdfz"
    shutil.copytree(maps["int8"], p)
    before = sdfcodec.open_map(p).decode_region()
    far = np.array(volume[:32, :32, :32])
    with sdfcodec.update_map(p) as m:
        m.write_volume(far, offset=(96, 0, 0))  # grows the grid: code_scale grows with codes
    m = sdfcodec.open_map(p)
    assert m.header.codes.dtype == "int8" and verify_map(p).ok
    after = m.decode_region()
    np.testing.assert_allclose(after[:90, :70, :45], before, atol=1e-6)  # batched products round differently
    ref = sdfcodec.open_map(maps["int8"]).decode_region()[:32, :32, :32]
    np.testing.assert_allclose(after[96:128, :32, :32], ref, atol=1e-5)
    # the dask encoder writes the same int8 map as the single-process writer
    q = tmp_path / "dask.sdfz"
    with sdfcodec.create_map(q, codec=pca64, voxel_size=VS, truncation=TRUNC, code_dtype="int8") as m:
        m.write_volume(da.from_array(volume, chunks=(64, 64, 45)))
    a, b = sdfcodec.open_map(q), sdfcodec.open_map(maps["int8"])
    (ca, za), (cb, zb) = a.read_codes(), b.read_codes()
    assert np.array_equal(ca, cb)
    step = (zb.max(axis=1) - zb.min(axis=1)) / 254
    assert np.all(np.abs(za - zb).max(axis=1) <= step + 1e-6)  # one step apart at most (float32 rounding of codes)


def _golden_map(path: Path) -> np.ndarray:
    codec = sdfcodec.get_codec("pca", code_size=4).fit(analytic_blocks(64, seed=5))
    vol = sample_volume(analytic_scene(), (40, 24, 20), VS, truncation=TRUNC)
    with sdfcodec.create_map(path, codec=codec, voxel_size=VS, truncation=TRUNC, code_dtype="int8",
                             chunk_blocks=2, tool="tests/test_int8_codes.py golden") as m:
        m.write_volume(vol)
    return vol


def test_golden_int8_map_decodes_forever(regen_golden, tmp_path):
    """A small int8 map written once (regenerate only with --regen-golden, for a format change): today's reader
    must open it, verify it and decode it to the frozen values."""
    m = check_golden_map(GOLDEN, _golden_map, regen_golden)
    assert m.header.codes.dtype == "int8"
