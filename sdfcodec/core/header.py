"""The map header: pydantic models of the ``sdfcodec`` attribute of a map's root Zarr group.

``spec/map-format.md`` is normative; ``spec/map-header.schema.json`` is generated from these models by
``python -m sdfcodec.core.header > spec/map-header.schema.json`` and a test keeps the two in step.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from datetime import datetime, timezone
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_serializer, model_validator

from .blocks import truncation_problem
from ..errors import FormatError, VersionError

__all__ = ["MapHeader", "CodecSpec", "CodesSpec", "Truncation", "Provenance", "Extension", "StateReference",
           "parse_header", "CODED_MASK_EXTENSION", "FORMAT_NAME", "FORMAT_VERSION", "BlockState", "KNOWN_EXTENSIONS", "INT8_EXTENSION",
           "STATE_REFERENCE_EXTENSION", "MAX_EXTENT", "QUANT_EXTENSION", "CodeQuantisation", "FIELD_EXTENSION",
           "FieldCompression", "RESIDUAL_EXTENSION", "ResidualSpec", "SHARD_EXTENSION", "MANIFEST_EXTENSION",
           "ManifestRef", "MAX_MANIFEST_BYTES", "VARIABLE_RATE_EXTENSION", "VariableRate",
           "METRIC_EXTENSION", "FLOAT32_WEIGHTS_EXTENSION", "APPROX_MASK_EXTENSION", "public_source",
           "PINNED_MASK_EXTENSION", "REFINEMENT_EXTENSION", "Refinement"]

FORMAT_NAME = "sdfcodec-map"
#: Largest extent along one axis, in voxels or blocks: keeps index arithmetic inside int64 and a hostile header
#: from naming absurd sizes (a reader also checks the bytes it would allocate against ``max_decode_bytes``).
MAX_EXTENT = 2**31 - 1
#: Names of codec state arrays: plain path segments, so a header cannot point a reader outside ``codec/``.
STATE_NAME_PATTERN = r"^[A-Za-z0-9_][A-Za-z0-9_.-]*$"
FORMAT_VERSION = 1
BLOCK_EXTENT = 16  # voxels per block edge (block_size, the only one defined)
#: Extensions this reader implements. "fusion-weights": an optional ``weights`` array (spec section 6a);
#: "int8-codes": 8-bit codes with a per-block ``code_scale`` array (spec section 4a), required when used;
#: "codec-state-reference": the codec state named by a shipped model instead of stored (spec section 6c), required.
KNOWN_EXTENSIONS: frozenset[str] = frozenset({"fusion-weights", "int8-codes", "observation-mask",
                                              "codec-state-reference"})
INT8_EXTENSION = "int8-codes"
STATE_REFERENCE_EXTENSION = "codec-state-reference"
#: Shipped model names in a state reference: plain words, never a path (a reader looks the name up among the
#: models its installed plugin ships, nowhere else).
MODEL_NAME_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9_.+-]*$"
#: "quantised-codes": int16 codes with a per-map step per component in ``codes.quantisation`` (spec section 4b)
QUANT_EXTENSION = "quantised-codes"
KNOWN_EXTENSIONS = KNOWN_EXTENSIONS | {QUANT_EXTENSION}
#: "field-compression": voxel codes stored through an error-bounded field compressor (SZ3) as the Zarr codec of
#: ``codes``, a chunk's blocks compressed as one 3-D field, described by ``codes.field_compression`` (spec 4c)
FIELD_EXTENSION = "field-compression"
KNOWN_EXTENSIONS = KNOWN_EXTENSIONS | {FIELD_EXTENSION}
#: "residual-bound": a per-voxel residual on top of the codes (``--max-error`` / ``--sign-exact`` of block codecs),
#: the array ``residual`` described by the header field ``residual`` (spec section 6d)
RESIDUAL_EXTENSION = "residual-bound"
KNOWN_EXTENSIONS = KNOWN_EXTENSIONS | {RESIDUAL_EXTENSION}
#: "sharded-codes": the chunks of ``codes`` stored in Zarr v3 shards of ``codes.shard_blocks`` blocks per axis
#: (spec section 4d); required, since a reader that refuses sharding (section 9a) could not read the codes
SHARD_EXTENSION = "sharded-codes"
KNOWN_EXTENSIONS = KNOWN_EXTENSIONS | {SHARD_EXTENSION}
#: "integrity-manifest": the SHA-256 of every stored object keyed by its path, in ``manifest.json``, recorded by
#: the header field ``manifest`` (spec section 9b); required, so that no reader reads such a map unchecked
MANIFEST_EXTENSION = "integrity-manifest"
KNOWN_EXTENSIONS = KNOWN_EXTENSIONS | {MANIFEST_EXTENSION}
#: Largest manifest document a reader loads (about 600,000 objects; shard a larger map's codes).
MAX_MANIFEST_BYTES = 64 << 20
#: "variable-rate-codes": per block a prefix of its code, quantised and entropy-coded into one stream per chunk
#: (the array ``code_streams``), described by ``codes.variable_rate`` (spec section 4e)
VARIABLE_RATE_EXTENSION = "variable-rate-codes"
KNOWN_EXTENSIONS = KNOWN_EXTENSIONS | {VARIABLE_RATE_EXTENSION}
#: "quantised-fusion-weights": the optional ``weights`` array as uint8 counts instead of float16 (spec section 6a)
KNOWN_EXTENSIONS = KNOWN_EXTENSIONS | {"quantised-fusion-weights"}
#: "metric-codes": raw codes stored as the voxels' own float32 metres, not normalised (spec section 4f), so a
#: lossless map returns its input bit for bit; required: a reader that ignored it would scale metres again
METRIC_EXTENSION = "metric-codes"
#: "float32-fusion-weights": the optional ``weights`` array as float32, the weights exactly (spec section 6a)
FLOAT32_WEIGHTS_EXTENSION = "float32-fusion-weights"
KNOWN_EXTENSIONS = KNOWN_EXTENSIONS | {METRIC_EXTENSION, FLOAT32_WEIGHTS_EXTENSION}
#: "coded-observation-mask": the ``observed`` array's chunks context-coded by the Zarr codec ``sdfcodec.mask-ans``
#: (spec section 6e); required, since a reader without that codec cannot read the mask
CODED_MASK_EXTENSION = "coded-observation-mask"
KNOWN_EXTENSIONS = KNOWN_EXTENSIONS | {CODED_MASK_EXTENSION}
#: "approximate-observation-mask": the mask is exact only where it decides the surface of the decoded field (spec
#: section 6f); optional: the mask reads as any mask does, only what it says of voxels far from a surface differs
APPROX_MASK_EXTENSION = "approximate-observation-mask"
KNOWN_EXTENSIONS = KNOWN_EXTENSIONS | {APPROX_MASK_EXTENSION}
#: "pinned-observation-mask": the mask stored only at the voxels where it can change the surface, which the
#: reader finds from an exact integer decode of the variable-rate codes, one stream per chunk in ``mask_streams``
#: (spec section 6g); required: it replaces the ``observed`` array
PINNED_MASK_EXTENSION = "pinned-observation-mask"
KNOWN_EXTENSIONS = KNOWN_EXTENSIONS | {PINNED_MASK_EXTENSION}
#: Required: integer corrections at the voxels near the surface of a variable-rate map's decode (spec section 6h).
REFINEMENT_EXTENSION = "surface-refinement"
KNOWN_EXTENSIONS = KNOWN_EXTENSIONS | {REFINEMENT_EXTENSION}


class BlockState:
    """Values of the ``state`` array (uint8)."""

    UNOBSERVED = 0  #: never written; decodes as free space
    EMPTY = 1  #: observed and entirely free space; stores no code
    CODED = 2  #: has a code vector in ``codes``
    NAMES = {0: "unobserved", 1: "empty", 2: "coded"}


class _Model(BaseModel):
    # NaN and infinities are no valid voxel size, origin or truncation
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class Truncation(_Model):
    """Distances are truncated to ``[d_min, d_max]`` metres; negative is inside/behind the surface."""

    d_min: float = Field(description="lower truncation distance in metres (behind the surface)")
    d_max: float = Field(description="upper truncation distance in metres; free space stores d_max")

    @model_validator(mode="after")
    def _ordered(self) -> "Truncation":
        if not self.d_min < self.d_max:
            raise ValueError(f"d_min ({self.d_min}) must be below d_max ({self.d_max})")
        if (problem := truncation_problem(self.d_min, self.d_max)) is not None:  # overflows the float32 decode
            raise ValueError(problem)
        return self


class StateReference(_Model):
    """The codec state by reference: a model the codec's installed plugin ships, checked by the digest of the
    state it gives at the map's code size (spec section 6c)."""

    model: str = Field(pattern=MODEL_NAME_PATTERN, max_length=255,
                       description="name of a model the codec's plugin ships (Codec.shipped_models), never a path")
    sha256: str = Field(pattern=r"^[0-9a-f]{64}$",
                        description="state digest (section 6) of the arrays that model gives a codec of this size")


