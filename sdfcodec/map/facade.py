"""The map as users see it: :class:`Map` (read and write one map), :func:`open_map`, :func:`create_map` and
:func:`update_map`. ``Map`` holds a :class:`~sdfcodec.map.reader.MapReader` (``Map.reader``) and, while
being written, a :class:`~sdfcodec.map.writer.MapWriter` (``Map.writer``), and delegates to them.

The format, crash safety and the limits on untrusted maps: ``sdfcodec.map`` and spec/map-format.md.
"""

from __future__ import annotations

import math
import os
from typing import Any, Callable, Iterator, Sequence

import numpy as np
import zarr
import zarr.abc.store

from ..core._lazy import lazy_module
from ..core._validate import BLOCK
from ..codec import Codec
from ..errors import InvalidValueError, ReadOnlyError
from ..core.header import APPROX_MASK_EXTENSION, Extension, MapHeader
from .format import DEFAULT_MAX_DECODE_BYTES, Region, check_coords, check_volume, is_dask_array
from .observed import SURFACE_WEIGHT, pack_mask, read_observed
from .opening import open_reader
from .reader import CodecCache, MapReader
from .io.stores import PinnedStore
from .summary import summarize
from .varrate import VariableRateWriter
from .writer import LOCK_TIMEOUT, MapWriter, create_writer, update_writer

torch = lazy_module("torch")  # imported on first use: info, codecs, verify of a header never need it

__all__ = ["Map", "open_map", "create_map", "update_map"]


