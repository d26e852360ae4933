"""Retrieval metrics: precision/recall of finding labelled blocks in maps of synthetic rooms
(:func:`evaluate_retrieval`, with the ground-truth definitions :data:`TRUTH`), and the curve summaries
(:func:`pr_curve`, :func:`operating_points`) behind the figures of ``docs/search.md``.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from ..codec import Codec
from .rooms import LabelledRoom
from ..errors import InvalidValueError
from ..map import open_map
from .engine import search
from .query import build_query

__all__ = [
    "TRUTH",
    "PURE_MIN_SURFACE",
    "SLIVER_SECTION",
    "pr_curve",
    "operating_points",
    "evaluate_retrieval",
]


def _clean(lab: dict, kind: str = "floor") -> np.ndarray:
    if f"{kind}_section_cover" in lab:  # the surface's own plane (any angle to the grid)
        return ((lab[f"{kind}_main"] >= 0.9) & (lab[f"{kind}_section_cover"] >= 0.9)
                & (lab[f"{kind}_section"] >= SLIVER_SECTION))
    return (lab[kind] >= 0.9) & (lab[f"{kind}_cover"] >= 0.9)


def _sliver(lab: dict, kind: str) -> np.ndarray:
    """Blocks whose surface is that surface alone but only clips a corner: left out of the strict truth."""
    if f"{kind}_section" not in lab:
        return np.zeros(len(lab[kind]), bool)
    return (lab[f"{kind}_main"] >= 0.9) & (lab[f"{kind}_section"] < SLIVER_SECTION)


def _strict(kind: str) -> Callable[[dict], tuple[np.ndarray, np.ndarray]]:
    return lambda lab: (_clean(lab, kind), ~_clean(lab, kind) & ~_sliver(lab, kind))


#: The strict truths leave out blocks whose section of the surface's plane is smaller than this (voxels
#: squared, a quarter of a block face): a plane clipping a block's corner.
SLIVER_SECTION = 64.0


def _pure(lab: dict, kind: str) -> np.ndarray:
    return (lab[kind] >= 0.9) & (lab["surface_voxels"] >= PURE_MIN_SURFACE)


#: The ``*-pure`` truths: a block with at least this many surface voxels, >= 90 % of them on the surface.
PURE_MIN_SURFACE = 64


#: Ground-truth definitions for :func:`evaluate_retrieval`: ``name -> f(block_labels) -> (positive, negative)``
#: boolean masks (blocks in neither are left out of precision and recall). A *clean floor block*: >= 90 % of
#: its surface voxels lie on the floor, and the floor covers >= 90 % of its section of the block, measured in the
#: floor's own plane (``LabelledRoom.block_labels``: ``floor_main``, ``floor_section_cover``; a tilted floor or a
#: wall crossing a block obliquely covers all of its section, a surface ending inside the block does not), a
#: section of at least :data:`SLIVER_SECTION`; a *partial* one holds some floor but is not clean (blocks shared
#: with walls or furniture, surfaces ending inside the block). Clean walls and ceilings alike, each on one wall
#: or ceiling primitive (a block holding two walls is a corner, not a wall block).
#:
#: ``"floor"``: clean floor blocks against all others but slivers (a surface alone in the block that only
#: clips its corner, left out; partial ones count as false positives when retrieved);
#: ``"floor-vs-none"``: clean floor blocks against blocks holding no floor at all (partial ones left out);
#: ``"floor-majority"``: blocks whose surface is at least half floor (``RoomScene.floor_blocks``) against all
#: others; ``"up"``: clean upward-facing blocks (floor and furniture tops alike) against all others; ``"wall"``,
#: ``"ceiling"``: clean wall or ceiling blocks (the same 90 % / 90 % rule) against all others; ``"floor-pure"``,
#: ``"wall-pure"``, ``"ceiling-pure"``: blocks whose surface is >= 90 % that surface (at least
#: :data:`PURE_MIN_SURFACE` surface voxels, however little of the cross-section it covers: a wall crossing a
#: block obliquely, a tilted floor) against blocks with < 10 % of it; mixed blocks are left out.
#: ``"edge"``, ``"corner"``: see :func:`_parts`; ``"pole"``: blocks whose surface is >= 90 % the sides of thin
#: upright primitives (cylinders and table legs up to 10 voxels across the axis) against blocks with < 10 %.
TRUTH: dict[str, Callable[[dict], tuple[np.ndarray, np.ndarray]]] = {
    "floor": _strict("floor"),
    "floor-vs-none": lambda lab: (_clean(lab), lab["floor"] == 0),
    "floor-majority": lambda lab: (lab["floor"] >= 0.5, lab["floor"] < 0.5),
    "up": lambda lab: (_clean(lab, "up"), ~_clean(lab, "up")),
    "wall": _strict("wall"),
    "ceiling": _strict("ceiling"),
    **{f"{k}-pure": (lambda k: lambda lab: (_pure(lab, k), lab[k] < 0.1))(k) for k in ("floor", "wall", "ceiling")},
    "edge": lambda lab: _parts(lab, 2),
    "corner": lambda lab: _parts(lab, 3),
    "pole": lambda lab: (_pure(lab, "pole"), lab["pole"] < 0.1),
}


def _parts(lab: dict, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Edges (``k`` = 2) and corners (3) of a room: blocks whose surface is >= 90 % the room's structure, on
    exactly ``k`` floor, wall or ceiling primitives holding >= 10 % each and no other holding 2 %, against blocks
    not near ``k`` of them; blocks near ``k`` with a smaller share (the edge passes near the block's face) and
    corners for the edge truth are left out."""
    near = (lab["structure"] >= 0.9) & (lab["structure_touch"] >= k)
    pos = (near & (lab["structure_parts"] == k) & (lab["structure_touch"] == k)
           & (lab["surface_voxels"] >= PURE_MIN_SURFACE))
    return pos, ~near


