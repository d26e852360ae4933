"""What a map's arrays and inputs must look like (spec/map-format.md): array metadata checks, the allowed Zarr
codecs and the compressors a writer uses, the codec-state digest, the code layout of a new map, and the checks
on volumes, block coordinates and codes that readers and writers (the dask writer too) share.

Pure functions of their arguments: nothing here opens or reads a store.
"""

from __future__ import annotations

import json
import math
import os
import warnings
from pathlib import Path
from typing import TYPE_CHECKING, Any, Sequence

import numpy as np
import zarr
from zarr.codecs import BloscCodec, BytesCodec, Crc32cCodec, GzipCodec, ShardingCodec, ZstdCodec

from ..core._lazy import lazy_module
from ..core.blocks import DECODE_LIMIT, check_truncation  # DECODE_LIMIT: defined beside the truncation check
from ..codec import FINITE_BOUND, Codec  # FINITE_BOUND: defined where the codec checks its own decodes
from ..errors import DTypeError, FormatError, InvalidValueError, SDFCodecWarning, ShapeError
from ..core.header import CodeQuantisation, CodesSpec, FieldCompression
from ..core.quantize import dequantise_step, dequantize_codes
from .field import FIELD_CHUNK_BLOCKS, check_field_pipeline
from .io.shards import check_sharding
from .maskcoder import MaskANS

if TYPE_CHECKING:
    from .reader import MapReader

torch = lazy_module("torch")  # imported on first use: info, codecs, verify of a header never need it

__all__ = ["region_voxels", "DEFAULT_MAX_DECODE_BYTES", "CODE_DTYPES", "ALLOWED_ZARR_CODECS", "MIN_CHUNKS_PER_READ",
           "BYTES_PER_CHUNK", "EMPTY_EPS", "FINITE_BOUND", "DECODE_LIMIT", "Region", "compressors",
           "code_layout", "check_array_metadata", "check_stream_array", "unstored_suspects", "check_coords",
           "check_volume", "warn_clipped", "check_codes",
           "code_values", "free_space", "is_dask_array", "decoded_range", "check_decoded", "code_compressors",
           "QUANT_CLEVEL", "mask_compressors", "compact_documents", "root_document", "field_compression_of"]

#: A read that would allocate more than this many bytes at once (a decoded region, a dense read of codes, the
#: block-state array, one chunk, the codec state) is refused unless the caller raises the limit, so a hostile
#: or mistaken header cannot make a reader allocate without bound.
DEFAULT_MAX_DECODE_BYTES = 8 << 30
#: The Zarr codecs a map's arrays may use (spec section 4): anything else (numcodecs.* such as pickle,
#: variable-length types; sharding except around these in the ``codes`` of a map that says so, section 4d) is
#: refused before a chunk is read.
ALLOWED_ZARR_CODECS = (BytesCodec, BloscCodec, ZstdCodec, GzipCodec, Crc32cCodec)
#: A read may touch at most max(MIN_CHUNKS_PER_READ, max_decode_bytes // BYTES_PER_CHUNK) chunks.
MIN_CHUNKS_PER_READ, BYTES_PER_CHUNK = 64, 4096
EMPTY_EPS = 1e-6  # a normalised voxel >= 1 - eps is free space
#: How codes may be stored (spec sections 4 and 4a).
CODE_DTYPES = ("float32", "float16", "int8", "int16")
#: Blosc zstd level of int16 (step-quantised) codes: on the kitchen map level 5 stores 1 % fewer bytes and level
#: 9 4 % fewer, but level 9 halves the transcode speed and level 5 costs 1.3-1.8x level 3's compress time
#: (docs/rate-distortion.md, "Quantised codes"); the issue asks for >= 0.8x the speed of float32 codes
QUANT_CLEVEL = 3
#: ``((x0, x1), (y0, y1), (z0, z1))``: half-open voxels, or half-open metres (the voxels whose centres lie inside).
Region = Sequence[Sequence[float]]


def compressors() -> list:
    """The compressor chain of every array a map writes: Blosc/zstd, then a CRC32C checksum (spec section 4)."""
    return [BloscCodec(cname="zstd", clevel=3, shuffle="shuffle"), Crc32cCodec()]


