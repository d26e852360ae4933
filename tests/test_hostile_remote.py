"""Remote reads against a hostile server (issue 21, items 3 and 4): a small valid map served on loopback over
HTTP and through moto's S3 server behind a fault-injecting proxy, with drips, endless and truncated bodies,
wrong Content-Lengths, 5xx (retried, and forever), resets, redirect loops, slow headers and gzip bombs. Every
read either decodes exactly what the local map decodes or ends, within its time bound, in one
``SDFCodecError`` naming the object; the bomb and huge-length cases also have their peak memory measured in a
subprocess. The ``slow`` variant injects >= 500 random faults and counts the outcomes.

moto offers no fault injection of its own (its ``moto_api`` has state transitions and a recorder), hence the
proxy. Every server binds 127.0.0.1 only, each of its loops is bounded (bytes, seconds, or a stop event), and it is
shut down when its test ends.
"""

from __future__ import annotations

import gzip
import http.client
import http.server
import json
import os
import random
import re
import socket
import struct
import subprocess
import sys
import threading
import time
import zlib
from pathlib import Path

import numpy as np
import pytest

import sdfcodec
from sdfcodec import errors
from sdfcodec.map.io.remote import RemoteLimits, encoded_bound

ROOT = Path(__file__).resolve().parents[1]
VS, TRUNC = 0.02, (-0.04, 0.1)
#: Short limits so that the suite is quick: what a read of each fault is allowed
FAST = {"connect_timeout": 1.0, "read_timeout": 1.0, "total_timeout": 1.5, "tries": 3, "backoff": 0.05,
        "max_backoff": 0.2}
BOUND_S = 3 * 1.5 + 3 * 0.2 + 5  # the longest a failing read may take: tries x total + backoff + slack
#: When a read that should fail is called a hang: far above ``BOUND_S``, because the wait also holds what precedes the
#: faulty object's first request (opening the map, a worker's first imports and compiles: 30 s once on CI's loaded
#: machine); the bound under test is timed from that request (``_since_first_request``)
HANG_S = 120.0
CHUNK = "codes/c/0/0/0/0"
S3_ERROR = (b'<?xml version="1.0" encoding="UTF-8"?><Error><Code>InternalError</Code><Message>injected fault'
            b'</Message></Error>')


def gzip_bomb(mib: int = 2500) -> bytes:
    """A gzip body of about 2.6 MB that decodes to ``mib`` MiB of zeros (its trailer's CRC is not that of the
    zeros: nothing should decode that far)."""
    c = zlib.compressobj(9, zlib.DEFLATED, 31)
    zeros = bytes(1 << 20)
    head = c.compress(zeros) + c.flush(zlib.Z_FULL_FLUSH)
    piece = c.compress(zeros) + c.flush(zlib.Z_FULL_FLUSH)  # the same bytes each time: the history is reset
    return head + piece * (mib - 1) + c.flush()


BOMB = gzip_bomb()
SMALL_BOMB = gzip_bomb(150)  # 155 kB: smaller than a chunk's bound, 150 MiB decoded


