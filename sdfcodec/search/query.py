"""Queries for a map: building a query model by encoding shapes with a map's codec, in the map's context
(:func:`build_query`), a model of a map's own blocks (:func:`like_blocks`), and turning any query a search
accepts into a model for one map (:func:`resolve_query`). The models themselves and their files are
:mod:`sdfcodec.search.models`."""

from __future__ import annotations

import math
import os
import warnings
from dataclasses import replace
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from ..core._validate import BLOCK
from ..core.blocks import check_truncation, normalise
from ..codec import Codec
from ..errors import InvalidValueError, SDFCodecWarning, ShapeError
from ..map import Map
from .arrays import encode_array
from .context import check_up, map_context
from .models import QueryModel, codec_state_sha256, encode_query_blocks, load_query, query_model, shape_model
from .shapes import (FUSED_STRETCH, QUERY_NAMES, check_query_name, dedupe_blocks, probe_blocks, query_blocks, rotate_blocks,
                     rotation_set)

__all__ = ["build_query", "like_blocks", "resolve_query"]


# -------------------------------------------------------------------------------------------- query model


def build_query(shape: str | np.ndarray = "floor", *, map: Map | None = None, codec: Codec | None = None,
                voxel_size: float | None = None, truncation: tuple[float, float] | None = None,
                up: Sequence[float] | None = None, rotations: Any = None, offsets: int | str = "auto",
                behind: str | None = None, keep_blocks: bool = True, name: str | None = None,
                tilt: float | None = None, weighted: bool | None = None,
                stretch: Sequence[float] | None = None) -> QueryModel:
    """Build a query model by encoding shapes with a codec (the map's own, for searching that map).

    Parameters
    ----------
    shape : str or np.ndarray
        A built-in name (:data:`QUERY_NAMES`, see :func:`query_blocks`), or user blocks ``(N, 16, 16, 16)`` in
        metres (e.g. blocks cut from a map with ``Map.iter_blocks``), truncated to the map's range.
    map : Map, optional
        The map the query is for: its codec, voxel size and truncation are used.
    codec, voxel_size, truncation :
        Instead of ``map``: a fitted codec, metres per voxel (default 0.02) and ``(d_min, d_max)`` metres
        (default ``(-0.04, 0.1)``).
    up, rotations, offsets, behind :
        See :func:`query_blocks`. For user blocks, ``rotations`` resamples them (exactly for the 24 axis
        rotations, trilinearly otherwise) and ``up``, ``offsets``, ``behind`` are unused. ``up`` and ``behind``
        default to what the map records (:func:`sdfcodec.search.context.map_context`: its header's up
        direction, else ``+z``; ``"unobserved"`` for fused maps, ``"solid"`` for exact SDFs); without a map, to
        ``+z`` and ``"unobserved"``.
    tilt : float, optional
        Degrees: also sample the shapes tilted within a cone of this angle about ``up`` (a spin about it
        included), for surfaces up to that far from level. Shorthand for ``rotations="cone:TILT:COUNT"`` with
        16 rotations up to 5 degrees and 48 beyond; not with ``rotations``.
    weighted : bool, optional
        Encode the shapes surface-true (weighted least squares with :func:`sdfcodec.map.observed.error_weights`
        and the mask of what a camera in front of each shape observes), as maps with an observation mask encode
        their blocks. Default: when the map records its observation.
    stretch : sequence of float, optional
        Field stretches to sample the shapes at (:func:`query_blocks`); default :data:`FUSED_STRETCH` for
        weighted queries with unobserved space behind (fused maps), else 1.
    keep_blocks : bool
        Store the normalised shape blocks in the model (re-encodable for other maps; 16 KiB each).
    name : str, optional
        Model name (default: the shape name, or ``"blocks"``).

    Returns
    -------
    QueryModel
        ``descriptors`` ``(M, D)`` float32 on the CPU.
    """
    context = None
    if map is not None:
        codec = map.codec
        voxel_size, truncation = map.voxel_size, map.truncation
        if isinstance(shape, str) or weighted is None:
            context = map_context(map, behind=behind if isinstance(shape, str) else "solid", up=up)
            behind, up = context.behind, context.up
            weighted = context.weighted if weighted is None else bool(weighted)
    if codec is None:
        raise InvalidValueError("build_query needs the map (map=...) or a fitted codec (codec=...) to encode with")
    up = check_up((0.0, 0.0, 1.0) if up is None else up)
    behind = "unobserved" if behind is None else behind
    weighted = bool(weighted)
    if tilt is not None:
        if rotations is not None:
            raise InvalidValueError("give tilt= or rotations=, not both (tilt is a cone of rotations)")
        if isinstance(tilt, bool) or not isinstance(tilt, (int, float)) or not 0 <= tilt <= 90:
            raise InvalidValueError(f"tilt must be degrees in [0, 90], got {tilt!r}")
        rotations = None if tilt == 0 else f"cone:{float(tilt):g}:{16 if tilt <= 5 else 48}"
    voxel_size = 0.02 if voxel_size is None else float(voxel_size)
    truncation = (-0.04, 0.1) if truncation is None else tuple(float(t) for t in truncation)
    check_truncation(*truncation)
    if isinstance(shape, str):
        # a map that records its observation was fused: its fields hold projective distances, stretched
        if stretch is None:
            stretch = FUSED_STRETCH if weighted and behind == "unobserved" else (1.0,)
        stretch = tuple(float(x) for x in stretch)
        model = shape_model(shape, codec, voxel_size, truncation, up, rotations, offsets, behind, weighted, stretch,
                             keep_blocks)
        spec = dict(model.spec)
        if context is not None:
            spec["context"] = context.to_json()
        return replace(model, name=name or shape, spec=spec)
    b = np.asarray(shape)
    if b.dtype.kind != "f":
        raise InvalidValueError(f"query blocks must be floating-point metres, got dtype {b.dtype}")
    if b.ndim == 3:
        b = b[None]
    if b.ndim != 4 or b.shape[1:] != (BLOCK, BLOCK, BLOCK) or not len(b):
        raise ShapeError(f"query blocks must have shape (N, 16, 16, 16) (metres), got {b.shape}")
    if not np.isfinite(b).all():
        raise InvalidValueError("query blocks hold NaN or infinite values")
    v = normalise(np.clip(b, *truncation), *truncation)
    mats, _ = rotation_set(rotations)
    if len(mats) > 1 or not np.allclose(mats[0], np.eye(3)):
        v = dedupe_blocks(rotate_blocks(v, mats))[0]
    return query_model(name or "blocks", encode_query_blocks(codec, v, None, truncation, voxel_size, weighted), codec,
                       voxel_size, truncation, v if keep_blocks else None)


