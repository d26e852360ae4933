"""Maps beyond one machine's memory: dask arrays of decoded voxels, encoding dense volumes with dask, and
streamed fitting.

* :func:`map_to_dask` (``Map.to_dask``): a lazy ``(X, Y, Z)`` float32 array of metres, one dask chunk per
  chunk of the map's code array, each decoded on demand through the map's read pipeline
  (``MapReader.decode_region``). It pickles: a worker process reopens the map by its path or URL.
* :func:`write_volume_dask` (also what ``Map.write_volume`` does with a dask array) and
  :func:`encode_volume_dask`: encode a dense TSDF that need not fit in memory (a dask array, a Zarr array, a
  ``.npy`` file or ``np.memmap``) chunk by chunk on dask's scheduler or a ``dask.distributed`` cluster. Each
  task encodes the blocks of one chunk of the code array and writes that chunk straight into the map's
  temporary directory; the caller then commits as usual, so the crash-safe create protocol
  (spec/map-format.md, section 9) holds: until the commit nothing at the map's path changes.
* :func:`fit_volume_stream`: train a codec on the blocks of such a volume through ``Codec.fit_stream`` (for
  PCA an exact, one-pass streamed covariance in bounded memory, about 260 MB whatever the data size).

The map, its temporary directory and ``.npy`` inputs must be on a file system every worker sees (one machine,
or a shared mount); remote maps (HTTP, S3) are read from anywhere.
"""

from __future__ import annotations

import mmap
import os
import threading
import uuid
from pathlib import Path
from typing import TYPE_CHECKING, Any, Sequence

import numpy as np
import torch
import zarr

from ..core._validate import BLOCK
from ..core.blocks import normalise, split_blocks
from ..codec import Codec
from ..errors import DTypeError, InvalidValueError, ShapeError
from ..core.header import BlockState
from .codec_state import state_digest
from .format import check_codes, free_space, warn_clipped
from .observed import encode_blocks
from .opening import open_reader
from .reader import MapReader
from .io.stores import CowLocalStore
from .writer import MapWriter, create_writer, store_code_chunk

if TYPE_CHECKING:
    from .facade import Map

__all__ = ["map_to_dask", "write_volume_dask", "encode_volume_dask", "fit_volume_stream", "as_dask_volume"]

# -- reading: a map as a dask array ---------------------------------------------------------------------------

_OPEN_MAPS: dict[tuple, MapReader] = {}  # maps reopened in this process (dask workers), by (source, options, limit)
_OPEN_LOCK = threading.Lock()


def _reopened(source: Any, storage_options: dict | None, max_decode_bytes: int) -> MapReader:
    if not isinstance(source, str):  # a Zarr store object: nothing to key a cache on
        return open_reader(source, storage_options=storage_options, max_decode_bytes=max_decode_bytes)
    key = (source, repr(sorted((storage_options or {}).items())), max_decode_bytes)
    with _OPEN_LOCK:
        m = _OPEN_MAPS.get(key)
        if m is None:
            if len(_OPEN_MAPS) >= 16:
                _OPEN_MAPS.pop(next(iter(_OPEN_MAPS)))
            m = _OPEN_MAPS[key] = open_reader(source, storage_options=storage_options,
                                              max_decode_bytes=max_decode_bytes)
        return m


