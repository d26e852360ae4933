"""Remote reads that trust nothing: the store a map at an ``http(s)://`` or ``s3://`` URL is read through.

:class:`RemoteStore` wraps Zarr's fsspec store and replaces its reads (every read a map makes: metadata
documents and chunks whole, the indexes and chunks of shards as byte ranges, spec section 4d) with its own,
which

- time out: connect, silence between bytes (read), and a total per object, every try of it together
  (:class:`RemoteLimits`): a stalled object fails within ``total_timeout`` (60 s by default), never
  ``tries`` x that;
- bound the body while it streams, before anything is buffered whole: a Content-Length above the object's
  limit is refused unread, the bytes actually received are counted, and a ``Content-Encoding`` of gzip or
  deflate is decoded here, incrementally, never past the limit (a decompression bomb stops at limit + 1
  bytes). A byte range is bounded by its own length (sent as an HTTP ``Range`` or the ``Range`` of an S3
  GET; a server that ignores it and sends the whole object is bounded by the object's limit and cut here).
  An object's limit is what the reader allows it to be: a metadata document at most
  ``max_metadata_bytes`` (the guard's ``MAX_METADATA_BYTES``), a chunk at most the largest encoding of its
  decoded size (:func:`encoded_bound` of the size its array's checked metadata gives), anything else
  ``RemoteLimits.max_object_bytes``;
- retry transient errors (HTTP 500/502-504/408/429, S3 ``InternalError``/``SlowDown``..., connection resets,
  truncated bodies) with exponential backoff and jitter, within the object's total time; a stall (a timeout)
  is not retried: a server that stopped answering rarely answers the next try, and each try would cost the
  whole timeout again. After the last try, or the stall, raise one
  :class:`~sdfcodec.errors.RemoteReadError` naming the object, the status and the number of tries, saying
  the failure is the server's or the network's, not the map's.

A missing object (HTTP 404/410, S3 ``NoSuchKey``) is returned as missing, as Zarr expects of a chunk never
written. The limits travel inside ``storage_options`` under the key ``"remote_limits"`` (a
:class:`RemoteLimits` or a dict of its fields), so a map reopened in another process (dask) keeps them.
"""

from __future__ import annotations

import asyncio
import atexit
import dataclasses
import random
import time
import weakref
import zlib
from typing import Any

import zarr
import zarr.abc.store
from zarr.abc.store import OffsetByteRequest, RangeByteRequest, SuffixByteRequest
from zarr.buffer import default_buffer_prototype

from ...errors import FormatError, InvalidValueError, RemoteReadError

__all__ = ["RemoteLimits", "RemoteStore", "remote_store", "encoded_bound", "LIMITS_KEY", "set_default_limits",
           "default_limits"]

#: The ``storage_options`` key that holds the :class:`RemoteLimits` of a read (removed before fsspec sees it).
LIMITS_KEY = "remote_limits"

_STREAM_PIECE = 1 << 16  # bytes read from the socket at a time: the most a body is ahead of its checks
_TRANSIENT_HTTP = {408, 425, 429, 500, 502, 503, 504}
_MISSING_HTTP = {404, 410}
_TRANSIENT_S3 = {"InternalError", "ServiceUnavailable", "SlowDown", "RequestTimeout", "Throttling",
                 "ThrottlingException", "OperationAborted"}
_MISSING_S3 = {"NoSuchKey", "NotFound", "404", "NoSuchBucket", "NoSuchVersion"}
#: Fields of :class:`RemoteLimits` that replace its defaults for every remote read of this process (the CLI's
#: --remote-timeout and --remote-tries set them); a map's own ``storage_options`` still override them.
_PROCESS_LIMITS: dict[str, float] = {}