class CodecSpec(_Model):
    """Which codec wrote the codes, its configuration and a digest of its learned state."""

    id: str = Field(pattern=r"^[a-z0-9][a-z0-9_.-]*$", description="codec id (entry point name)")
    config: dict[str, Any] = Field(description="the codec's get_config() (JSON); contains 'id'")
    package: str | None = Field(None, description="distribution that provides the codec, to name in errors")
    package_version: str | None = None
    state_arrays: list[Annotated[str, Field(pattern=STATE_NAME_PATTERN, max_length=255)]] = Field(
        default_factory=list, description="names of the arrays under codec/")
    state_sha256: str | None = Field(None, pattern=r"^[0-9a-f]{64}$",
                                     description="SHA-256 over the learned state (see spec)")
    state_reference: StateReference | None = Field(
        None, description="OPTIONAL (extension codec-state-reference): the state is not stored under codec/ but is "
                          "that of a model the plugin ships; omitted when the state is stored")

    @model_serializer(mode="wrap")
    def _omit_no_reference(self, handler):
        # a stored state leaves the field out, not null: headers of embedded maps stay byte-identical to those
        # written before the field existed
        out = handler(self)
        if isinstance(out, dict) and out.get("state_reference", 0) is None:
            out.pop("state_reference")
        elif isinstance(out, dict) and not out.get("state_arrays") and \
                out.get("state_sha256") == (out.get("state_reference") or {}).get("sha256"):
            # by reference both say nothing the reference does not (spec section 6c): 100 bytes of every such map
            out.pop("state_arrays", None)
            out.pop("state_sha256", None)
        return out

    @model_validator(mode="before")
    @classmethod
    def _digest_of_reference(cls, data: Any) -> Any:
        # a header by reference may leave out state_sha256 (spec 6c): it is the reference's digest
        ref = data.get("state_reference") if isinstance(data, dict) else None
        if isinstance(ref, dict) and "state_sha256" not in data and "sha256" in ref:
            data = {**data, "state_sha256": ref["sha256"]}
        return data

    @model_validator(mode="after")
    def _id_matches(self) -> "CodecSpec":
        if self.config.get("id") != self.id:
            raise ValueError(f"codec.config.id ({self.config.get('id')!r}) differs from codec.id ({self.id!r})")
        ref = self.state_reference
        if ref is not None and (self.state_arrays or self.state_sha256 != ref.sha256):
            raise ValueError("a codec state by reference stores no arrays (state_arrays must be empty) and "
                             "state_sha256 must equal state_reference.sha256")
        return self


