"""Sharded code arrays (spec/map-format.md section 4d, extension ``sharded-codes``): the chunks of ``codes``
stored as Zarr v3 shards, objects of megabytes holding many chunks each and an index of where each lies, so a
map of a million blocks is hundreds of objects on a file system or in a bucket, not tens of thousands.

What a shard is (Zarr's ``sharding_indexed`` codec, index at the end): the encoded chunks (each exactly the
bytes an unsharded chunk file holds: Blosc frame and CRC32C), then the index, ``(offset, nbytes)`` as
little-endian uint64 per chunk in C order of the chunks inside the shard (``2**64 - 1`` twice for a chunk not
stored), then the CRC32C of the index. Readers fetch the index (a suffix range) and then each chunk they need
(a byte range), so a region still transfers only its chunks.

Writers never write a shard chunk by chunk: every writer (one process or dask tasks) writes plain chunk files
into the map's temporary directory, and :func:`pack_shards` packs them into shards at commit, byte for byte
(no chunk is decoded or re-compressed), before the new version is swapped into place; an update first unpacks
the version it copies (:func:`unpack_shards`). A shard is thus always written whole, into a new file of a
version nobody reads yet: a failed write leaves the map as it was (spec section 9).

Checks on reads (used by :class:`sdfcodec.map.io.stores.GuardStore`, spec section 9a): a range read of a chunk
is at most what a chunk may take (:func:`~sdfcodec.map.io.stores.chunk_read_limit`) and its Blosc frame is
checked before decompression like a chunk file's; an index read is exactly the index's size; a whole shard is
at most its chunks' bound plus the index, its index must pass its CRC32C and point inside the shard, and every
chunk's frame is checked.
"""

from __future__ import annotations

import asyncio
import json
import math
import os
from pathlib import Path
from typing import TYPE_CHECKING, Any

import google_crc32c
import numpy as np
import zarr
from zarr.abc.store import RangeByteRequest, SuffixByteRequest
from zarr.codecs import BytesCodec, Crc32cCodec, ShardingCodec
from zarr.buffer import default_buffer_prototype
from zarr.core.sync import sync as zarr_sync

from ...core import _atomic
from ...errors import FormatError, InvalidValueError
from ...core.header import SHARD_EXTENSION, CodesSpec

if TYPE_CHECKING:
    from zarr.abc.store import Store

__all__ = ["chunk_ranges", "shard_contents", "index_size", "check_sharding", "read_cap", "range_problem",
           "shard_problem", "pack_shards", "unpack_shards", "chunk_stored", "chunk_name", "storage_shape",
           "shard_layout", "sharded_spec"]

_EMPTY = np.uint64(2 ** 64 - 1)  # an index entry of a chunk not stored (both offset and nbytes)
#: The largest shard index a reader fetches (1,048,575 chunks per shard; writers' shards hold at most 4^3 x 2)
MAX_INDEX_BYTES = 16 << 20
_INDEX_META = [{"name": "bytes", "configuration": {"endian": "little"}}, {"name": "crc32c"}]


def index_size(per_shard: int) -> int:
    """Bytes of the index of a shard of ``per_shard`` chunks: 16 per chunk and the CRC32C."""
    return 16 * per_shard + 4