@dataclasses.dataclass(frozen=True)
class RemoteLimits:
    """How a remote map is read. Times are seconds, sizes bytes.

    ``connect_timeout``: to open a connection; ``read_timeout``: the longest silence while waiting for the
    response or its body; ``total_timeout``: one object, every try and the waits between them together, from
    the first request to the last byte (a server that drips a byte a second ends here, and a stalled one at
    ``read_timeout``: a timeout is not retried); ``tries``: attempts per object (transient errors only, within
    ``total_timeout``; the first retry waits ``backoff`` seconds, each next one twice as long, at most
    ``max_backoff``, with +-25% jitter); ``max_redirects``: redirects followed per request; ``max_object_bytes``: the bound of an object
    that is neither metadata nor a chunk of a checked array.
    """

    connect_timeout: float = 10.0
    read_timeout: float = 30.0
    total_timeout: float = 60.0
    tries: int = 4
    backoff: float = 0.5
    max_backoff: float = 8.0
    max_redirects: int = 5
    max_object_bytes: int = 256 << 20

    def __post_init__(self):
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not v >= 0 or v == float("inf"):
                raise InvalidValueError(f"remote_limits.{f.name} must be a finite number >= 0, got {v!r}")
        if self.tries < 1 or int(self.tries) != self.tries:
            raise InvalidValueError(f"remote_limits.tries must be a whole number >= 1, got {self.tries!r}")
        if min(self.connect_timeout, self.read_timeout, self.total_timeout) <= 0:
            raise InvalidValueError("remote_limits timeouts must be > 0 seconds")

    @classmethod
    def of(cls, value: "RemoteLimits | dict | None") -> "RemoteLimits":
        """``value`` as limits: itself, a dict of field values (unknown names are an error), or the defaults."""
        if value is None:
            return cls(**_PROCESS_LIMITS)
        if isinstance(value, cls):
            return value
        if isinstance(value, dict):
            known = {f.name for f in dataclasses.fields(cls)}
            unknown = sorted(set(value) - known)
            if unknown:
                raise InvalidValueError(f"storage_options['{LIMITS_KEY}'] has unknown fields {unknown}; known: "
                                        f"{sorted(known)}")
            return cls(**{**_PROCESS_LIMITS, **value})
        raise InvalidValueError(f"storage_options['{LIMITS_KEY}'] must be a RemoteLimits or a dict, got "
                                f"{type(value).__name__}")


def set_default_limits(fields: dict | None = None) -> None:
    """Make ``fields`` (of :class:`RemoteLimits`, e.g. ``{"total_timeout": 5, "tries": 2}``) the defaults of every
    remote read this process makes from now on (None or ``{}``: the built-in defaults again). A map's
    ``storage_options["remote_limits"]`` still override them field by field; maps reopened in other processes
    (dask workers that are not forks) carry only their own ``storage_options``.

    Raises:
        InvalidValueError: an unknown field or a value :class:`RemoteLimits` refuses.
    """
    fields = dict(fields or {})
    known = {f.name for f in dataclasses.fields(RemoteLimits)}
    if set(fields) - known:
        raise InvalidValueError(f"unknown remote limits {sorted(set(fields) - known)}; known: {sorted(known)}")
    RemoteLimits(**fields)  # checked before it applies
    _PROCESS_LIMITS.clear()
    _PROCESS_LIMITS.update(fields)


def default_limits() -> RemoteLimits:
    """The limits a remote read of this process gets when its map's ``storage_options`` set none."""
    return RemoteLimits(**_PROCESS_LIMITS)


def encoded_bound(decoded_bytes: int) -> int:
    """The most bytes a chunk of ``decoded_bytes`` can take encoded by the codecs a map may use (section 9a:
    bytes, blosc, zstd, gzip, crc32c; incompressible data grows by under 1/256 per compressor plus a header),
    with slack: ``n + n // 64 + 64 KiB``."""
    return decoded_bytes + decoded_bytes // 64 + (64 << 10)


class _Transient(Exception):
    """One try failed in a way a later try may not (the server's or the network's fault)."""

    def __init__(self, status: str):
        super().__init__(status)
        self.status = status


class _Refused(Exception):
    """The object is refused: retrying cannot help (too large, a client error, a redirect loop...)."""


