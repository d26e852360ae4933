"""The integrity manifest of a map (spec/map-format.md section 9b, extension ``integrity-manifest``): the
SHA-256 of every object the map stores, keyed by its path, in the document ``manifest.json`` at the map's
root, whose own SHA-256 and size the header records (``manifest``).

CRC32C (every chunk's last four bytes) and the codec state digest catch accidents. They cannot catch a chunk
moved to another key (two chunks swapped, along the block axes or the code axis), a chunk rewritten with its CRC
recomputed, a shard index entry pointing at another chunk, or a server sending another map's objects under the
right names: each of those is a sound object in the wrong place. The manifest binds each object's bytes to its
key, so a reader refuses any of them (:meth:`Manifest.check`, called by
:class:`~sdfcodec.map.io.stores.GuardStore` on every read, the fast local path included), and ``verify`` checks
every listed object and that nothing stored is unlisted. It does not say who wrote the map: anyone who can
rewrite the map can rewrite the manifest and the header too; a signature over the header
(:mod:`sdfcodec.map.signing`) does.

Writers (:func:`build_manifest`) hash the files of the new version in its temporary directory at commit, after
shards are packed, so the manifest is swapped into place with the rest (spec section 9). The objects of a
sharded array are listed whole, and again as its index and each stored chunk (a reader fetches those as byte
ranges and checks each on its own).

SHA-256 (not BLAKE2): the digest the header already uses for codec state, checkable with ``sha256sum`` and any
language's standard library, and hardware-accelerated (SHA-NI, ARMv8 SHA2) where BLAKE2 is not.
"""

from __future__ import annotations

import base64
import binascii
import hashlib
import json
import math
import os
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Iterable

import numpy as np
from zarr.abc.store import RangeByteRequest, SuffixByteRequest

from ..errors import FormatError, IntegrityError
from ..core.header import MAX_MANIFEST_BYTES, ManifestRef
from .io.shards import index_size

if TYPE_CHECKING:
    from zarr.abc.store import Store

__all__ = ["VERSION", "manifest_bytes_estimate", "MANIFEST_KEY", "SIGNATURE_KEY", "UNLISTED", "Manifest", "build_manifest", "manifest_ref",
           "manifest_placeholder",
           "load_manifest", "sha256_hex", "set_check_default", "check_default", "object_problems",
           "previous_digests", "write_manifest"]

#: Where the manifest lives, relative to the map's root (fixed: never taken from the map).
MANIFEST_KEY = "manifest.json"
#: Where a signature lives (:mod:`sdfcodec.map.signing`).
SIGNATURE_KEY = "signature.json"
#: Keys a manifest never lists: the root document holds the header that holds the manifest's digest, and the
#: signature is made after the manifest.
UNLISTED = frozenset({"zarr.json", MANIFEST_KEY, SIGNATURE_KEY})
_FORMAT = "sdfcodec-manifest"
#: The version writers write: 2 spells each SHA-256 as 43 characters of unpadded base64url, not 64 hex digits
#: (168 bytes of the kitchen half's 773 at 64 B per block: a fifth of its documents' bytes are digests);
#: version 1 (hex) is still read.
VERSION = 2
_HEX = frozenset("0123456789abcdef")
_B64 = frozenset("ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789-_")
#: Longest key a manifest may list (a map's keys are a few dozen characters).
_MAX_KEY = 512


def sha256_hex(data: Any) -> str:
    """The SHA-256 of ``data`` (bytes-like, read in place) as 64 lowercase hex digits."""
    return hashlib.sha256(data).hexdigest()


_CHECK = [True]


def set_check_default(check: bool = True) -> None:
    """Whether maps opened from now on in this process check each chunk against their manifest (the default;
    ``--no-verify-chunks`` turns it off, for benchmarks only)."""
    _CHECK[0] = bool(check)


def check_default() -> bool:
    """See :func:`set_check_default`."""
    return _CHECK[0]


