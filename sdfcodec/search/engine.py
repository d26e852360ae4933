"""Searching and expanding a map: :func:`search` (score every coded block against
a query model, select by threshold and/or top-k, with :func:`auto_threshold`) and :func:`expand` (decode only
the selected blocks). See :mod:`sdfcodec.search` for the conventions and units.
"""

from __future__ import annotations

import json
import os
import sys
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..core._lazy import lazy_module
from ..core._validate import BLOCK, check_device
from ..core.tiling import one_blas_thread
from ..codec import Codec
from ..errors import InvalidValueError, ShapeError
from ..core.header import BlockState
from ..map import Map, open_map
from ..map.grouping import chunk_box
from ..map.metric import codec_codes
from .arrays import encode_array
from .counting import CountingStore, code_bytes_read, code_chunk_bytes, counting_view, release_view
from .calibrate import SURFACE_SHARE, calibrate_threshold, cone_angle
from .models import QueryModel
from .query import build_query, resolve_query
from .scoring import ObservedScorer, Scorer, score_codes, scored_voxels

__all__ = [
    "AUTO_FRACTION",
    "codes_at",
    "SearchResult",
    "Expansion",
    "auto_threshold",
    "search",
    "expand",
]

torch = lazy_module("torch")  # GPU scoring and codecs without a numpy path only: a CPU search of pca never imports it
#: Device nodes of GPU drivers (NVIDIA; AMD's ROCm, which torch also calls cuda): without one, torch can find no
#: CUDA device, so the default device is the CPU without asking torch.
_GPU_NODES = ("/dev/nvidiactl", "/dev/nvidia0", "/dev/kfd", "/dev/dxg")


# ---------------------------------------------------------------------------------------------- searching
@dataclass
class SearchResult:
    """What :func:`search` found.

    Attributes
    ----------
    coords : np.ndarray
        ``(N, 3)`` int64 block indices of the selected blocks, best (lowest score) first.
    scores : np.ndarray
        ``(N,)`` float32 minimum squared code distance of each to the query's descriptors (see the
        :mod:`sdfcodec.search` docstring for units).
    nearest : np.ndarray
        ``(N,)`` int64 index of the nearest descriptor (into ``query.descriptors``; for the floor model, which
        plane offset).
    level : int
        Code elements compared (``L``).
    query : QueryModel
        The model as used (encoded with the map's codec).
    threshold, top :
        The selection asked for (None: not used).
    stats : dict
        ``blocks_scored`` (every coded block), ``selected``, ``descriptors``, ``level``, ``code_size``,
        ``bytes_read`` (dict per array: ``codes``, ``state``, ``codec``, ``meta``), ``code_bytes_read``,
        ``code_bytes_full`` (all code chunks of the map on disk; local maps, else None),
        ``code_bytes_level`` (the chunks holding the first ``L`` elements), ``seconds``, ``blocks_per_s``,
        ``device``.
    all_coords, all_scores : np.ndarray or None
        Every coded block and its score (``keep_scores=True`` only): ``(B, 3)`` int64 and ``(B,)`` float32.
    """

    coords: np.ndarray
    scores: np.ndarray
    nearest: np.ndarray
    level: int
    query: QueryModel
    threshold: float | None
    top: int | None
    stats: dict = field(default_factory=dict)
    all_coords: np.ndarray | None = None
    all_scores: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.coords)

    def to_json(self, blocks: bool = True) -> dict:
        """JSON-able summary; with ``blocks``, every selected block as ``{"coords": [x, y, z], "score": s}``."""
        out = {"query": self.query.name, "level": self.level, "threshold": self.threshold, "top": self.top,
               **{k: v for k, v in self.stats.items()}}
        if blocks:
            out["blocks"] = [{"coords": [int(c) for c in xyz], "score": float(s)}
                             for xyz, s in zip(self.coords, self.scores)]
        return out


def _default_device(device: Any) -> Any:
    """The device to score on: ``device`` checked, or by default CUDA when available, else ``"cpu"``; a machine
    without a GPU driver has no CUDA to look for, and its search never imports torch."""
    if device == "cpu":  # always there: no torch import to check it
        return "cpu"
    if device is None:
        if not (any(os.path.exists(p) for p in _GPU_NODES) or "torch" in sys.modules):
            return "cpu"
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return check_device(device)


