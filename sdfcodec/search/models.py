"""Query models: descriptor sets made by encoding shapes with a codec (:class:`QueryModel`; a built-in shape
with every parameter given, :func:`shape_model`, through the query cache), and their ``.npz`` files of plain
arrays (:func:`save_query`, :func:`load_query`, never pickles). Building a query for a map, which first works
out what the map says about itself, is :func:`sdfcodec.search.query.build_query`."""

from __future__ import annotations

import json
import os
import threading
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from ..core._validate import BLOCK
from ..codec import Codec
from ..errors import FormatError, InvalidValueError, ShapeError
from ..map import state_digest
from .arrays import encode_array
from .cache import cache_key, cached_model
from .shapes import QUERY_NAMES, probe_blocks, query_blocks, rotation_set

__all__ = ["QUERY_FORMAT", "QUERY_VERSION", "QueryModel", "codec_state_sha256", "query_model", "shape_model",
           "encode_query_blocks", "save_query", "load_query"]


_QUERY_META = "__sdfcodec_query__"


QUERY_FORMAT = "sdfcodec-query"


QUERY_VERSION = 1


@dataclass
class QueryModel:
    """A descriptor set: shapes of interest encoded with a map's codec.

    Attributes
    ----------
    name : str
        Free-text name (``"floor"`` for the built-in floor model).
    descriptors : np.ndarray
        ``(M, D)`` float32 codes of the shapes, from the codec described by ``codec_config``.
    codec_config : dict
        ``get_config()`` of the codec that encoded them (JSON).
    codec_state_sha256 : str or None
        Digest of that codec's learned state (``sdfcodec.map.state_digest``), None without state.
    voxel_size : float
        Metres per voxel the shapes were sampled at.
    truncation : tuple of float
        ``(d_min, d_max)`` metres the shapes were truncated and normalised with.
    blocks : np.ndarray or None
        ``(M, 16, 16, 16)`` float32 normalised shape blocks. With them, :func:`search` re-encodes the model
        with any map's codec; without them, the descriptors are used only on maps whose codec agrees.
    rotations : np.ndarray or None
        ``(M, 3, 3)`` float32 shape-to-grid rotations (built-in shapes).
    positions : np.ndarray or None
        ``(M, 3)`` float32 shape positions in voxels (built-in shapes; see :func:`query_blocks`).
    spec : dict or None
        How a built-in query was made (``{"shape", "up", "rotations", "offsets", "behind"}``): a map with a
        different voxel size or truncation gets the query rebuilt from it.
    probe_codes : np.ndarray or None
        ``(6, D)`` float32 codes of fixed probe blocks under the same codec, used to check that a map's codec
        agrees with the one that made descriptors-only models.
    """

    name: str
    descriptors: np.ndarray
    codec_config: dict
    codec_state_sha256: str | None
    voxel_size: float
    truncation: tuple[float, float]
    blocks: np.ndarray | None = None
    rotations: np.ndarray | None = None
    positions: np.ndarray | None = None
    spec: dict | None = None
    probe_codes: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.descriptors = np.ascontiguousarray(self.descriptors, dtype=np.float32)
        if self.descriptors.ndim != 2 or not len(self.descriptors):
            raise ShapeError(f"descriptors must have shape (M, D) with M >= 1, got {self.descriptors.shape}")
        if not np.isfinite(self.descriptors).all():
            raise InvalidValueError("descriptors hold NaN or infinite values")
        m = len(self.descriptors)
        if self.blocks is not None:
            self.blocks = np.asarray(self.blocks, dtype=np.float32)
            if self.blocks.shape != (m, BLOCK, BLOCK, BLOCK):
                raise ShapeError(f"blocks must have shape ({m}, 16, 16, 16) to match the descriptors, got "
                                 f"{self.blocks.shape}")
        self.truncation = (float(self.truncation[0]), float(self.truncation[1]))

    def __len__(self) -> int:
        return len(self.descriptors)

    @property
    def code_size(self) -> int:
        """``D``, the descriptors' length."""
        return int(self.descriptors.shape[1])

    @property
    def up(self) -> np.ndarray:
        """``(3,)`` float64 unit up direction of a built-in query (``+z`` otherwise)."""
        u = np.asarray((self.spec or {}).get("up", (0.0, 0.0, 1.0)), dtype=np.float64)
        return u / np.linalg.norm(u)

    def matches_codec(self, codec: Codec, state_sha256: str | None = None) -> bool:
        """True when ``codec`` is the one that made the descriptors (same config and state digest)."""
        sha = state_sha256 if state_sha256 is not None else codec_state_sha256(codec)
        return codec.get_config() == self.codec_config and sha == self.codec_state_sha256

    def without_blocks(self) -> "QueryModel":
        """A copy holding only descriptors (small; usable on maps whose codec agrees, checked by probes)."""
        return replace(self, blocks=None)