class CodeQuantisation(_Model):
    """int16 codes (spec section 4b): element ``j`` of a stored code ``q`` decodes as ``offset[j] + step[j] * q``."""

    step: list[Annotated[float, Field(gt=0)]] = Field(description="quantisation step per code element (> 0)")
    offset: list[float] = Field(description="offset per code element")


class FieldCompression(_Model):
    """Voxel codes compressed as a field (spec section 4c): every stored voxel of a coded block lies within
    ``max_error`` (normalised units) of the value the writer was given."""

    name: Literal["sz3"] = Field(description="the field compressor; 'sz3': SZ3, absolute error bound")
    max_error: float = Field(gt=0, le=0.5, description="absolute error bound in normalised units (1 = d_max - d_min)")


class ResidualSpec(_Model):
    """The residual stage (spec section 6d): voxel ``i`` of a coded block decodes, at full level, as
    ``clamp(d_i + step * q_i, d_min, d_max)`` in float32 metres, ``q`` the stored small integers."""

    step: float = Field(gt=0, description="metres per residual unit")
    dtype: Literal["int8", "int16"] = Field(description="element type of the residual array")
    max_error: float | None = Field(None, gt=0, description="the writer's bound: every observed voxel of a coded "
                                                            "block decodes within it (metres); null: none")
    sign_exact: bool = Field(False, description="every observed voxel touching a surface crossing of the input "
                                                "decodes with its sign")

    @model_validator(mode="after")
    def _something(self) -> "ResidualSpec":
        if self.max_error is None and not self.sign_exact:
            raise ValueError("a residual stage bounds something: max_error, sign_exact or both")
        return self