class HostileServer:
    """An HTTP server on 127.0.0.1 that answers GET/HEAD with the file under ``root`` (or, with ``upstream``,
    the response of that server: a proxy in front of moto) unless ``plan(path, n)`` names a fault for the
    ``n``-th request (from 1) of that path. Every response closes its connection."""

    def __init__(self, root: Path | None = None, upstream: tuple[str, int] | None = None, s3: bool = False):
        self.root, self.upstream, self.s3 = root, upstream, s3
        self.plan = lambda path, n: None
        self.counts: dict[str, int] = {}
        self.first: dict[str, float] = {}  # path -> time.monotonic() of its first request since counts.clear()
        self.faults: dict[str, int] = {}
        self.stop = threading.Event()
        self.lock = threading.Lock()
        owner = self

        class Handler(http.server.BaseHTTPRequestHandler):
            protocol_version = "HTTP/1.1"

            def log_message(self, *a, **k):
                pass

            def do_HEAD(self):
                owner.handle(self, head=True)

            def do_GET(self):
                owner.handle(self, head=False)

        self.server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.server.daemon_threads = True
        self.thread = threading.Thread(target=self.server.serve_forever, kwargs={"poll_interval": 0.05}, daemon=True)

    def __enter__(self):
        self.thread.start()
        return self

    def __exit__(self, *exc):
        self.stop.set()
        self.server.shutdown()
        self.server.server_close()

    @property
    def address(self) -> str:
        return f"http://127.0.0.1:{self.server.server_address[1]}"

    # -- the normal answer ---------------------------------------------------------------------------
    def normal(self, h, path: str, head: bool) -> tuple[int, dict[str, str], bytes]:
        if self.upstream is not None:
            conn = http.client.HTTPConnection(*self.upstream, timeout=10)
            try:
                headers = {k: v for k, v in h.headers.items() if k.lower() not in ("connection", "accept-encoding")}
                conn.request("HEAD" if head else "GET", h.path, headers=headers)
                r = conn.getresponse()
                body = r.read()
                return r.status, {k: v for k, v in r.getheaders()
                                  if k.lower() not in ("connection", "transfer-encoding", "content-length")}, body
            finally:
                conn.close()
        f = (self.root / path.lstrip("/")).resolve()
        if self.root.resolve() not in f.parents or not f.is_file():
            return 404, {}, b"not found"
        return 200, {"Content-Type": "application/octet-stream"}, f.read_bytes()

    # -- a request ------------------------------------------------------------------------------------
    def handle(self, h, head: bool) -> None:
        path = h.path.split("?", 1)[0]
        with self.lock:
            n = self.counts[path] = self.counts.get(path, 0) + 1
            if n == 1:
                self.first[path] = time.monotonic()
        fault = None if head else self.plan(path, n)
        if fault is not None:
            with self.lock:
                self.faults[fault] = self.faults.get(fault, 0) + 1
        try:
            self.answer(h, path, head, fault)
        except (BrokenPipeError, ConnectionResetError, socket.timeout, OSError):
            pass  # the client went away, as it should after refusing
        h.close_connection = True

    def send(self, h, status: int, headers: dict[str, str], body: bytes, length: int | None = None) -> None:
        h.send_response(status)
        for k, v in headers.items():
            h.send_header(k, v)
        if length is not None:
            h.send_header("Content-Length", str(length))
        h.send_header("Connection", "close")
        h.end_headers()
        if body:
            h.wfile.write(body)

    def answer(self, h, path: str, head: bool, fault: str | None) -> None:
        if fault in ("500", "503"):
            body = S3_ERROR if self.s3 else b"injected"
            return self.send(h, int(fault), {"Content-Type": "application/xml"}, body, len(body))
        if fault == "reset":  # RST instead of a response
            h.connection.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
            return None
        if fault == "redirect":
            return self.send(h, 302, {"Location": h.path}, b"", 0)
        if fault == "hang":  # accept, then say nothing
            self.stop.wait(20)
            return None
        if fault == "slow_headers":  # one byte of the status line every 0.4 s
            for b in b"HTTP/1.1 200 OK\r\nContent-Type: application/octet-stream\r\n"[:50]:
                if self.stop.wait(0.4):
                    break
                h.wfile.write(bytes([b]))
                h.wfile.flush()
            return None
        if fault == "huge_length":  # 10^12 bytes declared, a little sent
            self.send(h, 200, {}, b"", 10 ** 12)
            for _ in range(64):
                if self.stop.is_set():
                    break
                h.wfile.write(bytes(1 << 16))
            return None
        if fault == "endless":  # no length, zeros until the client hangs up (at most 256 MiB or 20 s)
            self.send(h, 200, {}, b"")
            t = time.monotonic()
            for _ in range(4096):
                if self.stop.is_set() or time.monotonic() - t > 20:
                    break
                h.wfile.write(bytes(1 << 16))
            return None
        if fault in ("bomb", "small_bomb"):
            body = BOMB if fault == "bomb" else SMALL_BOMB
            return self.send(h, 200, {"Content-Encoding": "gzip"}, body, len(body))
        status, headers, body = self.normal(h, path, head)
        if head:
            return self.send(h, status, headers, b"", len(body))
        if fault is None or status != 200:
            return self.send(h, status, headers, body, len(body))
        if fault in ("gzip_ok", "deflate_ok"):  # a legitimate encoded body (deflate: zlib-wrapped)
            enc = zlib.compress(body) if fault == "deflate_ok" else gzip.compress(body)
            return self.send(h, status, {**headers, "Content-Encoding": fault[:-3]}, enc, len(enc))
        if fault == "truncate":  # the right length declared, half sent
            return self.send(h, status, headers, body[: len(body) // 2], len(body))
        if fault == "long_length":
            return self.send(h, status, headers, body, len(body) + 100)
        if fault == "short_length":
            return self.send(h, status, headers, body, max(0, len(body) - 7))
        if fault == "drip":  # the right length, two bytes a second (at most 20 s)
            self.send(h, status, headers, b"", len(body))
            for i in range(min(len(body), 40)):
                if self.stop.wait(0.5):
                    break
                h.wfile.write(body[i:i + 1])
                h.wfile.flush()
            return None
        raise AssertionError(f"unknown fault {fault}")


# -- fixtures ---------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def small_map(tmp_path_factory):
    """A raw-codec map of 3 x 3 x 2 blocks in chunks of 2^3 blocks (4 chunks of codes, 128 KiB each decoded)."""
    from sdfcodec.core.sdf import sample_volume
    from sdfcodec.testing import analytic_scene

    root = tmp_path_factory.mktemp("hostile")
    vol = sample_volume(analytic_scene(), (48, 48, 32), VS, truncation=TRUNC)
    path = root / "x.sdfz"
    with sdfcodec.create_map(path, codec=sdfcodec.get_codec("raw"), voxel_size=VS, truncation=TRUNC,
                             chunk_blocks=2) as m:
        m.write_volume(vol)
    assert (path / CHUNK).is_file()
    return path, sdfcodec.open_map(path).decode_region()


@pytest.fixture(scope="module")
def http_server(small_map):
    with HostileServer(root=small_map[0].parent) as srv:
        yield srv


@pytest.fixture(scope="module")
def s3_proxy(small_map):
    """moto's S3 server holding the map at s3://maps/x.sdfz, a hostile proxy in front of it, and the
    storage_options that read through the proxy."""
    moto_server = pytest.importorskip("moto.server", reason="S3 tests need moto[server] (pip install moto[server])")
    s3fs = pytest.importorskip("s3fs", reason="S3 maps need s3fs (pip install s3fs)")
    saved = {k: os.environ.pop(k, None) for k in ("AWS_PROFILE", "AWS_CONFIG_FILE", "AWS_SHARED_CREDENTIALS_FILE")}
    os.environ["AWS_EC2_METADATA_DISABLED"] = "true"
    server = moto_server.ThreadedMotoServer(ip_address="127.0.0.1", port=0, verbose=False)
    server.start()
    host, port = server.get_host_and_port()
    # moto's buckets are process-wide state shared with other modules' servers: start from an empty S3
    import urllib.request

    urllib.request.urlopen(urllib.request.Request(f"http://{host}:{port}/moto-api/reset", method="POST"), timeout=10)
    base = {"key": "testing", "secret": "testing", "client_kwargs": {"region_name": "eu-west-1"},
            "skip_instance_cache": True}
    fs = s3fs.S3FileSystem(endpoint_url=f"http://{host}:{port}", **base)
    fs.mkdir("maps")
    fs.put(str(small_map[0]), "maps/x.sdfz", recursive=True)
    try:
        with HostileServer(upstream=(host, port), s3=True) as proxy:
            yield proxy, {"endpoint_url": proxy.address, **base}
    finally:
        server.stop()
        for k, v in saved.items():
            if v is not None:
                os.environ[k] = v


def _read(url: str, opts: dict) -> np.ndarray:
    return sdfcodec.open_map(url, storage_options=opts).decode_region()


def _since_first_request(server: "HostileServer", obj: str, start: float) -> float:
    """Seconds from the first request of ``obj`` since ``server.counts`` was cleared (the server stamps it) to now,
    else from ``start``: what opening the map and the imports of a first read cost before it (seconds on a loaded CI
    machine) is no part of the bound under test."""
    return time.monotonic() - server.first.get(obj, start) if server.counts.get(obj) else time.monotonic() - start


def _bounded(fn, seconds: float):
    """``fn()`` in a thread: ("ok", value), ("error", exc) or ("hang", None) when it outlasts ``seconds``."""
    out: list = []

    def run():
        try:
            out.append(("ok", fn()))
        except BaseException as e:  # noqa: BLE001 - sorted by the caller
            out.append(("error", e))

    t = threading.Thread(target=run, daemon=True)
    t.start()
    t.join(seconds)
    return out[0] if out else ("hang", None)


TARGETS = {"meta": "x.sdfz/zarr.json", "array": "x.sdfz/codes/zarr.json", "chunk": "x.sdfz/" + CHUNK}


# -- HTTP ------------------------------------------------------------------------------------------------

FAILING = [  # fault, object, what the one line must say
    ("500", "chunk", r"HTTP 500.* on each of 3 tries"),
    ("503", "meta", r"HTTP 503.* on each of 3 tries"),
    ("reset", "chunk", r"connection .* on each of 3 tries"),
    ("truncate", "chunk", r"truncated body .* on each of 3 tries"),
    ("long_length", "array", r"truncated body .* on each of 3 tries"),
    ("drip", "chunk", r"no complete response within the timeouts .* stalled .* not retried"),
    ("slow_headers", "meta", r"no complete response within the timeouts .* stalled .* not retried"),
    ("hang", "array", r"no complete response within the timeouts .* stalled .* not retried"),
    ("endless", "meta", r"more than 16777216 bytes.*refused \(not retried\)"),
    ("endless", "chunk", r"more than \d+ bytes.*refused \(not retried\)"),
    ("huge_length", "meta", r"declares 1000000000000 bytes.*refused"),
    ("bomb", "meta", r"decodes \(gzip\) to more than 16777216 bytes.*refused"),
    ("bomb", "chunk", r"declares \d+ bytes \(Content-Length\).*refused"),  # 2.6 MB: more than a chunk
    ("small_bomb", "chunk", r"decodes \(gzip\) to more than \d+ bytes.*refused"),
    ("redirect", "meta", r"more than 5 redirects \(a redirect loop\?\); refused \(not retried\)"),
]


@pytest.mark.parametrize("fault,target,says", FAILING, ids=[f"{f}-{t}" for f, t, _ in FAILING])
def test_http_fault_is_one_clear_error(small_map, http_server, fault, target, says):
    obj = "/" + TARGETS[target]
    http_server.plan = lambda path, n: fault if path == obj else None
    http_server.counts.clear()
    t = time.monotonic()
    kind, res = _bounded(lambda: _read(f"{http_server.address}/x.sdfz", {"remote_limits": FAST}), HANG_S)
    took = _since_first_request(http_server, obj, t)
    assert kind == "error", f"{fault} on {obj}: {kind}"
    assert isinstance(res, errors.RemoteReadError), f"{type(res).__name__}: {res}"
    msg = str(res)
    assert f"{http_server.address}{obj}" in msg and "\n" not in msg
    assert re.search(says, msg), msg
    assert "corrupt" not in msg and "restore" not in msg  # the server's fault is not called the map's
    assert took < BOUND_S, f"{fault}: {took:.1f} s"


@pytest.mark.parametrize("fault", ["500", "503", "reset", "truncate", "long_length"])
def test_http_transient_faults_are_retried(small_map, http_server, fault):
    path, ref = small_map
    obj = "/" + TARGETS["chunk"]
    http_server.plan = lambda p, n: fault if p == obj and n <= 2 else None  # two failures, then the object
    http_server.counts.clear()
    got = _read(f"{http_server.address}/x.sdfz", {"remote_limits": FAST})
    assert np.array_equal(got, ref)
    assert http_server.counts[obj] == 3


@pytest.mark.parametrize("encoding", ["gzip_ok", "deflate_ok"])
def test_http_content_encoding_is_decoded(small_map, http_server, encoding):
    http_server.plan = lambda p, n: encoding
    assert np.array_equal(_read(f"{http_server.address}/x.sdfz", {"remote_limits": FAST}), small_map[1])


def test_http_short_length_is_caught(small_map, http_server):
    # a Content-Length below the object's size: aiohttp sees data after the declared end (a malformed
    # response, retried) or, when the rest arrives later, delivers a prefix that the chunk's crc32c refuses
    obj = "/" + TARGETS["chunk"]
    http_server.plan = lambda p, n: "short_length" if p == obj else None
    with pytest.raises((errors.ChecksumError, errors.RemoteReadError), match="c/0/0/0/0"):
        _read(f"{http_server.address}/x.sdfz", {"remote_limits": FAST})


def test_connection_refused_is_retried_then_one_line():
    with socket.socket() as s:  # a port nobody listens on (bound, never listening)
        s.bind(("127.0.0.1", 0))
        url = f"http://127.0.0.1:{s.getsockname()[1]}/x.sdfz"
        with pytest.raises(errors.RemoteReadError, match=r"x\.sdfz/zarr\.json: connection failed .* on each of 3 tries"):
            _read(url, {"remote_limits": FAST})


@pytest.mark.parametrize("fault", ["hang", "drip", "slow_headers"])
def test_stall_fails_once_within_the_total_deadline(small_map, http_server, fault):
    """Issue 40: a stalled object is not retried: it ends in one request, within ``total_timeout`` (every try
    together), not tries x timeout (on main: 3 requests, 3 x 1.5 s here; 4 x 60 s = 244 s by default)."""
    obj = "/" + TARGETS["array"]
    http_server.plan = lambda p, n: fault if p == obj else None
    http_server.counts.clear()
    lim = {**FAST, "read_timeout": 0.5, "total_timeout": 1.5, "tries": 4}
    t = time.monotonic()
    kind, res = _bounded(lambda: _read(f"{http_server.address}/x.sdfz", {"remote_limits": lim}), HANG_S)
    took = _since_first_request(http_server, obj, t)
    assert kind == "error" and isinstance(res, errors.RemoteReadError), (kind, res)
    assert re.search(r"no complete response within the timeouts .* not retried", str(res)), res
    assert http_server.counts[obj] == 1, http_server.counts
    assert took < 1.5 + 1.0, f"{fault}: {took:.1f} s from the request of {obj}"


def test_errors_are_retried_only_within_the_total_deadline(small_map, http_server):
    """Retries of a failing object stop at ``total_timeout`` however many tries are allowed."""
    obj = "/" + TARGETS["chunk"]
    http_server.plan = lambda p, n: "503" if p == obj else None
    http_server.counts.clear()
    lim = {**FAST, "total_timeout": 1.0, "tries": 1000, "backoff": 0.1, "max_backoff": 0.1}
    t = time.monotonic()
    # the deadline ends the retries between two tries ("HTTP 503 ... on each of N tries") or, on a loaded machine,
    # during one ("no complete response ... after N failed tries (HTTP 503 ...)"): either names the status and count
    with pytest.raises(errors.RemoteReadError, match=r"HTTP 503.* on each of \d+ tries|after \d+ failed tries \(HTTP 503"):
        _read(f"{http_server.address}/x.sdfz", {"remote_limits": lim})
    took = _since_first_request(http_server, obj, t)
    assert 2 <= http_server.counts[obj] < 20, http_server.counts
    # the read's time before that object's first try (opening the map, a worker's first imports and compiles) is
    # no part of the deadline under test: on CI's loaded machine it has taken 30 s
    assert took < 1.0 + 1.0, f"{took:.1f} s from the first try of {obj}"


def test_default_stall_deadline_is_at_most_a_minute(monkeypatch):
    """What a stall costs with the default limits, every try together: at most 60 s (on main: 4 tries of 60 s
    plus backoff). The clock is not waited on: each try's timeout is recorded and the try times out at once."""
    import asyncio

    from sdfcodec.map.io import remote

    budgets = []

    async def times_out(aw, timeout):
        aw.close()
        budgets.append(timeout)
        raise asyncio.TimeoutError

    monkeypatch.setattr(remote.asyncio, "wait_for", times_out)
    real_sleep = asyncio.sleep
    monkeypatch.setattr(remote.asyncio, "sleep", lambda s: real_sleep(0))
    store = remote.remote_store("http://127.0.0.1:9/x.sdfz", None)
    assert store.remote == RemoteLimits()

    async def stalled():
        await asyncio.Event().wait()

    with pytest.raises(errors.RemoteReadError, match="not retried"):
        asyncio.run(store._retried("zarr.json", stalled))
    assert len(budgets) == 1 and sum(budgets) <= 60, budgets


def test_remote_limits_are_checked_and_documented_defaults(small_map, http_server):
    d = RemoteLimits()
    assert (d.connect_timeout, d.read_timeout, d.total_timeout, d.tries) == (10.0, 30.0, 60.0, 4)
    http_server.plan = lambda p, n: None
    for bad in ({"tries": 0}, {"total_timeout": -1}, {"nope": 1}, "fast"):
        with pytest.raises(errors.InvalidValueError, match="remote_limits"):
            _read(f"{http_server.address}/x.sdfz", {"remote_limits": bad})
    # defaults work too (and RemoteLimits itself is accepted)
    assert np.array_equal(_read(f"{http_server.address}/x.sdfz", {"remote_limits": RemoteLimits(tries=1)}),
                          small_map[1])
    assert encoded_bound(131072) < 2 * 131072


def test_cli_remote_options_bound_a_drip(small_map, http_server):
    """``sdfcodec --remote-timeout SECONDS --remote-tries N COMMAND`` sets the remote limits of every read the
    command makes: a server dripping the map's ``zarr.json`` (2 B/s, 20 s in all) ends ``info`` after 2 tries
    of 1 s, in one line that counts them, instead of the default 4 tries of 60 s."""
    from typer.testing import CliRunner

    from sdfcodec.cli import app
    from sdfcodec.map.io.remote import default_limits
    from sdfcodec.map.io.stores import set_read_defaults

    runner = CliRunner()
    url = f"{http_server.address}/x.sdfz"
    http_server.plan = lambda p, n: "drip" if p == "/x.sdfz/zarr.json" else None
    try:
        for cmd in ("info", "verify"):
            http_server.counts.clear()
            t = time.monotonic()
            r = runner.invoke(app, ["--remote-timeout", "1", "--remote-tries", "2", cmd, url])
            took = _since_first_request(http_server, "/x.sdfz/zarr.json", t)
            assert r.exit_code == 1, r.output
            assert re.search(r"x\.sdfz/zarr\.json: no complete response within the timeouts .* not retried",
                             r.output), r.output
            assert took < 1 + 3, f"{cmd}: {took:.1f} s"
        assert default_limits().tries == 2  # set for the process by the last invocation...
        http_server.plan = lambda p, n: None
        r = runner.invoke(app, ["info", url])
        assert r.exit_code == 0, r.output
        assert default_limits() == RemoteLimits()  # ...and back to the defaults by the next one
        r = runner.invoke(app, ["--remote-tries", "0", "info", url])
        assert r.exit_code == 1 and "--remote-tries must be a whole number >= 1" in r.output, r.output
    finally:
        set_read_defaults()
        http_server.plan = lambda p, n: None


def test_verify_says_no_map_at_for_a_missing_remote_map(http_server):
    """``verify`` of a URL where nothing is says what ``info`` says, "no map at URL", without zarr's class
    names (it said "not a readable Zarr v3 group (GroupNotFoundError: ...WrapperStore(FsspecStore...")."""
    from typer.testing import CliRunner

    from sdfcodec.cli import app
    from sdfcodec.map.verify import verify_map

    http_server.plan = lambda p, n: None
    url = f"{http_server.address}/nosuch.sdfz"
    rep = verify_map(url, storage_options={"remote_limits": FAST})
    assert [str(p) for p in rep.problems] == [f"map: no map at {url}"]
    r = CliRunner().invoke(app, ["verify", url])
    assert r.exit_code == 1 and f"no map at {url}" in r.output and "Error" not in r.output, r.output
    r = CliRunner().invoke(app, ["info", url])
    assert r.exit_code == 1 and f"no map at {url}" in r.output, r.output


# -- S3 through moto -------------------------------------------------------------------------------------

S3_FAILING = [
    ("500", "chunk", r"S3 InternalError \(HTTP 500\) on each of 3 tries"),
    ("reset", "meta", r"connection .* on each of 3 tries"),
    ("truncate", "chunk", r"(truncated|connection).* on each of 3 tries"),
    ("drip", "array", r"no complete response within the timeouts .* not retried|connection.* on each of 3 tries"),
    ("huge_length", "chunk", r"declares 1000000000000 bytes.*refused"),
    ("bomb", "meta", r"decodes \(gzip\) to more than 16777216 bytes.*refused"),
]


@pytest.mark.parametrize("fault,target,says", S3_FAILING, ids=[f"{f}-{t}" for f, t, _ in S3_FAILING])
def test_s3_fault_is_one_clear_error(small_map, s3_proxy, fault, target, says):
    proxy, opts = s3_proxy
    obj = "/maps/" + TARGETS[target]
    proxy.plan = lambda path, n: fault if path == obj else None
    proxy.counts.clear()
    t = time.monotonic()
    kind, res = _bounded(lambda: _read("s3://maps/x.sdfz", {**opts, "remote_limits": FAST}), HANG_S)
    took = _since_first_request(proxy, obj, t)
    assert kind == "error", f"{fault} on {obj}: {kind}"
    assert isinstance(res, errors.RemoteReadError), f"{type(res).__name__}: {res}"
    msg = str(res)
    assert "s3:/" + obj in msg and "\n" not in msg
    assert re.search(says, msg), msg
    assert took < BOUND_S, f"{fault}: {took:.1f} s"


def test_s3_transient_500_is_retried_and_deleted_objects_are_named(small_map, s3_proxy):
    proxy, opts = s3_proxy
    obj = "/maps/" + TARGETS["chunk"]
    proxy.plan = lambda p, n: "500" if p == obj and n <= 2 else None
    proxy.counts.clear()
    # FAST's tries with calm timeouts: what is checked is the retries and the errors' words, and FAST's 1.5 s in
    # all ran out under the suite's load (a RemoteReadError where the missing metadata was to be named)
    calm = {**FAST, "connect_timeout": 5.0, "read_timeout": 10.0, "total_timeout": 15.0}
    assert np.array_equal(_read("s3://maps/x.sdfz", {**opts, "remote_limits": calm}), small_map[1])
    assert proxy.counts[obj] == 3
    proxy.plan = lambda p, n: None
    # deleted objects (straight on moto): the map's metadata missing is a clear error naming the map
    import s3fs

    fs = s3fs.S3FileSystem(endpoint_url=f"http://{proxy.upstream[0]}:{proxy.upstream[1]}",
                           **{k: v for k, v in opts.items() if k != "endpoint_url"})
    fs.cp("maps/x.sdfz", "maps/y.sdfz", recursive=True)
    fs.rm("maps/y.sdfz/codes/zarr.json")
    # the manifest lists the metadata removed (maps without one: "lacks array 'codes'")
    with pytest.raises(errors.FormatError, match=r"s3://maps/y.sdfz.*codes/zarr.json\) is listed in the manifest but missing"):
        sdfcodec.open_map("s3://maps/y.sdfz", storage_options={**opts, "remote_limits": calm})
    fs.rm("maps/y.sdfz/zarr.json")
    with pytest.raises(errors.SDFCodecError, match="s3://maps/y.sdfz"):
        sdfcodec.open_map("s3://maps/y.sdfz", storage_options={**opts, "remote_limits": calm})
    # a deleted code chunk under coded blocks: verify names it
    from sdfcodec.map.verify import verify_map

    fs.cp("maps/x.sdfz", "maps/z.sdfz", recursive=True)
    fs.rm("maps/z.sdfz/" + CHUNK)
    rep = verify_map("s3://maps/z.sdfz", storage_options={**opts, "remote_limits": calm})
    assert not rep.ok and "0/0/0" in json.dumps(rep.to_dict() if hasattr(rep, "to_dict") else str(rep))


# -- memory: a refused read stays small ------------------------------------------------------------------

_MEMORY_SCRIPT = r"""
import json, sys, tracemalloc
import sdfcodec
base, cases = sys.argv[1], json.loads(sys.argv[2])
opts = {"remote_limits": {"connect_timeout": 2, "read_timeout": 2, "total_timeout": 20, "tries": 1}}
sdfcodec.open_map(base + "/good/x.sdfz", storage_options=opts).decode_region()  # warm every code path
tracemalloc.start()
out = {}
for case in ["good", *cases]:
    tracemalloc.reset_peak()
    now = tracemalloc.get_traced_memory()[0]
    try:
        sdfcodec.open_map(base + "/" + case + "/x.sdfz", storage_options=opts).decode_region()
        msg = "decoded"
    except sdfcodec.errors.SDFCodecError as e:
        msg = type(e).__name__ + ": " + str(e)
    out[case] = [msg, tracemalloc.get_traced_memory()[1] - now]
print(json.dumps(out))
"""


def test_refused_reads_have_bounded_peak_memory(small_map, http_server):
    # each case is a URL prefix the plan recognises: /<fault>-<target>/x.sdfz/... (files come from the map)
    root = small_map[0].parent
    cases = ["bomb-meta", "huge_length-meta", "endless-meta", "small_bomb-chunk", "endless-chunk",
             "huge_length-chunk"]
    for name in ["good", *cases]:
        (root / name).mkdir(exist_ok=True)
        if not (root / name / "x.sdfz").exists():
            (root / name / "x.sdfz").symlink_to(small_map[0])
    obj = {"meta": "x.sdfz/zarr.json", "chunk": "x.sdfz/" + CHUNK}

    def plan(path, n):
        head, _, rest = path.lstrip("/").partition("/")
        fault, _, target = head.partition("-")
        return fault if target and rest == obj[target] else None

    http_server.plan = plan
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), str(ROOT / "plugins"),
                                                        os.environ.get("PYTHONPATH", "")])}
    r = subprocess.run([sys.executable, "-c", _MEMORY_SCRIPT, http_server.address, json.dumps(cases)],
                       capture_output=True, text=True, timeout=120, env=env)
    assert r.returncode == 0, r.stderr[-2000:]
    out = json.loads(r.stdout.strip().splitlines()[-1])
    chunk_bound = encoded_bound(8 * 4096 * 4)
    assert out["good"][0] == "decoded"
    for case in cases:
        msg, grow = out[case]
        assert msg.startswith("RemoteReadError") and "refused" in msg, (case, msg)
        # Python-level peak (tracemalloc) while reading: at most twice what the object may legitimately be
        # (16 MiB of metadata, one chunk's encoding), plus 2 MiB for the reader itself
        limit = 2 * (16 << 20 if case.endswith("meta") else chunk_bound) + (2 << 20)
        assert grow <= limit, f"{case}: peak {grow / 2 ** 20:.1f} MiB (limit {limit / 2 ** 20:.1f})"
    print("\npeak memory per read (MiB, tracemalloc):", {k: round(v[1] / 2 ** 20, 2) for k, v in out.items()})