class RemoteStore(zarr.storage.WrapperStore):
    """A read-only wrapper around a :class:`zarr.storage.FsspecStore` over HTTP(S) or S3 whose whole-object
    reads are bounded, timed and retried (module docstring). ``limits`` is the guard's table (array path ->
    (decoded chunk bytes, Blosc first)), shared with the :class:`~sdfcodec.map.io.stores.GuardStore` above it, so
    that a chunk is bounded as soon as its array's metadata has been checked."""

    def __init__(self, store: zarr.storage.FsspecStore, remote: RemoteLimits | None = None,
                 limits: dict[str, tuple[int, bool]] | None = None, *, url: str | None = None,
                 max_metadata_bytes: int = 16 << 20):
        super().__init__(store)
        self.remote = RemoteLimits.of(remote)
        self.limits: dict[str, tuple[int, bool]] = {} if limits is None else limits
        self.protocol = _protocol(store.fs)
        self.url = url if url is not None else store.path
        self.max_metadata_bytes = int(max_metadata_bytes)

    def _with_store(self, store):
        return type(self)(store, self.remote, self.limits, url=self.url, max_metadata_bytes=self.max_metadata_bytes)

    def close(self) -> None:
        """Close the store and the HTTP or S3 client session its filesystem opened (each remote map owns its
        filesystem: ``skip_instance_cache``). Without it aiohttp warns "Unclosed client session" when the process
        ends, and the connections stay open until then. A map dropped without ``close()`` closes it when its
        filesystem is collected."""
        super().close()
        _close_sessions(_SESSIONS.get(id(self._store.fs)))

    def _opened(self, close: Any) -> None:
        """Remember the session ``close`` (a coroutine function) of this store's filesystem, once, with the loop it
        runs on (Zarr's: a session belongs to the loop that made it)."""
        fs = self._store.fs
        opened = _SESSIONS.get(id(fs))
        if opened is None:
            # by identity: fsspec filesystems made with equal options compare equal, yet each has its own session
            opened = _SESSIONS[id(fs)] = []
            weakref.finalize(fs, _forget, id(fs))
            if not _AT_EXIT:
                # registered after Zarr's own exit hook, which stops its loop: this one runs first (last in, first out)
                _AT_EXIT.append(atexit.register(_close_all))
        if not any(c == close for _, c in opened):
            opened.append((asyncio.get_running_loop(), close))

    @property
    def inner(self) -> zarr.storage.FsspecStore:
        """The fsspec store this one reads through."""
        return self._store

    def limit_of(self, key: str) -> int:
        """The most bytes object ``key`` may have (module docstring): a shard (spec section 4d) its chunks'
        bounds and its index."""
        if key == "zarr.json" or key.endswith("/zarr.json"):
            return self.max_metadata_bytes
        hit = next((v for p, v in self.limits.items() if key.startswith(p + "/")), None)
        if hit is None:
            return int(self.remote.max_object_bytes)
        per = hit[2] if len(hit) > 2 else 1
        return per * encoded_bound(hit[0]) + (16 * per + 4 if per > 1 else 0)

    def object_url(self, key: str) -> str:
        """The URL of object ``key``, as error messages name it."""
        base = self.url.rstrip("/")
        if self.protocol == "s3" and not base.startswith("s3://"):
            base = "s3://" + base
        return f"{base}/{key}" if key else base

    async def get(self, key, prototype=None, byte_range=None):
        # ranges: the index and the chunks of a shard (spec section 4d), bounded by the range asked for
        data = await self._retried(key, lambda: self.fetch(key, byte_range))
        if data is None:
            return None
        return (prototype or default_buffer_prototype()).buffer.from_bytes(data)

    async def exists(self, key: str) -> bool:
        # a one-byte range read: bounded, timed and retried as any read, with a 5xx retried and then an error
        # (fsspec's own check reads any error as "missing", and for HTTP sends a GET of the whole object)
        return await self._retried(key, lambda: self.fetch(key, RangeByteRequest(0, 1))) is not None

    @property
    def supports_listing(self) -> bool:
        return False

    def _no_listing(self, prefix: str):
        raise FormatError(f"{self.object_url(prefix)}: a remote map is never listed (HTTP listings are HTML pages a "
                          "server may not make, or make without end); what it stores follows from its header")

    def list(self):
        self._no_listing("")

    def list_prefix(self, prefix: str):
        self._no_listing(prefix)

    def list_dir(self, prefix: str):
        self._no_listing(prefix)

    async def get_partial_values(self, prototype, key_ranges):
        key_ranges = list(key_ranges)
        return list(await asyncio.gather(*(self.get(k, prototype, r) for k, r in key_ranges)))

    # -- one object, all tries -------------------------------------------------------------------------
    async def _retried(self, key: str, attempt) -> Any:
        r = self.remote
        start = time.monotonic()
        deadline = start + r.total_timeout  # every try of this object together
        status, n = "no try", 0
        while n < r.tries:
            left = deadline - time.monotonic()
            if left <= 0:
                break
            n += 1
            try:
                return await asyncio.wait_for(attempt(), left)
            except _Refused as e:
                raise RemoteReadError(f"{self.object_url(key)}: {e}; refused (not retried)") from None
            except Exception as e:  # noqa: BLE001 - every transport failure is sorted here
                if _is_stall(e):
                    done = f" after {n - 1} failed {'try' if n == 2 else 'tries'} ({status})" if n > 1 else ""
                    raise RemoteReadError(
                        f"{self.object_url(key)}: {_stall_status(r)}{done}, {time.monotonic() - start:.1f} s in "
                        "all; a stalled server or network is not retried: try again later (--remote-timeout or "
                        "storage_options['remote_limits'] set the timeouts)") from None
                status = _transient_status(e, r)
                if status is None:
                    raise RemoteReadError(f"{self.object_url(key)}: could not be read ({type(e).__name__}: "
                                          f"{_short(e)}); not retried") from None
            if n == r.tries:
                break
            wait = min(r.max_backoff, r.backoff * 2 ** (n - 1)) * random.uniform(0.75, 1.25)
            if time.monotonic() + wait >= deadline:
                break  # no time left for another try
            await asyncio.sleep(wait)
        raise RemoteReadError(f"{self.object_url(key)}: {status} on each of {n} {'try' if n == 1 else 'tries'} "
                              f"over {time.monotonic() - start:.1f} s; the server or the network failed, not "
                              "necessarily the map: try again later (storage_options['remote_limits'] sets "
                              "tries and timeouts)") from None

    async def fetch(self, key: str, byte_range: Any = None) -> bytes | None:
        """One try at object ``key`` (``byte_range``: a Zarr byte request, sent as an HTTP ``Range``), bounded but
        not retried nor timed in total: its bytes, None when missing. A range is bounded by its own length (a
        server that ignores it and sends the whole object is bounded by the object's limit, and cut here)."""
        limit, rng = self.limit_of(key), _range_header(byte_range)
        if isinstance(byte_range, RangeByteRequest):
            limit = min(limit, max(0, byte_range.end - byte_range.start))
        elif isinstance(byte_range, SuffixByteRequest):
            limit = min(limit, byte_range.suffix)
        if self.protocol == "s3":
            return await self._fetch_s3(key, limit, rng)
        return await self._fetch_http(key, limit, rng, byte_range)

    async def _fetch_http(self, key: str, limit: int, rng: str | None = None, byte_range: Any = None) -> bytes | None:
        import aiohttp

        try:
            return await self._get_http(key, limit, rng, byte_range)
        except aiohttp.TooManyRedirects:
            raise _Refused(f"more than {int(self.remote.max_redirects)} redirects (a redirect loop?)") from None

    async def _get_http(self, key: str, limit: int, rng: str | None = None, byte_range: Any = None) -> bytes | None:
        import aiohttp

        fs, r = self._store.fs, self.remote
        url = f"{self._store.path.rstrip('/')}/{key}"
        session = await fs.set_session()
        self._opened(session.close)
        kw = dict(fs.kwargs)  # request options from storage_options (headers, auth, ...)
        kw.pop("timeout", None)
        headers = dict(kw.pop("headers", None) or {})
        if rng is not None:
            headers["Range"] = rng
            headers["Accept-Encoding"] = "identity"  # a range is of the object's own bytes
        elif not any(k.lower() == "accept-encoding" for k in headers):
            headers["Accept-Encoding"] = "gzip, deflate"  # the encodings decoded here (aiohttp may offer more)
        timeout = aiohttp.ClientTimeout(total=None, connect=r.connect_timeout, sock_read=r.read_timeout)
        async with session.get(fs.encode_url(url), timeout=timeout, max_redirects=int(r.max_redirects),
                               auto_decompress=False, headers=headers, **kw) as resp:
            if resp.status in _MISSING_HTTP:
                return None
            if resp.status == 416 and rng is not None:  # a range past the end: the object exists, and is shorter
                return b""
            if resp.status in _TRANSIENT_HTTP:
                raise _Transient(f"HTTP {resp.status} {resp.reason or ''}".rstrip())
            if resp.status >= 300:
                raise _Refused(f"HTTP {resp.status} {resp.reason or ''}".rstrip())
            length = resp.content_length
            enc = resp.headers.get("Content-Encoding", "identity").strip().lower()
            whole = rng is not None and resp.status != 206  # the server ignored the range: cut it here
            try:
                data = await _bounded(resp.content.read, length, enc, self.limit_of(key) if whole else limit)
                return _cut(data, byte_range) if whole else data
            except aiohttp.ClientPayloadError as e:  # aiohttp's word for a body cut short
                declared = f"the {length} bytes declared" if length is not None else "the end of the body"
                raise _Transient(f"truncated body (the connection closed before {declared})") from e

    async def _fetch_s3(self, key: str, limit: int, rng: str | None = None) -> bytes | None:
        from botocore.exceptions import ClientError

        fs = self._store.fs
        client = await fs.set_session()
        self._opened(client.close)
        bucket, obj, version = fs.split_path(f"{self._store.path.rstrip('/')}/{key}")
        extra = {**({"VersionId": version} if version else {}), **({"Range": rng} if rng else {})}
        try:
            resp = await fs.s3.get_object(Bucket=bucket, Key=obj, **extra)
        except ClientError as e:
            err, meta = e.response.get("Error", {}), e.response.get("ResponseMetadata", {})
            code, status = str(err.get("Code", "")), int(meta.get("HTTPStatusCode") or 0)
            if code in _MISSING_S3 or status == 404:
                return None
            if rng is not None and (code == "InvalidRange" or status == 416):  # as HTTP 416 above
                return b""
            if code in _TRANSIENT_S3 or status in _TRANSIENT_HTTP:
                raise _Transient(f"S3 {code or 'error'} (HTTP {status})")
            raise _Refused(f"S3 {code or 'error'} (HTTP {status}): {err.get('Message', '')}".rstrip(": "))
        body = resp["Body"]
        try:
            enc = str(resp.get("ContentEncoding") or "identity").strip().lower()
            return await _bounded(body.read, resp.get("ContentLength"), enc, limit)
        finally:
            body.close()


