"""How a map's bytes are read and written, below the map itself: the guarded stores (:mod:`~sdfcodec.map.io.stores`),
remote reads bounded, timed and retried (:mod:`~sdfcodec.map.io.remote`), shards (:mod:`~sdfcodec.map.io.shards`),
chunk frames (:mod:`~sdfcodec.map.io.frames`), the chunks a remote map stores (:mod:`~sdfcodec.map.io.unlisted`) and what a
metadata document may cost to parse (:mod:`~sdfcodec.map.io.metadata_limits`). Nothing here imports the rest of
:mod:`sdfcodec.map`."""

__all__: list[str] = []
