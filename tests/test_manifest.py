"""The integrity manifest (spec/map-format.md section 9b): objects bound to their keys. Each attack below is a
sound object in the wrong place (CRC32C and the state digest pass), which today's readers decoded silently
and ``verify`` called sound; each must now be refused by ``decode`` with one line naming the array and key,
and flagged by ``verify``."""

from __future__ import annotations

import json
import os
import shutil
import zipfile
from pathlib import Path

import numpy as np
import pytest
import zarr
from typer.testing import CliRunner

import sdfcodec
from sdfcodec.cli import app
from sdfcodec.errors import FormatError
from sdfcodec.map.codec_state import state_digest
from sdfcodec.map.verify import verify_map

VS = 0.02
runner = CliRunner()


def run(*args):
    return runner.invoke(app, [str(a) for a in args])


@pytest.fixture(scope="module")
def maps(tmp_path_factory, volume, pca64):
    """Two maps of the same volume and layout (so the same keys), coded by two different pca-64 fits; and a
    sharded one. chunk_code 16: four chunks along the code axis."""
    from sdfcodec.testing import analytic_blocks

    root = tmp_path_factory.mktemp("manifest")
    other = sdfcodec.get_codec("pca", code_size=64).fit(analytic_blocks(800, seed=5))
    for name, codec, kw in (("a", pca64, {}), ("b", other, {}), ("sharded", pca64, {"shard_blocks": 4})):
        with sdfcodec.create_map(root / name, codec=codec, voxel_size=VS, chunk_blocks=2, chunk_code=16, **kw) as m:
            m.write_volume(volume)
    return root


def copy(maps: Path, name: str, tmp_path: Path) -> Path:
    dst = tmp_path / name
    shutil.copytree(maps / name, dst)
    return dst


def refused(path, key: str, tmp_path: Path, *also: str) -> None:
    """``decode`` refuses the map in one line naming ``key`` (or one of ``also``: of two swapped chunks, the
    reader's threads meet either first); ``verify`` flags every one of them."""
    r = run("decode", path, tmp_path / "out.npy")
    assert r.exit_code == 1, r.output
    line = r.stderr.strip()
    assert "\n" not in line and any(k in line for k in (key, *also)) and "manifest" in line, line
    assert not (tmp_path / "out.npy").exists()
    rep = verify_map(path)
    for k in (key, *also):
        assert not rep.ok and any(k in p.message for p in rep.problems), rep.problems
    r = run("verify", path)
    assert r.exit_code == 1 and all(k in r.stdout for k in (key, *also))


def swap(a: Path, b: Path) -> None:
    """Exchange the bytes of two stored objects (both sound, each now at the other's key)."""
    da, db = a.read_bytes(), b.read_bytes()
    assert da != db
    a.write_bytes(db)
    b.write_bytes(da)


def coded_chunks(path: Path) -> list[Path]:
    return sorted(f for f in (path / "codes" / "c").rglob("*") if f.is_file())


def test_untampered_maps_read_and_verify(maps, volume):
    for name in ("a", "sharded"):
        m = sdfcodec.open_map(maps / name)
        assert m.header.manifest is not None
        assert m.reader.group.store.manifest is not None  # reads are checked
        rep = verify_map(maps / name)
        assert rep.ok, rep.problems
        assert rep.integrity["manifest"]["objects"] == m.header.manifest.objects
        assert rep.chunks_checked["manifest"] == m.header.manifest.objects
    listed = set(json.loads((maps / "a" / "manifest.json").read_text())["objects"])
    stored = {f.relative_to(maps / "a").as_posix() for f in (maps / "a").rglob("*") if f.is_file()}
    assert listed == stored - {"zarr.json", "manifest.json"}  # every object, and only those


def test_chunks_swapped_between_positions(maps, tmp_path):
    p = copy(maps, "a", tmp_path)
    swap(p / "codes/c/0/0/0/0", p / "codes/c/1/1/0/0")
    refused(p, "codes/c/0/0/0/0", tmp_path, "codes/c/1/1/0/0")


