"""Which voxels a map observed, and how that steers encoding (spec/map-format.md, section 6b).

A fused map knows which voxels some frame saw (fusion weight > 0). The rest, above all the space more than
``|d_min|`` behind each surface, reads ``d_max`` although nothing was seen there: a fused block is a thin
negative band behind a surface followed by a step back to ``d_max``, which a low-dimensional code cannot
follow, so the band washes out and the zero crossing moves (measured: docs/surface.md). Two things fix it:

- **Error weights** (:func:`error_weights`): the codec encodes each block by weighted least squares
  (:meth:`sdfcodec.Codec.encode_weighted`), with weight 0 on unobserved voxels (their value does not matter)
  and ``1 + SURFACE_WEIGHT`` within ``SURFACE_BAND_VOXELS`` voxels of the surface (the two voxels around a zero
  crossing decide where the surface is; the far free space is easy and need not dominate the fit). Readers
  truncate what they decode to ``[d_min, d_max]``, so a voxel stored at a bound and decoded beyond it has no
  error at all: :func:`encode_blocks` refits without those (:data:`TRUNCATION_ROUNDS`).
- **The observation mask** (extension ``observation-mask``): one bit per voxel of each coded block, packed
  (``numpy.packbits`` of the C-order voxels, 512 bytes per block before compression), in the array
  ``observed`` chunked like ``codes``; readers put ``d_max`` back on every unobserved voxel after decoding, so
  what the codec made of them never shows. Blocks written without one read as fully observed (fill 255).

Both are the writer's and reader's business; codecs only see weights.
"""

from __future__ import annotations

import inspect
import json
import os
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import zarr

from ..core._lazy import lazy_module
from ..core._validate import BLOCK
from ..codec import capabilities, learns_weights, numpy_path_of, uses_weights
from ..errors import FormatError
from ..core.header import CODED_MASK_EXTENSION, PINNED_MASK_EXTENSION, BlockState, Extension
from .format import mask_compressors
from .grouping import chunk_box

if TYPE_CHECKING:
    from ..codec import Codec
    from .reader import MapReader

torch = lazy_module("torch")  # imported on first use: info, codecs, verify of a header never need it

__all__ = ["MASK_EXTENSION", "MASK_ARRAY", "MASK_BYTES", "SURFACE_BAND_VOXELS", "SURFACE_WEIGHT", "TRUNCATION_ROUNDS",
           "error_weights", "fill_unobserved", "encode_blocks", "encode_truncated", "fit_codec", "pack_mask",
           "unpack_mask", "restore_unobserved", "restore_unobserved_voxels", "read_block_rows", "write_block_rows",
           "store_mask_chunk", "read_observed", "read_observation", "checked_mask_array", "finish_mask"]

MASK_EXTENSION = "observation-mask"
MASK_ARRAY = "observed"
MASK_BYTES = BLOCK ** 3 // 8  # 512: one bit per voxel
#: Voxels this close to the surface (``|d| < SURFACE_BAND_VOXELS * voxel_size``) weigh ``1 + SURFACE_WEIGHT``:
#: the voxels that can end an axis crossing (a distance changes by about a voxel between neighbours). Measured
#: on the held-out half of a fused kitchen (docs/surface.md): 1.0 beat 0.75, 1.5 and 2.0.
SURFACE_BAND_VOXELS = 1.0
SURFACE_WEIGHT = 50.0
#: Refits of a weighted encode that drop the voxels a reader's truncation makes exact (:func:`encode_blocks`).
TRUNCATION_ROUNDS = 3
_WEIGHT_SLAB = 64  # blocks per in-place pass of error_weights: 1 MiB of float32