def _search_level(m: Map, query: QueryModel, level: int | None) -> int:
    if level is None:
        level = min(m.code_size, query.code_size)
    _check_map_level(m, level)
    if level > query.code_size:
        raise InvalidValueError(f"level {level} exceeds the query's {query.code_size}-element descriptors; use a "
                                f"level <= {query.code_size}")
    return int(level)


def _check_map_level(m: Map, level: Any) -> None:
    """What the map alone says of ``level`` (checked before the query is built: a bad level costs nothing)."""
    size, prefix = m.code_size, m.header.codes.prefix_ordered
    if isinstance(level, bool) or not isinstance(level, (int, np.integer)) or not 1 <= level <= size:
        raise InvalidValueError(f"level must be an int in 1..{size} (the map's code size), got {level!r}")
    if level < size and not prefix:
        raise InvalidValueError(f"the map's {m.header.codec.id!r} codes are not prefix-ordered, so their first "
                                f"{level} of {size} elements are not a coarser descriptor and a prefix search is "
                                f"meaningless; search at the full size (omit level / --level), or encode the map "
                                "with a prefix-ordered codec such as pca")


#: :func:`auto_threshold`'s fraction of the model's median nearest-neighbour squared distance.
AUTO_FRACTION = 0.15


def auto_threshold(model: QueryModel, level: int | None = None, codec: Codec | None = None) -> float:
    """A default threshold from the model's own resolution: ``AUTO_FRACTION`` (0.15) times the median squared
    distance between each descriptor and its nearest other descriptor, over the first ``level`` elements.
    For a built-in model sampled over extra rotations, the spacing is that of its unrotated shapes (rebuilt
    with ``codec``, the one that made the descriptors), so rotation sampling does not tighten the threshold.

    For the default floor model (17 planes a voxel apart) this gives 7.2 / 12.8 / 16.8 at levels 32 / 64 / 128
    with the shipped eigenshapes, close to the thresholds that maximise F1 on synthetic rooms (6.9 / 13.0 /
    23.7, docs/search.md). It is a heuristic: pick a threshold from a PR curve, or use ``top``, when it
    matters.

    Raises
    ------
    InvalidValueError
        The model has a single descriptor (no spacing to scale from): give a threshold or ``top``.
    """
    spec = model.spec
    if spec is not None and spec.get("rotations", "none") != "none" and codec is not None:
        model = build_query(spec["shape"], codec=codec, voxel_size=model.voxel_size, truncation=model.truncation,
                            up=spec["up"], offsets=spec["offsets"], behind=spec["behind"], keep_blocks=False)
    q = model.descriptors[:, :level] if level else model.descriptors
    if len(q) < 2:
        raise InvalidValueError(f"query model {model.name!r} has one descriptor, so no automatic threshold can be "
                                "derived; pass threshold= (--threshold) or top= (--top)")
    d = np.einsum("ij,ij->i", q, q)[:, None] - 2 * q @ q.T + np.einsum("ij,ij->i", q, q)[None]
    np.fill_diagonal(d, np.inf)
    return float(AUTO_FRACTION * np.median(np.maximum(d.min(axis=1), 0.0)))