def test_chunks_swapped_along_the_code_axis(maps, tmp_path):
    p = copy(maps, "a", tmp_path)
    swap(p / "codes/c/1/1/0/0", p / "codes/c/1/1/0/2")
    refused(p, "codes/c/1/1/0/0", tmp_path, "codes/c/1/1/0/2")


def test_state_chunk_rewritten_with_a_valid_crc(maps, tmp_path):
    p = copy(maps, "a", tmp_path)
    st = zarr.open_array(p / "state", mode="r+")
    s = st[...]
    coded = np.argwhere(s == 2)[0]
    s[tuple(coded)] = 1  # a coded block now "empty": Zarr writes a sound chunk with its CRC32C
    st[...] = s
    refused(p, "state/c/0/0/0", tmp_path)


def test_codec_state_rewritten_with_its_digest_recomputed(maps, tmp_path):
    p = copy(maps, "a", tmp_path)
    comp = zarr.open_array(p / "codec" / "components", mode="r+")
    comp[...] = comp[...] * 3  # the PCA basis x3: 6 cm off on main
    doc = json.loads((p / "zarr.json").read_text())
    h = doc["attributes"]["sdfcodec"]
    state = {n: zarr.open_array(p / "codec" / n, mode="r")[...] for n in h["codec"]["state_arrays"]}
    h["codec"]["state_sha256"] = state_digest(state)
    (p / "zarr.json").write_text(json.dumps(doc))
    refused(p, "codec/components/c/0/0", tmp_path)


def test_shard_index_entry_aliasing_another_chunk(maps, tmp_path):
    import google_crc32c

    p = copy(maps, "sharded", tmp_path)
    shard = p / "codes/c/0/0/0/0"
    data = bytearray(shard.read_bytes())
    per = 2 * 2 * 2 * 4  # 4-block shards of 2-block chunks, the 4 chunks of the code axis
    n = 16 * per + 4
    index = np.frombuffer(bytes(data[-n:-4]), "<u8").reshape(per, 2).copy()
    stored = [i for i in range(per) if index[i, 0] != 2 ** 64 - 1]
    assert len(stored) >= 2
    index[stored[0]] = index[stored[1]]  # chunk 0 now reads chunk 1's bytes: a sound frame, a sound CRC
    body = index.tobytes()
    data[-n:] = body + google_crc32c.value(body).to_bytes(4, "little")
    shard.write_bytes(bytes(data))
    refused(p, "codes/c/0/0/0/0", tmp_path)


def test_http_server_sending_another_maps_chunks(maps, tmp_path):
    from sdfcodec.bench.serve import FileServer

    served = copy(maps, "a", tmp_path / "www")
    shutil.rmtree(served / "codes" / "c")
    shutil.copytree(maps / "b" / "codes" / "c", served / "codes" / "c")  # same keys, another map's bytes
    with FileServer(tmp_path / "www") as srv:
        url = srv.url("a")
        with pytest.raises(FormatError, match=r"codes/c/.*manifest"):
            sdfcodec.open_map(url).decode_region()
        r = run("decode", url, tmp_path / "out.npy")
        assert r.exit_code == 1 and "\n" not in r.stderr.strip() and "codes/c/" in r.stderr
        rep = verify_map(url)
        assert not rep.ok and any("codes/c/" in p.message and "manifest" in p.message for p in rep.problems)


def test_zip_with_two_root_documents_is_refused(maps, tmp_path):
    z = tmp_path / "two.zip"
    with zipfile.ZipFile(z, "w") as f:
        for file in sorted((maps / "a").rglob("*")):
            if file.is_file():
                f.write(file, file.relative_to(maps / "a").as_posix())
        with pytest.warns(UserWarning, match="Duplicate name"):
            f.writestr("zarr.json", (maps / "b" / "zarr.json").read_bytes())
    with pytest.raises(FormatError, match="member zarr.json appears twice"):
        sdfcodec.open_map(z)
    r = run("decode", z, tmp_path / "out.npy")
    assert r.exit_code == 1 and "member zarr.json appears twice" in r.stderr and "\n" not in r.stderr.strip()
    rep = verify_map(z)
    assert not rep.ok and any("zarr.json appears twice" in p.message for p in rep.problems)


