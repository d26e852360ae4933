"""sdfcodec: compress truncated signed distance field (TSDF) maps into per-block codes.

    import sdfcodec
    codec = sdfcodec.get_codec("pca", code_size=64).fit(blocks)      # normalised (N, 16, 16, 16)
    with sdfcodec.create_map("room.sdfz", codec=codec, voxel_size=0.02) as m:
        m.write_volume(tsdf)                                           # metres, (X, Y, Z)
    tsdf_hat = sdfcodec.open_map("room.sdfz").decode_region(level=32)
"""

from __future__ import annotations


__version__ = "0.1.0"

from . import errors
from .core._lazy import lazy_exports

__all__ = ["Codec", "Map", "get_codec", "list_codecs", "register_codec", "pretrained_codec", "open_map", "create_map",
           "update_map", "load_model", "save_model", "import_map", "export_map", "errors", "__version__"]

# Where each public name lives. They load on first use (PEP 562), not at `import sdfcodec`: the codec contract
# imports torch (about 2 s), which `sdfcodec --help`, `--version` and `info` on a local map never need.
_LAZY = {"Codec": ".codec", "Map": ".map", "create_map": ".map", "open_map": ".map", "update_map": ".map",
         "load_model": ".model", "save_model": ".model", "get_codec": ".registry", "list_codecs": ".registry",
         "pretrained_codec": ".registry", "register_codec": ".registry",
         "import_map": ".interop.importer", "export_map": ".interop.importer"}

__getattr__, __dir__ = lazy_exports(__name__, _LAZY)