class Map:
    """An open sdfcodec map. Get one from :func:`open_map` (read) or :func:`create_map` (write).

    Geometry: voxel ``(i, j, k)`` lies at world position ``origin + voxel_size * (i, j, k)``; block
    ``(bx, by, bz)`` covers voxels ``[16 bx, 16 bx + 16)`` on each axis. Decoded values are metres.

    ``reader`` (:class:`~sdfcodec.map.reader.MapReader`) reads and decodes; ``writer`` is the
    :class:`~sdfcodec.map.writer.MapWriter` of a map being written (ReadOnlyError otherwise).
    """

    def __init__(self, group: zarr.Group, header: MapHeader, location: str, *,
                 max_decode_bytes: int = DEFAULT_MAX_DECODE_BYTES):
        self.reader = MapReader(group, header, location, max_decode_bytes=max_decode_bytes)
        self._writer: MapWriter | None = None
        self._close_on_exit = False

    @classmethod
    def _of(cls, reader: MapReader, writer: MapWriter | None = None) -> "Map":
        m = cls.__new__(cls)
        m.reader, m._writer, m._close_on_exit = reader, writer, False
        return m

    # -- what the map is ------------------------------------------------------------------------------
    @property
    def header(self) -> MapHeader:
        return self.reader.header

    @property
    def location(self) -> str:
        return self.reader.location

    @property
    def max_decode_bytes(self) -> int:
        return self.reader.max_decode_bytes

    @property
    def voxel_size(self) -> float:
        return self.header.voxel_size

    @property
    def truncation(self) -> tuple[float, float]:
        return self.reader.truncation

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

    @property
    def writer(self) -> MapWriter:
        """The writer of a map being written (from :func:`create_map` or :func:`update_map`)."""
        if self._writer is None:
            raise ReadOnlyError(f"{self.location} is open read-only; write with sdfcodec.create_map(...)")
        return self._writer

    @property
    def codec(self) -> Codec:
        """The codec that wrote the map, with its learned state (loaded on first use).

        Raises:
            UnknownCodecError: its plugin is not installed (names the id and the package to install).
        """
        return self.reader.codec

    def with_store(self, wrap: Callable[[zarr.abc.store.Store], zarr.abc.store.Store]) -> "Map":
        """The same map re-opened read-only over ``wrap(store)`` (``store``: the one this map reads through),
        e.g. a store that counts the keys read. It shares the header, the limits and the codec cache (a codec
        loaded through either map is then loaded for both); closing it leaves this map open. A map being
        written raises InvalidValueError (commit it first)."""
        return Map._of(self.reader.with_store(wrap))

    # -- reading --------------------------------------------------------------------------------------
    def block_states(self) -> np.ndarray:
        """``(Bx, By, Bz)`` uint8 block states (see :class:`sdfcodec.core.header.BlockState`)."""
        return self.reader.block_states()

    def count_states(self) -> dict[str, int]:
        return self.reader.count_states()

    def read_codes(self, region: Region | None = None, *, units: str = "voxels", level: int | None = None
                   ) -> tuple[np.ndarray, np.ndarray]:
        """Codes of the coded blocks touching ``region``.

        Returns:
            ``coords`` ``(N, 3)`` int64 block indices and ``codes`` ``(N, L)`` float32, ``L = level or D``.
            Only the chunks holding the first ``L`` code elements are read.
        """
        return self.reader.read_codes(region, units=units, level=level)

    def iter_codes(self, *, level: int | None = None, chunks_per_batch: int = 8, prefetch: int = 2
                   ) -> Iterator[tuple[np.ndarray, np.ndarray]]:
        """Yield ``(coords (n, 3) int64, codes (n, L) float32)`` for every coded block, ``chunks_per_batch``
        chunks of the block grid at a time (bounded memory), in grid order; only the chunks holding the first
        ``L = level or D`` elements are read, and the next ``prefetch`` batches are read ahead concurrently."""
        return self.reader.iter_codes(level=level, chunks_per_batch=chunks_per_batch, prefetch=prefetch)

    def iter_decoded(self, region: Region | None = None, *, units: str = "voxels", level: int | None = None,
                     device: str | torch.device | None = None, batch_blocks: int = 8192, prefetch: int = 2,
                     copy: bool = True) -> Iterator[tuple[np.ndarray, Any]]:
        """Decode on read: yield ``(coords (n, 3) int64, blocks (n, 16, 16, 16) float32 metres)`` for every coded
        block touching ``region`` (default: the whole map), a group of chunks at a time, in grid order.

        This is the pipeline every decoding reader uses (:meth:`iter_blocks`, :meth:`decode_region`,
        :meth:`to_dask`): the chunks holding coded blocks are grouped (consecutive chunks until they hold about
        ``batch_blocks`` blocks, capped by ``max_decode_bytes``); while the calling thread decodes one group
        in a single batched call, ``prefetch`` worker threads fetch the next groups (each group's chunks
        concurrently, through Zarr's async I/O), decompress them and, when
        ``device`` is CUDA, copy their codes into pinned host memory and start the host-to-device copy on a
        side stream (non-blocking), so transfers overlap decoding. Empty and unobserved blocks are not
        yielded (they decode to ``d_max``).

        Args:
            region: ``((x0, x1), (y0, y1), (z0, z1))`` half-open voxels, or half-open metres with ``units="m"``;
                every coded block with a voxel in it is yielded, whole.
            level: decode only the first ``level`` code elements (prefix-ordered codecs).
            device: ``None``: decode on the CPU and yield numpy arrays; otherwise yield torch tensors on it.
            batch_blocks: about how many blocks one decode call gets. prefetch: groups read ahead (0: none).
            copy: True (the default): every yielded ``blocks`` is a fresh array the caller owns. False: the
                blocks are decoded into a ring of two reused buffers (no allocation, no page faults: the fast
                path, see ``sdfcodec bench``'s ``decode-on-read-into``), so a yielded array is valid only until the
                ring wraps: it is overwritten two iterations later, by the decode of the group after next. The
                map keeps the ring for its next ``copy=False`` iteration (its buffers already in memory), which
                overwrites the last blocks of the one before; it holds ``2 x 16 KiB x batch_blocks`` (256 MiB at
                the default) until the map is closed. Copy what you keep, or use the default. The default is the
                safe one because ``list(m.iter_decoded())``, ``zip(*...)`` and any caller keeping batches would
                otherwise silently see later groups' values.

        Values are metres, exactly as :meth:`iter_blocks` and :meth:`decode_region` give them; codecs with a
        decode halo see their neighbours (decoded chunk by chunk, each with its neighbourhood).
        """
        return self.reader.iter_decoded(region, units=units, level=level, device=device, batch_blocks=batch_blocks,
                                        prefetch=prefetch, copy=copy)

    def iter_blocks(self, *, level: int | None = None, device: str | torch.device | None = None,
                    chunks_per_batch: int | None = None) -> Iterator[tuple[np.ndarray, Any]]:
        """Yield ``(coords (n, 3) int64, blocks (n, 16, 16, 16) metres)`` for every coded block, a group of
        chunks at a time (bounded memory): :meth:`iter_decoded` over the whole map. ``blocks`` is numpy, or a
        tensor on ``device``. ``chunks_per_batch``: fixed number of chunks per group (default: about 8192
        blocks per group). Codecs with a decode halo get their neighbours' context, as in :meth:`decode_region`."""
        return self.reader.iter_blocks(level=level, device=device, chunks_per_batch=chunks_per_batch)

    def to_dask(self, level: int | None = None):
        """A lazy dask array of the decoded map: shape :attr:`shape_voxels`, float32 metres (``d_max`` where no
        block is coded), one dask chunk per chunk of the code array (``16 * chunk_blocks`` voxels per axis),
        each decoded on demand by :meth:`decode_region`. It pickles (a worker process reopens the map by its
        path or URL), so it computes on a ``dask.distributed`` cluster. See :func:`sdfcodec.map.scale.map_to_dask`."""
        from .scale import map_to_dask  # dask is imported only by those who use it

        return map_to_dask(self, level=level)

    def decode_region(self, region: Region | None = None, *, units: str = "voxels", level: int | None = None,
                      device: str | torch.device | None = None, batch_blocks: int = 8192, out: Any = None) -> Any:
        """Decode a region to a dense TSDF in metres.

        Args:
            region: ``((x0, x1), (y0, y1), (z0, z1))`` half-open, in voxels (default: the whole map) or, with
                ``units="m"``, half-open bounds in metres (the voxels whose centres lie in [lo, hi)); or step-1
                slices, ``np.s_[x0:x1, y0:y1, z0:z1]``, an open end being the map's edge.
            level: decode only the first ``level`` code elements (prefix-ordered codecs only).
            device: where to decode. ``None``: on the CPU, returning numpy. Otherwise a torch tensor on it.
            batch_blocks: about how many blocks one decode call gets (the size of the reused decode buffer).
            out: a volume to decode into, e.g. the previous call's, reused: a writeable C-contiguous float32 numpy
                array (``device=None``) or a contiguous float32 tensor on ``device``, of exactly the region's
                shape. Every voxel is written. A fresh volume costs its page faults on first touch: reuse one
                for repeated decodes of a region.

        Returns:
            ``(x1 - x0, y1 - y0, z1 - z0)`` float32 metres (``out`` itself when given); voxels of no coded block
            hold ``d_max``. Codecs with a decode halo (e.g. ``gaussian-blur``) see their neighbour blocks, so
            there are no seams.

        Blocks are decoded a group of chunk columns at a time, in cache-sized tiles where the codec offers them
        (else into one reused buffer), and copied from there straight into the volume, one copy per run of
        blocks along z (no per-block Python): peak memory is the output plus one group's decodes (at most
        ``2 x 16 KiB x batch_blocks``), not a second volume.

        The values are reproducible to float32 rounding, not to the bit, across regions and map versions: a block
        decoded in another batch may differ in its last bit, because a BLAS product rounds a row by its place in
        the batch (OpenBLAS on AMD EPYC: one ulp in 0.3 % of the voxels). The same call on the same map and
        machine gives the same volume.
        """
        return self.reader.decode_region(region, units=units, level=level, device=device, batch_blocks=batch_blocks,
                                         out=out)

    def info(self) -> dict[str, Any]:
        """Summary: header, blocks by state, bytes on disk (local maps), ratio to dense float32."""
        return summarize(self.header, self.location, self.reader.local_root(), self.count_states())

    @property
    def has_weights(self) -> bool:
        """True when the map stores fusion weights."""
        return self.reader.has_weights

    def read_weights(self, coords: Any) -> np.ndarray:
        """Fusion weights ``(N, 16, 16, 16)`` float32 of blocks ``coords`` (0 where none were written)."""
        return self.reader.read_weights(coords)

    @property
    def records_observation(self) -> bool:
        """True when the map knows which voxels were observed (it stores fusion weights or a mask)."""
        return any(a is not None for a in self.reader.observation_arrays())

    def read_observed(self, coords: Any) -> np.ndarray:
        """Which voxels of blocks ``coords`` ``(N, 3)`` were observed: ``(N, 16, 16, 16)`` bool, from the fusion
        weights (> 0) or the observation mask the map stores; all True for a map that stores neither."""
        return read_observed(self.reader, check_coords(coords, grid=self.grid_blocks))

    def close(self) -> None:
        """Release the map: a read-only map lets go of the version it holds (a replaced version is removed once
        its last reader closes it), and further reads raise. Dropping the object does the same. A map being
        written must be committed or aborted first."""
        if self._writer is not None:
            raise InvalidValueError(f"{self.location} is being written: commit() or abort() it before close()")
        self.reader.close()

    # -- writing (maps from create_map / update_map) --------------------------------------------------
    def write_volume(self, volume: Any, *, offset: Sequence[int] = (0, 0, 0), batch_size: int = 16384,
                     progress: Callable[[int], None] | None = None) -> None:
        """Encode a dense TSDF ``(X, Y, Z)`` in metres, placed at voxel ``offset`` (multiples of 16).

        The map's extent grows to hold it (``shape_voxels`` records the true extent; its last blocks are padded
        by repeating the volume's last voxel layer, so no surface appears where it ends). Values outside the
        truncation are clipped with a warning; NaN/Inf are refused.

        A dask array (e.g. ``dask.array.from_zarr`` of a volume larger than memory) is encoded chunk by chunk by
        dask's scheduler, or a ``dask.distributed`` cluster if a client is active, each task writing its chunks
        of codes into this map's temporary directory (:func:`sdfcodec.map.scale.write_volume_dask`).
        """
        w = self.writer
        if is_dask_array(volume):
            from .scale import write_volume_dask

            if self.header.residual is not None:
                raise InvalidValueError(f"{self.location} has a residual stage (--max-error/--sign-exact), which the "
                                        "dask encoder does not write: pass a numpy volume (or write_blocks by region)")
            return write_volume_dask(self, volume, offset=offset)
        # checked here, not in the writer: the clipping warning then names the caller's line
        w.write_volume(check_volume(volume, self.truncation), offset=offset, batch_size=batch_size,
                       progress=progress)

    def write_blocks(self, coords: Any, blocks: Any, *, weights: Any = None, observed: Any = None,
                     batch_size: int = 16384, progress: Callable[[int], None] | None = None) -> None:
        """Encode blocks ``(N, 16, 16, 16)`` in metres at block indices ``coords`` ``(N, 3)`` (non-negative).

        ``weights`` ``(N, 16, 16, 16)``, optional: per-voxel fusion weights (observation counts), stored
        losslessly up to 2048 as float16 in the optional ``weights`` array (extension "fusion-weights").
        ``observed`` ``(N, 16, 16, 16)`` bool, optional: which voxels were observed, when there are no weights
        to store (weights imply ``weights > 0``). Either way the map stores the observation mask (extension
        "observation-mask"), the codec ignores unobserved voxels, and they decode to ``d_max``
        (:mod:`sdfcodec.map.observed`).
        """
        w = self.writer
        c = check_coords(coords)
        b = check_volume(blocks, self.truncation, shape=(len(c), BLOCK, BLOCK, BLOCK), name="blocks")
        w.write_blocks(c, b, weights=weights, observed=observed, batch_size=batch_size, progress=progress)

    def write_map(self, source: "Map", *, progress: Callable[[int], None] | None = None,
                  keep_weights: bool = False) -> None:
        """Transcode every block of the map ``source`` (same voxel size and truncation) into this one: its empty
        blocks stay empty, its coded blocks are decoded (clipped to the truncation: a lossy decode overshoots a
        little) and encoded here with their observation (fusion weights or mask), ``progress(n)`` per batch.
        When this map has the source's very codec (class, configuration and state) and float codes of the same
        type, the codes are copied, not re-encoded: lossless, e.g. to store a state by reference or embed it.
        ``keep_weights``: carry the source's fusion weights too (stored as this map's ``keep_weights`` says: a
        map created with the default stores them only when its codec is lossless; create it with
        ``keep_weights=True`` to keep them quantised in a lossy map)."""
        if (source.voxel_size, source.truncation) != (self.voxel_size, self.truncation):
            raise InvalidValueError(f"cannot transcode {source.location} (voxel size {source.voxel_size} m, truncation "
                                    f"{source.truncation}) into a map with {self.voxel_size} m, {self.truncation}: "
                                    "create the new map with the source's voxel size and truncation")
        if source.header.up is not None and self.writer.header_kw.get("up") is None:
            self.writer.header_kw["up"] = source.header.up  # the gravity direction travels with the map
        empty = np.argwhere(source.block_states() == 1)
        self.mark_empty(empty)
        # a source that records no observation (a dense exact SDF) is observed everywhere: encoded plainly
        knows = source.records_observation
        if knows and APPROX_MASK_EXTENSION in {e.name for e in source.header.extensions}:
            # its mask, exact only near its own decode's surface, is all this map learns of the observation
            self.writer.carried.append(Extension(name=APPROX_MASK_EXTENSION, required=False))
        carry = keep_weights and source.has_weights
        if carry:  # empty blocks were observed too (free space): their weights travel with the coded ones'
            self.writer.write_weights(empty, source.read_weights(empty))
        dtype = self.header.codes.dtype
        if (dtype != "int8" and dtype == source.header.codes.dtype and source.codec == self.codec
                and self.header.codes.units is None and source.header.codes.units is None  # metric: via blocks
                and self.header.residual is None and self.writer.vr is None):  # a residual needs the voxels: they are decoded and encoded
            for coords, codes in source.iter_codes():  # int8 is left out: quantising again may move a code
                self.writer.write_codes(coords, codes, pack_mask(source.read_observed(coords)) if knows else None)
                if carry:
                    self.writer.write_weights(coords, source.read_weights(coords))
                if progress is not None:
                    progress(len(coords))
            return
        for coords, blocks in source.iter_blocks():
            self.write_blocks(coords, np.clip(blocks, *self.truncation),
                              observed=source.read_observed(coords) if knows else None,
                              weights=source.read_weights(coords) if carry else None)
            if progress is not None:
                progress(len(coords))

    def write_codes(self, coords: Any, codes: Any) -> None:
        """Store already-encoded codes ``(N, D)`` (from this map's codec) at block indices ``coords``."""
        self.writer.write_codes(coords, codes)

    def mark_empty(self, coords: Any) -> None:
        """Record blocks as observed free space (no code stored)."""
        self.writer.mark_empty(coords)

    def commit(self) -> None:
        """Finish writing and move the map into place atomically; the object then reads the committed map."""
        writer = self.writer
        final = writer.commit(keep=True)
        self._writer = None
        # the version this writer committed, held since the swap: not whatever is at the path by now (another
        # writer may have replaced it), so that info() and the commands' reports describe what was written
        fd, writer.committed_fd = writer.committed_fd, None
        src = final if fd is None else PinnedStore.hold(final, fd)
        self.reader = open_reader(src, max_decode_bytes=self.max_decode_bytes, cache=self.reader.cache,
                                  location=str(final))

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


