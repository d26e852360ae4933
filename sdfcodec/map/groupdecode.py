"""The decode of one group of codes, what every map reader's pipeline runs per group (:meth:`MapReader.decode_codes`):
the codec's core decode with the scaling to metres folded in, the corruption check, the truncation to
``[d_min, d_max]``, an observation mask's free space, a residual stage, and (``placer``) the placing of the decoded
blocks to their destination, e.g. a dense volume.

The plain path is one pass per step over the group's 16 KiB per block. When nothing but the truncation follows
the decode (no mask, no residual) and the codec's bound proves the output finite, the group goes through the
codec's ``decode_tiles`` hook instead: a codec that overrides it (PCA) decodes, truncates and places
cache-sized tiles on every core: the clip and the placing read the tile from cache, not memory
(:mod:`sdfcodec.core.tiling` gives the measurements).
"""

from __future__ import annotations

import math
from contextlib import contextmanager
from typing import TYPE_CHECKING, Iterator

import numpy as np

from ..core._lazy import lazy_module
from ..core._validate import BLOCK, empty
from ..codec import decodes_tiles, plugin_calls
from ..core.header import PINNED_MASK_EXTENSION
from ..errors import InvalidValueError
from .format import DECODE_LIMIT, check_decoded
from .metric import decode_affine
from .observed import read_block_rows, restore_unobserved
from .placement import BlockPlacer
from .residual import apply_residual

if TYPE_CHECKING:
    from .reader import MapReader

torch = lazy_module("torch")  # imported on first use: reading a header never needs it

__all__ = ["decode_group", "float32_products"]


@contextmanager
def float32_products(on: bool = True) -> Iterator[None]:
    """torch's float32 matrix products in full float32 while inside (``on``): a pinned mask's pins (spec 6g) are
    proven against a true float32 decode, and ``torch.set_float32_matmul_precision("high")`` or ``"medium"`` (a
    user's, for speed elsewhere) would let TF32 or bfloat16 units decode, whose error the bound does not cover.
    The user's setting is restored on leaving."""
    was = torch.get_float32_matmul_precision() if on else "highest"
    if was == "highest":
        yield
        return
    torch.set_float32_matmul_precision("highest")
    try:
        yield
    finally:
        torch.set_float32_matmul_precision(was)


def decode_group(reader: MapReader, codes: torch.Tensor, **kw) -> torch.Tensor | None:
    """:meth:`MapReader.decode_codes` (see there): :func:`_decode_group`, in full float32 for a map whose mask is
    pinned (:func:`float32_products`)."""
    with float32_products(any(e.name == PINNED_MASK_EXTENSION for e in reader.header.extensions)):
        return _decode_group(reader, codes, **kw)