def shard_layout(codes_chunks: tuple[int, ...], size: int, shard_blocks: int) -> tuple[int, ...]:
    """The shard shape of a ``codes`` array whose chunks are ``codes_chunks`` ``(c, c, c, chunk_code)`` and code
    length ``size``: ``shard_blocks`` per block axis, all the code axis (rounded up to whole chunks)."""
    cc = codes_chunks[3]
    return (shard_blocks,) * 3 + (-(-size // cc) * cc,)


def check_sharding(codec: ShardingCodec, arr: zarr.Array, where: str, shards: tuple[int, ...] | None) -> tuple:
    """The inner codecs of a sharded array's ``codec`` after checking what the spec fixes (section 4d): sharding
    only where the header says so (``shards``: the expected shard shape, None when the array may not be
    sharded), the index chain ``bytes`` (little-endian) + ``crc32c``, the index at the end, chunks that tile
    the shard. Returns ``(inner codecs, chunks per shard)``."""
    if shards is None:
        raise FormatError(f"{where} is sharded, which only the 'codes' array of a map with the extension "
                          f"'{SHARD_EXTENSION}' may be (spec sections 4d and 9a)")
    inner = tuple(int(c) for c in codec.chunk_shape)
    outer = tuple(int(s) for s in arr.shards)
    if outer != tuple(shards):
        raise FormatError(f"{where} has shards {outer}, expected {tuple(shards)} (from the header)")
    if len(inner) != len(outer) or any(c < 1 or s % c for c, s in zip(inner, outer)):
        raise FormatError(f"{where} has chunks {inner} that do not tile its shards {outer}")
    idx = tuple(codec.index_codecs)
    endian = getattr(getattr(idx[0], "endian", None), "value", None) if idx else None
    if (len(idx) != 2 or not isinstance(idx[0], BytesCodec) or endian != "little"
            or not isinstance(idx[1], Crc32cCodec)):
        names = [getattr(c, "codec_name", type(c).__name__) for c in idx]
        raise FormatError(f"{where} has shard index codecs {names}; the spec requires little-endian bytes then crc32c (section 4d)")
    if getattr(codec.index_location, "value", codec.index_location) != "end":
        raise FormatError(f"{where} keeps its shard index at the {codec.index_location}; the spec requires the end")
    per = math.prod(s // c for c, s in zip(inner, outer))
    if index_size(per) > MAX_INDEX_BYTES:  # every read of a shard starts by fetching its index whole
        raise FormatError(f"{where} has {per} chunks per shard: an index of {index_size(per)} bytes, more than the "
                          f"{MAX_INDEX_BYTES} a reader fetches (section 4d)")
    return tuple(codec.codecs), per


def read_cap(limit: tuple, byte_range: Any, chunk_cap: int) -> int:
    """Most bytes one read of an object of an array with guard entry ``limit`` ``(chunk bytes, Blosc first,
    chunks per object)`` may return: ``chunk_cap`` for a chunk (a whole unsharded object, or a range of a
    shard), the index's size for a suffix read, every chunk and the index for a whole shard."""
    per = limit[2] if len(limit) > 2 else 1
    if per == 1 or isinstance(byte_range, RangeByteRequest):
        return chunk_cap
    if byte_range is not None:
        return index_size(per)
    return per * chunk_cap + index_size(per)


def range_problem(limit: tuple, byte_range: Any, chunk_cap: int) -> str | None:
    """Why a byte range request on an object of an array with guard entry ``limit`` is refused unread, or None:
    only shards are read in ranges, a chunk at most ``chunk_cap`` bytes, the index exactly its size."""
    per = limit[2] if len(limit) > 2 else 1
    if per == 1:
        return f"a byte range ({byte_range!r}) of a chunk that is not in a shard"
    if isinstance(byte_range, RangeByteRequest):
        n = byte_range.end - byte_range.start
        return None if 0 <= n <= chunk_cap else f"a chunk range of {n} bytes, more than a chunk may take ({chunk_cap})"
    if isinstance(byte_range, SuffixByteRequest):
        want = index_size(per)
        return None if byte_range.suffix == want else f"a suffix of {byte_range.suffix} bytes, not the index's {want}"
    return f"a byte request {type(byte_range).__name__} readers of shards never make"


def _parse_index(data: bytes | memoryview, per: int) -> tuple[np.ndarray | None, str | None]:
    """``(index (per, 2) uint64, None)`` from the index bytes of a shard, or ``(None, problem)``."""
    if len(data) != index_size(per):
        return None, f"its index is {len(data)} bytes, not {index_size(per)}"
    body, crc = bytes(data[:-4]), bytes(data[-4:])
    if google_crc32c.value(body).to_bytes(4, "little") != crc:
        return None, "its index fails its CRC32C checksum"
    return np.frombuffer(body, dtype="<u8").reshape(per, 2), None


def shard_problem(data: bytes | memoryview, per: int, chunk_cap: int, frame_problem: Any = None) -> str | None:
    """What is wrong with a whole shard of ``per`` chunks (each at most ``chunk_cap`` bytes), or None: its index
    (size, CRC32C, every entry inside the chunks' bytes) and, with ``frame_problem(frame)`` (a chunk's Blosc
    frame without its CRC32C -> a problem or None), every chunk's frame."""
    if len(data) < index_size(per):
        return f"{len(data)} bytes, shorter than its index ({index_size(per)})"
    index, problem = _parse_index(memoryview(data)[len(data) - index_size(per):], per)
    if problem:
        return problem
    body = len(data) - index_size(per)
    for i, (off, n) in enumerate(index):
        if off == _EMPTY and n == _EMPTY:
            continue
        if n > chunk_cap or off > body or n > body - off:
            return f"index entry {i} ({int(off)}, {int(n)}) lies outside the shard's {body} bytes of chunks"
        if frame_problem is not None and n >= 4:
            bad = frame_problem(memoryview(data)[int(off):int(off + n) - 4])
            if bad:
                return f"chunk {i} is not a sound Blosc frame: {bad}"
    return None


def storage_shape(arr: zarr.Array) -> tuple[int, ...]:
    """The shape of one stored object of ``arr``: its shards, or its chunks when it is not sharded."""
    return tuple(int(s) for s in (arr.shards or arr.chunks))


def chunk_name(arr: zarr.Array, chunk: tuple[int, ...]) -> str:
    """The store key of chunk ``chunk`` of ``arr`` as error messages name it: its file, or its shard's with the
    chunk's place in it."""
    chunk = tuple(int(c) for c in chunk)
    if arr.shards is None:
        return f"{arr.path}/{arr.metadata.encode_chunk_key(chunk)}"
    per = [s // c for s, c in zip(arr.shards, arr.chunks)]
    shard = tuple(c // p for c, p in zip(chunk, per))
    return f"{arr.path}/{arr.metadata.encode_chunk_key(shard)} (chunk {chunk} in it)"


async def _stored(store: Store, arr: zarr.Array, chunks: list[tuple[int, ...]]) -> list[bool]:
    if arr.shards is None:
        keys = [f"{arr.path}/{arr.metadata.encode_chunk_key(tuple(int(v) for v in c))}" for c in chunks]
        return list(await asyncio.gather(*(store.exists(k) for k in keys)))
    ratio = [s // c for s, c in zip(arr.shards, arr.chunks)]
    per = math.prod(ratio)
    shards = sorted({tuple(int(c) // r for c, r in zip(ch, ratio)) for ch in chunks})
    proto = default_buffer_prototype()

    async def index_of(shard):
        buf = await store.get(f"{arr.path}/{arr.metadata.encode_chunk_key(shard)}", proto,
                              SuffixByteRequest(index_size(per)))
        if buf is None:
            return None
        index, problem = _parse_index(buf.to_bytes(), per)
        if problem:
            raise FormatError(f"shard {arr.path}/{arr.metadata.encode_chunk_key(shard)}: {problem}; the map is "
                              "corrupted there: restore it from a copy or re-encode")
        return index

    found = dict(zip(shards, await asyncio.gather(*(index_of(s) for s in shards))))
    out = []
    for ch in chunks:
        index = found[tuple(int(c) // r for c, r in zip(ch, ratio))]
        i = int(np.ravel_multi_index(tuple(int(c) % r for c, r in zip(ch, ratio)), ratio))
        out.append(index is not None and not (index[i, 0] == _EMPTY and index[i, 1] == _EMPTY))
    return out


def shard_contents(store: Store, arr: zarr.Array, shards: dict[tuple[int, ...], str]
                   ) -> tuple[dict[tuple[int, ...], str], dict[str, str]]:
    """The chunks stored in the given shards of ``arr`` (shard coordinates -> key), from their indexes (read
    concurrently, each checked): ``({chunk coordinates: name}, {shard key: problem})``."""
    ratio = [s // c for s, c in zip(arr.shards, arr.chunks)]
    per = math.prod(ratio)
    proto = default_buffer_prototype()

    async def read_all():
        async def one(key):
            try:
                buf = await store.get(key, proto, SuffixByteRequest(index_size(per)))
            except Exception as e:  # noqa: BLE001 - reported by the caller, naming the shard
                return None, f"its index cannot be read ({e})"
            return (None, "is missing") if buf is None else _parse_index(buf.to_bytes(), per)
        return await asyncio.gather(*(one(k) for k in shards.values()))

    found, broken = {}, {}
    for (shard, key), (index, problem) in zip(shards.items(), zarr_sync(read_all())):
        if problem:
            broken[key] = problem
            continue
        for i in np.flatnonzero(~((index[:, 0] == _EMPTY) & (index[:, 1] == _EMPTY))):
            ch = tuple(int(s * r + c) for s, r, c in zip(shard, ratio, np.unravel_index(int(i), ratio)))
            if all(c < n for c, n in zip(ch, arr.cdata_shape)):
                found[ch] = f"{key} (chunk {ch} in it)"
    return found, broken


def chunk_stored(store: Store, arr: zarr.Array, chunks: list[tuple[int, ...]]) -> list[bool]:
    """Whether each chunk of ``arr`` (chunk coordinates) is stored: its file exists, or its shard's index (read
    and checked) has an entry for it."""
    return zarr_sync(_stored(store, arr, list(chunks)))


# -- writers: packing chunk files into shards at commit, and back for an update -----------------------------

def _chunk_files(root: Path) -> dict[tuple[int, ...], Path]:
    """Chunk coordinates -> file of every chunk file under an array's directory ``root`` (keys ``c/i/j/k/l``)."""
    out = {}
    base = root / "c"
    if not base.is_dir():
        return out
    for dirpath, _, files in os.walk(base):
        rel = Path(dirpath).relative_to(base).parts
        for f in files:
            if f.isdigit() and all(p.isdigit() for p in rel):
                out[tuple(int(p) for p in (*rel, f))] = Path(dirpath) / f
    return out


def _replace_chunks(array_dir: Path, built: Path, meta: dict) -> None:
    """Put the chunk tree ``built/c`` in place of ``array_dir/c`` and write the array's new metadata. Only
    links are removed and names renamed: the files of the version this one was copied from stay as they are."""
    old = array_dir / "c"
    if old.exists():
        _atomic.remove_tree(old)
    if (built / "c").exists():
        os.rename(built / "c", old)
    _atomic.remove_tree(built)
    _atomic.write_new_file(array_dir / "zarr.json", json.dumps(meta, indent=2).encode())


def pack_shards(root: str | os.PathLike, path: str, shard_blocks: int) -> int:
    """Pack the chunk files of array ``path`` of the map being written in the temporary directory ``root`` into
    shards of ``shard_blocks`` blocks per axis (whole code axis), byte for byte, and make the array's metadata
    say so. Returns the number of shards written."""
    array_dir = Path(root) / path
    meta = json.loads((array_dir / "zarr.json").read_bytes())
    if meta["codecs"][0]["name"] == "sharding_indexed":
        raise InvalidValueError(f"array {path} is already sharded")
    chunks = tuple(meta["chunk_grid"]["configuration"]["chunk_shape"])
    shards = shard_layout(chunks, meta["shape"][3], shard_blocks)
    ratio = tuple(s // c for s, c in zip(shards, chunks))
    per = math.prod(ratio)
    groups: dict[tuple[int, ...], list[tuple[int, Path]]] = {}
    for ch, f in _chunk_files(array_dir).items():
        shard = tuple(c // r for c, r in zip(ch, ratio))
        groups.setdefault(shard, []).append((int(np.ravel_multi_index(tuple(c % r for c, r in zip(ch, ratio)),
                                                                      ratio)), f))
    built = Path(root) / f".{path}.shards"
    for shard, members in groups.items():
        index = np.full((per, 2), _EMPTY, dtype="<u8")
        parts, pos = [], 0
        for i, f in sorted(members):
            data = f.read_bytes()
            index[i] = (pos, len(data))
            parts.append(data)
            pos += len(data)
        body = index.tobytes()
        parts += [body, google_crc32c.value(body).to_bytes(4, "little")]
        target = built / "c" / Path(*map(str, shard))
        target.parent.mkdir(parents=True, exist_ok=True)
        _atomic.write_new_file(target, b"".join(parts))
    meta["codecs"] = [{"name": "sharding_indexed", "configuration": {
        "chunk_shape": list(chunks), "codecs": meta["codecs"], "index_codecs": _INDEX_META, "index_location": "end"}}]
    meta["chunk_grid"]["configuration"]["chunk_shape"] = list(shards)
    _replace_chunks(array_dir, built, meta)
    return len(groups)


def unpack_shards(root: str | os.PathLike, path: str) -> int:
    """The inverse of :func:`pack_shards` on the copy of a map an update writes (``root``): every shard of array
    ``path`` back into chunk files (byte for byte, each shard's index checked), and plain chunked metadata.
    Returns the number of chunk files written."""
    array_dir = Path(root) / path
    meta = json.loads((array_dir / "zarr.json").read_bytes())
    if meta["codecs"][0]["name"] != "sharding_indexed":
        return 0
    conf = meta["codecs"][0]["configuration"]
    chunks, shards = tuple(conf["chunk_shape"]), tuple(meta["chunk_grid"]["configuration"]["chunk_shape"])
    ratio = tuple(s // c for s, c in zip(shards, chunks))
    per = math.prod(ratio)
    built, n = Path(root) / f".{path}.chunks", 0
    for shard, f in _chunk_files(array_dir).items():
        data = f.read_bytes()
        problem = shard_problem(data, per, len(data))
        if problem:
            raise FormatError(f"shard {path}/c/{'/'.join(map(str, shard))}: {problem}; the map is corrupted there: "
                              "restore it from a copy or re-encode")
        index = np.frombuffer(data[len(data) - index_size(per):-4], dtype="<u8").reshape(per, 2)
        for i, (off, size) in enumerate(index):
            if off == _EMPTY and size == _EMPTY:
                continue
            ch = tuple(s * r + c for s, r, c in zip(shard, ratio, np.unravel_index(i, ratio)))
            target = built / "c" / Path(*map(str, ch))
            target.parent.mkdir(parents=True, exist_ok=True)
            _atomic.write_new_file(target, data[int(off):int(off + size)])
            n += 1
    meta["codecs"] = conf["codecs"]
    meta["chunk_grid"]["configuration"]["chunk_shape"] = list(chunks)
    _replace_chunks(array_dir, built, meta)
    return n


def sharded_spec(spec: CodesSpec, shard_blocks: Any) -> CodesSpec:
    """``spec`` with its chunks of codes stored in shards of ``shard_blocks`` blocks per axis (spec section 4d),
    checked: a whole number of chunks per axis (at least two) that divides the 64-block chunks of ``state``, so
    a shard never straddles two state chunks (the state-chunk presence check looks at a state chunk's shards)."""
    cb = spec.chunk_blocks
    if (isinstance(shard_blocks, bool) or not isinstance(shard_blocks, (int, np.integer)) or shard_blocks <= cb
            or shard_blocks % cb or 64 % shard_blocks):
        raise InvalidValueError(f"shard_blocks must be a multiple of chunk_blocks ({cb}) above it that divides 64 "
                                f"(e.g. {min(64, 4 * cb)}), got {shard_blocks!r}")
    if spec.field_compression is not None:
        raise InvalidValueError("field-compressed codes (sz3) are not sharded: their chunks are already 8 MiB "
                                "fields; leave shard_blocks unset")
    return spec.model_copy(update={"shard_blocks": int(shard_blocks)})


def chunk_ranges(arr: Any, sel: tuple) -> list[range]:
    """Chunk indices per axis that reading ``arr[sel]`` touches (``sel``: ints and step-1 slices; ``arr``: a Zarr
    array, or anything with its ``shape`` and ``chunks``)."""
    ranges = []
    for s, n, c in zip(sel, arr.shape, arr.chunks):
        start, stop, _ = s.indices(n) if isinstance(s, slice) else (s, s + 1, 1)
        ranges.append(range(start // c, max(start // c + 1, -(-stop // c))))
    return ranges
