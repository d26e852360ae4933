"""The sdfcodec map: a Zarr v3 group holding per-block codes (``spec/map-format.md`` is normative).

::

    <map>/zarr.json            group; attribute "sdfcodec" = the header (sdfcodec.header.MapHeader)
    <map>/codes                (Bx, By, Bz, D) float32|float16|int8 code vectors, chunked (c, c, c, chunk_code)
    <map>/code_scale           (Bx, By, Bz, 2) float32 [offset, scale] per block, int8 codes only (spec 4a)
    <map>/state                (Bx, By, Bz) uint8 block state (0 unobserved, 1 empty, 2 coded)
    <map>/codec/<name>         the codec's learned state, one array per state_dict entry

Every chunk is Blosc/zstd-compressed and carries a CRC32C checksum (Zarr's ``crc32c`` codec). A map is
written (or, by :func:`update_map`, copied and changed) in a hidden sibling directory and swapped into place
on commit, so an interrupted write leaves the previous map (or none), never half of one; readers hold the
version they opened, so a swap never mixes two versions under them (``sdfcodec._atomic``, spec section 9).

Maps are untrusted input: opening one never runs code from it (codec ids resolve only to installed entry
points, array codecs come from a fixed list, nothing is unpickled), and every size the header or the array
metadata names is checked against ``max_decode_bytes`` before anything that large is allocated.
"""

from __future__ import annotations

import asyncio
import collections
import hashlib
import itertools
import json
import math
import os
import re
import shutil
import warnings
import weakref
from importlib import metadata
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any, Callable, Iterator, Sequence

import numpy as np
import torch
import zarr
import zarr.abc.store
from zarr.codecs import BloscCodec, BytesCodec, Crc32cCodec, GzipCodec, ZstdCodec
from zarr.core.sync import sync as zarr_sync

from . import __version__, _atomic
from ._validate import BLOCK, as_float_tensor, empty
from .blocks import check_truncation, normalise, split_blocks
from .codec import Codec
from .errors import (ChecksumError, FormatError, InvalidValueError, MapExistsError, MapNotFoundError,
                     ReadOnlyError, SDFCodecError, SDFCodecWarning, ShapeError, VersionError)
from .header import (INT8_EXTENSION, KNOWN_EXTENSIONS, STATE_NAME_PATTERN, BlockState, CodecSpec, CodesSpec,
                     Extension, MapHeader, Provenance, Truncation, now_iso, parse_header)
from .quantize import dequantize_codes, quantize_codes
from .registry import codec_package, get_codec_class

__all__ = ["Map", "open_map", "create_map", "update_map", "state_digest", "DEFAULT_MAX_DECODE_BYTES"]

#: A read that would allocate more than this many bytes at once (a decoded region, a dense read of codes, the
#: block-state array, one chunk, the codec state) is refused unless the caller raises the limit, so a hostile
#: or mistaken header cannot make a reader allocate without bound.
DEFAULT_MAX_DECODE_BYTES = 8 << 30
#: The Zarr codecs a map's arrays may use (spec section 4): anything else (sharding, numcodecs.* such as
#: pickle, variable-length types) is refused before a chunk is read.
_ALLOWED_ZARR_CODECS = (BytesCodec, BloscCodec, ZstdCodec, GzipCodec, Crc32cCodec)
#: Largest zarr.json a reader loads: metadata documents of a map are a few kB.
_MAX_METADATA_BYTES = 16 << 20
#: A read may touch at most max(_MIN_CHUNKS_PER_READ, max_decode_bytes // _BYTES_PER_CHUNK) chunks.
_MIN_CHUNKS_PER_READ, _BYTES_PER_CHUNK = 64, 4096
#: How long a writer waits for another process's update of the same map to finish before giving up.
_LOCK_TIMEOUT = 60.0
_EMPTY_EPS = 1e-6  # a normalised voxel >= 1 - eps is free space
#: Decoded values a codec bounds below this are finite however float32 rounding goes (float32 max ~3.4e38).
_FINITE_BOUND = 1e37
#: How codes may be stored (spec sections 4 and 4a).
CODE_DTYPES = ("float32", "float16", "int8")
Region = Sequence[Sequence[float]]


def _compressors() -> list:
    return [BloscCodec(cname="zstd", clevel=3, shuffle="shuffle"), Crc32cCodec()]


def state_digest(state: dict[str, np.ndarray]) -> str:
    """SHA-256 of a codec state: for each array by sorted name, ``name NUL dtype NUL shape-json NUL`` then
    its little-endian C-order bytes (spec/map-format.md, "Codec state")."""
    h = hashlib.sha256()
    for name in sorted(state):
        a = np.ascontiguousarray(state[name])
        a = a.astype(a.dtype.newbyteorder("<"), copy=False)
        h.update(f"{name}\0{a.dtype.str}\0{json.dumps(list(a.shape))}\0".encode())
        h.update(a.tobytes())
    return h.hexdigest()


def _code_layout(codec: Codec, dtype: str, chunk_blocks: int | None, chunk_code: int | None) -> CodesSpec:
    size = codec.code_size
    if chunk_code is None:
        # a prefix level of 32 elements reads only its own chunk along the code axis
        chunk_code = 32 if codec.prefix_ordered and size > 32 else size
    chunk_code = min(chunk_code, size)
    levels = sorted({*range(chunk_code, size, chunk_code), size}) if codec.prefix_ordered else [size]
    if chunk_blocks is None:
        # the largest of 16, 8, 4 blocks per axis that keeps an uncompressed chunk at or below 2 MiB (pca-64: 16,
        # 512 KiB; raw 4096-element codes: 4). Zarr costs about 1 ms per chunk read on top of its bytes, so
        # decoding a whole map from 16^3-block chunks fetches 4x faster than from 8^3 ones (docs/scale.md); a
        # map read mostly in small remote regions may prefer chunk_blocks=8 (less transferred per region)
        itemsize = np.dtype(dtype).itemsize
        chunk_blocks = next((c for c in (16, 8) if c ** 3 * chunk_code * itemsize <= 2 << 20), 4)
    return CodesSpec(size=size, dtype=dtype, chunk_blocks=chunk_blocks, chunk_code=chunk_code,
                     prefix_ordered=codec.prefix_ordered, levels=levels)


def _is_url(s: str) -> bool:
    return "://" in s


class _GuardStore(zarr.storage.WrapperStore):
    """Read-side wrapper around any store: refuses oversize metadata documents, and chunks whose Blosc header
    claims more bytes than the chunk's shape holds (a decompression bomb), before anything that large is
    allocated. ``limits`` maps an array's path to (decoded chunk bytes, whether Blosc decodes it first)."""

    def __init__(self, store: zarr.abc.store.Store, limits: dict[str, tuple[int, bool]] | None = None):
        super().__init__(store)
        self.limits: dict[str, tuple[int, bool]] = {} if limits is None else limits

    def _with_store(self, store):
        return type(self)(store, self.limits)

    def _local_size(self, key: str) -> int | None:
        inner = self._store
        if isinstance(inner, zarr.storage.LocalStore):
            try:
                return os.stat(inner.root / key).st_size
            except OSError:
                return None
        return None

    async def get(self, key, prototype=None, byte_range=None):
        meta = key == "zarr.json" or key.endswith("/zarr.json")
        limit = None if meta else next((v for p, v in self.limits.items() if key.startswith(p + "/")), None)
        size = self._local_size(key) if (meta or limit) else None
        if meta and size is not None and size > _MAX_METADATA_BYTES:
            raise FormatError(f"{key} is {size} bytes, more than any map metadata ({_MAX_METADATA_BYTES}); refused")
        if limit and size is not None and size > 2 * limit[0] + (1 << 20):
            raise ChecksumError(f"chunk {key} is {size} bytes on disk, far more than its {limit[0]} bytes of data")
        buf = await self._store.get(key, prototype, byte_range)
        if buf is None or byte_range is not None:
            return buf
        if meta and len(buf) > _MAX_METADATA_BYTES:
            raise FormatError(f"{key} is {len(buf)} bytes, more than any map metadata ({_MAX_METADATA_BYTES}); refused")
        if limit and limit[1] and len(buf) >= 16:
            # Blosc header: bytes 4..8 hold the uncompressed size, which decompression would allocate
            claimed = int.from_bytes(bytes(buf.as_numpy_array()[4:8]), "little")
            if claimed > limit[0]:
                raise ChecksumError(f"chunk {key} claims {claimed} bytes uncompressed, more than its shape holds "
                                    f"({limit[0]}); refused without decompressing")
        return buf


class _PinnedStore(zarr.storage.LocalStore):
    """A read-only local store over one version of a map directory, held open by a file descriptor and read
    through ``/proc/self/fd/N``: a writer that swaps in a new version cannot mix it into what this reader
    sees, and the held version is not removed while this store lives (``sdfcodec._atomic``)."""

    def __init__(self, root, *, read_only: bool = True, _path: Path | None = None, _fd: int | None = None):
        super().__init__(root, read_only=True)
        self._path, self._fd, self._closed = _path, _fd, False
        self._release = (weakref.finalize(self, _atomic.release_pin, _fd, _path, os.getpid())
                         if _fd is not None else None)

    @classmethod
    def pin(cls, path: Path) -> "_PinnedStore":
        fd = _atomic.pin_dir(path)
        return cls(f"/proc/self/fd/{fd}", _path=path, _fd=fd)

    def close_pin(self) -> None:
        self._closed = True
        if self._release is not None:
            self._release()

    def with_read_only(self, read_only: bool = False):
        if not read_only:
            raise ReadOnlyError(f"{self._path} is open read-only")
        return self

    def __reduce__(self):
        # the descriptor means nothing in another process: pin the map there afresh
        return (_PinnedStore.pin, (self._path,))

    def _check_open(self) -> None:
        if self._closed:
            raise InvalidValueError(f"{self._path}: the map was closed; open it again with sdfcodec.open_map")

    async def get(self, key, prototype=None, byte_range=None):
        self._check_open()
        return await super().get(key, prototype, byte_range)

    async def get_partial_values(self, prototype, key_ranges):
        self._check_open()
        return await super().get_partial_values(prototype, key_ranges)

    async def exists(self, key: str) -> bool:
        self._check_open()
        return await super().exists(key)