def _decode_group(reader: MapReader, codes: torch.Tensor, *, metres: bool, coords: np.ndarray | None = None,
                 mask_rows: np.ndarray | None = None, residual: bool = True,
                 residual_rows: np.ndarray | None = None, out: torch.Tensor | None = None,
                 placer: BlockPlacer | None = None, refine: bool = True,
                 refine_rows: np.ndarray | None = None, unmasked: bool = False) -> torch.Tensor | None:
    """:meth:`MapReader.decode_codes` (see there). With ``placer``, the decoded blocks go into its volume (from
    several threads at once, for disjoint blocks): ``out`` is only scratch memory then, and None is returned.
    ``unmasked``: unobserved voxels keep their decode (the caller restores them: a pinned mask is decoded from
    this decode, :meth:`sdfcodec.map.pinstore.PinnedMaskArray.unmask`)."""
    codec = reader.codec
    d_min, d_max = reader.truncation
    scale, offset = decode_affine(reader.header.codes, (d_min, d_max), metres)  # metric codes: no scaling (4f)
    mask = None if unmasked else reader.observation_arrays()[1]
    res = reader.residual_rows_array(codes.shape[1]) if residual else None
    ref = getattr(reader, "refinement", None) if refine else None  # a surface refinement (spec 6h)
    if (mask is not None or res is not None or ref is not None) and coords is None:
        raise InvalidValueError(f"{reader.location} has an observation mask or a residual: decode_codes needs the "
                                "blocks' coords")
    if placer is not None and coords is None:
        raise InvalidValueError("decode_codes needs the blocks' coords to place them")
    with plugin_calls(codec, "bounding its decode"):
        bound = codec.decode_bound(codes)
    proven = bound is not None and math.isfinite(bound) and bound <= DECODE_LIMIT
    tiles = placer is not None or decodes_tiles(codec)
    if metres and proven and mask is None and res is None and ref is None and len(codes) and tiles:
        # nothing follows the truncation: decode, clip and place tile by tile (codec.decode_tiles; a codec keeping
        # the default, only to be placed: then it is the plain path below, in one call)
        with plugin_calls(codec, "decoding"):  # a plugin's exception is one line naming it, as on every path
            if placer is not None:  # each tile placed from its core's cache
                _decode_placed(codec, codes, coords, placer, scale, offset, (d_min, d_max), out)
                return None
            out = empty((len(codes), BLOCK, BLOCK, BLOCK), codes.device) if out is None else out
            codec.decode_tiles(codes, scale, offset, (d_min, d_max), None, out)
        return out
    v = codec.decode_core(codes, scale=scale, offset=offset, out=out)
    if not proven:
        # the values judged in the map's own units, whatever the stored codes' (metres or normalised)
        unit, zero = (d_max - d_min, d_min) if metres else (1.0, 0.0)
        v = check_decoded(v, scale=unit, offset=zero, coords=coords, location=reader.location,
                          codec_id=reader.header.codec.id, chunk_blocks=reader.header.codes.chunk_blocks)
    if metres:  # a TSDF lies in [d_min, d_max]; a lossy decode may overshoot it (after the corruption check)
        if v.device.type == "cpu":  # numpy's: torch's threaded clamp after a numpy product waits for BLAS threads
            a = v.numpy()
            np.clip(a, d_min, d_max, out=a)
        else:
            v = v.clamp_(d_min, d_max)
    if ref is not None and len(codes):  # corrections in metres, then the truncation again (spec 6h)
        add = torch.from_numpy(ref.rows(coords) if refine_rows is None else refine_rows).to(v.device).view(v.shape)
        v = v.add_(add if metres else add / (d_max - d_min))
        if metres:
            v = v.clamp_(d_min, d_max)
    if mask is not None:
        rows = read_block_rows(reader, mask, coords) if mask_rows is None else mask_rows
        # unobserved voxels read d_max, whatever the codec made of them (spec section 6b)
        v = restore_unobserved(v, rows, d_max if metres else 1.0)
    if res is not None:
        step = reader.header.residual.step / (1.0 if metres else d_max - d_min)
        rows = reader.read_residual(coords) if residual_rows is None else residual_rows
        v = apply_residual(v, rows, step, *((d_min, d_max) if metres else (0.0, 1.0)))
    if placer is not None:
        placer.place(coords, v)
        return None
    return v


def _decode_placed(codec, codes: torch.Tensor, coords: np.ndarray, placer: BlockPlacer, scale: float,
                   offset: float, clip: tuple[float, float], scratch: torch.Tensor | None) -> None:
    """Decode, clip and place a group: tiles decoded in a core's cache and copied from there to their places
    (``decode_tiles``; a codec keeping the default decodes the group whole, into ``scratch`` when given, the
    reader's reused buffer). Measured: writing runs of whole blocks straight into the volume with one batched
    product per run (a (r, 65) x (65, 16) product per voxel column) measured 0.4-0.8x as fast as this (medians,
    interleaved, 2 loaded cores)."""
    # rows in the volume's C order: a group of whole chunk columns then holds each row of blocks along z in
    # one piece, copied as runs of contiguous voxels as long as the region's z extent (chunk order gave runs of
    # one chunk's 16 blocks: the copy ran 1.4x slower)
    order = np.lexsort((coords[:, 2], coords[:, 1], coords[:, 0]))
    if np.any(order[1:] < order[:-1]):
        coords = coords[order]
        # on the CPU numpy's gather: torch's threaded one waits on the BLAS threads (19 -> 5 ms a 65k-block map)
        codes = (torch.from_numpy(np.take(codes.numpy(), order, axis=0)) if codes.device.type == "cpu"
                 else codes[torch.from_numpy(order).to(codes.device)])
    buf = None if scratch is None or decodes_tiles(codec) else scratch[:len(codes)]
    if codes.device.type == "cpu":  # the runs worked out once for the group, each tile copying its share
        plan = placer.plan(coords)
        codec.decode_tiles(codes, scale, offset, clip, plan.place, buf)
    else:
        codec.decode_tiles(codes, scale, offset, clip, lambda a, b, tile: placer.place(coords[a:b], tile), buf)