def codec_state_sha256(codec: Codec) -> str | None:
    """:func:`sdfcodec.map.state_digest` of ``codec``'s state, None for a codec without one: what names the
    codec's state in query models and cache keys."""
    state = codec.state_dict()
    return state_digest(state) if state else None


def query_model(name: str, codes: np.ndarray, codec: Codec, voxel_size: float, truncation: tuple[float, float],
           blocks: np.ndarray | None, rotations: np.ndarray | None = None, positions: np.ndarray | None = None,
           spec: dict | None = None, sha: str | None = None) -> QueryModel:
    """A :class:`QueryModel` of ``codes`` ``(M, D)`` float32 encoded by ``codec`` (with the probe codes that tell
    whether another codec encodes alike); ``sha``: the codec's state digest when the caller has it already
    (hashing a large state costs)."""
    probes = encode_array(codec, probe_blocks(voxel_size, truncation))
    return QueryModel(name=name, descriptors=codes, codec_config=codec.get_config(),
                      codec_state_sha256=codec_state_sha256(codec) if sha is None else sha, voxel_size=voxel_size,
                      truncation=truncation,
                      blocks=blocks, rotations=rotations, positions=positions, spec=spec, probe_codes=probes)


def shape_model(shape: str, codec: Codec, voxel_size: float, truncation: tuple[float, float], up: tuple,
                 rotations: Any, offsets: int | str, behind: str, weighted: bool, stretch: tuple[float, ...],
                 keep_blocks: bool) -> QueryModel:
    """The model of the built-in ``shape`` encoded by ``codec`` with every parameter given (what
    :func:`sdfcodec.search.query.build_query` works out from a map first), from the query cache (:mod:`sdfcodec.search.cache`) when it holds one made
    with the same codec and parameters (rotations given as arrays are not cached)."""
    _, rot_json = rotation_set(rotations)
    spec = {"shape": shape, "up": list(up), "rotations": rot_json,
            "offsets": offsets if isinstance(offsets, str) else int(offsets), "behind": behind,
            "weighted": weighted, "stretch": list(stretch)}

    config, sha = codec.get_config(), codec_state_sha256(codec)

    def build() -> QueryModel:
        ready = _first_encode(codec, truncation, voxel_size, weighted)
        v, rot, pos, seen = query_blocks(shape, voxel_size=voxel_size, truncation=truncation, up=up,
                                         rotations=rotations, offsets=offsets, behind=behind, return_observed=True,
                                         stretch=stretch)
        ready.join()
        codes = encode_query_blocks(codec, v, seen, truncation, voxel_size, weighted)
        return query_model(shape, codes, codec, voxel_size, truncation, v if keep_blocks else None, rot, pos, dict(spec),
                      sha=sha)

    if not (rotations is None or isinstance(rotations, str)):
        return build()
    key = cache_key("query", spec=spec, codec=config, state=sha, voxel_size=voxel_size, truncation=truncation,
                    keep_blocks=keep_blocks)

    def valid(q: QueryModel) -> bool:  # a file is only trusted to be what its key says after this check
        return (q.codec_config == config and q.codec_state_sha256 == sha and q.spec == spec
                and q.voxel_size == voxel_size and tuple(q.truncation) == truncation
                and (q.blocks is not None) == keep_blocks and q.descriptors.ndim == 2
                and q.descriptors.shape[1] == codec.code_size and q.descriptors.dtype == np.float32
                and bool(np.isfinite(q.descriptors).all()))

    q = cached_model(key, build, valid, load=load_query, save=save_query, what=f"building the {shape} query for {codec.codec_id}-{codec.code_size}")
    # a copy: callers may write into what they get without changing the cached model
    return replace(q, descriptors=q.descriptors.copy(), spec=dict(q.spec),
                   blocks=None if q.blocks is None else q.blocks.copy())


