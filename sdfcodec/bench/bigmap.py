"""Maps of a million blocks (issue 18, item 3): build one out of core with dask distributed, and measure what
opening, reading a region, decoding it all and verifying it cost, from a local store, over HTTP and from S3.

``python -m sdfcodec.bench.bigmap build OUT --rooms 26 24 3`` encodes :class:`sdfcodec.data.offices.OfficeVolume`
(about 1.06 million coded blocks at 2 cm with these rooms) with the shipped pca-64 model on a
``dask.distributed.LocalCluster`` of worker processes (:func:`sdfcodec.scale.encode_volume_dask`: one task per
chunk of codes, the volume computed by each task for its own chunk, never whole anywhere).
``python -m sdfcodec.bench.bigmap measure MAP...`` prints the figures of ``docs/scale.md`` as JSON (a region
read's peak memory is measured in a fresh process each: ``ru_maxrss``).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path
from typing import Any, Sequence

__all__ = ["build", "region_read", "main"]

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
    from ..scale import encode_volume_dask
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


def region_read(location: str, centre_m: Sequence[float], edge_m: float = 1.0,
                storage_options: dict | None = None) -> dict[str, Any]:
    """Open the map at ``location`` and decode the ``edge_m`` cube around ``centre_m`` (metres, map frame): the
    seconds of each step and this process's peak RSS (the caller runs it in a fresh process)."""
    from ..map import open_map

    t0 = time.perf_counter()
    m = open_map(location, storage_options=storage_options)
    t1 = time.perf_counter()
    h = edge_m / 2
    region = [(c - h, c + h) for c in centre_m]
    v = m.decode_region(region, units="m")
    t2 = time.perf_counter()
    return {"open_s": t1 - t0, "region_s": t2 - t1, "voxels": list(v.shape),
            "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}


def _region_in_process(location: str, centre: Sequence[float], storage_options: dict | None) -> dict[str, Any]:
    code = ("import json,sys; from sdfcodec.bench.bigmap import region_read; "
            "a=json.loads(sys.argv[1]); print(json.dumps(region_read(*a)))")
    arg = json.dumps([location, list(centre), 1.0, storage_options])
    out = subprocess.run([sys.executable, "-c", code, arg], check=True, capture_output=True, text=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


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
    r = sub.add_parser("region", help="open a map and read a 1 m cube in a fresh process (time, peak RSS)")
    r.add_argument("location")
    r.add_argument("--centre", type=float, nargs=3, default=(10.0, 10.0, 1.5))
    a = p.parse_args(argv)
    if a.cmd == "build":
        doc = build(a.out, a.rooms, workers=a.workers, chunk_blocks=a.chunk_blocks, shard_blocks=a.shard_blocks,
                    overwrite=a.overwrite)
    else:
        doc = _region_in_process(a.location, a.centre, None)
    print(json.dumps(doc, indent=1))


if __name__ == "__main__":
    main()