class Manifest:
    """A parsed manifest: ``objects`` key -> SHA-256 (hex) of every listed object, ``shards`` shard key ->
    ``(index digest, {(offset, nbytes): chunk digest})``. ``where`` names the map in errors."""

    def __init__(self, objects: dict[str, str], shards: dict[str, tuple[str, dict[tuple[int, int], str]]],
                 where: str, digest: str):
        self.objects, self.shards, self.where, self.digest = objects, shards, where, digest

    def _refuse(self, key: str, what: str) -> IntegrityError:
        if "/c/" in key:
            array, chunk = key.rsplit("/c/", 1)
            name = f"chunk c/{chunk} of array '{array}' ({key})"
        elif key.endswith("/zarr.json"):
            name = f"the metadata of '{key[:-len('/zarr.json')]}' ({key})"
        else:
            name = key
        return IntegrityError(f"{self.where}: {name} {what}; its bytes were changed, moved or come from another "
                              "map: refused (restore the map from a copy; `sdfcodec verify` lists every such object)")

    def check(self, key: str, data: Any, byte_range: Any = None) -> None:
        """Refuse ``data`` (bytes-like; None: the store has nothing at ``key``) read at ``key`` (``byte_range``:
        the Zarr byte request, for shards) unless the manifest lists exactly those bytes there.

        Raises:
            IntegrityError: one line naming the map, the array and the key.
        """
        if key in UNLISTED:
            return
        if byte_range is None:
            want = self.objects.get(key)
            if data is None:
                if want is not None:
                    raise self._refuse(key, "is listed in the manifest but missing")
                return
            if want is None:
                raise self._refuse(key, "is not listed in the manifest")
            if sha256_hex(data) != want:
                raise self._refuse(key, "does not match its SHA-256 in the manifest")
            return
        shard = self.shards.get(key)
        if shard is None:
            raise self._refuse(key, "is read in byte ranges but the manifest lists it as no shard")
        if data is None:
            raise self._refuse(key, "is a shard listed in the manifest but missing")
        if isinstance(byte_range, SuffixByteRequest):
            if sha256_hex(data) != shard[0]:
                raise self._refuse(key, "has a shard index that does not match its SHA-256 in the manifest")
            return
        if isinstance(byte_range, RangeByteRequest):
            want = shard[1].get((int(byte_range.start), int(byte_range.end - byte_range.start)))
            if want is None:
                raise self._refuse(key, f"has bytes [{byte_range.start}, {byte_range.end}) read as a chunk, "
                                        "which the manifest lists as none")
            if sha256_hex(data) != want:
                raise self._refuse(key, f"has a chunk at bytes [{byte_range.start}, {byte_range.end}) that "
                                        "does not match its SHA-256 in the manifest")
            return
        raise self._refuse(key, f"is asked for a byte request ({type(byte_range).__name__}) readers never make")

    @classmethod
    def parse(cls, data: bytes, ref: ManifestRef, where: str) -> "Manifest":
        """The manifest in ``data``, checked against the header's ``ref`` (size and SHA-256 first, so nothing
        unbound is parsed) and for its structure.

        Raises:
            IntegrityError: the bytes are not those the header names. FormatError: not a manifest.
        """
        if len(data) != ref.size or sha256_hex(data) != ref.sha256:
            raise IntegrityError(f"{where}: {MANIFEST_KEY} ({len(data)} bytes) is not the manifest the header names "
                                 f"({ref.size} bytes, SHA-256 {ref.sha256[:16]}...): the map was altered or "
                                 "mixed with another; refused (restore it from a copy)")
        try:
            doc = json.loads(data.decode("utf-8"))
        except (UnicodeDecodeError, ValueError, RecursionError):
            raise FormatError(f"{where}: {MANIFEST_KEY} is not a JSON document; refused") from None
        bad = _structure_problem(doc, ref)
        if bad:
            raise FormatError(f"{where}: {MANIFEST_KEY} is malformed ({bad}); refused")
        hx = _hex if doc["version"] == 2 else str  # held as hex whatever the version
        shards = {k: (hx(v["index"]), {(int(o), int(n)): hx(h) for o, n, h in v["chunks"]})
                  for k, v in doc.get("shards", {}).items()}
        return cls({k: hx(h) for k, h in doc["objects"].items()}, shards, where, ref.sha256)


