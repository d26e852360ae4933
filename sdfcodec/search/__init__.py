"""Descriptor search and selective expansion of compressed maps (the paper's section V-C, Fig. 7).

Similar blocks get similar codes, so a map's codes double as shape descriptors. A *query model* is a small set
of descriptors made by encoding shapes of interest with the map's own codec: the paper's floor model is the
TSDF of a horizontal plane at 15 offsets across a block. :func:`search` scores every coded block of a map by
its minimum squared distance to the set (one matrix product per streamed batch of chunks), selects by
threshold and/or top-k, and :func:`expand` decodes only the selected blocks (as blocks, a dense sub-volume or
a mesh). Nothing else of the map is decoded.

Conventions
-----------
* Block voxel ``(i, j, k)`` sits at ``(i, j, k)`` voxel units inside its block; shapes are posed about the
  block's centre ``(7.5, 7.5, 7.5)``, and the 15 plane offsets are the midpoints of 15 equal parts of the
  block's extent ``[-0.5, 15.5]`` (its voxels' cells), 1.07 voxels apart, so every plane that crosses a block
  is within 0.53 voxels of one of them.
* ``up`` is the world direction of "up" in the map's grid. The shapes are defined with ``+z`` up and rotated
  onto ``up``. By default it comes from the map (:func:`sdfcodec.search.context.map_context`): the header's
  optional ``up`` field (``sdfcodec fuse`` records a 7-Scenes sequence's gravity there), else an estimate from
  the map's level surfaces (``+z`` when they say the map is level within a degree). ``up=`` / ``--up`` wins.
* ``behind``: how the shapes treat voxels more than ``|d_min|`` behind a surface. ``"unobserved"`` stores them
  as free space ``d_max``, which is what fusion produces (a camera never sees behind a surface, see
  ``sdfcodec/fusion/tsdf.py``); ``"solid"`` clips them to ``d_min``, as a truncated exact SDF of a solid
  (``write_volume(sample_volume(...))``) does. By default it comes from the map: ``"unobserved"`` for maps
  that record their observation (fusion weights, observation mask) or were written by ``sdfcodec fuse``, else
  a vote of the map's plane-like blocks between the two plane families. ``behind=`` / ``--behind`` wins.
* Maps with an observation mask were encoded surface-true (weighted least squares,
  :func:`sdfcodec.map.observed.error_weights`). Their queries are encoded the same way, with the mask of what
  a camera would observe of each shape, and sampled at fusion's projective stretches
  (:data:`~sdfcodec.search.shapes.FUSED_STRETCH`); partly observed blocks are scored on their observed voxels
  only (:class:`~sdfcodec.search.scoring.ObservedScorer`).
* ``threshold="auto"`` (the CLI's default) is calibrated on the map searched
  (:func:`~sdfcodec.search.engine.calibrate_threshold`): clean instances of the query's shape with continuous
  parameters, stored, encoded and scored the map's way; the threshold keeps 99 % of them (and, for edges,
  corners and poles, at most 1 % of near-miss shapes). Floor, ceiling and wall searches then keep what the
  query means in the map (:mod:`sdfcodec.search.scene`; ``scene=False`` / ``--shape-only`` skips it).
* Scores are squared Euclidean distances between codes (float32). For ``pca`` maps (``mean="dataset"``)
  they equal squared distances between the blocks' projections onto the first ``L`` eigenshapes, in
  normalised units (``v = (d - d_min) / (d_max - d_min)``, summed over the 4096 voxels); for ``raw`` maps
  they are exact squared voxel distances.

Prefix levels
-------------
For prefix-ordered codecs (PCA), a query encoded with the map's codec and cut to its first ``L`` elements is
compared with the first ``L`` elements of the map's codes, reading only the code chunks that hold them (a
level-32 search of a 128-element map reads a quarter of the code bytes). Maps with different code sizes whose
bases share their leading components (pca-32/64/128 prefixes of one basis) give the same level-``L``
scores. Codecs whose codes are not prefix-ordered (``raw``, ``ae``) are searched at their full size only.

Bytes read are counted by wrapping the map's Zarr store (:class:`CountingStore`): what the search actually
fetched, per array (``codes``, ``state``, ``codec``, metadata), for any store (local, zip, HTTP...).

Query models are saved as ``.npz`` files of plain arrays (:func:`save_query`, :func:`load_query`, never
pickles): the descriptors, optionally the normalised shape blocks (so the model can be re-encoded for any
map), and JSON metadata in a uint8 array.

Evaluation helpers (:func:`synthetic_room`, :func:`evaluate_retrieval`, and ``sdfcodec.bench.bench_search``)
produce the precision/recall curves and throughput figures of ``docs/search.md``.

Layout (one job per module; every name below is re-exported here, so ``from sdfcodec.search import ...``
works as before):

* :mod:`sdfcodec.search.shapes`: the built-in query shapes and rotation sets;
* :mod:`sdfcodec.search.query`: query models, their ``.npz`` files, resolving a query for a map;
* :mod:`sdfcodec.search.context`: what a query must know about the map (behind, up, surface-true encoding);
* :mod:`sdfcodec.search.counting`: the counting store (what a search read) and the code bytes on disk;
* :mod:`sdfcodec.search.engine`: the scoring kernels, the calibrated threshold, :func:`search` (scoring in
  the reader's fetching threads, overlapped with the reads) and :func:`expand`;
* :mod:`sdfcodec.search.scene`: the map-level stage of floor, ceiling and wall searches (the lowest large
  up-facing level, a ceiling that closes the map, large vertical planes);
* :mod:`sdfcodec.search.plane_check`: the plane check that ends those searches (every block a chosen plane
  crosses, checked against that plane with a calibrated threshold; its functions are not re-exported here);
* :mod:`sdfcodec.search.metrics`: precision/recall of retrieval on labelled rooms;
* the labelled rooms themselves are :mod:`sdfcodec.search.rooms`, the rotations :mod:`sdfcodec.core.geometry`, and
  the search benchmark ``sdfcodec.bench.bench_search`` (``sdfcodec.bench.search.bench_search`` still works, with a
  :class:`DeprecationWarning`).
"""