def code_compressors(dtype: str) -> list:
    """The chain of the ``codes`` array: :func:`compressors`, except for int16 (step-quantised) codes, whose
    small integers bit shuffle then zstd code closer to their entropy (byte shuffle leaves their high bytes'
    zeros interleaved: the kitchen map's pca-128 codes at step 0.32 take 115.8 B per coded block with byte
    shuffle, 87.8 with bit shuffle, both zstd level 3)."""
    if dtype == "int16":
        return [BloscCodec(cname="zstd", clevel=QUANT_CLEVEL, shuffle="bitshuffle"), Crc32cCodec()]
    return compressors()


def root_document(attributes: dict[str, Any]) -> bytes:
    """The root ``zarr.json`` of a map whose header is ``attributes`` (the ``sdfcodec`` object), as
    :func:`compact_documents` stores it."""
    return _compact({"attributes": {"sdfcodec": attributes}, "zarr_format": 3, "node_type": "group"})


def _compact(doc: Any) -> bytes:
    if isinstance(doc, dict) and doc.get("node_type") in ("array", "group"):
        # both OPTIONAL in Zarr v3 and empty in every map array (and the codec group): 40 bytes a document, which
        # readers never miss
        doc = {k: v for k, v in doc.items() if not (k in ("attributes", "storage_transformers") and not v)}
        if doc.get("node_type") == "array":
            # Zarr v3 defaults, spelt out by zarr-python: the default encoding's separator is "/" and dimension
            # names are OPTIONAL labels no reader uses (spec section 4): 32 + 46 bytes a document
            doc.pop("dimension_names", None)
            if doc.get("chunk_key_encoding") == {"name": "default", "configuration": {"separator": "/"}}:
                doc["chunk_key_encoding"] = {"name": "default"}
    return json.dumps(doc, separators=(",", ":")).encode()


def compact_documents(root: str | Path, *, root_doc: bool = False) -> None:
    """Rewrite the Zarr documents of the map being written in ``root`` as compact JSON: its arrays'
    ``zarr.json`` (the root's too with ``root_doc``). zarr-python indents them, 40 % of their bytes, and on a
    small lossy map the documents are a fifth of it (docs/side-information.md); any JSON reader reads both.
    Each is written as a new file (an update's may be a hard link into the version readers hold)."""
    root = Path(root)
    # the arrays' and an embedded codec state's (codec/NAME/zarr.json); no walk through the chunk directories
    docs = [*root.glob("*/zarr.json"), *root.glob("codec/*/zarr.json")]
    for path in [root / "zarr.json"] if root_doc else docs:
        raw = path.read_bytes()
        data = _compact(json.loads(raw))
        if data != raw:
            part = path.with_name("zarr.json.part")
            part.write_bytes(data)
            os.replace(part, path)


def mask_compressors(final: bool = True, coded: bool = False) -> list:
    """The chain of the observation mask ``observed``: packed bits gain nothing from a byte shuffle; zstd level 9
    of Blosc stores the 500-frame kitchen map's mask (pca-64 int8) in 65.3 B per coded block against 73.8 at level
    5 and 84.1 with bit shuffle (docs/side-information.md); readers decode any allowed Blosc settings, so old
    readers read it. Level 9 writes 13x slower than 5 (medians of 5, interleaved), so a writer writes its mask
    chunks at level 5 (``final=False``: online fusion rewrites them at every page-out) and recompresses the
    chunks it wrote once, at commit (:func:`sdfcodec.map.observed.finish_mask`). ``coded`` (with ``final``): the
    whole chain of a context-coded mask (extension ``coded-observation-mask``, :mod:`sdfcodec.map.maskcoder`),
    which replaces the ``bytes`` codec too."""
    if coded and final:
        return [MaskANS(), Crc32cCodec()]
    return [BloscCodec(cname="zstd", clevel=9 if final else 5, shuffle="noshuffle"), Crc32cCodec()]