class _MapVoxels:
    """The decoded voxels of a map as an array-like for ``dask.array.from_array``: slicing decodes the region
    (``MapReader.decode_region``). In the process that made it, it uses the open map's reader (the version it
    holds); a copy unpickled elsewhere reopens the map by path or URL, once per process."""

    def __init__(self, m: Map | MapReader, level: int | None):
        reader = m if isinstance(m, MapReader) else m.reader
        if reader.source is None:
            raise InvalidValueError(f"{m.location}: to_dask needs a map opened for reading (sdfcodec.open_map); "
                                    "commit the map being written first")
        self._map: MapReader | None = reader
        self._source = (*reader.source, reader.max_decode_bytes)
        self.level = reader.level(level)
        self.shape = tuple(int(n) for n in m.shape_voxels)
        self.dtype = np.dtype(np.float32)
        self.ndim = 3
        self.d_max = float(m.truncation[1])

    def __getstate__(self) -> dict:
        return {"source": self._source, "level": self.level, "shape": self.shape, "d_max": self.d_max}

    def __setstate__(self, state: dict) -> None:
        self._source, self.level, self.shape = state["source"], state["level"], state["shape"]
        self.d_max, self.dtype, self.ndim, self._map = state["d_max"], np.dtype(np.float32), 3, None

    def __getitem__(self, sel: Any) -> np.ndarray:
        sel = sel if isinstance(sel, tuple) else (sel,)
        sel = sel + (slice(None),) * (3 - len(sel))
        if len(sel) != 3 or not all(isinstance(s, slice) and s.step in (None, 1) for s in sel):
            raise InvalidValueError(f"a map's voxels are read by step-1 slices on three axes, got {sel!r}")
        bounds = [s.indices(n)[:2] for s, n in zip(sel, self.shape)]
        if any(b <= a for a, b in bounds):
            return np.full([max(0, b - a) for a, b in bounds], self.d_max, np.float32)
        if self._map is None:
            self._map = _reopened(*self._source)
        return self._map.decode_region(bounds, level=self.level)


def map_to_dask(m: Map | MapReader, level: int | None = None):
    """The decoded map ``m`` (a :class:`sdfcodec.Map` or its reader) as a lazy ``dask.array.Array``: shape
    ``m.shape_voxels``, float32 metres (``d_max`` for
    unobserved and empty blocks and nothing beyond the true extent), chunked as the code array
    (``16 * chunk_blocks`` voxels per axis, the last chunk of each axis cut at the extent). Computing a chunk
    reads and decodes only the code chunks under it (plus the neighbours a halo codec needs)."""
    import dask.array as da

    arr = _MapVoxels(m, level)
    cv = m.header.codes.chunk_blocks * BLOCK
    return da.from_array(arr, chunks=(cv, cv, cv), name=f"sdfcodec-decode-{uuid.uuid4().hex}", lock=False,
                         fancy=False, meta=np.empty((0, 0, 0), np.float32))


# -- volumes that need not fit in memory -----------------------------------------------------------------------

class _NpySource:
    """A read-only memory-mapped array on disk (a ``.npy`` file or a whole ``np.memmap``) that pickles as its
    file name, so that dask workers map the file themselves instead of receiving a copy of it."""

    def __init__(self, filename: str, dtype: Any, shape: tuple, offset: int, order: str):
        self.filename, self.dtype, self.shape = str(filename), np.dtype(dtype), tuple(int(n) for n in shape)
        self.offset, self.order, self.ndim = int(offset), order, len(shape)
        self._mm: np.memmap | None = None

    def __getstate__(self) -> dict:
        return {k: v for k, v in self.__dict__.items() if k != "_mm"}

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self._mm = None

    def __dask_tokenize__(self):
        st = os.stat(self.filename)
        return ("sdfcodec-npy", self.filename, st.st_mtime_ns, st.st_size, self.offset, str(self.dtype), self.shape)

    def __getitem__(self, sel: Any) -> np.ndarray:
        if self._mm is None:
            self._mm = np.memmap(self.filename, dtype=self.dtype, mode="r", offset=self.offset, shape=self.shape,
                                 order=self.order)
        return np.array(self._mm[sel])  # a copy: the result does not keep the mapping alive


def _source_of(volume: Any) -> Any:
    """A picklable, sliceable stand-in for ``volume`` when it is a file on disk (``.npy`` path, memmap)."""
    if isinstance(volume, (str, os.PathLike)):
        p = Path(volume)
        if p.suffix == ".npy":
            volume = np.load(p, mmap_mode="r")
        elif p.is_dir():
            return zarr.open_array(str(p), mode="r")
        else:
            raise InvalidValueError(f"{p}: expected a .npy file or a Zarr array directory")
    if isinstance(volume, np.memmap) and isinstance(volume.base, mmap.mmap) and volume.filename:
        # a whole mapping (not a view of one): its file, offset and shape describe it exactly
        order = "F" if volume.flags.f_contiguous and not volume.flags.c_contiguous else "C"
        return _NpySource(volume.filename, volume.dtype, volume.shape, volume.offset, order)
    return volume