def _writing(w: MapWriter) -> Map:
    """The facade of a map being written: its reader reads the writer's arrays and block states."""
    reader = MapReader(w.group, w.header, w.location, max_decode_bytes=w.max_state_bytes, cache=CodecCache(w.codec),
                       live=w)
    return Map._of(reader, w)


def create_map(path: str | os.PathLike, *, codec: Codec, voxel_size: float,
               truncation: tuple[float, float] = (-0.04, 0.1), origin: Sequence[float] = (0.0, 0.0, 0.0),
               shape_voxels: Sequence[int] = (0, 0, 0), code_dtype: str = "float32",
               chunk_blocks: int | None = None, chunk_code: int | None = None, overwrite: bool = False,
               device: str | torch.device = "cpu", tool: str | None = None, source: str | None = None,
               surface_weight: float = SURFACE_WEIGHT, up: Sequence[float] | None = None,
               codec_state: str = "embedded", code_step: Any = None, code_offset: Any = None,
               max_error: float | None = None, sign_exact: bool = False, shard_blocks: int | None = None,
               manifest: bool = True, variable_rate: dict | None = None,
               keep_weights: bool | None = None, exact: bool = False) -> Map:
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
            sdfcodec 0.2 refuse such maps by the extension they require), or ``"int16"``: codes quantised with
            one step per map (``code_step``: one number, or one per code element; ``code_offset``: optional,
            default 0) and entropy-coded, ``|error| <= step / 2`` per element (spec section 4b; codecs with
            orthonormal codes only, :data:`sdfcodec.core.quantize.UNIFORM_STEP_CODECS`).
        chunk_blocks, chunk_code: chunk shape (blocks per axis, code elements); sensible defaults.
        shard_blocks: store the chunks of codes in Zarr shards of this many blocks per axis (a multiple of
            ``chunk_blocks`` that divides 64, e.g. 32 or 64): objects of megabytes instead of one file per chunk,
            for maps of millions of blocks on object storage (extension ``sharded-codes``, spec section 4d; readers
            before it refuse such maps). Reads still fetch only the chunks they need (byte ranges).
        overwrite: replace an existing map at ``path`` (atomically, on commit).
        device: where encoding runs.
        surface_weight: extra error weight of voxels near the surface when encoding (the codec fits
            ``1 + surface_weight`` there, 1 elsewhere, 0 on unobserved voxels; :mod:`sdfcodec.map.observed`);
            0 encodes every observed voxel alike.
        up: the world's up direction (opposite gravity) in the grid's axes, when known: recorded in the header
            (optional field ``up``, spec section 3) for descriptor search; normalised here.
        codec_state: ``"embedded"`` (default: the learned state is stored in the map, which is then
            self-contained) or ``"reference"``: only the name and digest of the shipped model the codec holds
            (``pretrained_codec``) are stored, for collections of maps that share one codec; readers need that
            model in the installed plugin (spec section 6c; raises InvalidValueError for a codec that holds no
            shipped model's state; a codec without learned state stores nothing either way).
        max_error: metres; every observed voxel of a coded block decodes within it at full level, through a
            residual stage on top of the codes (extension ``residual-bound``, spec section 6d; docs/error-bounds.md).
        sign_exact: every observed voxel touching a surface crossing of the input decodes with its sign (the
            same residual stage); with ``max_error`` both hold.
        manifest: write the integrity manifest (default; extension ``integrity-manifest``, spec section 9b):
            readers check every object against it, and the map can be signed. False writes a map that readers
            before the extension open, unchecked (updates keep a map's choice).
        variable_rate: variable-rate codes (extension ``variable-rate-codes``, spec section 4e;
            docs/variable-rate.md): per block a prefix of its code chosen by rate-distortion, entropy-coded on
            commit; a dict with one of ``step`` (normalised code units), ``target_bytes`` (stored bytes per coded
            block, every file counted) or ``target_error`` (metres: the error of 99 % of the voxels that place the
            surface, docs/variable-rate.md), and optionally ``lagrange`` and
            ``exact_mask`` (True keeps the observation mask exact; by default it is exact only where it decides
            the decoded surface, extension ``approximate-observation-mask``, spec section 6f) and ``pinned_mask``
            (False codes that mask at every voxel; by default only the voxels that decide the surface are stored,
            extension ``pinned-observation-mask``, section 6g), ``refine_step`` (metres: corrections of that step
            at the voxels next to the decoded surface, extension ``surface-refinement``, section 6h; a
            ``target_bytes`` of 160 B or more shares its bytes with them, and a ``target_error`` takes them where
            they make the map smaller, unless ``refine`` is False).
            Prefix-ordered codecs (pca) only; such a map is not updated in place.
        keep_weights: what becomes of the fusion weights given to ``write_blocks(weights=...)``: None (default)
            keeps them (float16) for the lossless ``raw`` codec and drops them at commit for lossy codecs (the
            observation mask keeps which voxels were observed); True keeps them, quantised to uint8 counts for
            lossy codecs (extension ``quantised-fusion-weights``, spec section 6a); False drops them
            (:mod:`sdfcodec.map.weights`).
        exact: store the voxels' own float32 metres (extension ``metric-codes``, spec section 4f; raw codec,
            float32 codes only): every voxel written reads back bit for bit, and the weights are kept as float32
            (extension ``float32-fusion-weights``); without it a raw map returns its input to float32 rounding
            of the normalisation, ``(d_max - d_min) x 2^-24`` m. Readers before the extension refuse such maps.
    """
    up_unit = None
    if up is not None:
        u = np.asarray(up, dtype=np.float64).reshape(-1)
        if u.shape != (3,) or not np.all(np.isfinite(u)) or np.linalg.norm(u) < 1e-9:
            raise InvalidValueError(f"up must be three finite numbers of non-zero length, got {up!r}")
        up_unit = tuple(float(x) for x in u / np.linalg.norm(u))
    if isinstance(surface_weight, bool) or not isinstance(surface_weight, (int, float)) or not (
            math.isfinite(surface_weight) and surface_weight >= 0):
        raise InvalidValueError(f"surface_weight must be a finite number >= 0, got {surface_weight!r}")
    if variable_rate is not None and (not isinstance(variable_rate, dict) or not set(variable_rate) <= {
            "step", "target_bytes", "target_error", "lagrange", "exact_mask", "pinned_mask", "refine",
            "refine_step"}):
        raise InvalidValueError(f"variable_rate must be a dict with one of step, target_bytes, target_error (and "
                                f"optionally lagrange, exact_mask, pinned_mask, refine, refine_step), got "
                                f"{variable_rate!r}")
    writer = create_writer(path, codec=codec, voxel_size=voxel_size, truncation=truncation, origin=origin,
                                  shape_voxels=shape_voxels, code_dtype=code_dtype, chunk_blocks=chunk_blocks,
                                  chunk_code=chunk_code, overwrite=overwrite, device=device, tool=tool,
                                  source=source, codec_state=codec_state, code_step=code_step,
                                  code_offset=code_offset, max_error=max_error, sign_exact=sign_exact,
                                  shard_blocks=shard_blocks, manifest=manifest, keep_weights=keep_weights, exact=exact,
                                  variable_rate=None if variable_rate is None else VariableRateWriter(
                                      codec, **variable_rate))
    writer.surface_weight = float(surface_weight)
    if up_unit is not None:
        writer.header_kw["up"] = up_unit
    return _writing(writer)


def update_map(path: str | os.PathLike, *, device: str | torch.device = "cpu", tool: str | None = None,
               wait: float = LOCK_TIMEOUT, max_decode_bytes: int = DEFAULT_MAX_DECODE_BYTES) -> Map:
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
    return _writing(update_writer(path, device=device, tool=tool, wait=wait, max_decode_bytes=max_decode_bytes))


def open_map(path_or_url: str | os.PathLike | zarr.abc.store.Store, *, storage_options: dict | None = None,
             max_decode_bytes: int = DEFAULT_MAX_DECODE_BYTES, follow_symlinks: bool = False,
             trusted_keys: Sequence[Any] | None = None, verify_chunks: bool | None = None) -> Map:
    """Open a map read-only: a local directory, a ``.zip``, a URL (``http(s)://``, ``s3://``, ``file://``...
    through fsspec) or any Zarr store. Reads only the header and array metadata; data is read on demand.

    A local directory map is held at the version opened (Linux): a writer replacing it meanwhile changes
    nothing this object reads; open the path again to see the new version. ``close()`` (or dropping the object,
    or leaving a ``with`` block) lets the old version go.

    ``max_decode_bytes`` bounds what one call may allocate (a decoded region, a dense read of codes, the
    block states, one chunk, the codec state): maps whose header or array metadata name more are refused with
    FormatError before anything is read. Opening never runs code from the map. A local map's files must be
    regular files inside it: symbolic links are refused unless ``follow_symlinks`` (spec section 9a).

    A map with an integrity manifest (spec section 9b) has every object it reads checked against it: a chunk
    moved, changed or from another map is an IntegrityError naming the array and key (``verify_chunks=False``
    skips that, for benchmarks only). ``trusted_keys`` (Ed25519 public keys: PEM or raw files, key objects;
    :mod:`sdfcodec.map.signing`): the map must be signed by one of them, as it is (SignatureError otherwise).
    Both default to the process's (the commands' ``--trusted-key`` and ``--no-verify-chunks``).
    """
    return Map._of(open_reader(path_or_url, storage_options=storage_options, max_decode_bytes=max_decode_bytes,
                               follow_symlinks=follow_symlinks, trusted_keys=trusted_keys,
                               verify_chunks=verify_chunks))
