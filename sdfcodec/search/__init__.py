"""Descriptor search and selective expansion of compressed maps (the paper's section V-C, Fig. 7).

Similar blocks get similar codes, so a map's codes double as shape descriptors. A *query model* is a small set
of descriptors made by encoding shapes of interest with the map's own codec: the paper's floor model is the
TSDF of a horizontal plane at 15 offsets across a block. :func:`sdfcodec.search.engine.search` scores every
coded block of a map by its minimum squared distance to the set (one matrix product per streamed batch of
chunks), selects by threshold and/or top-k, and :func:`sdfcodec.search.engine.expand` decodes only the selected
blocks (as blocks, a dense sub-volume or a mesh). Nothing else of the map is decoded.

    from sdfcodec.search.engine import expand, search
    res = search("room.sdfz", "floor", level=32)
    mesh = expand("room.sdfz", res, as_="mesh")

Conventions
-----------
* Block voxel ``(i, j, k)`` sits at ``(i, j, k)`` voxel units inside its block; shapes are posed about the
  block's centre ``(7.5, 7.5, 7.5)``, and the 15 plane offsets are the midpoints of 15 equal parts of the
  block's extent ``[-0.5, 15.5]``, 1.07 voxels apart, so every plane that crosses a block is within 0.53 voxels
  of one of them.
* ``up`` and ``behind`` come from the map (:func:`sdfcodec.search.context.map_context`: its header, else what
  its blocks say); ``up=`` / ``--up`` and ``behind=`` / ``--behind`` win.
* ``threshold="auto"`` (the CLI's default) is calibrated on the map searched
  (:func:`sdfcodec.search.calibrate.calibrate_threshold`); floor, ceiling and wall searches then keep what the
  query means in the map (:mod:`sdfcodec.search.scene`, ending with :mod:`sdfcodec.search.plane_check`).
* Scores are squared Euclidean distances between codes (float32); for prefix-ordered codecs (PCA) a level-``L``
  search reads only the code chunks of the first ``L`` elements.

Layout, lowest first (each module imports only those above it in this list; ``tests/test_architecture.py``):

* :mod:`~sdfcodec.search.shapes`: the built-in query shapes and rotation sets;
  :mod:`~sdfcodec.search.scene`: the map-level stage of floor, ceiling and wall searches;
  :mod:`~sdfcodec.search.scoring`: the scoring kernels; :mod:`~sdfcodec.search.counting`: what a search read;
* :mod:`~sdfcodec.search.cache`: built query models and thresholds kept in memory and on disk;
* :mod:`~sdfcodec.search.models`: query models, their ``.npz`` files, built-in shapes encoded with a codec;
* :mod:`~sdfcodec.search.calibrate`: the calibrated threshold;
* :mod:`~sdfcodec.search.context`: what a query must know about the map (behind, up, surface-true encoding);
* :mod:`~sdfcodec.search.query`: building a query for a map, resolving any query for one;
* :mod:`~sdfcodec.search.plane_check`: the plane check that ends floor, ceiling and wall searches;
* :mod:`~sdfcodec.search.engine`: :func:`~sdfcodec.search.engine.search` and
  :func:`~sdfcodec.search.engine.expand`;
* :mod:`~sdfcodec.search.rooms`: labelled synthetic rooms; :mod:`~sdfcodec.search.metrics`: precision/recall
  of retrieval on them. The search benchmark is :func:`sdfcodec.bench.search.bench_search`; the ``sdfcodec
  search`` command's work and its pictures, :mod:`sdfcodec.view.search`.
"""

__all__: list[str] = []