# ------------------------------------------------------------------------------------- evaluation: metrics
def pr_curve(scores: np.ndarray, labels: np.ndarray) -> dict:
    """Precision and recall of "score <= t" for every distinct threshold ``t``.

    Parameters
    ----------
    scores : np.ndarray
        ``(N,)`` lower is more similar.
    labels : np.ndarray
        ``(N,)`` bool ground truth.

    Returns
    -------
    dict
        ``thresholds``, ``precision``, ``recall`` ``(T,)`` float64 arrays (ascending thresholds), and
        ``positives`` (count).
    """
    s = np.asarray(scores, dtype=np.float64)
    y = np.asarray(labels, dtype=bool)
    order = np.argsort(s, kind="stable")
    s, y = s[order], y[order]
    tp = np.cumsum(y)
    k = np.arange(1, len(s) + 1)
    last = np.r_[np.flatnonzero(np.diff(s) > 0), len(s) - 1]  # the last index of each distinct score
    pos = max(int(y.sum()), 1)
    return {"thresholds": s[last], "precision": tp[last] / k[last], "recall": tp[last] / pos,
            "positives": int(y.sum())}


def operating_points(curve: dict, target: float = 0.9) -> dict:
    """Summaries of a :func:`pr_curve`: average precision (``ap``: precision summed over recall steps), the
    best F1 and its threshold, the highest precision at recall ``>= target`` and the highest recall at
    precision ``>= target`` with their thresholds (None when unreachable)."""
    p, r, t = curve["precision"], curve["recall"], curve["thresholds"]
    ap = float(np.sum(np.diff(np.r_[0.0, r]) * p))
    f1 = np.where(p + r > 0, 2 * p * r / np.maximum(p + r, 1e-12), 0.0)
    i = int(np.argmax(f1))
    out = {"ap": ap, "best_f1": float(f1[i]), "best_f1_threshold": float(t[i]),
           "best_f1_precision": float(p[i]), "best_f1_recall": float(r[i])}
    # the best of one measure where the other reaches the target (None when it never does)
    for name, ok, best in (("precision_at_recall", r >= target, p), ("recall_at_precision", p >= target, r)):
        j = np.flatnonzero(ok)[np.argmax(best[ok])] if ok.any() else None
        out[name] = None if j is None else float(best[j])
        out[f"{name}_threshold"] = None if j is None else float(t[j])
    return out


