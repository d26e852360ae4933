"""Deprecated: the map lives in the package :mod:`sdfcodec.map` (issue 14). This module re-exports its public
names so that old imports keep working, and warns once on import; import from ``sdfcodec`` or
``sdfcodec.map`` instead."""

from __future__ import annotations

import warnings

from .map import DEFAULT_MAX_DECODE_BYTES, Map, create_map, open_map, state_digest, update_map

__all__ = ["Map", "open_map", "create_map", "update_map", "state_digest", "DEFAULT_MAX_DECODE_BYTES"]

warnings.warn("sdfcodec.mapfile is deprecated: import Map, open_map, create_map, update_map and state_digest from "
              "sdfcodec.map (or sdfcodec)", DeprecationWarning, stacklevel=2)
