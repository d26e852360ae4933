"""The documents of a map (issue 42, "side information near zero"; spec/map-format.md sections 2, 3, 4, 6c and
9b): what a small lossy map spends beside its chunks. Each check is made here with the standard library and
zarr-python, independently of sdfcodec's reader: the manifest's base64url digests, plain Zarr v3 documents, no
codec group or duplicated digest by reference, no local path in the provenance, and the golden map of this
layout."""

from __future__ import annotations

import base64
import hashlib
import json
import shutil
import zlib
from pathlib import Path

import numpy as np
import pytest
import zarr

import sdfcodec
from _golden_maps import check_golden_map
from sdfcodec import errors
from sdfcodec.core.header import public_source
from sdfcodec.map.verify import verify_map
from sdfcodec.core.sdf import sample_volume
from sdfcodec.registry import pretrained_codec
from sdfcodec.testing import analytic_scene

VS, TRUNC = 0.02, (-0.04, 0.1)
GOLDEN = Path(__file__).parent / "golden" / "maps" / "side-docs-pca-128"


def _write(path: Path, volume: np.ndarray, source: str | None = None) -> Path:
    """A variable-rate map of ``volume`` by reference to the shipped pca-128, as `encode --target-bytes` writes."""
    with sdfcodec.create_map(path, codec=pretrained_codec("pca", 128), voxel_size=VS, truncation=TRUNC,
                             codec_state="reference", variable_rate={"step": 2.0}, chunk_blocks=2,
                             tool="tests/test_side_docs.py", source=source) as m:
        m.write_volume(volume)
    return path


@pytest.fixture(scope="module")
def volume() -> np.ndarray:
    return sample_volume(analytic_scene(), (40, 24, 20), VS, truncation=TRUNC)


def _b64(data: bytes) -> str:
    return base64.urlsafe_b64encode(hashlib.sha256(data).digest()).decode().rstrip("=")


def test_documents_are_plain_zarr_v3_without_what_zarr_makes_optional(tmp_path, volume):
    root = _write(tmp_path / "m.sdfz", volume, source=str(tmp_path / "private" / "scan.npy"))
    header = json.loads((root / "zarr.json").read_bytes())["attributes"]["sdfcodec"]
    # by reference: neither the codec group nor the digest the reference already gives (spec 6c)
    assert not (root / "codec").exists()
    assert "state_sha256" not in header["codec"] and "state_arrays" not in header["codec"]
    assert header["codec"]["state_reference"]["sha256"] == sdfcodec.open_map(root).header.codec.state_sha256
    # the input's name, not the writer's directories (spec 3)
    assert header["provenance"]["source"] == "scan.npy" and str(tmp_path) not in (root / "zarr.json").read_text()
    for doc in root.glob("*/zarr.json"):
        meta = json.loads(doc.read_bytes())
        assert meta["chunk_key_encoding"] == {"name": "default"} and "dimension_names" not in meta, doc
        assert doc.read_bytes() == json.dumps(meta, separators=(",", ":")).encode()  # compact
        arr = zarr.open_array(str(root), path=doc.parent.name, mode="r")  # plain zarr-python reads each array
        assert arr.metadata.chunk_key_encoding.separator == "/"
    # the block states travel in the header (spec 4e): base64 of zlib of the grid's bytes, read here with the stdlib
    assert not (root / "state").exists() and not (root / "codes").exists()
    grid = tuple(header["grid_blocks"])
    states = np.frombuffer(zlib.decompress(base64.b64decode(header["codes"]["variable_rate"]["states"])), np.uint8)
    assert np.array_equal(states.reshape(grid), sdfcodec.open_map(root).block_states())


def test_inline_states_read_as_stored_ones_in_fewer_bytes(tmp_path, volume, monkeypatch):
    from sdfcodec.map import implied

    inline = _write(tmp_path / "inline.sdfz", volume)
    monkeypatch.setattr(implied, "INLINE_MAX", -1)  # what a writer does for a grid too large to inline
    stored = _write(tmp_path / "stored.sdfz", volume)
    assert (stored / "state" / "zarr.json").is_file() and (stored / "codes" / "zarr.json").is_file()
    assert "states" not in json.loads((stored / "zarr.json").read_bytes())["attributes"]["sdfcodec"]["codes"][
        "variable_rate"]
    a, b = sdfcodec.open_map(inline), sdfcodec.open_map(stored)
    plain = zarr.open_array(str(stored), path="state", mode="r")[...]  # zarr-python's read of the stored array
    assert np.array_equal(a.block_states(), plain) and (plain == 2).sum() == 10 and (plain == 1).any()
    np.testing.assert_array_equal(a.decode_region(), b.decode_region())
    box = ((8, 30), (0, 24), (4, 20))
    np.testing.assert_array_equal(a.decode_region(box), b.decode_region(box))
    assert verify_map(inline).ok and verify_map(stored).ok

    def size(p: Path) -> int:
        return sum(f.stat().st_size for f in p.rglob("*") if f.is_file())

    saved = sum(size(stored / n) for n in ("state", "codes"))  # their files, less what the header takes instead
    assert size(inline) < size(stored) and saved > 400


@pytest.mark.parametrize("how, match", [("truncated", "not base64 of zlib|holds"), ("longer", "holds 1"),
                                        ("reserved", "reserved value"), ("text", "not base64"),
                                        ("charset", "codes.variable_rate.states: String should match")])