#: The client sessions each remote filesystem opened, by the filesystem's id: ``[(loop, close coroutine function)]``.
_SESSIONS: dict[int, list] = {}
_AT_EXIT: list = []  # the exit hook, once registered


def _forget(key: int) -> None:
    """A filesystem was collected: close what it opened."""
    _close_sessions(_SESSIONS.pop(key, None))


def _close_all() -> None:
    """At exit: close every session still open, while Zarr's loop still runs them."""
    for key in list(_SESSIONS):
        _close_sessions(_SESSIONS.get(key))


def _close_sessions(opened: list | None) -> None:
    """Close the sessions in ``opened`` on their loops (waiting up to 5 s each unless called on that loop), then
    forget them."""
    while opened:
        loop, close = opened.pop()
        if loop.is_closed() or not loop.is_running():
            continue  # nothing can run it any more (the process is ending)
        try:
            here = asyncio.get_running_loop()
        except RuntimeError:
            here = None
        if here is loop:
            loop.create_task(close())
            continue
        try:
            asyncio.run_coroutine_threadsafe(close(), loop).result(timeout=5)
        except Exception:  # noqa: BLE001 - a session that fails to close is no reason to fail closing a map
            pass


def _range_header(byte_range: Any) -> str | None:
    """The HTTP ``Range`` value of a Zarr byte request (None: the whole object)."""
    if byte_range is None:
        return None
    if isinstance(byte_range, RangeByteRequest):
        if byte_range.end <= byte_range.start:
            raise _Refused(f"an empty byte range [{byte_range.start}, {byte_range.end})")
        return f"bytes={byte_range.start}-{byte_range.end - 1}"
    if isinstance(byte_range, SuffixByteRequest):
        return f"bytes=-{byte_range.suffix}"
    if isinstance(byte_range, OffsetByteRequest):
        return f"bytes={byte_range.offset}-"
    raise _Refused(f"an unknown byte request {byte_range!r}")


