"""Signed maps (spec/map-format.md section 9c): ``sdfcodec sign`` and ``keygen``, ``open_map(trusted_keys=...)``
and ``--trusted-key``. Keys are made in the tests (cryptography, openssl where installed)."""

from __future__ import annotations

import errno
import json
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

import sdfcodec
from sdfcodec.cli import app
import sdfcodec.map.sign
from sdfcodec.errors import FormatError, IntegrityError, SignatureError, WriteFailedError
from sdfcodec.map.verify import verify_map

pytest.importorskip("cryptography")
from cryptography.hazmat.primitives import serialization  # noqa: E402
from cryptography.hazmat.primitives.asymmetric import ed25519  # noqa: E402

VS = 0.02
runner = CliRunner()


def run(*args):
    return runner.invoke(app, [str(a) for a in args])


@pytest.fixture(scope="module")
def keys(tmp_path_factory):
    d = tmp_path_factory.mktemp("keys")
    r = run("keygen", d / "maker")
    assert r.exit_code == 0, r.output
    r = run("keygen", d / "other")
    assert r.exit_code == 0, r.output
    return d


@pytest.fixture(scope="module")
def signed(tmp_path_factory, volume, pca64, keys):
    root = tmp_path_factory.mktemp("signed")
    with sdfcodec.create_map(root / "plain", codec=pca64, voxel_size=VS, chunk_blocks=2) as m:
        m.write_volume(volume)
    shutil.copytree(root / "plain", root / "signed")
    r = run("sign", root / "signed", "--key", keys / "maker")
    assert r.exit_code == 0, r.output
    return root


def copy(src: Path, tmp_path: Path) -> Path:
    dst = tmp_path / src.name
    shutil.copytree(src, dst)
    return dst


def files(p: Path) -> dict[str, bytes]:
    return {f.relative_to(p).as_posix(): f.read_bytes() for f in sorted(p.rglob("*")) if f.is_file()}


def test_keygen_writes_a_private_and_a_public_pem(keys):
    priv = serialization.load_pem_private_key((keys / "maker").read_bytes(), None)
    pub = serialization.load_pem_public_key((keys / "maker.pub").read_bytes())
    assert isinstance(priv, ed25519.Ed25519PrivateKey)
    assert priv.public_key().public_bytes_raw() == pub.public_bytes_raw()
    assert (keys / "maker").stat().st_mode & 0o077 == 0  # the private key is the owner's alone
    r = run("keygen", keys / "maker")
    assert r.exit_code == 1 and "exists" in r.stderr


def test_a_signed_map_opens_with_its_key_and_decodes_the_same(signed, keys):
    a = sdfcodec.open_map(signed / "plain").decode_region()
    m = sdfcodec.open_map(signed / "signed", trusted_keys=[keys / "maker.pub"])
    np.testing.assert_array_equal(m.decode_region(), a)
    # signing changed nothing but adding the signature
    before, after = files(signed / "plain"), files(signed / "signed")
    assert set(after) - set(before) == {"signature.json"} and all(after[k] == before[k] for k in before)
    doc = json.loads((signed / "signed" / "signature.json").read_text())
    assert doc["algorithm"] == "ed25519" and len(bytes.fromhex(doc["signature"])) == 64
    r = run("decode", signed / "signed", signed / "out.npy", "--trusted-key", keys / "maker.pub")
    assert r.exit_code == 0, r.output
    rep = verify_map(signed / "signed", trusted_keys=[keys / "maker.pub"])
    assert rep.ok and rep.integrity["signature"]["valid"], rep.problems
    r = run("info", signed / "signed")
    assert r.exit_code == 0 and "signed by key" in r.stdout
    r = run("verify", signed / "signed", "--trusted-key", keys / "maker.pub")
    assert r.exit_code == 0 and "signature valid" in r.stdout


@pytest.mark.parametrize("command", ["decode", "verify", "info", "mesh", "search"])
def test_unsigned_and_wrongly_signed_maps_are_refused_with_keys(signed, keys, tmp_path, command):
    out = {"decode": [tmp_path / "o.npy"], "mesh": [tmp_path / "o.ply"], "search": ["--no-mesh"],
           "verify": [], "info": []}[command]
    for path, key, says in ((signed / "plain", keys / "maker.pub", "not signed"),
                            (signed / "signed", keys / "other.pub", "not among the trusted keys")):
        r = run(command, path, *out, "--trusted-key", key)
        assert r.exit_code == 1, (command, r.output)
        text = r.stdout if command == "verify" else r.stderr.strip()
        assert says in text, (command, text)
        if command != "verify":
            assert "\n" not in text
    with pytest.raises(SignatureError, match="not signed"):
        sdfcodec.open_map(signed / "plain", trusted_keys=[keys / "maker.pub"])


