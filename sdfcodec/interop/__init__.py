"""Other systems' map files: voxblox TSDF layers (:mod:`sdfcodec.interop.voxblox`), Open3D VoxelBlockGrids
(:mod:`sdfcodec.interop.open3d_grid`), and their streaming into and out of sdfcodec maps
(:mod:`sdfcodec.interop.importer`: :func:`import_map`, :func:`export_map`)."""

from __future__ import annotations

from ..core._lazy import lazy_exports

__all__ = ["import_map", "export_map"]

__getattr__, __dir__ = lazy_exports(__name__, {"import_map": ".importer", "export_map": ".importer"})
