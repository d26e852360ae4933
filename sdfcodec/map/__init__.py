"""The sdfcodec map: a Zarr v3 group holding per-block codes (``spec/map-format.md`` is normative).

::

    <map>/zarr.json            group; attribute "sdfcodec" = the header (sdfcodec.core.header.MapHeader)
    <map>/codes                (Bx, By, Bz, D) float32|float16|int8|int16 code vectors, chunked (c, c, c, chunk_code)
    <map>/code_scale           (Bx, By, Bz, 2) float32 [offset, scale] per block, int8 codes only (spec 4a)
    <map>/state                (Bx, By, Bz) uint8 block state (0 unobserved, 1 empty, 2 coded)
    <map>/codec/<name>         the codec's learned state, one array per state_dict entry

Every chunk is Blosc/zstd-compressed and carries a CRC32C checksum (Zarr's ``crc32c`` codec). A map is
written (or, by :func:`update_map`, copied and changed) in a hidden sibling directory and swapped into place
on commit, so an interrupted write leaves the previous map (or none), never half of one; readers hold the
version they opened, so a swap never mixes two versions under them (``sdfcodec.core._atomic``, spec section 9).

Maps are untrusted input: opening one never runs code from it (codec ids resolve only to installed entry
points, array codecs come from a fixed list, nothing is unpickled), and every size the header or the array
metadata names is checked against ``max_decode_bytes`` before anything that large is allocated.

One job per module: :mod:`~sdfcodec.map.io.stores` (the stores a map is read through),
:mod:`~sdfcodec.map.format` (array and input checks, digests, layout), :mod:`~sdfcodec.map.reader`
(:class:`MapReader`: codes, states, the decode pipeline), :mod:`~sdfcodec.map.writer` (:class:`MapWriter`:
create, update, commit) and :mod:`~sdfcodec.map.facade` (:class:`Map` and the functions below).
"""

from __future__ import annotations

from ..core._lazy import lazy_exports

__all__ = ["Map", "open_map", "create_map", "update_map", "state_digest", "DEFAULT_MAX_DECODE_BYTES", "CODE_DTYPES",
           "MapReader", "MapWriter"]

# Where each public name lives. They load on first use (PEP 562): `import sdfcodec.map.summary` (what `sdfcodec
# info` reads a local map with) must not import Zarr, a third of that command's time budget.
_LAZY = {"Map": ".facade", "open_map": ".facade", "create_map": ".facade", "update_map": ".facade",
         "state_digest": ".codec_state", "DEFAULT_MAX_DECODE_BYTES": ".format", "CODE_DTYPES": ".format",
         "MapReader": ".reader", "MapWriter": ".writer"}

__getattr__, __dir__ = lazy_exports(__name__, _LAZY)
