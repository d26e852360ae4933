"""Error-bounded field compression of voxel codes (map extension ``field-compression``, spec/map-format.md
section 4c): the ``codes`` array of a map whose codes are the blocks' voxels is compressed by SZ3 (through
pysz) with an absolute error bound, a chunk's blocks assembled into one 3-D field so that SZ3's predictor sees
each voxel's neighbours across block faces.

Why a Zarr codec of the ``codes`` array, not a per-block codec: SZ3 streams have variable length (no fixed
code vector) and compress far better as one field than block by block (on the fused kitchen at a 1 cm bound:
285-351 B per coded block from 2^3- to 16^3-block fields, docs/rate-distortion.md), and as the array's codec
the block states, the observation mask, decode_region, iter_decoded, verify and the reader's limits all work
unchanged. A writer stores the voxels losslessly while it works (an update of a chunk would otherwise decode
and re-encode its other blocks, piling one bound on another) and compresses every chunk once, at commit
(:func:`compress_codes`); a map written so cannot be updated in place (:func:`refuse_update`).

pysz is an optional dependency (``pip install 'sdfcodec[sz3]'``), imported on first use.
"""

from __future__ import annotations

import asyncio
import math
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import zarr
from zarr.abc.codec import ArrayBytesCodec
from zarr.codecs import Crc32cCodec
from zarr.abc.buffer import Buffer, NDBuffer

from ..errors import ChecksumError, FormatError, InvalidValueError, MissingDependencyError
from ..core.header import BlockState, FieldCompression
from .grouping import chunk_box

__all__ = ["SZ3_ZARR_CODEC", "ThreadedArrayBytesCodec", "SZ3Field", "sz3_compress", "sz3_decompress",
           "field_compressors", "field_of", "chunks_of", "compress_codes", "refuse_update", "check_field_pipeline",
           "sz3_version", "MIN_MAX_ERROR", "FIELD_CHUNK_BLOCKS"]

#: Name of the Zarr v3 codec in a map's array metadata.
SZ3_ZARR_CODEC = "sdfcodec.sz3"
#: Smallest bound a writer accepts (normalised units: 1.4e-7 m at the paper's truncation); below it SZ3 stores
#: float32 noise and its stream can outgrow the raw chunk.
MIN_MAX_ERROR = 1e-6
#: Blocks per chunk edge of a field-compressed map: 8^3 blocks is a 128^3-voxel field. Larger fields compress
#: better (kitchen, 1 cm: 321 B per coded block at 4^3, 300 at 8^3, 285 at 16^3) and 8^3 keeps a chunk at 8 MiB
#: of float32 (decompressed in tens of milliseconds).
FIELD_CHUNK_BLOCKS = 8
_BLOCK = 16


def _pysz():
    try:
        import pysz
    except ImportError as e:
        raise MissingDependencyError("SZ3 field compression needs pysz: pip install 'sdfcodec[sz3]' "
                                     "(pysz==1.1.0)") from e
    return pysz


def sz3_version() -> str | None:
    """The installed pysz version, or None."""
    from importlib import metadata

    try:
        return metadata.version("pysz")
    except metadata.PackageNotFoundError:
        return None


def sz3_compress(field: np.ndarray, max_error: float) -> bytes:
    """SZ3 stream of a float32 array (any number of axes) with every value within ``max_error`` (absolute).

    Raises:
        InvalidValueError: a bound that is not a finite number >= :data:`MIN_MAX_ERROR`, or non-finite values.
    """
    pysz = _pysz()
    if not (isinstance(max_error, (int, float)) and math.isfinite(max_error) and max_error >= MIN_MAX_ERROR):
        raise InvalidValueError(f"the SZ3 error bound must be a number >= {MIN_MAX_ERROR:g} (normalised units), "
                                f"got {max_error!r}")
    a = np.ascontiguousarray(field, dtype=np.float32)
    if not np.isfinite(a).all():
        raise InvalidValueError("SZ3 cannot bound the error of NaN/Inf values; replace them first")
    conf = pysz.szConfig()
    conf.errorBoundMode = pysz.szErrorBoundMode.ABS
    conf.absErrorBound = float(max_error)
    stream, _ = pysz.sz.compress(a, conf)
    return stream.tobytes()


