"""The map writer: :class:`MapWriter` holds a map being written in its hidden temporary directory (a new map
from :func:`create_writer`, or a copy of the current version from :func:`update_writer`), encodes volumes and
blocks into it, and commits it into place atomically (or aborts, leaving the previous map untouched;
``sdfcodec.core._atomic``, spec section 9). :class:`sdfcodec.Map` is the facade users write through; the dask
encoder (``sdfcodec.map.scale``) writes chunks into :attr:`MapWriter.tmp` with :func:`store_code_chunk`."""

from __future__ import annotations

import contextlib
import json
import math
import os
import re
from importlib import metadata
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np
import zarr

from ..core._lazy import lazy_module
from .. import __version__
from ..core import _atomic
from ..core._validate import BLOCK, as_float_tensor, check_device, check_weights
from ..core.blocks import check_truncation, normalise, split_blocks
from ..codec import Codec
from ..errors import (FormatError, InvalidValueError, MapExistsError, MapNotFoundError, NotFittedError,
                      SDFCodecError, ShapeError, VersionError, WriteFailedError)
from ..core.header import (FIELD_EXTENSION, INT8_EXTENSION, KNOWN_EXTENSIONS, MANIFEST_EXTENSION, METRIC_EXTENSION,
                           QUANT_EXTENSION, RESIDUAL_EXTENSION, SHARD_EXTENSION, STATE_NAME_PATTERN,
                           STATE_REFERENCE_EXTENSION, VARIABLE_RATE_EXTENSION, public_source,
                           BlockState, CodecSpec, CodeQuantisation, CodesSpec, Extension, MapHeader, Provenance, Truncation,
                           VariableRate, now_iso)
from ..core.quantize import check_quantisable, check_step, quantise_step, quantize_codes
from ..registry import codec_package
from .codec_state import shipped_reference, state_digest
from .field import compress_codes, refuse_update
from .implied import IMPLIED, inline_states
from .format import (CODE_DTYPES, DEFAULT_MAX_DECODE_BYTES, check_codes, check_coords, code_compressors,
                     code_layout, compact_documents, compressors, free_space, mask_compressors, root_document)
from .observed import (MASK_ARRAY, MASK_BYTES, SURFACE_WEIGHT, encode_blocks, finish_mask, pack_mask, store_mask_chunk,
                       write_block_rows)
from .opening import open_reader
from .reader import CodecCache, MapReader
from .residual import (RESIDUAL_ARRAY, crossing_voxels, residual_compressors, residual_rows, residual_spec,
                       stored_code_values)
from .manifest import manifest_bytes_estimate, manifest_placeholder, previous_digests, write_manifest
from .metric import check_metric, is_metric, metric_empty, metric_spec
from .io.shards import pack_shards, sharded_spec, unpack_shards
from .io.stores import MAX_METADATA_BYTES, CowLocalStore, is_url
from .varrate import GAIN_ARRAY, STREAM_ARRAY, STREAM_METADATA_BYTES, VariableRateWriter, stream_chunk_keys
from .weights import WEIGHTS_ARRAY, finish_weights, stored_weights, weights_mode

torch = lazy_module("torch")  # imported on first use: info, codecs, verify of a header never need it

__all__ = ["MapWriter", "create_writer", "update_writer", "check_replaceable", "store_code_chunk", "LOCK_TIMEOUT"]

#: How long a writer waits for another process's update of the same map to finish before giving up.
LOCK_TIMEOUT = 60.0

#: Blocks whose residual is computed at once: 1024 blocks' float64 work arrays take 32 MiB each.
_RESIDUAL_SLAB = 1024
_UNCHANGED = "the previous map there is unchanged and no temporary files are left"
_NOTHING = "nothing was written there and no temporary files are left"


@contextlib.contextmanager
def _write_errors(final: Path, doing: str, outcome: str, cleanup: Callable[[], None] | None = None):
    """Turn an ``OSError`` from the file system (disk full, permission, I/O error...) into a
    :class:`WriteFailedError` naming ``final``, after ``cleanup()`` (which removes the temporary copy: the
    message promises ``outcome``). sdfcodec's own errors pass through unchanged (MapBusyError and
    MapExistsError are OSErrors too)."""
    try:
        yield
    except SDFCodecError:
        raise
    except OSError as e:
        if cleanup is not None:
            cleanup()
        raise WriteFailedError.from_os_error(e, final, doing, outcome) from e


def _final_of(tmp: str | os.PathLike) -> Path:
    """The map path a writer's temporary directory ``.NAME.tmp-<hex>`` stands for."""
    p = Path(tmp)
    m = re.fullmatch(r"\.(.+)\.tmp-[0-9a-f]+", p.name)
    return p.with_name(m.group(1)) if m else p


def store_code_chunk(codes_arr: zarr.Array, scale_arr: zarr.Array | None, box: tuple[slice, ...],
                     local: np.ndarray, codes: np.ndarray, had: bool, quant: CodeQuantisation | None = None) -> None:
    """Write float32 ``codes`` ``(n, D)`` of the blocks at ``local`` (indices inside the chunk ``box`` of the block
    axes) into that chunk of ``codes_arr``, quantised to int8 with their ``[offset, scale]`` rows in ``scale_arr``
    when the map stores int8 codes, to int16 with the map's step and offset ``quant`` for int16 codes: one write
    per array (each chunk read first only when it already ``had`` codes). The single-process writer and the dask
    encoder both write through here.

    Raises:
        WriteFailedError: the file system refused the write (the dask encoder's tasks raise it; the writer
            that owns the temporary directory removes it when aborted)."""
    root = getattr(codes_arr.store, "root", None)
    final = _final_of(root) if root is not None else Path(str(codes_arr.store))
    with _write_errors(final, "writing the map", "nothing at that path changes; the write is aborted and its "
                       "temporary copy removed"):
        _store_code_chunk(codes_arr, scale_arr, box, local, codes, had, quant)


