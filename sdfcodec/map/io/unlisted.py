"""Which chunks a remote map stores, found without listing its store (spec section 9a).

A map read over HTTP(S) or S3 is never listed: HTTP has no listing, only HTML pages that some servers
generate (nginx's default and S3 websites generate none, and a hostile server can generate a listing that
never ends), and an S3 bucket may hold millions of keys that are not the map's. What a remote map must store
follows from its header and its block states instead (:mod:`sdfcodec.map.presence`): every chunk position of
the ``state`` array, the code chunks of every coded block, the chunks of per-block arrays under the blocks
that are observed, every chunk of a codec state array. Each of those is asked for by its key (a one-byte
range read, or a shard's index), so checking a map costs a bounded number of requests, known before the
first is sent: at most :data:`MAX_CANDIDATES` chunk positions per array.
"""

from __future__ import annotations

import asyncio
import itertools
import math
from typing import TYPE_CHECKING, Any

import numpy as np
import zarr
from zarr.core.sync import sync as zarr_sync

from ...errors import FormatError
from .remote import RemoteStore
from .shards import chunk_name, chunk_stored, shard_contents
from .stores import unguarded

if TYPE_CHECKING:
    from zarr.abc.store import Store

__all__ = ["is_unlisted", "chunk_positions", "stored_chunks", "MAX_CANDIDATES"]

#: Chunk positions of one array a remote map's check may ask for: a million-block map in the writer's
#: layout has a few thousand per array; a header that needs more (chunks of one block over a huge grid) is
#: refused, rather than sending millions of requests.
MAX_CANDIDATES = 1 << 18
_BATCH = 1024  # requests in flight at a time


def is_unlisted(store: Store) -> bool:
    """Whether ``store`` (guarded or not) is one that is never listed: a remote map's."""
    return isinstance(unguarded(store), RemoteStore)


def _grid(arr: zarr.Array) -> tuple[int, ...]:
    """The grid of ``arr``'s (inner) chunks."""
    return tuple(-(-int(n) // int(c)) for n, c in zip(arr.shape, arr.chunks))


def chunk_positions(arr: zarr.Array, blocks: np.ndarray | None = None) -> list[tuple[int, ...]]:
    """The chunk coordinates of ``arr`` to ask for: all of them, or (``blocks``: ``(N, 3)`` integer block
    coordinates, ``arr`` indexed by block along its first three axes) those holding one of ``blocks``, with
    every chunk along the remaining axes.

    Raises:
        FormatError: more than :data:`MAX_CANDIDATES` positions (naming the array and the count).
    """
    grid = _grid(arr)
    if blocks is None:
        count = math.prod(grid)
        lead: Any = None
    else:
        lead = np.unique(np.asarray(blocks, np.int64).reshape(-1, 3) // np.asarray(arr.chunks[:3]), axis=0)
        count = len(lead) * math.prod(grid[3:])
    if count > MAX_CANDIDATES:
        raise FormatError(f"array '{arr.path}' has {count} chunk positions to check, more than a remote map's "
                          f"check asks for ({MAX_CANDIDATES}; its chunks are tiny for its size): copy the map "
                          "to a local directory and verify it there")
    if lead is None:
        return [tuple(int(v) for v in c) for c in np.ndindex(*grid)]
    rest = list(np.ndindex(*grid[3:]))
    return [(*map(int, c), *map(int, r)) for c, r in itertools.product(lead, rest)]


def stored_chunks(arr: zarr.Array, positions: list[tuple[int, ...]]
                  ) -> tuple[dict[tuple[int, ...], str], dict[str, str]]:
    """Which of ``positions`` (chunk coordinates of ``arr``) are stored, asked for by key: ``({chunk
    coordinates: name}, {shard key: problem})`` as :func:`sdfcodec.map.io.shards.shard_contents` gives them (a
    sharded array's chunks from the indexes of its shards that exist)."""
    store = arr.store
    if arr.shards is None:
        found = {}
        for start in range(0, len(positions), _BATCH):
            part = positions[start:start + _BATCH]
            found.update({c: chunk_name(arr, c) for c, ok in zip(part, chunk_stored(store, arr, part)) if ok})
        return found, {}
    ratio = [s // c for s, c in zip(arr.shards, arr.chunks)]
    shards = sorted({tuple(c // r for c, r in zip(p, ratio)) for p in positions})
    keys = {s: f"{arr.path}/{arr.metadata.encode_chunk_key(s)}" for s in shards}

    async def exist(part):
        return await asyncio.gather(*(store.exists(keys[s]) for s in part))

    present = {}
    for start in range(0, len(shards), _BATCH):
        part = shards[start:start + _BATCH]
        present.update({s: keys[s] for s, ok in zip(part, zarr_sync(exist(part))) if ok})
    found, broken = shard_contents(store, arr, present)
    wanted = set(positions)
    return {c: k for c, k in found.items() if c in wanted}, broken