def sz3_decompress(stream: bytes | memoryview | np.ndarray, shape: tuple[int, ...], where: str = "SZ3 stream"
                   ) -> np.ndarray:
    """The float32 array of ``shape`` an SZ3 stream holds.

    pysz 1.1.0 checks the stream's payload length and element count against ``shape`` before SZ3 writes
    anything; every failure of the stream (truncated, not SZ3, another shape, a corrupt payload) is a
    :class:`FormatError` naming ``where``, as are non-finite values (SZ3 bounds the error of finite data only).
    """
    pysz = _pysz()
    buf = np.frombuffer(stream, dtype=np.uint8) if not isinstance(stream, np.ndarray) else stream.view(np.uint8)
    try:
        out, _ = pysz.sz.decompress(np.ascontiguousarray(buf.ravel()), np.float32, tuple(int(n) for n in shape))
    except Exception as e:  # noqa: BLE001 - pysz raises ValueError, RuntimeError (C++ exceptions), TypeError
        raise FormatError(f"{where} is not a sound SZ3 stream of {tuple(shape)} float32 values "
                          f"({type(e).__name__}: {e})") from e
    if not np.isfinite(out).all():
        raise FormatError(f"{where}: the SZ3 stream decodes to NaN/Inf values; it is corrupted")
    return out


def field_of(chunk: np.ndarray) -> np.ndarray:
    """Codes of a chunk ``(c, c, c, 4096)`` as the voxel field ``(16c, 16c, 16c)`` they tile (C order)."""
    c = chunk.shape[:3]
    f = chunk.reshape(*c, _BLOCK, _BLOCK, _BLOCK).transpose(0, 3, 1, 4, 2, 5)
    return np.ascontiguousarray(f.reshape(c[0] * _BLOCK, c[1] * _BLOCK, c[2] * _BLOCK))