def _cut(data: bytes, byte_range: Any) -> bytes:
    """The bytes of ``byte_range`` out of a whole object ``data``."""
    n = len(data)
    if isinstance(byte_range, RangeByteRequest):
        return data[min(byte_range.start, n):min(byte_range.end, n)]
    if isinstance(byte_range, SuffixByteRequest):
        return data[max(0, n - byte_range.suffix):]
    return data[min(byte_range.offset, n):]


async def _bounded(read, length: int | None, encoding: str, limit: int) -> bytes:
    """The body ``read(n)`` streams, decoded, refused once it (or its declared ``length``, or its decoding)
    exceeds ``limit`` bytes; a body shorter than ``length`` is a transient failure (truncated)."""
    if length is not None and length > limit:
        raise _Refused(f"the server declares {length} bytes (Content-Length), more than this object can be "
                       f"({limit})")
    if encoding in ("gzip", "x-gzip"):
        decoder = _Decoder(31)
    elif encoding == "deflate":
        decoder = _Decoder(None)
    elif encoding in ("identity", ""):
        decoder = None
    else:
        raise _Refused(f"the server sent Content-Encoding {encoding!r}, which sdfcodec does not decode")
    buf, got = bytearray(), 0
    while True:
        piece = await read(_STREAM_PIECE)
        if not piece:
            break
        got += len(piece)
        if got > limit:
            raise _Refused(f"the server sent more than {limit} bytes, more than this object can be")
        if decoder:
            decoder.feed(piece, buf, limit + 1)
        else:
            buf += piece
        if len(buf) > limit:
            raise _Refused(f"the body decodes ({encoding}) to more than {limit} bytes, more than this object "
                           "can be (a decompression bomb?)")
    if length is not None and got < length:
        raise _Transient(f"truncated body ({got} of {length} bytes)")
    if decoder is not None and not decoder.done:
        raise _Transient(f"truncated {encoding} body")
    return bytes(buf)