def _b64(hex_digest: str) -> str:
    """A SHA-256 given as 64 hex digits, as version 2 spells it: 43 characters of unpadded base64url."""
    return base64.urlsafe_b64encode(bytes.fromhex(hex_digest)).rstrip(b"=").decode()


def _hex(b64_digest: str) -> str:
    return base64.urlsafe_b64decode(b64_digest + "=").hex()


def _digest_ok(h: Any, version: int = 1) -> bool:
    if version == 1:
        return isinstance(h, str) and len(h) == 64 and set(h) <= _HEX
    try:  # canonical only: one spelling per digest (the last character's unused bits zero)
        return isinstance(h, str) and len(h) == 43 and set(h) <= _B64 and _b64(_hex(h)) == h
    except (ValueError, binascii.Error):
        return False


def _key_ok(k: Any) -> bool:
    return (isinstance(k, str) and 0 < len(k) <= _MAX_KEY and k not in UNLISTED and not k.startswith("/")
            and all(p not in ("", ".", "..") for p in k.split("/")))


def _structure_problem(doc: Any, ref: ManifestRef) -> str | None:
    version = doc.get("version") if isinstance(doc, dict) else None
    if not isinstance(doc, dict) or doc.get("format") != _FORMAT or version not in (1, 2) \
            or isinstance(version, bool):
        return f"not a {_FORMAT} version 1 or 2 document"
    what = "64 hex digits" if version == 1 else "43 base64url characters"
    if doc.get("algorithm") != "sha256":
        return f"algorithm {doc.get('algorithm')!r}, not 'sha256'"
    objects, shards = doc.get("objects"), doc.get("shards", {})
    if not isinstance(objects, dict) or not isinstance(shards, dict):
        return "'objects' and 'shards' must be objects"
    if len(objects) != ref.objects:
        return f"{len(objects)} objects, the header says {ref.objects}"
    for k, h in objects.items():
        if not _key_ok(k) or not _digest_ok(h, version):
            return f"entry {str(k)[:80]!r}: a relative key and a SHA-256 of {what} are required"
    for k, v in shards.items():
        if k not in objects or not isinstance(v, dict) or not _digest_ok(v.get("index"), version) \
                or not isinstance(v.get("chunks"), list):
            return f"shard {str(k)[:80]!r}: a listed object with an index digest and a list of chunks is required"
        for c in v["chunks"]:
            if not (isinstance(c, list) and len(c) == 3 and all(isinstance(x, int) and not isinstance(x, bool)
                                                                and x >= 0 for x in c[:2]) and _digest_ok(c[2], version)):
                return f"shard {k!r}: each chunk is [offset, nbytes, sha256]"
    return None