def chunks_of(field: np.ndarray) -> np.ndarray:
    """Inverse of :func:`field_of`: ``(16a, 16b, 16c)`` -> ``(a, b, c, 4096)``."""
    a, b, c = (n // _BLOCK for n in field.shape)
    f = field.reshape(a, _BLOCK, b, _BLOCK, c, _BLOCK).transpose(0, 2, 4, 1, 3, 5)
    return np.ascontiguousarray(f.reshape(a, b, c, _BLOCK ** 3))


@dataclass(frozen=True)
class ThreadedArrayBytesCodec(ArrayBytesCodec):
    """A Zarr array-to-bytes codec whose work is plain synchronous numpy (``_encode_sync``, ``_decode_sync``),
    run off Zarr's event loop in a worker thread, so chunks of one read encode or decode side by side; its
    streams have no fixed length. The map's own Zarr codecs (SZ3 fields here, the context-coded mask of
    :mod:`sdfcodec.map.maskcoder`) derive from it."""

    async def _encode_single(self, chunk_array: NDBuffer, chunk_spec) -> Buffer | None:
        return await asyncio.to_thread(self._encode_sync, chunk_array, chunk_spec)

    async def _decode_single(self, chunk_bytes: Buffer, chunk_spec) -> NDBuffer:
        return await asyncio.to_thread(self._decode_sync, chunk_bytes, chunk_spec)

    def compute_encoded_size(self, input_byte_length: int, _chunk_spec) -> int:
        raise NotImplementedError  # variable-length streams


class SZ3Field(ThreadedArrayBytesCodec):
    """Zarr v3 array-to-bytes codec ``sdfcodec.sz3``: a float32 chunk ``(c, c, c, 4096)`` of voxel codes as one
    SZ3 stream of its ``(16c)^3`` field, every value within ``max_error`` (absolute, the array's units)."""

    is_fixed_size = False
    max_error: float

    def __init__(self, *, max_error: float) -> None:
        object.__setattr__(self, "max_error", float(max_error))

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> "SZ3Field":
        conf = data.get("configuration") if isinstance(data, dict) else None
        if data.get("name") != SZ3_ZARR_CODEC or not isinstance(conf, dict) or set(conf) != {"max_error"} \
                or isinstance(conf["max_error"], bool) or not isinstance(conf["max_error"], (int, float)):
            raise FormatError(f"a {SZ3_ZARR_CODEC} codec needs exactly the configuration {{'max_error': number}}, "
                             f"got {data!r}")
        return cls(max_error=conf["max_error"])

    def to_dict(self) -> dict[str, Any]:
        return {"name": SZ3_ZARR_CODEC, "configuration": {"max_error": self.max_error}}

    def _check_spec(self, spec) -> tuple[int, ...]:
        shape = tuple(int(n) for n in spec.shape)
        if np.dtype(spec.dtype.to_native_dtype()) != np.float32 or len(shape) != 4 or shape[3] != _BLOCK ** 3:
            raise FormatError(f"{SZ3_ZARR_CODEC} compresses float32 chunks of voxel codes (c, c, c, 4096), got "
                              f"{spec.dtype} {shape}")
        return shape

    def _encode_sync(self, chunk_array: NDBuffer, chunk_spec) -> Buffer:
        shape = self._check_spec(chunk_spec)
        stream = sz3_compress(field_of(np.asarray(chunk_array.as_numpy_array(), np.float32).reshape(shape)),
                              self.max_error)
        return chunk_spec.prototype.buffer.from_bytes(stream)

    def _decode_sync(self, chunk_bytes: Buffer, chunk_spec) -> NDBuffer:
        shape = self._check_spec(chunk_spec)
        try:
            field = sz3_decompress(chunk_bytes.as_numpy_array(), tuple(_BLOCK * n for n in shape[:3]),
                                   f"the {SZ3_ZARR_CODEC} stream")
        except FormatError as e:  # a ChecksumError: map readers re-raise it naming the chunk it came from
            raise ChecksumError(str(e)) from e
        return chunk_spec.prototype.nd_buffer.from_numpy_array(chunks_of(field))



zarr.registry.register_codec(SZ3_ZARR_CODEC, SZ3Field)


def field_compressors(fc: FieldCompression) -> list:
    """The chain of a field-compressed ``codes`` array: SZ3 at the header's bound, then the CRC32C checksum."""
    if fc.name != "sz3":
        raise InvalidValueError(f"unknown field compressor {fc.name!r} (known: sz3)")
    return [SZ3Field(max_error=fc.max_error), Crc32cCodec()]


def check_field_pipeline(codecs: tuple, fc: FieldCompression | None, where: str) -> bool:
    """True when ``codecs`` are exactly the field chain of ``fc`` (the header's ``codes.field_compression``);
    a :class:`FormatError` when an SZ3 codec appears anywhere else or with another bound; False when there is
    none (the ordinary chains are checked by the caller)."""
    has = [c for c in codecs if isinstance(c, SZ3Field)]
    if not has:
        if fc is not None:
            raise FormatError(f"{where} lacks the {SZ3_ZARR_CODEC} codec its header's codes.field_compression "
                              "declares (spec section 4c)")
        return False
    if fc is None:
        raise FormatError(f"{where} uses the Zarr codec {SZ3_ZARR_CODEC} without the header's "
                          "codes.field_compression and extension 'field-compression' (spec section 4c)")
    if len(codecs) != 2 or not isinstance(codecs[0], SZ3Field) or not isinstance(codecs[1], Crc32cCodec):
        raise FormatError(f"{where} must use exactly the codecs [{SZ3_ZARR_CODEC}, crc32c] (spec section 4c)")
    if codecs[0].max_error != fc.max_error:
        raise FormatError(f"{where}: its {SZ3_ZARR_CODEC} bound {codecs[0].max_error} differs from the header's "
                          f"codes.field_compression.max_error {fc.max_error}")
    return True


def compress_codes(group: zarr.Group, tmp: Path, state: np.ndarray, fc: FieldCompression) -> None:
    """At commit: replace the exact (lossless) ``codes`` a writer built in its temporary directory ``tmp`` by the
    field-compressed array, one chunk at a time; blocks that are not coded enter the field as free space (1.0),
    so SZ3 spends nothing on them, and so does the padding of chunks at the grid's edge (the array's fill value
    is 1.0). Each chunk is compressed once, from the values the writer was given."""
    exact_dir = tmp / "codes-exact"
    (tmp / "codes").rename(exact_dir)
    exact = zarr.open_array(group.store, path="codes-exact", mode="r")
    cb, grid = exact.chunks[0], exact.shape[:3]
    out = group.create_array("codes", shape=exact.shape, dtype="float32", fill_value=1.0, chunks=exact.chunks,
                             serializer=field_compressors(fc)[0], compressors=[Crc32cCodec()],
                             dimension_names=["bx", "by", "bz", "code"])
    for ch in np.ndindex(*(-(-g // cb) for g in grid)):
        box = chunk_box(ch, cb, grid)
        coded = state[box] == BlockState.CODED
        if not coded.any():
            continue
        buf = np.asarray(exact[box])
        buf[~coded] = 1.0
        out[box] = buf
    shutil.rmtree(exact_dir)


def refuse_update(location: Any, fc: FieldCompression | None) -> None:
    """Field-compressed maps are written once: updating a chunk would re-encode its other blocks from their
    decoded values, and each pass could add another bound to their error."""
    if fc is not None:
        raise InvalidValueError(f"{location} stores its field compressed by {fc.name} (error bound "
                                f"{fc.max_error:g}, normalised); such a map cannot be updated in place (re-encoding "
                                "a chunk from its decoded values would stack error bounds): update the lossless "
                                "map and transcode it again (sdfcodec encode LOSSLESS OUT --codec sz3)")
