"""Data: synthetic TSDF blocks and scenes, synthetic labelled rooms (``rooms``), RGB-D sequence readers and
renderers, sub-volume sampling. Import the submodules (``sdfcodec.search.rooms``, ``sdfcodec.data.render``, ...)."""

__all__: list[str] = []
