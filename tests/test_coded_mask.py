"""The context-coded observation mask and compact documents (issue 42, side information; spec/map-format.md section
6e): the stream round trip, its size against Blosc's, a variable-rate map that stores it, the golden map, and a
map that uses the codec without listing the extension."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import zarr
from numcodecs import Blosc

import sdfcodec
from _fused_maps import fused_like, write_volume_map
from _golden_maps import check_golden_map
from sdfcodec import errors
from sdfcodec.core.blocks import split_blocks
from sdfcodec.map.maskcoder import MASK_ANS_CODEC, decode_mask_rows, encode_mask_rows
from sdfcodec.map.observed import pack_mask
from sdfcodec.registry import pretrained_codec
from sdfcodec.core.sdf import sample_volume
from sdfcodec.testing import analytic_scene

GOLDEN = Path(__file__).parent / "golden" / "maps" / "coded-mask-pca-8"


def _fused_scene(shape=(96, 80, 48)):
    """The analytic scene as fusion leaves it (unobserved deeper than |d_min| behind surfaces): (metres, observed)."""
    vol, obs = fused_like(sample_volume(analytic_scene(), shape, 0.02, truncation=(-0.04, 0.1)))
    assert 0.05 < (~obs).mean() < 0.5  # the scene has unobserved space to code
    return vol, obs


@pytest.fixture(scope="module")
def room():
    return _fused_scene()


def _room_rows(room) -> np.ndarray:
    obs = split_blocks(room[1].astype(np.float32), fill=1.0).reshape(-1, 16, 16, 16) > 0.5
    return pack_mask(obs)


def test_round_trip_is_exact_on_random_and_fused_masks(room):
    rng = np.random.default_rng(0)
    cases = {
        "random": rng.integers(0, 256, (40, 512), dtype=np.uint8),
        "sparse": np.packbits(rng.random((30, 4096)) < 0.02, axis=1),
        "all observed": np.full((8, 512), 255, np.uint8),
        "none observed": np.zeros((5, 512), np.uint8),
        "fused room": _room_rows(room),
    }
    mixed = cases["random"].copy()
    mixed[::3] = 255  # rows observed everywhere between partial ones: the row flags
    cases["mixed"] = mixed
    for name, rows in cases.items():
        stream = encode_mask_rows(rows)
        assert np.array_equal(decode_mask_rows(stream, len(rows)), rows), name


def test_irregular_coherent_mask_codes_well_below_blosc():
    """Masks of real fusion are spatially coherent with irregular borders (where rays stopped), which Blosc's zstd
    on packed bytes cannot follow (the kitchen half: 46.2 against 66.1 B per coded block). A thresholded smooth
    random field is such a mask; an axis-aligned analytic scene is not (zstd wins there on repeated rows)."""
    from scipy.ndimage import gaussian_filter

    field = gaussian_filter(np.random.default_rng(0).standard_normal((100, 16, 16, 16)), (0, 2, 2, 2))
    rows = pack_mask(field > 0.1)
    stream = encode_mask_rows(rows)
    blosc = Blosc("zstd", 9, Blosc.NOSHUFFLE).encode(rows.tobytes())  # what maps without the extension store
    assert len(stream) < 0.8 * len(blosc), (len(stream), len(blosc))
    assert np.array_equal(decode_mask_rows(stream, len(rows)), rows)


def test_a_damaged_stream_is_one_checksum_error():
    rows = np.packbits(np.random.default_rng(1).random((6, 4096)) < 0.5, axis=1)
    stream = bytearray(encode_mask_rows(rows))
    with pytest.raises(errors.ChecksumError, match="mask-ans"):
        decode_mask_rows(bytes(stream[:3]), len(rows))
    stream[2:6] = np.uint32(99).tobytes()  # more partial rows than the chunk has
    with pytest.raises(errors.ChecksumError, match="partial rows"):
        decode_mask_rows(bytes(stream), len(rows))


def _masked_varrate_map(path: Path, room) -> None:
    write_volume_map(path, *room, pretrained_codec("pca", 64), codec_state="reference",
                     variable_rate={"target_bytes": 96.0, "exact_mask": True})


def test_variable_rate_map_stores_the_coded_mask_and_compact_documents(tmp_path, room):
    p = tmp_path / "vr.sdfz"
    _masked_varrate_map(p, room)
    m = sdfcodec.open_map(p)
    assert "coded-observation-mask" in [e.name for e in m.header.extensions]
    meta = json.loads((p / "observed" / "zarr.json").read_text())
    assert [c["name"] for c in meta["codecs"]] == [MASK_ANS_CODEC, "crc32c"]
    # the mask reads back exactly: every block's observed voxels as written
    vol, obs = room
    blocks_obs = split_blocks(obs.astype(np.float32), fill=1.0) > 0.5
    coords = np.argwhere(m.block_states() == 2)
    assert np.array_equal(m.read_observed(coords), blocks_obs[tuple(coords.T)].reshape(-1, 16, 16, 16))
    # unobserved voxels decode to d_max (spec 6b), observed ones to the codes' decode
    dec = m.decode_region()
    assert np.all(dec[~obs[:dec.shape[0], :dec.shape[1], :dec.shape[2]]] == np.float32(m.truncation[1]))
    # every document compact, and plain zarr still reads the header and the code streams
    for doc in p.rglob("zarr.json"):
        assert b"\n" not in doc.read_bytes(), doc
    g = zarr.open_group(p, mode="r")
    assert g.attrs["sdfcodec"]["codes"]["variable_rate"]["coder"]
    assert np.asarray(zarr.open_array(p / "code_streams", mode="r")[:]).any()
    # the block states travel in the header, so neither the empty codes array nor the state array is stored
    # (spec 4e, tests/test_side_docs.py); no array document carries an empty attributes or storage_transformers
    # (optional in Zarr v3)
    assert g.attrs["sdfcodec"]["codes"]["variable_rate"]["states"]
    assert not (p / "codes").exists() and not (p / "state").exists()
    for doc in p.glob("*/zarr.json"):
        meta = json.loads(doc.read_text())
        assert meta.get("attributes", 1) and meta.get("storage_transformers", 1), doc
    from sdfcodec.map.verify import verify_map
    assert verify_map(p).ok
    from typer.testing import CliRunner
    from sdfcodec.cli import app
    out = CliRunner().invoke(app, ["info", str(p)])
    assert out.exit_code == 0 and "context-coded (coded-observation-mask)" in out.output, out.output


def test_the_codec_without_the_extension_is_refused(tmp_path, room):
    p = tmp_path / "vr.sdfz"
    _masked_varrate_map(p, room)
    root = json.loads((p / "zarr.json").read_text())
    h = root["attributes"]["sdfcodec"]
    h["extensions"] = [e for e in h["extensions"] if e["name"] != "coded-observation-mask"]
    (p / "zarr.json").write_text(json.dumps(root))
    with pytest.raises(errors.FormatError, match="coded-observation-mask"):
        sdfcodec.open_map(p)


def test_golden_coded_mask_map(regen_golden):
    vol, obs = _fused_scene((48, 48, 32))  # 18 blocks
    codec = sdfcodec.get_codec("pca", code_size=8).fit(
        split_blocks(vol, fill=0.1).reshape(-1, 16, 16, 16)[:64].astype(np.float32))

    def make(path: Path) -> None:
        write_volume_map(path, vol, obs, codec, variable_rate={"step": 0.2, "exact_mask": True})

    m = check_golden_map(GOLDEN, make, regen_golden)
    assert "coded-observation-mask" in [e.name for e in m.header.extensions]
    coords = np.argwhere(m.block_states() == 2)
    want = split_blocks(obs.astype(np.float32), fill=1.0) > 0.5
    assert np.array_equal(m.read_observed(coords), want[tuple(coords.T)].reshape(-1, 16, 16, 16))
