"""The stores a map is read and written through: a guard against oversize metadata and decompression bombs, a
local store that reads only regular files inside the map directory (bounded while reading), the same pinned to
one version of a map directory, the copy-on-write store writers use, URL detection, and opening the right
store for a path or URL. (Search counts what it reads with its own wrapper, through
``Map.with_store``.)

Nothing here knows the map format beyond the sizes it is told (:class:`GuardStore.limits`); the checks of the
format itself live in :mod:`sdfcodec.map.format`.
"""

from __future__ import annotations

import asyncio
import collections
import errno
import json
import os
import stat
import threading
import weakref
import zipfile
import zlib
from pathlib import Path
from typing import Any

import zarr
import zarr.abc.store
from zarr.abc.buffer import Buffer
from zarr.abc.store import OffsetByteRequest, RangeByteRequest, SuffixByteRequest
from zarr.buffer import default_buffer_prototype
from zarr.core.group import get_node

from ...core import _atomic
from .frames import blosc_frame_problem
from .metadata_limits import MetadataBudget, check_metadata_size
from .remote import remote_store, set_default_limits
from .shards import range_problem, read_cap, shard_problem
from ...errors import ChecksumError, FormatError, InvalidValueError, MapNotFoundError, ReadOnlyError


__all__ = ["MAX_METADATA_BYTES", "MAX_OTHER_MEMBER_BYTES", "blosc_frame_problem", "HAVE_DIR_FD", "GuardStore",
           "SafeLocalStore", "SafeZipStore", "PinnedStore", "CowLocalStore", "is_url", "open_store",
           "set_read_defaults", "unguarded", "chunk_read_limit", "check_metadata_document", "fetch_members"]

#: Largest zarr.json a reader loads: metadata documents of a map are a few kB.
MAX_METADATA_BYTES = 16 << 20


def chunk_read_limit(chunk_bytes: int) -> int:
    """Most bytes a stored chunk of ``chunk_bytes`` decoded bytes may take: compression can grow incompressible
    data a little, never to twice its size plus 1 MiB."""
    return 2 * chunk_bytes + (1 << 20)


def check_metadata_document(key: str, data: bytes) -> int:
    """Refuse a ``zarr.json`` that is not one plain JSON object in UTF-8: a byte order mark, other encodings
    and duplicate keys (which parsers resolve differently, so two readers could see two maps) are refused
    here, and, before it is parsed, one with more values or deeper nesting than any map's metadata
    (:mod:`sdfcodec.map.io.metadata_limits`), all as one-line FormatErrors naming ``key``. Returns its node
    count."""
    def no_duplicates(pairs: list[tuple[str, object]]) -> dict:
        seen = dict(pairs)
        if len(seen) != len(pairs):
            dup = next(k for i, (k, _) in enumerate(pairs) if k in dict(pairs[:i]))
            raise FormatError(f"{key} has the key {dup!r} twice in one object (parsers would disagree on which "
                              "counts); refused")
        return seen

    if data.startswith(b"\xef\xbb\xbf"):
        raise FormatError(f"{key} starts with a byte order mark; a map's metadata is plain UTF-8 JSON; refused")
    nodes = check_metadata_size(key, data)
    try:
        doc = json.loads(data.decode("utf-8"), object_pairs_hook=no_duplicates)
    except FormatError:
        raise
    except UnicodeDecodeError as e:
        raise FormatError(f"{key} is not UTF-8 ({e.reason} at byte {e.start}); refused") from None
    except RecursionError:
        raise FormatError(f"{key} is nested too deeply to be map metadata; refused") from None
    except ValueError as e:  # JSONDecodeError
        raise FormatError(f"{key} is not valid map metadata JSON ({str(e).splitlines()[0]}); refused") from None
    if not isinstance(doc, dict):
        raise FormatError(f"{key} holds a JSON {type(doc).__name__}, not the object Zarr metadata is; refused")
    return nodes


def is_url(s: str) -> bool:
    """True for ``scheme://...`` locations (HTTP, S3, ``file://``...), which fsspec opens."""
    return "://" in s