def error_weights(v: np.ndarray, observed: np.ndarray | None, truncation: tuple[float, float], voxel_size: float,
                  surface_weight: float = SURFACE_WEIGHT) -> np.ndarray | None:
    """Per-voxel error weights ``(N, 16, 16, 16)`` float32 for normalised blocks ``v`` ``(N, 16, 16, 16)``:
    0 where ``observed`` ``(N, 16, 16, 16)`` bool is False, ``1 + surface_weight`` near the surface, 1 elsewhere.
    None (encode unweighted, the plain projection) without a mask: blocks of dense volumes (exact SDFs, observed
    everywhere) encode exactly as before the observation mask, and their code distances stay reconstruction
    distances (what descriptor search relies on)."""
    if observed is None:
        return None
    d_min, d_max = truncation
    # |d| < band metres  <=>  |v - v0| < band / (d_max - d_min), v0 the normalised zero
    v0, half = np.float32(-d_min / (d_max - d_min)), np.float32(SURFACE_BAND_VOXELS * voxel_size / (d_max - d_min))
    w = np.empty(v.shape, dtype=np.float32)
    # in place, a cache-sized slab of blocks at a time: one pass over memory instead of five (3.6x here)
    for i in range(0, len(v), _WEIGHT_SLAB):
        o, sl = w[i:i + _WEIGHT_SLAB], slice(i, i + _WEIGHT_SLAB)
        if surface_weight:
            np.subtract(v[sl], v0, out=o)
            np.abs(o, out=o)
            np.multiply(o < half, np.float32(surface_weight), out=o)
            o += np.float32(1)
            o *= observed[sl]
        else:
            o[...] = observed[sl]
    return w


#: Blocks filled together by :func:`fill_unobserved`: 4 arrays of 32 x 16 KiB, 2 MiB, fit a core's L2.
FILL_GROUP = 32


def fill_unobserved(v: np.ndarray, observed: np.ndarray) -> np.ndarray:
    """A copy of normalised blocks ``v`` ``(N, 16, 16, 16)`` whose unobserved voxels (``observed`` False) hold the
    mean of their nearest observed voxels, grown one face-neighbour layer at a time inside each block (the
    space behind a surface becomes solid, what the observed band there says); blocks with nothing observed
    are left as they are. For codecs that cannot use error weights: what they are given to encode then has no
    step from the band behind a surface to ``d_max``, which no short code follows (docs/surface.md)."""
    x = np.array(v, dtype=np.float32)
    flat = observed.reshape(len(x), -1)
    todo = np.flatnonzero(~flat.all(axis=1) & flat.any(axis=1))
    # a few blocks at a time: their four working arrays stay in cache over the up to 45 layers, and each
    # group stops at its own last layer (the whole batch at once was 3-6x slower, memory-bound)
    for i in range(0, len(todo), FILL_GROUP):
        idx = todo[i:i + FILL_GROUP]
        x[idx] = _grow(x[idx], observed[idx])
    return x


def _face_shifts() -> list[tuple[tuple[slice, ...], tuple[slice, ...]]]:
    """(destination, source) index pairs of ``(n, 16, 16, 16)`` arrays: each voxel and its six face neighbours."""
    out = []
    for axis in (1, 2, 3):
        for dst, src in ((slice(1, BLOCK), slice(0, BLOCK - 1)), (slice(0, BLOCK - 1), slice(1, BLOCK))):
            d, s_ = [slice(None)] * 4, [slice(None)] * 4
            d[axis], s_[axis] = dst, src
            out.append((tuple(d), tuple(s_)))
    return out


def _grow(val: np.ndarray, observed: np.ndarray) -> np.ndarray:
    """:func:`fill_unobserved` of blocks ``val`` ``(n, 16, 16, 16)`` float32 (a copy, filled in place), each with
    something observed."""
    known = observed.astype(np.float32)
    val *= known
    total, count = np.empty_like(val), np.empty_like(val)
    shifts = _face_shifts()
    while True:
        total.fill(0)
        count.fill(0)
        for d, s_ in shifts:  # sums over the known face neighbours, by shifted slices
            total[d] += val[s_]
            count[d] += known[s_]
        new = (count > 0) & (known == 0)
        if not new.any():
            return val
        np.divide(total, count, out=val, where=new)
        known[new] = 1