class _DeviceFeed:
    """Brings a group's host codes to the decode device (the staging step of the read pipeline).

    ``stage`` runs in the worker thread that fetched the group; ``ready`` in the thread that decodes it. On CUDA,
    ``stage`` copies the codes into pinned (page-locked) host memory and starts a non-blocking host-to-device
    copy on a side stream, recording an event; ``ready`` makes the decoding stream wait for that event (on the
    GPU, not the host) and tells the caching allocator that the decoding stream uses the tensor. The copy of
    the next group thus overlaps the decode of the current one. On the CPU the codes are used as they are.
    """

    def __init__(self, dev: torch.device):
        self.cuda = dev.type == "cuda"
        if self.cuda and dev.index is None:
            dev = torch.device("cuda", torch.cuda.current_device())
        self.dev = dev
        self.stream = torch.cuda.Stream(device=dev) if self.cuda else None

    def stage(self, codes: np.ndarray) -> tuple[torch.Tensor, Any, Any]:
        t = torch.from_numpy(codes)
        if not self.cuda:
            return (t if self.dev.type == "cpu" else t.to(self.dev)), None, None
        host = t.pin_memory()
        with torch.cuda.device(self.dev), torch.cuda.stream(self.stream):
            on_dev = host.to(self.dev, non_blocking=True)
            done = torch.cuda.Event()
            done.record(self.stream)
        # ``host`` travels with the group until ``ready``: the pinned buffer outlives its copy (the caching host
        # allocator would also hold it until the copy's event, but nothing depends on that)
        return on_dev, done, host

    def ready(self, staged: tuple[torch.Tensor, Any, Any]) -> torch.Tensor:
        on_dev, done, _host = staged
        if done is not None:
            current = torch.cuda.current_stream(self.dev)
            current.wait_event(done)
            on_dev.record_stream(current)
        return on_dev