class GuardStore(zarr.storage.WrapperStore):
    """Read-side wrapper around any store: refuses oversize metadata documents, and chunks whose Blosc header
    claims more bytes than the chunk's shape holds (a decompression bomb), before anything that large is
    allocated. ``limits`` maps an array's path to (decoded chunk bytes, whether Blosc decodes it first, chunks
    per stored object: more than 1 for shards, whose ranges and indexes are checked by
    :mod:`sdfcodec.map.io.shards`).
    Over a :class:`SafeLocalStore` the size bounds hold while reading (a file growing meanwhile, or anything
    that is not a regular file, is refused), not only from ``stat``."""

    def __init__(self, store: zarr.abc.store.Store, limits: dict[str, tuple[int, bool]] | None = None,
                 indexes: ShardIndexCache | None = None, manifest: Any = None,
                 metadata: MetadataBudget | None = None):
        super().__init__(store)
        self.limits: dict[str, tuple[int, bool]] = {} if limits is None else limits
        self.indexes = ShardIndexCache() if indexes is None else indexes
        self.metadata = MetadataBudget() if metadata is None else metadata  # the map's documents, together
        #: the map's integrity manifest (:class:`sdfcodec.map.manifest.Manifest`) once the reader loaded it: every
        #: object read from then on is checked against it (spec section 9b); None: unchecked
        self.manifest = manifest

    def _with_store(self, store):
        return type(self)(store, self.limits, self.indexes, self.manifest, self.metadata)

    def read_small(self, key: str, max_bytes: int) -> bytes | None:
        """The whole object ``key`` (a document beside the arrays: the manifest, a signature), at most
        ``max_bytes`` read (more is a FormatError), unchecked by the manifest; None when absent."""
        def too_big(size: int) -> Exception:
            return FormatError(f"{key} is {size} bytes, more than the {max_bytes} expected; refused")

        inner = self._store
        if isinstance(inner, (SafeLocalStore, SafeZipStore)):
            buf = zarr.core.sync.sync(inner.get_bounded(key, None, None, max_bytes, too_big))
        else:
            buf = zarr.core.sync.sync(inner.get(key, default_buffer_prototype()))
        if buf is not None and len(buf) > max_bytes:
            raise too_big(len(buf))
        return None if buf is None else buf.to_bytes()

    def _local_size(self, key: str) -> int | None:
        inner = self._store
        if isinstance(inner, zarr.storage.LocalStore) and not isinstance(inner, SafeLocalStore):
            try:
                return os.lstat(inner.root / key).st_size  # never follows a link to a device or FIFO
            except OSError:
                return None
        return None

    @property
    def inner(self) -> zarr.abc.store.Store:
        """The store this one guards."""
        return self._store

    def limit_of(self, key: str) -> tuple | None:
        """The limits of the checked array ``key`` is a stored object of (see ``limits``), or None."""
        if key == "zarr.json" or key.endswith("/zarr.json"):
            return None
        return next((v for p, v in self.limits.items() if key.startswith(p + "/")), None)

    async def get(self, key, prototype=None, byte_range=None):
        buf = await self._get(key, prototype, byte_range)
        if self.manifest is not None:  # after the bounds and frame checks: nothing unbounded is hashed
            self.manifest.check(key, None if buf is None else buf.as_numpy_array(), byte_range)
        return buf

    async def _get(self, key, prototype=None, byte_range=None):
        meta = key == "zarr.json" or key.endswith("/zarr.json")
        limit = self.limit_of(key)

        def meta_error(size: int) -> Exception:
            return FormatError(f"{key} is {size} bytes, more than any map metadata ({MAX_METADATA_BYTES}); refused")

        chunk_error = _chunk_too_big(key, limit)

        if limit and byte_range is not None:  # only shards are read in ranges (spec section 4d)
            problem = range_problem(limit, byte_range, chunk_read_limit(limit[0]))
            if problem:
                raise ChecksumError(f"{key}: {problem}; refused unread")
        cap, too_big = ((MAX_METADATA_BYTES, meta_error) if meta else
                        (read_cap(limit, byte_range, chunk_read_limit(limit[0])), chunk_error) if limit else
                        (None, None))
        index = limit is not None and isinstance(byte_range, SuffixByteRequest)  # a shard's index (checked above)
        if index and (hit := self.indexes.get(key)) is not None:
            return (prototype or default_buffer_prototype()).buffer.from_bytes(hit)
        if isinstance(self._store, (SafeLocalStore, SafeZipStore)):
            buf = await self._store.get_bounded(key, prototype, byte_range, cap, too_big)
        else:
            size = self._local_size(key) if cap is not None and byte_range is None else None
            if cap is not None and size is not None and size > cap:
                raise too_big(size)
            buf = await self._store.get(key, prototype, byte_range)
            if buf is not None and cap is not None and len(buf) > cap:
                raise too_big(len(buf))
        if buf is None:
            return buf
        if index:
            self.indexes.put(key, buf.to_bytes())
        if byte_range is not None:
            if limit and limit[1] and isinstance(byte_range, RangeByteRequest):  # one chunk of a shard
                _check_frame(_range_name(key, byte_range), memoryview(buf.as_numpy_array()), limit)
            return buf
        if meta and len(buf) > MAX_METADATA_BYTES:
            raise meta_error(len(buf))
        if meta:
            raw = buf.to_bytes()
            self.metadata.charge(key, len(raw), check_metadata_document(key, raw))
        if limit and len(limit) > 2 and limit[2] > 1:  # a whole shard: its index, and every chunk's frame
            frames = (lambda f: blosc_frame_problem(f, limit[0])) if limit[1] else None
            problem = shard_problem(memoryview(buf.as_numpy_array()), limit[2], chunk_read_limit(limit[0]), frames)
            if problem:
                raise ChecksumError(f"shard {key} is not sound: {problem}; refused without decompressing")
        elif limit and limit[1]:
            _check_frame(key, memoryview(buf.as_numpy_array()), limit)
        return buf