def _sharded_arrays(root: Path) -> dict[str, int]:
    """Array path -> chunks per shard of every sharded array in the map directory ``root``."""
    out = {}
    for dirpath, _, files in os.walk(root):
        if "zarr.json" not in files or Path(dirpath) == root:
            continue
        try:
            meta = json.loads((Path(dirpath) / "zarr.json").read_bytes())
            codec = meta["codecs"][0]
            if codec["name"] == "sharding_indexed":
                inner = codec["configuration"]["chunk_shape"]
                outer = meta["chunk_grid"]["configuration"]["chunk_shape"]
                out[Path(dirpath).relative_to(root).as_posix()] = math.prod(s // c for s, c in zip(outer, inner))
        except (ValueError, KeyError, IndexError, TypeError):
            continue  # not an array sdfcodec wrote sharded: listed as a plain object
    return out


def _shard_entry(data: bytes, per: int) -> dict[str, Any]:
    n = index_size(per)
    index = np.frombuffer(data[len(data) - n:-4], dtype="<u8").reshape(per, 2)
    empty = np.uint64(2 ** 64 - 1)
    chunks = [[int(o), int(s), sha256_hex(memoryview(data)[int(o):int(o + s)])]
              for o, s in index if not (o == empty and s == empty)]
    return {"index": sha256_hex(memoryview(data)[len(data) - n:]), "chunks": chunks}


def build_manifest(root: str | os.PathLike, reuse: Callable[[str, os.stat_result], str | None] | None = None
                   ) -> tuple[bytes, int]:
    """The manifest document of the map directory ``root`` (a writer's temporary copy, complete but for its
    root ``zarr.json``) and how many objects it lists. ``reuse(key, stat)`` may return the digest of a file an
    update copied unchanged from the previous version (its previous manifest entry), sparing a read of it.

    Raises:
        OSError: a file could not be read (the writer turns it into WriteFailedError).
        InvalidValueError: the manifest would exceed :data:`~sdfcodec.core.header.MAX_MANIFEST_BYTES`.
    """
    from ..errors import InvalidValueError

    root = Path(root)
    sharded = _sharded_arrays(root)
    objects: dict[str, str] = {}
    shards: dict[str, Any] = {}
    for dirpath, dirnames, files in os.walk(root):
        dirnames.sort()
        rel_dir = Path(dirpath).relative_to(root).as_posix()
        for name in sorted(files):
            key = name if rel_dir == "." else f"{rel_dir}/{name}"
            if key in UNLISTED:
                continue
            path = Path(dirpath) / name
            array = next((a for a in sharded if key.startswith(a + "/c/")), None)
            if array is not None:
                data = path.read_bytes()
                objects[key] = sha256_hex(data)
                shards[key] = _shard_entry(data, sharded[array])
                continue
            hit = reuse(key, os.stat(path)) if reuse is not None else None
            if hit is None:
                with open(path, "rb") as f:
                    hit = hashlib.file_digest(f, "sha256").hexdigest()
            objects[key] = hit
    data = _document(objects, shards)
    if len(data) > MAX_MANIFEST_BYTES:
        raise InvalidValueError(f"the map's manifest would take {len(data)} bytes, above the format's limit of "
                                f"{MAX_MANIFEST_BYTES} ({len(objects)} objects): store fewer, larger objects "
                                "(larger --chunk-blocks, or --shard-blocks)")
    return data, len(objects)


def _document(objects: dict[str, str], shards: dict[str, Any]) -> bytes:
    """The manifest document's bytes (compact JSON, keys sorted, version :data:`VERSION`) of ``objects`` and
    ``shards`` as :func:`build_manifest` makes them (hex digests)."""
    doc = {"format": _FORMAT, "version": VERSION, "algorithm": "sha256",
           "objects": {k: _b64(h) for k, h in objects.items()}}
    if shards:
        doc["shards"] = {k: {"index": _b64(v["index"]), "chunks": [[o, n, _b64(h)] for o, n, h in v["chunks"]]}
                         for k, v in shards.items()}
    return json.dumps(doc, separators=(",", ":"), sort_keys=True).encode()


def manifest_bytes_estimate(keys: Iterable[str]) -> int:
    """The size of the manifest that will list ``keys`` (unsharded objects): exact, since a digest's length is
    fixed; what rate control counts before the files exist."""
    return len(_document({k: "0" * 64 for k in keys if k not in UNLISTED}, {}))


def manifest_placeholder(keys: Iterable[str]) -> ManifestRef:
    """A record of the manifest that will list ``keys`` as long as the real one (digest zeros): what rate control
    counts in the root document before the manifest exists."""
    listed = [k for k in keys if k not in UNLISTED]
    return ManifestRef(sha256="0" * 64, size=manifest_bytes_estimate(listed), objects=len(listed))


def manifest_ref(data: bytes, objects: int) -> ManifestRef:
    """The header's record of the manifest document ``data`` listing ``objects`` objects."""
    return ManifestRef(sha256=sha256_hex(data), size=len(data), objects=objects)


def load_manifest(read: Callable[[str, int], bytes | None], ref: ManifestRef | None, where: str
                  ) -> Manifest | None:
    """The manifest of a map whose header records ``ref`` (None: the map has none), read through
    ``read(key, max_bytes)``.

    Raises:
        IntegrityError: the manifest is missing or not the one the header names. FormatError: malformed.
    """
    if ref is None:
        return None
    try:
        data = read(MANIFEST_KEY, ref.size)
    except IntegrityError:
        raise
    except FormatError as e:  # larger than the header says
        raise IntegrityError(f"{where}: {e}: not the manifest the header names; the map was altered or mixed with "
                             "another (restore it from a copy)") from None
    if data is None:
        raise IntegrityError(f"{where}: the header names a manifest ({MANIFEST_KEY}) but the map has none: it was "
                             "altered or copied incompletely; refused (restore it from a copy)")
    return Manifest.parse(bytes(data), ref, where)



def _stored_keys(store: Store) -> list[str] | None:
    """Every key a local directory or zip map stores (None for stores that cannot be listed: remote maps)."""
    from .io.stores import SafeLocalStore, SafeZipStore, unguarded

    inner = unguarded(store)
    if isinstance(inner, SafeZipStore):
        return inner.member_names()
    root = getattr(inner, "root", None)
    if not isinstance(inner, SafeLocalStore) or root is None:
        return None
    out = []
    for dirpath, _, files in os.walk(root):
        rel = Path(dirpath).relative_to(root).as_posix()
        out += [f if rel == "." else f"{rel}/{f}" for f in files]
    return out


def object_problems(store: Store, manifest: Manifest, *, listing: bool = True, limit: int = 1000) -> list[str]:
    """Every way the objects of the map behind ``store`` (a :class:`~sdfcodec.map.io.stores.GuardStore` checking
    against ``manifest``) differ from it: each listed object read and checked (a shard's index and chunks too),
    and with ``listing`` each stored object the manifest does not list (local and zip maps). At most
    ``limit`` problems are collected."""
    import asyncio

    from zarr.core.sync import sync

    from ..errors import SDFCodecError

    problems: list[str] = []
    keys = sorted(manifest.objects)

    async def one(key: str) -> str | None:
        try:
            # the guard checks the digest (and the size bounds it knows); a shard whole, so its index and chunk
            # entries, derived from those bytes by the writer, need no second look
            await store.get(key)
        except SDFCodecError as e:
            return str(e)
        return None

    async def batch(ks: list[str]) -> list[str | None]:
        return await asyncio.gather(*(one(k) for k in ks))

    for i in range(0, len(keys), 64):
        problems += [p for p in sync(batch(keys[i:i + 64])) if p]
        if len(problems) >= limit:
            return problems[:limit]
    if listing:
        stored = _stored_keys(store)
        if stored is not None:
            extra = sorted(set(stored) - set(manifest.objects) - UNLISTED)
            problems += [f"{manifest.where}: {k} is stored but not listed in the manifest (added or renamed after "
                         "the map was written)" for k in extra[:max(0, limit - len(problems))]]
    return problems



def previous_digests(final: str | os.PathLike, manifest: Manifest | None
                     ) -> Callable[[str, os.stat_result], str | None] | None:
    """For an update of the map at ``final`` (whose current version ``manifest`` describes): the ``reuse``
    argument of :func:`build_manifest`, giving the listed digest of a file the update left as the hard link it
    copied (same device and inode as in the current version), so a commit reads only what changed. A file
    altered since it was listed keeps its listed digest, and so stays detectable."""
    if manifest is None:
        return None
    final = Path(final)

    def reuse(key: str, st: os.stat_result) -> str | None:
        try:
            src = os.stat(final / key, follow_symlinks=False)
        except OSError:
            return None
        return manifest.objects.get(key) if (src.st_dev, src.st_ino) == (st.st_dev, st.st_ino) else None

    return reuse


def write_manifest(root: str | os.PathLike, reuse: Callable[[str, os.stat_result], str | None] | None = None
                   ) -> ManifestRef:
    """Write the manifest of the map directory ``root`` (a writer's temporary copy, complete but for its root
    document) as ``manifest.json`` there, dropping a signature copied from the previous version (it signed
    that version); returns the header's record of it."""
    from ..core import _atomic

    root = Path(root)
    sig = root / SIGNATURE_KEY
    if os.path.lexists(sig):
        os.unlink(sig)  # a link to the previous version's file: that file stays as it is
    data, n = build_manifest(root, reuse)
    _atomic.write_new_file(root / MANIFEST_KEY, data)
    return manifest_ref(data, n)