class _Decoder:
    """Incremental gzip (``wbits=31``, members in sequence) or deflate (zlib or raw, ``wbits=None``) decoding
    that never returns more than it is asked for."""

    def __init__(self, wbits: int | None):
        self.wbits, self.d, self.done = wbits, None, False

    def feed(self, data: bytes, buf: bytearray, max_len: int) -> None:
        """Decode ``data`` onto ``buf``, stopping once ``buf`` holds ``max_len`` bytes; decoded in steps of at
        most 1 MiB, so that nothing beyond ``buf`` is ever large."""
        while data and len(buf) < max_len:
            if self.d is None:
                wbits = self.wbits if self.wbits is not None else (15 if data[0] & 0x0F == 8 else -15)
                self.d, self.done = zlib.decompressobj(wbits), False
            try:
                buf += self.d.decompress(data, min(1 << 20, max_len - len(buf)))
            except zlib.error as e:
                raise _Refused(f"the body is not valid {'gzip' if self.wbits else 'deflate'} ({e})") from None
            if self.d.eof:
                data, self.d, self.done = self.d.unused_data, None, True
            else:
                data = self.d.unconsumed_tail


def _stall_status(r: RemoteLimits) -> str:
    return (f"no complete response within the timeouts (connect {r.connect_timeout:g} s, read {r.read_timeout:g} s, "
            f"total {r.total_timeout:g} s)")


def _is_stall(e: BaseException) -> bool:
    """Whether ``e`` is a timeout: the server or the network stopped answering (aiohttp's read and connect
    timeouts are TimeoutErrors too; botocore's are its own)."""
    if isinstance(e, (asyncio.TimeoutError, TimeoutError)):
        return True
    try:
        from botocore import exceptions as bx
    except ImportError:
        return False
    return isinstance(e, (bx.ReadTimeoutError, bx.ConnectTimeoutError))


