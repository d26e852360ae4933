"""What a search reads, counted: the store wrapper that counts the bytes read per array
(:class:`CountingStore`), a map's view through it (:func:`counting_view`), and the bytes its code chunks take on
disk (:func:`code_chunk_bytes`), which :func:`sdfcodec.search.engine.search` reports beside what it read.
"""

from __future__ import annotations

import contextlib
import os
import threading
import weakref

import zarr
import zarr.abc.store

from ..errors import InvalidValueError
from ..map import Map

__all__ = ["CountingStore", "counting_view", "release_view", "code_chunk_bytes", "code_bytes_read"]

#: Where a map keeps its codes: ``codes`` (fixed-length) or the variable-rate code streams (spec section 4e),
#: whose rows each hold every element of a chunk's codes (any level reads the whole row)
_CODE_ARRAYS = ("codes", "code_streams")


class CountingStore(zarr.storage.WrapperStore):
    """A read-through Zarr store wrapper that counts the bytes it returns, per top-level array name
    (``codes``, ``state``, ``codec``, ``weights``) and ``meta`` for ``zarr.json`` metadata documents."""

    def __init__(self, store: zarr.abc.store.Store):
        super().__init__(store)
        self.bytes: dict[str, int] = {}
        self.keys: list[str] = []
        self._lock = threading.Lock()  # local chunks are read by several threads at once
        self.busy = False  # a search is counting through it (counting_view)

    def reset(self) -> None:
        """Counts back to zero."""
        with self._lock:
            self.bytes, self.keys = {}, []

    @property
    def inner(self) -> zarr.abc.store.Store:
        """The store counted."""
        return self._store

    def observe(self, key: str, nbytes: int) -> None:
        """Count ``nbytes`` read at ``key`` (from several threads)."""
        kind = "meta" if key.endswith("zarr.json") else key.split("/", 1)[0]
        with self._lock:
            self.bytes[kind] = self.bytes.get(kind, 0) + nbytes
            self.keys.append(key)

    def _count(self, key: str, buf) -> None:
        if buf is not None:
            self.observe(key, len(buf))

    async def get(self, key, prototype, byte_range=None):
        buf = await self._store.get(key, prototype, byte_range)
        self._count(key, buf)
        return buf

    async def get_partial_values(self, prototype, key_ranges):
        out = await self._store.get_partial_values(prototype, key_ranges)
        for (key, _), buf in zip(key_ranges, out):
            self._count(key, buf)
        return out


#: map -> (its counting view, that view's store, code chunk bytes by levels): a search of a map searched before
#: reuses them (opening the view checks every array's metadata through Zarr: 3 ms of a 50 ms whole-map search)
_VIEWS: "weakref.WeakKeyDictionary[Map, tuple[Map, CountingStore, dict]]" = weakref.WeakKeyDictionary()
_VIEWS_LOCK = threading.Lock()


def counting_view(m: Map) -> tuple[Map, CountingStore]:
    """The same map read through a :class:`CountingStore` with its counts at zero (shares the header and any
    loaded codec). The view of a map searched before is reused unless another search holds it; a caller
    hands it back with :func:`release_view` once it has read the counts."""
    if m.writable:
        raise InvalidValueError(f"{m.location} is still being written; leave the create_map block (commit) and "
                                "search the map with sdfcodec.open_map")
    with _VIEWS_LOCK:
        held = _VIEWS.get(m)
        if held is not None and not held[1].busy:
            held[1].reset()
            held[1].busy = True
            return held[0], held[1]
    made: list[CountingStore] = []

    def wrap(store):
        made.append(CountingStore(store))
        return made[0]

    view = m.with_store(wrap)  # shares the header and the codec cache: a codec loaded by either serves both
    made[0].busy = True
    with _VIEWS_LOCK:
        if m not in _VIEWS:
            _VIEWS[m] = (view, made[0], {})
    return view, made[0]


def release_view(store: CountingStore) -> None:
    """Let the next search of the map reuse the view read through ``store``."""
    store.busy = False


def code_chunk_bytes(m: Map, *levels: int | None) -> list[int | None]:
    """Bytes on disk of the map's code chunks holding elements ``[0, level)`` (all when None), one total per
    level, from one walk of the chunk folders; local directory maps only (None otherwise)."""
    held = _VIEWS.get(m)
    if held is not None and levels in held[2]:  # a committed map's files do not change under its reader
        return list(held[2][levels])
    streams = m.header.codes.variable_rate is not None
    root = os.path.join(m.location, _CODE_ARRAYS[streams], "c")
    if "://" in m.location or not os.path.isdir(root):
        return [None] * len(levels)
    per_column: dict[int, int] = {}  # bytes per chunk index along the code axis (the last key segment)
    folders = [root]
    while folders:  # os.scandir: its entries know their type; os.walk and pathlib's rglob took 2-3 ms per map
        with contextlib.suppress(OSError), os.scandir(folders.pop()) as entries:
            for e in entries:
                if e.is_dir(follow_symlinks=False):
                    folders.append(e.path)
                elif e.name.isdigit() and e.is_file(follow_symlinks=False):
                    with contextlib.suppress(OSError):
                        per_column[int(e.name)] = per_column.get(int(e.name), 0) + e.stat(follow_symlinks=False).st_size
    cc = m.header.codes.chunk_code
    out = [sum(n for k, n in per_column.items() if streams or k < -(-(lv or m.code_size) // cc)) for lv in levels]
    if held is not None:
        held[2][levels] = tuple(out)
    return out


def code_bytes_read(store: CountingStore) -> int:
    """Bytes of code chunks ``store`` returned: the ``codes`` array's or, in a variable-rate map, its code streams'."""
    return sum(int(store.bytes.get(a, 0)) for a in _CODE_ARRAYS)