class Map:
    """An open sdfcodec map. Get one from :func:`open_map` (read) or :func:`create_map` (write).

    Geometry: voxel ``(i, j, k)`` lies at world position ``origin + voxel_size * (i, j, k)``; block
    ``(bx, by, bz)`` covers voxels ``[16 bx, 16 bx + 16)`` on each axis. Decoded values are metres.
    """

    def __init__(self, group: zarr.Group, header: MapHeader, location: str, *,
                 max_decode_bytes: int = DEFAULT_MAX_DECODE_BYTES):
        self._group = group
        self.header = header
        self.location = location
        self.max_decode_bytes = max_decode_bytes
        self._codec: Codec | None = None
        self._writer: _Writer | None = None
        self._closed = False
        self._close_on_exit = False
        self._chunk_bytes: dict[str, int] = {}
        self._reopen: tuple[Any, dict | None] | None = None  # (path, URL or store; storage options): see to_dask
        self._check_arrays()

    # -- geometry -------------------------------------------------------------------------------------
    @property
    def voxel_size(self) -> float:
        return self.header.voxel_size

    @property
    def truncation(self) -> tuple[float, float]:
        return self.header.truncation.d_min, self.header.truncation.d_max

    @property
    def origin(self) -> tuple[float, float, float]:
        return self.header.origin

    @property
    def shape_voxels(self) -> tuple[int, int, int]:
        return self.header.shape_voxels

    @property
    def grid_blocks(self) -> tuple[int, int, int]:
        return self.header.grid_blocks

    @property
    def code_size(self) -> int:
        return self.header.codes.size

    @property
    def writable(self) -> bool:
        return self._writer is not None

    def _member(self, path: str, kind: type = zarr.Array) -> Any:
        """The array (or group) at ``path``, or None when absent; unreadable metadata is a FormatError."""
        try:
            node = self._group[path]
        except KeyError:
            return None
        except SDFCodecError:
            raise
        except Exception as e:  # zarr's many ways to say its metadata is malformed
            raise FormatError(f"{self.location}: the metadata of '{path}' is invalid ({type(e).__name__}: {e}); "
                              "the map is corrupted: restore it from a copy or re-encode") from e
        if not isinstance(node, kind):
            raise FormatError(f"{self.location}: '{path}' must be a Zarr {kind.__name__.lower()}")
        return node

    def _check_array(self, arr: zarr.Array, *, dtype: Any = None, shape: tuple | None = None,
                     chunks: tuple | None = None, zero_fill: bool = False) -> None:
        """Validate an array's metadata against the spec and the reader's limits *before* reading from it, and
        register its chunk size with the guard store (a chunk claiming more is refused unread)."""
        where = f"{self.location}: array '{arr.path}'"
        try:
            dt = np.dtype(arr.dtype)
            codecs = tuple(arr.metadata.codecs)
            ch = tuple(int(c) for c in arr.chunks)
            fill = arr.metadata.fill_value
        except Exception as e:  # noqa: BLE001 - irregular chunk grids, data types numpy lacks...
            raise FormatError(f"{where} has metadata this reader cannot use ({type(e).__name__}: {e})") from e
        if dt.kind not in "biuf" or dt.itemsize > 8:
            raise FormatError(f"{where} has data type {dt}; map arrays hold plain numbers only")
        if dtype is not None and dt != np.dtype(dtype):
            raise FormatError(f"{where} has data type {dt}, expected {np.dtype(dtype)}")
        if shape is not None and tuple(arr.shape) != tuple(shape):
            raise FormatError(f"{where} has shape {tuple(arr.shape)}, expected {tuple(shape)} (from the header)")
        if chunks is not None and ch != tuple(chunks):
            raise FormatError(f"{where} has chunks {ch}, expected {tuple(chunks)} (from the header)")
        bad = [getattr(c, "codec_name", None) or type(c).__name__ for c in codecs
               if not isinstance(c, _ALLOWED_ZARR_CODECS)]
        if bad:
            raise FormatError(f"{where} uses Zarr codec(s) {bad}, which a map may not use (allowed: bytes, blosc, "
                              "zstd, gzip, crc32c)")
        if not codecs or not isinstance(codecs[-1], Crc32cCodec):
            raise FormatError(f"{where} has no crc32c checksum codec (spec section 4): it cannot be verified")
        # checked when reading (_read), so that a small limit still lets a map open and say what is too big
        chunk_bytes = self._chunk_bytes[arr.path] = math.prod(ch) * dt.itemsize
        if zero_fill and not (np.ndim(fill) == 0 and np.asarray(fill) == 0):
            raise FormatError(f"{where} has fill value {fill!r}; the spec requires 0")
        store = self._group.store
        if isinstance(store, _GuardStore):
            first = next((c for c in codecs if not isinstance(c, BytesCodec)), None)
            store.limits[arr.path] = (chunk_bytes, isinstance(first, BloscCodec))

    def _check_arrays(self) -> None:
        h = self.header
        state_bytes = math.prod(h.grid_blocks)
        if state_bytes > self.max_decode_bytes:
            raise FormatError(f"{self.location}: header field grid_blocks {h.grid_blocks} needs {state_bytes} bytes "
                              f"of block states, above the reader's limit of {self.max_decode_bytes} bytes (raise "
                              "max_decode_bytes in open_map() if the map is genuine)")
        codes, state = self._member("codes"), self._member("state")
        if codes is None or state is None:
            missing = "codes" if codes is None else "state"
            raise FormatError(f"{self.location}: map lacks array '{missing}'; it is incomplete or not an sdfcodec map")
        cb = h.codes.chunk_blocks
        self._check_array(codes, dtype=h.codes.dtype, shape=(*h.grid_blocks, h.codes.size),
                          chunks=(cb, cb, cb, h.codes.chunk_code), zero_fill=True)
        self._check_array(state, dtype=np.uint8, shape=tuple(h.grid_blocks), zero_fill=True)
        self._code_scale = None
        if h.codes.dtype == "int8":
            self._code_scale = self._member("code_scale")
            if self._code_scale is None:
                raise FormatError(f"{self.location}: map has int8 codes but lacks array 'code_scale' (spec section "
                                  "4a); it is incomplete")
            self._check_array(self._code_scale, dtype=np.float32, shape=(*h.grid_blocks, 2), chunks=(cb, cb, cb, 2),
                              zero_fill=True)
        self._weights = None
        if any(e.name == "fusion-weights" for e in h.extensions):
            self._weights = self._member("weights")
            if self._weights is not None:
                self._check_array(self._weights, dtype=np.float16, shape=(*h.grid_blocks, 4096))
        self._codes, self._state = codes, state

    # -- reading --------------------------------------------------------------------------------------
    def _read(self, arr: zarr.Array, sel: tuple) -> np.ndarray:
        """Read ``arr[sel]``; a chunk that fails its checksum or decompression becomes a ChecksumError
        naming the chunk."""
        self._check_read(arr, sel)
        try:
            return np.asarray(arr[sel])
        except Exception as exc:  # find the chunk(s) to name: slow path, errors only
            raise self._chunk_error(arr, sel, exc) from exc

    def _read_many(self, arr: zarr.Array, sels: Sequence[tuple]) -> list[np.ndarray]:
        """Read ``arr[sel]`` for every selection concurrently (one batch of Zarr's async I/O: the chunks are
        fetched and decompressed in parallel, off the calling thread), with the checks of :meth:`_read`."""
        if len(sels) == 1:
            return [self._read(arr, sels[0])]
        for sel in sels:
            self._check_read(arr, sel)
        aarr = arr.async_array

        async def gather():
            return await asyncio.gather(*(aarr.getitem(sel) for sel in sels), return_exceptions=True)

        out = []
        for sel, res in zip(sels, zarr_sync(gather())):
            if isinstance(res, BaseException):
                if not isinstance(res, Exception):
                    raise res
                raise self._chunk_error(arr, sel, res) from res
            out.append(np.asarray(res))
        return out

    def _chunk_error(self, arr: zarr.Array, sel: tuple, exc: Exception) -> Exception:
        return ChecksumError(f"{self.location}: {self._bad_chunks(arr, sel)} of array '{arr.path}' is "
                             f"corrupted or truncated ({type(exc).__name__}: {exc}); the map cannot be "
                             "trusted there: restore it from a copy or re-encode")

    def _check_read(self, arr: zarr.Array, sel: tuple) -> None:
        """The limits on one read (module docstring): open map, chunk size, number of chunks touched."""
        if self._closed:
            raise InvalidValueError(f"{self.location}: the map was closed; open it again with sdfcodec.open_map")
        chunk_bytes = self._chunk_bytes.get(arr.path, 0)
        if chunk_bytes > self.max_decode_bytes:
            raise InvalidValueError(f"{self.location}: array '{arr.path}' has chunks of {chunk_bytes} bytes, above the "
                                    f"limit of {self.max_decode_bytes} bytes; raise max_decode_bytes in open_map() "
                                    "if the map is genuine")
        # each chunk costs a request and a task however small it is: a read may touch only so many (a hostile
        # chunk grid of 1-element chunks would otherwise take hours to read a modest array)
        n_chunks = math.prod(len(r) for r in _chunk_ranges(arr, sel))
        max_chunks = max(_MIN_CHUNKS_PER_READ, self.max_decode_bytes // _BYTES_PER_CHUNK)
        if n_chunks > max_chunks:
            raise InvalidValueError(f"{self.location}: reading array '{arr.path}' there touches {n_chunks} chunks, above "
                                    f"the limit of {max_chunks} for max_decode_bytes={self.max_decode_bytes}; read a "
                                    "smaller region, or raise max_decode_bytes if the map is genuine")

    def _bad_chunks(self, arr: zarr.Array, sel: tuple) -> str:
        # probe chunk by chunk, but boundedly: naming five is enough, and probing is one request per chunk
        bad, probed = [], 0
        for idx in itertools.product(*_chunk_ranges(arr, sel)):
            if len(bad) > 5 or probed >= 256:
                break
            probed += 1
            try:
                arr.blocks[idx]
            except Exception:  # noqa: BLE001
                bad.append("chunk c/" + "/".join(map(str, idx)))
        if not bad:
            return "a chunk"
        return ", ".join(bad[:5]) + (" and more" if len(bad) > 5 else "")

    def block_states(self) -> np.ndarray:
        """``(Bx, By, Bz)`` uint8 block states (see :class:`sdfcodec.header.BlockState`)."""
        if self._writer is not None:
            return self._writer.state.copy()
        return self._valid_states(self._read(self._state, (slice(None),) * 3))

    def count_states(self) -> dict[str, int]:
        counts = np.bincount(self.block_states().ravel(), minlength=3)
        return {name: int(counts[v]) for v, name in BlockState.NAMES.items()}

    @property
    def codec(self) -> Codec:
        """The codec that wrote the map, with its learned state (loaded on first use).

        Raises:
            UnknownCodecError: its plugin is not installed (names the id and the package to install).
        """
        if self._codec is None:
            self._codec = self._load_codec()
        return self._codec

    def _load_codec(self) -> Codec:
        h, where = self.header, self.location
        spec = h.codec
        cls = get_codec_class(spec.id, package_hint=spec.package)
        try:
            codec = cls.from_config(spec.config)
        except Exception as e:  # a hostile or stale config: the plugin's own error, whatever its type
            raise FormatError(f"{where}: header field codec.config is not a valid {spec.id!r} configuration "
                              f"({type(e).__name__}: {e})") from e
        state = {}
        if spec.state_arrays:
            total = 0
            for name in spec.state_arrays:
                arr = self._member(f"codec/{name}")
                if arr is None:
                    raise FormatError(f"{where}: codec state array 'codec/{name}' (listed in codec.state_arrays) "
                                      "is missing")
                self._check_array(arr)
                total += math.prod(arr.shape) * np.dtype(arr.dtype).itemsize
                if total > self.max_decode_bytes:
                    raise FormatError(f"{where}: the codec state is over {self.max_decode_bytes} bytes, the reader's "
                                      "limit (raise max_decode_bytes in open_map() if the map is genuine)")
                state[name] = self._read(arr, (slice(None),) * arr.ndim)
        if spec.state_sha256 is not None and state_digest(state) != spec.state_sha256:
            raise ChecksumError(f"{where}: the codec state under codec/ does not match the digest "
                                "in the header; the map's codec arrays were altered or corrupted")
        try:
            if state:
                codec = codec.load_state_dict(state)
            fitted = codec.is_fitted
        except Exception as e:
            raise FormatError(f"{where}: the codec state under codec/ does not fit codec {spec.id!r} "
                              f"({type(e).__name__}: {e})") from e
        if not fitted:
            raise FormatError(f"{where}: codec {spec.id!r} needs learned state, which the map does not store")
        if codec.code_size != h.codes.size:
            raise FormatError(f"{where}: header field codes.size is {h.codes.size}, but the codec makes codes of "
                              f"{codec.code_size} elements")
        if h.codes.prefix_ordered and not codec.prefix_ordered:
            raise FormatError(f"{where}: header field codes.prefix_ordered is true, but codec {spec.id!r} codes "
                              "are not prefix-ordered")
        return codec

    def _level(self, level: int | None) -> int:
        size = self.header.codes.size
        if level is None or level == size:
            return size
        if not self.header.codes.prefix_ordered:
            raise InvalidValueError(f"codec {self.header.codec.id!r} codes are not prefix-ordered, so level "
                                    f"{level} cannot be decoded; omit the level (full size {size})")
        if not isinstance(level, (int, np.integer)) or not 1 <= level <= size:
            raise InvalidValueError(f"level must be an int in 1..{size}, got {level!r}")
        return int(level)

    def _block_box(self, region: Region | None, units: str) -> tuple[tuple[int, int], ...]:
        """Voxel region -> validated half-open voxel bounds per axis."""
        shape = self.shape_voxels
        if region is None:
            return tuple((0, n) for n in shape)
        if len(region) != 3 or any(len(r) != 2 for r in region):
            raise ShapeError(f"region must be ((x0, x1), (y0, y1), (z0, z1)), got {region!r}")
        if units in ("m", "metres", "meters"):
            o, vs = self.origin, self.voxel_size
            # voxels whose centre lies in [lo, hi]; 1e-9 guards against rounding at exact voxel positions
            vox = tuple((int(np.ceil((lo - oo) / vs - 1e-9)), int(np.floor((hi - oo) / vs + 1e-9)) + 1)
                        for (lo, hi), oo in zip(region, o))
        elif units in ("voxels", "vox"):
            vox = tuple((int(lo), int(hi)) for lo, hi in region)
        else:
            raise InvalidValueError(f"units must be 'voxels' or 'm', got {units!r}")
        for axis, ((lo, hi), n) in enumerate(zip(vox, shape)):
            if not 0 <= lo < hi <= n:
                raise InvalidValueError(f"region {region!r} ({units}) is outside the map on axis {'xyz'[axis]}: "
                                        f"voxels [{lo}, {hi}) vs extent [0, {n})")
        return vox

    def read_codes(self, region: Region | None = None, *, units: str = "voxels", level: int | None = None
                   ) -> tuple[np.ndarray, np.ndarray]:
        """Codes of the coded blocks touching ``region``.

        Returns:
            ``coords`` ``(N, 3)`` int64 block indices and ``codes`` ``(N, L)`` float32, ``L = level or D``.
            Only the chunks holding the first ``L`` code elements are read.
        """
        lv = self._level(level)
        box = self._block_range(self._block_box(region, units))
        return self._codes_in(box, lv)

    @staticmethod
    def _block_range(vox: tuple[tuple[int, int], ...]) -> tuple[slice, slice, slice]:
        return tuple(slice(lo // BLOCK, -(-hi // BLOCK)) for lo, hi in vox)  # type: ignore[return-value]

    def _codes_in(self, box: tuple[slice, slice, slice], level: int, states: np.ndarray | None = None
                  ) -> tuple[np.ndarray, np.ndarray]:
        state = (self.block_states() if states is None else states)[box]
        local = np.argwhere(state == BlockState.CODED)
        if not len(local):
            return np.zeros((0, 3), np.int64), np.zeros((0, level), np.float32)
        nbytes = state.size * self.header.codes.stored_bytes(level)
        if nbytes > self.max_decode_bytes:
            raise InvalidValueError(f"reading the codes of blocks {[(s.start, s.stop) for s in box]} densely needs "
                                    f"{nbytes / 2**30:.1f} GiB, above the limit of {self.max_decode_bytes / 2**30:.1f}"
                                    " GiB; read a smaller region, use iter_codes(), or raise max_decode_bytes")
        codes = self._read(self._codes, (*box, slice(0, level)))[tuple(local.T)]
        params = None if self._code_scale is None else self._read(self._code_scale, (*box, slice(0, 2)))[tuple(local.T)]
        coords = local + np.array([s.start for s in box], dtype=np.int64)
        return coords, self._code_values(coords, codes, params)

    def _code_values(self, coords: np.ndarray, codes: np.ndarray, params: np.ndarray | None) -> np.ndarray:
        """Stored ``codes`` of blocks ``coords`` as float32 (dequantised with their ``code_scale`` rows
        ``params`` for int8 maps), refusing NaN/Inf (a corrupted but checksum-valid chunk) by naming a block."""
        out = codes.astype(np.float32, copy=False) if params is None else dequantize_codes(codes, params)
        finite = np.isfinite(out).all(axis=1)
        if not finite.all():
            bad = coords[~finite]
            raise FormatError(f"{self.location}: {len(bad)} coded block(s) hold NaN/Inf code values, e.g. block "
                              f"{tuple(int(v) for v in bad[0])}; the map is corrupted there (`sdfcodec verify` lists "
                              "them): restore it from a copy or re-encode those blocks")
        return out

    # -- the decode-on-read pipeline ------------------------------------------------------------------
    # One path reads and decodes codes for every reader (iter_codes, iter_decoded, iter_blocks, decode_region,
    # to_dask, the tracker's map field): the chunks of the code array that hold coded blocks of a block box are
    # cut into groups; a small thread pool fetches the next groups (each group's chunks concurrently, through
    # Zarr's async I/O, which also decompresses them off the calling thread) and stages their codes for the
    # device (pinned host memory + an asynchronous copy on CUDA) while the calling thread decodes the current
    # group in one batched call.

    def _grid(self) -> tuple[int, int, int]:
        return self._writer.grid if self._writer is not None else self.grid_blocks

    def _states_in(self, box: tuple[slice, slice, slice]) -> np.ndarray:
        """Block states of a block box: only the state chunks it touches are read."""
        if self._writer is not None:
            return self._writer.state[box]
        return self._valid_states(self._read(self._state, box))

    def _valid_states(self, state: np.ndarray) -> np.ndarray:
        if state.size and state.max() > BlockState.CODED:
            raise FormatError(f"{self.location}: state array holds reserved value {int(state.max())} "
                              "(valid: 0 unobserved, 1 empty, 2 coded)")
        return state

    def _chunk_groups(self, box: tuple[slice, slice, slice], states: np.ndarray, level: int, *,
                      batch_blocks: int | None = None, chunks_per_group: int | None = None) -> list[np.ndarray]:
        """Chunk indices ``(G, 3)`` (of the block axes of ``codes``) holding coded blocks inside ``box``, in grid
        order, grouped: ``chunks_per_group`` chunks, or (``batch_blocks``) consecutive chunks until they hold
        that many coded blocks. A group never holds more than ``max_decode_bytes`` of codes and decoded blocks.
        A sparse map (or a hostile, huge and empty grid) costs what it stores, not its extent."""
        spec = self.header.codes
        cb = spec.chunk_blocks
        b0 = np.array([s.start for s in box], dtype=np.int64)
        n = np.array(states.shape, dtype=np.int64)
        if not n.all():
            return []
        lead = b0 % cb
        # coded blocks per chunk, summed axis by axis between chunk boundaries: time and memory follow the block
        # states, never the chunks' volume (a hostile 256^3-block chunk over a thin box costs nothing extra)
        counts = states == BlockState.CODED
        for ax in range(3):
            starts = np.r_[0, np.arange(cb - lead[ax] if lead[ax] else cb, n[ax], cb)]
            counts = np.add.reduceat(counts, starts, axis=ax, dtype=np.int32)
        idx = np.argwhere(counts)
        if not len(idx):
            return []
        per_block = counts[tuple(idx.T)]
        idx += b0 // cb
        read = -(-level // spec.chunk_code) * spec.chunk_code * np.dtype(spec.dtype).itemsize
        cap = max(1, self.max_decode_bytes // (cb ** 3 * (read + 4 * BLOCK ** 3)))
        if chunks_per_group is not None:
            cap, target = min(cap, chunks_per_group), None
        else:
            target = batch_blocks
        groups, start, acc = [], 0, 0
        for i, c in enumerate(per_block.tolist()):
            acc += c
            if (target is not None and acc >= target) or i + 1 - start >= cap:
                groups.append(idx[start:i + 1])
                start, acc = i + 1, 0
        if start < len(idx):
            groups.append(idx[start:])
        return groups

    def _fetch_group(self, chunks: np.ndarray, b0: np.ndarray, b1: np.ndarray, states: np.ndarray, level: int
                     ) -> tuple[np.ndarray, np.ndarray]:
        """Codes ``(n, level)`` float32 and block coords ``(n, 3)`` of the coded blocks of the given chunks
        inside the block box ``[b0, b1)`` (``states`` covers that box): the chunks are read concurrently."""
        cb = self.header.codes.chunk_blocks
        sels, locs, los = [], [], []
        for c in chunks:
            lo, hi = np.maximum(c * cb, b0), np.minimum(c * cb + cb, b1)
            sub = states[tuple(slice(int(a), int(b)) for a, b in zip(lo - b0, hi - b0))]
            sels.append((*(slice(int(a), int(b)) for a, b in zip(lo, hi)), slice(0, level)))
            locs.append(np.argwhere(sub == BlockState.CODED))
            los.append(lo)
        arrays = self._read_many(self._codes, sels)
        codes = np.concatenate([a[tuple(loc.T)] for a, loc in zip(arrays, locs)])
        coords = np.concatenate([loc + lo for loc, lo in zip(locs, los)]).astype(np.int64, copy=False)
        params = None
        if self._code_scale is not None:
            scales = self._read_many(self._code_scale, [(*sel[:3], slice(0, 2)) for sel in sels])
            params = np.concatenate([a[tuple(loc.T)] for a, loc in zip(scales, locs)])
        return coords, self._code_values(coords, codes, params)

    def _fetch_stream(self, box: tuple[slice, slice, slice], level: int, *, states: np.ndarray | None = None,
                      stage: Callable[[np.ndarray], Any] | None = None, batch_blocks: int | None = 8192,
                      chunks_per_group: int | None = None, prefetch: int = 2) -> Iterator[tuple[np.ndarray, Any]]:
        """Yield ``(coords, codes)`` per group of chunks (see :meth:`_chunk_groups`), ``codes`` passed through
        ``stage`` in the fetching thread. Up to ``prefetch`` further groups are fetched (and staged) by a
        thread pool while the caller works on the one yielded; with one group, everything runs inline."""
        if isinstance(prefetch, bool) or not isinstance(prefetch, (int, np.integer)) or prefetch < 0:
            raise InvalidValueError(f"prefetch must be an int >= 0 (groups read ahead), got {prefetch!r}")
        for name, v in (("batch_blocks", batch_blocks), ("chunks_per_batch", chunks_per_group)):
            if v is not None and (isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1):
                raise InvalidValueError(f"{name} must be an int >= 1, got {v!r}")
        if states is None:
            states = self._states_in(box)
        groups = self._chunk_groups(box, states, level, batch_blocks=batch_blocks, chunks_per_group=chunks_per_group)
        b0 = np.array([s.start for s in box], dtype=np.int64)
        b1 = b0 + np.array(states.shape, dtype=np.int64)

        def job(chunks: np.ndarray) -> tuple[np.ndarray, Any]:
            coords, codes = self._fetch_group(chunks, b0, b1, states, level)
            return coords, (stage(codes) if stage is not None else codes)

        if len(groups) <= 1 or prefetch == 0:
            for g in groups:
                yield job(g)
            return
        pool = ThreadPoolExecutor(max_workers=int(prefetch), thread_name_prefix="sdfcodec-read")
        pending: collections.deque = collections.deque()
        todo = iter(groups)
        finished = False
        try:
            for g in itertools.islice(todo, int(prefetch)):
                pending.append(pool.submit(job, g))
            while pending:
                result = pending.popleft().result()
                nxt = next(todo, None)
                if nxt is not None:
                    pending.append(pool.submit(job, nxt))
                yield result
            finished = True
        finally:
            # abandoned early (an error, a consumer that stopped): do not wait for reads nobody will use
            for f in pending:
                f.cancel()
            pool.shutdown(wait=finished, cancel_futures=True)

    def _decode_stream(self, box: tuple[slice, slice, slice], level: int, dev: torch.device, *, metres: bool,
                       **kw) -> Iterator[tuple[np.ndarray, torch.Tensor]]:
        """The decode path: ``(coords (n, 3), core decodes (n, 16, 16, 16) on dev)`` per group of chunks, one
        batched decode per group (:meth:`_decode_codes`; keywords: see :meth:`_fetch_stream`)."""
        self.codec  # loaded (and its state checked) here, before any thread starts
        feed = _DeviceFeed(dev)
        for coords, staged in self._fetch_stream(box, level, stage=feed.stage, **kw):
            yield coords, self._decode_codes(feed.ready(staged), metres=metres)

    def _decode_codes(self, codes: torch.Tensor, *, metres: bool) -> torch.Tensor:
        """Core decodes ``(n, 16, 16, 16)`` of codes ``(n, L)`` on their device, in metres (the scaling folded
        into the codec's decode where it can, :meth:`Codec.decode_core`) or normalised. NaN/Inf out of the
        codec (a corrupted or hostile learned state) are refused: proven impossible by the codec's bound on
        its outputs when it gives one (no pass over the output), else checked on the output."""
        codec = self.codec
        d_min, d_max = self.truncation
        scale, offset = (d_max - d_min, d_min) if metres else (1.0, 0.0)
        v = codec.decode_core(codes, scale=scale, offset=offset)
        bound = codec._decode_bound(codes)
        if bound is not None and math.isfinite(bound) and bound * scale + abs(offset) < _FINITE_BOUND:
            return v
        return self._decoded(v)

    def iter_codes(self, *, level: int | None = None, chunks_per_batch: int = 8, prefetch: int = 2
                   ) -> Iterator[tuple[np.ndarray, np.ndarray]]:
        """Yield ``(coords (n, 3) int64, codes (n, L) float32)`` for every coded block, ``chunks_per_batch``
        chunks of the block grid at a time (bounded memory), in grid order; only the chunks holding the first
        ``L = level or D`` elements are read, and the next ``prefetch`` batches are read ahead concurrently."""
        lv = self._level(level)
        box = tuple(slice(0, n) for n in self._grid())
        yield from self._fetch_stream(box, lv, chunks_per_group=chunks_per_batch, batch_blocks=None,
                                      prefetch=prefetch)

    def iter_decoded(self, region: Region | None = None, *, units: str = "voxels", level: int | None = None,
                     device: str | torch.device | None = None, batch_blocks: int = 8192, prefetch: int = 2
                     ) -> Iterator[tuple[np.ndarray, Any]]:
        """Decode on read: yield ``(coords (n, 3) int64, blocks (n, 16, 16, 16) float32 metres)`` for every coded
        block touching ``region`` (default: the whole map), a group of chunks at a time, in grid order.

        This is the pipeline every decoding reader uses (:meth:`iter_blocks`, :meth:`decode_region`,
        :meth:`to_dask`): the chunks holding coded blocks are grouped (consecutive chunks until they hold about
        ``batch_blocks`` blocks, capped by ``max_decode_bytes``); while the calling thread decodes one group
        in a single batched call, ``prefetch`` worker threads fetch the next groups (each group's chunks
        concurrently through Zarr's async I/O: local files, HTTP or S3 alike), decompress them and, when
        ``device`` is CUDA, copy their codes into pinned host memory and start the host-to-device copy on a
        side stream (non-blocking), so transfers overlap decoding. Empty and unobserved blocks are not
        yielded (they decode to ``d_max``).

        Args:
            region: ``((x0, x1), (y0, y1), (z0, z1))`` half-open voxels, or closed metres with ``units="m"``;
                every coded block with a voxel in it is yielded, whole.
            level: decode only the first ``level`` code elements (prefix-ordered codecs).
            device: ``None``: decode on the CPU and yield numpy arrays; otherwise yield torch tensors on it.
            batch_blocks: about how many blocks one decode call gets. prefetch: groups read ahead (0: none).

        Values are metres, exactly as :meth:`iter_blocks` and :meth:`decode_region` give them; codecs with a
        decode halo see their neighbours (decoded chunk by chunk, each with its neighbourhood).
        """
        lv = self._level(level)
        box = self._block_range(self._block_box(region, units))
        yield from self._decoded_blocks(box, lv, device, batch_blocks=batch_blocks, prefetch=prefetch)

    def _decoded_blocks(self, box: tuple[slice, slice, slice], level: int, device: str | torch.device | None,
                        **kw) -> Iterator[tuple[np.ndarray, Any]]:
        """:meth:`_decoded_metres` on ``device``, as numpy when ``device`` is None (decoded on the CPU)."""
        dev = torch.device(device) if device is not None else torch.device("cpu")
        for coords, blocks in self._decoded_metres(box, level, dev, **kw):
            yield coords, blocks if device is not None else blocks.numpy()

    def _decoded_metres(self, box: tuple[slice, slice, slice], level: int, dev: torch.device, **kw
                        ) -> Iterator[tuple[np.ndarray, torch.Tensor]]:
        if not self.codec.halo:
            yield from self._decode_stream(box, level, dev, metres=True, **kw)
            return
        # a halo codec's blocks need their neighbours' core decodes: chunk by chunk, decode the bounding box of
        # its coded blocks with context (the same pipeline, reading the neighbouring chunks too)
        states = self._states_in(box)
        b0 = np.array([s.start for s in box], dtype=np.int64)
        cb = self.header.codes.chunk_blocks
        for (chunk,) in self._chunk_groups(box, states, level, chunks_per_group=1):
            lo, hi = np.maximum(chunk * cb, b0), np.minimum(chunk * cb + cb, b0 + states.shape)
            sub = states[tuple(slice(int(a), int(b)) for a, b in zip(lo - b0, hi - b0))]
            coords = np.argwhere(sub == BlockState.CODED) + lo
            vlo, vhi = coords.min(axis=0) * BLOCK, (coords.max(axis=0) + 1) * BLOCK
            vol = self._decode_voxels(vlo, vhi, level, dev)
            view = _block_view(vol, [(h - l) // BLOCK for l, h in zip(vlo, vhi)])
            rel = torch.from_numpy(coords - vlo // BLOCK).to(dev)
            yield coords, view[rel[:, 0], rel[:, 1], rel[:, 2]]

    def iter_blocks(self, *, level: int | None = None, device: str | torch.device | None = None,
                    chunks_per_batch: int | None = None) -> Iterator[tuple[np.ndarray, Any]]:
        """Yield ``(coords (n, 3) int64, blocks (n, 16, 16, 16) metres)`` for every coded block, a group of
        chunks at a time (bounded memory): :meth:`iter_decoded` over the whole map. ``blocks`` is numpy, or a
        tensor on ``device``. ``chunks_per_batch``: fixed number of chunks per group (default: about 8192
        blocks per group). Codecs with a decode halo get their neighbours' context, as in :meth:`decode_region`."""
        lv = self._level(level)
        box = tuple(slice(0, n) for n in self._grid())
        kw = {} if chunks_per_batch is None else {"chunks_per_group": chunks_per_batch, "batch_blocks": None}
        yield from self._decoded_blocks(box, lv, device, **kw)

    def to_dask(self, level: int | None = None):
        """A lazy dask array of the decoded map: shape :attr:`shape_voxels`, float32 metres (``d_max`` where no
        block is coded), one dask chunk per chunk of the code array (``16 * chunk_blocks`` voxels per axis),
        each decoded on demand by :meth:`decode_region`. It pickles (a worker process reopens the map by its
        path or URL), so it computes on a ``dask.distributed`` cluster. See :func:`sdfcodec.scale.map_to_dask`."""
        from .scale import map_to_dask

        return map_to_dask(self, level=level)

    def _decoded(self, v: torch.Tensor) -> torch.Tensor:
        """Refuse NaN/Inf out of the codec (a corrupted or hostile learned state) rather than return them."""
        # fast path: one reduction (NaN/Inf propagate into the sum); the exact test only when it is not finite
        if not bool(torch.isfinite(v.sum())) and not bool(torch.isfinite(v).all()):
            raise FormatError(f"{self.location}: codec {self.header.codec.id!r} decoded NaN/Inf values; its learned "
                              "state in the map is broken: restore the map from a copy or re-encode it")
        return v

    def _to_metres(self, v: torch.Tensor) -> torch.Tensor:
        d_min, d_max = self.truncation
        return v.mul_(d_max - d_min).add_(d_min)

    def _dense_core(self, lo: np.ndarray, hi: np.ndarray, level: int, dev: torch.device, *, metres: bool
                    ) -> torch.Tensor:
        """Core decodes (no halo processing) of voxels ``[lo, hi)``, which may reach outside the grid, in metres
        or normalised: free space (``d_max`` or 1.0) wherever no coded block is."""
        free = self.truncation[1] if metres else 1.0
        grid_hi = np.asarray(self.grid_blocks) * BLOCK
        clo, chi = np.maximum(lo, 0), np.minimum(hi, grid_hi)
        if np.any(chi <= clo):
            return empty(tuple(int(n) for n in hi - lo), dev).fill_(free)
        box = self._block_range(tuple(zip(clo.tolist(), chi.tolist())))
        b0 = np.array([s.start for s in box])
        nb = [s.stop - s.start for s in box]
        tmp = empty(tuple(n * BLOCK for n in nb), dev).fill_(free)
        view = _block_view(tmp, nb)
        for coords, core in self._decode_stream(box, level, dev, metres=metres):
            idx = torch.from_numpy(coords - b0).to(dev)
            view[idx[:, 0], idx[:, 1], idx[:, 2]] = core
        src = tuple(slice(int(a - o * BLOCK), int(b - o * BLOCK)) for a, b, o in zip(clo, chi, b0))
        if np.array_equal(clo, lo) and np.array_equal(chi, hi):
            return tmp[src]  # inside the grid (always, without a halo): a view, no copy
        out = empty(tuple(int(n) for n in hi - lo), dev).fill_(free)
        out[tuple(slice(int(a - l), int(b - l)) for a, b, l in zip(clo, chi, lo))] = tmp[src]
        return out

    def _decode_voxels(self, lo: np.ndarray, hi: np.ndarray, level: int, dev: torch.device) -> torch.Tensor:
        """Final decoded metres of voxels ``[lo, hi)`` inside the grid, neighbour context included."""
        h = self.codec.halo
        if not h:  # metres straight out of the decode
            return self._dense_core(np.asarray(lo), np.asarray(hi), level, dev, metres=True)
        core = self._dense_core(np.asarray(lo) - h, np.asarray(hi) + h, level, dev, metres=False)
        return self._to_metres(self.codec.decode_context(core[None])[0])

    def decode_region(self, region: Region | None = None, *, units: str = "voxels", level: int | None = None,
                      device: str | torch.device | None = None) -> Any:
        """Decode a region to a dense TSDF in metres.

        Args:
            region: ``((x0, x1), (y0, y1), (z0, z1))`` half-open, in voxels (default: the whole map) or, with
                ``units="m"``, closed bounds in metres (the voxels whose centres lie inside).
            level: decode only the first ``level`` code elements (prefix-ordered codecs only).
            device: where to decode. ``None``: on the CPU, returning numpy. Otherwise a torch tensor on it.

        Returns:
            ``(x1 - x0, y1 - y0, z1 - z0)`` float32 metres; voxels of no coded block hold ``d_max``. Codecs with
            a decode halo (e.g. ``gaussian-blur``) see their neighbour blocks, so there are no seams.
        """
        lv = self._level(level)
        vox = self._block_box(region, units)
        box = self._block_range(vox)
        nbytes = 4 * int(np.prod([(s.stop - s.start) * BLOCK + 2 * 16 for s in box]))
        if nbytes > self.max_decode_bytes:
            raise InvalidValueError(f"decoding {region or 'the whole map'} needs {nbytes / 2**30:.1f} GiB, above the "
                                    f"limit of {self.max_decode_bytes / 2**30:.1f} GiB; decode a smaller region or "
                                    "raise max_decode_bytes in open_map()")
        dev = torch.device(device) if device is not None else torch.device("cpu")
        lo, hi = np.array([v[0] for v in vox]), np.array([v[1] for v in vox])
        out = self._decode_voxels(lo, hi, lv, dev)
        return out.contiguous() if device is not None else np.ascontiguousarray(out.numpy())

    def info(self) -> dict[str, Any]:
        """Summary: header, blocks by state, bytes on disk (local maps), ratio to dense float32."""
        h = self.header
        dense = int(np.prod(h.shape_voxels)) * 4
        root = self._local_root()
        on_disk = _dir_bytes(root) if root is not None else None
        state_bytes = _dir_bytes(str(Path(root) / "codec")) if on_disk is not None else None
        counts = self.count_states()
        return {
            "location": self.location,
            "format_version": h.format_version,
            "codec": h.codec.config,
            "code_size": h.codes.size,
            "code_dtype": h.codes.dtype,
            "levels": h.codes.levels,
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
        }

    def _local_root(self) -> str | None:
        """The directory (or zip) this map reads from: the pinned version for maps opened by path."""
        store = self._group.store
        inner = store._store if isinstance(store, _GuardStore) else store
        if isinstance(inner, zarr.storage.LocalStore):
            return str(inner.root)
        if isinstance(inner, zarr.storage.ZipStore):
            return str(inner.path)
        return None

    def close(self) -> None:
        """Release the map: a read-only map lets go of the version it holds (a replaced version is removed once
        its last reader closes it), and further reads raise. Dropping the object does the same. A map being
        written must be committed or aborted first."""
        if self._writer is not None:
            raise InvalidValueError(f"{self.location} is being written: commit() or abort() it before close()")
        self._closed = True
        store = self._group.store
        inner = store._store if isinstance(store, _GuardStore) else store
        if isinstance(inner, _PinnedStore):
            inner.close_pin()

    # -- writing (maps from create_map) ---------------------------------------------------------------
    def _w(self) -> "_Writer":
        if self._writer is None:
            raise ReadOnlyError(f"{self.location} is open read-only; write with sdfcodec.create_map(...)")
        return self._writer

    def write_volume(self, volume: Any, *, offset: Sequence[int] = (0, 0, 0), batch_size: int = 16384,
                     progress: Callable[[int], None] | None = None) -> None:
        """Encode a dense TSDF ``(X, Y, Z)`` in metres, placed at voxel ``offset`` (multiples of 16).

        The map's extent grows to hold it (``shape_voxels`` records the true extent; the far faces are padded
        with free space). Values outside the truncation are clipped with a warning; NaN/Inf are refused.

        A dask array (e.g. ``dask.array.from_zarr`` of a volume larger than memory) is encoded chunk by chunk by
        dask's scheduler, or a ``dask.distributed`` cluster if a client is active, each task writing its chunks
        of codes into this map's temporary directory (:func:`sdfcodec.scale.write_volume_dask`).
        """
        w = self._w()
        if _is_dask_array(volume):
            from .scale import write_volume_dask

            return write_volume_dask(self, volume, offset=offset)
        vol = _check_volume(volume, self.truncation)
        off = np.asarray(offset, dtype=np.int64)
        if off.shape != (3,) or (off % BLOCK).any() or (off < 0).any():
            raise ShapeError(f"offset must be three non-negative multiples of {BLOCK} voxels, got {tuple(offset)}")
        w.grow_voxels(tuple(int(o + n) for o, n in zip(off, vol.shape)))
        d_min, d_max = self.truncation
        blocks = split_blocks(vol, fill=d_max)
        gb = blocks.shape[:3]
        flat = blocks.reshape(-1, BLOCK, BLOCK, BLOCK)
        coords = np.stack(np.meshgrid(*[np.arange(n) for n in gb], indexing="ij"), -1).reshape(-1, 3) + off // BLOCK
        w.put_blocks(coords, flat, batch_size=batch_size, progress=progress)

    def write_blocks(self, coords: Any, blocks: Any, *, weights: Any = None, batch_size: int = 16384,
                     progress: Callable[[int], None] | None = None) -> None:
        """Encode blocks ``(N, 16, 16, 16)`` in metres at block indices ``coords`` ``(N, 3)`` (non-negative).

        ``weights`` ``(N, 16, 16, 16)``, optional: per-voxel fusion weights (observation counts), stored
        losslessly up to 2048 as float16 in the optional ``weights`` array (extension "fusion-weights").
        """
        w = self._w()
        c = _check_coords(coords)
        b = _check_volume(blocks, self.truncation, shape=(len(c), BLOCK, BLOCK, BLOCK), name="blocks")
        if weights is not None:
            wt, _ = as_float_tensor(weights, "weights", (len(c), BLOCK, BLOCK, BLOCK))
            if len(c) and float(wt.min()) < 0:
                raise InvalidValueError("weights must be non-negative (observation counts)")
        if len(c):
            w.grow_blocks(c.max(axis=0))
        w.put_blocks(c, b, batch_size=batch_size, progress=progress)
        if weights is not None:
            w.put_weights(c, wt.numpy())

    @property
    def has_weights(self) -> bool:
        """True when the map stores fusion weights."""
        if self._writer is not None:
            return "weights" in self._group
        return self._weights is not None

    def read_weights(self, coords: Any) -> np.ndarray:
        """Fusion weights ``(N, 16, 16, 16)`` float32 of blocks ``coords`` (0 where none were written)."""
        if not self.has_weights:
            raise FormatError(f"{self.location} stores no fusion weights (write them with write_blocks(weights=...),"
                              " e.g. `sdfcodec fuse --weights`)")
        c = _check_coords(coords)
        if len(c) and np.any(c >= np.asarray(self.grid_blocks)):
            raise InvalidValueError(f"block coords outside the map's grid {self.grid_blocks}")
        arr = self._weights if self._writer is None else self._group["weights"]
        out = np.zeros((len(c), 4096), np.float32)
        for i, (x, y, z) in enumerate(c):
            out[i] = self._read(arr, (int(x), int(y), int(z), slice(None)))
        return out.reshape(len(c), BLOCK, BLOCK, BLOCK)

    def write_codes(self, coords: Any, codes: Any) -> None:
        """Store already-encoded codes ``(N, D)`` (from this map's codec) at block indices ``coords``."""
        w = self._w()
        c = _check_coords(coords)
        z, _ = as_float_tensor(codes, "codes", (len(c), self.code_size))
        if len(c):
            w.grow_blocks(c.max(axis=0))
        w.put_codes(c, z.numpy())

    def mark_empty(self, coords: Any) -> None:
        """Record blocks as observed free space (no code stored)."""
        w = self._w()
        c = _check_coords(coords)
        if len(c):
            w.grow_blocks(c.max(axis=0))
            w.set_state(c, BlockState.EMPTY)

    def commit(self) -> None:
        """Finish writing and move the map into place atomically; the object then reads the committed map."""
        w = self._w()
        final = w.commit()
        self._writer = None
        reopened = open_map(final, max_decode_bytes=self.max_decode_bytes)
        self._group, self.header, self.location = reopened._group, reopened.header, reopened.location
        self._reopen = reopened._reopen
        self._check_arrays()

    def abort(self) -> None:
        """Discard everything written; the previous map at the path (if any) is untouched."""
        if self._writer is not None:
            self._writer.abort()
            self._writer = None

    def __enter__(self) -> "Map":
        # a map opened for reading is closed on leaving the block; one being written is committed (and stays
        # open for reading, e.g. for info())
        self._close_on_exit = self._writer is None
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if self._close_on_exit:
            self.close()
            return
        if self._writer is None:
            return
        if exc_type is None:
            self.commit()
        else:
            self.abort()

    def __repr__(self) -> str:
        mode = "writing" if self._writer else "read-only"
        return (f"<sdfcodec.Map {self.location!r} {mode} codec={self.header.codec.id}-{self.code_size} "
                f"voxels={self.shape_voxels} voxel_size={self.voxel_size}>")


def _chunk_ranges(arr: zarr.Array, sel: tuple) -> list[range]:
    """Chunk indices per axis that reading ``arr[sel]`` touches (``sel``: ints and step-1 slices)."""
    ranges = []
    for s, n, c in zip(sel, arr.shape, arr.chunks):
        start, stop, _ = s.indices(n) if isinstance(s, slice) else (s, s + 1, 1)
        ranges.append(range(start // c, max(start // c + 1, -(-stop // c))))
    return ranges


def _dir_bytes(path: str) -> int | None:
    p = Path(path)
    if p.is_file():
        return p.stat().st_size
    if not p.is_dir():
        return None
    return sum(f.stat().st_size for f in p.rglob("*") if f.is_file())


def _is_dask_array(x: Any) -> bool:
    return type(x).__module__.split(".")[0] == "dask" and hasattr(x, "chunks") and hasattr(x, "dask")


def _check_coords(coords: Any) -> np.ndarray:
    c = np.asarray(coords)
    if c.ndim != 2 or c.shape[1] != 3:
        raise ShapeError(f"block coords must have shape (N, 3), got {c.shape}")
    if c.dtype.kind not in "iu":
        if c.dtype.kind == "f" and np.all(np.isfinite(c)) and np.all(c == np.round(c)):
            c = c.astype(np.int64)
        else:
            raise ShapeError(f"block coords must be integers, got dtype {c.dtype}")
    if len(c) and c.min() < 0:
        raise InvalidValueError("block coords must be non-negative (move the map origin to cover negative "
                                f"positions); got minimum {int(c.min())}")
    if len(np.unique(c, axis=0)) != len(c):
        raise InvalidValueError("block coords hold duplicates; write each block once per call")
    return c.astype(np.int64)


def _free_space(v: np.ndarray) -> np.ndarray:
    """``(N,)`` bool: which normalised blocks ``(N, 16, 16, 16)`` hold only free space (stored as ``empty``)."""
    return (v >= 1.0 - _EMPTY_EPS).reshape(len(v), -1).all(axis=1)


def _check_codes(codes: np.ndarray) -> None:
    """Refuse NaN/Inf codes out of an encoder before they are stored."""
    if not np.isfinite(codes).all():
        raise InvalidValueError("the codec produced NaN/Inf codes; the input or the codec state is broken")


def _store_code_chunk(codes_arr: zarr.Array, scale_arr: zarr.Array | None, box: tuple[slice, ...],
                      local: np.ndarray, codes: np.ndarray, had: bool) -> None:
    """Write float32 ``codes`` ``(n, D)`` of the blocks at ``local`` (indices inside the chunk ``box`` of the block
    axes) into that chunk of ``codes_arr``, quantised to int8 with their ``[offset, scale]`` rows in ``scale_arr``
    when the map stores int8 codes: one write per array (each chunk read first only when it already ``had``
    codes). The single-process writer and the dask encoder both write through here."""
    shape = [s.stop - s.start for s in box]
    idx = tuple(local.T)
    buf = np.asarray(codes_arr[box]) if had else np.zeros((*shape, codes_arr.shape[3]), dtype=codes_arr.dtype)
    if scale_arr is None:
        buf[idx] = codes.astype(codes_arr.dtype)
    else:
        q, params = quantize_codes(codes, per="block")
        sbuf = np.asarray(scale_arr[box]) if had else np.zeros((*shape, 2), dtype=np.float32)
        buf[idx], sbuf[idx] = q, params
        scale_arr[box] = sbuf
    codes_arr[box] = buf


def _check_volume(volume: Any, truncation: tuple[float, float], shape: tuple | None = None,
                  name: str = "volume") -> np.ndarray:
    if isinstance(volume, torch.Tensor):
        volume = volume.detach().cpu().numpy()
    v = np.asarray(volume)
    if v.dtype.kind != "f":
        from .errors import DTypeError

        raise DTypeError(f"{name} must be floating point metres, got dtype {v.dtype}")
    if shape is None and v.ndim != 3:
        raise ShapeError(f"{name} must be a dense (X, Y, Z) array of metres, got shape {v.shape}")
    if shape is not None and v.shape != shape:
        raise ShapeError(f"{name} must have shape {shape}, got {v.shape}")
    finite = np.isfinite(v)
    if not finite.all():
        raise InvalidValueError(f"{name} holds {int((~finite).sum())} NaN/Inf value(s); replace unobserved "
                                f"voxels with d_max (e.g. np.nan_to_num(v, nan={truncation[1]}))")
    d_min, d_max = truncation
    outside = int(((v < d_min) | (v > d_max)).sum())
    if outside:
        warnings.warn(f"{outside} value(s) of {name} lie outside the truncation [{d_min}, {d_max}] m and were "
                      "clipped to it", SDFCodecWarning, stacklevel=3)
        v = np.clip(v, d_min, d_max)
    return v.astype(np.float32, copy=False)


class _Writer:
    """State of a map being written into its temporary directory (``.NAME.tmp-*``, locked while we live).

    ``update`` is set for :func:`update_map`: the temporary directory starts as a copy of the current version
    (whose directory identity is ``update["source"]``), the grid and block states start from it, and the
    writer lock ``update["lock"]`` is held from the copy to the swap so no other update is lost.
    """

    def __init__(self, final: Path, tmp: Path, tmp_fd: int, group: zarr.Group, codec: Codec, header_kw: dict,
                 codes_spec: CodesSpec, overwrite: bool, device: torch.device, *,
                 max_state_bytes: int = DEFAULT_MAX_DECODE_BYTES, grid: tuple | None = None,
                 state: np.ndarray | None = None, update: dict | None = None):
        self.final, self.tmp, self.tmp_fd, self.group, self.codec = final, tmp, tmp_fd, group, codec
        self.header_kw, self.codes_spec, self.overwrite, self.device = header_kw, codes_spec, overwrite, device
        self.max_state_bytes, self.update = max_state_bytes, update
        self.shape_voxels = tuple(header_kw.pop("shape_voxels"))
        self.grid = tuple(grid) if grid is not None else tuple(-(-n // BLOCK) for n in self.shape_voxels)
        self.state = state if state is not None else np.zeros(self.grid, dtype=np.uint8)
        self.codes = group["codes"]
        self.code_scale = group["code_scale"] if codes_spec.dtype == "int8" else None

    def grow_voxels(self, need: tuple[int, int, int]) -> None:
        shape = tuple(max(a, b) for a, b in zip(self.shape_voxels, need))
        grid = tuple(max(g, -(-n // BLOCK)) for g, n in zip(self.grid, shape))
        if math.prod(grid) > self.max_state_bytes or max(shape) > 2**31 - 1:
            raise InvalidValueError(f"writing there would grow the map to {grid} blocks ({shape} voxels), whose block "
                                    f"states alone exceed the limit of {self.max_state_bytes} bytes; check the block "
                                    "coordinates or offset (or move the map's origin)")
        self.shape_voxels = shape
        if grid != self.grid:
            state = np.zeros(grid, dtype=np.uint8)
            state[tuple(slice(0, n) for n in self.grid)] = self.state
            self.state, self.grid = state, grid
            self.codes.resize((*grid, self.codes_spec.size))
            if self.code_scale is not None:
                self.code_scale.resize((*grid, 2))

    def grow_blocks(self, max_coord: np.ndarray) -> None:
        """Make the grid hold block ``max_coord``; the voxel extent grows only on axes the grid grows."""
        need = tuple((int(m) + 1) * BLOCK if int(m) >= g else n
                     for m, g, n in zip(max_coord, self.grid, self.shape_voxels))
        self.grow_voxels(need)

    def put_weights(self, coords: np.ndarray, weights: np.ndarray) -> None:
        if "weights" not in self.group:
            self.group.create_array("weights", shape=(*self.grid, 4096), dtype="float16", fill_value=0,
                                    chunks=(4, 4, 4, 4096), compressors=_compressors(),
                                    dimension_names=["bx", "by", "bz", "voxel"])
        arr = self.group["weights"]
        if tuple(arr.shape[:3]) != self.grid:
            arr.resize((*self.grid, 4096))
        # float16 counts are exact to 2048 frames and saturate at its maximum beyond
        w16 = np.minimum(weights.reshape(len(weights), 4096), 65504).astype(np.float16)
        for (x, y, z), row in zip(coords, w16):
            arr[int(x), int(y), int(z)] = row

    def set_state(self, coords: np.ndarray, value: int) -> None:
        self.state[tuple(coords.T)] = value

    def put_blocks(self, coords: np.ndarray, blocks_m: np.ndarray, *, batch_size: int,
                   progress: Callable[[int], None] | None) -> None:
        d_min, d_max = self.header_kw["truncation"].d_min, self.header_kw["truncation"].d_max
        for i in range(0, len(coords), batch_size):
            c = coords[i:i + batch_size]
            v = normalise(blocks_m[i:i + batch_size], d_min, d_max)
            empty = _free_space(v)
            self.set_state(c[empty], BlockState.EMPTY)
            if (~empty).any():
                codes = self.codec.encode(torch.from_numpy(np.ascontiguousarray(v[~empty])).to(self.device))
                self.put_codes(c[~empty], codes.cpu().numpy())
            if progress is not None:
                progress(len(c))

    def put_codes(self, coords: np.ndarray, codes: np.ndarray) -> None:
        """Scatter codes into whole chunks: one write per touched chunk (read first only if it had data)."""
        if not len(coords):
            return
        _check_codes(codes)
        cb = self.codes_spec.chunk_blocks
        chunk_of = coords // cb
        order = np.lexsort(chunk_of.T[::-1])
        coords, codes, chunk_of = coords[order], codes[order], chunk_of[order]
        bounds = np.flatnonzero(np.any(np.diff(chunk_of, axis=0) != 0, axis=1)) + 1
        for lo, hi in zip(np.r_[0, bounds], np.r_[bounds, len(coords)]):
            ch = chunk_of[lo]
            box = tuple(slice(int(c) * cb, min(int(c) * cb + cb, g)) for c, g in zip(ch, self.grid))
            had = bool((self.state[box] == BlockState.CODED).any())
            _store_code_chunk(self.codes, self.code_scale, box, coords[lo:hi] - ch * cb, codes[lo:hi], had)
        self.set_state(coords, BlockState.CODED)

    def commit(self) -> Path:
        st = self.group.create_array("state", shape=self.grid, dtype="uint8", fill_value=0,
                                     chunks=tuple(min(64, max(1, n)) for n in self.grid),
                                     compressors=_compressors(), overwrite=True)
        st[...] = self.state
        extensions = []
        if "weights" in self.group:
            if tuple(self.group["weights"].shape[:3]) != self.grid:
                self.group["weights"].resize((*self.grid, 4096))
            extensions.append(Extension(name="fusion-weights", required=False))
        if self.code_scale is not None:
            extensions.append(Extension(name=INT8_EXTENSION, required=True))
        header = MapHeader(shape_voxels=self.shape_voxels, grid_blocks=self.grid, codes=self.codes_spec,
                           extensions=extensions, **self.header_kw)
        # the header goes last: until the swap below nobody sees any of this anyway
        self.group.attrs["sdfcodec"] = json.loads(header.model_dump_json())
        try:
            lock = self.update["lock"] if self.update else _atomic.WriterLock(self.final, _LOCK_TIMEOUT).acquire()
        except BaseException:
            self.abort()
            raise
        try:
            exists = os.path.lexists(self.final)
            if self.update and (not exists or _stat_id(self.final) != self.update["source"]):
                raise FormatError(f"{self.final} was replaced or removed by something other than sdfcodec while "
                                  "this update ran; nothing was written: update it again")
            if exists and not self.overwrite:
                raise MapExistsError(f"{self.final} appeared while writing; nothing was replaced (use overwrite)")
            # on failure either call leaves everything as it was (the new version still at self.tmp)
            if exists:
                _atomic.swap_into_place(self.tmp, self.final)
            else:
                os.rename(self.tmp, self.final)
        except BaseException:
            self.abort()
            raise
        finally:
            lock.release()
        os.close(self.tmp_fd)  # the new version is in place: readers may now hold it
        self.tmp_fd = None
        _atomic.collect(self.final)  # the version replaced, if nobody reads it, and dead writers' leftovers
        return self.final

    def abort(self) -> None:
        if self.tmp_fd is not None:
            _rmtree(self.tmp)
            os.close(self.tmp_fd)
            self.tmp_fd = None
        if self.update:
            self.update["lock"].release()


def _stat_id(p: Path) -> tuple[int, int]:
    st = os.stat(p)
    return st.st_dev, st.st_ino


def _rmtree(p: Path) -> None:
    if p.is_dir():
        shutil.rmtree(p, ignore_errors=True)
    elif p.exists():
        p.unlink()


def _distribution_of(codec: Codec) -> tuple[str | None, str | None]:
    pkg = codec_package(codec.codec_id)
    if pkg is None:
        top = type(codec).__module__.split(".")[0]
        pkg = (metadata.packages_distributions().get(top) or [None])[0]
    try:
        version = metadata.version(pkg) if pkg else None
    except metadata.PackageNotFoundError:
        version = None
    return pkg, version


def create_map(path: str | os.PathLike, *, codec: Codec, voxel_size: float,
               truncation: tuple[float, float] = (-0.04, 0.1), origin: Sequence[float] = (0.0, 0.0, 0.0),
               shape_voxels: Sequence[int] = (0, 0, 0), code_dtype: str = "float32",
               chunk_blocks: int | None = None, chunk_code: int | None = None, overwrite: bool = False,
               device: str | torch.device = "cpu", tool: str | None = None, source: str | None = None) -> Map:
    """Start writing a new map at ``path`` (a local directory). Use as a context manager::

        with sdfcodec.create_map("room.sdfz", codec=codec, voxel_size=0.02) as m:
            m.write_volume(tsdf)          # metres, (X, Y, Z)

    Everything is written to a hidden sibling directory and moved into place on commit (leaving the block
    without an exception); on an exception, or if the process dies, nothing at ``path`` changes. Replacing a
    map (``overwrite``) swaps the new version in atomically; readers of the old one keep reading it.

    Args:
        codec: a fitted codec instance (its config and learned state are stored in the map).
        voxel_size: voxel edge in metres. truncation: ``(d_min, d_max)`` metres. origin: world position of
            voxel (0, 0, 0). shape_voxels: initial extent (grows with the data written).
        code_dtype: ``"float32"``, ``"float16"`` or ``"int8"`` code storage (int8: each block's code quantised
            with its own offset and scale, spec section 4a; a quarter of float32's bytes, readers before
            sdfcodec 0.2 refuse such maps by the extension they require).
        chunk_blocks, chunk_code: chunk shape (blocks per axis, code elements); sensible defaults.
        overwrite: replace an existing map at ``path`` (atomically, on commit).
        device: where encoding runs.
    """
    final = Path(path)
    if _is_url(str(path)):
        raise InvalidValueError(f"maps are written to local paths; got URL {path} (write locally, then upload)")
    if final.exists() and not overwrite:
        raise MapExistsError(f"{final} exists; pass overwrite=True (CLI: --overwrite) to replace it")
    if final.suffix == ".zip":
        raise InvalidValueError("writing zip maps is not supported; write a directory map and zip its contents")
    if not codec.is_fitted:
        codec._check_fitted()
    if code_dtype not in CODE_DTYPES:
        raise InvalidValueError(f"code_dtype must be one of {', '.join(CODE_DTYPES)}, got {code_dtype!r}")
    if not (np.isfinite(voxel_size) and voxel_size > 0):
        raise InvalidValueError(f"voxel_size must be a positive number of metres, got {voxel_size!r}")
    check_truncation(*truncation)
    if len(origin) != 3 or not np.all(np.isfinite(origin)):
        raise InvalidValueError(f"origin must be three finite numbers (metres), got {origin!r}")
    spec = _code_layout(codec, code_dtype, chunk_blocks, chunk_code)
    state = codec.state_dict()
    pkg, pkg_version = _distribution_of(codec)
    header_kw = dict(
        voxel_size=float(voxel_size), truncation=Truncation(d_min=truncation[0], d_max=truncation[1]),
        origin=tuple(float(o) for o in origin),
        codec=CodecSpec(id=codec.codec_id, config=codec.get_config(), package=pkg, package_version=pkg_version,
                        state_arrays=sorted(state), state_sha256=state_digest(state) if state else None),
        provenance=Provenance(created=now_iso(), sdfcodec_version=__version__, tool=tool, source=source),
    )
    bad_names = [n for n in state if not re.fullmatch(STATE_NAME_PATTERN, n)]
    if bad_names:
        raise InvalidValueError(f"codec {codec.codec_id!r} state array names {bad_names} cannot be stored in a map: "
                                f"names must match {STATE_NAME_PATTERN} (a plugin bug)")
    final.parent.mkdir(parents=True, exist_ok=True)
    _atomic.collect(final)  # leftovers of writers killed earlier
    tmp, tmp_fd = _atomic.make_temp_dir(final)
    try:
        group = zarr.open_group(_atomic.CowLocalStore(str(tmp)), mode="w", zarr_format=3)
        grid = tuple(-(-int(n) // BLOCK) for n in shape_voxels)
        cb, cc = spec.chunk_blocks, spec.chunk_code
        group.create_array("codes", shape=(*grid, spec.size), dtype=code_dtype, fill_value=0,
                           chunks=(cb, cb, cb, cc), compressors=_compressors(),
                           dimension_names=["bx", "by", "bz", "code"])
        if code_dtype == "int8":
            group.create_array("code_scale", shape=(*grid, 2), dtype="float32", fill_value=0, chunks=(cb, cb, cb, 2),
                               compressors=_compressors(), dimension_names=["bx", "by", "bz", "offset_scale"])
        cgroup = group.create_group("codec")
        for name, arr in state.items():
            arr = np.ascontiguousarray(arr)
            a = cgroup.create_array(name, shape=arr.shape, dtype=arr.dtype, chunks=arr.shape or (1,),
                                    compressors=_compressors())
            a[...] = arr
        header = MapHeader(shape_voxels=tuple(int(n) for n in shape_voxels), grid_blocks=grid, codes=spec,
                           extensions=[Extension(name=INT8_EXTENSION)] if code_dtype == "int8" else [], **header_kw)
    except BaseException:
        _rmtree(tmp)
        os.close(tmp_fd)
        raise
    writer = _Writer(final, tmp, tmp_fd, group, codec, dict(header_kw, shape_voxels=header.shape_voxels), spec,
                     overwrite, torch.device(device))
    return _writing_map(group, header, str(final), codec, writer, DEFAULT_MAX_DECODE_BYTES)


def _writing_map(group: zarr.Group, header: MapHeader, location: str, codec: Codec, writer: _Writer,
                 max_decode_bytes: int) -> Map:
    m = Map.__new__(Map)
    m._group, m.header, m.location, m.max_decode_bytes, m._codec = group, header, location, max_decode_bytes, codec
    m._writer, m._closed, m._close_on_exit, m._chunk_bytes = writer, False, False, {}
    m._reopen = None
    m._codes = group["codes"]
    m._code_scale = writer.code_scale
    return m


def update_map(path: str | os.PathLike, *, device: str | torch.device = "cpu", tool: str | None = None,
               wait: float = _LOCK_TIMEOUT, max_decode_bytes: int = DEFAULT_MAX_DECODE_BYTES) -> Map:
    """Start adding or replacing blocks of the existing map at ``path`` (a local directory). Use as a context
    manager, with the same write methods as :func:`create_map`::

        with sdfcodec.update_map("room.sdfz") as m:
            m.write_blocks(coords, blocks)      # new blocks grow the map; existing ones are replaced
            m.mark_empty(cleared)

    The current version is copied (hard links: writers only ever replace files) into a hidden sibling
    directory, changed there, and swapped into place atomically on commit. Until then, and if anything fails
    or the process dies, the map at ``path`` stays exactly as it was; readers that opened it keep reading the
    version they opened. One update at a time: a second waits up to ``wait`` seconds for the first.

    Args:
        device: where encoding runs. tool: recorded as the map's provenance tool (default: kept).
        wait: seconds to wait for another update of the same map to finish.
        max_decode_bytes: limit for reading the current version (see :func:`open_map`) and for growing it.

    Raises:
        MapNotFoundError: no map at ``path``. MapBusyError: another update held it for ``wait`` seconds.
        FormatError, UnknownCodecError: the current map is unreadable, or its codec plugin is missing (the
        codec is needed to encode the new blocks).
    """
    final = Path(path)
    if _is_url(str(path)) or final.is_file():
        raise InvalidValueError(f"only local directory maps can be updated, got {path} (copy it locally first)")
    if not final.exists():
        raise MapNotFoundError(f"no map at {final}; create it with sdfcodec.create_map")
    lock = _atomic.WriterLock(final, wait).acquire()
    tmp = tmp_fd = None
    try:
        src = open_map(final, max_decode_bytes=max_decode_bytes)
        h = src.header
        unknown = [e.name for e in h.extensions if e.name not in KNOWN_EXTENSIONS]
        if unknown:
            raise VersionError(f"{final} uses extension(s) {unknown} that this sdfcodec cannot keep consistent "
                               "while changing blocks; update it with a newer sdfcodec")
        codec = src.codec  # checks the state digest; the codec encodes the new blocks
        states = src.block_states()
        root = src._local_root()
        source_id = _stat_id(Path(root))
        tmp, tmp_fd = _atomic.make_temp_dir(final)
        _atomic.link_tree(root, tmp)
        src.close()
        group = zarr.open_group(_atomic.CowLocalStore(str(tmp)), mode="r+", zarr_format=3)
        prov = h.provenance if tool is None else h.provenance.model_copy(update={"tool": tool})
        header_kw = dict(voxel_size=h.voxel_size, truncation=h.truncation, origin=h.origin, codec=h.codec,
                         provenance=prov, shape_voxels=h.shape_voxels)
        writer = _Writer(final, tmp, tmp_fd, group, codec, header_kw, h.codes, True, torch.device(device),
                         max_state_bytes=max_decode_bytes, grid=h.grid_blocks, state=states.copy(),
                         update={"lock": lock, "source": source_id})
    except BaseException:
        if tmp is not None:
            _rmtree(tmp)
            os.close(tmp_fd)
        lock.release()
        raise
    return _writing_map(group, h, str(final), codec, writer, max_decode_bytes)


def _reader_store(path_or_url: str | os.PathLike | zarr.abc.store.Store, loc: str,
                  storage_options: dict | None) -> zarr.abc.store.Store:
    if isinstance(path_or_url, zarr.abc.store.Store):
        return _GuardStore(path_or_url)
    if _is_url(loc):
        return _GuardStore(zarr.storage.FsspecStore.from_url(loc, read_only=True, storage_options=storage_options))
    p = Path(loc)
    if not p.exists():
        raise MapNotFoundError(f"no map at {loc}")
    if p.is_file():
        return _GuardStore(zarr.storage.ZipStore(p, mode="r"))
    if _atomic.HAVE_PROC_FD:
        return _GuardStore(_PinnedStore.pin(p))
    return _GuardStore(zarr.storage.LocalStore(p, read_only=True))


def open_map(path_or_url: str | os.PathLike | zarr.abc.store.Store, *, storage_options: dict | None = None,
             max_decode_bytes: int = DEFAULT_MAX_DECODE_BYTES) -> Map:
    """Open a map read-only: a local directory, a ``.zip``, a URL (``http(s)://``, ``s3://``, ``file://``...
    through fsspec) or any Zarr store. Reads only the header and array metadata; data is read on demand.

    A local directory map is held at the version opened (Linux): a writer replacing it meanwhile changes
    nothing this object reads; open the path again to see the new version. ``close()`` (or dropping the object,
    or leaving a ``with`` block) lets the old version go.

    ``max_decode_bytes`` bounds what one call may allocate (a decoded region, a dense read of codes, the
    block states, one chunk, the codec state): maps whose header or array metadata name more are refused with
    FormatError before anything is read. Opening never runs code from the map.
    """
    loc = str(path_or_url)
    try:
        store = _reader_store(path_or_url, loc, storage_options)
        group = zarr.open_group(store, mode="r", zarr_format=3)
        raw = group.attrs.get("sdfcodec")
    except (MapNotFoundError, FormatError):
        raise
    except (FileNotFoundError, NotADirectoryError) as e:
        raise MapNotFoundError(f"no map at {loc}") from e
    except SDFCodecError:
        raise
    except Exception as e:
        raise FormatError(f"{loc}: not a readable Zarr v3 group ({type(e).__name__}: {e})") from e
    header = parse_header(raw, where=loc)
    m = Map(group, header, loc, max_decode_bytes=max_decode_bytes)
    inner = store._store if isinstance(store, _GuardStore) else store
    m._reopen = (path_or_url if isinstance(path_or_url, zarr.abc.store.Store) else
                 str(inner._path) if isinstance(inner, _PinnedStore) else loc, storage_options)
    return m


def _block_view(vol: torch.Tensor, nb) -> torch.Tensor:
    """``(16 bx, 16 by, 16 bz)`` -> a ``(bx, by, bz, 16, 16, 16)`` view of the same memory."""
    return vol.view(nb[0], BLOCK, nb[1], BLOCK, nb[2], BLOCK).permute(0, 2, 4, 1, 3, 5)
