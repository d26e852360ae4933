"""Which chunks of the ``state`` array a map must store (spec section 9a).

Zarr reads a chunk that is not stored as the array's fill value, and the fill value of ``state`` is 0,
*unobserved*: a deleted state chunk would make its blocks vanish without a word. Writers leave unwritten the
state chunks whose blocks are all unobserved (Zarr does not store a chunk equal to the fill value), so a
missing state chunk is legitimate exactly when nothing is stored for its blocks. A reader tells the two apart
by the code chunks of its region: a coded block always has its code chunks (spec section 4), so a stored code
chunk (or ``code_scale`` chunk) under a missing state chunk means the state chunk was lost, and reading it as
unobserved would drop those blocks. The checks are cached per reader, so each state chunk is looked at once.
"""

from __future__ import annotations

import asyncio
import itertools
from typing import TYPE_CHECKING

import numpy as np
from zarr.core.sync import sync as zarr_sync

from ..errors import FormatError
from .io.shards import storage_shape

if TYPE_CHECKING:
    from zarr.abc.store import Store

    from .reader import MapReader

__all__ = ["state_chunk_regions", "check_state_chunks", "MAX_PROBES"]

#: Code chunks looked up per missing state chunk: a writer's layout has 8^3 code chunks under a state chunk
#: (64^3 blocks in 8^3-block chunks); a hostile layout of 1-block chunks would otherwise mean 262,144 lookups.
MAX_PROBES = 4096


def state_chunk_regions(state_chunks: tuple[int, ...], grid: tuple[int, ...], box: tuple[slice, ...]
                        ) -> list[tuple[tuple[int, ...], tuple[slice, ...]]]:
    """``(chunk coords, block box of that chunk)`` of every chunk of a ``state`` array chunked ``state_chunks``
    over ``grid`` blocks that block box ``box`` touches."""
    ranges = [range(s.start // c, -(-s.stop // c)) for s, c in zip(box, state_chunks)]
    return [(idx, tuple(slice(i * c, min((i + 1) * c, n)) for i, c, n in zip(idx, state_chunks, grid)))
            for idx in itertools.product(*ranges)]


async def _exist(store: Store, keys: list[str]) -> list[bool]:
    return list(await asyncio.gather(*(store.exists(k) for k in keys)))


def check_state_chunks(reader: MapReader, box: tuple[slice, ...], state: np.ndarray) -> None:
    """Refuse a missing ``state`` chunk in block box ``box`` (whose states ``state`` were just read) under
    which a code chunk is stored (see the module docstring). ``reader``: a
    :class:`~sdfcodec.map.reader.MapReader` of a committed map; its ``state_chunks_checked`` set caches the
    state chunks found sound.

    Raises:
        FormatError: naming the missing state chunk and a stored code chunk of its region.
    """
    arr, store, done = reader.state_array, reader.group.store, reader.state_chunks_checked
    box = tuple(slice(0 if s.start is None else s.start, n if s.stop is None else s.stop)
                for s, n in zip(box, arr.shape))
    suspects = []
    for idx, region in state_chunk_regions(arr.chunks, arr.shape, box):
        if idx in done:
            continue
        local = tuple(slice(max(r.start, b.start) - b.start, min(r.stop, b.stop) - b.start)
                      for r, b in zip(region, box))
        if state[local].any():  # a chunk that holds anything but 0 is stored
            done.add(idx)
        else:
            suspects.append((idx, region))
    if not suspects:
        return
    keys = [f"{arr.path}/{arr.metadata.encode_chunk_key(idx)}" for idx, _ in suspects]
    for (idx, region), key, stored in zip(suspects, keys, zarr_sync(_exist(store, keys))):
        if stored:
            done.add(idx)
            continue
        for codes in (reader.codes_array, reader.code_scale_array):
            if codes is None:
                continue
            cb = storage_shape(codes)[:3]  # its stored objects: chunk files, or shards (spec section 4d)
            chunks = list(itertools.islice(itertools.product(*(range(r.start // c, -(-r.stop // c))
                                                               for r, c in zip(region, cb))), MAX_PROBES))
            code_keys = [f"{codes.path}/{codes.metadata.encode_chunk_key((*c, 0))}" for c in chunks]
            found = [k for k, ok in zip(code_keys, zarr_sync(_exist(store, code_keys))) if ok]
            if found:
                raise FormatError(f"{reader.location}: chunk {key} of array 'state' is missing, but chunk {found[0]} "
                                  f"of its blocks {[(r.start, r.stop) for r in region]} is stored: the block states "
                                  "there are lost (they would read as unobserved and the coded blocks vanish); the "
                                  "map is incomplete there: restore it from a copy or re-encode")
        done.add(idx)  # nothing stored for its blocks: a legitimately unwritten, all-unobserved chunk
