"""``sdfcodec verify MAP``: check a map end to end and say precisely what is wrong.

What is checked (spec/map-format.md):

* the header validates against the schema (format and version first), and the arrays' metadata matches it
  (shapes, dtypes, chunk layout, fill values, allowed Zarr codecs with a crc32c checksum);
* every stored chunk of every array reads back: its checksum matches and it decompresses, and it is a regular
  file inside the map (no symbolic link, FIFO, device, socket or directory: spec section 9a);
* block states hold only defined values; every coded block has its code chunks and finite code values;
* the codec state under ``codec/`` matches ``codec.state_sha256``, and the listed arrays are all there (a state
  by reference: the installed plugin ships the model named, and its state has the digest named);
* the codec plugin is installed, accepts the stored configuration and state, and decodes the stored codes
  (up to ``decode_blocks`` of them) to finite blocks within :data:`sdfcodec.map.format.DECODE_LIMIT`;
* with an integrity manifest (spec section 9b): every object it lists matches its SHA-256 and nothing stored is
  unlisted (local and zip maps); a signature (section 9c) holds, and with ``trusted_keys`` one of them made it.
  A map without a manifest gets the note "no manifest".

Problems name the header field, array chunk (``codes/c/0/0/0/1``) or block they are about. Notes are things
the spec discourages without making the map invalid (stray files, codes stored for blocks that are not coded).
:func:`verify_map` never raises for anything wrong with the map: everything goes into the report.
"""

from __future__ import annotations

import asyncio
import json
import os
import warnings
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
import zarr

from ..core._lazy import lazy_module
from ..errors import ChecksumError, FormatError, MapNotFoundError, SDFCodecError, StateReferenceError
from ..core.header import BlockState, parse_header
from .grouping import chunk_box
from .io.shards import chunk_name, shard_contents
from .io.unlisted import chunk_positions, is_unlisted, stored_chunks

torch = lazy_module("torch")  # imported on first use: info, codecs, verify of a header never need it

__all__ = ["Problem", "VerifyReport", "verify_map", "verify_command"]

#: How many coded blocks verify decodes by default (all of them would take as long as decoding the map).
DEFAULT_DECODE_BLOCKS = 4096
_SHOWN = 5  # blocks named per problem before "and N more"
VERIFY_BATCH = 64  # chunks read concurrently (64 of pca-64's 512 KiB chunks: 32 MiB decoded at a time)


@dataclass(frozen=True)
class Problem:
    """One finding: ``where`` names the header field, chunk or block; ``message`` says what is wrong."""

    where: str
    message: str

    def __str__(self) -> str:
        return f"{self.where}: {self.message}"


@dataclass
class VerifyReport:
    """The result of :func:`verify_map`. ``ok`` is true when there are no problems (notes do not count)."""

    location: str
    problems: list[Problem] = field(default_factory=list)
    notes: list[Problem] = field(default_factory=list)
    chunks_checked: dict[str, int] = field(default_factory=dict)
    blocks: dict[str, int] | None = None
    codec: str | None = None
    decoded_blocks: int = 0
    #: the integrity manifest and signature (spec sections 9b, 9c): ``{"manifest": None or {"objects", "sha256"},
    #: "signature": None or :func:`~sdfcodec.map.signing.signature_status`}``; None before the header is read
    integrity: dict[str, Any] | None = None

    @property
    def ok(self) -> bool:
        return not self.problems

    def problem(self, where: str, message: str) -> None:
        self.problems.append(Problem(where, message))

    def note(self, where: str, message: str) -> None:
        self.notes.append(Problem(where, message))

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["ok"] = self.ok
        return d


def _blocks_text(coords: np.ndarray) -> str:
    shown = ", ".join(str(tuple(int(v) for v in c)) for c in coords[:_SHOWN])
    return shown + (f" and {len(coords) - _SHOWN} more" if len(coords) > _SHOWN else "")


def _decode_key(enc: Any, rel: str) -> tuple[int, ...]:
    """Chunk coordinates of a key relative to its array, () when it is no chunk key (zarr's own decoder
    mishandles the default "c/" prefix); the key must encode back to itself."""
    sep = getattr(enc, "separator", "/")
    body = rel[2:] if getattr(enc, "name", "") == "default" and rel.startswith("c" + sep) else rel
    try:
        coords = tuple(int(c) for c in body.split(sep))
    except ValueError:
        return ()
    try:
        return coords if enc.encode_chunk_key(coords) == rel else ()
    except Exception:  # noqa: BLE001
        return ()


