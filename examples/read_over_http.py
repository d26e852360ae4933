"""Read a map over HTTP: serve a map folder with Python's http.server, open it by URL and decode one region.

    python examples/read_over_http.py                  # makes a small synthetic pca-64 map and serves it
    python examples/read_over_http.py --map room.sdfz  # serve your own map

The server runs in a thread on 127.0.0.1 (any free port) and counts the bytes it sends, so you see that
decoding a region fetches only the chunks that hold it (plus the header and the codec's state), not the map.
"""

from __future__ import annotations

import argparse
import functools
import http.server
import shutil
import tempfile
import threading
from pathlib import Path

import numpy as np

import sdfcodec


class CountingHandler(http.server.SimpleHTTPRequestHandler):
    """A static file handler that counts requests and body bytes sent (shared by all its instances)."""

    sent: dict[str, int] = {}  # bytes per part of the map: codes, state, codec, meta (zarr.json documents)
    requests = 0
    lock = threading.Lock()

    def copyfile(self, source, outputfile):
        n = 0
        while chunk := source.read(64 * 1024):
            outputfile.write(chunk)
            n += len(chunk)
        parts = self.path.strip("/").split("/")
        kind = "meta" if parts[-1] == "zarr.json" else (parts[1] if len(parts) > 1 else parts[0])
        with self.lock:
            CountingHandler.sent[kind] = CountingHandler.sent.get(kind, 0) + n
            CountingHandler.requests += 1

    def log_message(self, format, *args):  # quiet
        pass


def _kib(n: int) -> str:
    return f"{n / 1024:.1f} KiB"


def _dir_bytes(path: Path) -> int:
    return sum(f.stat().st_size for f in path.rglob("*") if f.is_file())


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--map", type=Path, help="a local map directory to serve (default: a synthetic pca-64 room)")
    ap.add_argument("--size", type=float, default=4.0, help="length of the synthetic map in metres (default 4)")
    ap.add_argument("--region", default="0:64,0:64,0:64", help="voxels x0:x1,y0:y1,z0:z1 to decode")
    args = ap.parse_args(argv)
    work = Path(tempfile.mkdtemp(prefix="sdfcodec-http-"))
    if args.map is None:  # a floor, a wall and a box, long enough along x for two chunks of blocks
        from sdfcodec.core.sdf import Box, Plane, Scene, sample_volume

        e = args.size
        scene = Scene([Plane((0, 0, 1), 0.1), Plane((0, 1, 0), 0.1), Box((0.7 * e, 0.6, 0.4), (0.3, 0.3, 0.3))])
        path = work / "room.sdfz"
        # chunk_blocks=8 (128^3 voxels per chunk) rather than the default 16: a map mostly read in small
        # remote regions transfers less per region with smaller chunks (docs/scale.md, "Chunk size")
        with sdfcodec.create_map(path, codec=sdfcodec.pretrained_codec("pca", 64), voxel_size=0.02, chunk_blocks=8) as m:
            m.write_volume(sample_volume(scene, (round(e / 0.02), 64, 64), 0.02))
    else:
        path = args.map.resolve()
    region = tuple(tuple(int(v) for v in part.split(":")) for part in args.region.split(","))

    handler = functools.partial(CountingHandler, directory=str(path.parent))
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        url = f"http://127.0.0.1:{server.server_address[1]}/{path.name}"
        remote = sdfcodec.open_map(url)
        opened = sum(CountingHandler.sent.values())
        tsdf = remote.decode_region(region)
        local = sdfcodec.open_map(path).decode_region(region)
        sent = CountingHandler.sent
        print(f"opened {url}: {remote.header.codec.id}-{remote.code_size}, {remote.shape_voxels} voxels "
              f"({_kib(opened)} fetched: header and array metadata)")
        print(f"decoded region {region} -> {tsdf.shape}, identical to the local read: {np.array_equal(tsdf, local)}")
        print(f"fetched {_kib(sum(sent.values()))} in {CountingHandler.requests} requests: codes "
              f"{_kib(sent.get('codes', 0))} of {_kib(_dir_bytes(path / 'codes'))}, block states "
              f"{_kib(sent.get('state', 0))}, codec state {_kib(sent.get('codec', 0))} (fetched once per reader), "
              f"metadata {_kib(sent.get('meta', 0))}; the whole map is {_kib(_dir_bytes(path))}")
    finally:
        server.shutdown()
        server.server_close()
        if args.map is None:
            shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