def _transient_status(e: BaseException, r: RemoteLimits) -> str | None:
    """A short status for a transient error ``e`` (worth another try), or None when it is not one."""
    if isinstance(e, _Transient):
        return e.status
    try:
        import aiohttp
    except ImportError:  # pragma: no cover - fsspec's HTTP needs it
        aiohttp = None
    if aiohttp is not None:
        if isinstance(e, aiohttp.ClientResponseError):  # raised by the parser: we never raise_for_status
            return f"malformed HTTP response ({_short(e)[:120]})"
        if isinstance(e, (aiohttp.ClientPayloadError, aiohttp.ServerDisconnectedError)):
            return f"connection lost mid-response ({type(e).__name__})"
        if isinstance(e, aiohttp.ClientConnectionError):
            return f"connection failed ({type(e).__name__}: {_short(e)})"
    try:
        from botocore import exceptions as bx
    except ImportError:
        bx = None
    if bx is not None and isinstance(e, (bx.ConnectionError, bx.HTTPClientError, bx.ReadTimeoutError,
                                         bx.ResponseStreamingError, bx.IncompleteReadError)):
        return f"connection failed ({type(e).__name__})"
    if isinstance(e, (ConnectionError, OSError)) and not isinstance(e, FileNotFoundError):
        return f"connection failed ({type(e).__name__}: {_short(e)})"
    return None


def _short(e: BaseException) -> str:
    s = " ".join(str(e).split())
    return s if len(s) <= 200 else s[:197] + "..."


def _protocol(fs: Any) -> str:
    p = fs.protocol
    p = p[0] if isinstance(p, (tuple, list)) else p
    return "s3" if p in ("s3", "s3a") else str(p)


def _with_defaults(protocol: str, options: dict, r: RemoteLimits) -> dict:
    """fsspec options with this read's timeouts as defaults for what fsspec itself sends (existence checks,
    listings), and botocore's own retries off (this module retries, counting the tries)."""
    opts = dict(options)
    if protocol in ("http", "https"):
        import aiohttp

        ck = dict(opts.get("client_kwargs") or {})
        ck.setdefault("timeout", aiohttp.ClientTimeout(total=r.total_timeout, connect=r.connect_timeout,
                                                       sock_read=r.read_timeout))
        opts["client_kwargs"] = ck
    elif protocol in ("s3", "s3a"):
        ck = dict(opts.get("config_kwargs") or {})
        ck.setdefault("connect_timeout", r.connect_timeout)
        ck.setdefault("read_timeout", r.read_timeout)
        ck.setdefault("retries", {"total_max_attempts": 1})
        opts["config_kwargs"] = ck
    return opts


def remote_store(url: str, storage_options: dict | None, *, limits: dict[str, tuple[int, bool]] | None = None,
                 max_metadata_bytes: int = 16 << 20) -> zarr.abc.store.Store:
    """The read-only store of the map at ``url``: a :class:`RemoteStore` for ``http(s)://`` and ``s3://``, Zarr's
    fsspec store as it is for other URLs (``file://``, ``memory://``...). ``storage_options`` go to fsspec, less
    the key ``"remote_limits"`` (:class:`RemoteLimits`); ``limits`` is the guard's table of chunk sizes (shared,
    filled in as arrays are checked) and ``max_metadata_bytes`` the bound of a metadata document."""
    opts = dict(storage_options or {})
    r = RemoteLimits.of(opts.pop(LIMITS_KEY, None))
    protocol = url.split("://", 1)[0].lower()
    if protocol not in ("http", "https", "s3", "s3a"):
        return zarr.storage.FsspecStore.from_url(url, read_only=True, storage_options=opts or None)
    # a filesystem of its own (fsspec shares equal ones between callers): closing the map closes its session
    opts.setdefault("skip_instance_cache", True)
    store = zarr.storage.FsspecStore.from_url(url, read_only=True, storage_options=_with_defaults(protocol, opts, r))
    return RemoteStore(store, r, limits, url=url, max_metadata_bytes=max_metadata_bytes)