def code_layout(codec: Codec, dtype: str, chunk_blocks: int | None, chunk_code: int | None,
                quantisation: CodeQuantisation | None = None) -> CodesSpec:
    """The ``codes`` layout of a new map for ``codec``: chunk shape and prefix levels (defaults when None), and
    the step and offset of int16 codes."""
    size = codec.code_size
    for name, value, top in (("chunk_blocks (--chunk-blocks)", chunk_blocks, 256), ("chunk_code", chunk_code, None)):
        if value is not None and (isinstance(value, bool) or not isinstance(value, (int, np.integer))
                                  or not 1 <= value <= (top or value)):
            raise InvalidValueError(f"{name} must be a whole number of {'blocks per axis' if top else 'code elements'}"
                                    f" from 1{f' to {top}' if top else ''} (e.g. 8 or 16), got {value!r}")
    fc = field_compression_of(codec, dtype)
    if fc is not None and chunk_blocks is None:
        chunk_blocks = FIELD_CHUNK_BLOCKS  # SZ3's predictor gains from larger fields (sdfcodec.map.field)
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
                     prefix_ordered=codec.prefix_ordered, levels=levels, quantisation=quantisation,
                     field_compression=fc)


def field_compression_of(codec: Codec, dtype: str = "float32") -> FieldCompression | None:
    """The header's ``codes.field_compression`` for ``codec`` (its :meth:`~sdfcodec.Codec.field_compression`
    hook), checked: voxel codes stored as float32. None when the codec stores plain codes."""
    fc = codec.field_compression()
    if fc is None:
        return None
    if codec.code_size != 4096 or dtype != "float32":
        raise InvalidValueError(f"codec {codec.codec_id!r} asks for field compression, which stores float32 voxel "
                                f"codes (code size 4096); got code size {codec.code_size}, code dtype {dtype!r}")
    try:
        return FieldCompression(**fc)
    except Exception as e:  # noqa: BLE001 - pydantic's ValidationError: name the codec and the setting
        first = e.errors()[0] if hasattr(e, "errors") else {"loc": (), "msg": str(e)}
        where = ".".join(str(p) for p in first["loc"])
        raise InvalidValueError(f"codec {codec.codec_id!r} asks for an invalid field compression {fc!r}: {where} "
                                f"{first['msg']} (max_error is in normalised units, 1 = d_max - d_min; at most "
                                "half the truncation range)") from e