def like_blocks(m: Map, coords: Any, codec: Codec) -> QueryModel:
    """A "blocks like these" model: the map's own codes of coded blocks ``coords`` (``(N, 3)`` block indices,
    or ``"X,Y,Z;X,Y,Z"`` as the CLI's ``--query like:...`` passes them) are the descriptors, so they compare
    with the map's codes exactly, at any prefix level of a prefix-ordered codec.

    Raises
    ------
    InvalidValueError
        Unparseable coordinates, or a block that is not coded in the map.
    """
    from ..core.header import BlockState

    text = coords
    try:
        if isinstance(coords, str):
            coords = [[int(v) for v in part.split(",")] for part in coords.split(";") if part.strip()]
        if len(coords) and any(len(p) != 3 for p in coords):  # "1,2": two numbers are no block index
            raise ValueError(coords)
        c = np.asarray(coords, dtype=np.int64).reshape(-1, 3) if len(coords) else np.zeros((0, 3), np.int64)
    except (ValueError, TypeError) as e:
        raise InvalidValueError(f"like: wants block indices X,Y,Z[;X,Y,Z...] (three whole numbers each), got "
                                f"{text!r}") from e
    if not len(c):
        raise InvalidValueError("like: needs at least one block index X,Y,Z")
    states = m.block_states()
    grid = np.asarray(states.shape)
    if c.min() < 0 or np.any(c >= grid) or np.any(states[tuple(c.T)] != BlockState.CODED):
        raise InvalidValueError(f"like: every block must be a coded block of the map (grid {tuple(grid)}); "
                                f"{c.tolist()} are not all coded")
    all_c, all_codes = m.read_codes()
    key = {tuple(r): i for i, r in enumerate(np.asarray(all_c).tolist())}
    rows = np.asarray([key[tuple(r)] for r in c.tolist()])
    return QueryModel(name="like " + ";".join(",".join(str(v) for v in r) for r in c.tolist()),
                      descriptors=np.asarray(all_codes, dtype=np.float32)[rows], codec_config=codec.get_config(),
                      codec_state_sha256=codec_state_sha256(codec), voxel_size=m.voxel_size, truncation=m.truncation)


