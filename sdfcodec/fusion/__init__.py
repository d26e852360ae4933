"""Fusion: depth frames into TSDF blocks with open3d (:mod:`~sdfcodec.fusion.tsdf`: :func:`fuse`, meshes of
blocks) and online fusion into a compressed map with a bounded working set (:mod:`~sdfcodec.fusion.online`).
The frames come from :mod:`sdfcodec.data`."""

__all__: list[str] = []
