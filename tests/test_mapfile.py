"""Map format v1: writing, reading, prefix levels, checksums, versions and nothing lost on bad input."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
import zarr

import sdfcodec
from sdfcodec import errors
from sdfcodec.core.header import BlockState
from sdfcodec.testing import analytic_blocks

VS, TRUNC = 0.02, (-0.04, 0.1)


@pytest.fixture(scope="module")
def map_path(tmp_path_factory, volume, pca64) -> Path:
    path = tmp_path_factory.mktemp("maps") / "scene.sdfz"
    # no integrity manifest: tests below edit array metadata to test the checks under it
    with sdfcodec.create_map(path, codec=pca64, voxel_size=VS, truncation=TRUNC, origin=(1.0, -2.0, 0.5),
                             manifest=False) as m:
        m.write_volume(volume)
    return path


def independent_decode(volume: np.ndarray, codec, level: int | None = None) -> np.ndarray:
    """Numpy projection onto the codec's basis, block by block, in float64: the reference decode."""
    w, mu = codec.components_.astype(np.float64), codec.mean_.astype(np.float64)
    k = level or w.shape[0]
    d_min, d_max = TRUNC
    X, Y, Z = volume.shape
    # the spec's padding (section 4): a volume's last blocks repeat its last voxel layer
    pad = np.pad(volume.astype(np.float64), [(0, -(-n // 16) * 16 - n) for n in volume.shape], mode="edge")
    out = np.full_like(pad, d_max)
    for bx in range(pad.shape[0] // 16):
        for by in range(pad.shape[1] // 16):
            for bz in range(pad.shape[2] // 16):
                sl = np.s_[bx * 16:(bx + 1) * 16, by * 16:(by + 1) * 16, bz * 16:(bz + 1) * 16]
                v = (pad[sl].ravel() - d_min) / (d_max - d_min)
                if np.all(v >= 1 - 1e-6):
                    continue  # empty block: stores no code, decodes as free space
                c = (v - mu) @ w.T
                out[sl] = ((c[:k] @ w[:k] + mu) * (d_max - d_min) + d_min).reshape(16, 16, 16)
    return np.clip(out[:X, :Y, :Z], d_min, d_max)  # a decoded TSDF is truncated to [d_min, d_max]


def test_decode_matches_independent_projection(map_path, volume, pca64):
    m = sdfcodec.open_map(map_path)
    assert m.shape_voxels == volume.shape and m.grid_blocks == (6, 5, 3)
    dec = m.decode_region()
    assert dec.shape == volume.shape and dec.dtype == np.float32
    ref = independent_decode(volume, pca64)
    assert np.abs(dec - ref).max() < 2e-5  # float32 precision in metres
    # and the codec really compresses this scene well near the surface
    assert np.sqrt(np.mean((dec - volume) ** 2)) < 0.01


def test_a_volume_that_ends_inside_solid_decodes_solid_to_its_last_layer(tmp_path, pca64):
    """A volume cut inside solid (the slab above a ceiling, 40 voxels: two and a half blocks) holds no surface
    where it ends. Padded with free space, its last blocks held one, and pca-64's smear of it decoded solid voxels
    of the last layers as free space (948 of them, up to +0.016 m where the field is -0.04 m)."""
    from sdfcodec.core.sdf import Plane, sample_volume

    vol = sample_volume(Plane((0.0, 0.0, -1.0), -0.305), (32, 32, 40), VS, truncation=TRUNC)  # solid above 0.305
    with sdfcodec.create_map(tmp_path / "slab.sdfz", codec=pca64, voxel_size=VS, truncation=TRUNC) as m:
        m.write_volume(vol)
    dec = sdfcodec.open_map(tmp_path / "slab.sdfz").decode_region()
    solid = vol < -VS  # more than a voxel inside
    assert solid[:, :, 32:].all()  # the last, partial block is solid through
    assert (dec[solid] < 0).all(), f"{int((dec[solid] >= 0).sum())} solid voxels decode as free space"
    # the last block is as exact as a solid block (2.4 mm measured; 55.6 mm in its last layer with free space)
    assert np.abs(dec - vol)[:, :, 32:].max() < 0.25 * VS


@pytest.mark.parametrize("level", [32, 17])
def test_prefix_level_matches_truncated_projection(map_path, volume, pca64, level):
    m = sdfcodec.open_map(map_path)
    dec = m.decode_region(level=level)
    assert np.abs(dec - independent_decode(volume, pca64, level)).max() < 2e-5
    full_err = np.mean((m.decode_region() - volume) ** 2)
    assert np.mean((dec - volume) ** 2) > full_err  # fewer components, more error


def test_region_in_voxels_and_metres(map_path):
    m = sdfcodec.open_map(map_path)
    full = m.decode_region()
    part = m.decode_region(((10, 40), (3, 70), (20, 21)))
    # decoding fewer blocks per batch may change float32 summation order: equal to rounding, not bitwise
    assert np.allclose(part, full[10:40, 3:70, 20:21], rtol=0, atol=1e-6)
    # metres: voxels whose centres lie in the half-open box [lo, hi), like voxel ranges; origin (1.0, -2.0, 0.5)
    metres = m.decode_region(((1.2, 1.5), (-2.0, -1.9), (0.9, 0.92)), units="m")
    assert np.allclose(metres, full[10:25, 0:5, 20:21], rtol=0, atol=1e-6)
    with pytest.raises(errors.InvalidValueError, match="holds no voxel on axis z"):
        m.decode_region(((1.2, 1.5), (-2.0, -1.9), (0.9, 0.9)), units="m")
    with pytest.raises(errors.InvalidValueError, match="outside the map on axis x"):
        m.decode_region(((0, 91), (0, 1), (0, 1)))
    # numpy's slices, an open end being the map's edge
    assert np.allclose(m.decode_region(np.s_[10:40, 3:70, 20:21]), part, rtol=0, atol=1e-6)
    assert np.allclose(m.decode_region(np.s_[:, 60:, 20:21]), full[:, 60:, 20:21], rtol=0, atol=1e-6)
    assert np.allclose(m.decode_region(np.s_[1.2:1.5, :-1.9, 0.9:0.92], units="m"), metres, rtol=0, atol=1e-6)
    for bad, what in [(np.s_[0:10:2, :, :], "take no step"), (np.s_[0:10, :], "must be"), ("xyz", "must be"),
                      (((0, 1), (0, 1), (0, "2")), "finite numbers"), (((0, 1), (0, 1), (0, 1, 2)), "must be")]:
        with pytest.raises(errors.ShapeError, match=what):
            m.decode_region(bad)


def test_read_codes_and_states(map_path, volume, pca64):
    m = sdfcodec.open_map(map_path)
    coords, codes = m.read_codes()
    states = m.block_states()
    assert states.shape == m.grid_blocks
    assert len(coords) == (states == BlockState.CODED).sum() == m.count_states()["coded"]
    # empty blocks (pure free space) store no code, only their state
    assert m.count_states()["empty"] > 0 and m.count_states()["unobserved"] == 0
    bx, by, bz = coords[0]
    blk = np.full((16, 16, 16), TRUNC[1], np.float32)
    src = volume[bx * 16:bx * 16 + 16, by * 16:by * 16 + 16, bz * 16:bz * 16 + 16]
    blk[: src.shape[0], : src.shape[1], : src.shape[2]] = src
    expect = pca64.encode(((blk - TRUNC[0]) / (TRUNC[1] - TRUNC[0]))[None])[0]
    assert np.allclose(codes[0], expect, atol=1e-4)
    c32, z32 = m.read_codes(level=32)
    assert np.array_equal(c32, coords) and np.array_equal(z32, codes[:, :32])


class CountingStore(zarr.storage.WrapperStore):
    """Records the keys read, to check which chunks a read touches."""

    def __init__(self, store):
        super().__init__(store)
        self.keys: list[str] = []

    async def get(self, key, prototype, byte_range=None):
        self.keys.append(key)
        return await self._store.get(key, prototype, byte_range)


def test_prefix_level_reads_only_its_own_chunks(tmp_path, volume):
    codec = sdfcodec.get_codec("pca", code_size=128).fit(analytic_blocks(800, seed=5))
    path = tmp_path / "m128.sdfz"
    with sdfcodec.create_map(path, codec=codec, voxel_size=VS, truncation=TRUNC) as m:
        m.write_volume(volume)
    assert sdfcodec.open_map(path).header.codes.levels == [32, 64, 96, 128]
    store = CountingStore(zarr.storage.LocalStore(path, read_only=True))
    m = sdfcodec.open_map(store)
    m.read_codes(level=32)
    code_keys = [k for k in store.keys if k.startswith("codes/c/")]
    assert code_keys and all(k.endswith("/0") for k in code_keys), code_keys
    store.keys.clear()
    m.read_codes()
    assert {k.rsplit("/", 1)[1] for k in store.keys if k.startswith("codes/c/")} == {"0", "1", "2", "3"}


def test_plain_zarr_reads_header_and_codes(map_path):
    g = zarr.open_group(str(map_path), mode="r")
    hdr = g.attrs["sdfcodec"]
    assert hdr["format"] == "sdfcodec-map" and hdr["format_version"] == 1
    assert hdr["codec"]["id"] == "pca" and hdr["codes"]["size"] == 64
    codes = g["codes"]
    assert codes.shape == (6, 5, 3, 64) and codes.chunks == (16, 16, 16, 32)  # 512 KiB chunks (2 MiB at most)
    coded = np.asarray(g["state"][:]) == 2
    assert np.abs(np.asarray(codes[:])[coded]).sum() > 0
    names = [type(c).__name__ for c in codes.metadata.codecs]
    assert "BloscCodec" in names and "Crc32cCodec" in names


def test_float16_codes(tmp_path, volume, pca64, map_path):
    path = tmp_path / "f16.sdfz"
    with sdfcodec.create_map(path, codec=pca64, voxel_size=VS, truncation=TRUNC, origin=(1.0, -2.0, 0.5),
                             code_dtype="float16") as m:
        m.write_volume(volume)
    m16 = sdfcodec.open_map(path)
    assert str(m16.reader.codes_array.dtype) == "float16"
    d16, d32 = m16.decode_region(), sdfcodec.open_map(map_path).decode_region()
    # float16 keeps ~3 significant digits of each code: the extra error is small against the codec's own
    extra = np.sqrt(np.mean((d16 - d32) ** 2))
    own = np.sqrt(np.mean((d32 - volume) ** 2))
    assert 0 < extra < 0.1 * own


def test_write_blocks_grows_map_and_round_trips(tmp_path):
    raw = sdfcodec.get_codec("raw")
    rng = np.random.default_rng(0)
    blocks = rng.uniform(*TRUNC, size=(5, 16, 16, 16)).astype(np.float32)
    coords = np.array([[0, 0, 0], [3, 1, 2], [9, 0, 0], [1, 1, 1], [0, 4, 0]])
    path = tmp_path / "raw.sdfz"
    with sdfcodec.create_map(path, codec=raw, voxel_size=VS, truncation=TRUNC) as m:
        m.write_blocks(coords[:3], blocks[:3])
        m.write_blocks(coords[3:], blocks[3:])
        m.mark_empty([[2, 2, 2]])
    m = sdfcodec.open_map(path)
    assert m.grid_blocks == (10, 5, 3) and m.shape_voxels == (160, 80, 48)
    full = m.decode_region()
    for (bx, by, bz), b in zip(coords, blocks):
        # raw is lossless up to float32 rounding of the metres <-> [0, 1] mapping (~1e-8 m)
        assert np.allclose(full[bx * 16:bx * 16 + 16, by * 16:by * 16 + 16, bz * 16:bz * 16 + 16], b,
                           rtol=0, atol=1e-7)
    assert m.count_states() == {"unobserved": 10 * 5 * 3 - 6, "empty": 1, "coded": 5}


def test_overwriting_blocks_in_one_chunk_keeps_neighbours(tmp_path):
    raw = sdfcodec.get_codec("raw")
    a = np.full((2, 16, 16, 16), 0.05, np.float32)
    b = np.full((1, 16, 16, 16), -0.01, np.float32)
    with sdfcodec.create_map(tmp_path / "m.sdfz", codec=raw, voxel_size=VS, truncation=TRUNC) as m:
        m.write_blocks([[0, 0, 0], [1, 0, 0]], a)
        m.write_blocks([[1, 0, 0]], b)
    dec = sdfcodec.open_map(tmp_path / "m.sdfz").decode_region()
    assert np.allclose(dec[:16], 0.05, atol=1e-7) and np.allclose(dec[16:32], -0.01, atol=1e-7)


def test_decode_on_torch_device(map_path):
    import torch

    m = sdfcodec.open_map(map_path)
    t = m.decode_region(device="cpu", level=32)
    assert isinstance(t, torch.Tensor) and t.device.type == "cpu"
    assert np.array_equal(t.numpy(), m.decode_region(level=32))


def test_open_map_over_file_url_and_http(map_path):
    import http.server
    import threading
    from functools import partial

    ref = sdfcodec.open_map(map_path).decode_region(level=32)
    assert np.array_equal(sdfcodec.open_map(map_path.resolve().as_uri()).decode_region(level=32), ref)
    handler = partial(http.server.SimpleHTTPRequestHandler, directory=str(map_path.parent))
    handler.log_message = lambda *a, **k: None
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        url = f"http://127.0.0.1:{server.server_address[1]}/{map_path.name}"
        assert np.array_equal(sdfcodec.open_map(url).decode_region(level=32), ref)
    finally:
        server.shutdown()
        server.server_close()


# -- bad input: a clear error, and nothing lost ----------------------------------------------------------

def _snapshot(path: Path) -> dict[str, bytes]:
    return {str(p.relative_to(path)): p.read_bytes() for p in sorted(path.rglob("*")) if p.is_file()}


@pytest.fixture
def existing(tmp_path, volume, pca64):
    path = tmp_path / "keep.sdfz"
    # no integrity manifest: the tampering tests below test the checksums and digests under it
    with sdfcodec.create_map(path, codec=pca64, voxel_size=VS, truncation=TRUNC, manifest=False) as m:
        m.write_volume(volume)
    return path


def _no_leftovers(directory: Path) -> None:
    assert not [p.name for p in directory.iterdir() if p.name.startswith(".")], "temporary files left behind"


@pytest.mark.parametrize("bad, exc, msg", [
    (lambda v: np.where(v > 0.09, np.nan, v), errors.InvalidValueError, "NaN/Inf"),
    (lambda v: np.where(v > 0.09, np.inf, v), errors.InvalidValueError, "NaN/Inf"),
    (lambda v: (v * 1000).astype(np.int16), errors.DTypeError, "floating point"),
    (lambda v: v[None], errors.ShapeError, r"dense \(X, Y, Z\)"),
])
def test_bad_volume_is_refused_and_old_map_kept(existing, volume, pca64, bad, exc, msg):
    before = _snapshot(existing)
    with pytest.raises(exc, match=msg):
        with sdfcodec.create_map(existing, codec=pca64, voxel_size=VS, truncation=TRUNC, overwrite=True) as m:
            m.write_volume(bad(volume))
    assert _snapshot(existing) == before
    _no_leftovers(existing.parent)


@pytest.mark.parametrize("lazy", [False, True], ids=["numpy", "dask"])
def test_values_outside_truncation_are_clipped_with_a_warning(tmp_path, volume, pca64, lazy):
    raw = sdfcodec.get_codec("raw")
    wild = volume.copy()
    wild[0, 0, 0], wild[1, 1, 1] = 5.0, -3.0
    if lazy:  # chunk by chunk (sdfcodec.map.scale): one warning for the whole volume all the same
        import dask.array as da

        wild = da.from_array(wild, chunks=32)
    want = r"^2 value.* \(0\.0%\) lie outside the truncation.*spans \[-3, 5\] m.*--truncation -3,5"
    with pytest.warns(errors.SDFCodecWarning, match=want) as got:
        with sdfcodec.create_map(tmp_path / "w.sdfz", codec=raw, voxel_size=VS, truncation=TRUNC) as m:
            m.write_volume(wild)
    # attributed to the caller's line
    assert [w.filename for w in got if issubclass(w.category, errors.SDFCodecWarning)] == [__file__]
    dec = sdfcodec.open_map(tmp_path / "w.sdfz").decode_region()
    assert dec[0, 0, 0] == pytest.approx(TRUNC[1]) and dec[1, 1, 1] == pytest.approx(TRUNC[0])


def test_existing_output_refused_without_overwrite(existing, pca64, volume):
    before = _snapshot(existing)
    with pytest.raises(errors.MapExistsError, match="overwrite"):
        sdfcodec.create_map(existing, codec=pca64, voxel_size=VS)
    assert _snapshot(existing) == before
    with sdfcodec.create_map(existing, codec=pca64, voxel_size=VS, truncation=TRUNC, overwrite=True) as m:
        m.write_volume(volume[:20, :20, :20])
    assert sdfcodec.open_map(existing).shape_voxels == (20, 20, 20)
    _no_leftovers(existing.parent)


def test_exception_during_write_leaves_old_map(existing, pca64, volume):
    before = _snapshot(existing)
    with pytest.raises(RuntimeError, match="boom"):
        with sdfcodec.create_map(existing, codec=pca64, voxel_size=VS, truncation=TRUNC, overwrite=True) as m:
            m.write_volume(volume[:40])
            raise RuntimeError("boom")
    assert _snapshot(existing) == before
    _no_leftovers(existing.parent)


def test_crash_during_write_leaves_old_map(existing, volume):
    """A writer process that dies abruptly (os._exit, no clean-up) leaves the previous map readable."""
    ref = sdfcodec.open_map(existing).decode_region()
    script = textwrap.dedent(f"""
        import os, numpy as np, sdfcodec
        from sdfcodec.testing import analytic_blocks
        codec = sdfcodec.get_codec("pca", code_size=32).fit(analytic_blocks(300))
        m = sdfcodec.create_map({str(existing)!r}, codec=codec, voxel_size=0.05, overwrite=True)
        m.write_volume(np.zeros((64, 64, 64), np.float32))
        os._exit(9)  # crash before commit
    """)
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 9, proc.stderr
    m = sdfcodec.open_map(existing)
    assert m.voxel_size == VS and np.array_equal(m.decode_region(), ref)


def test_corrupted_chunk_names_the_chunk(existing):
    chunk = existing / "codes" / "c" / "0" / "0" / "0" / "0"
    data = bytearray(chunk.read_bytes())
    data[len(data) // 2] ^= 0xFF
    chunk.write_bytes(bytes(data))
    m = sdfcodec.open_map(existing)
    m.block_states()  # the state array is intact
    with pytest.raises(errors.ChecksumError, match=r"chunk c/0/0/0/0 of array 'codes'"):
        m.decode_region()
    with pytest.raises(errors.ChecksumError, match=r"chunk c/0/0/0/0"):
        m.read_codes(level=32)


def test_truncated_chunk_names_the_chunk(existing):
    chunk = existing / "state" / "c" / "0" / "0" / "0"
    chunk.write_bytes(chunk.read_bytes()[:7])
    with pytest.raises(errors.ChecksumError, match=r"chunk c/0/0/0 of array 'state'"):
        sdfcodec.open_map(existing).decode_region()


def _edit_header(path: Path, fn) -> None:
    meta = path / "zarr.json"
    doc = json.loads(meta.read_text())
    fn(doc["attributes"]["sdfcodec"])
    meta.write_text(json.dumps(doc))


def test_newer_format_version_is_refused_naming_both(existing):
    _edit_header(existing, lambda h: h.update(format_version=2))
    with pytest.raises(errors.VersionError, match="format version 2.*reads up to version 1"):
        sdfcodec.open_map(existing)


def test_unknown_required_extension_is_refused(existing):
    _edit_header(existing, lambda h: h.update(extensions=[{"name": "octree-lod", "required": True}]))
    with pytest.raises(errors.VersionError, match="extension 'octree-lod'"):
        sdfcodec.open_map(existing)


def test_invalid_header_field_is_named(existing):
    _edit_header(existing, lambda h: h.update(voxel_size=-1))
    with pytest.raises(errors.FormatError, match="voxel_size"):
        sdfcodec.open_map(existing)


def test_missing_codec_plugin_names_id_and_package(existing):
    def swap(h):
        h["codec"].update(id="eigen-ae", package="sdfcodec-eigen-ae")
        h["codec"]["config"]["id"] = "eigen-ae"

    _edit_header(existing, swap)
    m = sdfcodec.open_map(existing)  # header, states and codes stay readable without the plugin
    assert m.count_states()["coded"] > 0 and len(m.read_codes()[0]) > 0
    with pytest.raises(errors.UnknownCodecError, match="'eigen-ae'.*package 'sdfcodec-eigen-ae'"):
        m.decode_region()


def test_altered_codec_state_is_detected(existing):
    arr = zarr.open_array(str(existing / "codec" / "mean"), mode="r+")
    arr[0] = arr[0] + 0.5
    with pytest.raises(errors.ChecksumError, match="codec state"):
        sdfcodec.open_map(existing).decode_region()


def test_not_a_map(tmp_path):
    with pytest.raises(errors.MapNotFoundError, match="no map at"):
        sdfcodec.open_map(tmp_path / "absent.sdfz")
    zarr.open_group(str(tmp_path / "plain"), mode="w")
    with pytest.raises(errors.FormatError, match="no sdfcodec header"):
        sdfcodec.open_map(tmp_path / "plain")


def test_read_only_map_refuses_writes(map_path):
    with pytest.raises(errors.ReadOnlyError):
        sdfcodec.open_map(map_path).write_blocks([[0, 0, 0]], np.zeros((1, 16, 16, 16), np.float32))


def test_unfitted_codec_is_refused(tmp_path):
    with pytest.raises(errors.NotFittedError, match="fit"):
        sdfcodec.create_map(tmp_path / "x.sdfz", codec=sdfcodec.get_codec("pca"), voxel_size=VS)


def test_decode_size_limit(map_path):
    m = sdfcodec.open_map(map_path, max_decode_bytes=1000)
    with pytest.raises(errors.InvalidValueError, match="above the limit"):
        m.decode_region()


def test_header_schema_is_current():
    from sdfcodec.core.header import json_schema

    spec = Path(__file__).resolve().parents[1] / "spec" / "map-header.schema.json"
    assert json.loads(spec.read_text()) == json_schema(), \
        "spec/map-header.schema.json is stale: python -m sdfcodec.core.header > spec/map-header.schema.json"


def test_fusion_weights_are_optional_and_lossless(tmp_path):
    raw = sdfcodec.get_codec("raw")
    rng = np.random.default_rng(1)
    blocks = rng.uniform(*TRUNC, size=(3, 16, 16, 16)).astype(np.float32)
    weights = rng.integers(0, 300, size=(3, 16, 16, 16)).astype(np.float32)
    coords = [[0, 0, 0], [2, 1, 0], [5, 5, 5]]
    with sdfcodec.create_map(tmp_path / "w.sdfz", codec=raw, voxel_size=VS, truncation=TRUNC) as m:
        m.write_blocks(coords, blocks, weights=weights)
    m = sdfcodec.open_map(tmp_path / "w.sdfz")
    assert m.has_weights and m.header.extensions[0].name == "fusion-weights"
    assert np.array_equal(m.read_weights(coords), weights)  # integers below 2048 are exact in float16
    assert np.array_equal(m.read_weights([[1, 1, 1]]), np.zeros((1, 16, 16, 16)))
    with sdfcodec.create_map(tmp_path / "n.sdfz", codec=raw, voxel_size=VS, truncation=TRUNC) as m:
        m.write_blocks(coords, blocks)
    m = sdfcodec.open_map(tmp_path / "n.sdfz")
    assert not m.has_weights and [e.name for e in m.header.extensions] == ["integrity-manifest"]
    with pytest.raises(errors.FormatError, match="no fusion weights"):
        m.read_weights(coords)


class _KeyCounter(zarr.storage.WrapperStore):
    """A read-through store that records every key it is asked for (as search's counting store does)."""

    def __init__(self, store, keys: list | None = None):
        super().__init__(store)
        self.keys: list[str] = [] if keys is None else keys

    def _with_store(self, store):
        return type(self)(store, self.keys)

    async def get(self, key, prototype=None, byte_range=None):
        self.keys.append(key)
        return await self._store.get(key, prototype, byte_range)

    async def get_partial_values(self, prototype, key_ranges):
        self.keys.extend(k for k, _ in key_ranges)
        return await self._store.get_partial_values(prototype, key_ranges)


def test_with_store_reads_through_the_wrapper_and_shares_the_codec(map_path):
    """Map.with_store: the same map over a wrapped store (header, limits, codec cache shared); what it reads
    goes through the wrapper, its decodes equal the map's, and closing it leaves the map open."""
    m = sdfcodec.open_map(map_path, max_decode_bytes=1 << 30)
    wrappers: list[_KeyCounter] = []
    view = m.with_store(lambda s: wrappers.append(_KeyCounter(s)) or wrappers[-1])
    assert isinstance(view, sdfcodec.Map) and not view.writable
    assert view.header is m.header and view.max_decode_bytes == m.max_decode_bytes == 1 << 30
    assert view.reader.group.store is wrappers[0]
    keys = wrappers[0].keys
    assert "zarr.json" in keys or any(k.endswith("zarr.json") for k in keys)  # the arrays' metadata, re-read
    # the codec cache is shared: loaded through the view (reading codec/ through the wrapper), loaded for both
    assert m.reader.cache.codec is None
    codec = view.codec
    assert m.codec is codec and any(k.startswith("codec/") for k in keys)
    n = len(keys)
    coords, codes = view.read_codes(((0, 16), (0, 16), (0, 16)), level=32)
    assert len(keys) > n and any(k.startswith("codes/") for k in keys[n:])
    c2, z2 = m.read_codes(((0, 16), (0, 16), (0, 16)), level=32)
    np.testing.assert_array_equal(coords, c2)
    np.testing.assert_array_equal(codes, z2)
    np.testing.assert_array_equal(view.decode_region(), m.decode_region())
    # the other way round: a codec loaded through the map first is the view's
    m2 = sdfcodec.open_map(map_path)
    c = m2.codec
    assert m2.with_store(lambda s: s).codec is c
    view.close()
    assert m.block_states().shape == m.grid_blocks  # the map still reads
    with pytest.raises(errors.InvalidValueError, match="closed"):
        view.block_states()
    m.close()
    # a map being written cannot be viewed: commit it first
    with sdfcodec.create_map(map_path.parent / "w.sdfz", codec=c, voxel_size=VS, truncation=TRUNC) as w:
        with pytest.raises(errors.InvalidValueError, match="being written"):
            w.with_store(lambda s: s)
        w.mark_empty([[0, 0, 0]])


def test_map_package_imports_no_cycle():
    """The map package never imports the dask layer (sdfcodec.map.scale imports the package's reader and writer, not
    the other way round)."""
    code = textwrap.dedent("""
        import sys, warnings
        warnings.simplefilter("error", DeprecationWarning)
        import sdfcodec.map, sdfcodec.map.io.stores, sdfcodec.map.format, sdfcodec.map.reader, sdfcodec.map.writer
        assert "sdfcodec.map.scale" not in sys.modules, "the map package imported sdfcodec.map.scale"
        import sdfcodec.map.scale, sdfcodec.map.verify, sdfcodec.tracking.mapfield, sdfcodec.cli
        print("ok")
    """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.returncode == 0 and out.stdout.strip() == "ok", out.stderr


def test_safe_local_store_reads_like_zarrs_local_store(map_path):
    """The store local maps are read through (regular files only, bounded reads) returns what Zarr's own
    LocalStore returns, byte ranges included, and None for keys that are not stored."""
    from zarr.abc.store import OffsetByteRequest, RangeByteRequest, SuffixByteRequest
    from zarr.core.buffer import default_buffer_prototype
    from zarr.core.sync import sync

    from sdfcodec.map.io.stores import SafeLocalStore

    safe, plain = SafeLocalStore(map_path), zarr.storage.LocalStore(map_path, read_only=True)
    proto = default_buffer_prototype()
    keys = sorted(sync(_keys(plain)))
    assert keys and sorted(sync(_keys(safe))) == keys
    for key in keys[:6] + ["codes/c/9/9/9/9", "nothing/zarr.json"]:
        for rng in (None, RangeByteRequest(3, 11), OffsetByteRequest(5), SuffixByteRequest(4)):
            a, b = sync(safe.get(key, proto, rng)), sync(plain.get(key, proto, rng))
            assert (a is None and b is None) or a.to_bytes() == b.to_bytes(), (key, rng)
        assert sync(safe.exists(key)) == sync(plain.exists(key))
    with pytest.raises(errors.FormatError, match="more than the 10 allowed"):
        safe.read_file("zarr.json", max_bytes=10)


async def _keys(store) -> list[str]:
    return [k async for k in store.list()]


@pytest.mark.parametrize("array", ["codes", "state", "codec/explained_variance"])
def test_zero_chunk_edge_is_a_clear_error(map_path, tmp_path, array):
    """A chunk shape with a 0 edge (Zarr accepts it in metadata) is refused by name, not divided by: the
    10,000-case fuzz run found a ZeroDivisionError from codec/explained_variance with chunk_shape [0]."""
    import json
    import re
    import shutil

    from sdfcodec.map.verify import verify_map

    bad = tmp_path / "bad.sdfz"
    shutil.copytree(map_path, bad)
    doc_path = bad / array / "zarr.json"
    doc = json.loads(doc_path.read_text())
    doc["chunk_grid"]["configuration"]["chunk_shape"] = [0] * len(doc["shape"])
    doc_path.write_text(json.dumps(doc))
    said = r"chunk edge must be >= 1|has chunks \(0, 0, 0, 0\), expected"  # codes: the header names its chunks
    with pytest.raises(errors.FormatError, match=said):
        m = sdfcodec.open_map(bad)
        m.decode_region()
    report = verify_map(bad)
    assert not report.ok and any(re.search(said, p) for p in map(str, report.problems))


def test_blosc_frames_are_checked_before_decompression(map_path, tmp_path):
    """A Blosc frame cut short or with a tampered header, under a valid CRC32C, made the C decompressor read
    outside its buffer (the 10,000-case fuzz run died of a segfault): the guard checks the frame's structure
    first. Valid frames of every array pass; damaged ones are one clear error, in a child that must not crash."""
    import subprocess
    import sys

    import google_crc32c
    from numcodecs import Blosc

    from sdfcodec.map.io.stores import blosc_frame_problem

    data = np.random.default_rng(0).random(4096).astype(np.float32).tobytes()
    for shuffle in (Blosc.NOSHUFFLE, Blosc.SHUFFLE, Blosc.BITSHUFFLE):
        frame = Blosc(cname="zstd", clevel=3, shuffle=shuffle, blocksize=4096).encode(data)
        assert blosc_frame_problem(frame, len(data)) is None
        assert "shorter" in blosc_frame_problem(frame[:10], len(data))
        assert "compressed bytes" in blosc_frame_problem(frame[:-7], len(data))
        assert "more than its shape" in blosc_frame_problem(frame, len(data) - 1)
        bad = bytearray(frame)
        bad[16:20] = (len(frame) + 100).to_bytes(4, "little")  # the first block starts past the end
        assert "outside" in blosc_frame_problem(bytes(bad), len(data))
    for p in sorted((map_path / "codes" / "c").rglob("*"))[:3] + sorted((map_path / "codec").rglob("c/*"))[:3]:
        if p.is_file():
            assert blosc_frame_problem(p.read_bytes()[:-4], 1 << 30) is None, p
    # end to end: a code chunk cut short, its checksum recomputed
    import shutil

    bad_map = tmp_path / "cut.sdfz"
    shutil.copytree(map_path, bad_map)
    chunk = next(p for p in sorted((bad_map / "codes" / "c").rglob("*")) if p.is_file())
    body = chunk.read_bytes()[:-4][: 40]
    chunk.write_bytes(body + google_crc32c.value(body).to_bytes(4, "little"))
    code = ("import sdfcodec, sys\n"
            "try:\n    sdfcodec.open_map(sys.argv[1]).decode_region()\n"
            "except sdfcodec.errors.SDFCodecError as e:\n    print('refused:', e)\n")
    r = subprocess.run([sys.executable, "-c", code, str(bad_map)], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and "not a sound Blosc frame" in r.stdout, (r.returncode, r.stdout, r.stderr[-500:])