# -- hostile header: the install advice ------------------------------------------------------------------

@pytest.mark.parametrize("package,printed", [
    ("sdfcodec-evil", "pip install sdfcodec-evil"),
    ("x --index-url http://evil.example/ y", None),
    ("https://evil.example/pkg.whl", None),
    ("a\nb", None),
])
def test_unknown_codec_hint_prints_only_valid_package_names(small_map, tmp_path, package, printed):
    import shutil

    path = tmp_path / "x.sdfz"
    shutil.copytree(small_map[0], path)
    meta = json.loads((path / "zarr.json").read_text())
    meta["attributes"]["sdfcodec"]["codec"].update({"id": "no-such-codec", "package": package})
    meta["attributes"]["sdfcodec"]["codec"]["config"]["id"] = "no-such-codec"
    (path / "zarr.json").write_text(json.dumps(meta))
    try:
        m = sdfcodec.open_map(path)
    except errors.FormatError:
        pytest.skip("the header schema refuses this package name outright")
    with pytest.raises(errors.UnknownCodecError) as ei:
        m.decode_region()
    msg = str(ei.value)
    assert "'no-such-codec' is not installed" in msg
    if printed:
        assert printed in msg and "the map's header names package" in msg
    else:
        assert "pip install" not in msg and package not in msg