def _store_code_chunk(codes_arr: zarr.Array, scale_arr: zarr.Array | None, box: tuple[slice, ...],
                      local: np.ndarray, codes: np.ndarray, had: bool, quant: CodeQuantisation | None = None) -> None:
    # readers refuse a coded block whose chunk is missing (spec 9a), so a chunk equal to the fill value (raw
    # codes of solid blocks are all 0) must be stored too: Zarr skips writing those by default
    codes_arr = codes_arr.with_config({"write_empty_chunks": True})
    scale_arr = None if scale_arr is None else scale_arr.with_config({"write_empty_chunks": True})
    shape = [s.stop - s.start for s in box]
    idx = tuple(local.T)
    buf = np.asarray(codes_arr[box]) if had else np.zeros((*shape, codes_arr.shape[3]), dtype=codes_arr.dtype)
    if quant is not None:
        buf[idx] = quantise_step(codes, quant.step, quant.offset)
    elif scale_arr is None:
        buf[idx] = codes.astype(codes_arr.dtype)
    else:
        q, params = quantize_codes(codes, per="block")
        sbuf = np.asarray(scale_arr[box]) if had else np.zeros((*shape, 2), dtype=np.float32)
        buf[idx], sbuf[idx] = q, params
        scale_arr[box] = sbuf
    codes_arr[box] = buf


