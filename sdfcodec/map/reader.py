"""The map reader: :class:`MapReader` reads one open map's header-checked arrays (the codes of a region or a
level, block states, fusion weights), loads its codec, and decodes through the streaming pipeline to blocks
or dense voxels. :class:`sdfcodec.Map` is a thin facade over it; ``MapField``, search, verify and the dask
path (``sdfcodec.map.scale``) call it directly as ``Map.reader``.

Maps are untrusted input: opening one never runs code from it, and every size the header or the array
metadata names is checked against ``max_decode_bytes`` before anything that large is allocated. A coded block
whose code chunk is not stored is an error naming the chunk (Zarr alone would read zeros), and decoded values
beyond :data:`~sdfcodec.map.format.DECODE_LIMIT` or non-finite are refused naming the blocks (spec section 9a).
"""

from __future__ import annotations

import asyncio
import itertools
import math
from typing import Any, Callable, Iterator, Sequence

import numpy as np
import zarr
import zarr.abc.store
from zarr.core.sync import sync as zarr_sync

from ..core._lazy import lazy_module
from ..core._validate import BLOCK, check_device, empty, output_buffer
from ..codec import Codec
from ..errors import ChecksumError, FormatError, IntegrityError, InvalidValueError, RemoteReadError, SDFCodecError
from ..core.header import PINNED_MASK_EXTENSION, BlockState, MapHeader
from .format import (BYTES_PER_CHUNK, DEFAULT_MAX_DECODE_BYTES, MIN_CHUNKS_PER_READ, Region, check_array_metadata,
                     check_coords, code_values, region_voxels, unstored_suspects)
from .io.shards import chunk_ranges
from .groupdecode import decode_group
from .grouping import Box, chunk_groups, prefetched
from .metric import codec_codes, is_metric
from .codec_state import load_codec
from .implied import ImpliedArray, implied_arrays, unpack_states
from .presence import check_state_chunks
from .placement import BlockPlacer, BufferRing, RingPool
from .observed import (MASK_ARRAY, MASK_EXTENSION, checked_mask_array, read_block_rows, restore_unobserved,
                       restore_unobserved_voxels)
from .residual import check_residual_stored, checked_residual_array
from .io.remote import RemoteStore
from .io.stores import GuardStore, PinnedStore, fetch_members, unguarded
from .weights import checked_weights_array
from .device_feed import DeviceFeed
from .io.shards import chunk_name, chunk_stored, shard_layout
from .varread import STREAM_ARRAY, VariableRateReader, decode_runs, prefix_lengths

torch = lazy_module("torch")  # imported on first use: info, codecs, verify of a header never need it

__all__ = ["MapReader", "CodecCache", "DeviceFeed"]

#: Output buffers ``iter_decoded(copy=False)`` cycles through: a yielded batch stays valid while the next one is
#: decoded and used (a consumer may look one batch back), and is overwritten by the one after.
RING = 2


class CodecCache:
    """Holds the codec of a map once loaded; shared by readers of the same map (:meth:`MapReader.with_store`),
    so a codec loaded through one is loaded for all."""

    def __init__(self, codec: Codec | None = None):
        self.codec = codec