# -- the slow variant: random faults, counted ------------------------------------------------------------

def _random_faults(http_server, s3_proxy, ref, want: int, faults: list[str], seed: int) -> dict:
    """Reads of the whole map over HTTP or S3 (at random) with faults at random requests until ``want`` faults
    were injected; the outcome of every read, counted per protocol."""
    proxy, s3_opts = s3_proxy
    rng = random.Random(seed)
    lim = {**FAST, "total_timeout": 1.0, "tries": 3}
    counts = {p: {"faults": 0, "reads": 0, "decoded": 0, "errors": 0, "tracebacks": 0, "hangs": 0, "wrong": 0}
              for p in ("http", "s3")}
    kinds: dict[str, int] = {}
    for srv in (http_server, proxy):
        srv.faults.clear()
    while sum(c["faults"] for c in counts.values()) < want:
        proto = "http" if rng.random() < 0.5 else "s3"
        srv, url, opts = ((http_server, f"{http_server.address}/x.sdfz", {}) if proto == "http" else
                          (proxy, "s3://maps/x.sdfz", dict(s3_opts)))
        p, local = rng.choice([0.1, 0.3, 0.6]), random.Random(rng.random())
        srv.plan = lambda path, n, local=local, p=p: local.choice(faults) if local.random() < p else None
        before = sum(srv.faults.values())
        kind, res = _bounded(lambda: _read(url, {**opts, "remote_limits": lim}), 40)
        c = counts[proto]
        c["faults"] += sum(srv.faults.values()) - before
        c["reads"] += 1
        if kind == "hang":
            c["hangs"] += 1
        elif kind == "ok":
            c["decoded"] += 1
            c["wrong"] += not np.array_equal(res, ref)
        elif isinstance(res, errors.SDFCodecError) and "\n" not in str(res):
            c["errors"] += 1
            kinds[type(res).__name__] = kinds.get(type(res).__name__, 0) + 1
        else:
            c["tracebacks"] += 1
            print("foreign:", type(res).__name__, res)
    by_fault = {k: http_server.faults.get(k, 0) + proxy.faults.get(k, 0) for k in sorted(set(faults))}
    print(f"\nfaults injected: {by_fault}\noutcomes: {counts}; errors by type: {kinds}")
    for c in counts.values():
        assert c["hangs"] == c["tracebacks"] == c["wrong"] == 0, counts
    return counts


