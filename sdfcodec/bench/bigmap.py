"""Maps of a million blocks: build one out of core with dask distributed, and measure what
opening, reading a region, decoding it all and verifying it cost, from a local store, over HTTP and from S3.

``python -m sdfcodec.bench.bigmap build OUT --rooms 26 24 3`` encodes :class:`sdfcodec.data.offices.OfficeVolume`
(about 1.06 million coded blocks at 2 cm with these rooms) with the shipped pca-64 model on a
``dask.distributed.LocalCluster`` of worker processes (:func:`sdfcodec.map.scale.encode_volume_dask`: one task per
chunk of codes, the volume computed by each task for its own chunk, never whole anywhere).
``python -m sdfcodec.bench.bigmap measure MAP...`` prints the figures of ``docs/scale.md`` as JSON (a region
read's peak memory is measured in a fresh process each: ``ru_maxrss``).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any, Sequence

__all__ = ["build", "region_read", "decode_rate", "measure", "main"]

VOXEL_SIZE, TRUNCATION = 0.02, (-0.04, 0.1)


def build(out: str | os.PathLike, rooms: Sequence[int], *, workers: int = 2, processes: bool = True,
          chunk_blocks: int | None = None, shard_blocks: int | None = None, seed: int = 0,
          overwrite: bool = False) -> dict[str, Any]:
    """Encode the office volume of ``rooms`` into the map ``out`` on a ``LocalCluster`` of ``workers`` processes
    (threads with ``processes=False``; one thread each); returns the figures (seconds, blocks, bytes and
    objects on disk)."""
    import dask.distributed

    from ..data.offices import OfficeVolume
    from ..map import open_map
    from ..registry import pretrained_codec
    from ..map.scale import encode_volume_dask
    from .harness import load

    vol = OfficeVolume(rooms, voxel_size=VOXEL_SIZE, truncation=TRUNCATION, seed=seed)
    codec = pretrained_codec("pca", 64)
    doc: dict[str, Any] = {"rooms": list(vol.rooms), "shape_voxels": list(vol.shape), "workers": workers,
                           "load_start": load()}
    with dask.distributed.LocalCluster(n_workers=workers, threads_per_worker=1, processes=processes,
                                       dashboard_address=None) as cluster, dask.distributed.Client(cluster):
        t0 = time.perf_counter()
        encode_volume_dask(vol, out, codec, voxel_size=VOXEL_SIZE, truncation=TRUNCATION, overwrite=overwrite,
                           chunk_blocks=chunk_blocks, shard_blocks=shard_blocks, tool="sdfcodec.bench.bigmap")
        doc["build_s"] = time.perf_counter() - t0
    doc["load_end"] = load()
    with open_map(out) as m:
        doc["states"] = m.count_states()
        doc["codes"] = m.header.codes.model_dump(exclude_none=True, exclude={"quantisation"})
    files = [p for p in Path(out).rglob("*") if p.is_file()]
    codes = [p for p in files if (Path(out) / "codes") in p.parents and p.name != "zarr.json"]
    doc.update(objects=len(files), bytes=sum(p.stat().st_size for p in files), code_objects=len(codes),
               code_bytes=sum(p.stat().st_size for p in codes))
    return doc


#: A child's peak resident memory in MiB, printed last: ``VmHWM`` of ``/proc/self/status``, not ``ru_maxrss``,
#: which in a child started by fork and exec on Linux reports the parent's peak at the fork.
_PEAK = ("with open('/proc/self/status') as f:\n"
         "    peak = next(int(x.split()[1]) for x in f if x.startswith('VmHWM:')) / 1024\n")

#: The region reads of :func:`region_read`, in a fresh process that imports what a user's program does (torch,
#: sdfcodec; of this benchmark package only this module, not the package's heavy imports): argv[1] is
#: ``[location, centres, storage_options]``; prints the figures as JSON.
_REGION_SCRIPT = """
import json, sys, time
import torch, sdfcodec
location, centres, options = json.loads(sys.argv[1])
t0 = time.perf_counter()
import zarr, sdfcodec.map.facade  # what the first open_map of a process imports (zarr, pydantic, numcodecs...)
t1 = time.perf_counter()
m = sdfcodec.open_map(location, storage_options=options)
out = {"imports_s": t1 - t0, "open_s": time.perf_counter() - t1, "region_s": []}
for c in centres:
    t0 = time.perf_counter()
    v = m.decode_region([(x - 0.5, x + 0.5) for x in c], units="m")
    out["region_s"].append(time.perf_counter() - t0)