def _first_encode(codec: Codec, truncation: tuple[float, float], voxel_size: float, weighted: bool
                  ) -> threading.Thread:
    """A started thread encoding one block as :func:`encode_query_blocks` will encode the shapes, so that what a
    codec loads on its first encode overlaps the making of the shapes, whose numpy work (and page faults) runs
    mostly without the GIL: for pca's weighted encode, numba's import and the start of its compiled pass, ~0.6 s
    of one core, paid once per process (a first search on two cores: 0.2-0.3 s sooner). Join it before encoding.
    Whatever goes wrong in it is left for the real encode to raise."""

    def run() -> None:
        one = np.ones((1, BLOCK, BLOCK, BLOCK), np.float32)  # free space: a block any codec encodes
        try:
            encode_query_blocks(codec, one, np.ones(one.shape, bool), truncation, voxel_size, weighted)
        except Exception:  # noqa: BLE001 - the same error comes from the real encode, in the caller's thread
            pass

    thread = threading.Thread(target=run, name="sdfcodec-first-encode", daemon=True)
    thread.start()
    return thread


def encode_query_blocks(codec: Codec, v: np.ndarray, observed: np.ndarray | None, truncation: tuple[float, float],
                        voxel_size: float, weighted: bool) -> np.ndarray:
    """Codes ``(N, D)`` float32 of normalised query blocks ``v``: the plain projection, or with ``weighted`` the
    surface-true encoding a masked map's writer uses (:func:`sdfcodec.map.observed.encode_blocks`, ``observed``
    ``(N, 16, 16, 16)`` bool, all observed when None), so query codes and map codes compare like with like."""
    if not weighted:
        return encode_array(codec, v)
    from ..map.observed import SURFACE_WEIGHT, encode_blocks

    obs = np.ones(v.shape, bool) if observed is None else observed
    return encode_blocks(codec, v, obs, truncation, voxel_size, SURFACE_WEIGHT, "cpu", numpy_path=True)


def save_query(model: QueryModel, path: str | os.PathLike) -> Path:
    """Write a query model as ``.npz`` (plain arrays, compressed, atomic); returns the path.

    Layout: ``descriptors`` and, when present, ``blocks``, ``rotations``, ``positions``, ``probe_codes``, plus
    ``__sdfcodec_query__``, a uint8 array of UTF-8 JSON ``{"format": "sdfcodec-query", "version": 1, "name",
    "codec_config", "codec_state_sha256", "voxel_size", "truncation", "spec"}``.
    """
    from ..model import save_state_file

    meta = {"format": QUERY_FORMAT, "version": QUERY_VERSION, "name": model.name, "codec_config": model.codec_config,
            "codec_state_sha256": model.codec_state_sha256, "voxel_size": model.voxel_size,
            "truncation": list(model.truncation), "spec": model.spec}
    arrays = {"descriptors": model.descriptors,
              _QUERY_META: np.frombuffer(json.dumps(meta).encode(), dtype=np.uint8)}
    for key in ("blocks", "rotations", "positions", "probe_codes"):
        if getattr(model, key) is not None:
            arrays[key] = getattr(model, key)
    save_state_file(path, arrays)
    return Path(path)


def load_query(path: str | os.PathLike) -> QueryModel:
    """Read a query model written by :func:`save_query` (never unpickles).

    Raises
    ------
    FormatError
        Not a query model, or its metadata is broken. ``VersionError`` for a newer format version.
    """
    from ..model import load_meta_file

    if not Path(path).is_file():
        raise InvalidValueError(f"no query model at {path}: give a built-in query ({', '.join(QUERY_NAMES)}) or the "
                                "path of a model written by sdfcodec.search.models.save_query")
    meta, arrays = load_meta_file(path, _QUERY_META, QUERY_FORMAT, QUERY_VERSION, "query model",
                                  "sdfcodec.search.models.save_query")
    if "descriptors" not in arrays:
        raise FormatError(f"{path}: query model lacks its descriptors array")
    try:
        return QueryModel(name=str(meta["name"]), descriptors=arrays["descriptors"], codec_config=meta["codec_config"],
                          codec_state_sha256=meta["codec_state_sha256"], voxel_size=float(meta["voxel_size"]),
                          truncation=tuple(meta["truncation"]), blocks=arrays.get("blocks"),
                          rotations=arrays.get("rotations"), positions=arrays.get("positions"),
                          spec=meta.get("spec"), probe_codes=arrays.get("probe_codes"))
    except KeyError as e:
        raise FormatError(f"{path}: query metadata lacks {e}") from e