_QUICK_FAULTS = ["500", "503", "reset", "truncate", "long_length", "short_length", "huge_length", "endless",
                 "bomb", "small_bomb", "redirect"]


def test_random_remote_faults_short_run(small_map, http_server, s3_proxy):
    """CI's short fault run: 24 faults at random, none of the slow kinds (drip, hang, slow headers); each kind
    alone, at each kind of object: the FAILING and S3_FAILING tests above; 520 faults: the slow run below."""
    counts = _random_faults(http_server, s3_proxy, small_map[1], 24, _QUICK_FAULTS, seed=7)
    assert all(c["reads"] for c in counts.values())


@pytest.mark.slow
def test_random_remote_faults(small_map, http_server, s3_proxy):
    """>= 500 faults injected at random requests of random reads over HTTP and S3: every read ends within its
    bound (0 hangs), in a decode equal to the local map's or an SDFCodecError (0 tracebacks, 0 wrong)."""
    counts = _random_faults(http_server, s3_proxy, small_map[1], 520,
                            _QUICK_FAULTS * 5 + ["drip", "hang", "slow_headers"], seed=21)
    assert sum(c["faults"] for c in counts.values()) >= 500


# -- verify of a URL: what the header lists, never a listing ---------------------------------------------

def _map_objects(path: Path) -> int:
    return sum(1 for p in path.rglob("*") if p.is_file())