def _chunk_too_big(key: str, limit: tuple | None):
    def chunk_error(size: int) -> Exception:
        return ChecksumError(f"chunk {key} is {size} bytes on disk, far more than its {limit[0]} bytes of data")
    return chunk_error


def _range_name(key: str, byte_range: Any) -> str:
    return f"{key} [{byte_range.start}, {byte_range.end})" if isinstance(byte_range, RangeByteRequest) else key


def _check_frame(key: str, data: memoryview, limit: tuple) -> None:
    """Refuse a stored chunk (a Blosc frame and its CRC32C) whose frame is unsound, before it is decompressed."""
    # a view, not a copy: only the header, the offset table and a few stream lengths are read
    problem = blosc_frame_problem(data[:-4], limit[0])
    if problem:
        raise ChecksumError(f"chunk {key} is not a sound Blosc frame: {problem}; refused without decompressing")


class ShardIndexCache:
    """The indexes of shards a reader has fetched (spec section 4d), by key: Zarr fetches a shard's index again
    for every chunk it reads from the shard, which would double the requests of a region read. At most
    ``max_bytes`` of indexes are kept (the oldest dropped first). A local map is read pinned to one version, so
    an index never goes stale; a remote map replaced while read could pair an old index with new chunk bytes,
    which then fail their own CRC32C (a read error, never wrong values)."""

    def __init__(self, max_bytes: int = 16 << 20):
        self.max_bytes, self.size = max_bytes, 0
        self.items: collections.OrderedDict[str, bytes] = collections.OrderedDict()
        self.lock = threading.Lock()

    def get(self, key: str) -> bytes | None:
        with self.lock:
            return self.items.get(key)

    def put(self, key: str, data: bytes) -> None:
        with self.lock:
            if key in self.items or len(data) > self.max_bytes:
                return
            self.items[key] = data
            self.size += len(data)
            while self.size > self.max_bytes:
                self.size -= len(self.items.popitem(last=False)[1])