class Refinement(_Model):
    """The surface refinement of a variable-rate map (spec section 6h): corrections in steps of ``step`` at the
    voxels whose exact decode lies within ``tau`` of zero, both in units of ``2^-24`` m."""

    step: int = Field(ge=1, lt=1 << 24, description="correction step, metres times 2^24 (an integer)")
    tau: int = Field(ge=1, lt=1 << 24, description="voxels with |exact decode| < tau are refined, metres times 2^24")
    model: str = Field(max_length=1 << 16, pattern=r"^[A-Za-z0-9+/=]*$",
                       description="base64 of the zlib-compressed law of the corrections (spec section 6h)")


class VariableRate(_Model):
    """Variable-rate codes (spec section 4e): element ``j`` of a block's prefix decodes as ``step[j] * q`` (one step:
    every element's); ``model`` packs each element's law of ``q`` and the law of the prefix lengths."""

    step: list[Annotated[float, Field(gt=0)]] = Field(description="quantisation step, one for all elements or one "
                                                                  "per element (> 0)")
    coder: Literal["constriction-ans-1"] = Field(description="the entropy coder of the chunk streams")
    model: str = Field(max_length=1 << 20, pattern=r"^[A-Za-z0-9+/=]*$",
                       description="base64 of the zlib-compressed probability model (spec section 4e)")
    states: str | None = Field(None, max_length=1 << 20, pattern=r"^[A-Za-z0-9+/=]*$",
                               description="OPTIONAL: base64 of the zlib-compressed block states (grid_blocks, "
                                           "uint8, C order); the map then stores neither 'state' nor 'codes' "
                                           "(spec section 4e); omitted otherwise")
    refinement: Refinement | None = Field(None, description="OPTIONAL: with the required extension "
                                                            "'surface-refinement' (spec section 6h); omitted otherwise")

    @model_serializer(mode="wrap")
    def _omit_no_states(self, handler):
        out = handler(self)  # maps whose states are in the array stay byte-identical to those before the field
        if isinstance(out, dict):
            for name in ("states", "refinement"):
                if out.get(name, 0) is None:
                    out.pop(name)
        return out


