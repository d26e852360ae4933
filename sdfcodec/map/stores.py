"""The stores a map is read and written through: a guard against oversize metadata and decompression bombs, a
local store pinned to one version of a map directory, the copy-on-write store writers use, URL detection, and
opening the right store for a path or URL. (Search counts what it reads with its own wrapper, through
``Map.with_store``.)

Nothing here knows the map format beyond the sizes it is told (:class:`GuardStore.limits`); the checks of the
format itself live in :mod:`sdfcodec.map.format`.
"""

from __future__ import annotations

import asyncio
import os
import weakref
from pathlib import Path

import zarr
import zarr.abc.store
from zarr.core.buffer import Buffer

from .. import _atomic
from .remote import remote_store
from ..errors import ChecksumError, FormatError, InvalidValueError, MapNotFoundError, ReadOnlyError

__all__ = ["MAX_METADATA_BYTES", "GuardStore", "PinnedStore", "CowLocalStore", "is_url", "open_store", "unguarded"]

#: Largest zarr.json a reader loads: metadata documents of a map are a few kB.
MAX_METADATA_BYTES = 16 << 20


def is_url(s: str) -> bool:
    """True for ``scheme://...`` locations (HTTP, S3, ``file://``...), which fsspec opens."""
    return "://" in s


class GuardStore(zarr.storage.WrapperStore):
    """Read-side wrapper around any store: refuses oversize metadata documents, and chunks whose Blosc header
    claims more bytes than the chunk's shape holds (a decompression bomb), before anything that large is
    allocated. ``limits`` maps an array's path to (decoded chunk bytes, whether Blosc decodes it first)."""

    def __init__(self, store: zarr.abc.store.Store, limits: dict[str, tuple[int, bool]] | None = None):
        super().__init__(store)
        self.limits: dict[str, tuple[int, bool]] = {} if limits is None else limits

    def _with_store(self, store):
        return type(self)(store, self.limits)

    def _local_size(self, key: str) -> int | None:
        inner = self._store
        if isinstance(inner, zarr.storage.LocalStore):
            try:
                return os.stat(inner.root / key).st_size
            except OSError:
                return None
        return None

    @property
    def inner(self) -> zarr.abc.store.Store:
        """The store this one guards."""
        return self._store

    async def get(self, key, prototype=None, byte_range=None):
        meta = key == "zarr.json" or key.endswith("/zarr.json")
        limit = None if meta else next((v for p, v in self.limits.items() if key.startswith(p + "/")), None)
        size = self._local_size(key) if (meta or limit) else None
        if meta and size is not None and size > MAX_METADATA_BYTES:
            raise FormatError(f"{key} is {size} bytes, more than any map metadata ({MAX_METADATA_BYTES}); refused")
        if limit and size is not None and size > 2 * limit[0] + (1 << 20):
            raise ChecksumError(f"chunk {key} is {size} bytes on disk, far more than its {limit[0]} bytes of data")
        buf = await self._store.get(key, prototype, byte_range)
        if buf is None or byte_range is not None:
            return buf
        if meta and len(buf) > MAX_METADATA_BYTES:
            raise FormatError(f"{key} is {len(buf)} bytes, more than any map metadata ({MAX_METADATA_BYTES}); refused")
        if limit and limit[1] and len(buf) >= 16:
            # Blosc header: bytes 4..8 hold the uncompressed size, which decompression would allocate
            claimed = int.from_bytes(bytes(buf.as_numpy_array()[4:8]), "little")
            if claimed > limit[0]:
                raise ChecksumError(f"chunk {key} claims {claimed} bytes uncompressed, more than its shape holds "
                                    f"({limit[0]}); refused without decompressing")
        return buf


