"""A static file server on loopback for measuring and testing remote maps: HTTP/1.1 byte ranges (``Range:
bytes=a-b``, ``bytes=-n``, ``bytes=a-``; what readers of sharded maps send) or, with ``ranges=False``, a server
that ignores them (sends whole files, as Python's ``http.server`` does), TCP_NODELAY like production servers
(without it the client's delayed ACK stalls each response by ~40 ms), and a log of ``(path, range, bytes)``
sent. Directories are answered as ``listings`` says: an HTML listing (``"html"``, what ``http.server`` makes),
404 (``"none"``: nginx's default and S3 websites make no listings), or a self-similar tree (``"loop"``: every
directory lists a ``loop/`` link back to itself, as a symbolic link to ``.`` served with listings does, so that
a crawler following links never ends).
"""

from __future__ import annotations

import http.server
import os
import re
import socket
import threading
from functools import partial
from pathlib import Path

from ..errors import InvalidValueError

__all__ = ["FileServer"]

_RANGE = re.compile(r"bytes=(\d*)-(\d*)$")


class _Handler(http.server.SimpleHTTPRequestHandler):
    protocol_version = "HTTP/1.1"
    ranges = True
    listings = "html"
    log: list = []
    requests: list = []  # every request's path, directories and misses included
    lock = threading.Lock()

    def log_message(self, *a, **k):
        pass

    def setup(self):
        super().setup()
        self.connection.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)

    def translate_path(self, path):
        if self.listings == "loop":  # x/loop/loop/y is x/y: the tree under every directory is the whole tree again
            head, sep, query = path.partition("?")
            head = re.sub(r"(?:/loop)+(?=/|$)", "", head) or "/"
            path = head + sep + query
        return super().translate_path(path)

    def list_directory(self, path):
        if self.listings == "none":
            self.send_error(404)
            return None
        if self.listings != "loop":
            return super().list_directory(path)
        names = ["loop/", *sorted(n + ("/" if os.path.isdir(os.path.join(path, n)) else "") for n in os.listdir(path))]
        body = "".join(f'<a href="{n}">{n}</a>\n' for n in names).encode()
        self.send_response(200)
        self.send_header("Content-Type", "text/html; charset=utf-8")
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        import io

        return io.BytesIO(body)

    def do_HEAD(self):
        with self.lock:
            self.requests.append(self.path)
        super().do_HEAD()

    def do_GET(self):
        with self.lock:
            self.requests.append(self.path)
        path = Path(self.translate_path(self.path))
        if path.is_dir():  # a listing as ``listings`` says (fsspec lists HTTP "directories" from HTML listings)
            super().do_GET()
            return
        if not path.is_file():
            self.send_error(404)
            return
        size = path.stat().st_size
        m = _RANGE.match(self.headers.get("Range", "")) if self.ranges else None
        start, stop = 0, size
        if m and (m.group(1) or m.group(2)):
            if m.group(1):
                start = int(m.group(1))
                stop = min(size, int(m.group(2)) + 1) if m.group(2) else size
            else:
                start = max(0, size - int(m.group(2)))
            if start >= size or stop <= start:
                self.send_error(416)
                return
        with open(path, "rb") as f:
            f.seek(start)
            data = f.read(stop - start)
        self.send_response(206 if m else 200)
        if m:
            self.send_header("Content-Range", f"bytes {start}-{stop - 1}/{size}")
        self.send_header("Content-Length", str(len(data)))
        self.send_header("Content-Type", "application/octet-stream")
        self.end_headers()
        self.wfile.write(data)
        with self.lock:
            self.log.append((self.path, self.headers.get("Range") if m else None, len(data)))


class _Server(http.server.ThreadingHTTPServer):
    # The listen backlog: the standard library's 5 is too short for a reader that opens a dozen connections at
    # once (fsspec's pool, several processes). Linux then drops the handshake's last ACK of the overflow; the
    # client believes it is connected and waits for an answer while the server retransmits its SYN-ACK with
    # back-off (1, 2, 4... s, about 31 s in all): one request of a whole-map read stalled until the client's
    # read timeout, and fresh processes reading a 65k-block map took 2.4-4.5 s instead of 1.4-1.7 s (measured)
    request_queue_size = 128
    daemon_threads = True


class FileServer:
    """Serve directory ``root`` on ``127.0.0.1`` in a thread while used as a context manager; ``url(name)`` is
    the URL of ``root/name``, ``take()`` the files served since the last call, ``requests`` the path of every
    request (directories and misses too). ``ranges`` and ``listings``: see the module docstring."""

    def __init__(self, root: str | os.PathLike, *, ranges: bool = True, listings: str = "html"):
        if listings not in ("html", "none", "loop"):
            raise InvalidValueError(f"listings must be 'html', 'none' or 'loop', got {listings!r}")
        handler = type("Handler", (_Handler,), {"ranges": ranges, "listings": listings, "log": [], "requests": [],
                                                "lock": threading.Lock()})
        self.log, self.requests = handler.log, handler.requests
        self.server = _Server(("127.0.0.1", 0), partial(handler, directory=str(root)))
        self.thread = threading.Thread(target=self.server.serve_forever, daemon=True)

    def __enter__(self) -> "FileServer":
        self.thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self.server.shutdown()
        self.server.server_close()

    def url(self, name: str) -> str:
        return f"http://127.0.0.1:{self.server.server_address[1]}/{name}"

    def take(self) -> list[tuple[str, str | None, int]]:
        out = list(self.log)
        self.log.clear()
        return out