class CodesSpec(_Model):
    """How code vectors are stored in the ``codes`` array."""

    size: int = Field(ge=1, le=1 << 16, description="code length D (last axis of codes)")
    dtype: Literal["float32", "float16", "int8", "int16"] = Field(
        "float32", description="element type of codes; int8 needs the required extension 'int8-codes', int16 "
                               "the required extension 'quantised-codes' and 'quantisation'")
    chunk_blocks: int = Field(8, ge=1, le=256, description="blocks per chunk along x, y and z")
    chunk_code: int = Field(ge=1, description="code elements per chunk along the code axis")
    prefix_ordered: bool = Field(description="a code prefix decodes (levels are meaningful)")
    levels: list[int] = Field(description="prefix lengths a reader may request cheaply, ascending, last = size")
    quantisation: CodeQuantisation | None = Field(
        None, description="int16 codes only: step and offset per code element (spec section 4b); omitted otherwise")
    field_compression: FieldCompression | None = Field(
        None, description="float32 voxel codes (size 4096) only, with the required extension 'field-compression': "
                          "the error-bounded compressor of the codes array (spec section 4c); omitted otherwise")
    shard_blocks: int | None = Field(
        None, ge=2, le=256, description="with the required extension 'sharded-codes': blocks per axis of one shard "
                                        "of codes, a multiple of chunk_blocks (spec section 4d); omitted otherwise")
    variable_rate: VariableRate | None = Field(
        None, description="with the required extension 'variable-rate-codes': float32 codes stored as one "
                          "entropy-coded stream per chunk (spec section 4e); omitted otherwise")
    units: Literal["metres"] | None = Field(
        None, description="with the required extension 'metric-codes' (codec raw, float32 codes only): the codes "
                          "are the voxels in metres, decoded without the normalisation (spec section 4f); omitted "
                          "otherwise (codes in normalised units)")

    @model_serializer(mode="wrap")
    def _omit_no_quantisation(self, handler):
        # omitted, never null: headers of float and int8 maps stay byte-identical to those written before 4b-4f
        out = handler(self)
        for key in ("quantisation", "field_compression", "shard_blocks", "variable_rate", "units"):
            if isinstance(out, dict) and out.get(key, 0) is None:
                out.pop(key)
        return out

    def stored_bytes(self, level: int | None = None) -> int:
        """Uncompressed bytes of one coded block's first ``level`` (default: all) code elements, with the
        float32 ``[offset, scale]`` pair int8 codes carry (spec section 4a)."""
        n = self.size if level is None else level
        return n * {"float32": 4, "float16": 2, "int8": 1, "int16": 2}[self.dtype] + 8 * (self.dtype == "int8")

    @model_validator(mode="after")
    def _levels(self) -> "CodesSpec":
        if not self.levels or self.levels[-1] != self.size or sorted(set(self.levels)) != self.levels:
            raise ValueError(f"levels must be ascending, unique and end at size {self.size}, got {self.levels}")
        if self.chunk_code > self.size:
            raise ValueError(f"chunk_code ({self.chunk_code}) exceeds size ({self.size})")
        q = self.quantisation
        if (self.dtype == "int16") != (q is not None):
            raise ValueError(f"codes.quantisation is required with codes.dtype 'int16' and only then (dtype "
                             f"{self.dtype!r})")
        if q is not None and not len(q.step) == len(q.offset) == self.size:
            raise ValueError(f"codes.quantisation needs {self.size} steps and offsets (one per code element), got "
                             f"{len(q.step)} and {len(q.offset)}")
        if self.field_compression is not None and (self.dtype != "float32" or self.size != 4096
                                                   or self.chunk_code != 4096):
            raise ValueError("codes.field_compression needs float32 voxel codes: size 4096 in one chunk along the "
                             f"code axis (got dtype {self.dtype!r}, size {self.size}, chunk_code {self.chunk_code})")
        if self.shard_blocks is not None and (self.shard_blocks % self.chunk_blocks
                                              or self.shard_blocks == self.chunk_blocks):
            raise ValueError(f"codes.shard_blocks ({self.shard_blocks}) must be a multiple of chunk_blocks "
                             f"({self.chunk_blocks}) and larger")
        vr = self.variable_rate
        if vr is not None and (self.dtype != "float32" or not self.prefix_ordered or self.shard_blocks is not None
                               or len(vr.step) not in (1, self.size)):
            raise ValueError(f"codes.variable_rate needs float32, prefix-ordered, unsharded codes and 1 or {self.size} "
                             "steps")
        if self.shard_blocks is not None and self.field_compression is not None:
            raise ValueError("codes.shard_blocks and codes.field_compression do not go together (spec section 4d)")
        if self.units is not None and (self.dtype != "float32" or self.size != 4096 or vr is not None
                                       or self.field_compression is not None):
            raise ValueError("codes.units 'metres' needs plain float32 voxel codes of size 4096 (spec section 4f), "
                             f"got dtype {self.dtype!r}, size {self.size}")
        return self