@pytest.mark.parametrize("listings", ["none", "loop", "html"])
def test_verify_url_checks_what_the_header_lists_never_a_listing(small_map, tmp_path, listings):
    """``verify URL`` against a server without listings (nginx's default, S3 websites), one whose listings are a
    self-similar tree (a ``loop/`` link in every directory) and an ordinary one: the same verdict, blocks and
    chunks as the local map's verify, in a bounded number of requests (on main: FAILED "27 unobserved, 0
    coded" with 0 chunks checked without listings, and a crawl without end through ``loop/``)."""
    import shutil

    from sdfcodec.bench.serve import FileServer
    from sdfcodec.map.verify import verify_map

    path = tmp_path / "x.sdfz"
    shutil.copytree(small_map[0], path)
    local = verify_map(path)
    assert local.ok and local.blocks["coded"] > 0
    with FileServer(tmp_path, listings=listings) as srv:
        # a healthy server: timeouts a loaded machine meets (FAST's 1 s failed once under the suite's two workers);
        # a crawl through listings would still run into the 60 s bound
        calm = {**FAST, "connect_timeout": 5.0, "read_timeout": 10.0, "total_timeout": 15.0}
        kind, rep = _bounded(lambda: verify_map(srv.url("x.sdfz"), storage_options={"remote_limits": calm}), 60)
        assert kind == "ok", (kind, rep, len(srv.requests))
        assert rep.ok, rep.problems
        assert rep.blocks == local.blocks and rep.chunks_checked == local.chunks_checked, (rep, local)
        assert rep.decoded_blocks == local.decoded_blocks
        # each object asked for at most three times (a one-byte probe, the read, the decode's read)
        assert len(srv.requests) <= 3 * _map_objects(path) + 10, sorted(srv.requests)
        assert not any(r.rstrip("/").endswith(("x.sdfz", "codes", "state", "c", "loop")) for r in srv.requests), \
            "a directory was listed"