def _chunk_keys(arr: zarr.Array, rep: VerifyReport | None = None, blocks: np.ndarray | None = None
                ) -> tuple[dict[tuple[int, ...], str], list[str], dict[str, str]] | None:
    """Chunk coordinates -> store key of every chunk stored for ``arr`` (of a sharded array: from its shards'
    indexes, the shard's key naming the chunk's place in it), stray keys under it, and shards whose index does
    not read back (key -> why); None when the store cannot list (every chunk position is then read). A remote
    map is never listed: its chunks are asked for by key, those of ``blocks`` (``(N, 3)`` block coordinates;
    None: every position), :mod:`sdfcodec.map.io.unlisted`; a layout too fine for that is a problem in ``rep``."""
    from zarr.core.sync import sync


    store = arr.store
    if is_unlisted(store):
        try:
            found, broken = stored_chunks(arr, chunk_positions(arr, blocks))
        except FormatError as e:
            if rep is not None:
                rep.problem(arr.path, str(e))
            return {}, [], {}
        return found, [], broken
    prefix = arr.path + "/"

    async def keys() -> list[str]:
        return [k async for k in store.list_prefix(prefix)]

    try:
        listed = sync(keys())
    except Exception:  # noqa: BLE001 - HTTP and other stores that cannot list
        return None
    enc = arr.metadata.chunk_key_encoding
    grid = (arr.cdata_shape if arr.shards is None else
            tuple(-(-n // s) for n, s in zip(arr.shape, arr.shards)))
    found: dict[tuple[int, ...], str] = {}
    stray: list[str] = []
    for key in sorted(listed):
        rel = key[len(prefix):]
        if rel == "zarr.json":
            continue
        coords = _decode_key(enc, rel)
        if len(coords) == len(grid) and all(0 <= c < n for c, n in zip(coords, grid)):
            found[coords] = key
        else:
            stray.append(key)
    if arr.shards is None:
        return found, stray, {}
    found, broken = shard_contents(store, arr, found)
    return found, stray, broken


def _iter_chunks(rep: VerifyReport, arr: zarr.Array, listing: Any = False):
    """Yield ``(coords, key, data or None)`` for every stored chunk of ``arr``; a chunk that does not read back
    is reported (data None). Counts the chunks in ``rep.chunks_checked``. ``listing``: from _chunk_keys. The
    chunks are read :data:`VERIFY_BATCH` at a time concurrently (Zarr's async I/O, decompression on its
    threads), so a map of a million blocks verifies on every core."""
    from zarr.core.sync import sync

    if listing is False:
        listing = _chunk_keys(arr)
    if listing is None:
        positions = {c: arr.metadata.encode_chunk_key(c) for c in np.ndindex(*arr.cdata_shape)}
        positions = {tuple(int(v) for v in c): f"{arr.path}/{k}" for c, k in positions.items()}
    else:
        positions, stray, broken = listing
        for key in stray:
            rep.note(key, "a file that is no chunk of this array (ignored by readers)")
        for key, why in broken.items():
            rep.problem(key, f"shard {why}: none of its chunks can be read")
    rep.chunks_checked.setdefault(arr.path, 0)
    items, batch = list(positions.items()), VERIFY_BATCH
    if arr.shards is not None:  # shard by shard, a few at a time: each shard is then read once, whole
        ratio = [s // c for s, c in zip(arr.shards, arr.chunks)]
        items.sort(key=lambda kv: (tuple(c // r for c, r in zip(kv[0], ratio)), kv[0]))
        batch = max(batch, 4 * int(np.prod(ratio)))
    for start in range(0, len(items), batch):
        part = items[start:start + batch]
        for (coords, key), res in zip(part, sync(_read_chunks(arr, [c for c, _ in part]))):
            rep.chunks_checked[arr.path] += 1
            data = None
            if isinstance(res, ChecksumError):
                rep.problem(key, f"does not read back: checksum mismatch, truncated or not decompressible ({res})")
            elif isinstance(res, FormatError):  # the store refused the file itself (a link, a FIFO...)
                rep.problem(key, f"is refused: {res}")
            elif isinstance(res, BaseException):
                if not isinstance(res, Exception):
                    raise res
                msg = str(res) or type(res).__name__
                rep.problem(key, f"does not read back: checksum mismatch, truncated or not decompressible ({msg})")
            else:
                data = np.asarray(res)
            yield coords, key, data


async def _read_chunks(arr: zarr.Array, chunks: list[tuple[int, ...]]) -> list[Any]:
    """The data of each chunk of ``arr`` (or the exception reading it raised), read concurrently. A sharded
    array's chunks are read a whole shard at a time (one object read, every chunk's frame and checksum checked
    by the store and Zarr); a shard that fails is read again chunk by chunk, to name the chunks that fail."""
    aarr = arr.async_array

    async def each(cs):
        return await asyncio.gather(*(aarr.getitem(chunk_box(c, arr.chunks, arr.shape)) for c in cs),
                                    return_exceptions=True)

    if arr.shards is None:
        return list(await each(chunks))
    ratio = [s // c for s, c in zip(arr.shards, arr.chunks)]
    by_shard: dict[tuple[int, ...], list[int]] = {}
    for i, c in enumerate(chunks):
        by_shard.setdefault(tuple(v // r for v, r in zip(c, ratio)), []).append(i)
    out: list[Any] = [None] * len(chunks)

    async def shard(sh, idxs):
        box = tuple(slice(v * s, min((v + 1) * s, n)) for v, s, n in zip(sh, arr.shards, arr.shape))
        try:
            whole = await aarr.getitem(box)
        except Exception:  # noqa: BLE001 - named chunk by chunk below
            for i, res in zip(idxs, await each([chunks[i] for i in idxs])):
                out[i] = res
            return
        for i in idxs:
            out[i] = whole[tuple(slice(b.start - o.start, b.stop - o.start)
                                 for b, o in zip(chunk_box(chunks[i], arr.chunks, arr.shape), box))]

    await asyncio.gather(*(shard(sh, idxs) for sh, idxs in by_shard.items()))
    return out


def _members(group: zarr.Group, **kwargs) -> tuple:
    """``group.members(**kwargs)`` without Zarr's warning about objects it cannot place (the manifest, the
    signature, or whatever a damaged document leaves): they are no arrays to check, and what is wrong with them
    is the report's to say, not a warning printed before it."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=r"Object at .* is not recognized")
        return tuple(group.members(**kwargs))


def _generic_chunks(rep: VerifyReport, group: zarr.Group) -> None:
    """Without a valid header: still check every chunk of every array found (of a local map: a remote one is
    never listed, and without its header nothing says what it stores)."""
    if is_unlisted(group.store):
        rep.note("map", "without a valid header, the chunks of a remote map are not checked (it is never listed)")
        return
    try:
        arrays = [a for _, a in _members(group, max_depth=None) if isinstance(a, zarr.Array)]
    except SDFCodecError as e:  # the store refused a member (a link, a FIFO...): its own message
        rep.problem("map", f"its arrays cannot be listed: {e}")
        return
    except Exception as e:  # noqa: BLE001
        rep.problem("map", f"its arrays cannot be listed ({type(e).__name__}: {e})")
        return
    for arr in arrays:
        try:
            for _ in _iter_chunks(rep, arr):
                pass
        except Exception as e:  # noqa: BLE001 - malformed metadata of that array
            rep.problem(arr.path, f"cannot be read ({type(e).__name__}: {e})")


def _absent(m, key: str) -> str:
    """What a chunk key that is not listed holds, as the reads say it: "is missing", or why the store refuses
    what is there instead (a directory where the chunk file belongs, a link, a FIFO...)."""
    from zarr.buffer import default_buffer_prototype
    from zarr.core.sync import sync

    try:
        found = sync(m.reader.group.store.get(key, default_buffer_prototype()))
    except SDFCodecError as e:
        return f"is refused: {e}"
    except Exception:  # noqa: BLE001 - whatever else is there, it is no readable chunk
        return "is missing"
    return "is missing" if found is None else "is not listed by the store, yet reads"


def _check_states(rep: VerifyReport, m) -> np.ndarray | None:
    arr = m.reader.state_array
    states = np.zeros(m.grid_blocks, np.uint8)
    ok = True
    listing = _chunk_keys(arr, rep)
    for coords, key, data in _iter_chunks(rep, arr, listing):
        if data is None:
            ok = False
            continue
        box = tuple(slice(c * n, c * n + s) for c, n, s in zip(coords, arr.chunks, data.shape))
        states[box] = data
    if ok and is_unlisted(arr.store):  # no listing of code chunks to walk: those under each absent state chunk
        from .presence import check_state_chunks

        try:
            check_state_chunks(m.reader, (slice(None),) * 3, states)
        except FormatError as e:
            rep.problem(arr.path, str(e).removeprefix(f"{m.location}: "))
            ok = False
    elif listing is not None:  # a state chunk not stored where code chunks are: its blocks would vanish
        # walked from the stored code chunks (bounded by the files there), not over every state chunk position
        # (a hostile grid has billions): the state chunk holding each code chunk's first block must be stored
        lost: dict[tuple[int, ...], list[str]] = {}
        for codes in (m.reader.codes_array, m.reader.code_scale_array):
            found = None if codes is None else _chunk_keys(codes)
            for c, k in ({} if found is None else found[0]).items():
                idx = tuple(v * n // s for v, n, s in zip(c[:3], codes.chunks, arr.chunks))
                if idx not in listing[0]:
                    lost.setdefault(idx, []).append(k)
        for idx, under in sorted(lost.items())[:_SHOWN * 4]:
            key = f"{arr.path}/{arr.metadata.encode_chunk_key(idx)}"
            region = [(v * s, min((v + 1) * s, n)) for v, s, n in zip(idx, arr.chunks, arr.shape)]
            what = _absent(m, key)
            more = f" and {len(under) - 3} more" if len(under) > 3 else ""
            rep.problem(key, f"{what}, but chunk(s) {', '.join(sorted(under)[:3])}{more} of its blocks {region} are "
                             "stored: its block states are lost (they would read as unobserved, and the coded blocks "
                             "vanish)")
            ok = False
    if not ok:
        return None
    bad = np.argwhere(states > BlockState.CODED)
    if len(bad):
        rep.problem("state", f"{len(bad)} block(s) hold reserved state values (valid: 0, 1, 2), e.g. value "
                             f"{int(states[tuple(bad[0])])} at block(s) {_blocks_text(bad)}")
        return None
    return states


def _check_codes(rep: VerifyReport, m, states: np.ndarray | None) -> None:
    """Every chunk of ``codes`` (and of ``code_scale`` for int8 maps: same block chunking, spec section 4a)
    reads back, holds finite values for coded blocks, and is present wherever a block is coded; for variable-rate
    codes (spec 4e), every chunk stream holding coded blocks is present and decodes."""
    if m.reader.vr is not None:
        if states is not None:
            try:
                m.reader.vr.codes_for(np.argwhere(states == BlockState.CODED), m.reader.header.codes.size)
            except SDFCodecError as e:
                rep.problem("code_streams", str(e))
                return
            if m.reader.refinement is not None:  # every stream of the surface refinement decodes (spec 6h)
                try:
                    m.reader.refinement.check(np.argwhere(states == BlockState.CODED))
                except SDFCodecError as e:
                    rep.problem("refine_streams", str(e))
        return
    for arr in (m.reader.codes_array, m.reader.code_scale_array):
        if arr is not None:
            _check_code_array(rep, m, arr, states)


def _check_code_array(rep: VerifyReport, m, codes, states: np.ndarray | None) -> None:
    cb, cc = codes.chunks[0], codes.chunks[3]
    n_code_chunks = codes.cdata_shape[3]
    stored: set[tuple[int, ...]] = set()
    if states is None and is_unlisted(codes.store):
        rep.note(codes.path, "not checked: without the block states, which of its chunks a remote map stores is "
                             "unknown (it is never listed)")
        return
    listing = _chunk_keys(codes, rep, None if states is None else np.argwhere(states == BlockState.CODED))
    stray_codes = 0
    for coords, key, data in _iter_chunks(rep, codes, listing):
        stored.add(coords)
        if data is None or states is None:
            continue
        box = tuple(slice(c * cb, c * cb + s) for c, s in zip(coords[:3], data.shape[:3]))
        coded = states[box] == BlockState.CODED
        finite = np.isfinite(data).all(axis=3)
        bad = np.argwhere(coded & ~finite)
        if len(bad):
            rep.problem(key, f"holds NaN/Inf code values for coded block(s) "
                             f"{_blocks_text(bad + np.array([s.start for s in box]))}")
        # a field-compressed map (spec section 4c) stores free space, within its bound, in blocks not coded
        if m.reader.header.codes.field_compression is None:
            stray_codes += int(((data != 0).any(axis=3) & ~coded).sum())
    if stray_codes:
        rep.note(codes.path, f"{stray_codes} block(s) that are not coded have values stored (spec: SHOULD be "
                               "left unwritten); readers ignore them")
    if states is None or listing is None:  # without a listing, missing chunks cannot be told from zeros
        return
    coded = np.argwhere(states == BlockState.CODED)
    if not len(coded):
        return
    for chunk in np.unique(coded // cb, axis=0):
        for k in range(n_code_chunks):
            coords = (*map(int, chunk), k)
            if coords not in stored:
                inside = coded[(coded // cb == chunk).all(axis=1)]
                key = chunk_name(codes, coords)
                what = _absent(m, key) if codes.shards is None else "is missing"
                span = f"[{k * cc}, {min((k + 1) * cc, codes.shape[3])})"
                rep.problem(key, f"is missing, but block(s) {_blocks_text(inside)} are coded: their elements "
                                 f"{span} would read as zeros" if what == "is missing" else
                            f"{what}; block(s) {_blocks_text(inside)} are coded there (elements {span})")


def _check_codec(rep: VerifyReport, m, decode_blocks: int) -> None:
    from . import state_digest
    from .format import DECODE_LIMIT

    spec = m.header.codec
    rep.codec = spec.id
    present = set()
    try:
        group = m.reader.member("codec", zarr.Group)
        if group is not None and is_unlisted(group.store):  # never listed: the arrays the header names
            present = set(spec.state_arrays)
        elif group is not None:
            present = {name for name, node in _members(group) if isinstance(node, zarr.Array)}
    except SDFCodecError as e:
        rep.problem("codec", str(e))
        return
    except Exception as e:  # noqa: BLE001 - a member whose metadata zarr cannot parse
        rep.problem("codec", f"the codec group cannot be listed ({type(e).__name__}: {e})")
        present = set(m.header.codec.state_arrays)
    state, complete = {}, True
    for name in spec.state_arrays:
        if name not in present:
            rep.problem(f"codec/{name}", "is missing, but header field codec.state_arrays lists it")
            complete = False
            continue
        try:
            arr = m.reader.member(f"codec/{name}")
            m.reader.check_array(arr)
        except SDFCodecError as e:
            rep.problem(f"codec/{name}", str(e).removeprefix(f"{m.location}: "))
            complete = False
            continue
        if arr is None:
            rep.problem(f"codec/{name}", "is missing, but header field codec.state_arrays lists it")
            complete = False
            continue
        for _, _, data in _iter_chunks(rep, arr, _chunk_keys(arr, rep)):
            complete &= data is not None
        if complete:
            try:
                state[name] = m.reader.read(arr, (slice(None),) * arr.ndim)
            except SDFCodecError as e:
                rep.problem(f"codec/{name}", str(e))
                complete = False
    for name in sorted(present - set(spec.state_arrays)):
        rep.note(f"codec/{name}", "is not listed in header field codec.state_arrays (readers ignore it)")
    if complete and spec.state_arrays:
        if spec.state_sha256 is None:
            rep.note("header field codec.state_sha256", "is null: the codec state cannot be checked against it")
        elif state_digest(state) != spec.state_sha256:
            rep.problem("header field codec.state_sha256", "does not match the codec state under codec/ (the "
                        "state arrays were altered or corrupted, or the header was)")
            return
    if not complete:
        return
    try:
        codec = m.codec  # a state by reference resolves here: the shipped model's state against its digest
    except SDFCodecError as e:
        rep.problem("header field codec.state_reference" if isinstance(e, StateReferenceError) else "codec", str(e))
        return
    if decode_blocks <= 0:
        return
    try:
        done = 0
        for coords, codes in m.iter_codes():
            z = codes[: decode_blocks - done]
            # decode_core: the plugin checks of every decode path (sdfcodec.codec.plugin_calls, the output's shape
            # and type), the values judged below, block by block
            out = codec.decode_core(torch.from_numpy(np.ascontiguousarray(z)))
            out = out.numpy()
            sane = (np.abs(out) <= DECODE_LIMIT).reshape(len(z), -1).all(axis=1)  # False for NaN too
            if not sane.all():
                bad = coords[: len(z)][~sane]
                what = "NaN/Inf" if not np.isfinite(out[~sane]).all() else f"absurd (beyond {DECODE_LIMIT:g})"
                rep.problem("codec", f"{codec.codec_id!r} decodes the stored codes of {len(bad)} block(s) to {what} "
                                     "values, block(s) "
                                     f"{_blocks_text(bad)}: the codes or the codec state are corrupted, or its "
                                     "plugin is faulty")
                return
            done += len(z)
            if done >= decode_blocks:
                break
        rep.decoded_blocks = done
    except SDFCodecError as e:
        rep.problem("codec", f"decoding failed: {e}")
    except Exception as e:  # noqa: BLE001 - a plugin failing on stored codes is a finding, not a crash
        rep.problem("codec", f"decoding failed: {type(e).__name__}: {e}")


def verify_map(path_or_url: str | os.PathLike, *, storage_options: dict | None = None,
               max_decode_bytes: int | None = None, decode_blocks: int = DEFAULT_DECODE_BLOCKS,
               follow_symlinks: bool = False, trusted_keys: Any = None) -> VerifyReport:
    """Check the map at ``path_or_url`` end to end (see the module docstring); never raises for a bad map.

    Args:
        storage_options: passed to fsspec for URLs.
        max_decode_bytes: the reader's allocation limit (default: :data:`sdfcodec.map.DEFAULT_MAX_DECODE_BYTES`).
        decode_blocks: how many coded blocks to decode with the codec (0: none, only load it).
        follow_symlinks: follow symbolic links inside a local map, as ``open_map(..., follow_symlinks=True)``
            does (by default each one is a problem: spec section 9a).
        trusted_keys: Ed25519 public keys (as ``open_map``); a map not signed by one of them as it is has a
            problem. Default: the process's (``--trusted-key``).
    """
    from . import DEFAULT_MAX_DECODE_BYTES, Map
    from .io.stores import open_store

    limit = DEFAULT_MAX_DECODE_BYTES if max_decode_bytes is None else max_decode_bytes
    loc = str(path_or_url)
    rep = VerifyReport(location=loc)
    try:
        _verify(rep, path_or_url, loc, storage_options, limit, decode_blocks, Map,
                lambda p, l, o: open_store(p, l, o, follow_symlinks=follow_symlinks), trusted_keys)
    except Exception as e:  # noqa: BLE001 - a bug in verify itself: reported, never a traceback
        rep.problem("verify", f"internal error while checking ({type(e).__name__}: {e}); please report it")
    return rep


def _integrity(rep: VerifyReport, store, header, raw, loc: str, trusted_keys: Any):
    """Load the manifest (installed on ``store``, so every later read is checked against it) and check the
    signature; returns the manifest or None."""
    from .manifest import load_manifest
    from .signing import check_trust, signature_status, trust_default
    from .io.stores import MAX_METADATA_BYTES

    keys = trust_default() if trusted_keys is None else trusted_keys
    rep.integrity = {"manifest": None, "signature": None}
    try:
        manifest = load_manifest(store.read_small, header.manifest, "manifest")
    except SDFCodecError as e:
        rep.problem("manifest", str(e).removeprefix("manifest: "))
        return None
    if manifest is None:
        rep.note("manifest", "no manifest: this map (written by an older sdfcodec, or with manifest=False) cannot "
                             "show that its objects are where they were written; write it again to get one")
        if keys:
            rep.problem("signature", "keys to trust were given but the map has no manifest, so no signature")
        return None
    rep.integrity["manifest"] = {"objects": len(manifest.objects), "sha256": manifest.digest}
    store.manifest = manifest
    try:
        root_doc = store.read_small("zarr.json", MAX_METADATA_BYTES)
        same = json.loads(root_doc)["attributes"]["sdfcodec"] == raw
        if not same:
            rep.problem("signature", "the header read twice differs; signature not checked")
            return manifest
        st = signature_status(store.read_small, root_doc, header, loc)
        rep.integrity["signature"] = st
        if keys:
            check_trust(store.read_small, root_doc, header, loc, keys)
        elif st["signed"] and not st["valid"]:
            rep.problem("signature", st["problem"])
    except SDFCodecError as e:
        rep.problem("signature", str(e).removeprefix(f"{loc}: "))
    except (TypeError, ValueError, KeyError) as e:
        rep.problem("signature", f"the root zarr.json could not be read again ({type(e).__name__})")
    return manifest


def _manifest_objects(rep: VerifyReport, store, manifest) -> None:
    """Every object the manifest lists, checked; every object stored and not listed (local and zip maps)."""
    from .manifest import object_problems

    for p in object_problems(store, manifest, listing=True):
        rep.problem("manifest", p.removeprefix(f"{manifest.where}: "))
    rep.chunks_checked["manifest"] = len(manifest.objects)


def _verify(rep, path_or_url, loc, storage_options, limit, decode_blocks, Map, open_store,
            trusted_keys=None) -> None:
    try:
        store = open_store(path_or_url, loc, storage_options)
        group = zarr.open_group(store, mode="r", zarr_format=3)
        raw = group.attrs.get("sdfcodec")
    except MapNotFoundError as e:
        rep.problem("map", str(e))
        return
    except (FileNotFoundError, NotADirectoryError):  # zarr's GroupNotFoundError: what open_map says too
        rep.problem("map", f"no map at {loc}")
        return
    except SDFCodecError as e:
        rep.problem("map", str(e))
        return
    except Exception as e:  # noqa: BLE001
        rep.problem("map", f"not a readable Zarr v3 group ({type(e).__name__}: {e})")
        return
    try:
        header = parse_header(raw, where="header")
    except SDFCodecError as e:
        rep.problem("header", str(e).removeprefix("header: "))
        _generic_chunks(rep, group)
        return
    manifest = _integrity(rep, store, header, raw, loc, trusted_keys)
    try:
        m = Map(group, header, loc, max_decode_bytes=limit)
    except SDFCodecError as e:
        rep.problem("arrays", str(e).removeprefix(f"{loc}: "))
        _generic_chunks(rep, group)
        if manifest is not None:
            _manifest_objects(rep, store, manifest)
        return
    if manifest is not None:
        _manifest_objects(rep, store, manifest)
    states = _check_states(rep, m)
    if states is not None:
        counts = np.bincount(states.ravel(), minlength=3)
        rep.blocks = {name: int(counts[v]) for v, name in BlockState.NAMES.items()}
    _check_codes(rep, m, states)
    # fusion weights, observation mask, residual stage: every chunk read and checked (of a remote map: those
    # under the observed blocks, the only ones it may store)
    observed = None if states is None else np.argwhere(states != BlockState.UNOBSERVED)
    for arr in (*m.reader.observation_arrays(), m.reader.residual_array):
        where = observed
        if hasattr(arr, "streams"):  # a pinned mask's chunks are its streams', one per chunk of codes (pinstore)
            arr, where = arr.streams, None if observed is None else np.unique(observed // arr.cb, axis=0)
        if arr is not None:
            for _ in _iter_chunks(rep, arr, _chunk_keys(arr, rep, where)):
                pass
    _check_codec(rep, m, decode_blocks)
    m.close()


def verify_command(map_path: str, as_json: bool = False, *, decode_blocks: int = DEFAULT_DECODE_BLOCKS) -> int:
    """Run :func:`verify_map` (decoding ``decode_blocks`` coded blocks) and print the report (rich text, or JSON
    with ``as_json``) on stdout.

    Returns:
        The exit status: 0 when the map has no problems, 1 otherwise.
    """
    rep = verify_map(map_path, decode_blocks=decode_blocks)
    if as_json:
        print(json.dumps(rep.to_dict(), indent=2))
        return 0 if rep.ok else 1
    from rich.console import Console
    from rich.markup import escape

    out = Console(soft_wrap=True, highlight=False)
    chunks = sum(rep.chunks_checked.values())
    status = "[bold green]OK[/]" if rep.ok else f"[bold red]FAILED[/] ({len(rep.problems)} problem(s))"
    out.print(f"verify {escape(rep.location)}: {status}")
    if rep.blocks is not None:
        out.print("  blocks: " + ", ".join(f"{v} {k}" for k, v in rep.blocks.items()))
    out.print(f"  chunks checked: {chunks} (" + ", ".join(f"{escape(k)} {v}" for k, v in rep.chunks_checked.items())
              + ")")
    if rep.codec is not None:
        out.print(f"  codec: {escape(rep.codec)}, {rep.decoded_blocks} block(s) decoded")
    if rep.integrity is not None:
        from .summary import integrity_line

        out.print(f"  integrity: {escape(integrity_line(rep.integrity))}")
    for p in rep.problems:
        out.print(f"  [red]problem[/] [bold]{escape(p.where)}[/]: {escape(p.message)}")
    for p in rep.notes:
        out.print(f"  [yellow]note[/] [bold]{escape(p.where)}[/]: {escape(p.message)}")
    return 0 if rep.ok else 1