# numpy's BLAS at one thread throughout: a search's products are small (a few hundred blocks against a model, the
# plane check's (n, 4096) x (4096, 3)), and OpenBLAS's second thread, woken for each and waiting on a core busy
# elsewhere, made them 2-4x slower on two loaded cores (the plane check's own-plane fit: 0.12 s of CPU with one
# thread, 0.26-0.30 s with two); the large products tile themselves over the cores (ObservedScorer)
@one_blas_thread()
def search(map: Map | str | os.PathLike, query: Any = "floor", *, level: int | None = None,
           threshold: float | str | None = None, top: int | None = None, device: str | torch.device | None = None,
           keep_scores: bool = False, chunks_per_batch: int = 8, behind: str | None = None, up: Any = None,
           tilt: float | None = None, scene: bool = True) -> SearchResult:
    """Score every coded block of a map against a query model and select the closest.

    Streams the map's codes a few chunks at a time (``Map.iter_codes``), reading only the code chunks that
    hold the first ``level`` elements; memory is bounded by the batch plus the selection (and, with
    ``keep_scores``, 28 bytes per coded block).

    Parameters
    ----------
    map : Map or path
        A committed map (open_map), or its path/URL.
    query : str, path, QueryModel or np.ndarray
        A built-in name (:data:`QUERY_NAMES`; built for this map with :func:`build_query` defaults), the path
        of a saved model (``.npz``), a :class:`QueryModel` (re-encoded with the map's codec when it has
        blocks; descriptors-only models must agree with the map's codec), or user blocks ``(N, 16, 16, 16)``
        in metres.
    level : int, optional
        Compare the first ``level`` code elements (prefix-ordered codecs; default: all the map and query
        have in common).
    threshold : float or "auto", optional
        Select blocks whose score is ``<= threshold``; ``"auto"``: :func:`auto_threshold` of the model.
    top : int, optional
        Select at most ``top`` best blocks (with ``threshold``: the best ``top`` under it). With neither,
        every coded block is returned.
    device : str or torch.device, optional
        Where the distances are computed; default CUDA when available, else the CPU.
    keep_scores : bool
        Also return every coded block's coordinates and score (for pictures and PR curves).
    chunks_per_batch : int
        Code chunks read per step (memory vs. call overhead).
    scene : bool
        For the built-in floor, ceiling and wall models: after scoring, keep what the query means in the map
        (:func:`sdfcodec.search.scene.scene_select`: the lowest large up-facing level, the highest down-facing
        one that closes the map, large vertical patches); the candidates are the blocks under the threshold
        (the calibrated one when only ``top`` is given) and those up to ``WEAK_FACTOR`` times it that continue
        their planes. ``False``: the shape score alone (``--shape-only``).

    Returns
    -------
    SearchResult

    Raises
    ------
    InvalidValueError
        A prefix level on a map whose codes are not prefix-ordered, a bad level/threshold/top, or a
        descriptors-only model made by another codec.
    """
    t0 = time.perf_counter()
    m = map if isinstance(map, Map) else open_map(map)
    if threshold is not None and threshold != "auto" and (isinstance(threshold, (str, bool)) or not (
            np.isfinite(threshold) and threshold >= 0)):
        raise InvalidValueError(f"threshold must be a finite squared distance >= 0 or 'auto', got {threshold!r}")
    if top is not None and (isinstance(top, bool) or not isinstance(top, (int, np.integer)) or top < 1):
        raise InvalidValueError(f"top must be a positive int, got {top!r}")
    if level is not None:
        _check_map_level(m, level)
    view, store = counting_view(m)
    codec = view.codec  # loads (and counts) the codec state unless the map already holds it
    model = resolve_query(query, m, codec, behind=behind, up=up, tilt=tilt)
    lv = _search_level(m, model, level)
    dev = _default_device(device)
    scorer = Scorer(model.descriptors[:, :lv], dev)
    masked = any(a is not None for a in view.reader.observation_arrays())
    obs_scorer = ObservedScorer(model.descriptors[:, :lv], codec, m.truncation, m.voxel_size) if masked else None
    threshold_info = {"method": "given"} if threshold not in (None, "auto") else None
    if threshold == "auto":
        threshold, threshold_info = calibrate_threshold(model, codec, lv, scorer, obs_scorer)
    from .scene import SCENE_QUERIES, WEAK_FACTOR, scene_select

    rot = (model.spec or {}).get("rotations", "none")
    staged = (bool(scene) and (model.spec or {}).get("shape") in SCENE_QUERIES and model.rotations is not None
              and (rot == "none" or 0 < cone_angle(rot) <= 45))  # not "axis": a floor model then holds walls
    stage_t = threshold
    if staged and stage_t is None:  # top only: the scene stage still needs to know which blocks are the shape
        stage_t, _ = calibrate_threshold(model, codec, lv, scorer, obs_scorer)
    # blocks scoring up to WEAK_FACTOR times the threshold may still join the plane they continue (scene stage)
    loop_t = WEAK_FACTOR * stage_t if staged else threshold

    sel_c, sel_s, sel_i = np.zeros((0, 3), np.int64), np.zeros(0, np.float32), np.zeros(0, np.int64)
    sel_q = np.zeros((0, lv), np.float32)
    all_c, all_s = [], []
    held: list | None = [] if staged else None  # the streamed codes, for the plane check (read once)
    held_bytes = 0
    n_scored = 0
    def scored(coords: np.ndarray, codes: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        # in the reader's fetching threads, so that scoring a batch overlaps reading the next ones; metric codes
        # (spec 4f) scored as the codec encodes them, normalised
        codes = codec_codes(m.header.codes, m.truncation, codes)
        return codes, *score_codes(scorer, obs_scorer, codes, scored_voxels(view, coords) if masked else None,
                                   bound=None if keep_scores else loop_t)  # bounded: scores over it not exact

    whole = tuple(slice(0, n) for n in view.reader.grid())
    for coords, (codes, s, idx) in view.reader.fetch_stream(whole, lv, stage=scored, batch_blocks=None,
                                                            chunks_per_group=chunks_per_batch):
        n_scored += len(s)
        if held is not None:
            held.append((np.array(coords, np.int64), np.array(codes, np.float32)))  # copies: batches may be reused
            held_bytes += held[-1][1].nbytes
            if held_bytes > HOLD_CODES_BYTES:
                held = None  # a map too large to hold: the plane check reads its planes' chunks again
        if keep_scores:
            all_c.append(coords)
            all_s.append(s)
        keep = np.ones(len(s), bool) if loop_t is None else s <= loop_t
        if not keep.any():
            continue
        sel_c = np.concatenate([sel_c, coords[keep]])
        sel_s = np.concatenate([sel_s, s[keep]])
        sel_i = np.concatenate([sel_i, idx[keep]])
        sel_q = np.concatenate([sel_q, np.asarray(codes, np.float32)[keep]])  # to tell surfaces from solid
        if top is not None and not staged and len(sel_s) > top:
            # running top-k: memory stays O(top + batch)
            part = np.argpartition(sel_s, top - 1)[:top]
            sel_c, sel_s, sel_i, sel_q = sel_c[part], sel_s[part], sel_i[part], sel_q[part]
    scene_info = None
    surf_t = stage_t if staged else threshold
    has_surface = _surface_test(view, codec, lv, surf_t) if surf_t is not None else None
    if has_surface is not None and (model.spec or {}).get("shape") and len(sel_c):
        # a built-in shape near a block's face is nearly a solid or a free block: blocks that hold no surface (the
        # solid around an exact room) are no result of any shape query
        real = has_surface(sel_c, sel_q)
        sel_c, sel_s, sel_i = sel_c[real], sel_s[real], sel_i[real]
    if staged:
        coded = np.argwhere(view.block_states() == BlockState.CODED)
        kept, scene_info = scene_select(model.spec["shape"], model, sel_c, sel_s, sel_i, stage_t, coded,
                                        np.asarray(m.origin, np.float64), m.voxel_size, has_surface)
        sel_c, sel_s, sel_i = sel_c[kept], sel_s[kept], sel_i[kept]
        if scene_info.get("planes"):  # the chosen planes checked block by block (sdfcodec.search.plane_check)
            from .plane_check import check_planes

            codes_of = _held_codes(view, lv, held)
            pre = {tuple(c): k for k, c in enumerate(sel_c.tolist())}
            pre_s, pre_i = sel_s, sel_i
            sel_c = check_planes(view, model, scene_info, sel_c, sel_s <= stage_t, coded, codes_of)
            # the streamed scores stand (exact under the loop's bound, which every block the stage kept is); only
            # the blocks the check added are scored (a fused map's partly observed blocks: the model decoded)
            rows = np.array([pre.get(tuple(c), -1) for c in sel_c.tolist()], np.int64)
            old = rows >= 0
            sel_s, sel_i = np.empty(len(sel_c), np.float32), np.empty(len(sel_c), np.int64)
            sel_s[old], sel_i[old] = pre_s[rows[old]], pre_i[rows[old]]
            if not old.all():
                added = sel_c[~old]
                sel_s[~old], sel_i[~old] = score_codes(scorer, obs_scorer, codes_of(added),
                                                       scored_voxels(view, added) if masked else None)
    order = np.lexsort((sel_c[:, 2], sel_c[:, 1], sel_c[:, 0], sel_s))
    sel_c, sel_s, sel_i = sel_c[order], sel_s[order], sel_i[order]
    if top is not None:  # ties at the cut: the lexsort above makes the kept set deterministic only here
        sel_c, sel_s, sel_i = sel_c[:top], sel_s[:top], sel_i[:top]
    seconds = time.perf_counter() - t0
    stats = {
        "map": m.location, "codec": m.header.codec.id, "code_size": m.code_size, "level": lv,
        "descriptors": len(model), "blocks_scored": n_scored, "selected": int(len(sel_c)),
        "bytes_read": dict(store.bytes), "code_bytes_read": code_bytes_read(store),
        **dict(zip(("code_bytes_level", "code_bytes_full"), code_chunk_bytes(m, lv, None))),
        "seconds": seconds, "blocks_per_s": n_scored / seconds if seconds > 0 else None, "device": str(dev),
        "threshold_info": threshold_info, "context": (model.spec or {}).get("context"),
        "observed_scoring": masked, "scene": scene_info,
    }
    release_view(store)
    return SearchResult(
        coords=sel_c, scores=sel_s.astype(np.float32), nearest=sel_i, level=lv, query=model, threshold=threshold,
        top=top, stats=stats,
        all_coords=np.concatenate(all_c) if all_c else (np.zeros((0, 3), np.int64) if keep_scores else None),
        all_scores=np.concatenate(all_s) if all_s else (np.zeros(0, np.float32) if keep_scores else None))


def codes_at(m: Map, coords: np.ndarray, level: int) -> np.ndarray:
    """The first ``level`` code elements ``(N, level)`` float32 of coded blocks ``coords`` ``(N, 3)``, each code
    chunk holding one read once."""
    coords = np.asarray(coords, np.int64).reshape(-1, 3)
    grid = np.asarray(m.grid_blocks)
    cb = m.header.codes.chunk_blocks
    arr = m.reader.codes_array
    chunk_of = coords // cb
    order = np.lexsort(chunk_of.T[::-1])
    bounds = np.flatnonzero(np.any(np.diff(chunk_of[order], axis=0) != 0, axis=1)) + 1
    codes = np.empty((len(coords), level), np.float32)
    for lo, hi in zip(np.r_[0, bounds], np.r_[bounds, len(order)]):
        if lo == hi:
            continue
        idx = order[lo:hi]
        ch = chunk_of[idx[0]]
        box = chunk_box(ch, cb, grid)
        chunk = m.reader.read(arr, (*box, slice(0, level)))
        codes[idx] = chunk[tuple((coords[idx] - ch * cb).T)]
    return codec_codes(m.header.codes, m.truncation, codes)  # metric codes: as the codec encodes them


#: :func:`search` holds the codes it streams, up to this many bytes, so the plane check of a floor, ceiling or wall
#: search reads no chunk twice; beyond it, the check reads the chunks of its planes' blocks again.
HOLD_CODES_BYTES = 256 << 20


def _held_codes(view: Map, level: int, held: list | None):
    """``coords (N, 3) -> codes (N, level)``: from the codes a search held (``[(coords, codes), ...]``), else
    read (:func:`codes_at`)."""
    if held is None:
        return lambda c: codes_at(view, c, level)
    grid = tuple(int(g) for g in view.grid_blocks)
    all_c = np.concatenate([c for c, _ in held]) if held else np.zeros((0, 3), np.int64)
    all_q = np.concatenate([q for _, q in held]) if held else np.zeros((0, level), np.float32)
    keys = np.ravel_multi_index(all_c.T, grid)
    order = np.argsort(keys)
    skeys = keys[order]

    def codes_of(c: np.ndarray) -> np.ndarray:
        c = np.asarray(c, np.int64).reshape(-1, 3)
        return all_q[order[np.searchsorted(skeys, np.ravel_multi_index(c.T, grid))]]

    return codes_of


def _surface_test(view: Map, codec: Codec, level: int, t: float):
    """``coords (N, 3) -> (N,) bool``: whether each coded block holds a surface, i.e. its code is farther than
    :data:`SURFACE_SHARE` of ``t`` (the query's threshold) from the codes of a block of solid and a block of free
    space. An exact SDF codes the solid around a room too; those blocks are no surface above or below anything."""
    ref: list[Scorer] = []  # made on first use: encoding costs a search that selects nothing ~20 ms

    def has_surface(coords: np.ndarray, codes: np.ndarray | None = None) -> np.ndarray:
        if not len(coords):
            return np.zeros(0, bool)
        if not ref:
            const = np.stack([np.zeros((BLOCK,) * 3, np.float32), np.ones((BLOCK,) * 3, np.float32)])
            ref.append(Scorer(encode_array(codec, const)[:, :level], "cpu"))
        return ref[0](codes_at(view, coords, level) if codes is None else codes)[0] > SURFACE_SHARE * t

    return has_surface


# ---------------------------------------------------------------------------------------------- expanding
@dataclass
class Expansion:
    """Selected blocks decoded from a map (:func:`expand`).

    Attributes
    ----------
    coords : np.ndarray
        ``(N, 3)`` int64 block indices.
    blocks : np.ndarray
        ``(N, 16, 16, 16)`` float32 metres (voxels ``(x, y, z)``), decoded at ``level``.
    origin : np.ndarray
        ``(3,)`` float64 metres, world position of the map's voxel ``(0, 0, 0)``.
    voxel_size : float
    truncation : tuple of float
    level : int
    dense : np.ndarray or None
        ``as_="dense"``: ``(16 nx, 16 ny, 16 nz)`` float32 metres over the selected blocks' bounding box,
        ``d_max`` wherever no selected block is (nothing else is decoded).
    dense_offset : np.ndarray or None
        ``(3,)`` int64 map voxel index of ``dense[0, 0, 0]`` (world position ``origin + voxel_size * offset``).
    mesh : open3d.geometry.TriangleMesh or None
        ``as_="mesh"``: marching-cubes mesh of the selected blocks (world metres).
    stats : dict
        ``blocks_decoded``, ``coded_blocks`` (in the whole map), ``code_bytes_read`` (chunks fetched to get
        the selected codes), ``code_bytes_full`` (all code chunks on disk; local maps), ``bytes_read`` (per
        array), ``seconds``.
    """

    coords: np.ndarray
    blocks: np.ndarray
    origin: np.ndarray
    voxel_size: float
    truncation: tuple[float, float]
    level: int
    dense: np.ndarray | None = None
    dense_offset: np.ndarray | None = None
    mesh: Any = None
    stats: dict = field(default_factory=dict)


def expand(map: Map | str | os.PathLike, selection: SearchResult | np.ndarray, as_: str = "blocks", *,
           level: int | None = None, device: str | torch.device | None = None) -> Expansion:
    """Decode only the selected blocks of a map.

    Parameters
    ----------
    map : Map or path
        The map that was searched.
    selection : SearchResult or np.ndarray
        A search result, or block indices ``(N, 3)`` of coded blocks.
    as_ : {"blocks", "dense", "mesh"}
        ``"blocks"``: the decoded blocks; ``"dense"``: also a dense sub-volume over their bounding box;
        ``"mesh"``: also a marching-cubes mesh (``sdfcodec.fusion.tsdf.mesh_from_blocks``, open3d).
    level : int, optional
        Decode from the first ``level`` code elements (default: the full code, the best reconstruction,
        whatever level the search compared).
    device : str or torch.device, optional
        Where to decode (default CUDA when available, else the CPU); results are numpy.

    Returns
    -------
    Expansion
    """
    t0 = time.perf_counter()
    if as_ not in ("blocks", "dense", "mesh"):
        raise InvalidValueError(f"as_ must be 'blocks', 'dense' or 'mesh', got {as_!r}")
    m = map if isinstance(map, Map) else open_map(map)
    coords = selection.coords if isinstance(selection, SearchResult) else np.asarray(selection)
    if coords.ndim != 2 or coords.shape[1] != 3 or coords.dtype.kind not in "iu":
        raise ShapeError(f"selected block coords must be an integer (N, 3) array, got {coords.shape} {coords.dtype}")
    coords = coords.astype(np.int64)
    view, store = counting_view(m)
    lv = view.reader.level(level)
    dev = _default_device(device)
    states = view.block_states()
    grid = np.asarray(m.grid_blocks)
    if len(coords) and (coords.min() < 0 or np.any(coords >= grid)):
        raise InvalidValueError(f"selected blocks lie outside the map's block grid {tuple(grid)}")
    if len(coords) and np.any(states[tuple(coords.T)] != BlockState.CODED):
        raise InvalidValueError("some selected blocks are not coded in this map (empty or unobserved): select from "
                                "a search of this map")
    codec = view.codec
    d_min, d_max = m.truncation
    blocks = np.empty((len(coords), BLOCK, BLOCK, BLOCK), np.float32)
    if codec.halo:
        # codecs that need neighbour context: decode each block's region (the map reader adds the context)
        for i, c in enumerate(coords):
            region = tuple((int(a) * BLOCK, min(int(a + 1) * BLOCK, n)) for a, n in zip(c, m.shape_voxels))
            out = view.decode_region(region, level=lv, device=dev).cpu().numpy()
            blocks[i] = d_max
            blocks[i][tuple(slice(0, s) for s in out.shape)] = out
    elif len(coords):
        codes = codes_at(view, coords, lv)
        for i in range(0, len(coords), 65536):
            v = codec.decode(torch.from_numpy(codes[i:i + 65536]).to(dev))
            # truncated to [d_min, d_max] as the map reader's decodes (a lossy decode may overshoot)
            blocks[i:i + 65536] = (v * (d_max - d_min) + d_min).clamp_(d_min, d_max).cpu().numpy()
    out = Expansion(coords=coords, blocks=blocks, origin=np.asarray(m.origin, np.float64), voxel_size=m.voxel_size,
                    truncation=m.truncation, level=lv)
    if as_ == "dense" and len(coords):
        lo, hi = coords.min(axis=0), coords.max(axis=0) + 1
        nbytes = int(np.prod(hi - lo)) * BLOCK ** 3 * 4
        if nbytes > m.max_decode_bytes:
            raise InvalidValueError(f"the selected blocks' bounding box needs {nbytes / 2**30:.1f} GiB as a dense "
                                    f"volume, above the limit of {m.max_decode_bytes / 2**30:.1f} GiB; use "
                                    "as_='blocks' or raise max_decode_bytes in open_map()")
        dense = np.full(tuple(int(n) * BLOCK for n in hi - lo), d_max, np.float32)
        for c, b in zip(coords - lo, blocks):
            dense[c[0] * BLOCK:(c[0] + 1) * BLOCK, c[1] * BLOCK:(c[1] + 1) * BLOCK, c[2] * BLOCK:(c[2] + 1) * BLOCK] = b
        out.dense, out.dense_offset = dense, lo * BLOCK
    elif as_ == "dense":
        out.dense, out.dense_offset = np.full((0, 0, 0), d_max, np.float32), np.zeros(3, np.int64)
    if as_ == "mesh":
        from ..fusion.tsdf import mesh_from_blocks

        out.mesh = mesh_from_blocks(coords, blocks, origin=m.origin, voxel_size=m.voxel_size, truncation=m.truncation)
    out.stats = {"blocks_decoded": int(len(coords)), "coded_blocks": int((states == BlockState.CODED).sum()),
                 "level": lv, "code_bytes_read": code_bytes_read(store),
                 "code_bytes_full": code_chunk_bytes(m, None)[0], "bytes_read": dict(store.bytes),
                 "seconds": time.perf_counter() - t0}
    release_view(store)
    return out