from __future__ import annotations

import warnings
from typing import Any

from .rooms import LabelledRoom, synthetic_room
from ..core.geometry import axis_rotations, rotation_to
from .context import MapContext, estimate_up, map_context
from .counting import CountingStore
from .engine import Expansion, SearchResult, auto_threshold, calibrate_threshold, expand, search
from .metrics import TRUTH, evaluate_retrieval, operating_points, pr_curve
from .query import QueryModel, build_query, load_query, save_query
from .shapes import BEHIND, QUERY_NAMES, ConeRotations, cone_rotations, plane_offsets, query_blocks

__all__ = [
    "QUERY_NAMES",
    "BEHIND",
    "ConeRotations",
    "QueryModel",
    "SearchResult",
    "Expansion",
    "CountingStore",
    "axis_rotations",
    "cone_rotations",
    "rotation_to",
    "plane_offsets",
    "query_blocks",
    "build_query",
    "save_query",
    "load_query",
    "auto_threshold",
    "calibrate_threshold",
    "MapContext",
    "map_context",
    "estimate_up",
    "search",
    "expand",
    "LabelledRoom",
    "synthetic_room",
    "TRUTH",
    "pr_curve",
    "operating_points",
    "evaluate_retrieval",
    "bench_search",
]


def __getattr__(name: str) -> Any:
    # the search benchmark moved to the benchmark module; resolved lazily because sdfcodec.bench imports the
    # conformance toolkit, which a plain search does not need
    if name == "bench_search":
        warnings.warn("sdfcodec.bench.search.bench_search moved to sdfcodec.bench.bench_search; import it from there",
                      DeprecationWarning, stacklevel=2)
        from ..bench import bench_search

        return bench_search
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