def test_hostile_inline_states_are_refused_in_one_line(tmp_path, volume, how, match):
    root = _write(tmp_path / "m.sdfz", volume)
    top = json.loads((root / "zarr.json").read_bytes())
    vr = top["attributes"]["sdfcodec"]["codes"]["variable_rate"]
    raw = zlib.decompress(base64.b64decode(vr["states"]))
    packed = {"truncated": base64.b64encode(zlib.compress(raw)[:-6]).decode(),
              "longer": base64.b64encode(zlib.compress(raw + b"\0")).decode(),
              "reserved": base64.b64encode(zlib.compress(b"\3" + raw[1:])).decode(),
              "text": "AAAAA", "charset": "AAAA!"}[how]
    vr["states"] = packed
    (root / "zarr.json").write_text(json.dumps(top))
    with pytest.raises(errors.SDFCodecError, match=match) as e:
        sdfcodec.open_map(root).decode_region()
    assert "\n" not in str(e.value)


def test_manifest_v2_lists_every_object_in_base64url_and_refuses_a_swap(tmp_path, volume):
    root = _write(tmp_path / "m.sdfz", volume)
    raw = (root / "manifest.json").read_bytes()
    doc = json.loads(raw)
    assert (doc["format"], doc["version"], doc["algorithm"]) == ("sdfcodec-manifest", 2, "sha256")
    stored = {f.relative_to(root).as_posix(): f for f in root.rglob("*") if f.is_file()}
    assert set(doc["objects"]) == set(stored) - {"zarr.json", "manifest.json"}
    for key, digest in doc["objects"].items():
        assert len(digest) == 43 and digest == _b64(stored[key].read_bytes()), key
    # 21 bytes fewer per object than the same manifest in hex (version 1)
    hexdoc = {**doc, "version": 1, "objects": {k: hashlib.sha256(stored[k].read_bytes()).hexdigest()
                                               for k in doc["objects"]}}
    assert len(json.dumps(hexdoc, separators=(",", ":"), sort_keys=True)) - len(raw) == 21 * len(doc["objects"])
    assert verify_map(root).ok
    # a sound object in the wrong place is still refused: the two code stream chunks swapped
    chunks = sorted(k for k in stored if k.startswith("code_streams/c/"))
    assert len(chunks) >= 2
    a, b = stored[chunks[0]], stored[chunks[1]]
    da, db = a.read_bytes(), b.read_bytes()
    a.write_bytes(db)
    b.write_bytes(da)
    with pytest.raises(errors.IntegrityError, match="SHA-256 in the manifest"):
        sdfcodec.open_map(root).decode_region()
    rep = verify_map(root)
    assert not rep.ok and any(chunks[0] in p or chunks[1] in p for p in map(str, rep.problems))


def test_manifest_v2_refuses_hex_or_non_canonical_digests(tmp_path, volume):
    root = _write(tmp_path / "m.sdfz", volume)
    doc = json.loads((root / "manifest.json").read_bytes())
    key = sorted(doc["objects"])[0]
    good = doc["objects"][key]
    # the same digest in hex (version 1's spelling), and a last character whose unused low bits are not zero
    last = "ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789-_"
    bad_tail = last[last.index(good[-1]) ^ 1]
    for bad in (base64.urlsafe_b64decode(good + "=").hex(), good[:-1] + bad_tail):
        m = root.parent / f"bad-{len(bad)}.sdfz"
        shutil.copytree(root, m)
        doc["objects"][key] = bad
        data = json.dumps(doc, separators=(",", ":"), sort_keys=True).encode()
        (m / "manifest.json").write_bytes(data)
        top = json.loads((m / "zarr.json").read_bytes())  # the header names the new manifest, as a forger would
        top["attributes"]["sdfcodec"]["manifest"].update(sha256=hashlib.sha256(data).hexdigest(), size=len(data))
        (m / "zarr.json").write_text(json.dumps(top))
        with pytest.raises(errors.FormatError, match="manifest.json is malformed"):
            sdfcodec.open_map(m)


@pytest.mark.parametrize("source, name", [
    ("/home/alice/projects/lab/kitchen.sdfz", "kitchen.sdfz"),
    ("C:\\Users\\alice\\kitchen.npy", "kitchen.npy"),
    ("https://alice:secret@maps.example.org/a/room.sdfz?token=abc#x", "room.sdfz"),
    ("s3://bucket/dir/", "dir"),
    ("https://maps.example.org", "maps.example.org"),
    ("frames 0-499", "frames 0-499"),
    (None, None),
])
def test_public_source_keeps_the_name_only(source, name):
    assert public_source(source) == name


def _golden_map(path: Path) -> None:
    _write(path, sample_volume(analytic_scene(), (40, 24, 20), VS, truncation=TRUNC), source="/tmp/scene.npy")


def test_golden_side_docs_map_decodes_forever(regen_golden):
    """A small map of this layout written once (regenerate only with --regen-golden, for a format change):
    manifest version 2, no codec group, no duplicated digest; today's reader verifies it and decodes the frozen
    values."""
    m = check_golden_map(GOLDEN, _golden_map, regen_golden)
    root = GOLDEN / "map.zarr"
    assert json.loads((root / "manifest.json").read_bytes())["version"] == 2
    assert not any((root / n).exists() for n in ("codec", "codes", "state"))  # implied (spec 2, 4e, 6c)
    assert m.count_states()["coded"] == 10
    assert m.header.codec.state_sha256 == m.header.codec.state_reference.sha256
    assert m.header.provenance.source == "scene.npy"