class MapWriter:
    """State of a map being written into its temporary directory (``.NAME.tmp-*``, locked while we live).

    ``update`` is set for :func:`update_writer`: the temporary directory starts as a copy of the current
    version (whose directory identity is ``update["source"]``), the grid and block states start from it, and the
    writer lock ``update["lock"]`` is held from the copy to the swap so no other update is lost.

    ``state`` ``(Bx, By, Bz)`` uint8 and ``grid`` are the block states and grid so far (the ``state`` array is
    written on commit). The write methods take checked input (``sdfcodec.map.format.check_volume``): the
    facade checks it, so that its warnings point at the user's call.

    A write the file system refuses (disk full, permission, I/O error) aborts the writer, removing its
    temporary directory, and raises :class:`~sdfcodec.errors.WriteFailedError`: the map at the path is then
    exactly as it was, and the writer takes no further writes.
    """

    def __init__(self, final: Path, tmp: Path, tmp_fd: int, group: zarr.Group, codec: Codec, header_kw: dict,
                 codes_spec: CodesSpec, overwrite: bool, device: torch.device, *, header: MapHeader,
                 max_state_bytes: int = DEFAULT_MAX_DECODE_BYTES, grid: tuple | None = None,
                 state: np.ndarray | None = None, update: dict | None = None):
        self.committed_fd: int | None = None  # commit(keep=True): the descriptor of the version written
        self.final, self.tmp, self.tmp_fd, self.group, self.codec = final, tmp, tmp_fd, group, codec
        self.header, self.location = header, str(final)  # the header as opened (the final one is made on commit)
        self.header_kw, self.codes_spec, self.overwrite, self.device = header_kw, codes_spec, overwrite, device
        self.max_state_bytes, self.update = max_state_bytes, update
        self.shape_voxels = tuple(header_kw.pop("shape_voxels"))
        self.grid = tuple(grid) if grid is not None else tuple(-(-n // BLOCK) for n in self.shape_voxels)
        self.state = state if state is not None else np.zeros(self.grid, dtype=np.uint8)
        self.codes = group["codes"]
        self.code_scale = group["code_scale"] if codes_spec.dtype == "int8" else None
        self.mask = group[MASK_ARRAY] if MASK_ARRAY in group else None  # observation mask, once one is written
        # its chunks written here (recompressed at commit); what a transcode's source says of its mask (spec 6f)
        self.mask_touched, self.carried = set(), []
        # the residual stage (spec 6d): its array is made with the map, its step and bound are in the header
        self.residual = group[RESIDUAL_ARRAY] if header_kw.get("residual") is not None else None
        self._live_reader: MapReader | None = None
        self.surface_weight = SURFACE_WEIGHT  # error weight near surfaces (sdfcodec.map.observed); 0: none
        # what commit does with the fusion weights written (sdfcodec.map.weights): an update keeps the map's kind
        self.weights_mode = "float16"
        if update:
            self.doing = "updating the map"
        else:
            self.doing = "replacing the map" if os.path.lexists(final) else "creating the map"
        self.outcome = _UNCHANGED if self.doing != "creating the map" else _NOTHING
        self.failed: str | None = None  # why the writer aborted itself (further writes are refused)
        # the integrity manifest is written at commit (spec 9b): by default, and by an update where the map has one
        self.manifest = header.manifest is not None if update else True
        self.vr: VariableRateWriter | None = None  # variable-rate codes: their pass on commit (spec 4e)

    @contextlib.contextmanager
    def _writing(self):
        """Around every step that writes: a refused write aborts the writer (see the class docstring)."""
        if self.failed is not None or self.tmp_fd is None:
            why = f" after a failed write ({self.failed})" if self.failed else ""
            raise InvalidValueError(f"the writer of {self.final} was aborted{why}; nothing more can be written "
                                    "through it: start again with create_map or update_map")
        try:
            with _write_errors(self.final, self.doing, self.outcome, cleanup=self.abort):
                yield
        except WriteFailedError as e:
            self.failed = f"{e.strerror or 'error'}"
            self.abort()  # also when the error came from a dask task (store_code_chunk)
            raise

    def _grow_voxels(self, need: tuple[int, int, int]) -> None:
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
            if self.mask is not None:
                self.mask.resize((*grid, MASK_BYTES))
            if self.residual is not None:
                self.residual.resize((*grid, self.residual.shape[3]))
            if self.vr is not None:
                self.group[GAIN_ARRAY].resize((*grid, self.codes_spec.size))

    def grow_blocks(self, max_coord: np.ndarray) -> None:
        """Make the grid hold block ``max_coord``; the voxel extent grows only on axes the grid grows."""
        need = tuple((int(m) + 1) * BLOCK if int(m) >= g else n
                     for m, g, n in zip(max_coord, self.grid, self.shape_voxels))
        self._grow_voxels(need)

    @property
    def truncation(self) -> tuple[float, float]:
        """``(d_min, d_max)`` metres of the map being written."""
        t = self.header_kw["truncation"]
        return t.d_min, t.d_max

    def grow_voxels(self, need: tuple[int, int, int]) -> None:
        """Grow the extent to at least ``need`` voxels (the grid and the arrays with it)."""
        with self._writing():
            self._grow_voxels(need)

    def write_volume(self, vol: np.ndarray, *, offset: Sequence[int] = (0, 0, 0), batch_size: int = 16384,
                     progress: Callable[[int], None] | None = None) -> None:
        """Encode a checked dense volume ``(X, Y, Z)`` float32 metres placed at voxel ``offset`` (multiples of
        16): the grid grows to hold it, the far faces of its last blocks padded by repeating its last voxel
        layer (:func:`~sdfcodec.core.blocks.split_blocks`: no surface where the volume ends)."""
        with self._writing():
            self._write_volume(vol, offset, batch_size, progress)

    def _write_volume(self, vol, offset, batch_size, progress) -> None:
        off = np.asarray(offset, dtype=np.int64)
        if off.shape != (3,) or (off % BLOCK).any() or (off < 0).any():
            raise ShapeError(f"offset must be three non-negative multiples of {BLOCK} voxels, got {tuple(offset)}")
        self._grow_voxels(tuple(int(o + n) for o, n in zip(off, vol.shape)))
        blocks = split_blocks(vol)
        gb = blocks.shape[:3]
        flat = blocks.reshape(-1, BLOCK, BLOCK, BLOCK)
        coords = np.stack(np.meshgrid(*[np.arange(n) for n in gb], indexing="ij"), -1).reshape(-1, 3) + off // BLOCK
        self.put_blocks(coords, flat, batch_size=batch_size, progress=progress)

    def write_blocks(self, coords: np.ndarray, blocks: np.ndarray, *, weights: Any = None, observed: Any = None,
                     batch_size: int = 16384, progress: Callable[[int], None] | None = None) -> None:
        """Encode checked blocks ``(N, 16, 16, 16)`` float32 metres at checked block indices ``coords`` ``(N, 3)``
        int64, with optional fusion weights ``(N, 16, 16, 16)`` (non-negative; stored, and ``weights > 0`` is
        the observation mask) or an observation mask ``observed`` ``(N, 16, 16, 16)`` bool alone."""
        wt = obs = None
        if weights is not None:
            wt = check_weights(weights, len(coords), torch.device("cpu"))
            obs = wt.numpy() > 0
        if observed is not None:
            o = np.asarray(observed)
            if o.shape != (len(coords), BLOCK, BLOCK, BLOCK) or o.dtype != bool:
                raise ShapeError(f"observed must be a bool array of shape ({len(coords)}, 16, 16, 16), got "
                                 f"{o.dtype} {o.shape}")
            obs = o if obs is None else obs & o
        with self._writing():
            if len(coords):
                self.grow_blocks(coords.max(axis=0))
            self.put_blocks(coords, blocks, batch_size=batch_size, progress=progress, observed=obs)
            if wt is not None:
                self.put_weights(coords, wt.numpy())

    def write_codes(self, coords: Any, codes: Any, masks: np.ndarray | None = None) -> None:
        """Store already-encoded codes ``(N, D)`` (from this map's codec) at block indices ``coords`` ``(N, 3)``,
        with their packed observation masks ``(N, 512)`` uint8 (None: observed everywhere)."""
        c = check_coords(coords)
        if is_metric(self.codes_spec):
            raise InvalidValueError(f"{self.final} stores the voxels' metres bit for bit (metric codes, spec 4f): "
                                    "write blocks or volumes (write_blocks, write_volume), not codes")
        z, _ = as_float_tensor(codes, "codes", (len(c), self.codes_spec.size))
        with self._writing():
            if len(c):
                self.grow_blocks(c.max(axis=0))
            self.put_codes(c, z.numpy(), masks=masks, residual_ok=False)
            if self.vr is not None and len(c):  # no voxels: every voxel weighs 1
                write_block_rows(self.group[GAIN_ARRAY], c, np.ones((len(c), self.codes_spec.size), np.float32))

    def mark_empty(self, coords: Any) -> None:
        """Record blocks ``(N, 3)`` as observed free space (no code stored)."""
        c = check_coords(coords)
        if len(c):
            with self._writing():
                self.grow_blocks(c.max(axis=0))
            self.set_state(c, BlockState.EMPTY)

    def write_weights(self, coords: np.ndarray, weights: np.ndarray) -> None:
        """Store fusion weights ``(N, 16, 16, 16)`` (checked: finite, non-negative) of blocks ``coords`` ``(N, 3)``
        already written (a transcode carrying its source's weights, ``Map.write_map(keep_weights=True)``)."""
        if len(coords):
            with self._writing():
                self.grow_blocks(coords.max(axis=0))
                self.put_weights(coords, np.asarray(weights, dtype=np.float32))

    def put_weights(self, coords: np.ndarray, weights: np.ndarray) -> None:
        if WEIGHTS_ARRAY not in self.group:
            dtype = "float32" if self.weights_mode == "float32" else "float16"  # metric maps: exact (spec 6a)
            self.group.create_array(WEIGHTS_ARRAY, shape=(*self.grid, 4096), dtype=dtype, fill_value=0,
                                    chunks=(4, 4, 4, 4096), compressors=compressors(),
                                    dimension_names=["bx", "by", "bz", "voxel"])
        arr = self.group[WEIGHTS_ARRAY]
        if tuple(arr.shape[:3]) != self.grid:
            arr.resize((*self.grid, 4096))
        rows = stored_weights(weights.reshape(len(weights), 4096), arr.dtype)  # an update keeps the map's kind
        write_block_rows(arr, coords, rows)  # one write per chunk, not one per block

    def set_state(self, coords: np.ndarray, value: int) -> None:
        self.state[tuple(coords.T)] = value

    def put_blocks(self, coords: np.ndarray, blocks_m: np.ndarray, *, batch_size: int,
                   progress: Callable[[int], None] | None, observed: np.ndarray | None = None) -> None:
        """Encode blocks (metres) with error weights (:func:`~sdfcodec.map.observed.error_weights`: the
        observation mask ``observed`` (N, 16, 16, 16) bool, and the surface), storing the mask with them."""
        d_min, d_max = self.truncation
        spec, metric = self.header_kw.get("residual"), is_metric(self.codes_spec)
        # --sign-exact: the crossings of the whole call, so that those across the faces of two batches count too
        cross = crossing_voxels(coords, blocks_m, observed) if spec is not None and spec.sign_exact else None
        for i in range(0, len(coords), batch_size):
            c = coords[i:i + batch_size]
            # metric codes are the metres themselves, within the range in float32; only exact free space is empty (4f)
            v = (np.clip(blocks_m[i:i + batch_size], np.float32(d_min), np.float32(d_max)) if metric
                 else normalise(blocks_m[i:i + batch_size], d_min, d_max))
            empty = metric_empty(v, d_max) if metric else free_space(v)
            self.set_state(c[empty], BlockState.EMPTY)
            if (~empty).any():
                obs = None if observed is None else observed[i:i + batch_size][~empty]
                codes = (v[~empty].reshape(-1, BLOCK ** 3) if metric  # raw's encode: the identity
                         else encode_blocks(self.codec, v[~empty], obs, (d_min, d_max), self.header_kw["voxel_size"],
                                            self.surface_weight, self.device))
                packed = None if obs is None else pack_mask(obs)
                self.put_codes(c[~empty], codes, masks=packed)
                if self.vr is not None:  # the gains the variable-rate pass weighs errors with
                    self.vr.observe(self.group[GAIN_ARRAY], c[~empty], v[~empty], obs, codes, self.truncation,
                                    self.header_kw["voxel_size"], self.surface_weight)
                if spec is not None:
                    self.put_residual(c[~empty], codes, blocks_m[i:i + batch_size][~empty], obs, packed,
                                      None if cross is None else cross[i:i + batch_size][~empty])
            if progress is not None:
                progress(len(c))

    def put_residual(self, coords: np.ndarray, codes: np.ndarray, blocks_m: np.ndarray, observed: np.ndarray | None,
                     packed: np.ndarray | None, crossing: np.ndarray | None) -> None:
        """Store the residual (spec 6d) of blocks ``coords`` ``(n, 3)`` just stored with ``codes`` ``(n, D)``
        float32: their input ``blocks_m`` ``(n, 16, 16, 16)`` metres against the decode a reader makes of the
        stored codes (the reader's own ``decode_codes``, here on the writer's device), with their observation
        ``observed`` (bool, packed ``packed``; None: all) and surface-crossing voxels ``crossing``."""
        if self._live_reader is None:
            self._live_reader = MapReader(self.group, self.header, self.location, cache=CodecCache(self.codec),
                                          max_decode_bytes=self.max_state_bytes, live=self)
        stored = torch.from_numpy(stored_code_values(codes, self.codes_spec)).to(self.device)
        dec = self._live_reader.decode_codes(stored, metres=True, coords=coords, mask_rows=packed, residual=False)
        q = np.empty((len(coords), BLOCK ** 3), self.residual.dtype)
        for i in range(0, len(coords), _RESIDUAL_SLAB):  # a slab at a time: its float64 work arrays stay small
            sl = slice(i, i + _RESIDUAL_SLAB)
            q[sl] = residual_rows(self.header_kw["residual"], blocks_m[sl], dec[sl],
                                  None if observed is None else observed[sl], None if crossing is None else crossing[sl],
                                  self.truncation)
        # every chunk holding coded blocks is stored, zeros too, so a reader tells a lost chunk from one whose
        # blocks need no correction (spec 6d); Zarr skips all-zero chunks by default
        write_block_rows(self.residual.with_config({"write_empty_chunks": True}), coords, q)

    def put_codes(self, coords: np.ndarray, codes: np.ndarray, masks: np.ndarray | None = None, *,
                  residual_ok: bool = True) -> None:
        """Scatter codes (and their packed observation masks ``(n, 512)`` uint8, None: fully observed) into whole
        chunks: one write per touched chunk and array (read first only if it had data)."""
        if not len(coords):
            return
        check_codes(codes)
        if self.residual is not None and not residual_ok:
            raise InvalidValueError(f"{self.final} has a residual stage (--max-error/--sign-exact), computed from the "
                                    "input voxels: write blocks or volumes (write_blocks, write_volume), not codes")
        if masks is not None and self.mask is None:
            self.mask = self.group.create_array(MASK_ARRAY, shape=(*self.grid, MASK_BYTES), dtype="uint8",
                                                fill_value=255, chunks=(*(self.codes_spec.chunk_blocks,) * 3,
                                                                        MASK_BYTES),
                                                compressors=mask_compressors(final=False),
                                                dimension_names=["bx", "by", "bz", "byte"])
        cb = self.codes_spec.chunk_blocks
        chunk_of = coords // cb
        order = np.lexsort(chunk_of.T[::-1])
        coords, codes, chunk_of = coords[order], codes[order], chunk_of[order]
        masks = None if masks is None else masks[order]
        bounds = np.flatnonzero(np.any(np.diff(chunk_of, axis=0) != 0, axis=1)) + 1
        for lo, hi in zip(np.r_[0, bounds], np.r_[bounds, len(coords)]):
            ch = chunk_of[lo]
            box = tuple(slice(int(c) * cb, min(int(c) * cb + cb, g)) for c, g in zip(ch, self.grid))
            had = bool((self.state[box] == BlockState.CODED).any())
            _store_code_chunk(self.codes, self.code_scale, box, coords[lo:hi] - ch * cb, codes[lo:hi], had,
                              self.codes_spec.quantisation)
            if self.mask is not None:
                store_mask_chunk(self.mask, box, coords[lo:hi] - ch * cb, None if masks is None else masks[lo:hi],
                                 had)
                self.mask_touched.add(tuple(int(c) for c in ch))
        self.set_state(coords, BlockState.CODED)

    def commit(self, keep: bool = False) -> Path:
        """Write the block states and the header, then swap the new version into place (spec section 9).
        ``keep``: hold the version just written (a shared lock on its directory, the descriptor left in
        ``committed_fd`` for the caller to read it through and close), so that what the caller reports is the map
        this writer wrote, even if another writer replaced it at the path a moment later.

        On any failure before the swap (a refused write: :class:`~sdfcodec.errors.WriteFailedError`) the writer
        is aborted: the map at the path is exactly as it was and the temporary directory is gone. After the
        swap nothing can fail: collecting the replaced version is best effort (the next commit, or its last
        reader, collects what is left)."""
        with self._writing():
            try:
                self._finish()
                lock = self.update["lock"] if self.update else _atomic.WriterLock(self.final, LOCK_TIMEOUT).acquire()
            except BaseException:
                self.abort()
                raise
            try:
                self._swap()
            except BaseException:
                self.abort()
                raise
            finally:
                lock.release()
        if keep and _atomic.HAVE_PROC_FD:
            _atomic.share_lock(self.tmp_fd)  # a reader now, like any other: the version stays while it is held
            self.committed_fd = self.tmp_fd
        else:
            os.close(self.tmp_fd)  # the new version is in place: readers may now hold it
        self.tmp_fd = None
        try:
            _atomic.collect(self.final)  # the version replaced, if nobody reads it, and dead writers' leftovers
        except OSError:
            pass
        return self.final

    def _finish(self) -> None:
        """The ``state`` array and the header (last: until the swap nobody sees any of this anyway)."""
        st = self.group.create_array("state", shape=self.grid, dtype="uint8", fill_value=0, overwrite=True,
                                     chunks=tuple(min(64, max(1, n)) for n in self.grid), compressors=compressors())
        st[...] = self.state
        weights_ext = finish_weights(self.group, Path(self.tmp), self.weights_mode, self.grid)
        extensions = [e for e in self.carried if self.mask is not None] + ([weights_ext] if weights_ext else [])
        if self.code_scale is not None:
            extensions.append(Extension(name=INT8_EXTENSION, required=True))
        if self.codes_spec.quantisation is not None:
            extensions.append(Extension(name=QUANT_EXTENSION, required=True))
        if self.mask is not None:
            if tuple(self.mask.shape[:3]) != self.grid:
                self.mask.resize((*self.grid, MASK_BYTES))
            # a variable-rate map codes its mask too (spec 6e): both need constriction
            extensions += finish_mask(self.group, Path(self.tmp), self.mask_touched, coded=self.vr is not None)
        if self.header_kw["codec"].state_reference is not None:
            extensions.append(Extension(name=STATE_REFERENCE_EXTENSION, required=True))
        if self.header_kw.get("residual") is not None:
            if tuple(self.residual.shape[:3]) != self.grid:
                self.residual.resize((*self.grid, self.residual.shape[3]))
            extensions.append(Extension(name=RESIDUAL_EXTENSION, required=True))
        if self.codes_spec.field_compression is not None:
            # the exact voxels written so far become the field-compressed codes: every chunk compressed once
            compress_codes(self.group, Path(self.tmp), self.state, self.codes_spec.field_compression)
            extensions.append(Extension(name=FIELD_EXTENSION, required=True))
        if self.codes_spec.shard_blocks is not None:
            # every writer wrote plain chunk files; packed byte for byte into whole shards of the new version
            # (spec section 4d), which nobody reads before the swap
            pack_shards(self.tmp, "codes", self.codes_spec.shard_blocks)
            extensions.append(Extension(name=SHARD_EXTENSION, required=True))
        if is_metric(self.codes_spec):
            extensions.append(Extension(name=METRIC_EXTENSION, required=True))
        compact_documents(self.tmp)  # before anything counts or lists their bytes
        if self.vr is not None:  # the float codes become one entropy-coded stream per chunk (spec 4e)
            if (gain := self.group[GAIN_ARRAY]).shape[:3] != self.grid:
                gain.resize((*self.grid, self.codes_spec.size))
            extensions.append(Extension(name=VARIABLE_RATE_EXTENSION, required=True))
            implied = IMPLIED if inline_states(self.state) else ("codes/c",)  # what the streams replace (spec 4e)
            skip = {Path(self.tmp) / n for n in (GAIN_ARRAY, STREAM_ARRAY, *implied)}  # all but them, root, manifest
            files = [f for f in Path(self.tmp).glob("*/**/*") if f.is_file() and not any(p in skip for p in f.parents)]
            fixed = sum(f.stat().st_size for f in files) + STREAM_METADATA_BYTES
            if self.manifest:
                keys = [f.relative_to(self.tmp).as_posix() for f in files]
                keys += [f"{STREAM_ARRAY}/zarr.json"] + stream_chunk_keys(self.state, self.codes_spec.chunk_blocks)
                fixed += manifest_bytes_estimate(keys)
            mref = manifest_placeholder(keys) if self.manifest else None  # the root document records it

            def other_bytes(fields: dict) -> int:  # every file but the codes, with the header they will have
                spec = self.codes_spec.model_copy(update={"variable_rate": VariableRate(**fields)})
                h = MapHeader(shape_voxels=self.shape_voxels, grid_blocks=self.grid, codes=spec, manifest=mref,
                              extensions=extensions + [Extension(name=MANIFEST_EXTENSION, required=True)] * bool(mref),
                              **self.header_kw)
                return fixed + len(root_document(json.loads(h.model_dump_json())))  # as compact_documents stores it

            vr = self.vr.finish(self.group, self.state, self.codes_spec.chunk_blocks, other_bytes, self.truncation,
                                extensions)  # which the lossy mask's extension joins (spec 6f)
            self.codes_spec = self.codes_spec.model_copy(update={"variable_rate": vr})
        # the integrity manifest (spec section 9b): every object of the new version, now complete but for the
        # root document, which records the manifest's digest; an update's signature no longer holds
        compact_documents(self.tmp)  # code_streams' document, made since
        manifest = None
        if self.manifest:
            manifest = write_manifest(self.tmp, None if not self.update else self.update.get("reuse"))
            extensions.append(Extension(name=MANIFEST_EXTENSION, required=True))
        header = MapHeader(shape_voxels=self.shape_voxels, grid_blocks=self.grid, codes=self.codes_spec,
                           extensions=extensions, manifest=manifest, **self.header_kw)
        self.group.attrs["sdfcodec"] = json.loads(header.model_dump_json())
        compact_documents(self.tmp, root_doc=True)

    def _swap(self) -> None:
        """Under the writer lock: check the path still holds what we may replace, then swap or rename."""
        exists = os.path.lexists(self.final)
        if self.update and (not exists or _stat_id(self.final) != self.update["source"]):
            raise FormatError(f"{self.final} was replaced or removed by something other than sdfcodec while "
                              "this update ran; nothing was written: update it again")
        if exists and not self.overwrite:
            raise MapExistsError(f"{self.final} appeared while writing; nothing was replaced (use overwrite)")
        if exists and not self.update:
            check_replaceable(self.final)
        # on failure either call leaves everything as it was (the new version still at self.tmp)
        if exists:
            _atomic.swap_into_place(self.tmp, self.final)
        else:
            os.rename(self.tmp, self.final)

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
    _atomic.remove_tree(p)


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


def check_replaceable(final: Path) -> None:
    """Raise :class:`MapExistsError` unless ``final`` is something ``overwrite`` may replace: nothing, an empty
    directory, or a directory holding an sdfcodec map (a ``zarr.json`` group document with an ``sdfcodec``
    header). Anything else (a directory of other files, a plain file, a device, a FIFO, a symbolic link) is
    refused: overwrite exists to replace a map, and a typo in the output path must never delete a user's data."""
    if not os.path.lexists(final):
        return
    what = None
    if os.path.islink(final):
        what = "a symbolic link (replace its target map, or remove the link)"
    elif not final.is_dir():
        what = "not a directory" if final.is_file() else "not a directory (a device, FIFO or socket)"
    elif any(final.iterdir()):
        doc = final / "zarr.json"
        try:
            ok = doc.is_file() and not doc.is_symlink() and doc.stat().st_size <= MAX_METADATA_BYTES
            meta = json.loads(doc.read_bytes()) if ok else None
        except (OSError, ValueError):
            meta = None
        if not (isinstance(meta, dict) and meta.get("node_type") == "group"
                and isinstance(meta.get("attributes"), dict) and "sdfcodec" in meta["attributes"]):
            what = "a directory that is not an sdfcodec map (no zarr.json group with an sdfcodec header)"
    if what:
        raise MapExistsError(f"{final} exists and is {what}; overwrite replaces only sdfcodec maps, so nothing "
                             "was changed: remove it yourself or choose another output path")


def create_writer(path: str | os.PathLike, *, codec: Codec, voxel_size: float,
                  truncation: tuple[float, float] = (-0.04, 0.1), origin: Sequence[float] = (0.0, 0.0, 0.0),
                  shape_voxels: Sequence[int] = (0, 0, 0), code_dtype: str = "float32",
                  chunk_blocks: int | None = None, chunk_code: int | None = None, overwrite: bool = False,
                  device: str | torch.device = "cpu", tool: str | None = None, source: str | None = None,
                  codec_state: str = "embedded", code_step: Any = None, code_offset: Any = None,
                  max_error: float | None = None, sign_exact: bool = False,
                  shard_blocks: int | None = None, manifest: bool = True,
                  variable_rate: VariableRateWriter | None = None, keep_weights: bool | None = None,
                  exact: bool = False) -> MapWriter:
    """Start a new map at ``path`` in its temporary directory (:func:`sdfcodec.create_map` documents the
    arguments); commit or abort the writer returned."""
    final = Path(path)
    if is_url(str(path)):
        raise InvalidValueError(f"maps are written to local paths; got URL {path} (write locally, then upload)")
    device = check_device(device)  # before the temporary directory: a bad device leaves nothing behind
    if os.path.lexists(final) and not overwrite:
        raise MapExistsError(f"{final} exists; pass overwrite=True (CLI: --overwrite) to replace it")
    check_replaceable(final)
    if final.suffix == ".zip":
        raise InvalidValueError("writing zip maps is not supported; write a directory map and zip its contents")
    if not codec.is_fitted:
        raise NotFittedError(f"{codec!r} needs fitting: call fit(blocks), load_state_dict(...), "
                             "or pass a trained model (--model PATH)")
    if code_dtype not in CODE_DTYPES:
        raise InvalidValueError(f"code_dtype must be one of {', '.join(CODE_DTYPES)}, got {code_dtype!r}")
    if not (np.isfinite(voxel_size) and voxel_size > 0):
        raise InvalidValueError(f"voxel_size must be a positive number of metres, got {voxel_size!r}")
    check_truncation(*truncation)
    if len(origin) != 3 or not np.all(np.isfinite(origin)):
        raise InvalidValueError(f"origin must be three finite numbers (metres), got {origin!r}")
    if codec_state not in ("embedded", "reference"):
        raise InvalidValueError(f"codec_state must be 'embedded' or 'reference', got {codec_state!r}")
    spec = code_layout(codec, code_dtype, chunk_blocks, chunk_code, _quantisation(codec, code_dtype, code_step,
                                                                                  code_offset))
    if shard_blocks is not None:
        spec = sharded_spec(spec, shard_blocks)
    if variable_rate is not None and (code_dtype != "float32" or shard_blocks is not None or max_error is not None
                                      or sign_exact):
        raise InvalidValueError("variable-rate codes are their own storage: leave code_dtype float32 and shard_blocks, "
                                "max_error and sign_exact unset")
    if exact:  # codes in metres, bit for bit (spec 4f)
        check_metric(codec, code_dtype, step=code_step, residual=max_error is not None or sign_exact,
                     variable_rate=variable_rate is not None)
        spec = metric_spec(spec)
    residual = residual_spec(codec, code_dtype, voxel_size, truncation, max_error, sign_exact)
    state = codec.state_dict()
    # by reference: the header names the shipped model and its digest, and no state array is written; a codec
    # that learns nothing stores nothing either way, so its map stays plain (no extension older readers refuse)
    ref = shipped_reference(codec) if codec_state == "reference" and state else None
    pkg, pkg_version = _distribution_of(codec)
    header_kw = dict(
        voxel_size=float(voxel_size), truncation=Truncation(d_min=truncation[0], d_max=truncation[1]),
        origin=tuple(float(o) for o in origin),
        codec=CodecSpec(id=codec.codec_id, config=codec.get_config(), package=pkg, package_version=pkg_version,
                        state_arrays=[] if ref else sorted(state), state_sha256=state_digest(state) if state else None,
                        state_reference=ref),
        provenance=Provenance(created=now_iso(), sdfcodec_version=__version__, tool=tool, source=public_source(source)),
        residual=residual,
    )
    bad_names = [n for n in state if not re.fullmatch(STATE_NAME_PATTERN, n)]
    if bad_names:
        raise InvalidValueError(f"codec {codec.codec_id!r} state array names {bad_names} cannot be stored in a map: "
                                f"names must match {STATE_NAME_PATTERN} (a plugin bug)")
    doing, outcome = ("replacing the map", _UNCHANGED) if os.path.lexists(final) else ("creating the map", _NOTHING)
    with _write_errors(final, doing, outcome):
        final.parent.mkdir(parents=True, exist_ok=True)
        _collect_quietly(final)  # leftovers of writers killed earlier
        tmp, tmp_fd = _atomic.make_temp_dir(final)

    def discard() -> None:
        _rmtree(tmp)
        os.close(tmp_fd)

    try:
        with _write_errors(final, doing, outcome, cleanup=discard):
            group = _new_group(tmp, codec, {} if ref else state, spec, code_dtype, shape_voxels, residual)
        extensions = [Extension(name=n) for n, d in ((INT8_EXTENSION, "int8"), (QUANT_EXTENSION, "int16"))
                      if code_dtype == d]
        extensions += [Extension(name=STATE_REFERENCE_EXTENSION)] if ref else []
        extensions += [Extension(name=FIELD_EXTENSION)] if spec.field_compression is not None else []
        extensions += [Extension(name=RESIDUAL_EXTENSION)] if residual is not None else []
        extensions += [Extension(name=SHARD_EXTENSION)] if spec.shard_blocks is not None else []
        extensions += [Extension(name=METRIC_EXTENSION)] if exact else []
        header = MapHeader(shape_voxels=tuple(int(n) for n in shape_voxels), grid_blocks=_grid_of(shape_voxels),
                           codes=spec, extensions=extensions, **header_kw)
    except WriteFailedError:
        raise  # already cleaned up
    except BaseException:
        discard()
        raise
    writer = MapWriter(final, tmp, tmp_fd, group, codec, dict(header_kw, shape_voxels=header.shape_voxels), spec,
                       overwrite, device, header=header)
    writer.manifest = bool(manifest)
    if variable_rate is not None:
        writer.vr = variable_rate
        group.create_array(GAIN_ARRAY, shape=(*header.grid_blocks, spec.size), dtype="float32", fill_value=0,
                           chunks=(spec.chunk_blocks,) * 3 + (spec.size,), compressors=compressors())
    writer.weights_mode = weights_mode(codec, keep_weights, exact)
    return writer


def _quantisation(codec: Codec, code_dtype: str, step: Any, offset: Any) -> CodeQuantisation | None:
    """The step and offset of int16 codes (spec section 4b), checked; None for the other code types."""
    if code_dtype != "int16":
        if step is not None or offset is not None:
            raise InvalidValueError(f"a code step (or offset) quantises int16 codes only; code_dtype is "
                                    f"{code_dtype!r}: pass code_dtype='int16' (CLI: --step implies it)")
        return None
    check_quantisable(codec)
    if step is None:
        raise InvalidValueError("int16 codes need a quantisation step: pass code_step (one number, or one per "
                                "code element; CLI: --step or --target-bytes)")
    st = check_step(step, codec.code_size)
    off = np.zeros(codec.code_size) if offset is None else np.asarray(offset, dtype=np.float64)
    if off.shape != (codec.code_size,) or not np.isfinite(off).all():
        raise InvalidValueError(f"code_offset must be {codec.code_size} finite numbers, got shape {off.shape}")
    return CodeQuantisation(step=[float(v) for v in st], offset=[float(v) for v in off])


def _grid_of(shape_voxels: Sequence[int]) -> tuple[int, int, int]:
    """Blocks per axis holding ``shape_voxels``."""
    return tuple(-(-int(n) // BLOCK) for n in shape_voxels)


def _collect_quietly(final: Path) -> None:
    try:
        _atomic.collect(final)
    except OSError:
        pass  # garbage collection is best effort: a later commit tries again


def _new_group(tmp: Path, codec: Codec, state: dict, spec: CodesSpec, code_dtype: str,
               shape_voxels: Sequence[int], residual: Any = None) -> zarr.Group:
    """The arrays of a new, empty map in ``tmp``: ``codes`` (and ``code_scale`` for int8), ``codec/`` state."""
    # "w-", not "w": "w" clears the store by removing and re-making its root, which would leave the
    # temporary directory unlocked (our lock is on the inode removed) for another writer's garbage collection
    group = zarr.open_group(CowLocalStore(str(tmp)), mode="w-", zarr_format=3)
    grid = _grid_of(shape_voxels)
    cb, cc = spec.chunk_blocks, spec.chunk_code
    group.create_array("codes", shape=(*grid, spec.size), dtype=code_dtype, fill_value=0,
                       chunks=(cb, cb, cb, cc), compressors=code_compressors(code_dtype),
                       dimension_names=["bx", "by", "bz", "code"])
    if code_dtype == "int8":
        group.create_array("code_scale", shape=(*grid, 2), dtype="float32", fill_value=0, chunks=(cb, cb, cb, 2),
                           compressors=compressors(), dimension_names=["bx", "by", "bz", "offset_scale"])
    if residual is not None:
        group.create_array(RESIDUAL_ARRAY, shape=(*grid, BLOCK ** 3), dtype=residual.dtype, fill_value=0,
                           chunks=(cb, cb, cb, BLOCK ** 3), compressors=residual_compressors(),
                           dimension_names=["bx", "by", "bz", "voxel"])
    cgroup = group.create_group("codec") if state else None  # none without state arrays (spec section 2)
    for name, arr in state.items():
        arr = np.ascontiguousarray(arr)
        a = cgroup.create_array(name, shape=arr.shape, dtype=arr.dtype, chunks=arr.shape or (1,),
                                compressors=compressors())
        a[...] = arr
    return group


def update_writer(path: str | os.PathLike, *, device: str | torch.device = "cpu", tool: str | None = None,
                  wait: float = LOCK_TIMEOUT, max_decode_bytes: int = DEFAULT_MAX_DECODE_BYTES) -> MapWriter:
    """Start changing the map at ``path``: a hard-linked copy of its current version in a temporary directory,
    the writer lock held until commit or abort (:func:`sdfcodec.update_map` documents the arguments)."""
    final = Path(path)
    if is_url(str(path)) or final.is_file():
        raise InvalidValueError(f"only local directory maps can be updated, got {path} (copy it locally first)")
    if not final.exists():
        raise MapNotFoundError(f"no map at {final}; create it with sdfcodec.create_map")
    device = check_device(device)  # before the lock and the temporary copy
    with _write_errors(final, "updating the map", _UNCHANGED):
        lock = _atomic.WriterLock(final, wait).acquire()
    tmp = tmp_fd = None

    def discard() -> None:
        if tmp is not None:
            _rmtree(tmp)
            os.close(tmp_fd)
        lock.release()

    try:
        src = open_reader(final, max_decode_bytes=max_decode_bytes)
        h = src.header
        unknown = [e.name for e in h.extensions if e.name not in KNOWN_EXTENSIONS]
        if unknown:
            raise VersionError(f"{final} uses extension(s) {unknown} that this sdfcodec cannot keep consistent "
                               "while changing blocks; update it with a newer sdfcodec")
        refuse_update(final, h.codes.field_compression)
        if h.codes.variable_rate is not None:
            raise InvalidValueError(f"{final} stores variable-rate codes (one entropy-coded stream per chunk), which "
                                    "are not updated in place; encode it again from its source")
        codec = src.codec  # checks the state digest; the codec encodes the new blocks
        states = src.block_states()
        manifest = src.group.store.manifest  # its digests of the files copied unchanged are kept at commit
        root = src.local_root()
        source_id = _stat_id(Path(root))
        with _write_errors(final, "updating the map", _UNCHANGED, cleanup=discard):
            _collect_quietly(final)  # leftovers of writers killed earlier
            tmp, tmp_fd = _atomic.make_temp_dir(final)
            _atomic.link_tree(root, tmp)
            src.close()
            unpack_shards(tmp, "codes")  # written chunk by chunk, packed again at commit (spec section 4d)
            group = zarr.open_group(CowLocalStore(str(tmp)), mode="r+", zarr_format=3)
        prov = h.provenance if tool is None else h.provenance.model_copy(update={"tool": tool})
        header_kw = dict(voxel_size=h.voxel_size, truncation=h.truncation, origin=h.origin, codec=h.codec,
                         provenance=prov, shape_voxels=h.shape_voxels, up=h.up, residual=h.residual)
        writer = MapWriter(final, tmp, tmp_fd, group, codec, header_kw, h.codes, True, device,
                         max_state_bytes=max_decode_bytes, grid=h.grid_blocks, state=states.copy(),
                         update={"lock": lock, "source": source_id, "reuse": previous_digests(final, manifest)},
                         header=h)
        writer.weights_mode = "float32" if is_metric(h.codes) else writer.weights_mode  # weights as exact as codes
    except WriteFailedError:
        raise  # already cleaned up
    except BaseException:
        discard()
        raise
    return writer