def encode_blocks(codec: Codec, v: np.ndarray, observed: np.ndarray | None, truncation: tuple[float, float],
                  voxel_size: float, surface_weight: float, device: Any, *, numpy_path: bool = False,
                  shrink: float = 0.0) -> np.ndarray:
    """Codes ``(N, k)`` float32 numpy of normalised blocks ``v`` ``(N, 16, 16, 16)``, encoded on ``device`` with
    the error weights of :func:`error_weights`: how every map writer (one process, or dask tasks) encodes.
    A codec that ignores weights (:func:`sdfcodec.codec.uses_weights`) encodes the blocks with their
    unobserved voxels filled from the observed ones (:func:`fill_unobserved`) instead. A codec whose map stores
    its voxels as a compressed field (:meth:`~sdfcodec.Codec.field_compression`) gets them exactly as given:
    the field compressor, not ``encode``, bounds their error (spec/map-format.md section 4c). ``numpy_path``: on
    the CPU, through the codec's torch-free :meth:`~sdfcodec.Codec.numpy_path` where it has one (the same codes
    to float32 rounding; a search encoding its query shapes takes it, writers keep the torch hooks). ``shrink``:
    see :func:`encode_truncated`."""
    if codec.field_compression() is not None:
        return np.ascontiguousarray(v, dtype=np.float32).reshape(len(v), -1)
    w = error_weights(v, observed, truncation, voxel_size, surface_weight)
    if w is not None and not uses_weights(codec):
        v, w = fill_unobserved(v, observed), None
    path = numpy_path_of(codec) if numpy_path and str(device) == "cpu" else None
    if path is not None:  # numpy in, numpy out: no torch import (a search's first query on a pca map)
        x = np.ascontiguousarray(v, dtype=np.float32).reshape(len(v), -1)
        codes = path.encode(x) if w is None else path.encode_truncated(x, w.reshape(len(v), -1), TRUNCATION_ROUNDS,
                                                                        **_shrink_kw(path.encode_truncated, shrink))
        if codes is not None:
            return np.asarray(codes, dtype=np.float32)
    x = torch.from_numpy(np.ascontiguousarray(v)).to(device)
    if w is None:
        return codec.encode(x).cpu().numpy()
    return encode_truncated(codec, x, torch.from_numpy(w).to(device), shrink=shrink).cpu().numpy()


def _shrink_kw(hook: Any, shrink: float) -> dict:
    """``{"shrink": shrink}`` where it is > 0 and the codec's ``encode_truncated`` hook takes it, else ``{}``
    (a plugin written before the keyword still gets its three arguments)."""
    if not shrink > 0:
        return {}
    return {"shrink": float(shrink)} if "shrink" in inspect.signature(hook).parameters else {}


def encode_truncated(codec: Codec, x: Any, w: Any, rounds: int = TRUNCATION_ROUNDS, shrink: float = 0.0) -> Any:
    """Weighted codes ``(N, k)`` of normalised blocks ``x`` ``(N, 16, 16, 16)`` (tensor) under error weights
    ``w`` (same shape), for a reader that truncates what it decodes to ``[0, 1]`` (``[d_min, d_max]``).

    A voxel stored at a bound (``d_max``: observed free space, most of a fused block's observed voxels; or
    ``d_min``) and decoded beyond it reads back exact, so the fit should not spend code on pulling it in. The
    error a reader sees is ``sum_j w_j (clip(decode(c))_j - x_j)^2``: convex, one-sided at those voxels. An
    active-set iteration solves it: decode, give weight 0 to the bound voxels decoded beyond their bound,
    refit the blocks whose set changed; ``rounds`` refits at most (each one weighted encode of the blocks
    still changing). Measured on the held-out half of a fused kitchen, pca-64 (docs/surface.md): Chamfer-L1
    5.29 mm with none, 5.15 / 5.08 / 5.02 mm after 1 / 2 / 3.

    A codec declaring the capability ``encode_truncated`` MAY compute the same (or solve the same problem
    otherwise, no worse in total: spec/codec-plugins.md section 4) in one pass of its own
    (:meth:`Codec.encode_truncated`; None where it does not apply: the pca codec's compiled pass on the CPU,
    spec/codec-plugins.md section 4a).

    ``shrink`` > 0 (the variable-rate writer's at low rates, :data:`sdfcodec.core.varrate.SHRINK`):
    the hook adds a ridge towards the zero code of that relative weight (times the mean weight) where it takes
    the keyword; the batched loop below does not, and solves the problem without it."""
    if "encode_truncated" in capabilities(codec) and (codes := codec.encode_truncated(
            x, w, rounds, **_shrink_kw(codec.encode_truncated, shrink))) is not None:
        return codes
    codes = codec.encode(x, weights=w)
    n = len(x)
    xf, wf = x.reshape(n, -1), w.reshape(n, -1)
    top, bot = (xf >= 1 - 1e-6) & (wf > 0), (xf <= 1e-6) & (wf > 0)
    todo = torch.nonzero((top | bot).any(dim=1)).flatten()
    active = torch.zeros_like(top)
    for _ in range(rounds):
        if not len(todo):
            break
        d = codec.decode(codes[todo]).reshape(len(todo), -1)
        now = (top[todo] & (d >= 1)) | (bot[todo] & (d <= 0))
        changed = (now != active[todo]).any(dim=1)
        todo, now = todo[changed], now[changed]
        if not len(todo):
            break
        active[todo] = now
        codes[todo] = codec.encode(x[todo], weights=torch.where(now, 0.0, wf[todo]).reshape(x[todo].shape))
    return codes


