"""What ``sdfcodec info`` shows of a map: :func:`summarize` builds it (what :meth:`sdfcodec.Map.info` returns),
and :func:`local_info` reads it from a local map directory without importing Zarr.

Why a second way to read: ``info`` is a light command (held to 0.5 s), and importing Zarr costs 0.2-0.4 s
here, as much as the rest of the command. All ``info`` needs is the group's ``zarr.json`` (the header) and the
block states, one small uint8 array. :func:`local_info` reads those two from the pinned version of a plain local
map directory, with the same header parser and the same CRC32C check Zarr applies; anything it does not know for
certain (a zip, a URL, a symbolic link anywhere on its way (it opens every path component without
following one), a codec pipeline other than the ``bytes`` + Blosc + ``crc32c`` that sdfcodec writes, a checksum
that does not match or a Blosc frame whose structure does not hold (the guarded store's own checks,
:mod:`~sdfcodec.map.io.frames`), an array whose shape disagrees with the header) makes it return None, and the caller reads
the map the ordinary way, which gives the canonical answer or error. It never writes and never runs code from
the map; a header with an unknown required extension is refused by :func:`~sdfcodec.core.header.parse_header` as on
the ordinary path.
"""

from __future__ import annotations

import base64
import hashlib
import json
import math
import os
import stat
import sys
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from ..core._atomic import pin_dir, release_pin
from ..core._validate import BLOCK
from ..core.header import (APPROX_MASK_EXTENSION, CODED_MASK_EXTENSION, PINNED_MASK_EXTENSION, BlockState, MapHeader,
                           parse_header)
from ..errors import FormatError
from .implied import unpack_states
from .io.frames import blosc_frame_problem, crc32c_matches
from .io.metadata_limits import check_metadata_size

__all__ = ["summarize", "local_info", "dir_bytes", "integrity_line"]

#: the block-state array's chunks are at most this large decompressed (it is one byte per block; a bigger chunk
#: in a map's metadata is not one sdfcodec wrote): beyond it, the ordinary reader and its limits take over
_MAX_STATE_CHUNK = 1 << 28


def dir_bytes(path: str | os.PathLike) -> int | None:
    """Bytes of the files under ``path`` (a file's own size; None when nothing is there)."""
    p = Path(path)
    if p.is_file():
        return p.stat().st_size
    if not p.is_dir():
        return None
    return sum(f.stat().st_size for f in p.rglob("*") if f.is_file())