# ------------------------------------------------------------------------------------- resolving a query
def resolve_query(query: Any, m: Map, codec: Codec, *, behind: str | None = None, up: Any = None,
                  tilt: float | None = None) -> QueryModel:
    """Any query :func:`sdfcodec.search.engine.search` accepts (a built-in name, the path of a saved model, a
    :class:`QueryModel`, user blocks ``(N, 16, 16, 16)`` metres) -> a model for the map ``m`` whose descriptors
    come from ``codec`` (the map's) or agree with it (re-encoded, rebuilt for the map's geometry, or checked
    with the probe codes). ``behind``, ``up``, ``tilt`` (see :func:`build_query`) apply to built-in names;
    for a saved model they are refused (it was made with its own)."""
    if isinstance(query, str) and query in QUERY_NAMES:
        # descriptors only: a search never reads the shapes' blocks (16 KiB each: the wall's 2,856 made its cache
        # file 11 MB, zlib-compressed on a first search and inflated on every later one)
        return build_query(query, map=m, behind=behind, up=up, tilt=tilt, keep_blocks=False)
    if isinstance(query, str) and query.startswith("like:"):
        return like_blocks(m, query[5:], codec)
    if (behind, up, tilt) != (None, None, None):
        raise InvalidValueError("behind, up and tilt shape the built-in queries (floor, ceiling, wall, edge, corner); "
                                "a saved model or user blocks carry their own: rebuild the model with them instead")
    if isinstance(query, (str, os.PathLike)) and not (isinstance(query, str) and query in QUERY_NAMES):
        p = Path(query)
        if p.suffix == ".npz" or p.is_file():
            query = load_query(p)
        elif isinstance(query, str):
            check_query_name(query)  # raises the "unknown query" error naming the built-ins
    if isinstance(query, str):
        return build_query(query, map=m)
    if isinstance(query, np.ndarray):
        return build_query(query, map=m)
    if not isinstance(query, QueryModel):
        raise InvalidValueError(f"query must be a built-in name {QUERY_NAMES}, the path of a saved query model, "
                                f"a QueryModel or blocks (N, 16, 16, 16); got {type(query).__name__}")
    same_geometry = (math.isclose(query.voxel_size, m.voxel_size, rel_tol=1e-6)
                     and np.allclose(query.truncation, m.truncation, rtol=1e-6, atol=1e-9))
    if not same_geometry and query.spec is not None:
        s = query.spec
        return build_query(s["shape"], map=m, up=s["up"], rotations=s["rotations"], offsets=s["offsets"],
                           behind=s["behind"], keep_blocks=query.blocks is not None, name=query.name,
                           weighted=s.get("weighted"))
    if not same_geometry:
        warnings.warn(f"query model {query.name!r} was made for voxel size {query.voxel_size} m and truncation "
                      f"{query.truncation}, but the map has {m.voxel_size} m and {m.truncation}; its blocks are "
                      "used as they are (rebuild the model for this map to compare like with like)",
                      SDFCodecWarning, stacklevel=3)
    if query.matches_codec(codec, m.header.codec.state_sha256):
        return query
    if query.spec is not None and query.blocks is not None:  # a built-in shape: rebuilt as it was made
        s = query.spec
        return build_query(s["shape"], map=m, up=s["up"], rotations=s["rotations"], offsets=s["offsets"],
                           behind=s["behind"], name=query.name, weighted=s.get("weighted"))
    if query.blocks is not None:
        weighted = map_context(m, behind="solid").weighted
        return replace(query, descriptors=encode_query_blocks(codec, query.blocks, None, query.truncation,
                                                              query.voxel_size, weighted),
                       codec_config=codec.get_config(), codec_state_sha256=codec_state_sha256(codec),
                       probe_codes=encode_array(codec, probe_blocks(query.voxel_size, query.truncation)))
    # descriptors only: usable where the map's codec encodes the probe blocks to the same leading elements
    if query.probe_codes is None:
        raise InvalidValueError(f"query model {query.name!r} holds neither shape blocks nor probe codes, and its "
                                f"codec ({query.codec_config}) is not the map's; rebuild it with "
                                "build_query(..., map=the_map)")
    k = min(query.code_size, m.code_size)
    if not m.header.codes.prefix_ordered and query.code_size != m.code_size:
        raise InvalidValueError(f"query model {query.name!r} has {query.code_size}-element descriptors but the map's "
                                f"{m.header.codec.id!r} codes ({m.code_size}) are not prefix-ordered; rebuild the "
                                "model with build_query(..., map=the_map)")
    mine = encode_array(codec, probe_blocks(query.voxel_size, query.truncation))[:, :k]
    theirs = query.probe_codes[:, :k]
    if not np.allclose(mine, theirs, rtol=1e-3, atol=1e-3 * max(1.0, float(np.abs(theirs).max()))):
        raise InvalidValueError(f"query model {query.name!r} was encoded by a different codec or basis than the map "
                                f"{m.location} (model: {query.codec_config.get('id')!r} state "
                                f"{(query.codec_state_sha256 or 'none')[:16]}; map: {m.header.codec.id!r} state "
                                f"{(m.header.codec.state_sha256 or 'none')[:16]}; their first {k} code elements "
                                "disagree), so its descriptors cannot "
                                "be compared with the map's codes; rebuild it with build_query(..., map=the_map), or "
                                "keep its blocks (keep_blocks=True) so it can be re-encoded")
    return query