def evaluate_retrieval(rooms: Sequence[LabelledRoom], codecs: Mapping[str, Codec], *,
                       queries: Mapping[str, Mapping[str, Any]] | None = None,
                       levels: Mapping[str, Sequence[int]] | None = None, truths: Sequence[str] = ("floor",),
                       workdir: str | os.PathLike | None = None, keep_curves: bool = True,
                       progress: Callable[[str], None] | None = None) -> list[dict]:
    """Precision/recall of retrieving labelled blocks from maps of synthetic rooms.

    Each room is written as a map per codec (``create_map`` + ``write_volume``: the real pipeline), each map
    searched with each query at each level (every coded block scored), and the scores of all rooms pooled
    (one threshold for all rooms). Ground truth: :data:`TRUTH` definitions of
    :meth:`LabelledRoom.block_labels`.

    Parameters
    ----------
    rooms : sequence of LabelledRoom
    codecs : mapping of str to Codec
        Name (e.g. ``"pca-64"``) -> fitted codec.
    queries : mapping of str to dict, optional
        Name -> :func:`build_query` keyword arguments (``shape`` and options; ``map`` is added). Default:
        ``{"floor": {"shape": "floor"}}``. ``"up": "room"`` uses each room's true up direction.
    levels : mapping of str to sequence of int, optional
        Codec name -> levels to search at (default: the full size).
    truths : sequence of str
        Keys of :data:`TRUTH`.
    workdir : path, optional
        Where maps are written (default: a temporary directory, removed afterwards).
    keep_curves : bool
        Include the PR curve arrays in the records.

    Returns
    -------
    list of dict
        One record per (codec, query, level, truth): ``codec``, ``code_size``, ``query``, ``level``,
        ``descriptors``, ``truth``, ``rooms``, ``blocks`` (counted in precision/recall), ``positives``,
        ``partial`` (blocks holding some floor but not clean floor), the :func:`operating_points` fields,
        ``partial_selected`` (partial blocks under the best-F1 threshold) and, with ``keep_curves``, ``curve``
        (``thresholds``, ``precision``, ``recall`` lists).
    """
    import tempfile

    from ..map import create_map

    queries = queries or {"floor": {"shape": "floor"}}
    for t in truths:
        if t not in TRUTH:
            raise InvalidValueError(f"unknown truth {t!r}; choose from {sorted(TRUTH)}")
    tmp = tempfile.TemporaryDirectory(prefix="sdfcodec-eval-") if workdir is None else None
    root = Path(tmp.name if tmp else workdir)
    pooled: dict[tuple, list] = {}
    try:
        for r_i, room in enumerate(rooms):
            labels = None
            for cname, codec in codecs.items():
                path = root / f"room{r_i}-{cname}.sdfz"
                with create_map(path, codec=codec, voxel_size=room.voxel_size, truncation=room.truncation,
                                origin=tuple(room.origin), overwrite=True, tool="sdfcodec.search.evaluate") as w:
                    w.write_volume(room.volume)
                m = open_map(path)
                for qname, kw in queries.items():
                    kw = dict(kw)
                    if isinstance(kw.get("up"), str) and kw["up"] == "room":
                        kw["up"] = room.up
                    model = build_query(kw.pop("shape", "floor"), map=m, **kw)
                    for lv in (levels or {}).get(cname, [m.code_size]):
                        res = search(m, model, level=lv, keep_scores=True, device="cpu")
                        if labels is None or not np.array_equal(labels["coords"], res.all_coords):
                            labels = {"coords": res.all_coords, **room.block_labels(res.all_coords)}
                        partial = (labels["floor"] > 0) & ~_clean(labels)
                        for t in truths:
                            pos, neg = TRUTH[t](labels)
                            keep = pos | neg
                            pooled.setdefault((cname, m.code_size, qname, lv, len(model), t), []).append(
                                (res.all_scores[keep], pos[keep], partial[keep], res.all_scores[partial]))
                if progress:
                    progress(f"room {r_i + 1}/{len(rooms)} {cname}")
    finally:
        if tmp is not None:
            tmp.cleanup()
    records = []
    for (cname, size, qname, lv, n_desc, t), parts in pooled.items():
        s = np.concatenate([p[0] for p in parts])
        y = np.concatenate([p[1] for p in parts])
        partial_scores = np.concatenate([p[3] for p in parts])
        curve = pr_curve(s, y)
        ops = operating_points(curve)
        rec = {"codec": cname, "code_size": size, "query": qname, "level": lv, "descriptors": n_desc, "truth": t,
               "rooms": len(parts), "blocks": int(len(s)), "positives": int(y.sum()), "partial": len(partial_scores),
               **ops, "partial_selected": int((partial_scores <= ops["best_f1_threshold"]).sum())}
        if keep_curves:
            rec["curve"] = {k: np.asarray(curve[k]).tolist() for k in ("thresholds", "precision", "recall")}
        records.append(rec)
    return records
