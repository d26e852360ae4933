"""The arrays a small variable-rate map leaves implied (spec/map-format.md section 4e, ``codes.variable_rate.states``):
its block states travel in the header and neither ``state`` nor ``codes`` is stored.

A variable-rate map's ``codes`` array holds no chunk (the chunk streams replace them) and its metadata follows
from the header; its ``state`` array is one small chunk. On a map of a few hundred coded blocks the two
documents, the state chunk and their three manifest entries are 5 B per coded block of a 64 B budget (kitchen
half: 297 + 356 + 136 + 190 bytes), where the states take 144 bytes of header. Such maps are
never updated in place, so nothing writes those arrays again. Writers inline the states when they compress to
at most :data:`INLINE_MAX` bytes; readers take the states from the header and rebuild both arrays in memory
(:func:`implied_arrays`) where a path reads them through Zarr (verify, presence checks, prefix reads of codes), on
first use (:class:`ImpliedArray`), as it reads stored ones.
"""

from __future__ import annotations

import base64
import binascii
import math
import shutil
import zlib
from pathlib import Path
from typing import Any
import numpy as np

from ..errors import FormatError
from ..core.header import MapHeader

__all__ = ["INLINE_MAX", "pack_states", "unpack_states", "inline_states", "implied_arrays", "drop_implied",
           "IMPLIED", "ImpliedArray"]

#: Largest zlib-compressed block states a writer puts in the header (bytes; 5.5 KB of base64): a grid of
#: tens of thousands of blocks. Larger grids keep the ``state`` array, whose chunks a region reads alone.
INLINE_MAX = 4096
#: The arrays whose files a map with inline states does not store.
IMPLIED = ("codes", "state")


def pack_states(state: np.ndarray) -> str:
    """``codes.variable_rate.states`` of block states ``state`` ``(Bx, By, Bz)`` uint8: base64 of zlib (level 9) of
    their C-order bytes."""
    return base64.b64encode(zlib.compress(np.ascontiguousarray(state, np.uint8).tobytes(), 9)).decode()


def inline_states(state: np.ndarray) -> str | None:
    """The header field for ``state`` when it is small enough to travel in the header, else None."""
    packed = pack_states(state)
    return packed if len(packed) * 3 // 4 <= INLINE_MAX else None


def unpack_states(text: str, grid: tuple[int, int, int], where: str) -> np.ndarray:
    """The ``(Bx, By, Bz)`` uint8 block states of ``codes.variable_rate.states`` ``text``; never inflates more than
    the grid's bytes (a hostile header cannot make a reader allocate beyond what its grid already costs).

    Raises:
        FormatError: not base64 of zlib of exactly ``prod(grid)`` bytes, or a reserved state value.
    """
    n = math.prod(grid)
    try:
        d = zlib.decompressobj()
        raw = d.decompress(base64.b64decode(text, validate=True), n + 1)
        complete = d.eof and not d.unconsumed_tail and not d.unused_data
    except (binascii.Error, ValueError, OverflowError, zlib.error) as e:
        raise FormatError(f"{where}: header field codes.variable_rate.states is not base64 of zlib data ({e}); the "
                          "map is corrupted: restore it from a copy") from None
    if len(raw) != n or not complete:
        raise FormatError(f"{where}: header field codes.variable_rate.states holds {len(raw)}{'+' * (not complete)} "
                          f"block states, the grid {list(grid)} has {n}; the map is corrupted: restore it from a copy")
    return np.frombuffer(raw, np.uint8).reshape(grid)


def implied_arrays(h: MapHeader, states: np.ndarray) -> tuple[Any, Any]:
    """``(codes, state)`` of a map whose header holds its states ``states`` (:func:`unpack_states` of it), in
    memory, as a writer would have stored them: ``codes`` without a chunk, ``state`` holding the states (the
    reader's checks then apply unchanged): two ``zarr.Array`` (zarr is imported here only, so that the light
    reader of ``info`` unpacks states without it)."""
    import zarr
    from zarr.api.asynchronous import create_array
    from zarr.codecs import Crc32cCodec
    from zarr.core.sync import sync
    from zarr.storage import MemoryStore

    from .format import compressors

    cb, cs = h.codes.chunk_blocks, h.codes

    async def build() -> tuple[Any, Any]:
        # one trip to Zarr's event loop thread for the whole build, not one per array and write (a GIL hand-over
        # each; the build took 2.0 ms, now 1.5)
        store = MemoryStore()
        codes = await create_array(store, name="codes", shape=(*h.grid_blocks, cs.size), dtype=cs.dtype,
                                   fill_value=0, chunks=(cb, cb, cb, cs.chunk_code), compressors=[Crc32cCodec()])
        state = await create_array(store, name="state", shape=states.shape, dtype="uint8", fill_value=0,
                                   chunks=tuple(max(1, n) for n in states.shape), compressors=compressors())
        if states.size:
            await state.setitem(..., states)
        return codes, state

    codes, state = sync(build())
    return zarr.Array(codes), zarr.Array(state)


class ImpliedArray:
    """A reader's ``codes_array`` or ``state_array`` attribute that, on a map whose header holds its states, builds
    the implied arrays (the owner's ``build_implied()``, :func:`implied_arrays`) on first use: reads take the states
    from the header and never touch either array, and building them cost 1.5-3.5 ms of each open (two Zarr array
    documents and a state chunk encoded in memory); verify, presence checks and the codes' prefix reads use them."""

    def __set_name__(self, owner: type, name: str) -> None:
        self.slot = "_" + name

    def __get__(self, obj: Any, owner: type | None = None) -> Any:
        if obj is None:
            return self
        if obj.__dict__.get("implied_pending"):
            obj.build_implied()
        return obj.__dict__.get(self.slot)

    def __set__(self, obj: Any, value: Any) -> None:
        obj.__dict__[self.slot] = value


def drop_implied(root: str | Path) -> None:
    """Delete the arrays :data:`IMPLIED` of the map being written in ``root`` (a local directory)."""
    for name in IMPLIED:
        shutil.rmtree(Path(root) / name, ignore_errors=True)

