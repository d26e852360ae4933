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
from .codec import Codec
from .map import Map, create_map, open_map, update_map
from .model import load_model, save_model
from .registry import get_codec, list_codecs, pretrained_codec, register_codec

__all__ = ["Codec", "Map", "get_codec", "list_codecs", "register_codec", "pretrained_codec", "open_map", "create_map",
           "update_map", "load_model", "save_model", "errors", "__version__"]