def _aligned_chunks(n: int, offset: int, step: int) -> tuple[int, ...]:
    """Chunk sizes covering ``[offset, offset + n)`` whose boundaries fall on multiples of ``step``."""
    out, pos, end = [], offset, offset + n
    while pos < end:
        nxt = min((pos // step + 1) * step, end)
        out.append(nxt - pos)
        pos = nxt
    return tuple(out)


def as_dask_volume(volume: Any, chunk_voxels: int = 128, offset: Sequence[int] = (0, 0, 0)):
    """``volume`` as a dask array whose chunk boundaries fall on multiples of ``chunk_voxels`` in map
    coordinates (the volume placed at voxel ``offset``). ``volume``: a dask array (rechunked), a Zarr array,
    a ``.npy`` path or ``np.memmap`` (read lazily by each worker from the file), or any array."""
    import dask.array as da

    src = _source_of(volume)
    shape = tuple(int(n) for n in src.shape)
    if len(shape) != 3:
        raise ShapeError(f"volume must be a dense (X, Y, Z) array of metres, got shape {shape}")
    chunks = tuple(_aligned_chunks(n, int(o), chunk_voxels) for n, o in zip(shape, offset))
    if hasattr(src, "dask"):
        return src.rechunk(chunks) if src.chunks != chunks else src
    return da.from_array(src, chunks=chunks, lock=False, fancy=False, asarray=True,
                         meta=np.empty((0, 0, 0), np.dtype(src.dtype)))


# -- writing: encode a volume with dask -----------------------------------------------------------------------

class _CodecSpec:
    """A codec as workers rebuild it: its configuration and learned state (plain arrays, as a map stores them;
    no plugin object travels). In the process that made it, the codec object itself is used."""

    def __init__(self, codec: Codec):
        self.config, self.state = codec.get_config(), codec.state_dict()
        self.digest = state_digest(self.state) + repr(sorted(self.config.items()))
        self._codec: Codec | None = codec

    def __getstate__(self) -> dict:
        return {"config": self.config, "state": self.state, "digest": self.digest}

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self._codec = None

    def __dask_tokenize__(self):
        return ("sdfcodec-codec", self.digest)

    def get(self) -> Codec:
        if self._codec is None:
            with _OPEN_LOCK:
                codec = _WORKER_CODECS.get(self.digest)
                if codec is None:
                    from ..registry import get_codec

                    codec = get_codec(self.config)
                    if self.state:
                        codec = codec.load_state_dict(self.state)
                    _WORKER_CODECS.clear()  # one codec at a time is what a worker encodes with
                    _WORKER_CODECS[self.digest] = codec
            self._codec = codec
        return self._codec


_WORKER_CODECS: dict[str, Codec] = {}


def _encode_chunk(block: Any, spec: _CodecSpec, tmp: str, b0: tuple, cbox: tuple, had: bool,
                  truncation: tuple[float, float], code_dtype: str, device: str, voxel_size: float,
                  surface_weight: float, quant: Any = None) -> tuple[tuple, np.ndarray, int, tuple | None]:
    """One dask task: encode the blocks of one volume chunk (all inside one chunk of the code array, whose
    block box is ``cbox``) and write that chunk of codes into the map's temporary directory ``tmp``.
    Returns ``(b0, block states of the chunk's blocks, number of values clipped, (min, max) of the chunk or None
    when nothing was clipped)``."""
    d_min, d_max = truncation
    v = np.asarray(block)
    if v.dtype.kind != "f":
        raise DTypeError(f"volume must be floating point metres, got dtype {v.dtype}")
    v = v.astype(np.float32, copy=False)
    finite = np.isfinite(v)
    if not finite.all():
        raise InvalidValueError(f"volume holds {int((~finite).sum())} NaN/Inf value(s) in the chunk at voxel "
                                f"{tuple(int(b) * BLOCK for b in b0)}; replace unobserved voxels with d_max "
                                f"(e.g. np.nan_to_num(v, nan={d_max}))")
    clipped = int(((v < d_min) | (v > d_max)).sum())
    span = None
    if clipped:  # the span only for the warning: no extra passes over a chunk that was in range
        span = (float(v.min()), float(v.max()))
        v = np.clip(v, d_min, d_max)
    blocks = split_blocks(v)
    gb = blocks.shape[:3]
    norm = normalise(blocks.reshape(-1, BLOCK, BLOCK, BLOCK), d_min, d_max)
    empty = free_space(norm)
    states = np.where(empty, BlockState.EMPTY, BlockState.CODED).astype(np.uint8).reshape(gb)
    if not empty.all():
        codes = encode_blocks(spec.get(), norm[~empty], None, truncation, voxel_size, surface_weight, device)
        check_codes(codes)
        store = CowLocalStore(tmp)
        arr = zarr.open_array(store, path="codes", mode="r+")
        scale_arr = zarr.open_array(store, path="code_scale", mode="r+") if code_dtype == "int8" else None
        box = tuple(slice(int(a), int(b)) for a, b in cbox)
        local = np.argwhere(states == BlockState.CODED) + np.asarray(b0) - np.array([a for a, _ in cbox])
        store_code_chunk(arr, scale_arr, box, local, codes, had, quant)
    return b0, states, clipped, span


def _encode_chunk_or_error(*args: Any) -> tuple:
    """:func:`_encode_chunk` that returns its exception instead of raising it: every task then runs to its end
    before the write is aborted, so none is still writing into the temporary directory while the abort removes
    it (a failed task does not stop the others on a distributed cluster)."""
    try:
        return _encode_chunk(*args)
    except Exception as e:  # noqa: BLE001 - re-raised by the caller once every task has ended
        return (e,)


def write_volume_dask(m: Map | MapWriter, volume: Any, *, offset: Sequence[int] = (0, 0, 0), scheduler: Any = None) -> None:
    """Encode a dense TSDF ``(X, Y, Z)`` in metres into the map ``m`` being written (a :class:`sdfcodec.Map` from
    ``create_map`` or ``update_map``, or its ``MapWriter``), placed at voxel ``offset`` (multiples of 16),
    with dask: one task per chunk of the code
    array, each writing its chunk into the map's temporary directory. Gives the same map as
    ``m.write_volume`` of the whole array in memory (codes equal up to float32 rounding of batched products).

    ``volume``: see :func:`as_dask_volume`. ``scheduler``: passed to ``dask.compute`` (default: the active
    ``dask.distributed`` client if there is one, else dask's default). Values outside the truncation are
    clipped with one warning; NaN/Inf are refused (the map is then not changed: the write is aborted by the
    ``with`` block, or call ``m.abort()``).
    """
    import dask

    w = m if isinstance(m, MapWriter) else m.writer  # ReadOnlyError for a map open for reading
    off = np.asarray(offset, dtype=np.int64)
    if off.shape != (3,) or (off % BLOCK).any() or (off < 0).any():
        raise ShapeError(f"offset must be three non-negative multiples of {BLOCK} voxels, got {tuple(offset)}")
    spec_c = w.codes_spec
    if spec_c.units is not None:  # its tasks encode normalised blocks (spec 4f: metric codes store metres)
        raise InvalidValueError(f"{w.final} stores metric codes (exact=True), which the dask encoder does not write: "
                                "pass a numpy volume (m.write_volume) or create the map without exact")
    cb = spec_c.chunk_blocks
    vol = as_dask_volume(volume, cb * BLOCK, off)
    if np.dtype(vol.dtype).kind != "f":
        raise DTypeError(f"volume must be floating point metres, got dtype {vol.dtype}")
    w.grow_voxels(tuple(int(o + n) for o, n in zip(off, vol.shape)))
    truncation = w.truncation
    spec = dask.delayed(_CodecSpec(w.codec), pure=True, traverse=False)
    encode = dask.delayed(_encode_chunk_or_error, pure=False)
    starts = [np.r_[0, np.cumsum(c)[:-1]] for c in vol.chunks]
    tasks = []
    for idx, part in np.ndenumerate(vol.to_delayed()):
        b0 = (off + np.array([s[i] for s, i in zip(starts, idx)])) // BLOCK
        c0 = b0 // cb * cb
        cbox = tuple((int(a), int(min(a + cb, g))) for a, g in zip(c0, w.grid))
        had = bool((w.state[tuple(slice(a, b) for a, b in cbox)] == BlockState.CODED).any())
        tasks.append(encode(part, spec, str(w.tmp), tuple(int(b) for b in b0), cbox, had, truncation,
                            spec_c.dtype, str(w.device), w.header_kw["voxel_size"], w.surface_weight,
                            spec_c.quantisation))
    results = dask.compute(*tasks, scheduler=scheduler) if tasks else ()
    failed = next((r[0] for r in results if len(r) == 1), None)
    if failed is not None:
        raise failed
    for b0, states, _, _ in results:
        w.state[tuple(slice(a, a + s) for a, s in zip(b0, states.shape))] = states
    spans = [span for *_, span in results if span is not None]
    if spans:  # one warning for the whole volume, as a plain write gives (check_volume)
        clipped = sum(n for _, _, n, _ in results)
        lo, hi = min(s[0] for s in spans), max(s[1] for s in spans)
        warn_clipped(clipped, int(np.prod(vol.shape)), (lo, hi), truncation, stacklevel=3)


def encode_volume_dask(volume: Any, path: str | os.PathLike, codec: Codec, *, voxel_size: float,
                       truncation: tuple[float, float] = (-0.04, 0.1), origin: Sequence[float] = (0.0, 0.0, 0.0),
                       scheduler: Any = None, **create_kw: Any) -> Path:
    """Create the map at ``path`` from a dense volume with dask (:func:`write_volume_dask`) and commit it;
    ``create_kw`` go to :func:`sdfcodec.create_map` (``code_dtype``, ``chunk_blocks``, ``overwrite``...).
    On any error nothing at ``path`` changes. Returns the map's path."""

    w = create_writer(path, codec=codec, voxel_size=voxel_size, truncation=truncation, origin=origin, **create_kw)
    try:
        write_volume_dask(w, volume, scheduler=scheduler)
    except BaseException:
        w.abort()
        raise
    w.commit()
    return Path(path)


# -- training on data larger than memory ----------------------------------------------------------------------

def fit_volume_stream(codec: Codec, volume: Any, truncation: tuple[float, float] = (-0.04, 0.1), *,
                      chunk_voxels: int = 128, include_empty: bool = False) -> Codec:
    """Fit ``codec`` on the 16^3 blocks of a dense volume in metres that need not fit in memory (see
    :func:`as_dask_volume`), one chunk of ``chunk_voxels`` per axis at a time, through
    :meth:`Codec.fit_stream`. Empty blocks (all free space) are left out unless ``include_empty``.

    Memory stays bounded only for codecs that learn incrementally (``fit_batches``: PCA accumulates the exact
    4096 x 4096 covariance in one pass); the others get the concatenated blocks. For a block data set on disk
    (``sdfcodec.core.dataset``), ``codec.fit_stream(ds.iter_batches("train"))`` is the same thing, and what
    ``sdfcodec train`` does when the data set exceeds ``--max-memory-gb``."""
    if chunk_voxels % BLOCK or chunk_voxels <= 0:
        raise InvalidValueError(f"chunk_voxels must be a positive multiple of {BLOCK}, got {chunk_voxels}")
    d_min, d_max = truncation
    vol = as_dask_volume(volume, chunk_voxels)

    def batches():
        for idx in np.ndindex(*vol.numblocks):
            v = np.asarray(vol.blocks[idx].compute(scheduler="sync"), dtype=np.float32)
            if not np.isfinite(v).all():
                raise InvalidValueError("volume holds NaN/Inf values; replace unobserved voxels with d_max")
            v = np.clip(v, d_min, d_max)
            b = normalise(split_blocks(v).reshape(-1, BLOCK, BLOCK, BLOCK), d_min, d_max)
            if not include_empty:
                b = b[~free_space(b)]
            if len(b):
                yield b

    return codec.fit_stream(batches())