def summarize(h: MapHeader, location: str, root: str | None, counts: dict[str, int]) -> dict[str, Any]:
    """:meth:`sdfcodec.Map.info`: the header ``h`` of the map at ``location``, its blocks by state ``counts``,
    bytes on disk under ``root`` (its local directory, or None for a remote map) and ratio to dense float32."""
    dense = int(np.prod(h.shape_voxels)) * 4
    on_disk = dir_bytes(root) if root is not None else None
    # a map without a codec group (state by reference, or a codec that learns nothing) stores 0 bytes of state
    state_bytes = (dir_bytes(Path(root) / "codec") or 0) if on_disk is not None else None
    code_bytes = (sum(dir_bytes(Path(root) / a) or 0 for a in ("codes", "code_scale", "code_streams"))
                  if on_disk is not None else None)
    ref = h.codec.state_reference
    return {
        "location": location,
        "format_version": h.format_version,
        "codec": h.codec.config,
        "code_size": h.codes.size,
        "code_dtype": h.codes.dtype,
        "code_units": h.codes.units or "normalised",  # "metres": metric codes, bit-exact (spec 4f)
        "levels": h.codes.levels,
        # how the codes are stored beyond their dtype: variable-rate (a prefix per block, spec 4e) or int16 steps (4b)
        "code_storage": ("variable-rate" if h.codes.variable_rate is not None else
                         "quantised" if h.codes.quantisation is not None else "plain"),
        "chunk_blocks": h.codes.chunk_blocks,
        "shard_blocks": h.codes.shard_blocks,
        "voxel_size": h.voxel_size,
        "truncation": [h.truncation.d_min, h.truncation.d_max],
        "origin": list(h.origin),
        "shape_voxels": list(h.shape_voxels),
        "grid_blocks": list(h.grid_blocks),
        "blocks": counts,
        "code_bytes_raw": counts["coded"] * h.codes.stored_bytes(),
        "bytes_on_disk": on_disk,
        "dense_float32_bytes": dense,
        "codec_state_bytes": state_bytes,
        "ratio_dense_to_disk": (dense / on_disk) if on_disk else None,
        # the codec state (e.g. a PCA basis) is a fixed cost shared by a whole map: this ratio leaves it out
        "ratio_dense_to_codes": (dense / (on_disk - (state_bytes or 0))) if on_disk else None,
        "provenance": h.provenance.model_dump(),
        "code_bytes_on_disk": code_bytes,
        "codec_state": ({"stored": "reference", "model": ref.model, "sha256": ref.sha256} if ref is not None
                        else {"stored": "embedded", "sha256": h.codec.state_sha256}),
        "state_warning": _state_warning(state_bytes, code_bytes, h) if ref is None else None,
        "residual": _residual_info(h, root, counts["coded"]),
        # which voxels were observed (spec 6b), context-coded in maps that list coded-observation-mask (6e),
        # exact only where it decides the surface in maps that list approximate-observation-mask (6f), stored at
        # those voxels only in maps that list pinned-observation-mask (6g)
        "observation_mask": (None if not {"observation-mask", PINNED_MASK_EXTENSION} & (names := {e.name for e in
                                                                                             h.extensions}) else
                             ("pinned" if PINNED_MASK_EXTENSION in names else
                              "context-coded" if CODED_MASK_EXTENSION in names else "blosc")
                             + (", approximate" if APPROX_MASK_EXTENSION in names else "")),
        # spec 6h: the corrections' step and band in metres
        "refinement": (None if (ref6h := h.codes.variable_rate and h.codes.variable_rate.refinement) is None else
                       {"step": ref6h.step * 2.0 ** -24, "band": ref6h.tau * 2.0 ** -24}),
        "integrity": {"manifest": None if h.manifest is None else {"objects": h.manifest.objects,
                                                                    "sha256": h.manifest.sha256},
                      "signature": _signature_key(root) if root is not None else None},
    }


def _signature_key(root: str) -> dict[str, Any]:
    """What a local map's signature file names, unchecked (``verify`` and ``--trusted-key`` check it):
    ``{"signed": False}`` or ``{"signed": True, "key": its key id, "valid": None}``."""
    p = Path(root) / "signature.json"
    try:
        doc = json.loads(p.read_bytes()[:4096]) if p.is_file() and not p.is_symlink() else None
        key = hashlib.sha256(bytes.fromhex(doc["public_key"])).hexdigest()[:16] if doc is not None else None
    except (OSError, ValueError, TypeError, KeyError):
        return {"signed": True, "key": None, "valid": False, "problem": "signature.json is unreadable"}
    return {"signed": False} if doc is None else {"signed": True, "key": key, "valid": None}


def integrity_line(integrity: dict[str, Any]) -> str:
    """One line for ``info`` and ``verify``: a map's manifest and signature (spec sections 9b, 9c)."""
    man, sig = integrity.get("manifest"), integrity.get("signature")
    if man is None:
        return "no manifest (objects not bound to their keys), unsigned"
    text = f"manifest of {man['objects']} objects (sha256 {man['sha256'][:16]}...)"
    if sig is None:
        return text + " (signature: see verify)"
    if not sig.get("signed"):
        return text + ", unsigned"
    if sig.get("valid") is None:
        return text + f", signed by key {sig['key']} (checked by verify and --trusted-key)"
    if sig.get("valid"):
        return text + f", signed by key {sig['key']} (signature valid)"
    return text + f", signature INVALID ({sig.get('problem')})"


def _state_warning(state_bytes: int | None, code_bytes: int | None, h: MapHeader) -> str | None:
    """One line when the stored codec state outweighs the stored codes (None otherwise, or unknown: remote maps),
    with what to do: store it by reference when it is a shipped model's state, else use a shipped model."""
    if state_bytes is None or code_bytes is None or state_bytes <= code_bytes:
        return None
    from .codec_state import shipped_model_of  # loads the codec's plugin: only when there is something to say

    mib = 1 << 20
    model = shipped_model_of(h.codec.id, h.codes.size, h.codec.state_sha256)
    todo = (f"it is the shipped model {model}'s: for maps that share it, store it by reference (sdfcodec encode "
            "--codec-state reference; create_map(codec_state='reference')), readers then need that model in the "
            "installed plugin" if model is not None else
            "it is no shipped model's (fitted or trained): encode with a shipped model (no --fit or --model) and "
            "store that by reference (--codec-state reference), or accept the cost for a one-off map")
    return (f"the stored codec state ({state_bytes / mib:.2f} MiB) outweighs the codes ({code_bytes / mib:.2f} MiB) "
            f"by {(state_bytes - code_bytes) / mib:.2f} MiB; {todo}")