def test_object_added_or_removed_is_flagged(maps, tmp_path):
    p = copy(maps, "a", tmp_path)
    (p / "codes" / "stray").write_bytes(b"x")
    rep = verify_map(p)
    assert not rep.ok and any("codes/stray is stored but not listed" in x.message for x in rep.problems)
    (p / "codes" / "stray").unlink()
    victim = coded_chunks(p)[3]
    victim.unlink()
    key = victim.relative_to(p).as_posix()
    rep = verify_map(p)
    assert not rep.ok and any(key in x.message and "missing" in x.message for x in rep.problems)


def test_manifest_rewritten_without_the_header_is_refused(maps, tmp_path):
    p = copy(maps, "a", tmp_path)
    doc = json.loads((p / "manifest.json").read_text())
    (p / "manifest.json").write_text(json.dumps(doc, indent=1))  # same content, other bytes
    with pytest.raises(FormatError, match="not the manifest the header names"):
        sdfcodec.open_map(p)
    assert not verify_map(p).ok


def test_no_verify_chunks_is_for_benchmarks(maps, tmp_path):
    p = copy(maps, "a", tmp_path)
    swap(p / "codes/c/0/0/0/0", p / "codes/c/1/1/0/0")
    m = sdfcodec.open_map(p, verify_chunks=False)
    m.decode_region()  # unchecked: the swap goes through, as it did before manifests
    r = run("decode", p, tmp_path / "o.npy", "--no-verify-chunks")
    assert r.exit_code == 0, r.output


def test_update_keeps_the_manifest_true(maps, tmp_path, volume):
    for name in ("a", "sharded"):
        p = copy(maps, name, tmp_path)
        before = json.loads((p / "manifest.json").read_text())["objects"]
        with sdfcodec.update_map(p) as m:
            m.mark_empty([[0, 0, 0]])
        rep = verify_map(p)
        assert rep.ok, rep.problems
        after = json.loads((p / "manifest.json").read_text())["objects"]
        assert after["state/c/0/0/0"] != before["state/c/0/0/0"]
        assert sdfcodec.open_map(p).block_states()[0, 0, 0] == 1


def test_update_keeps_a_tampered_chunk_detectable(maps, tmp_path):
    """An update lists the files it copied unchanged with their previous digests (it does not read them): a chunk
    altered before the update stays refused after it."""
    p = copy(maps, "a", tmp_path)
    a, b = p / "codes/c/0/0/0/0", p / "codes/c/1/1/0/0"
    a.write_bytes(b.read_bytes())
    with sdfcodec.update_map(p) as m:
        m.mark_empty([[5, 4, 2]])
    with pytest.raises(FormatError, match="codes/c/0/0/0/0"):
        sdfcodec.open_map(p).decode_region()


def test_old_maps_open_and_say_no_manifest():
    old = Path(__file__).parent / "golden" / "maps" / "int8-pca-4" / "map.zarr"
    m = sdfcodec.open_map(old)
    assert m.header.manifest is None and m.info()["integrity"]["manifest"] is None
    m.decode_region()
    rep = verify_map(old)
    assert rep.ok and any("no manifest" in n.message for n in rep.notes)
    r = run("info", old)
    assert r.exit_code == 0 and "no manifest" in r.stdout
    r = run("verify", old)
    assert r.exit_code == 0 and "no manifest" in r.stdout


def test_info_checks_the_state_against_the_manifest(maps, tmp_path):
    p = copy(maps, "a", tmp_path)
    r = run("info", p, "--json")
    assert r.exit_code == 0 and json.loads(r.stdout)["integrity"]["manifest"]["objects"] > 0
    st = zarr.open_array(p / "state", mode="r+")
    s = st[...]
    s[tuple(np.argwhere(s == 2)[0])] = 1
    st[...] = s
    r = run("info", p)
    assert r.exit_code == 1 and "state/c/0/0/0" in r.stderr and "manifest" in r.stderr