def check_array_metadata(arr: zarr.Array, where: str, *, dtype: Any = None, shape: tuple | None = None,
                         chunks: tuple | None = None, zero_fill: bool = False, field: FieldCompression | None = None,
                         shards: tuple | None = None, mask_coded: bool = False) -> tuple[int, bool, int]:
    """Validate an array's metadata against the spec *before* reading from it (``where`` names it in errors).

    Returns:
        ``(chunk_bytes, blosc_frame, per_object)``: the decoded size of one chunk, whether a stored chunk is one
        Blosc frame followed by its CRC32C (the writers' chain; then the frame can be checked unread,
        :class:`~sdfcodec.map.io.stores.GuardStore`), and the chunks one stored object holds (1; a shard's
        chunks when the array is sharded).

    ``field``: the header's ``codes.field_compression`` when ``arr`` is a field-compressed ``codes`` array (spec
    section 4c): its chain must then be exactly SZ3 and CRC32C; anywhere else the SZ3 codec is refused.
    ``mask_coded``: ``arr`` is the mask of a map listing ``coded-observation-mask`` (section 6e): its chain must
    then be exactly ``sdfcodec.mask-ans`` and CRC32C; anywhere else that codec is refused.
    """
    try:
        dt = np.dtype(arr.dtype)
        codecs = tuple(arr.metadata.codecs)
        ch = tuple(int(c) for c in arr.chunks)
        fill = arr.metadata.fill_value
    except Exception as e:  # noqa: BLE001 - irregular chunk grids, data types numpy lacks...
        raise FormatError(f"{where} has metadata this reader cannot use ({type(e).__name__}: {e})") from e
    per_object = 1
    if any(isinstance(c, ShardingCodec) for c in codecs):
        if len(codecs) != 1 or not isinstance(codecs[0], ShardingCodec):
            raise FormatError(f"{where} mixes sharding with other codecs; a sharded map array has the sharding "
                              "codec alone (spec section 4d)")
        codecs, per_object = check_sharding(codecs[0], arr, where, shards)
    elif shards is not None:
        raise FormatError(f"{where} is not sharded, but the header says its shards are {tuple(shards)} (section 4d)")
    if dt.kind not in "biuf" or dt.itemsize > 8:
        raise FormatError(f"{where} has data type {dt}; map arrays hold plain numbers only")
    if dtype is not None and dt != np.dtype(dtype):
        raise FormatError(f"{where} has data type {dt}, expected {np.dtype(dtype)}")
    if shape is not None and tuple(arr.shape) != tuple(shape):
        raise FormatError(f"{where} has shape {tuple(arr.shape)}, expected {tuple(shape)} (from the header)")
    if chunks is not None and ch != tuple(chunks):
        raise FormatError(f"{where} has chunks {ch}, expected {tuple(chunks)} (from the header)")
    if len(ch) != len(arr.shape) or any(c < 1 for c in ch):
        # Zarr accepts a zero chunk edge in metadata; every chunk index computation would divide by it
        raise FormatError(f"{where} has chunk shape {ch}; every chunk edge must be >= 1, one per axis")
    fielded = check_field_pipeline(codecs, field, where)
    ans = [c for c in codecs if isinstance(c, MaskANS)]
    if mask_coded and (len(codecs) != 2 or not isinstance(codecs[0], MaskANS)):
        raise FormatError(f"{where} must have the chain sdfcodec.mask-ans, crc32c: its map lists "
                          "coded-observation-mask (spec section 6e)")
    if ans and not mask_coded:
        raise FormatError(f"{where} uses the Zarr codec sdfcodec.mask-ans, which only the observation mask of a map "
                          "listing coded-observation-mask may use (spec section 6e)")
    fielded = fielded or bool(ans)
    bad = [getattr(c, "codec_name", None) or type(c).__name__ for c in codecs[fielded:]
           if not isinstance(c, ALLOWED_ZARR_CODECS)]
    if bad:
        raise FormatError(f"{where} uses Zarr codec(s) {bad}, which a map may not use (allowed: bytes, blosc, "
                          "zstd, gzip, crc32c; sharding around them only in sharded codes, section 4d)")
    if not codecs or not isinstance(codecs[-1], Crc32cCodec):
        raise FormatError(f"{where} has no crc32c checksum codec (spec section 4): it cannot be verified")
    for c in codecs:
        # maps are little-endian (spec section 9a): a big-endian re-declaration would decode garbage silently
        endian = getattr(getattr(c, "endian", None), "value", getattr(c, "endian", None))
        if isinstance(c, BytesCodec) and dt.itemsize > 1 and endian != "little":
            raise FormatError(f"{where} declares byte order {endian!r} in its bytes codec; map arrays are "
                              "little-endian (spec section 9a)")
    try:
        enc = arr.metadata.chunk_key_encoding
        enc_name, sep = getattr(enc, "name", None), getattr(enc, "separator", None)
    except Exception as e:  # noqa: BLE001
        raise FormatError(f"{where} has an unreadable chunk_key_encoding ({type(e).__name__}: {e})") from e
    if enc_name != "default" or sep != "/":
        # another encoding names other files: every stored chunk would read as missing (zeros)
        raise FormatError(f"{where} has chunk_key_encoding {enc_name!r} with separator {sep!r}; map arrays use "
                          "'default' with '/' (spec section 9a), so its stored chunks would not be found")
    # the chunk size is checked when reading, so that a small limit still lets a map open and say what is too big
    chunk_bytes = math.prod(ch) * dt.itemsize
    # a field-compressed codes array is filled with free space (1.0): SZ3 then sees no wall where a chunk at the
    # grid's edge is padded (spec section 4c)
    want = 1 if fielded else 0
    if zero_fill and not (np.ndim(fill) == 0 and np.asarray(fill) == want):
        raise FormatError(f"{where} has fill value {fill!r}; the spec requires {want}")
    # the writers' chain (bytes, blosc, crc32c): a stored chunk is one Blosc frame and its 4-byte checksum, so
    # the guard can check the frame's structure before the C decompressor trusts it
    blosc_frame = (len(codecs) == 3 and isinstance(codecs[0], BytesCodec) and isinstance(codecs[1], BloscCodec)
                   and isinstance(codecs[2], Crc32cCodec))
    return chunk_bytes, blosc_frame, per_object


