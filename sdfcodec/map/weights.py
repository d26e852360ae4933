"""Fusion weights in a map (spec/map-format.md, section 6a): stored as float16 counts in lossless maps, dropped
from lossy ones unless asked, then quantised to uint8 counts.

A fused block's weights (observation counts per voxel) are 1.7 KB per coded block of the 500-frame kitchen map
as float16 and 1.3-1.4 KB as uint8 (docs/side-information.md): ten times a 128:1 block's budget. What a lossy
map needs of them, which voxels were observed, its observation mask keeps in 65 B (section 6b). So a writer
whose codec is lossy drops them at commit unless ``keep_weights=True`` (``--keep-weights``), and then stores
them quantised (:func:`quantise_weights`) under the optional extension ``quantised-fusion-weights``; the
lossless ``raw`` codec keeps its float16 weights as before, and a map with metric codes (spec 4f: ``sdfcodec
import``, ``exact=True``) keeps them as float32, exactly, under the optional extension
``float32-fusion-weights``. Online fusion writes the weights while it fuses (a block paged back in resumes from
them) and the choice is applied when the map is committed.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import zarr

from ..core._atomic import remove_tree
from ..errors import FormatError
from ..core.header import FLOAT32_WEIGHTS_EXTENSION, Extension
from .format import compressors

if TYPE_CHECKING:
    from ..codec import Codec
    from .reader import MapReader

__all__ = ["WEIGHTS_ARRAY", "WEIGHTS_EXTENSION", "QUANT_WEIGHTS_EXTENSION", "WEIGHT_LEVELS", "weights_mode",
           "quantise_weights", "stored_weights", "finish_weights", "checked_weights_array"]

WEIGHTS_ARRAY = "weights"
WEIGHTS_EXTENSION = "fusion-weights"
QUANT_WEIGHTS_EXTENSION = "quantised-fusion-weights"
#: The largest stored uint8 count: weights beyond it read as it.
WEIGHT_LEVELS = 255
#: Blocks quantised at once when a writer turns its float16 weights into uint8 ones: 16 MiB of float32.
_SLAB = 1024


def weights_mode(codec: Codec, keep_weights: bool | None, exact: bool = False) -> str:
    """What a writer of ``codec`` does with the fusion weights it is given: ``"float16"`` (stored as written: the
    lossless ``raw`` codec, by default or when kept), ``"float32"`` (the same, in a map with metric codes:
    ``exact``), ``"uint8"`` (a lossy codec asked to keep them: quantised at commit) or ``"drop"`` (a lossy codec
    by default, or anyone told ``keep_weights=False``)."""
    lossless = codec.codec_id == "raw"
    if keep_weights is None:
        keep_weights = lossless
    if not keep_weights:
        return "drop"
    return ("float32" if exact else "float16") if lossless else "uint8"


def stored_weights(w: np.ndarray, dtype: Any) -> np.ndarray:
    """Weights ``w`` (float32, non-negative) as a ``weights`` array of ``dtype`` stores them: uint8 counts
    (:func:`quantise_weights`), float32 as they are, float16 exact to 2048 frames and saturating at its maximum
    beyond (spec section 6a)."""
    if dtype == np.uint8:
        return quantise_weights(w)
    return np.asarray(w, np.float32) if dtype == np.float32 else np.minimum(w, 65504).astype(np.float16)


def quantise_weights(w: np.ndarray) -> np.ndarray:
    """uint8 counts of fusion weights ``w`` (any shape, non-negative): ``q = clip(round(w), 1, 255)`` where
    ``w > 0`` and 0 where ``w = 0``, so ``q > 0`` exactly where ``w > 0`` (the observation is kept bit for bit),
    ``|q - w| <= 0.5`` for ``0.5 <= w <= 255.5``, ``q = 1`` below and ``255`` above (spec section 6a)."""
    w = np.asarray(w, dtype=np.float32)
    q = np.clip(np.rint(w), 1, WEIGHT_LEVELS).astype(np.uint8)
    q[w <= 0] = 0
    return q


def finish_weights(group: zarr.Group, tmp: Path, mode: str, grid: tuple[int, int, int]) -> Extension | None:
    """At a writer's commit: apply ``mode`` (:func:`weights_mode`) to the ``weights`` array of the map being
    written in ``tmp`` (its ``group``, block grid ``grid``); the extension to list, None when none is stored."""
    if WEIGHTS_ARRAY not in group:
        return None
    arr = group[WEIGHTS_ARRAY]
    if mode == "drop":
        # the temporary directory is the writer's own (an update's files are hard links: unlinking them leaves
        # the version readers hold as it is)
        remove_tree(Path(tmp) / WEIGHTS_ARRAY)
        return None
    if tuple(arr.shape[:3]) != grid:
        arr.resize((*grid, arr.shape[3]))
    if mode == "uint8" and arr.dtype != np.uint8:
        q = group.create_array(WEIGHTS_ARRAY + ".q", shape=arr.shape, dtype="uint8", fill_value=0, chunks=arr.chunks,
                               compressors=compressors(), dimension_names=["bx", "by", "bz", "voxel"])
        for i in range(0, arr.shape[0], arr.chunks[0]):  # one slab of chunks at a time
            q[i:i + arr.chunks[0]] = quantise_weights(arr[i:i + arr.chunks[0]])
        remove_tree(Path(tmp) / WEIGHTS_ARRAY)
        (Path(tmp) / (WEIGHTS_ARRAY + ".q")).rename(Path(tmp) / WEIGHTS_ARRAY)
        return Extension(name=QUANT_WEIGHTS_EXTENSION, required=False)
    name = {np.dtype(np.uint8): QUANT_WEIGHTS_EXTENSION, np.dtype(np.float32): FLOAT32_WEIGHTS_EXTENSION}
    return Extension(name=name.get(np.dtype(arr.dtype), WEIGHTS_EXTENSION), required=False)


def checked_weights_array(reader: MapReader) -> zarr.Array | None:
    """The fusion weights of the map ``reader`` opens (a :class:`~sdfcodec.map.reader.MapReader`), checked: float16
    under ``fusion-weights``, uint8 counts under ``quantised-fusion-weights``, float32 under
    ``float32-fusion-weights``; None when none is listed or the array is absent (the extensions are optional)."""
    names = {e.name for e in reader.header.extensions}
    kinds = {WEIGHTS_EXTENSION: np.float16, QUANT_WEIGHTS_EXTENSION: np.uint8, FLOAT32_WEIGHTS_EXTENSION: np.float32}
    listed = [n for n in kinds if n in names]
    if len(listed) > 1:
        raise FormatError(f"{reader.location}: header lists {' and '.join(repr(n) for n in listed)} (spec section "
                          "6a allows one); the map is corrupted")
    dtype = kinds[listed[0]] if listed else None
    arr = reader.member(WEIGHTS_ARRAY) if dtype is not None else None
    if arr is not None:
        reader.check_array(arr, dtype=dtype, shape=(*reader.header.grid_blocks, 4096))
    return arr