GOLDEN = Path(__file__).parent / "golden" / "maps" / "signed-sharded-pca-4"
#: The golden map's signing key: a test key (its seed is public), so the golden signature is reproducible.
GOLDEN_SEED = bytes(range(32))


def _golden_map(path: Path) -> None:
    from sdfcodec.map.sign import sign_map
    from sdfcodec.core.sdf import sample_volume
    from sdfcodec.testing import analytic_blocks, analytic_scene

    codec = sdfcodec.get_codec("pca", code_size=4).fit(analytic_blocks(64, seed=5))
    vol = sample_volume(analytic_scene(), (40, 24, 20), VS, truncation=(-0.04, 0.1))
    with sdfcodec.create_map(path, codec=codec, voxel_size=VS, chunk_blocks=1, chunk_code=2, shard_blocks=2,
                             tool="tests/test_manifest.py golden") as m:
        m.write_volume(vol)
    sign_map(path, GOLDEN_SEED)


def test_golden_signed_map_decodes_forever(regen_golden):
    """A small sharded map with a manifest and a signature, written once (regenerate only with --regen-golden,
    for a format change): today's reader opens it trusting its key, verifies it and decodes the frozen values;
    its manifest lists each file's SHA-256 (checked here with hashlib, independently of the reader)."""
    import hashlib

    from _golden_maps import check_golden_map

    pytest.importorskip("cryptography")
    from cryptography.hazmat.primitives.asymmetric import ed25519

    m = check_golden_map(GOLDEN, _golden_map, regen_golden)
    root = GOLDEN / "map.zarr"
    doc = json.loads((root / "manifest.json").read_bytes())
    assert (doc["format"], doc["version"], doc["algorithm"]) == ("sdfcodec-manifest", 1, "sha256")
    stored = {f.relative_to(root).as_posix(): f for f in root.rglob("*") if f.is_file()}
    assert set(doc["objects"]) == set(stored) - {"zarr.json", "manifest.json", "signature.json"}
    for key, digest in doc["objects"].items():
        assert hashlib.sha256(stored[key].read_bytes()).hexdigest() == digest, key
    for key, entry in doc["shards"].items():  # each chunk of each shard, at the range its index gives
        data = stored[key].read_bytes()
        for off, n, digest in entry["chunks"]:
            assert hashlib.sha256(data[off:off + n]).hexdigest() == digest
    assert m.header.manifest.sha256 == hashlib.sha256((root / "manifest.json").read_bytes()).hexdigest()
    pub = ed25519.Ed25519PrivateKey.from_private_bytes(GOLDEN_SEED).public_key().public_bytes_raw()
    signed = sdfcodec.open_map(root, trusted_keys=[pub])
    np.testing.assert_array_equal(signed.decode_region(), m.decode_region())
    rep = verify_map(root, trusted_keys=[pub])
    assert rep.ok and rep.integrity["signature"]["valid"], rep.problems


# -- fuzzing the manifest: an attacker who also rewrites the header's record of it --------------------------
FUZZ_EXAMPLES = int(os.environ.get("SDFCODEC_FUZZ_EXAMPLES", "20"))