@pytest.mark.parametrize("listings", ["none", "loop"])
def test_verify_url_names_missing_chunks_without_a_listing(small_map, tmp_path, listings):
    """Damage a remote map cannot hide without listings: a code chunk under coded blocks, a state chunk
    under stored codes, a codec state array; each is named, as the local verify names it."""
    import shutil

    from sdfcodec.bench.serve import FileServer
    from sdfcodec.map.verify import verify_map

    cases = {"code": CHUNK, "state": "state/c/0/0/0"}
    for name, rel in cases.items():
        path = tmp_path / name / "x.sdfz"
        shutil.copytree(small_map[0], path)
        (path / rel).unlink()
    with FileServer(tmp_path, listings=listings) as srv:
        for name, rel in cases.items():
            local = verify_map(tmp_path / name / "x.sdfz")
            kind, rep = _bounded(lambda: verify_map(srv.url(f"{name}/x.sdfz"),
                                                    storage_options={"remote_limits": FAST}), 60)
            assert kind == "ok", (kind, rep)
            assert not local.ok and not rep.ok, (name, rep)
            assert any(rel in p.where or rel in p.message for p in rep.problems), (name, rep.problems, local.problems)


_SESSION_SCRIPT = r"""
import gc, os, sys, urllib.request
os.environ["AWS_EC2_METADATA_DISABLED"] = "true"
import s3fs
from moto.server import ThreadedMotoServer
import sdfcodec

server = ThreadedMotoServer(ip_address="127.0.0.1", port=0, verbose=False)
server.start()
host, port = server.get_host_and_port()
urllib.request.urlopen(urllib.request.Request(f"http://{host}:{port}/moto-api/reset", method="POST"), timeout=10)
opts = {"key": "testing", "secret": "testing", "client_kwargs": {"region_name": "eu-west-1"},
        "endpoint_url": f"http://{host}:{port}", "skip_instance_cache": True}  # as the suite's S3 tests
fs = s3fs.S3FileSystem(**opts)
fs.mkdir("maps")
fs.put(sys.argv[1], "maps/x.sdfz", recursive=True)
closed = sdfcodec.open_map("s3://maps/x.sdfz", storage_options=opts)
closed.decode_region()
closed.close()
dropped = sdfcodec.open_map("s3://maps/x.sdfz", storage_options=opts)
dropped.decode_region()
del dropped
gc.collect()
kept = sdfcodec.open_map("s3://maps/x.sdfz", storage_options=opts)  # still open when the process ends
kept.decode_region()
print("read", flush=True)
"""


def test_s3_maps_close_their_sessions(small_map, tmp_path):
    """A remote map closes the S3 client session its reads opened, whether closed, dropped or still open when the
    process ends: aiohttp printed "Unclosed client session" at the end of every process that read an S3 map."""
    pytest.importorskip("moto.server", reason="S3 tests need moto[server] (pip install moto[server])")
    pytest.importorskip("s3fs", reason="S3 maps need s3fs (pip install s3fs)")
    script = tmp_path / "s3_sessions.py"
    script.write_text(_SESSION_SCRIPT)
    env = {k: v for k, v in os.environ.items() if k not in ("AWS_PROFILE", "AWS_CONFIG_FILE",
                                                            "AWS_SHARED_CREDENTIALS_FILE")}
    env["PYTHONWARNINGS"] = "always::ResourceWarning"
    p = subprocess.run([sys.executable, str(script), str(small_map[0])], capture_output=True, text=True,
                       timeout=120, env=env)
    assert p.returncode == 0 and "read" in p.stdout, p.stderr[-2000:]
    assert "Unclosed" not in p.stderr and "ResourceWarning" not in p.stderr, p.stderr[-2000:]