def check_stream_array(reader: MapReader, arr: Any, name: str, section: str, lacks: str) -> None:
    """Check ``arr`` (``reader.member(name)``: None when absent), an array of one stream per chunk of codes (the
    codes', the pinned mask's, the refinement's: spec ``section``): shape ``(cgrid, L)``, uint8 rows of one chunk
    each, fill value 0, the codecs of section 9a and the size limit of every chunk read.

    Raises:
        FormatError: ``arr`` is None (``lacks``: what the map lists but lacks, the message's start) or does not
            have that form.
    """
    cb = reader.header.codes.chunk_blocks
    cgrid = tuple(-(-n // cb) for n in reader.header.grid_blocks)
    if arr is None:
        raise FormatError(f"{reader.location}: {lacks} (spec section {section}); it is incomplete")
    if len(arr.shape) != 4 or tuple(arr.shape[:3]) != cgrid:
        raise FormatError(f"{reader.location}: array '{name}' must have shape ({cgrid}, L), one row per chunk of "
                          f"codes; got {arr.shape}")
    reader.check_array(arr, dtype=np.uint8, shape=(*cgrid, arr.shape[3]), chunks=(1, 1, 1, arr.shape[3]),
                       zero_fill=True)


def is_dask_array(x: Any) -> bool:
    """True for a dask array (checked without importing dask)."""
    return type(x).__module__.split(".")[0] == "dask" and hasattr(x, "chunks") and hasattr(x, "dask")


def check_coords(coords: Any, grid: Sequence[int] | None = None) -> np.ndarray:
    """Block indices ``(N, 3)`` as int64: integers (or integral floats), non-negative, no duplicates, and inside
    ``grid`` (blocks per axis) when given (reads of existing blocks)."""
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
    if grid is not None and len(c) and np.any(c >= np.asarray(grid)):
        raise InvalidValueError(f"block coords outside the map's grid {tuple(grid)}")
    return c.astype(np.int64)


def unstored_suspects(coords: np.ndarray, codes: np.ndarray, params: np.ndarray | None,
                      spec: CodesSpec) -> list[tuple[str, tuple[int, ...], int]]:
    """The chunks that may be missing under coded blocks ``coords`` (n, 3) with stored ``codes`` (n, L) (and int8
    ``params`` (n, 2)): Zarr reads a chunk that is not stored as its fill value 0, so only a block with an
    all-zero stretch of one code chunk (or an all-zero ``[offset, scale]`` row) can lie in one (all 1.0, free
    space, in a field-compressed map: its fill value, spec section 4c). One pass over the codes. Returns
    ``(array name, chunk coords, row of a block in it)`` per suspect block."""
    if not len(coords):
        return []
    cb = spec.chunk_blocks
    fill = 1.0 if spec.field_compression is not None else 0
    zero = np.logical_and.reduceat(codes == fill, np.arange(0, codes.shape[1], spec.chunk_code), axis=1)
    out = [("codes", tuple(int(v) for v in coords[r] // cb) + (int(k),), int(r)) for r, k in zip(*np.nonzero(zero))]
    if params is not None:
        out += [("code_scale", tuple(int(v) for v in coords[r] // cb) + (0,), int(r))
                for r in np.flatnonzero((params == 0).all(axis=1))]
    return out


def free_space(v: np.ndarray) -> np.ndarray:
    """``(N,)`` bool: which normalised blocks ``(N, 16, 16, 16)`` hold only free space (stored as ``empty``)."""
    return (v >= 1.0 - EMPTY_EPS).reshape(len(v), -1).all(axis=1)


def check_codes(codes: np.ndarray) -> None:
    """Refuse NaN/Inf codes out of an encoder before they are stored."""
    if not np.isfinite(codes).all():
        raise InvalidValueError("the codec produced NaN/Inf codes; the input or the codec state is broken")


def code_values(codes: np.ndarray, params: np.ndarray | None,
                quant: CodeQuantisation | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Stored ``codes`` (N, k) as float32 values (dequantised with their ``(offset, scale)`` rows ``params``
    (N, 2) for int8 maps, with the header's step and offset ``quant`` for int16 ones: the first k of them, so
    a prefix dequantises alone), and ``(N,)`` bool: which rows are usable. A row is not when a value is
    NaN/Inf, or when its int8 scale is negative: writers store ``(max - min) / 254``, so only a corrupted
    (checksum-valid) chunk holds one, and it would decode mirrored codes within every bound."""
    if quant is not None:
        out = dequantise_step(codes, quant.step, quant.offset)
        return out, np.isfinite(out).all(axis=1)
    if params is None:
        out = codes.astype(np.float32, copy=False)
        return out, np.isfinite(out).all(axis=1)
    out = dequantize_codes(codes, params)
    return out, np.isfinite(out).all(axis=1) & ~(params[:, 1] < 0)


def check_volume(volume: Any, truncation: tuple[float, float], shape: tuple | None = None,
                 name: str = "volume", *, stacklevel: int = 3) -> np.ndarray:
    """A dense ``(X, Y, Z)`` volume (or an array of the given ``shape``) of metres as float32: floating point,
    finite, clipped to ``truncation`` with a warning (attributed ``stacklevel`` frames up: the caller's
    caller by default, i.e. the user code calling the writing method)."""
    if isinstance(volume, torch.Tensor):
        volume = volume.detach().cpu().numpy()
    v = np.asarray(volume)
    if v.dtype.kind != "f":
        raise DTypeError(f"{name} must be floating point metres, got dtype {v.dtype}")
    if shape is None and v.ndim != 3:
        raise ShapeError(f"{name} must be a dense (X, Y, Z) array of metres, got shape {v.shape}")
    if shape is not None and v.shape != shape:
        raise ShapeError(f"{name} must have shape {shape}, got {v.shape}")
    d_min, d_max = truncation
    check_truncation(d_min, d_max)  # before any clipping: a reversed range would clip everything, then be refused
    finite = np.isfinite(v)
    if not finite.all():
        raise InvalidValueError(f"{name} holds {int((~finite).sum())} NaN/Inf value(s); replace unobserved "
                                f"voxels with d_max (e.g. np.nan_to_num(v, nan={truncation[1]}))")
    outside = int(((v < d_min) | (v > d_max)).sum())
    if outside:
        warn_clipped(outside, v.size, (float(v.min()), float(v.max())), truncation, name, stacklevel=stacklevel)
        v = np.clip(v, d_min, d_max)
    return v.astype(np.float32, copy=False)


def warn_clipped(outside: int, size: int, span: tuple[float, float], truncation: tuple[float, float],
                 name: str = "volume", *, stacklevel: int = 3) -> None:
    """The warning of a write that clipped ``outside`` of ``size`` values of ``name`` to ``truncation``: how many,
    their share, the span the values had and the flag that keeps them (``stacklevel`` counted from the caller,
    as for :func:`warnings.warn`)."""
    (d_min, d_max), (lo, hi) = truncation, span
    warnings.warn(f"{outside} value(s) of {name} ({outside / max(size, 1):.1%}) lie outside the truncation "
                  f"[{d_min}, {d_max}] m and were clipped to it; the {name} spans [{lo:.4g}, {hi:.4g}] m: if "
                  f"that is its truncation, give it (--truncation {lo:.4g},{hi:.4g}; truncation= in Python)",
                  SDFCodecWarning, stacklevel=stacklevel + 1)


def decoded_range(scale: float, offset: float) -> tuple[float, float]:
    """``(lo, hi)``: the values a decode ``scale * normalised + offset`` may take before it is refused as absurd,
    :data:`DECODE_LIMIT` truncation ranges either side of ``offset`` (:func:`check_decoded`)."""
    return offset - DECODE_LIMIT * scale, offset + DECODE_LIMIT * scale


def check_decoded(v: torch.Tensor, *, scale: float, offset: float, coords: np.ndarray | None, location: str,
                  codec_id: str, chunk_blocks: int) -> torch.Tensor:
    """``v`` (n, 16, 16, 16) decodes (``scale * normalised + offset``) out of the codec, refused when they hold
    NaN/Inf or absurd values (beyond :data:`DECODE_LIMIT` truncation ranges) rather than returned: a
    :class:`FormatError` naming a block of ``coords`` (n, 3) and its chunk."""
    lo, hi = decoded_range(scale, offset)
    vmin, vmax = torch.aminmax(v) if v.numel() else (v.new_zeros(()) + offset,) * 2  # one pass; NaN propagates
    if bool(vmin >= lo) and bool(vmax <= hi):
        return v
    flat = v.reshape(len(v), -1)
    bad = (~((flat >= lo) & (flat <= hi)).all(dim=1)).nonzero().flatten().cpu().numpy()
    what = ("NaN/Inf values" if not bool(torch.isfinite(flat[bad]).all()) else
            f"absurd values (beyond {DECODE_LIMIT:g} truncation ranges)")
    b0 = None if coords is None or not len(bad) else coords[bad[0]]
    where = "" if b0 is None else (f" for {len(bad)} block(s), e.g. block {tuple(int(c) for c in b0)} in chunk "
                                   "c/" + "/".join(str(int(c) // chunk_blocks) for c in b0))
    raise FormatError(f"{location}: codec {codec_id!r} decoded {what}{where}; the stored codes or the codec's "
                      "learned state are corrupted: restore the map from a copy or re-encode it")


def _bound_pairs(region: Any) -> list[tuple[Any, Any]]:
    """Three ``(lo, hi)`` pairs or step-1 slices (``np.s_[0:64, :, 8:40]``; an open end is the map's edge) ->
    ``(lo or None, hi or None)`` per axis, numbers checked; anything else is a ShapeError naming the form."""
    form = "((x0, x1), (y0, y1), (z0, z1)) or np.s_[x0:x1, y0:y1, z0:z1]"
    try:
        axes = list(region)
    except TypeError:
        axes = []
    pairs = []
    for r in axes:
        if isinstance(r, slice):
            if r.step not in (None, 1):
                raise ShapeError(f"region slices take no step, got {r!r}: a region is {form}")
            pairs.append((r.start, r.stop))
        elif isinstance(r, (str, bytes)) or not hasattr(r, "__len__") or len(r) != 2:
            break
        else:
            pairs.append((r[0], r[1]))
    if len(axes) != 3 or len(pairs) != 3:
        raise ShapeError(f"region must be {form}, got {region!r}")
    for lo, hi in pairs:
        for v in (lo, hi):
            if v is not None and (isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating))
                                  or not np.isfinite(v)):
                raise ShapeError(f"region bounds must be finite numbers, got {v!r} in {region!r}")
    return pairs


def region_voxels(region: Region | None, units: str, shape: Sequence[int], origin: Sequence[float],
                  voxel_size: float) -> tuple[tuple[int, int], ...]:
    """Region (``units`` ``"voxels"`` or ``"m"``; None: the whole extent ``shape``) -> validated half-open voxel
    bounds per axis.

    Raises:
        ShapeError: not three (lo, hi) pairs. InvalidValueError: unknown units, or a region outside the map.
    """
    if region is None:
        return tuple((0, int(n)) for n in shape)
    pairs = _bound_pairs(region)
    if units in ("m", "metres", "meters"):
        vs = voxel_size

        def voxel(x: float, oo: float, n: int) -> int:
            # half-open like voxel ranges: the voxels whose centre lies in [lo, hi), so that -1:1 at 2 cm is 100
            # voxels and adjacent ranges share none; 1e-9 guards against rounding at exact voxel positions.
            # Clamped just past the map: a bound of 1e300 m is far outside it, not an integer overflow
            with np.errstate(all="ignore"):
                q = np.ceil((x - oo) / vs - 1e-9)
            return int(np.clip(q, -1, n + 1)) if not np.isnan(q) else -1

        vox = tuple((0 if lo is None else voxel(lo, oo, n), int(n) if hi is None else voxel(hi, oo, n))
                    for (lo, hi), oo, n in zip(pairs, origin, shape))
    elif units in ("voxels", "vox"):
        vox = tuple((0 if lo is None else int(lo), int(n) if hi is None else int(hi))
                    for (lo, hi), n in zip(pairs, shape))
    else:
        raise InvalidValueError(f"units must be 'voxels' or 'm', got {units!r}")
    for axis, ((lo, hi), n) in enumerate(zip(vox, shape)):
        if hi <= lo:
            raise InvalidValueError(f"region {region!r} ({units}) holds no voxel on axis {'xyz'[axis]}: "
                                    f"voxels [{lo}, {hi}) (ranges are half-open: lo <= x < hi)")
        if not 0 <= lo < hi <= n:
            raise InvalidValueError(f"region {region!r} ({units}) is outside the map on axis {'xyz'[axis]}: "
                                    f"voxels [{lo}, {hi}) vs extent [0, {n})")
    return vox