def test_changed_after_signing_is_refused(signed, keys, tmp_path):
    trust = [keys / "maker.pub"]
    # a chunk moved: the manifest refuses it
    p = copy(signed / "signed", tmp_path / "a")
    a, b = p / "codes/c/0/0/0/0", p / "codes/c/1/1/0/0"
    a.write_bytes(b.read_bytes())  # a sound chunk at another chunk's key
    with pytest.raises(IntegrityError, match="codes/c/0/0/0/0"):
        sdfcodec.open_map(p, trusted_keys=trust).decode_region()
    assert not verify_map(p, trusted_keys=trust).ok
    # the header changed (voxel size): the signature no longer holds
    p = copy(signed / "signed", tmp_path / "b")
    doc = json.loads((p / "zarr.json").read_text())
    doc["attributes"]["sdfcodec"]["voxel_size"] = 0.05
    (p / "zarr.json").write_text(json.dumps(doc))
    with pytest.raises(SignatureError, match="changed after signing"):
        sdfcodec.open_map(p, trusted_keys=trust)
    rep = verify_map(p)  # without keys: still a problem, a signature that does not hold
    assert not rep.ok and any("changed after signing" in x.message for x in rep.problems)
    # everything rewritten consistently (a chunk, the manifest, the header): only the signature catches it
    p = copy(signed / "signed", tmp_path / "c")
    a, b = p / "codes/c/0/0/0/0", p / "codes/c/1/1/0/0"
    a.write_bytes(b.read_bytes())
    from sdfcodec.map.manifest import write_manifest

    (p / "signature.json").rename(tmp_path / "sig")
    ref = write_manifest(p)
    (tmp_path / "sig").rename(p / "signature.json")
    doc = json.loads((p / "zarr.json").read_text())
    doc["attributes"]["sdfcodec"]["manifest"] = ref.model_dump()
    (p / "zarr.json").write_text(json.dumps(doc))
    sdfcodec.open_map(p).decode_region()  # consistent: without keys, nothing says who made it
    with pytest.raises(SignatureError):
        sdfcodec.open_map(p, trusted_keys=trust)
    # a signature copied from another signed map (its own key, its own header)
    p = copy(signed / "signed", tmp_path / "d")
    other = copy(signed / "plain", tmp_path / "e")
    with sdfcodec.update_map(other) as m:
        m.mark_empty([[0, 0, 0]])
    sdfcodec.map.sign.sign_map(other, keys / "maker")
    shutil.copy(other / "signature.json", p / "signature.json")
    with pytest.raises(SignatureError, match="changed after signing"):
        sdfcodec.open_map(p, trusted_keys=trust)


def test_raw_and_openssl_keys(signed, tmp_path):
    seed = bytes(range(32))
    (tmp_path / "raw.key").write_bytes(seed)
    pub = ed25519.Ed25519PrivateKey.from_private_bytes(seed).public_key().public_bytes_raw()
    (tmp_path / "raw.pub").write_bytes(pub)
    p = copy(signed / "plain", tmp_path / "m")
    sdfcodec.map.sign.sign_map(p, tmp_path / "raw.key")
    sdfcodec.open_map(p, trusted_keys=[tmp_path / "raw.pub"])
    sdfcodec.open_map(p, trusted_keys=[pub])  # the raw bytes themselves
    if shutil.which("openssl") is None:
        pytest.skip("openssl not installed: the PEM it writes is what keygen writes (PKCS8 / SubjectPublicKeyInfo)")
    subprocess.run(["openssl", "genpkey", "-algorithm", "ed25519", "-out", tmp_path / "o.pem"], check=True)
    subprocess.run(["openssl", "pkey", "-in", tmp_path / "o.pem", "-pubout", "-out", tmp_path / "o.pub"], check=True)
    r = run("sign", p, "--key", tmp_path / "o.pem")
    assert r.exit_code == 0, r.output
    sdfcodec.open_map(p, trusted_keys=[tmp_path / "o.pub"])
    with pytest.raises(SignatureError, match="not among the trusted keys"):
        sdfcodec.open_map(p, trusted_keys=[tmp_path / "raw.pub"])


def test_bad_key_files_are_one_line(signed, tmp_path):
    (tmp_path / "junk").write_text("not a key")
    for args in (("decode", signed / "signed", tmp_path / "o.npy", "--trusted-key", tmp_path / "junk"),
                 ("decode", signed / "signed", tmp_path / "o.npy", "--trusted-key", tmp_path / "absent"),
                 ("sign", signed / "plain", "--key", tmp_path / "junk")):
        r = run(*args)
        assert r.exit_code == 1 and r.stderr.strip() and "\n" not in r.stderr.strip(), r.output


def test_signing_is_atomic(signed, keys, tmp_path, monkeypatch):
    from sdfcodec.core import _atomic

    p = copy(signed / "signed", tmp_path / "m")
    before = files(p)

    def full(path, data, exclusive=False):
        raise OSError(errno.ENOSPC, "No space left on device", str(path))

    monkeypatch.setattr(_atomic, "write_new_file", full)
    with pytest.raises(WriteFailedError, match="No space left"):
        sdfcodec.map.sign.sign_map(p, keys / "other")
    monkeypatch.undo()
    assert files(p) == before  # the previous signature, untouched
    assert [e.name for e in p.parent.iterdir()] == [p.name]  # no temporary copy (nor lock) left
    sdfcodec.open_map(p, trusted_keys=[keys / "maker.pub"])


def test_sign_refuses_a_changed_or_unmanifested_map(signed, keys, tmp_path, volume, pca64):
    p = copy(signed / "plain", tmp_path / "m")
    a = p / "codes/c/0/0/0/0"
    a.write_bytes((p / "codes/c/1/1/0/0").read_bytes())
    with pytest.raises(IntegrityError, match="not signed"):
        sdfcodec.map.sign.sign_map(p, keys / "maker")
    assert not (p / "signature.json").exists()
    with sdfcodec.create_map(tmp_path / "old", codec=pca64, voxel_size=VS, manifest=False) as m:
        m.write_volume(volume[:32, :32, :32])
    r = run("sign", tmp_path / "old", "--key", keys / "maker")
    assert r.exit_code == 1 and "no integrity manifest" in r.stderr


def test_an_update_drops_the_signature(signed, keys, tmp_path):
    p = copy(signed / "signed", tmp_path / "m")
    with sdfcodec.update_map(p) as m:
        m.mark_empty([[0, 0, 0]])
    assert not (p / "signature.json").exists()
    assert verify_map(p).ok
    with pytest.raises(SignatureError, match="not signed"):
        sdfcodec.open_map(p, trusted_keys=[keys / "maker.pub"])