_KINDS = ((stat.S_ISLNK, "a symbolic link"), (stat.S_ISDIR, "a directory"), (stat.S_ISFIFO, "a FIFO (named pipe)"),
          (stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"), (stat.S_ISSOCK, "a socket"))
_FILE_FLAGS = os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_CLOEXEC", 0)
_DIR_FLAGS = _FILE_FLAGS | getattr(os, "O_DIRECTORY", 0)
#: Keys can be resolved from a directory descriptor (POSIX): elsewhere local maps are read by Zarr's LocalStore.
HAVE_DIR_FD = {os.open, os.stat} <= os.supports_dir_fd and hasattr(os, "O_NOFOLLOW") and hasattr(os, "pread")


def _kind(mode: int) -> str:
    return next((name for test, name in _KINDS if test(mode)), "not a regular file")


class _BoundedGets:
    """Zarr's ``get`` as :meth:`get_bounded`: the store's own bounded reader (``read_bounded``: a local map's
    :meth:`SafeLocalStore.read_file`, a zip's :meth:`SafeZipStore.read_member`) run in a worker thread."""

    def read_bounded(self, key: str, byte_range=None, max_bytes: int | None = None, too_big=None) -> bytes | None:
        raise NotImplementedError

    async def get_bounded(self, key, prototype=None, byte_range=None, max_bytes: int | None = None,
                          too_big=None) -> Buffer | None:
        """:meth:`get`, reading at most ``max_bytes`` (see ``read_file`` or ``read_member``)."""
        if prototype is None:
            prototype = default_buffer_prototype()
        data = await asyncio.to_thread(self.read_bounded, key, byte_range, max_bytes, too_big)
        return None if data is None else prototype.buffer.from_bytes(data)

    async def get(self, key, prototype=None, byte_range=None):
        return await self.get_bounded(key, prototype, byte_range)


class SafeLocalStore(_BoundedGets, zarr.storage.LocalStore):
    """A read-only local store that reads only regular files inside its root directory (spec section 9a).

    Every key is resolved one path segment at a time from a directory descriptor of the root: a symbolic link
    anywhere on the way (a chunk, or a whole ``codes/`` folder, linked to another map's) is refused naming the
    key and where the link leads, unless ``follow_symlinks``; a FIFO, device or socket is refused from its
    ``stat`` before it is opened (opening a FIFO blocks), and again from ``fstat`` after opening it without
    blocking; a directory where a file should be is refused. Reads are bounded while they happen: at most the
    size ``fstat`` gave (checked against the caller's cap), and a file that grew meanwhile is refused."""

    def __init__(self, root, *, read_only: bool = True, follow_symlinks: bool = False):
        super().__init__(root, read_only=True)
        self.follow_symlinks = bool(follow_symlinks)

    @property
    def label(self) -> str:
        """How errors name the map directory."""
        return str(self.root)

    def _root_fd(self) -> tuple[int, bool]:
        """A descriptor of the root directory and whether the caller closes it."""
        return os.open(self.root, _DIR_FLAGS), True

    def with_read_only(self, read_only: bool = False):
        if not read_only:
            raise ReadOnlyError(f"{self.label} is open read-only")
        return self

    def _refuse(self, key: str, where: str, what: str, dir_fd: int, name: str) -> FormatError:
        link, on = "", ("" if where == key else f"{key}: ")
        if what == "a symbolic link":
            try:
                link = f" (to {os.readlink(name, dir_fd=dir_fd)})"
            except OSError:
                pass
            return FormatError(f"{self.label}: {on}'{where}' is a symbolic link{link}; a map's files must be "
                               "regular files inside its directory, so it is refused (open_map(..., "
                               "follow_symlinks=True) follows links)")
        if what == "a directory":
            return FormatError(f"{self.label}: {on}'{where}' is a directory where a file (a chunk or a metadata "
                               "document) belongs; refused")
        return FormatError(f"{self.label}: {on}'{where}' is {what}, not a regular file; a map holds only regular "
                           "files and directories, so it is refused (without opening it)")

    def _lookup(self, key: str, fds: list[int]) -> tuple[int, str, os.stat_result] | None:
        """The directory descriptor holding ``key``'s last segment, that segment and its ``stat`` (links not
        followed unless ``follow_symlinks``); None when nothing is there. Opened descriptors go into ``fds``."""
        parts = key.split("/")
        if any(p in ("", ".", "..") for p in parts):
            raise FormatError(f"{self.label}: {key!r} is no plain store key; refused")
        fd, own = self._root_fd()
        if own:
            fds.append(fd)
        nofollow = 0 if self.follow_symlinks else os.O_NOFOLLOW
        for i, part in enumerate(parts):
            try:
                st = os.stat(part, dir_fd=fd, follow_symlinks=self.follow_symlinks)
            except FileNotFoundError:
                return None
            except OSError as e:
                if e.errno == errno.ELOOP:  # a link loop, followed
                    raise self._refuse(key, "/".join(parts[:i + 1]), "a symbolic link", fd, part) from e
                if e.errno == errno.ENOTDIR:
                    return None
                raise
            if i == len(parts) - 1:
                return fd, part, st
            if not stat.S_ISDIR(st.st_mode):
                if stat.S_ISREG(st.st_mode):
                    return None  # a file where a folder should be: nothing is stored under it
                raise self._refuse(key, "/".join(parts[:i + 1]), _kind(st.st_mode), fd, part)
            try:
                fd = os.open(part, _DIR_FLAGS | nofollow, dir_fd=fd)
            except OSError as e:  # replaced between stat and open
                raise FormatError(f"{self.label}: {key}: '{'/'.join(parts[:i + 1])}' changed while being "
                                  f"opened ({e}); refused") from e
            fds.append(fd)
        return None

    def read_file(self, key: str, byte_range=None, max_bytes: int | None = None,
                  too_big=None) -> bytes | None:
        """The bytes of ``key`` (``byte_range``: a Zarr byte request), or None when nothing is stored there.

        Raises:
            FormatError: a link, FIFO, device, socket or directory at the key or on its way; a file that
                changed while read. ``too_big(size)`` (default a FormatError): more than ``max_bytes`` to read.
        """
        fds: list[int] = []
        try:
            found = self._lookup(key, fds)
            if found is None:
                return None
            dfd, name, st = found
            if not stat.S_ISREG(st.st_mode):
                raise self._refuse(key, key, _kind(st.st_mode), dfd, name)
            fd = os.open(name, _FILE_FLAGS | (0 if self.follow_symlinks else os.O_NOFOLLOW), dir_fd=dfd)
            fds.append(fd)
            st = os.fstat(fd)
            if not stat.S_ISREG(st.st_mode):  # swapped for something else since the stat above
                raise self._refuse(key, key, _kind(st.st_mode), dfd, name)
            size = st.st_size
            start, stop = _byte_span(byte_range, size)
            if max_bytes is not None and stop - start > max_bytes:
                raise (too_big(stop - start) if too_big is not None else FormatError(
                    f"{self.label}: {key} is {stop - start} bytes, more than the {max_bytes} allowed; refused"))
            out = bytearray()
            while len(out) < stop - start:
                piece = os.pread(fd, stop - start - len(out), start + len(out))
                if not piece:
                    break
                out += piece
            if len(out) != stop - start or (byte_range is None and os.pread(fd, 1, size)):
                raise FormatError(f"{self.label}: {key} changed size while being read ({size} bytes at first); "
                                  "refused: a map must not be written in place while it is read")
            return bytes(out)
        except FileNotFoundError:
            return None
        finally:
            for fd in reversed(fds):
                os.close(fd)

    def read_bounded(self, key: str, byte_range=None, max_bytes: int | None = None, too_big=None) -> bytes | None:
        return self.read_file(key, byte_range, max_bytes, too_big)

    async def get_partial_values(self, prototype, key_ranges):
        return list(await asyncio.gather(*(self.get_bounded(k, prototype, r) for k, r in key_ranges)))

    def _exists(self, key: str) -> bool:
        fds: list[int] = []
        try:
            found = self._lookup(key, fds)
            return found is not None and stat.S_ISREG(found[2].st_mode)
        except FormatError:
            return False
        finally:
            for fd in reversed(fds):
                os.close(fd)

    async def exists(self, key: str) -> bool:
        return await asyncio.to_thread(self._exists, key)

    def _listing(self, prefix: str) -> list[str]:
        # every entry but directories (links and special files too, so that `verify` names them), links to
        # directories not descended into
        base = os.path.join(str(self.root), prefix.strip("/")) if prefix.strip("/") else str(self.root)
        root = str(self.root).rstrip("/") + "/"
        out = []
        for dirpath, dirnames, filenames in os.walk(base, followlinks=False):
            rel = dirpath[len(root):] if dirpath.startswith(root) else ""
            links = [d for d in dirnames if os.path.islink(os.path.join(dirpath, d))]
            for name in filenames + links:
                out.append(f"{rel}/{name}" if rel else name)
        return sorted(out)

    async def list(self):
        for key in await asyncio.to_thread(self._listing, ""):
            yield key

    async def list_prefix(self, prefix: str):
        for key in await asyncio.to_thread(self._listing, prefix):
            yield key


def _byte_span(byte_range, size: int) -> tuple[int, int]:
    """``[start, stop)`` of a Zarr byte request within a file of ``size`` bytes (None: all of it)."""
    if byte_range is None:
        return 0, size
    if isinstance(byte_range, RangeByteRequest):
        return min(byte_range.start, size), min(max(byte_range.start, byte_range.end), size)
    if isinstance(byte_range, OffsetByteRequest):
        return min(byte_range.offset, size), size
    if isinstance(byte_range, SuffixByteRequest):
        return max(0, size - byte_range.suffix), size
    raise InvalidValueError(f"unknown byte request {byte_range!r}")


#: Most bytes a zip member that is neither metadata nor a chunk of a checked array may hold (what a remote
#: object of no known kind may, ``RemoteLimits.max_object_bytes``).
MAX_OTHER_MEMBER_BYTES = 256 << 20


class SafeZipStore(_BoundedGets, zarr.storage.ZipStore):
    """A read-only Zarr zip store whose reads are bounded while they happen, as a local map's are: a member's
    size declared in the zip's directory is checked against the caller's cap before it is opened (a deflate
    bomb that declares its size), at most that many bytes are decompressed (a member that lies about its size
    ends at the declared size and then fails its CRC-32), only stored or deflated members are read (bzip2 and
    LZMA decompress unbounded steps), and a damaged member is one clear error naming it."""

    def __init__(self, path, *, mode: str = "r", read_only: bool | None = None, **kwargs):
        super().__init__(path, mode="r", read_only=True)

    def _sync_open(self) -> None:
        super()._sync_open()
        # two members of one name: Python's zipfile reads the last, other readers the first, so two readers
        # could see two maps (a second zarr.json, a second chunk): the zip is refused, naming the member
        seen: set[str] = set()
        for info in self._zf.infolist():
            if info.filename in seen:
                self._zf.close()
                self._is_open = False
                raise FormatError(f"{self.label}: member {info.filename} appears twice in the zip (readers would "
                                  "disagree on which counts); refused: zip the map directory again")
            seen.add(info.filename)

    @property
    def label(self) -> str:
        """How errors name the zip file."""
        return str(self.path)

    def member_names(self) -> list[str]:
        """The names of the zip's file members (what ``verify`` compares with a map's manifest)."""
        if not self._is_open:
            self._sync_open()
        return [n for n in self._zf.namelist() if not n.endswith("/")]

    def read_member(self, key: str, byte_range=None, max_bytes: int | None = None, too_big=None) -> bytes | None:
        """The bytes of member ``key`` (``byte_range``: a Zarr byte request), or None when there is none.

        Raises:
            FormatError: a directory entry or an unsupported compression method at the key.
            ChecksumError: a member whose bytes do not decompress to its declared size and CRC-32.
            ``too_big(size)`` (default a FormatError): a member declaring more than ``max_bytes``.
        """
        if not self._is_open:
            self._sync_open()
        cap = MAX_OTHER_MEMBER_BYTES if max_bytes is None else max_bytes
        with self._lock:
            try:
                info = self._zf.getinfo(key)
            except KeyError:
                return None
            where = f"{self.label}: member {key}"
            if info.is_dir():
                raise FormatError(f"{where} is a directory where a file belongs; refused")
            if info.compress_type not in (zipfile.ZIP_STORED, zipfile.ZIP_DEFLATED):
                raise FormatError(f"{where} uses zip compression method {info.compress_type}; a zip map's "
                                  "members must be stored or deflated; refused")
            size = info.file_size
            if size > cap:  # the whole member, whatever part is asked for: seeking decompresses the rest
                raise (too_big(size) if too_big is not None and max_bytes is not None else FormatError(
                    f"{where} declares {size} bytes, more than the {cap} allowed; refused unread"))
            start, stop = _byte_span(byte_range, size)
            try:
                with self._zf.open(info) as f:
                    if start:
                        f.seek(start)
                    data = f.read(stop - start)  # at most the declared size is decompressed
            except (zipfile.BadZipFile, zlib.error, EOFError, OSError, ValueError) as e:
                raise ChecksumError(f"{where} is damaged ({e}); refused") from None
            if len(data) != stop - start:
                raise ChecksumError(f"{where} holds {start + len(data)} bytes, not the {size} its zip entry "
                                    "declares; refused")
            return data

    def read_bounded(self, key: str, byte_range=None, max_bytes: int | None = None, too_big=None) -> bytes | None:
        return self.read_member(key, byte_range, max_bytes, too_big)

    async def get_partial_values(self, prototype, key_ranges):
        return [await self.get_bounded(k, prototype, r) for k, r in key_ranges]


class PinnedStore(SafeLocalStore):
    """A read-only :class:`SafeLocalStore` over one version of a map directory, held open by a file descriptor
    (keys are resolved from it; Zarr's own paths go through ``/proc/self/fd/N``): a writer that swaps in a new
    version cannot mix it into what this reader sees, and the held version is not removed while this store
    lives (``sdfcodec.core._atomic``)."""

    def __init__(self, root, *, read_only: bool = True, follow_symlinks: bool = False, _path: Path | None = None,
                 _fd: int | None = None):
        super().__init__(root, read_only=True, follow_symlinks=follow_symlinks)
        self._path, self._fd, self._closed = _path, _fd, False
        self._release = (weakref.finalize(self, _atomic.release_pin, _fd, _path, os.getpid())
                         if _fd is not None else None)

    @classmethod
    def pin(cls, path: Path, follow_symlinks: bool = False) -> "PinnedStore":
        return cls.hold(path, _atomic.pin_dir(path), follow_symlinks)

    @classmethod
    def hold(cls, path: Path, fd: int, follow_symlinks: bool = False) -> "PinnedStore":
        """The store of the version of ``path`` that the directory descriptor ``fd`` (already locked shared, e.g.
        by the writer that just committed it) holds; the store owns ``fd`` from now on."""
        return cls(f"/proc/self/fd/{fd}", follow_symlinks=follow_symlinks, _path=path, _fd=fd)

    @property
    def path(self) -> Path | None:
        """The map directory's path (where a new version would appear), not the pinned one."""
        return self._path

    @property
    def fd(self) -> int | None:
        """The directory descriptor holding the pinned version."""
        return self._fd

    @property
    def label(self) -> str:
        return str(self._path)

    def _root_fd(self) -> tuple[int, bool]:
        self._check_open()
        return (self._fd, False) if self._fd is not None else super()._root_fd()

    def close_pin(self) -> None:
        self._closed = True
        if self._release is not None:
            self._release()

    def __reduce__(self):
        # the descriptor means nothing in another process: pin the map there afresh
        return (PinnedStore.pin, (self._path, self.follow_symlinks))

    def _check_open(self) -> None:
        if self._closed:
            raise InvalidValueError(f"{self._path}: the map was closed; open it again with sdfcodec.open_map")

    async def get_bounded(self, key, prototype=None, byte_range=None, max_bytes=None, too_big=None):
        self._check_open()
        return await super().get_bounded(key, prototype, byte_range, max_bytes, too_big)

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
        self._write(key, value)

    async def _set(self, key: str, value: Buffer, exclusive: bool = False) -> None:
        if not self._is_open:
            await self._open()
        self._check_writable()
        await asyncio.to_thread(self._write, key, value, exclusive)

    def _write(self, key: str, value: Buffer, exclusive: bool = False) -> None:
        try:
            _atomic.write_new_file(self.root / key, value.as_buffer_like(), exclusive)
        except FileNotFoundError:
            # the directory being written is gone: an interrupt abandoned the write and removed it while Zarr
            # still had chunk writes in flight. Those writes are moot (the commit of a missing directory fails
            # by itself); raised from an orphaned task they only printed a traceback after "interrupted"
            if not self.root.is_dir():
                return
            raise


def unguarded(store: zarr.abc.store.Store) -> zarr.abc.store.Store:
    """The store under a :class:`GuardStore` (any other store as it is)."""
    return store.inner if isinstance(store, GuardStore) else store


#: Whether local reads of this process follow symbolic links inside a map unless told to (``set_read_defaults``).
_FOLLOW_SYMLINKS = [False]


def set_read_defaults(*, follow_symlinks: bool = False, remote_limits: dict | None = None) -> None:
    """Defaults for every map this process opens from now on (the ``sdfcodec`` command's root options
    ``--follow-symlinks``, ``--remote-timeout`` and ``--remote-tries`` set them, so that every command and the
    library functions they call read maps alike): ``follow_symlinks`` as if each ``open_map`` and
    ``verify_map`` passed it (an explicit ``True`` there still follows links when this is False), and
    ``remote_limits`` fields of :class:`~sdfcodec.map.io.remote.RemoteLimits` replacing its defaults (a map's own
    ``storage_options["remote_limits"]`` override them field by field). Called with no arguments: the
    built-in defaults again.

    Raises:
        InvalidValueError: an unknown remote limit or a value out of range.
    """
    set_default_limits(remote_limits)
    _FOLLOW_SYMLINKS[0] = bool(follow_symlinks)


def open_store(path_or_url: str | os.PathLike | zarr.abc.store.Store, loc: str,
               storage_options: dict | None, *, follow_symlinks: bool = False) -> GuardStore:
    """The guarded read-only store of a map: any Zarr store as given, a URL through fsspec, a ``.zip`` file, or
    a local directory (a :class:`SafeLocalStore`, pinned at its current version where ``/proc/self/fd``
    exists; ``follow_symlinks`` lets it follow symbolic links inside the map). ``loc`` is
    ``str(path_or_url)``. Raises MapNotFoundError for a local path that does not exist."""
    if isinstance(path_or_url, zarr.abc.store.Store):
        return GuardStore(path_or_url)
    follow_symlinks = follow_symlinks or _FOLLOW_SYMLINKS[0]
    if is_url(loc):  # http(s) and s3: bounded, timed and retried reads (sdfcodec.map.io.remote)
        limits: dict[str, tuple[int, bool]] = {}
        return GuardStore(remote_store(loc, storage_options, limits=limits, max_metadata_bytes=MAX_METADATA_BYTES),
                          limits)
    p = Path(loc)
    if not p.exists():
        raise MapNotFoundError(f"no map at {loc}")
    if p.is_file():
        return GuardStore(SafeZipStore(p))
    if not p.is_dir():  # a FIFO, device or socket: never opened
        raise MapNotFoundError(f"no map at {loc}: it is {_kind(os.stat(p).st_mode)}, neither a map directory nor "
                               "a zip file")
    if _atomic.HAVE_PROC_FD and HAVE_DIR_FD:
        return GuardStore(PinnedStore.pin(p, follow_symlinks=follow_symlinks))
    if HAVE_DIR_FD:
        return GuardStore(SafeLocalStore(p, follow_symlinks=follow_symlinks))
    return GuardStore(zarr.storage.LocalStore(p, read_only=True))


def fetch_members(group: zarr.Group, paths: list[str]) -> dict[str, Any]:
    """``{path: group[path]}`` for the members ``paths``, their metadata read concurrently in one trip to Zarr's
    event loop thread (read one by one, each took 0.4-0.9 ms of a read's timeline at load 1-2); where reading
    one raises, the exception (KeyError for an absent one, as ``group[path]`` says it). Empty for a group with
    consolidated metadata (its members are read from that)."""
    if not paths or group.metadata.consolidated_metadata is not None:
        return {}
    base = f"{group.path}/" if group.path else ""

    async def fetch() -> list[Any]:
        return await asyncio.gather(*(get_node(group.store, base + p, 3) for p in paths), return_exceptions=True)

    out: dict[str, Any] = {}
    for path, got in zip(paths, zarr.core.sync.sync(fetch())):
        if isinstance(got, FileNotFoundError):
            got = KeyError(path)
        elif not isinstance(got, BaseException):
            got = zarr.Array(got) if isinstance(got, zarr.AsyncArray) else zarr.Group(got)
        out[path] = got
    return out