class Provenance(_Model):
    created: str = Field(description="ISO 8601 UTC time the map was written")
    sdfcodec_version: str
    tool: str | None = Field(None, description="what wrote it, e.g. 'sdfcodec encode'")
    source: str | None = Field(None, description="input it was made from, free text")


def public_source(source: str | None) -> str | None:
    """What a writer records as ``provenance.source`` for the input ``source`` (a local path or a URL): its last
    component only. A map is shared; the directories of the machine that wrote it (user names, project
    layout) or a URL's credentials and query are not the reader's business, and its name is what a user needs
    to find the input again."""
    if not source:
        return source
    from urllib.parse import urlsplit

    url = urlsplit(source)
    if url.scheme and url.netloc:  # no user, password, query or fragment: the path's last part, or the host
        return url.path.rstrip("/").rsplit("/", 1)[-1] or url.hostname or None
    return source.replace("\\", "/").rstrip("/").rsplit("/", 1)[-1] or None


class ManifestRef(_Model):
    """The map's integrity manifest (spec section 9b): the document ``manifest.json`` at the map's root."""

    sha256: str = Field(pattern=r"^[0-9a-f]{64}$", description="SHA-256 of the bytes of manifest.json")
    size: int = Field(ge=2, le=MAX_MANIFEST_BYTES, description="its size in bytes")
    objects: int = Field(ge=0, description="how many objects it lists")


class Extension(_Model):
    """An optional feature a map uses. A reader MUST refuse a map with an unknown *required* extension."""

    name: str
    required: bool = True