def fit_codec(codec: Codec, v: np.ndarray, observed: np.ndarray | None, truncation: tuple[float, float],
              voxel_size: float, *, max_blocks: int, surface_weight: float = SURFACE_WEIGHT, seed: int = 0,
              log: Any = None) -> int:
    """Fit ``codec`` on the non-empty ones of normalised blocks ``v`` ``(N, 16, 16, 16)`` (at most
    ``max_blocks``, sampled with ``seed``) as a map writer will encode them: with the error weights of their
    observation ``observed`` (``(N, 16, 16, 16)`` bool, None: a dense volume, observed everywhere) when the
    codec learns from weights (:meth:`~sdfcodec.Codec.fit_weighted`), else on the blocks filled as
    :func:`encode_blocks` fills them for it. ``log(n)`` is called with the number of blocks before fitting;
    returns that number."""
    keep = ~(v >= 1 - 1e-6).reshape(len(v), -1).all(axis=1)
    if len(np.flatnonzero(keep)) > max_blocks:
        keep = np.sort(np.random.default_rng(seed).choice(np.flatnonzero(keep), max_blocks, replace=False))
    v, observed = v[keep], None if observed is None else observed[keep]
    if log is not None:
        log(len(v))
    w = error_weights(v, observed, truncation, voxel_size, surface_weight)
    if w is None:
        codec.fit(v)
    elif learns_weights(codec):
        codec.fit(v, weights=w)
    else:
        codec.fit(v if uses_weights(codec) else fill_unobserved(v, observed))
    return len(v)


def pack_mask(observed: np.ndarray) -> np.ndarray:
    """``(N, 16, 16, 16)`` bool -> ``(N, 512)`` uint8 (C-order voxels, most significant bit first)."""
    return np.packbits(np.asarray(observed, dtype=bool).reshape(len(observed), -1), axis=1)


def unpack_mask(rows: np.ndarray) -> np.ndarray:
    """``(N, 512)`` uint8 -> ``(N, 16, 16, 16)`` bool (the inverse of :func:`pack_mask`)."""
    # unpackbits gives bytes of 0 and 1: valid bools as they are, no converting copy
    return np.unpackbits(np.asarray(rows, dtype=np.uint8), axis=1).view(bool).reshape(len(rows), BLOCK, BLOCK, BLOCK)


def restore_unobserved(blocks: torch.Tensor, rows: np.ndarray, free: float) -> torch.Tensor:
    """Set the unobserved voxels of decoded ``blocks`` ``(n, 16, 16, 16)`` (any device) to ``free``, in place;
    ``rows`` ``(n, 512)`` uint8 packed masks. A batch of fully observed blocks (rows of 255) costs one pass over
    the rows; otherwise one in-place select over the batch (no gather and scatter of the partial blocks)."""
    if (rows != 255).any():
        observed = torch.from_numpy(unpack_mask(rows)).to(blocks.device)
        torch.where(observed, blocks, torch.tensor(free, dtype=blocks.dtype, device=blocks.device), out=blocks)
    return blocks


def restore_unobserved_voxels(reader: MapReader, vol: torch.Tensor, lo: np.ndarray, hi: np.ndarray,
                              free: float) -> torch.Tensor:
    """Set the unobserved voxels of ``vol``, the dense decode of voxels ``[lo, hi)`` (inside the grid) of the map
    ``reader`` opens, to ``free``, in place; a map without a mask is left as it is. For halo codecs: their
    context pass spreads values from observed voxels into unobserved ones after the core decode restored them,
    so the restore happens again on the final values (one read of the mask rows of the coded blocks there)."""
    mask = reader.observation_arrays()[1]
    if mask is None:
        return vol
    lo, hi = np.asarray(lo), np.asarray(hi)
    box = reader.block_range(tuple(zip(lo.tolist(), hi.tolist())))
    b0 = np.array([s.start for s in box], dtype=np.int64)
    coords = np.argwhere(reader.states_in(box) == BlockState.CODED) + b0
    rows = read_block_rows(reader, mask, coords)
    partial = (rows != 255).any(axis=1)
    for c, observed in zip(coords[partial], unpack_mask(rows[partial])):
        v0 = c * BLOCK
        a, b = np.maximum(v0, lo), np.minimum(v0 + BLOCK, hi)
        if np.any(b <= a):
            continue
        sub = vol[tuple(slice(int(x - l), int(y - l)) for x, y, l in zip(a, b, lo))]  # a view: filled in place
        seen = observed[tuple(slice(int(x - o), int(y - o)) for x, y, o in zip(a, b, v0))]
        sub.masked_fill_(torch.from_numpy(~seen).to(vol.device), free)
    return vol