class MapReader:
    """Reads one open map (a Zarr group whose header is ``header``); see the module docstring.

    ``live``: for a map being written, the writer (anything with ``state`` ``(Bx, By, Bz)`` uint8 and
    ``grid``), whose block states are read instead of the ``state`` array, which is written on commit.
    ``source``: ``(path, URL or store; storage options)`` to reopen the map by in another process (None for
    a map being written). Arrays (after :meth:`_check_arrays`): ``codes_array``, ``state_array``,
    ``code_scale_array`` (int8 maps), ``weights_array`` (maps with fusion weights), else None.
    """

    codes_array, state_array = ImpliedArray(), ImpliedArray()  # (built on first use where implied, spec 4e)

    def __init__(self, group: zarr.Group, header: MapHeader, location: str, *,
                 max_decode_bytes: int = DEFAULT_MAX_DECODE_BYTES, cache: CodecCache | None = None,
                 live: Any = None, source: tuple[Any, dict | None] | None = None, owns_store: bool = True):
        self.group, self.header, self.location, self.max_decode_bytes = group, header, location, max_decode_bytes
        self.live, self.source = live, source
        self._cache = cache if cache is not None else CodecCache()
        self._owns_store, self._closed = owns_store, False
        self._chunk_bytes: dict[str, int] = {}
        self.state_chunks_checked: set[tuple[int, ...]] = set()  # state chunks found present or legitimately absent
        self.implied_pending = False  # codes_array and state_array still to build (ImpliedArray)
        self.codes_array = self.state_array = self.code_scale_array = self.weights_array = self.mask_array = None
        self.residual_array = None
        self.residual_chunks_checked: set[str] = set()  # residual chunks found stored (under coded blocks)
        self.rings = RingPool(RING)  # iter_decoded(copy=False)'s output buffers, kept between its iterations
        self._inline_states: np.ndarray | None = None  # the header's block states (spec 4e), read-only
        self._fetched: dict[str, Any] = {}  # members read ahead by _check_arrays (node or exception), taken once
        if live is None:
            self._check_arrays()
        else:  # a map being written: its arrays are the writer's, checked as they were made
            self.codes_array, self.code_scale_array = group["codes"], live.code_scale

    # -- geometry (the header's) ---------------------------------------------------------------------
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
    def cache(self) -> CodecCache:
        """The codec cache (shared with the readers :meth:`with_store` makes)."""
        return self._cache

    @property
    def pinned_fd(self) -> int | None:
        """The directory descriptor holding the version of a local map this reader reads (None otherwise)."""
        inner = unguarded(self.group.store)
        return inner.fd if isinstance(inner, PinnedStore) else None

    def with_store(self, wrap: Callable[[zarr.abc.store.Store], zarr.abc.store.Store]) -> "MapReader":
        """The same map read through ``wrap(store)`` (e.g. a store counting what is read), sharing header,
        limits and codec cache; closing it leaves this reader's store open. The arrays' metadata is read
        again, through the wrapper."""
        if self.live is not None:
            raise InvalidValueError(f"{self.location} is still being written; leave the create_map block (commit) "
                                    "and open the map with sdfcodec.open_map")
        self._check_open()
        group = zarr.open_group(wrap(self.group.store), mode="r", path=self.group.path or None, zarr_format=3)
        return MapReader(group, self.header, self.location, max_decode_bytes=self.max_decode_bytes,
                         cache=self._cache, source=self.source, owns_store=False)

    def member(self, path: str, kind: type = zarr.Array) -> Any:
        """The array (or group) at ``path``, or None when absent; unreadable metadata is a FormatError."""
        try:
            node = self._fetched.pop(path, None)
            if isinstance(node, BaseException):
                raise node
            if node is None:
                node = self.group[path]
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

    def check_array(self, arr: zarr.Array, *, dtype: Any = None, shape: tuple | None = None,
                    chunks: tuple | None = None, zero_fill: bool = False, field: Any = None,
                    shards: tuple | None = None, mask_coded: bool = False) -> None:
        """Validate an array's metadata against the spec and the reader's limits *before* reading from it, and
        register its chunk size with the guard store (a chunk claiming more is refused unread)."""
        chunk_bytes, blosc_first, per_object = check_array_metadata(
            arr, f"{self.location}: array '{arr.path}'", dtype=dtype, shape=shape, chunks=chunks,
            zero_fill=zero_fill, field=field, shards=shards, mask_coded=mask_coded)
        # the chunk size is checked when reading (read), so that a small limit still lets a map open and say
        # what is too big
        self._chunk_bytes[arr.path] = chunk_bytes
        store = self.group.store
        if isinstance(store, GuardStore):
            store.limits[arr.path] = (chunk_bytes, blosc_first, per_object)

    def _check_arrays(self) -> None:
        h = self.header
        state_bytes = math.prod(h.grid_blocks)
        if state_bytes > self.max_decode_bytes:
            raise FormatError(f"{self.location}: header field grid_blocks {h.grid_blocks} needs {state_bytes} bytes "
                              f"of block states, above the reader's limit of {self.max_decode_bytes} bytes (raise "
                              "max_decode_bytes in open_map() if the map is genuine)")
        implied = h.codes.variable_rate is not None and h.codes.variable_rate.states is not None
        names = {e.name for e in h.extensions}
        mask = (MASK_ARRAY,) if MASK_EXTENSION in names else ()
        if PINNED_MASK_EXTENSION in names:  # pinstore (and the modules it loads) imported only for maps with one
            from .pinstore import PINNED_ARRAY
            mask = (PINNED_ARRAY,)
        # the members the checks below read, as the header names them, read together (absent: None there)
        self._fetched = fetch_members(self.group, [
            *(() if implied else ("codes", "state")), *(("code_scale",) if h.codes.dtype == "int8" else ()),
            *((STREAM_ARRAY,) if h.codes.variable_rate is not None else ()), *mask])
        if implied:  # the states in the header (spec 4e): codes and state built on first use (build_implied)
            self._inline_states = unpack_states(h.codes.variable_rate.states, tuple(h.grid_blocks), self.location)
            self.implied_pending = True
        else:
            codes, state = self.member("codes"), self.member("state")
            if codes is None or state is None:
                missing = "codes" if codes is None else "state"
                raise FormatError(f"{self.location}: map lacks array '{missing}'; it is incomplete or not an sdfcodec "
                                  "map")
            self._set_codes_state(codes, state)
        self.code_scale_array, cb = None, h.codes.chunk_blocks
        if h.codes.dtype == "int8":
            self.code_scale_array = self.member("code_scale")
            if self.code_scale_array is None:
                raise FormatError(f"{self.location}: map has int8 codes but lacks array 'code_scale' (spec section "
                                  "4a); it is incomplete")
            self.check_array(self.code_scale_array, dtype=np.float32, shape=(*h.grid_blocks, 2),
                             chunks=(cb, cb, cb, 2), zero_fill=True)
        self.weights_array = checked_weights_array(self)  # float16, or uint8 counts (spec section 6a)
        self.mask_array = checked_mask_array(self)
        self.residual_array = checked_residual_array(self)
        # variable-rate codes (spec 4e): read from their chunk streams, the codes array holds no chunk
        self.vr = None if h.codes.variable_rate is None else VariableRateReader(self, h.codes.variable_rate)
        self.refinement = None  # a surface refinement's corrections (spec 6h)
        if self.vr is not None and h.codes.variable_rate.refinement is not None:
            from .refine import RefinementReader

            self.refinement = RefinementReader(self, h.codes.variable_rate.refinement)

    def _set_codes_state(self, codes: zarr.Array, state: zarr.Array) -> None:
        """Check the ``codes`` and ``state`` arrays against the header and take them."""
        h = self.header
        cb, sb = h.codes.chunk_blocks, h.codes.shard_blocks
        chunks = (cb, cb, cb, h.codes.chunk_code)
        self.check_array(codes, dtype=h.codes.dtype, shape=(*h.grid_blocks, h.codes.size), chunks=chunks,
                         zero_fill=True, field=h.codes.field_compression,
                         shards=None if sb is None else shard_layout(chunks, h.codes.size, sb))
        self.check_array(state, dtype=np.uint8, shape=tuple(h.grid_blocks), zero_fill=True)
        self.codes_array, self.state_array = codes, state

    def build_implied(self) -> None:
        """The ``codes`` and ``state`` arrays of a map whose header holds its states (spec 4e), built in memory and
        checked as stored ones are (:class:`~sdfcodec.map.implied.ImpliedArray`: on first use)."""
        codes, state = implied_arrays(self.header, self._inline_states)  # the states unpacked at open
        self._set_codes_state(codes, state)
        self.implied_pending = False  # after the arrays are set: another thread reads them, or builds them too

    # -- reading --------------------------------------------------------------------------------------
    def read(self, arr: zarr.Array, sel: tuple) -> np.ndarray:
        """Read ``arr[sel]``; a chunk that fails its checksum or decompression becomes a ChecksumError
        naming the chunk."""
        self._check_read(arr, sel)
        try:
            return np.asarray(arr[sel])
        except RemoteReadError:  # the server or the network failed, not the chunk: its own message
            raise
        except Exception as exc:  # find the chunk(s) to name: slow path, errors only
            raise self._chunk_error(arr, sel, exc) from exc

    def read_many(self, arr: zarr.Array, sels: Sequence[tuple]) -> list[np.ndarray]:
        """Read ``arr[sel]`` for every selection concurrently (one batch of Zarr's async I/O: the chunks are
        fetched and decompressed in parallel, off the calling thread), with the checks of :meth:`read`."""
        for sel in sels:
            self._check_read(arr, sel)
        if not sels:  # no round trip to Zarr's event loop thread (a GIL hand-over each, ~1 ms on a busy machine)
            return []
        if len(sels) == 1:
            return [self.read(arr, sels[0])]
        aarr = arr.async_array

        async def gather():
            return await asyncio.gather(*(aarr.getitem(sel) for sel in sels), return_exceptions=True)

        out = []
        for sel, res in zip(sels, zarr_sync(gather())):
            if isinstance(res, BaseException):
                if not isinstance(res, Exception) or isinstance(res, RemoteReadError):
                    raise res
                raise self._chunk_error(arr, sel, res) from res
            out.append(np.asarray(res))
        return out

    def read_rows(self, arr: zarr.Array, keys: Sequence[Sequence[int]]) -> list[np.ndarray]:
        """The stored row ``(1, 1, 1, L)`` of each chunk ``k`` of ``keys`` of a stream array ``(Cx, Cy, Cz, L)`` (one
        row a chunk: codes, masks, corrections): :meth:`read_many` of ``arr[k0:k0 + 1, k1:k1 + 1, k2:k2 + 1, :]``."""
        return self.read_many(arr, [(*(slice(int(c), int(c) + 1) for c in k), slice(None)) for k in keys])

    def gather(self, arr: zarr.Array, sels: Sequence[tuple], locs: Sequence[np.ndarray]) -> np.ndarray:
        """The rows ``arr[sel][tuple(loc.T)]`` of every selection, stacked (:meth:`read_many`)."""
        return np.concatenate([a[tuple(loc.T)] for a, loc in zip(self.read_many(arr, sels), locs)])

    def _chunk_error(self, arr: zarr.Array, sel: tuple, exc: Exception) -> Exception:
        if isinstance(exc, IntegrityError) or (isinstance(exc, FormatError) and not isinstance(exc, ChecksumError)):
            return exc  # the store refused a file (a link, a FIFO, a manifest mismatch...): its message names the key
        return ChecksumError(f"{self.location}: {self._bad_chunks(arr, sel)} of array '{arr.path}' is "
                             f"corrupted or truncated ({type(exc).__name__}: {exc}); the map cannot be "
                             "trusted there: restore it from a copy or re-encode")

    def _check_open(self) -> None:
        if self._closed:
            raise InvalidValueError(f"{self.location}: the map was closed; open it again with sdfcodec.open_map")

    def _check_read(self, arr: zarr.Array, sel: tuple) -> None:
        """The limits on one read (module docstring): open map, chunk size, number of chunks touched."""
        self._check_open()
        chunk_bytes = self._chunk_bytes.get(arr.path, 0)
        if chunk_bytes > self.max_decode_bytes:
            raise InvalidValueError(f"{self.location}: array '{arr.path}' has chunks of {chunk_bytes} bytes, above the "
                                    f"limit of {self.max_decode_bytes} bytes; raise max_decode_bytes in open_map() "
                                    "if the map is genuine")
        # each chunk costs a request and a task however small it is: a read may touch only so many (a hostile
        # chunk grid of 1-element chunks would otherwise take hours to read a modest array)
        n_chunks = math.prod(len(r) for r in chunk_ranges(arr, sel))
        max_chunks = max(MIN_CHUNKS_PER_READ, self.max_decode_bytes // BYTES_PER_CHUNK)
        if n_chunks > max_chunks:
            raise InvalidValueError(f"{self.location}: reading array '{arr.path}' there touches {n_chunks} chunks, above "
                                    f"the limit of {max_chunks} for max_decode_bytes={self.max_decode_bytes}; read a "
                                    "smaller region, or raise max_decode_bytes if the map is genuine")

    def _bad_chunks(self, arr: zarr.Array, sel: tuple) -> str:
        # probe chunk by chunk, in one batch of Zarr's async I/O (one probe after another cost a round trip
        # each: 256 of them took seconds on a local map, more over HTTP), and boundedly: at most 256 chunks and
        # max_decode_bytes decoded in all (16 MiB chunks under a 64 MiB limit used to probe 4 GiB to name one)
        limit = min(256, max(1, self.max_decode_bytes // max(1, self._chunk_bytes.get(arr.path, 0))))
        idxs = list(itertools.islice(itertools.product(*chunk_ranges(arr, sel)), limit))
        sels = [tuple(slice(i * c, min((i + 1) * c, n)) for i, c, n in zip(idx, arr.chunks, arr.shape))
                for idx in idxs]
        aarr = arr.async_array

        async def probe():
            return await asyncio.gather(*(aarr.getitem(s) for s in sels), return_exceptions=True)

        bad = ["chunk " + chunk_name(arr, idx).split("/", 1)[1] for idx, res in zip(idxs, zarr_sync(probe()))
               if isinstance(res, Exception)]
        if not bad:
            return "a chunk"
        return ", ".join(bad[:5]) + (" and more" if len(bad) > 5 else "")

    def block_states(self) -> np.ndarray:
        """``(Bx, By, Bz)`` uint8 block states (see :class:`sdfcodec.core.header.BlockState`)."""
        if self.live is not None:
            return self.live.state.copy()
        return self._valid_states(self._stored_states((slice(None),) * 3), (slice(None),) * 3)

    def count_states(self) -> dict[str, int]:
        """Number of blocks per state name (``unobserved``, ``empty``, ``coded``)."""
        counts = np.bincount(self.block_states().ravel(), minlength=3)
        return {name: int(counts[v]) for v, name in BlockState.NAMES.items()}

    @property
    def codec(self) -> Codec:
        """The codec that wrote the map, with its learned state (loaded on first use).

        Raises:
            UnknownCodecError: its plugin is not installed (names the id and the package to install).
        """
        if self._cache.codec is None:
            self._cache.codec = load_codec(self)
        return self._cache.codec

    def level(self, level: int | None) -> int:
        """A code prefix level checked against the map: ``level`` itself, or the full code size for None."""
        size = self.header.codes.size
        if level is None or level == size:
            return size
        if not self.header.codes.prefix_ordered:
            raise InvalidValueError(f"codec {self.header.codec.id!r} codes are not prefix-ordered, so level "
                                    f"{level} cannot be decoded; omit the level (full size {size})")
        if not isinstance(level, (int, np.integer)) or not 1 <= level <= size:
            raise InvalidValueError(f"level must be an int in 1..{size}, got {level!r}")
        return int(level)

    def block_box(self, region: Region | None, units: str) -> tuple[tuple[int, int], ...]:
        """Region (``units`` ``"voxels"`` or ``"m"``; None: the whole map) -> validated half-open voxel bounds
        per axis (:func:`~sdfcodec.map.format.region_voxels`)."""
        return region_voxels(region, units, self.shape_voxels, self.origin, self.voxel_size)

    def read_codes(self, region: Region | None = None, *, units: str = "voxels", level: int | None = None
                   ) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`sdfcodec.Map.read_codes`: ``(coords (N, 3) int64, codes (N, L) float32)``, as the codec encodes
        them (metric codes normalised: sdfcodec.map.metric)."""
        lv = self.level(level)
        box = self.block_range(self.block_box(region, units))
        coords, codes = self.codes_in(box, lv)
        return coords, codec_codes(self.header.codes, self.truncation, codes)

    @staticmethod
    def block_range(vox: tuple[tuple[int, int], ...]) -> Box:
        """Half-open voxel bounds per axis -> the block box of every block with a voxel in them."""
        return tuple(slice(lo // BLOCK, -(-hi // BLOCK)) for lo, hi in vox)  # type: ignore[return-value]

    def codes_in(self, box: Box, level: int, states: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """``(coords (N, 3) int64, codes (N, level) float32)`` of the coded blocks in block box ``box``, read
        densely in one go (bounded by ``max_decode_bytes``); ``states``: the whole map's, if already read."""
        state = (self.block_states() if states is None else states)[box]
        local = np.argwhere(state == BlockState.CODED)
        if not len(local):
            return np.zeros((0, 3), np.int64), np.zeros((0, level), np.float32)
        nbytes = state.size * self.header.codes.stored_bytes(level)
        if nbytes > self.max_decode_bytes:
            raise InvalidValueError(f"reading the codes of blocks {[(s.start, s.stop) for s in box]} densely needs "
                                    f"{nbytes / 2**30:.1f} GiB, above the limit of {self.max_decode_bytes / 2**30:.1f}"
                                    " GiB; read a smaller region, use iter_codes(), or raise max_decode_bytes")
        coords = local + np.array([s.start for s in box], dtype=np.int64)
        if self.vr is not None:
            return coords, self.vr.codes_for(coords, level)
        codes = self.read(self.codes_array, (*box, slice(0, level)))[tuple(local.T)]
        params = (None if self.code_scale_array is None
                  else self.read(self.code_scale_array, (*box, slice(0, 2)))[tuple(local.T)])
        return coords, self._code_values(coords, codes, params)

    def _code_values(self, coords: np.ndarray, codes: np.ndarray, params: np.ndarray | None) -> np.ndarray:
        """Stored ``codes`` of blocks ``coords`` as float32 (dequantised with their ``code_scale`` rows
        ``params`` for int8 maps), refusing NaN/Inf or a negative scale (a corrupted, checksum-valid chunk)."""
        self._check_stored(coords, codes, params)
        out, finite = code_values(codes, params, self.header.codes.quantisation)
        if not finite.all():
            bad = coords[~finite]
            raise FormatError(f"{self.location}: {len(bad)} coded block(s) hold NaN/Inf code values (or a negative "
                              f"int8 scale), e.g. block {tuple(int(v) for v in bad[0])}; the map is corrupted there "
                              "(`sdfcodec verify` lists them): restore it from a copy or re-encode those blocks")
        return out

    def _check_stored(self, coords: np.ndarray, codes: np.ndarray, params: np.ndarray | None) -> None:
        """Refuse coded blocks ``coords`` (n, 3) whose code (or ``code_scale``) chunk is not stored: Zarr reads it
        as zeros. Only the chunks :func:`~sdfcodec.map.format.unstored_suspects` names are looked up."""
        if self.live is not None:
            return  # a map being written: its chunks are the writer's
        seen: set[str] = set()
        for name, chunk, row in unstored_suspects(coords, codes, params, self.header.codes):
            arr = self.codes_array if name == "codes" else self.code_scale_array
            key = chunk_name(arr, chunk)  # its file, or its place in its shard (spec section 4d)
            if key in seen:
                continue
            seen.add(key)
            if not chunk_stored(self.group.store, arr, [chunk])[0]:
                raise FormatError(f"{self.location}: chunk {key} of array '{arr.path}' is missing, but block "
                                  f"{tuple(int(v) for v in coords[row])} in it is coded (the state array says "
                                  "so); the map is incomplete there: restore it from a copy or re-encode")

    # -- the decode-on-read pipeline ------------------------------------------------------------------
    # One path reads and decodes codes for every reader (iter_codes, iter_decoded, iter_blocks, decode_region,
    # to_dask, the tracker's map field): the chunks of the code array that hold coded blocks of a block box are
    # cut into groups; a small thread pool fetches the next groups (each group's chunks concurrently, through Zarr's
    # async I/O) and stages codes for the
    # device (pinned host memory + an asynchronous copy on CUDA) while the calling thread decodes the current
    # group in one batched call.

    def grid(self) -> tuple[int, int, int]:
        """The block grid: the header's, or for a map being written, as far as it has grown."""
        return self.live.grid if self.live is not None else self.grid_blocks

    def states_in(self, box: Box) -> np.ndarray:
        """Block states of a block box: only the state chunks it touches are read."""
        if self.live is not None:
            return self.live.state[box]
        return self._valid_states(self._stored_states(box), box)

    def _stored_states(self, box: Box) -> np.ndarray:
        """The ``state`` array's values in block box ``box``: for a map whose header holds them (spec 4e), what
        its implied array holds, copied unread (a Zarr read of it cost ~1 ms, twice a read); else read."""
        if self._inline_states is None:
            return self.read(self.state_array, box)
        self._check_open()
        return self._inline_states[box].copy()

    def _valid_states(self, state: np.ndarray, box: Box) -> np.ndarray:
        if state.size and state.max() > BlockState.CODED:
            raise FormatError(f"{self.location}: state array holds reserved value {int(state.max())} "
                              "(valid: 0 unobserved, 1 empty, 2 coded)")
        if self._inline_states is None:  # (states in the header, spec 4e, have no chunk to lose)
            check_state_chunks(self, box, state)  # a lost state chunk must not read as unobserved (spec 9a)
        return state

    def _chunk_groups(self, box: Box, states: np.ndarray, level: int, **kw) -> list[np.ndarray]:
        """:func:`~sdfcodec.map.grouping.chunk_groups` of this map's codes (keywords: ``batch_blocks``,
        ``chunks_per_group``, ``columns``), capped by ``max_decode_bytes``."""
        return chunk_groups(self.header.codes, box, states, level, max_decode_bytes=self.max_decode_bytes, **kw)

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
        coords = np.concatenate([loc + lo for loc, lo in zip(locs, los)]).astype(np.int64, copy=False)
        if self.vr is not None:
            return coords, self.vr.codes_for(coords, level)
        codes = self.gather(self.codes_array, sels, locs)
        params = None
        if self.code_scale_array is not None:
            params = self.gather(self.code_scale_array, [(*sel[:3], slice(0, 2)) for sel in sels], locs)
        return coords, self._code_values(coords, codes, params)

    def fetch_stream(self, box: Box, level: int, *, states: np.ndarray | None = None,
                      stage: Callable[[np.ndarray, np.ndarray], Any] | None = None, batch_blocks: int | None = 8192,
                      chunks_per_group: int | None = None, prefetch: int = 2, columns: bool = False
                      ) -> Iterator[tuple[np.ndarray, Any]]:
        """Yield ``(coords, codes)`` per group of chunks (:func:`~sdfcodec.map.grouping.chunk_groups`), ``codes``
        replaced by ``stage(coords, codes)`` in the fetching thread when given; up to ``prefetch`` further groups
        are fetched (and staged) ahead (:func:`~sdfcodec.map.grouping.prefetched`)."""
        for name, v in (("batch_blocks", batch_blocks), ("chunks_per_batch", chunks_per_group)):
            if v is not None and (isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1):
                raise InvalidValueError(f"{name} must be an int >= 1, got {v!r}")
        if states is None:
            states = self.states_in(box)
        groups = self._chunk_groups(box, states, level, batch_blocks=batch_blocks, chunks_per_group=chunks_per_group,
                                    columns=columns)
        b0 = np.array([s.start for s in box], dtype=np.int64)
        b1 = b0 + np.array(states.shape, dtype=np.int64)

        def job(chunks: np.ndarray) -> tuple[np.ndarray, Any]:
            coords, codes = self._fetch_group(chunks, b0, b1, states, level)
            return coords, (stage(coords, codes) if stage is not None else codes)

        yield from prefetched(job, groups, prefetch)

    def decode_stream(self, box: Box, level: int, dev: torch.device, *, metres: bool,
                      out_for: Callable[[int], torch.Tensor] | None = None, placer: BlockPlacer | None = None,
                      **kw) -> Iterator[tuple[np.ndarray, torch.Tensor | None]]:
        """The decode path: ``(coords (n, 3), core decodes (n, 16, 16, 16) on dev)`` per group of chunks, one
        batched decode per group (:meth:`decode_codes`; keywords: see :meth:`fetch_stream`), written into
        ``out_for(n)`` (a contiguous ``(n, 16, 16, 16)`` float32 buffer on ``dev``, e.g. from a
        :class:`~sdfcodec.map.placement.BufferRing`) when given, else into a fresh array; ``placer``: see
        :meth:`decode_codes` (the decodes yielded are None then)."""
        self.codec  # loaded (and its state checked) here, before any thread starts
        feed, mask, res = DeviceFeed(dev), self.observation_arrays()[1], self.residual_rows_array(level)
        refining = self.refinement is not None and level == self.header.codes.size  # spec 6h: full level only
        # variable-rate codes on the CPU: decoded in cache-sized tiles, then masked (rows read beside the codes, or
        # a pinned mask read at full level decoded from the field's own decode, a refinement's corrections added
        # there: pinread), then placed; any other refined read at full level takes the path that adds its
        # corrections (decode_runs)
        fused = (self.vr is not None and res is None and dev.type == "cpu" and hasattr(mask, "unmask") and metres
                 and level == self.header.codes.size)
        after = fused or (self.vr is not None and res is None and dev.type == "cpu" and not refining)

        def stage(coords: np.ndarray, codes: np.ndarray) -> tuple[Any, np.ndarray | None, np.ndarray | None]:
            if self.vr is not None:  # blocks by prefix length, so that runs of like lengths decode their prefix
                order = np.argsort(prefix_lengths(codes), kind="stable")
                coords[:], codes = coords[order], codes[order]
            # a masked map's rows are read here too, in the fetching thread, beside their codes (and residuals,
            # or a refinement's corrections: after the mask, whose pins hand it each chunk's exact decode; the
            # chunk caches of both are this thread's alone)
            rows = None if mask is None or fused else read_block_rows(self, mask, coords)
            extra = (self.refinement.rows(coords) if refining and not fused else None if res is None
                     else self.read_residual(coords))
            return feed.stage(codes), rows, extra

        for coords, (staged, rows, resid) in self.fetch_stream(box, level, stage=stage, **kw):
            codes = feed.ready(staged)
            out = None if out_for is None else out_for(len(codes))
            if after:
                if fused and self.refinement is not None:  # its corrections decoded meanwhile, on threads
                    self.refinement.start(coords)
                v = decode_runs(self, codes, coords, None, out, None, metres, refine=False, unmasked=True)
                if fused:
                    mask.unmask(coords, v.numpy(), self.truncation[1] if metres else 1.0)
                elif mask is not None:
                    v = restore_unobserved(v, rows, self.truncation[1] if metres else 1.0)
                if placer is not None:
                    placer.place(coords, v)
                yield coords, None if placer is not None else v
                continue
            if self.vr is not None:
                yield coords, decode_runs(self, codes, coords, rows, out, placer, metres,
                                          refine=refining, refine_rows=resid)
                continue
            yield coords, self.decode_codes(codes, metres=metres, coords=coords, mask_rows=rows,
                                            residual_rows=resid, out=out, placer=placer)

    def residual_rows_array(self, level: int) -> Any:
        """The ``residual`` array when a decode at ``level`` applies it (a map with a residual stage, read at full
        level: the residual was measured against the full decode; spec 6d), else None."""
        arr = self.live.residual if self.live is not None else self.residual_array
        return arr if arr is not None and level == self.header.codes.size else None

    def read_residual(self, coords: np.ndarray) -> np.ndarray:
        """``(n, 4096)`` stored residual rows of coded blocks ``coords`` ``(n, 3)``; a chunk not stored under them
        is an error naming it (Zarr would read zeros: no correction, the bound silently lost)."""
        arr = self.live.residual if self.live is not None else self.residual_array
        rows = read_block_rows(self, arr, coords)
        if self.live is None:
            check_residual_stored(self, arr, coords, rows)
        return rows

    def decode_codes(self, codes: torch.Tensor, *, metres: bool, coords: np.ndarray | None = None,
                     mask_rows: np.ndarray | None = None, residual: bool = True,
                     residual_rows: np.ndarray | None = None, out: torch.Tensor | None = None,
                     placer: BlockPlacer | None = None, refine: bool = True,
                     refine_rows: np.ndarray | None = None, unmasked: bool = False) -> torch.Tensor | None:
        """Core decodes ``(n, 16, 16, 16)`` of codes ``(n, L)`` on their device, in metres (the scaling folded
        into the codec's decode where it can, :meth:`Codec.decode_core`) or normalised, unobserved voxels of a
        masked map set to free space (``coords`` (n, 3), the blocks, are required there; their packed mask rows
        ``mask_rows`` (n, 512) are read unless given). NaN/Inf or absurd values
        (normalised beyond +-DECODE_LIMIT) out of the codec (corrupted codes or learned state) are refused,
        naming a block of ``coords`` (n, 3) when given: proven impossible by the codec's bound on its outputs
        when it gives one within the limit (no pass over the output), else checked on the output. Full-length
        codes of a map with a residual stage get it added last (spec 6d; ``residual_rows`` (n, 4096), read unless
        given; ``residual=False``: the plain decode, what the writer measures the residual against). ``out``: a
        contiguous ``(n, 16, 16, 16)`` float32 buffer on the codes' device to decode into, or None. ``placer``:
        a :class:`BlockPlacer` the blocks go into (straight, or tile by tile from cache: sdfcodec.map.groupdecode);
        ``out`` is scratch then, and None is returned. ``refine=False``: without a surface refinement's
        corrections (spec 6h; what a decode below full level does); ``refine_rows`` (n, 4096): those corrections
        in metres, read unless given. ``unmasked``: unobserved voxels keep their decode (the caller restores
        them)."""
        return decode_group(self, codes, metres=metres, coords=coords, mask_rows=mask_rows, residual=residual,
                            residual_rows=residual_rows, out=out, placer=placer, refine=refine,
                            refine_rows=refine_rows, unmasked=unmasked)

    def iter_codes(self, *, level: int | None = None, chunks_per_batch: int = 8, prefetch: int = 2
                   ) -> Iterator[tuple[np.ndarray, np.ndarray]]:
        """:meth:`sdfcodec.Map.iter_codes`: ``(coords (n, 3) int64, codes (n, L) float32)`` per batch, as the codec
        encodes them (as :meth:`read_codes`)."""
        lv = self.level(level)
        box = tuple(slice(0, n) for n in self.grid())
        as_codec = None if not is_metric(self.header.codes) else (
            lambda c, z: codec_codes(self.header.codes, self.truncation, z))
        yield from self.fetch_stream(box, lv, chunks_per_group=chunks_per_batch, batch_blocks=None,
                                     prefetch=prefetch, stage=as_codec)

    def iter_decoded(self, region: Region | None = None, *, units: str = "voxels", level: int | None = None,
                     device: str | torch.device | None = None, batch_blocks: int = 8192, prefetch: int = 2,
                     copy: bool = True) -> Iterator[tuple[np.ndarray, Any]]:
        """:meth:`sdfcodec.Map.iter_decoded`: ``(coords (n, 3) int64, blocks (n, 16, 16, 16)
        float32 metres)`` per group of chunks (numpy, or torch on ``device``); ``copy=False``: ``blocks`` are
        views of a ring of :data:`RING` buffers, valid until the ring wraps (kept for the next iteration)."""
        if not isinstance(copy, bool):
            raise InvalidValueError(f"copy must be True or False, got {copy!r}")
        lv = self.level(level)
        box = self.block_range(self.block_box(region, units))
        yield from self.decoded_blocks(box, lv, device, batch_blocks=batch_blocks, prefetch=prefetch, copy=copy)

    def decoded_blocks(self, box: Box, level: int, device: str | torch.device | None, *, copy: bool = True,
                       **kw) -> Iterator[tuple[np.ndarray, Any]]:
        """:meth:`_decoded_metres` on ``device``, as numpy when ``device`` is None (decoded on the CPU); fresh
        arrays, or (``copy=False``) views of a ring of :data:`RING` reused buffers."""
        dev = check_device(device) if device is not None else torch.device("cpu")
        ring = None if copy else self.rings.borrow(dev)  # kept for the reader's next iteration (RingPool)
        try:
            for coords, blocks in self._decoded_metres(box, level, dev, out_for=None if ring is None else ring.take,
                                                        **kw):
                yield coords, blocks if device is not None else blocks.numpy()
        finally:
            if ring is not None:
                self.rings.give_back(ring)

    def _decoded_metres(self, box: Box, level: int, dev: torch.device, *,
                        out_for: Callable[[int], torch.Tensor] | None = None, **kw
                        ) -> Iterator[tuple[np.ndarray, torch.Tensor]]:
        if not self.codec.halo:
            yield from self.decode_stream(box, level, dev, metres=True, out_for=out_for, **kw)
            return
        # a halo codec's blocks need their neighbours' core decodes: chunk by chunk, decode the bounding box of
        # its coded blocks with context (the same pipeline, reading the neighbouring chunks too)
        states = self.states_in(box)
        b0 = np.array([s.start for s in box], dtype=np.int64)
        cb = self.header.codes.chunk_blocks
        for (chunk,) in self._chunk_groups(box, states, level, chunks_per_group=1):
            lo, hi = np.maximum(chunk * cb, b0), np.minimum(chunk * cb + cb, b0 + states.shape)
            sub = states[tuple(slice(int(a), int(b)) for a, b in zip(lo - b0, hi - b0))]
            coords = np.argwhere(sub == BlockState.CODED) + lo
            vlo, vhi = coords.min(axis=0) * BLOCK, (coords.max(axis=0) + 1) * BLOCK
            vol = self.decode_voxels(vlo, vhi, level, dev)
            view = _block_view(vol, [(h - l) // BLOCK for l, h in zip(vlo, vhi)])
            rel = torch.from_numpy(coords - vlo // BLOCK).to(dev)
            blocks = view[rel[:, 0], rel[:, 1], rel[:, 2]]
            yield coords, blocks if out_for is None else out_for(len(blocks)).copy_(blocks)

    def iter_blocks(self, *, level: int | None = None, device: str | torch.device | None = None,
                    chunks_per_batch: int | None = None) -> Iterator[tuple[np.ndarray, Any]]:
        """:meth:`sdfcodec.Map.iter_blocks`: :meth:`iter_decoded` over the whole map."""
        lv = self.level(level)
        box = tuple(slice(0, n) for n in self.grid())
        kw = {} if chunks_per_batch is None else {"chunks_per_group": chunks_per_batch, "batch_blocks": None}
        yield from self.decoded_blocks(box, lv, device, **kw)

    def _to_metres(self, v: torch.Tensor) -> torch.Tensor:
        d_min, d_max = self.truncation
        return v.mul_(d_max - d_min).add_(d_min).clamp_(d_min, d_max)  # truncated, as decode_codes' metres

    def _dense_core(self, lo: np.ndarray, hi: np.ndarray, level: int, dev: torch.device, *, metres: bool,
                    batch_blocks: int = 8192, out: torch.Tensor | None = None) -> torch.Tensor:
        """Core decodes (no halo processing) of voxels ``[lo, hi)``, which may reach outside the grid, in metres
        or normalised: free space (``d_max`` or 1.0) wherever no coded block is. Blocks are decoded a group at a
        time and copied straight into the volume (:class:`BlockPlacer`), from cache tile by tile or from one
        reused buffer: the memory is the volume plus one group's decodes; blocks not coded are filled, the rest
        written once. ``out``: the volume to fill (contiguous, ``hi - lo``), else a fresh one."""
        free = self.truncation[1] if metres else 1.0
        grid_hi = np.asarray(self.grid_blocks) * BLOCK
        clo, chi = np.maximum(lo, 0), np.minimum(hi, grid_hi)
        out = empty(tuple(int(n) for n in hi - lo), dev) if out is None else out
        if np.any(chi <= clo):
            return out.fill_(free)
        if np.any(clo != lo) or np.any(chi != hi):
            out.fill_(free)  # beyond the grid (a halo's context): free space, then the blocks inside
        box = self.block_range(tuple(zip(clo.tolist(), chi.tolist())))
        b0 = np.array([s.start for s in box], dtype=np.int64)
        states = self.states_in(box)
        placer = BlockPlacer(out, lo, clo, chi)
        placer.fill(np.argwhere(states != BlockState.CODED) + b0, free)
        scratch = BufferRing(1, dev)  # a group decoded whole (not in tiles) is decoded here, placed, overwritten
        # placed by the decode itself: tile by tile while in cache (codec.decode_tiles), else once per group
        for _ in self.decode_stream(box, level, dev, metres=metres, states=states, out_for=scratch.take,
                                    placer=placer, batch_blocks=batch_blocks, columns=True):
            pass
        return out

    def decode_voxels(self, lo: np.ndarray, hi: np.ndarray, level: int, dev: torch.device, *,
                      batch_blocks: int = 8192, out: torch.Tensor | None = None) -> torch.Tensor:
        """Final decoded metres of voxels ``[lo, hi)`` inside the grid, neighbour context included; blocks are
        decoded about ``batch_blocks`` at a time, into ``out`` (contiguous, ``hi - lo``) when given."""
        h = self.codec.halo
        if not h:  # metres straight out of the decode
            return self._dense_core(np.asarray(lo), np.asarray(hi), level, dev, metres=True, batch_blocks=batch_blocks,
                                    out=out)
        core = self._dense_core(np.asarray(lo) - h, np.asarray(hi) + h, level, dev, metres=False,
                                batch_blocks=batch_blocks)
        vol = self._to_metres(self.codec.decode_context(core[None])[0])
        vol = restore_unobserved_voxels(self, vol, lo, hi, self.truncation[1])  # the context spread into them
        return vol if out is None else out.copy_(vol)

    def decode_region(self, region: Region | None = None, *, units: str = "voxels", level: int | None = None,
                      device: str | torch.device | None = None, batch_blocks: int = 8192, out: Any = None) -> Any:
        """:meth:`sdfcodec.Map.decode_region`: ``(x1 - x0, y1 - y0, z1 - z0)`` float32 metres (in ``out``)."""
        lv = self.level(level)
        vox = self.block_box(region, units)
        box = self.block_range(vox)
        nbytes = 4 * int(np.prod([(s.stop - s.start) * BLOCK + 2 * 16 for s in box]))
        if nbytes > self.max_decode_bytes:
            raise InvalidValueError(f"decoding {region or 'the whole map'} needs {nbytes / 2**30:.1f} GiB, above the "
                                    f"limit of {self.max_decode_bytes / 2**30:.1f} GiB; decode a smaller region or "
                                    "raise max_decode_bytes in open_map()")
        dev = check_device(device) if device is not None else torch.device("cpu")
        lo, hi = np.array([v[0] for v in vox]), np.array([v[1] for v in vox])
        if out is not None:  # the caller's volume, reused: no allocation, no first-touch page faults
            shape = tuple(int(n) for n in hi - lo)
            dst = output_buffer(out, (shape,), numpy=device is None, device=dev, what=f"{shape} (the region's voxels)")
            self.decode_voxels(lo, hi, lv, dev, batch_blocks=batch_blocks, out=dst)
            return out
        vol = self.decode_voxels(lo, hi, lv, dev, batch_blocks=batch_blocks)  # contiguous, exactly the region: returned as it is
        return vol.contiguous() if device is not None else np.ascontiguousarray(vol.numpy())

    def local_root(self) -> str | None:
        """The directory (or zip) this map reads from: the pinned version for maps opened by path."""
        inner = unguarded(self.group.store)
        if isinstance(inner, zarr.storage.LocalStore):
            return str(inner.root)
        if isinstance(inner, zarr.storage.ZipStore):
            return str(inner.path)
        return None

    def observation_arrays(self) -> tuple[zarr.Array | None, zarr.Array | None]:
        """``(fusion weights, observation mask)`` arrays, None where the map has none: the checked ones, or, for
        a map being written, the writer's as they are now (it creates them on the first write that needs them)."""
        if self.live is None:
            return self.weights_array, self.mask_array
        return self.group.get("weights"), self.live.mask

    @property
    def has_weights(self) -> bool:
        """True when the map stores fusion weights."""
        return self.observation_arrays()[0] is not None

    def read_weights(self, coords: Any) -> np.ndarray:
        """:meth:`sdfcodec.Map.read_weights`: ``(N, 16, 16, 16)`` float32 fusion weights of blocks ``coords``."""
        if not self.has_weights:
            raise FormatError(f"{self.location} stores no fusion weights (write them with write_blocks(weights=...),"
                              " e.g. `sdfcodec fuse --keep-weights`)")
        c = check_coords(coords, grid=self.grid_blocks)
        return read_block_rows(self, self.observation_arrays()[0], c).astype(np.float32).reshape(len(c), BLOCK, BLOCK, BLOCK)

    def close(self) -> None:
        """Further reads raise; a reader that owns a pinned local store lets go of the version it holds."""
        self._closed = True
        self.rings.clear()
        inner = unguarded(self.group.store)
        if self._owns_store and isinstance(inner, PinnedStore):
            inner.close_pin()
        elif self._owns_store and isinstance(inner, RemoteStore):
            inner.close()  # its HTTP or S3 session


def _block_view(vol: torch.Tensor, nb) -> torch.Tensor:
    """``(16 bx, 16 by, 16 bz)`` -> a ``(bx, by, bz, 16, 16, 16)`` view of the same memory."""
    return vol.view(nb[0], BLOCK, nb[1], BLOCK, nb[2], BLOCK).permute(0, 2, 4, 1, 3, 5)