def _residual_info(h: MapHeader, root: str | None, coded: int) -> dict[str, Any] | None:
    """``info()["residual"]``: the residual stage's bound, step and bytes (None for a map without one)."""
    r = h.residual
    if r is None:
        return None
    nbytes = dir_bytes(Path(root) / "residual") if root is not None else None
    return {"extension": "residual-bound", "max_error": r.max_error, "sign_exact": r.sign_exact, "step": r.step,
            "dtype": r.dtype, "bytes_on_disk": nbytes,
            "bytes_per_coded_block": None if nbytes is None else nbytes / max(coded, 1),
            "holds_at": f"full level ({h.codes.size}) only: a prefix level decodes without the residual"}


def local_info(path: str | os.PathLike) -> dict[str, Any] | None:
    """:meth:`sdfcodec.Map.info` of the map directory at ``path``, read without Zarr; None when this light
    reader cannot be sure of the answer (see the module's docstring): open the map and ask it instead.

    Raises:
        FormatError, VersionError: the header is not one this version reads (as :func:`sdfcodec.open_map`).
    """
    if not isinstance(path, (str, os.PathLike)) or "://" in str(path):
        return None
    p = Path(path)
    if p.is_symlink() or not p.is_dir():
        return None
    try:
        fd = pin_dir(p, timeout=0.0)  # a map being replaced right now: the ordinary reader waits for it
    except Exception:
        return None
    try:
        group = _json(fd, ["zarr.json"])
        if not group or group.get("zarr_format") != 3 or group.get("node_type") != "group":
            return None
        raw = (group.get("attributes") or {}).get("sdfcodec")
        if raw is None:
            return None
        header = parse_header(raw, where=str(path))
        trust = sys.modules.get("sdfcodec.map.signing")
        if trust is not None and trust.trust_default():
            return None  # keys to trust: the ordinary reader checks the signature
        listed = _listed(fd, header)
        if header.manifest is not None and listed is None:
            return None  # the ordinary reader says what is wrong with the manifest
        vr = header.codes.variable_rate
        if vr is not None and vr.states is not None:  # in the header (spec 4e)
            if math.prod(header.grid_blocks) > _MAX_STATE_CHUNK:
                return None  # the ordinary reader applies its limit, naming it
            try:
                states = unpack_states(vr.states, tuple(header.grid_blocks), str(path))
            except FormatError:
                return None  # the ordinary reader names it
        else:
            states = _read_states(fd, tuple(header.grid_blocks), listed)
        if states is None:
            return None
        counts = np.bincount(states.ravel(), minlength=3)
        if len(counts) > 3:
            return None  # a state no version defines: the ordinary reader names it
        by_state = {name: int(counts[v]) for v, name in BlockState.NAMES.items()}
        return summarize(header, str(path), f"/proc/self/fd/{fd}", by_state)
    finally:
        release_pin(fd, p, os.getpid())


def _read(root: int, parts: Sequence[str], limit: int) -> bytes | None:
    """The first ``limit`` bytes of the file at ``parts`` under the directory descriptor ``root``, every
    component opened without following a symbolic link (the ordinary reader refuses links inside a map unless
    told to follow them); None when there is no such file, b"" when it is not a plain file we can read."""
    fds = []
    try:
        d = root
        for name in parts[:-1]:
            d = os.open(name, os.O_RDONLY | os.O_DIRECTORY | os.O_NOFOLLOW, dir_fd=d)
            fds.append(d)
        fd = os.open(parts[-1], os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK, dir_fd=d)
        fds.append(fd)
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            return b""
        with os.fdopen(os.dup(fd), "rb") as f:
            return f.read(limit)
    except FileNotFoundError:
        return None
    except OSError:
        return b""  # a link, a directory where a file should be, no permission: not certain
    finally:
        for fd in fds:
            os.close(fd)


