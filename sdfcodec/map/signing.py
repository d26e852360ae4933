"""Who made a map (spec/map-format.md section 9c): an Ed25519 signature over the map's root document (the header,
which records the SHA-256 of the integrity manifest, which records the SHA-256 of every other object), kept in
``signature.json`` at the map's root; keys a reader trusts (:func:`open_map(..., trusted_keys=...)
<sdfcodec.open_map>`, ``--trusted-key``); the signature document of a map (:func:`signature_document`; signing a map in place, atomically, is
:func:`sdfcodec.map.sign.sign_map`); and making a key pair (:func:`keygen`).

A map with an integrity manifest (section 9b) but no signature proves only that its objects are where its
writer put them. With keys to trust, a reader refuses a map that is unsigned, signed by a key it was not given,
or changed in any object after signing. Keys are read as PEM (what ``openssl genpkey -algorithm ed25519``
and :func:`keygen` write) or as the raw 32 bytes of an Ed25519 key. The ``cryptography`` package does the
Ed25519 arithmetic (the ``sign`` extra); it is imported only when a key is used.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path
from typing import Any, Callable, Iterable, Sequence

from ..core import _atomic
from ..errors import (InputNotFoundError, IntegrityError, InvalidValueError, MapExistsError, MissingDependencyError,
                      SignatureError)
from ..core.header import MapHeader
from .manifest import SIGNATURE_KEY, Manifest, load_manifest, sha256_hex
from .io.stores import MAX_METADATA_BYTES, GuardStore

__all__ = ["keygen", "load_public_key", "load_private_key", "key_id", "signature_document", "check_trust",
           "signature_status", "set_trust_defaults", "trust_default", "protect", "MAX_SIGNATURE_BYTES"]

_FORMAT = "sdfcodec-signature"
_CONTEXT = b"sdfcodec-map-signature-v1\n"
#: Largest signature document a reader loads (one is about 400 bytes).
MAX_SIGNATURE_BYTES = 4096
_TRUSTED: list[Any] = []


def _crypto():
    try:
        from cryptography.hazmat.primitives import serialization
        from cryptography.hazmat.primitives.asymmetric import ed25519
    except ImportError:  # pragma: no cover - the sign extra is not installed
        raise MissingDependencyError("signing and checking signatures needs the 'cryptography' package: "
                                     "pip install 'sdfcodec[sign]'") from None
    return serialization, ed25519


def _key_bytes(src: Any, what: str) -> tuple[bytes, str]:
    if isinstance(src, (bytes, bytearray)):
        return bytes(src), f"the {what} given as bytes"
    p = Path(src)
    try:
        if p.stat().st_size > 64 << 10:
            raise InvalidValueError(f"{p} is {p.stat().st_size} bytes: no Ed25519 key file; pass a PEM or raw key")
        return p.read_bytes(), str(p)
    except FileNotFoundError:
        raise InputNotFoundError(f"{what} file {p} does not exist") from None
    except IsADirectoryError:
        raise InvalidValueError(f"{what} {p} is a directory, not a key file") from None


def load_public_key(src: Any):
    """The Ed25519 public key in ``src``: a key object (public or private), raw bytes (32), or a file holding a
    PEM public or private key or the raw 32 bytes of a public key.

    Raises:
        SignatureError: not an Ed25519 key. InputNotFoundError: no such file.
    """
    serialization, ed25519 = _crypto()
    if isinstance(src, ed25519.Ed25519PublicKey):
        return src
    if isinstance(src, ed25519.Ed25519PrivateKey):
        return src.public_key()
    data, name = _key_bytes(src, "trusted key")
    if len(data) == 32:
        return ed25519.Ed25519PublicKey.from_public_bytes(data)
    try:
        if b"PRIVATE KEY" in data:
            key = serialization.load_pem_private_key(data, password=None).public_key()
        else:
            key = serialization.load_pem_public_key(data)
    except (ValueError, TypeError) as e:
        raise SignatureError(f"{name} is no key sdfcodec reads ({str(e).splitlines()[0]}): pass an Ed25519 "
                             "public key as PEM or its raw 32 bytes") from None
    if not isinstance(key, ed25519.Ed25519PublicKey):
        raise SignatureError(f"{name} is a {type(key).__name__}, not an Ed25519 key: make one with "
                             "`sdfcodec keygen` or `openssl genpkey -algorithm ed25519`")
    return key


def load_private_key(src: Any):
    """The Ed25519 private key in ``src``: a key object, or a file holding it as unencrypted PEM or as its raw
    32-byte seed.

    Raises:
        SignatureError: not an unencrypted Ed25519 private key. InputNotFoundError: no such file.
    """
    serialization, ed25519 = _crypto()
    if isinstance(src, ed25519.Ed25519PrivateKey):
        return src
    data, name = _key_bytes(src, "signing key")
    if len(data) == 32:
        return ed25519.Ed25519PrivateKey.from_private_bytes(data)
    try:
        key = serialization.load_pem_private_key(data, password=None)
    except (ValueError, TypeError) as e:
        raise SignatureError(f"{name} is no unencrypted private key sdfcodec reads ({str(e).splitlines()[0]}): "
                             "make one with `sdfcodec keygen KEY` or `openssl genpkey -algorithm ed25519 -out KEY`"
                             ) from None
    if not isinstance(key, ed25519.Ed25519PrivateKey):
        raise SignatureError(f"{name} is a {type(key).__name__}, not an Ed25519 private key")
    return key


def _raw(pub) -> bytes:
    serialization, _ = _crypto()
    return pub.public_bytes(serialization.Encoding.Raw, serialization.PublicFormat.Raw)


def key_id(pub) -> str:
    """A short name of a public key: the first 16 hex digits of the SHA-256 of its 32 raw bytes."""
    return hashlib.sha256(_raw(load_public_key(pub))).hexdigest()[:16]


def keygen(path: str | os.PathLike, *, overwrite: bool = False) -> tuple[Path, Path]:
    """Make an Ed25519 key pair: the private key as PEM at ``path`` (mode 0600), the public key as PEM at
    ``path`` + ``.pub``. Returns both paths.

    Raises:
        MapExistsError: either file exists and not ``overwrite``.
    """
    serialization, ed25519 = _crypto()
    priv_path = Path(path)
    pub_path = priv_path.with_name(priv_path.name + ".pub")
    for p in (priv_path, pub_path):
        if os.path.lexists(p) and not overwrite:
            raise MapExistsError(f"{p} exists; pass --overwrite to replace it (a replaced private key is lost)")
    key = ed25519.Ed25519PrivateKey.generate()
    pem = key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                            serialization.NoEncryption())
    pub = key.public_key().public_bytes(serialization.Encoding.PEM, serialization.PublicFormat.SubjectPublicKeyInfo)

    def write_private(tmp: Path) -> bool:
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        with os.fdopen(fd, "wb") as f:
            f.write(pem)
        return True

    _atomic.write_file(priv_path, write_private, "writing the private key")
    _atomic.write_file(pub_path, lambda tmp: bool(tmp.write_bytes(pub)), "writing the public key")
    return priv_path, pub_path


def set_trust_defaults(trusted_keys: Sequence[Any] | None = None) -> None:
    """Keys every map opened from now on in this process must be signed by (the ``--trusted-key`` option of the
    commands that read maps); None or empty: no signature required."""
    _TRUSTED[:] = [load_public_key(k) for k in trusted_keys or ()]


def trust_default() -> list[Any]:
    """See :func:`set_trust_defaults`."""
    return list(_TRUSTED)


def _message(root_sha256: str, manifest_sha256: str) -> bytes:
    return _CONTEXT + bytes.fromhex(root_sha256) + bytes.fromhex(manifest_sha256)


def _parse_signature(data: bytes, where: str) -> dict:
    try:
        doc = json.loads(data.decode("utf-8"))
    except (UnicodeDecodeError, ValueError, RecursionError):
        raise SignatureError(f"{where}: {SIGNATURE_KEY} is not a JSON document; refused") from None
    ok = (isinstance(doc, dict) and doc.get("format") == _FORMAT and doc.get("version") == 1
          and doc.get("algorithm") == "ed25519"
          and all(isinstance(doc.get(k), str) and len(doc[k]) == n and set(doc[k]) <= set("0123456789abcdef")
                  for k, n in (("public_key", 64), ("root_sha256", 64), ("manifest_sha256", 64), ("signature", 128))))
    if not ok:
        raise SignatureError(f"{where}: {SIGNATURE_KEY} is not an sdfcodec Ed25519 signature (version 1); refused")
    return doc


def signature_status(read: Callable[[str, int], bytes | None], root_doc: bytes, header: MapHeader, where: str
                     ) -> dict[str, Any]:
    """What the map's signature says: ``{"signed": False}``, or ``{"signed": True, "key": key id, "valid":
    bool, "problem": why not valid or None}``. ``read(key, max_bytes)`` reads the map's objects; ``root_doc`` is
    the root ``zarr.json`` the header was parsed from."""
    data = read(SIGNATURE_KEY, MAX_SIGNATURE_BYTES)
    if data is None:
        return {"signed": False}
    try:
        doc = _parse_signature(data, where)
    except SignatureError as e:
        return {"signed": True, "key": None, "valid": False, "problem": str(e)}
    _, ed25519 = _crypto()
    from cryptography.exceptions import InvalidSignature

    pub = ed25519.Ed25519PublicKey.from_public_bytes(bytes.fromhex(doc["public_key"]))
    out = {"signed": True, "key": key_id(pub), "valid": False, "problem": None}
    if header.manifest is None:
        out["problem"] = "the map has no integrity manifest for a signature to cover"
    elif doc["root_sha256"] != sha256_hex(root_doc) or doc["manifest_sha256"] != header.manifest.sha256:
        out["problem"] = "the header (zarr.json) changed after signing"
    else:
        try:
            pub.verify(bytes.fromhex(doc["signature"]), _message(doc["root_sha256"], doc["manifest_sha256"]))
            out["valid"] = True
        except InvalidSignature:
            out["problem"] = "the signature does not match the header it names (forged or damaged)"
    return out


def check_trust(read: Callable[[str, int], bytes | None], root_doc: bytes, header: MapHeader, where: str,
                trusted: Iterable[Any]) -> str:
    """Refuse the map unless a key of ``trusted`` signed it as it is; returns the signing key's id.

    Raises:
        SignatureError: one line saying what is wrong (unsigned, unknown key, changed after signing).
    """
    keys = {key_id(k): k for k in trusted}
    st = signature_status(read, root_doc, header, where)
    if not st["signed"]:
        raise SignatureError(f"{where} is not signed, and keys to trust were given "
                             f"({', '.join(sorted(keys))}); refused: ask its maker for a signed map "
                             "(`sdfcodec sign MAP --key KEY`)")
    if not st["valid"]:
        raise SignatureError(f"{where}: {st['problem']}; refused")
    if st["key"] not in keys:
        raise SignatureError(f"{where} is signed by key {st['key']}, which is not among the trusted keys "
                             f"({', '.join(sorted(keys))}); refused")
    return st["key"]


def protect(store: GuardStore, header: MapHeader, raw: Any, where: str, *, trusted_keys: Sequence[Any] | None,
            verify_chunks: bool) -> Manifest | None:
    """What a reader does after parsing the header ``raw`` of the map behind ``store``: load the integrity
    manifest the header records and have ``store`` check every object against it (unless not
    ``verify_chunks``), and with ``trusted_keys`` refuse the map unless one of them signed it.

    Raises:
        IntegrityError, SignatureError: as :func:`~sdfcodec.map.manifest.load_manifest` and
        :func:`check_trust`.
    """
    manifest = load_manifest(store.read_small, header.manifest, where)
    if trusted_keys:
        root_doc = store.read_small("zarr.json", MAX_METADATA_BYTES)
        try:
            same = json.loads(root_doc)["attributes"]["sdfcodec"] == raw
        except (TypeError, ValueError, KeyError):
            same = False
        if not same:  # a server answering twice differently: check what was parsed, or nothing
            raise SignatureError(f"{where}: the header read twice differs; refused")
        if manifest is None:
            raise SignatureError(f"{where} has no integrity manifest, so it cannot be signed, and keys to trust "
                                 "were given; refused: ask its maker for a signed map")
        check_trust(store.read_small, root_doc, header, where, trusted_keys)
    if verify_chunks:
        store.manifest = manifest
    return manifest


def signature_document(key: Any, root_doc: bytes, header: MapHeader) -> bytes:
    """The ``signature.json`` bytes signing a map's root document ``root_doc`` (whose header ``header`` records
    its manifest's SHA-256) with the Ed25519 private ``key`` object."""
    root_sha, man_sha = sha256_hex(root_doc), header.manifest.sha256
    doc = {"format": _FORMAT, "version": 1, "algorithm": "ed25519", "public_key": _raw(key.public_key()).hex(),
           "root_sha256": root_sha, "manifest_sha256": man_sha,
           "signature": key.sign(_message(root_sha, man_sha)).hex()}
    return (json.dumps(doc, indent=2) + "\n").encode()
