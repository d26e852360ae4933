"""Signing a local map in place, atomically (spec/map-format.md section 9c): :func:`sign_map` checks every object
against the map's manifest, then swaps in a new version that holds the signature (the keys and the signature
document are :mod:`sdfcodec.map.signing`). Apart from it because it opens the map with the reader, which itself
checks signatures through :mod:`~sdfcodec.map.signing`."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from ..core import _atomic
from ..errors import FormatError, IntegrityError, InvalidValueError, SDFCodecError, WriteFailedError
from .io.stores import MAX_METADATA_BYTES, is_url
from .manifest import SIGNATURE_KEY, object_problems
from .opening import open_reader
from .signing import key_id, load_private_key, signature_document

__all__ = ["sign_map"]


def sign_map(path: str | os.PathLike, key: Any, *, wait: float = 60.0) -> str:
    """Sign the local directory map at ``path`` with the Ed25519 private ``key`` (a key object or file, see
    :func:`load_private_key`), replacing any signature it had; returns the key's id.

    Every object is first checked against the map's manifest (a changed map is never signed). The signed map is
    a new version swapped into place as a writer's commit is (spec section 9): interrupted or failing, the map
    at ``path`` is the one before, never half-signed.

    Raises:
        IntegrityError: the map has no manifest, or an object does not match it. MapBusyError: another writer
        held it for ``wait`` seconds. WriteFailedError: the file system refused the write (nothing changed).
    """
    k = load_private_key(key)
    final = Path(path)
    if is_url(str(path)) or not final.is_dir():
        raise InvalidValueError(f"only local directory maps are signed, got {path} (sign it locally, then upload)")
    outcome = "the map there is unchanged and no temporary files are left"
    tmp = tmp_fd = None
    try:
        with _atomic.WriterLock(final, wait):
            src = open_reader(final, trusted_keys=(), verify_chunks=True)
            try:
                h = src.header
                if h.manifest is None:
                    raise IntegrityError(f"{final} has no integrity manifest to sign: write it again with this "
                                         "sdfcodec (e.g. `sdfcodec encode OLD NEW`), then sign the new map")
                store = src.group.store
                bad = object_problems(store, store.manifest, listing=True)
                if bad:
                    raise IntegrityError(f"{final} does not match its manifest ({bad[0]}"
                                         f"{f' and {len(bad) - 1} more' if len(bad) > 1 else ''}); not signed")
                root_doc = store.read_small("zarr.json", MAX_METADATA_BYTES)
                source = os.stat(final)
                _collect_quietly(final)  # what signers or writers killed earlier left
                tmp, tmp_fd = _atomic.make_temp_dir(final)
                _atomic.link_tree(src.local_root(), tmp)
            finally:
                src.close()
            _atomic.write_new_file(tmp / SIGNATURE_KEY, signature_document(k, root_doc, h))
            now = os.stat(final)
            if (now.st_dev, now.st_ino) != (source.st_dev, source.st_ino):
                raise FormatError(f"{final} was replaced while being signed; nothing was changed: sign it again")
            _atomic.swap_into_place(tmp, final)
            tmp = None
    except SDFCodecError:
        raise
    except OSError as e:
        raise WriteFailedError.from_os_error(e, final, "signing the map", outcome) from e
    finally:
        if tmp is not None:
            _atomic.remove_tree(tmp)
        if tmp_fd is not None:
            os.close(tmp_fd)
    _collect_quietly(final)
    return key_id(k.public_key())


def _collect_quietly(final: Path) -> None:
    try:
        _atomic.collect(final)
    except OSError:
        pass  # best effort: the next commit tries again