out["voxels"] = list(v.shape)
""" + _PEAK + """out["peak_rss_mb"] = peak
print(json.dumps(out))
"""


def region_read(location: str, centres: Sequence[Sequence[float]], storage_options: dict | None = None
                ) -> dict[str, Any]:
    """In a fresh process: open the map at ``location`` and decode the 1 m cube around each of ``centres``
    (metres, map frame) in turn. Returns the seconds of the imports a first open of a process makes (Zarr,
    pydantic, numcodecs, fsspec: per process, not per map), of the open and of each read (the first one loads
    the codec state), the voxels of the last, and the process's peak RSS in MiB (``VmHWM``, Linux)."""
    arg = json.dumps([str(location), [list(map(float, c)) for c in centres], storage_options])
    out = subprocess.run([sys.executable, "-c", _REGION_SCRIPT, arg], check=True, capture_output=True, text=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def _baseline_rss() -> float:
    """Peak RSS (MiB) of a fresh process that imports sdfcodec and torch and does nothing else."""
    code = "import torch, sdfcodec\n" + _PEAK + "print(peak)"
    return float(subprocess.run([sys.executable, "-c", code], check=True, capture_output=True,
                                text=True).stdout.split()[-1])


def decode_rate(location: str, storage_options: dict | None = None) -> dict[str, Any]:
    """Whole-map decode on read (``iter_decoded()``, defaults; the codec loaded first): blocks, wall and CPU
    seconds (this process, all threads), blocks per second of each."""
    from ..map import open_map

    m = open_map(location, storage_options=storage_options)
    m.reader.codec  # the codec state is loaded (and checked against its digest) once per open, not timed here
    t0, c0, n = time.perf_counter(), time.process_time(), 0
    for coords, _ in m.iter_decoded():
        n += len(coords)
    dt, cpu = time.perf_counter() - t0, time.process_time() - c0
    # CPU seconds (all threads of this process) are steadier than wall time on a machine others load
    return {"blocks": n, "seconds": dt, "blocks_per_s": n / dt, "cpu_s": cpu, "blocks_per_cpu_s": n / cpu}


class _MotoServer:
    """moto's S3 server on loopback in its own process (so that serving does not share the reader's GIL)."""

    def __enter__(self):
        import socket as _socket

        with _socket.socket() as sk:
            sk.bind(("127.0.0.1", 0))
            self.port = sk.getsockname()[1]
        code = ("import sys, time; from moto.server import ThreadedMotoServer; "
                "s = ThreadedMotoServer(ip_address='127.0.0.1', port=int(sys.argv[1]), verbose=False); s.start(); "
                "time.sleep(1e9)")
        self.proc = subprocess.Popen([sys.executable, "-c", code, str(self.port)])
        self.options = {"key": "testing", "secret": "testing", "endpoint_url": f"http://127.0.0.1:{self.port}",
                        "client_kwargs": {"region_name": "eu-west-1"}, "skip_instance_cache": True}
        import s3fs

        deadline = time.monotonic() + 60
        while True:
            try:
                self.fs = s3fs.S3FileSystem(**self.options)
                self.fs.mkdir("maps")
                return self
            except Exception:  # noqa: BLE001 - not listening yet
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.5)

    def __exit__(self, *exc):
        self.proc.terminate()
        self.proc.wait(10)


def measure(maps: Sequence[str], *, centres: Sequence[Sequence[float]] = ((10.0, 10.0, 1.5), (50.3, 40.1, 4.4)),
            remote: bool = True, decode: bool = True, verify: bool = True) -> dict[str, Any]:
    """The figures of docs/scale.md for each local map in ``maps``: objects and bytes; open and 1 m^3 region read
    (seconds, peak RSS of a fresh process per read) locally, over HTTP (byte ranges, loopback) and from S3 (moto
    on loopback); whole-map decode on read; ``verify_map``. Loads are recorded before each step."""
    from ..map.verify import verify_map
    from .harness import load
    from .serve import FileServer

    doc: dict[str, Any] = {"baseline_rss_mb": _baseline_rss(), "maps": {}}
    moto = _MotoServer().__enter__() if remote else None
    try:
        for path in maps:
            p = Path(path)
            files = [f for f in p.rglob("*") if f.is_file()]
            r: dict[str, Any] = {"objects": len(files), "bytes": sum(f.stat().st_size for f in files)}
            r["local"] = dict(region_read(str(p), centres), load=load())
            if remote:
                with FileServer(p.parent) as srv:
                    r["http"] = dict(region_read(srv.url(p.name), centres), load=load())
                    sent = srv.take()  # everything the open and the reads fetched, codec state included
                    r["http"].update(requests=len(sent), bytes=sum(n for _, _, n in sent),
                                     code_bytes=sum(n for q, _, n in sent if "/codes/c/" in q))
                t0 = time.perf_counter()
                moto.fs.put(str(p), f"maps/{p.name}", recursive=True)
                r["s3_upload_s"] = time.perf_counter() - t0
                r["s3"] = dict(region_read(f"s3://maps/{p.name}", centres, moto.options), load=load())
            if decode:
                r["decode"] = dict(decode_rate(str(p)), load=load())
            if verify:
                t0 = time.perf_counter()
                rep = verify_map(p)
                r["verify"] = {"ok": rep.ok, "seconds": time.perf_counter() - t0,
                               "chunks": rep.chunks_checked.get("codes"), "decoded_blocks": rep.decoded_blocks, "load": load()}
            doc["maps"][str(p)] = r
    finally:
        if moto is not None:
            moto.__exit__(None, None, None)
    return doc


def main(argv: Sequence[str] | None = None) -> None:
    p = argparse.ArgumentParser(prog="python -m sdfcodec.bench.bigmap", description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    b = sub.add_parser("build", help="encode the office volume into a map with dask distributed")
    b.add_argument("out")
    b.add_argument("--rooms", type=int, nargs=3, default=(26, 24, 3))
    b.add_argument("--workers", type=int, default=2)
    b.add_argument("--chunk-blocks", type=int, default=None)
    b.add_argument("--shard-blocks", type=int, default=None)
    b.add_argument("--overwrite", action="store_true")
    ms = sub.add_parser("measure", help="open, region reads (local, HTTP, S3), decode and verify of maps")
    ms.add_argument("maps", nargs="+")
    ms.add_argument("--no-remote", action="store_true")
    ms.add_argument("--no-decode", action="store_true")
    ms.add_argument("--no-verify", action="store_true")
    a = p.parse_args(argv)
    if a.cmd == "build":
        doc = build(a.out, a.rooms, workers=a.workers, chunk_blocks=a.chunk_blocks, shard_blocks=a.shard_blocks,
                    overwrite=a.overwrite)
    else:
        doc = measure(a.maps, remote=not a.no_remote, decode=not a.no_decode, verify=not a.no_verify)
    print(json.dumps(doc, indent=1))


if __name__ == "__main__":
    main()
