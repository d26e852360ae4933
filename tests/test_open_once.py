"""What opening a map and its first read do once, or not at all: block states a header holds are taken from it,
not read back through the array built from them; the members the open checks have their metadata read in one
batch, with the errors one by one gave; the pca codec's decode layer is its stored basis, scaled as before."""

from __future__ import annotations

import base64
import json
import shutil
import zlib
from pathlib import Path

import numpy as np
import pytest
import torch
import zarr

import sdfcodec
from sdfcodec import errors
from sdfcodec.map.reader import MapReader
from sdfcodec.map.verify import verify_map

GOLDEN = Path(__file__).parent / "golden" / "maps"


def test_header_states_are_not_read_back_through_the_implied_array(monkeypatch):
    root = GOLDEN / "side-docs-pca-128" / "map.zarr"  # states in the header (spec 4e)
    read = MapReader.read
    paths: list[str] = []

    def counted(self, arr, sel):
        paths.append(arr.path)
        return read(self, arr, sel)

    monkeypatch.setattr(MapReader, "read", counted)
    m = sdfcodec.open_map(root)
    header = m.reader.header
    # the stdlib's decode of the header field (base64 of zlib of the grid's bytes)
    want = np.frombuffer(zlib.decompress(base64.b64decode(header.codes.variable_rate.states)), np.uint8)
    want = want.reshape(tuple(header.grid_blocks))
    blocks = sum(len(c) for c, _ in m.iter_decoded())
    assert blocks == int((want == 2).sum()) > 0
    got = m.block_states()
    assert np.array_equal(got, want)
    got[...] = 0  # the caller's copy: the map's states stay
    assert np.array_equal(m.block_states(), want)
    assert "state" not in paths
    # the implied array itself still holds them, for what reads it through Zarr (verify)
    assert np.array_equal(np.asarray(m.reader.state_array[...]), want)
    m.close()
    with pytest.raises(errors.InvalidValueError, match="closed"):
        m.block_states()


def test_implied_arrays_are_built_only_when_used(monkeypatch):
    """A map whose header holds its states opens and reads without building its implied ``codes`` and ``state``
    arrays (nor checking state chunks it cannot lose); they are built, once, where something reads them, and are
    what a writer would have stored: shapes and chunks from the header, the states those of the stdlib's decode."""
    root = GOLDEN / "side-docs-pca-128" / "map.zarr"
    built: list[int] = []
    build = MapReader.build_implied

    def counted(self):
        built.append(1)
        return build(self)

    monkeypatch.setattr(MapReader, "build_implied", counted)
    with sdfcodec.open_map(root) as m:
        h = m.reader.header
        blocks = sum(len(c) for c, _ in m.iter_decoded())
        m.decode_region()
        assert blocks > 0 and built == []
        want = np.frombuffer(zlib.decompress(base64.b64decode(h.codes.variable_rate.states)), np.uint8)
        codes, state = m.reader.codes_array, m.reader.state_array
        assert built == [1]
        assert codes.shape == (*h.grid_blocks, h.codes.size) and codes.dtype == np.dtype(h.codes.dtype)
        assert codes.chunks == (h.codes.chunk_blocks,) * 3 + (h.codes.chunk_code,)
        assert np.array_equal(np.asarray(state[...]).reshape(-1), want)
        assert m.reader.codes_array is codes and built == [1]
    report = verify_map(root)  # verify reads the state and codes arrays through Zarr: built there
    assert report.ok, report.problems


@pytest.mark.parametrize("name, members", [("int16-pca-4", {"codes", "state"}),
                                           ("pinned-mask-pca-8", {"code_streams", "mask_streams", "codes", "state"}),
                                           ("coded-mask-pca-8", {"code_streams", "observed", "state", "codes"})])
def test_open_reads_the_checked_members_in_one_batch(monkeypatch, name, members):
    getitem = zarr.Group.__getitem__
    asked: list[str] = []

    def counted(self, path):
        asked.append(path)
        return getitem(self, path)

    monkeypatch.setattr(zarr.Group, "__getitem__", counted)
    m = sdfcodec.open_map(GOLDEN / name / "map.zarr")
    assert not members & set(asked), asked  # none of them read one by one
    assert m.decode_region().shape == tuple(m.shape_voxels)


def test_members_read_together_fail_as_one_by_one(tmp_path):
    root = tmp_path / "m.zarr"
    shutil.copytree(GOLDEN / "int16-pca-4" / "map.zarr", root)
    (root / "state" / "zarr.json").write_text("{not json")
    with pytest.raises(errors.FormatError, match="state/zarr.json is not valid map metadata JSON"):
        sdfcodec.open_map(root)
    meta = json.loads((GOLDEN / "int16-pca-4" / "map.zarr" / "state" / "zarr.json").read_bytes())
    (root / "state" / "zarr.json").write_text(json.dumps({**meta, "data_type": "foo"}))
    with pytest.raises(errors.FormatError, match=r"the metadata of 'state' is invalid \(ValueError: No Zarr data"):
        sdfcodec.open_map(root)
    (root / "state" / "zarr.json").write_text(json.dumps({"zarr_format": 3, "node_type": "group"}))
    with pytest.raises(errors.FormatError, match="'state' must be a Zarr array"):
        sdfcodec.open_map(root)
    shutil.rmtree(root / "state")
    with pytest.raises(errors.FormatError, match="map lacks array 'state'"):
        sdfcodec.open_map(root)


def test_pca_decode_layer_is_the_stored_basis_scaled_once():
    codec = sdfcodec.pretrained_codec("pca", 128)
    state = codec.state_dict()
    w, mu = state["components"].astype(np.float64), state["mean"].astype(np.float64)
    scale, offset = 0.1 - -0.04, -0.04  # a map's truncation: normalised -> metres
    bias = (mu * scale + offset).astype(np.float32)
    rows = (w * scale).astype(np.float32)
    codes = torch.zeros((4, 128))
    for i, j in enumerate((0, 1, 77, 127)):
        codes[i, j] = 1.0
    out = codec.decode_affine(torch.cat([torch.zeros((1, 128)), codes]), scale, offset).reshape(5, -1).numpy()
    assert np.array_equal(out[0], bias)  # a zero code: the bias row, exactly
    np.testing.assert_array_equal(out[1:], bias + rows[[0, 1, 77, 127]])  # one float32 sum each
    # the encoder, folded on first use, is still the basis's transpose and the mean's projection
    x = torch.from_numpy(np.random.default_rng(0).standard_normal((3, 16, 16, 16)).astype(np.float32))
    ref = (x.numpy().reshape(3, -1).astype(np.float64) - mu) @ w.T
    np.testing.assert_allclose(codec.encode(x).numpy(), ref, rtol=0, atol=1e-3)