def _json(root: int, parts: Sequence[str]) -> dict | None:
    raw = _read(root, parts, 1 << 24)
    try:
        if raw:
            check_metadata_size("/".join(parts), raw)  # before parsing: what it allocates is bounded too
        doc = json.loads(raw) if raw else None
    except (ValueError, FormatError):  # not certain: the ordinary reader refuses it, naming why
        return None
    return doc if isinstance(doc, dict) else None


def _listed(root: int, header: MapHeader) -> dict[str, str] | None:
    """The objects (key -> SHA-256) of the map's integrity manifest, checked against the header (spec section
    9b); None without one, or when it does not match (the ordinary reader then names the problem)."""
    ref = header.manifest
    if ref is None:
        return None
    data = _read(root, ["manifest.json"], ref.size + 1)
    if not data or len(data) != ref.size or hashlib.sha256(data).hexdigest() != ref.sha256:
        return None
    try:
        objects = json.loads(data).get("objects")
    except (ValueError, AttributeError):
        return None
    return objects if isinstance(objects, dict) else None


def _matches(data: bytes | None, key: str, listed: dict[str, str] | None) -> bool:
    """Whether ``data`` read at ``key`` is what the manifest ``listed`` says (always, without a manifest)."""
    if listed is None:
        return True
    if data is None:
        return False
    digest = hashlib.sha256(data).digest()  # as manifest version 1 (hex) or 2 (unpadded base64url) spells it
    return listed.get(key) in (digest.hex(), base64.urlsafe_b64encode(digest).rstrip(b"=").decode())


def _read_states(root: int, grid: tuple[int, ...], listed: dict[str, str] | None = None) -> np.ndarray | None:
    """The ``(Bx, By, Bz)`` uint8 block-state array (``state``) of the map directory ``root`` (a descriptor), or
    None (not certain: see the module). ``listed``: the manifest's objects, which every object read must match."""
    if not _matches(_read(root, ["state", "zarr.json"], 1 << 24), "state/zarr.json", listed):
        return None
    meta = _json(root, ["state", "zarr.json"])
    if (not meta or meta.get("zarr_format") != 3 or meta.get("node_type") != "array"
            or meta.get("data_type") != "uint8" or list(meta.get("shape", ())) != list(grid)
            or meta.get("storage_transformers") or not isinstance(meta.get("fill_value"), int)):
        return None
    cg, ke = meta.get("chunk_grid") or {}, meta.get("chunk_key_encoding") or {}
    chunk = (cg.get("configuration") or {}).get("chunk_shape")
    if (cg.get("name") != "regular" or not isinstance(chunk, list) or len(chunk) != 3
            or not all(isinstance(c, int) and c > 0 for c in chunk) or int(np.prod(chunk)) > _MAX_STATE_CHUNK
            or ke.get("name") != "default" or (ke.get("configuration") or {}).get("separator", "/") != "/"):
        return None
    codecs = meta.get("codecs")
    if not isinstance(codecs, list) or [c.get("name") if isinstance(c, dict) else None for c in codecs] != [
            "bytes", "blosc", "crc32c"]:  # what sdfcodec writes; anything else: the ordinary reader
        return None
    from numcodecs import blosc

    nbytes = int(np.prod(chunk))
    out = np.empty(grid, dtype=np.uint8)
    for idx in np.ndindex(*(-(-g // c) for g, c in zip(grid, chunk))):
        data = _read(root, ["state", "c", *map(str, idx)], _MAX_STATE_CHUNK + 1024)
        if not data:  # a chunk not stored is all unobserved only if no codes lie under it: the reader checks that
            return None
        if not _matches(data, "state/c/" + "/".join(map(str, idx)), listed):
            return None  # moved, altered or from another map: the ordinary reader refuses it, naming the key
        # the checks the guarded store applies before Blosc sees a frame (its C decoder trusts the header)
        if not crc32c_matches(data) or blosc_frame_problem(data[:-4], nbytes) is not None:
            return None
        data = blosc.decompress(data[:-4])
        if len(data) != nbytes:
            return None
        lo = [i * c for i, c in zip(idx, chunk)]
        sl = tuple(slice(a, min(a + c, g)) for a, c, g in zip(lo, chunk, grid))
        out[sl] = np.frombuffer(data, np.uint8).reshape(chunk)[tuple(slice(0, s.stop - s.start) for s in sl)]
    return out