class MapHeader(_Model):
    """The ``sdfcodec`` attribute of a map's root group (format version 1)."""

    format: Literal["sdfcodec-map"] = FORMAT_NAME
    format_version: Literal[1] = FORMAT_VERSION
    voxel_size: float = Field(gt=0, description="edge of one voxel in metres")
    truncation: Truncation
    origin: tuple[float, float, float] = Field(description="world position (metres) of voxel (0, 0, 0)")
    block_size: Literal[16] = 16
    shape_voxels: tuple[Annotated[int, Field(ge=0, le=MAX_EXTENT)], Annotated[int, Field(ge=0, le=MAX_EXTENT)],
                        Annotated[int, Field(ge=0, le=MAX_EXTENT)]] = Field(
        description="true extent of the map in voxels (x, y, z)")
    grid_blocks: tuple[Annotated[int, Field(ge=0, le=MAX_EXTENT)], Annotated[int, Field(ge=0, le=MAX_EXTENT)],
                       Annotated[int, Field(ge=0, le=MAX_EXTENT)]] = Field(description="shape of the block grid (x, y, z)")
    codec: CodecSpec
    codes: CodesSpec
    extensions: list[Extension] = Field(default_factory=list)
    provenance: Provenance
    up: tuple[float, float, float] | None = Field(
        None, description="OPTIONAL unit vector: the world's up direction (opposite gravity) in the map's grid "
                          "axes, when the writer knew it (e.g. sdfcodec fuse of a sequence with a gravity file); "
                          "omitted when unknown")
    residual: ResidualSpec | None = Field(
        None, description="OPTIONAL, with the required extension 'residual-bound': the residual stage on top of the "
                          "codes (spec section 6d); omitted otherwise")
    manifest: ManifestRef | None = Field(
        None, description="OPTIONAL, with the required extension 'integrity-manifest': the digest of every stored "
                          "object keyed by its path (spec section 9b); omitted in maps without one")

    @model_serializer(mode="wrap")
    def _omit_unknown_up(self, handler):
        # an unknown up direction is left out, not written as null: headers without it stay byte-identical to
        # those of writers that predate the field, and readers that predate it open them (so is no residual)
        out = handler(self)
        for key in ("up", "residual", "manifest"):
            if isinstance(out, dict) and out.get(key, 0) is None:
                out.pop(key)
        return out

    @model_validator(mode="after")
    def _consistent(self) -> "MapHeader":
        need = tuple(-(-n // self.block_size) for n in self.shape_voxels)
        if any(g < n for g, n in zip(self.grid_blocks, need)):
            raise ValueError(f"grid_blocks {self.grid_blocks} cannot hold shape_voxels {self.shape_voxels}")
        # each required extension goes with the field it describes: one without the other, or the extension not
        # required, would let a reader that ignores it misread the map (spec section 8)
        dtype = f"codes.dtype is {self.codes.dtype!r}, "
        for what, present, name, detail in (
                ("codes.dtype 'int8'", self.codes.dtype == "int8", INT8_EXTENSION, dtype),
                ("codec.state_reference", self.codec.state_reference is not None, STATE_REFERENCE_EXTENSION, ""),
                ("codes.dtype 'int16'", self.codes.dtype == "int16", QUANT_EXTENSION, dtype),
                ("codes.field_compression", self.codes.field_compression is not None, FIELD_EXTENSION, ""),
                ("residual", self.residual is not None, RESIDUAL_EXTENSION, ""),
                ("codes.shard_blocks", self.codes.shard_blocks is not None, SHARD_EXTENSION, ""),
                ("manifest", self.manifest is not None, MANIFEST_EXTENSION, ""),
                ("codes.variable_rate", self.codes.variable_rate is not None, VARIABLE_RATE_EXTENSION, ""),
                ("codes.units", self.codes.units is not None, METRIC_EXTENSION, "")):
            listed = [e for e in self.extensions if e.name == name]
            if present != bool(listed) or any(not e.required for e in listed):
                raise ValueError(f"{what} and the required extension {name!r} go together "
                                 f"({detail}extensions {[e.name for e in self.extensions]})")
        if self.codes.units is not None and (self.codec.id != "raw" or self.residual is not None):
            raise ValueError(f"codes.units 'metres' is defined for the codec 'raw' without a residual stage (spec "
                             f"section 4f), got codec {self.codec.id!r}")
        if self.up is not None and not 0.5 < sum(u * u for u in self.up) < 2.0:
            raise ValueError(f"up must be a unit vector, got {list(self.up)}")
        if (problem := self._arithmetic_problem()) is not None:
            raise ValueError(problem)
        return self

    def _arithmetic_problem(self) -> str | None:
        """Numbers the decode's float32 arithmetic cannot use (spec section 9a), though finite and positive: a
        voxel size that is 0 (or subnormal) in float32 or whose extent overflows (a region in metres divides by
        it), a residual step that is not a positive float32 number or whose largest residual overflows (``q *
        step`` with ``q`` up to the dtype's maximum, spec 6d). The truncation checks itself (:class:`Truncation`)."""
        f32 = np.float32
        with np.errstate(all="ignore"):
            vs = f32(self.voxel_size)
            extent = np.array([abs(f32(o)) + f32(BLOCK_EXTENT * g + 1) * vs
                               for o, g in zip(self.origin, self.grid_blocks)], np.float32)
            if not (np.isfinite(vs) and vs >= np.finfo(np.float32).tiny and np.isfinite(extent).all()
                    and np.isfinite(np.float64(MAX_EXTENT) / self.voxel_size)):
                return (f"voxel_size {self.voxel_size} m (with origin {list(self.origin)} and grid_blocks "
                        f"{list(self.grid_blocks)}) does not fit the float32 arithmetic of a decode: a voxel size is "
                        "a normal positive float32 number of metres, e.g. 0.02, and the map's extent finite")
            if self.residual is not None:
                step, qmax = f32(self.residual.step), f32(127 if self.residual.dtype == "int8" else 32767)
                t = self.truncation
                reach = abs(f32(t.d_min)) + abs(f32(t.d_max)) + qmax * step
                norm = qmax * f32(self.residual.step / (t.d_max - t.d_min))
                if not (np.isfinite(step) and step >= np.finfo(np.float32).tiny and np.isfinite(reach)
                        and np.isfinite(norm)):
                    return (f"residual.step {self.residual.step} m does not fit the float32 arithmetic of a decode "
                            f"(spec 6d: q * step for {self.residual.dtype} q must be finite and step a normal "
                            "positive float32 number)")
        return None


def now_iso() -> str:
    return datetime.now(timezone.utc).isoformat(timespec="seconds")


def _number_fields(raw: dict) -> Iterator[tuple[str, Any]]:
    """(dotted location, value) of the header's numeric fields that are present, list items included."""
    for path in ("voxel_size", "truncation.d_min", "truncation.d_max", "origin", "block_size", "shape_voxels",
                 "grid_blocks", "up", "codes.size", "codes.chunk_blocks", "codes.chunk_code", "codes.levels",
                 "codes.shard_blocks",
                 "codes.quantisation.step", "codes.quantisation.offset", "codes.field_compression.max_error",
                 "residual.step", "residual.max_error", "manifest.size", "manifest.objects"):
        value: Any = raw
        for key in path.split("."):
            value = value.get(key) if isinstance(value, dict) else None
        for i, v in enumerate(value) if isinstance(value, list) else [(None, value)]:
            yield (path if i is None else f"{path}.{i}"), v


def parse_header(raw: Any, where: str = "map") -> MapHeader:
    """Validate a header dict. Checks the format name and version *before* anything else, so a map from a
    newer sdfcodec is refused with both versions named, and unknown required extensions are refused."""
    if not isinstance(raw, dict):
        raise FormatError(f"{where}: no sdfcodec header (group attribute 'sdfcodec' missing or not an object); "
                          "is this an sdfcodec map?")
    if raw.get("format") != FORMAT_NAME:
        raise FormatError(f"{where}: header format is {raw.get('format')!r}, expected {FORMAT_NAME!r}")
    version = raw.get("format_version")
    if not isinstance(version, int) or isinstance(version, bool):
        raise FormatError(f"{where}: header format_version must be an integer, got {version!r}")
    if version > FORMAT_VERSION:
        raise VersionError(f"{where}: written in map format version {version}, but this sdfcodec reads up to "
                           f"version {FORMAT_VERSION}; upgrade sdfcodec to read it")
    if version < 1:
        raise FormatError(f"{where}: invalid format_version {version}")
    extensions = raw.get("extensions") or []
    for ext in extensions if isinstance(extensions, list) else []:
        # malformed entries (a name that is no string...) are left to the schema check below
        if isinstance(ext, dict) and isinstance(ext.get("name"), str) and ext.get("required", True) is not False \
                and ext["name"] not in KNOWN_EXTENSIONS:
            raise VersionError(f"{where}: needs extension {ext.get('name')!r}, which this sdfcodec "
                               f"(format version {FORMAT_VERSION}) does not know; upgrade sdfcodec")
    for loc, value in _number_fields(raw):
        # lax validation would read the string "0.02" (or true) as a number: a header stores JSON numbers
        if isinstance(value, (str, bool)):
            raise FormatError(f"{where}: invalid header field {loc}: a JSON number is required, got {value!r}")
    try:
        return MapHeader.model_validate(raw)
    except ValidationError as e:
        first = e.errors()[0]
        loc = ".".join(str(p) for p in first["loc"])
        # a check across fields (the header's own validator) names its fields in its message
        raise FormatError(f"{where}: invalid header{' field ' + loc if loc else ''}: {first['msg']} "
                          f"({e.error_count()} problem(s) in all)") from e


def json_schema() -> dict[str, Any]:
    schema = MapHeader.model_json_schema()
    schema["$schema"] = "https://json-schema.org/draft/2020-12/schema"
    schema["$id"] = "https://sdfcodec.dev/spec/map-header-v1.schema.json"
    return schema


if __name__ == "__main__":  # python -m sdfcodec.core.header > spec/map-header.schema.json
    print(json.dumps(json_schema(), indent=2, sort_keys=True))