def _mutate(doc: dict, data) -> bytes:
    """One hostile change to the manifest document ``doc`` (a copy), drawn by hypothesis's ``data``."""
    from hypothesis import strategies as st

    json_values = st.recursive(st.none() | st.booleans() | st.integers(-2**70, 2**70) | st.text(max_size=80)
                               | st.floats(allow_nan=False), lambda c: st.lists(c, max_size=4)
                               | st.dictionaries(st.text(max_size=20), c, max_size=4), max_leaves=12)
    objects = doc["objects"]
    keys = sorted(objects)
    kind = data.draw(st.sampled_from(["drop", "digest", "swap", "add", "value", "field", "shard", "bytes",
                                      "reorder"]))
    if kind == "drop":
        objects.pop(data.draw(st.sampled_from(keys)))
    elif kind == "digest":
        k = data.draw(st.sampled_from(keys))
        i = data.draw(st.integers(0, len(objects[k]) - 1))
        objects[k] = objects[k][:i] + ("0" if objects[k][i] != "0" else "1") + objects[k][i + 1:]
    elif kind == "swap":
        a, b = data.draw(st.sampled_from(keys)), data.draw(st.sampled_from(keys))
        objects[a], objects[b] = objects[b], objects[a]
    elif kind == "add":
        objects[data.draw(st.text(min_size=1, max_size=60))] = data.draw(st.text(max_size=70))
    elif kind == "value":
        objects[data.draw(st.sampled_from(keys))] = data.draw(json_values)
    elif kind == "field":
        doc[data.draw(st.sampled_from(["format", "version", "algorithm", "objects", "shards", "extra"]))] = \
            data.draw(json_values)
    elif kind == "shard" and doc.get("shards"):
        entry = doc["shards"][data.draw(st.sampled_from(sorted(doc["shards"])))]
        target = data.draw(st.sampled_from(["index", "chunks", "chunk"]))
        if target == "chunk" and entry["chunks"]:
            c = entry["chunks"][data.draw(st.integers(0, len(entry["chunks"]) - 1))]
            c[data.draw(st.integers(0, 2))] = data.draw(json_values | st.integers(0, 1 << 40))
        else:
            entry[target if target != "chunk" else "index"] = data.draw(json_values)
    raw = json.dumps(doc, sort_keys=data.draw(st.booleans())).encode()
    if kind == "bytes":
        raw = bytearray(raw)
        for _ in range(data.draw(st.integers(1, 4))):
            raw[data.draw(st.integers(0, len(raw) - 1))] = data.draw(st.integers(0, 255))
        raw = bytes(raw)
    return raw


@pytest.mark.parametrize("name", ["a", "sharded"])
def test_fuzzed_manifests_are_refused_or_harmless(maps, tmp_path_factory, name):
    """Hostile manifests whose digest the header records (what an attacker who rewrites both writes): reading
    and verifying the map raises only SDFCodecError, and a decode that succeeds is the map's true decode. Runs
    SDFCODEC_FUZZ_EXAMPLES cases (20; the slow suite's long run sets 10,000)."""
    from hypothesis import HealthCheck, given, settings, strategies as st

    from sdfcodec.errors import SDFCodecError
    from sdfcodec.map.manifest import sha256_hex

    ref = sdfcodec.open_map(maps / name).decode_region()
    base = tmp_path_factory.mktemp("fuzz") / name
    shutil.copytree(maps / name, base)
    doc0 = json.loads((base / "manifest.json").read_text())
    root0 = json.loads((base / "zarr.json").read_text())
    outcomes = {"refused": 0, "decoded": 0}

    @settings(max_examples=FUZZ_EXAMPLES, deadline=None, derandomize=True, database=None,
              suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
    @given(st.data())
    def case(data):
        raw = _mutate(json.loads(json.dumps(doc0)), data)
        (base / "manifest.json").write_bytes(raw)
        root = json.loads(json.dumps(root0))
        try:
            n = len(json.loads(raw).get("objects"))
        except Exception:  # noqa: BLE001 - not a dict of objects: any count
            n = 1
        root["attributes"]["sdfcodec"]["manifest"] = {"sha256": sha256_hex(raw), "size": max(2, len(raw)),
                                                      "objects": n}
        (base / "zarr.json").write_text(json.dumps(root))
        try:
            got = sdfcodec.open_map(base).decode_region()
        except SDFCodecError as e:
            assert str(e).strip() and "\n" not in str(e).strip()
            outcomes["refused"] += 1
        else:
            np.testing.assert_array_equal(got, ref)
            outcomes["decoded"] += 1
        rep = verify_map(base, decode_blocks=4)  # never raises; a foreign exception is an internal-error problem
        assert not any(p.where == "verify" for p in rep.problems), rep.problems

    case()
    assert outcomes["refused"] > FUZZ_EXAMPLES // 2, outcomes