class PinnedStore(zarr.storage.LocalStore):
    """A read-only local store over one version of a map directory, held open by a file descriptor and read
    through ``/proc/self/fd/N``: a writer that swaps in a new version cannot mix it into what this reader
    sees, and the held version is not removed while this store lives (``sdfcodec._atomic``)."""

    def __init__(self, root, *, read_only: bool = True, _path: Path | None = None, _fd: int | None = None):
        super().__init__(root, read_only=True)
        self._path, self._fd, self._closed = _path, _fd, False
        self._release = (weakref.finalize(self, _atomic.release_pin, _fd, _path, os.getpid())
                         if _fd is not None else None)

    @classmethod
    def pin(cls, path: Path) -> "PinnedStore":
        fd = _atomic.pin_dir(path)
        return cls(f"/proc/self/fd/{fd}", _path=path, _fd=fd)

    @property
    def path(self) -> Path | None:
        """The map directory's path (where a new version would appear), not the pinned one."""
        return self._path

    @property
    def fd(self) -> int | None:
        """The directory descriptor holding the pinned version."""
        return self._fd

    def close_pin(self) -> None:
        self._closed = True
        if self._release is not None:
            self._release()

    def with_read_only(self, read_only: bool = False):
        if not read_only:
            raise ReadOnlyError(f"{self._path} is open read-only")
        return self

    def __reduce__(self):
        # the descriptor means nothing in another process: pin the map there afresh
        return (PinnedStore.pin, (self._path,))

    def _check_open(self) -> None:
        if self._closed:
            raise InvalidValueError(f"{self._path}: the map was closed; open it again with sdfcodec.open_map")

    async def get(self, key, prototype=None, byte_range=None):
        self._check_open()
        return await super().get(key, prototype, byte_range)

    async def get_partial_values(self, prototype, key_ranges):
        self._check_open()
        return await super().get_partial_values(prototype, key_ranges)

    async def exists(self, key: str) -> bool:
        self._check_open()
        return await super().exists(key)


class CowLocalStore(zarr.storage.LocalStore):
    """A Zarr local store that writes every value into a new file and renames it over the key: never into an
    existing file. An update's copy of a map is made of hard links shared with the previous version, which
    must stay intact for its readers; this holds whatever Zarr's own LocalStore does."""

    def set_sync(self, key: str, value: Buffer) -> None:
        self._ensure_open_sync()
        self._check_writable()
        _atomic.write_new_file(self.root / key, value.as_buffer_like())

    async def _set(self, key: str, value: Buffer, exclusive: bool = False) -> None:
        if not self._is_open:
            await self._open()
        self._check_writable()
        await asyncio.to_thread(_atomic.write_new_file, self.root / key, value.as_buffer_like(), exclusive)


def unguarded(store: zarr.abc.store.Store) -> zarr.abc.store.Store:
    """The store under a :class:`GuardStore` (any other store as it is)."""
    return store.inner if isinstance(store, GuardStore) else store


def open_store(path_or_url: str | os.PathLike | zarr.abc.store.Store, loc: str,
               storage_options: dict | None) -> GuardStore:
    """The guarded read-only store of a map: any Zarr store as given, a URL through fsspec, a ``.zip`` file, or
    a local directory (pinned at its current version where ``/proc/self/fd`` exists). ``loc`` is
    ``str(path_or_url)``. Raises MapNotFoundError for a local path that does not exist."""
    if isinstance(path_or_url, zarr.abc.store.Store):
        return GuardStore(path_or_url)
    if is_url(loc):  # http(s) and s3: bounded, timed and retried reads (sdfcodec.map.remote)
        limits: dict[str, tuple[int, bool]] = {}
        return GuardStore(remote_store(loc, storage_options, limits=limits, max_metadata_bytes=MAX_METADATA_BYTES),
                          limits)
    p = Path(loc)
    if not p.exists():
        raise MapNotFoundError(f"no map at {loc}")
    if p.is_file():
        return GuardStore(zarr.storage.ZipStore(p, mode="r"))
    if _atomic.HAVE_PROC_FD:
        return GuardStore(PinnedStore.pin(p))
    return GuardStore(zarr.storage.LocalStore(p, read_only=True))