def checked_mask_array(reader: MapReader) -> zarr.Array | None:
    """The observation mask of the map ``reader`` opens (a :class:`~sdfcodec.map.reader.MapReader`), its
    metadata checked against the header; None when the header lists no ``observation-mask``.

    Raises:
        FormatError: the header lists the mask but the array is missing, or has the wrong dtype, shape or chunks.
    """
    h = reader.header
    if any(e.name == PINNED_MASK_EXTENSION for e in h.extensions):  # stored at pinned voxels only (spec 6g)
        from .pinstore import PinnedMaskArray

        return PinnedMaskArray(reader)
    if not any(e.name == MASK_EXTENSION for e in h.extensions):
        return None
    arr = reader.member(MASK_ARRAY)
    if arr is None:
        raise FormatError(f"{reader.location}: map lists the observation mask but lacks array '{MASK_ARRAY}' (spec "
                          "section 6b); it is incomplete")
    cb = h.codes.chunk_blocks
    coded = any(e.name == CODED_MASK_EXTENSION for e in h.extensions)
    reader.check_array(arr, dtype=np.uint8, shape=(*h.grid_blocks, MASK_BYTES), chunks=(cb, cb, cb, MASK_BYTES),
                       mask_coded=coded)
    return arr


def read_block_rows(reader: MapReader, arr: zarr.Array, coords: np.ndarray) -> np.ndarray:
    """``(n, R)`` rows of blocks ``coords`` ``(n, 3)`` of a per-block array ``arr`` ``(Bx, By, Bz, R)`` (the mask,
    fusion weights), read through ``reader`` (a :class:`~sdfcodec.map.reader.MapReader`: its checked,
    concurrent reads), one read per chunk touched."""
    if hasattr(arr, "block_rows"):  # a pinned mask (sdfcodec.map.pinstore) decodes its rows from the codes
        return arr.block_rows(coords)
    out = np.empty((len(coords), arr.shape[3]), dtype=arr.dtype)
    if not len(coords):
        return out
    cb = np.asarray(arr.chunks[:3])
    keys, inverse = np.unique(coords // cb, axis=0, return_inverse=True)
    inverse = inverse.reshape(-1)
    sels = [tuple(slice(int(c) * b, min(int(c) * b + b, g)) for c, b, g in zip(k, cb, arr.shape)) for k in keys]
    for i, a in enumerate(reader.read_many(arr, [(*s, slice(None)) for s in sels])):
        rows = np.flatnonzero(inverse == i)
        out[rows] = a[tuple((coords[rows] - keys[i] * cb).T)]
    return out


def write_block_rows(arr: zarr.Array, coords: np.ndarray, rows: np.ndarray) -> None:
    """Write ``rows`` ``(n, R)`` of blocks ``coords`` ``(n, 3)`` into a per-block array ``arr`` ``(Bx, By, Bz, R)``:
    one read and one write per chunk touched (the inverse of :func:`read_block_rows`)."""
    cb = np.asarray(arr.chunks[:3])
    keys, inverse = np.unique(coords // cb, axis=0, return_inverse=True)
    inverse = inverse.reshape(-1)
    for i, k in enumerate(keys):
        box = tuple(slice(int(c) * b, min(int(c) * b + b, g)) for c, b, g in zip(k, cb, arr.shape))
        sel = np.flatnonzero(inverse == i)
        buf = np.asarray(arr[box])
        buf[tuple((coords[sel] - k * cb).T)] = rows[sel]
        arr[box] = buf


def store_mask_chunk(arr: zarr.Array, box: tuple[slice, ...], local: np.ndarray, rows: np.ndarray | None,
                     had: bool) -> None:
    """Write mask ``rows`` ``(n, 512)`` (None: fully observed) of the blocks at ``local`` inside chunk ``box``
    (read first only when the chunk ``had`` coded blocks)."""
    shape = [s.stop - s.start for s in box]
    buf = np.asarray(arr[box]) if had else np.full((*shape, MASK_BYTES), 255, dtype=np.uint8)
    buf[tuple(local.T)] = 255 if rows is None else rows
    arr[box] = buf


def read_observed(reader: MapReader, coords: np.ndarray) -> np.ndarray:
    """``(n, 16, 16, 16)`` bool: which voxels of blocks ``coords`` ``(n, 3)`` (checked, inside the grid) were
    observed: fusion weight > 0 where the map stores weights, else its observation mask, else all of them."""
    arr, mask = reader.observation_arrays()
    if arr is not None:
        return (read_block_rows(reader, arr, coords) > 0).reshape(len(coords), BLOCK, BLOCK, BLOCK)
    if mask is not None:
        return unpack_mask(read_block_rows(reader, mask, coords))
    return np.ones((len(coords), BLOCK, BLOCK, BLOCK), dtype=bool)


def read_observation(reader: MapReader, coords: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
    """``(observed, known)`` of blocks ``coords`` ``(n, 3)``: :func:`read_observed`, and where it tells what the
    cameras saw, ``(n, 16, 16, 16)`` bool, or None where it does everywhere (weights, an exact mask, none). A
    pinned mask (spec 6g) stores its bits at the pinned voxels only, the corners of the cells whose decode may
    change sign: every other voxel reads observed by the format's rule, behind a surface too, where the cameras
    saw nothing and the decode is the codec's guess (what weighs the observation, such as a search's scores,
    should leave those voxels out). Both from one decode of each chunk of the mask."""
    arr, mask = reader.observation_arrays()
    if arr is None and mask is not None and hasattr(mask, "rows_with_pins"):
        rows, pins = mask.rows_with_pins(coords)
        return unpack_mask(rows), unpack_mask(pins)
    return read_observed(reader, coords), None


def finish_mask(group: zarr.Group, tmp: Path, touched: set[tuple[int, int, int]], coded: bool = False
                ) -> list[Extension]:
    """At a writer's commit: give the mask array of the map being written in ``tmp`` (its ``group``) its final
    compressor chain (:func:`~sdfcodec.map.format.mask_compressors`) and recompress with it the chunks this writer
    wrote (``touched``: chunk indices along the block axes), which it wrote at the fast level. Chunks it did not
    write (an update's, hard links to the version readers hold) keep their bytes: Blosc frames decode whatever
    level made them. ``coded``: the context-coded chain instead (extension ``coded-observation-mask``): the
    writer of a new map only (``touched`` then holds every chunk it has). Returns the extensions the header lists."""
    meta_path = Path(tmp) / MASK_ARRAY / "zarr.json"
    meta = json.loads(meta_path.read_bytes())
    final = [c.to_dict() for c in mask_compressors(coded=coded)]
    final = final if coded else meta["codecs"][:1] + final
    if meta["codecs"] != final:
        rows = {key: np.asarray(zarr.open_array(group.store, path=MASK_ARRAY, mode="r")[_box(key, meta)])
                for key in sorted(touched)} if coded else {}  # read through the old chain before it changes
        meta["codecs"] = final
        part = meta_path.with_name("zarr.json.part")
        part.write_text(json.dumps(meta, indent=2))
        os.replace(part, meta_path)  # a new file: an update's zarr.json may be a link into the previous version
    else:
        rows = {}
    arr = zarr.open_array(group.store, path=MASK_ARRAY, mode="r+")
    for key in sorted(touched):
        box = _box(key, meta)
        arr[box] = rows[key] if key in rows else np.asarray(arr[box])
    return [Extension(name=n, required=True) for n in (MASK_EXTENSION, CODED_MASK_EXTENSION)[:1 + coded]]


def _box(key: tuple[int, int, int], meta: dict) -> tuple[slice, ...]:
    """The block box of mask chunk ``key`` of the array whose metadata is ``meta``."""
    cb, shape = meta["chunk_grid"]["configuration"]["chunk_shape"], meta["shape"]
    return chunk_box(key, cb, shape)
