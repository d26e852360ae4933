"""Zarr's ``crc32c`` codec checked by hand, where a chunk is read without Zarr (:mod:`~sdfcodec.map.fastfetch`,
:mod:`~sdfcodec.map.summary`): a chunk's last four bytes are the little-endian CRC32C of the bytes before them."""

from __future__ import annotations

from typing import Any

import google_crc32c  # what Zarr's crc32c codec computes with
import numpy as np

__all__ = ["crc32c_matches"]


def crc32c_matches(data: Any) -> bool:
    """True when ``data`` (any bytes-like object) ends with the CRC32C of the rest, as Zarr writes it."""
    view = np.frombuffer(data, np.uint8)  # slices without a copy; google_crc32c takes arrays, not memoryviews
    return len(view) >= 4 and google_crc32c.value(view[:-4]) == int.from_bytes(view[-4:].tobytes(), "little")
