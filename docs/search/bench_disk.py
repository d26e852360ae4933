"""Whole-map search from disk against reading the same codes, interleaved (sdfcodec.bench.harness).

    PYTHONPATH=. .venv/bin/python docs/search/bench_disk.py [--blocks 65536] [--repeats 5]

A pca-64 map of ``--blocks`` coded blocks (random codes with the shipped eigenshapes' per-component spread, as
``sdfcodec.bench.bench_search`` writes) in a temporary directory; the candidate is a whole search of it for a
floor model at a fixed threshold, the code-space score alone (``scene=False``: the streaming fetch-and-score
loop whose throughput the search page reports); the baseline reads the same codes
(``Map.iter_codes(level=64)``) and does nothing with them. Both read the local map's chunks through the map's
reader; the search scores each batch in the reader's fetching threads. Prints
JSON with blocks/s, the harness's ratios, CPU milliseconds per call and the load before and after.
``--unpruned`` adds a third candidate, interleaved with the two: the same search with the scorer's prefix pruning
off (``sdfcodec.search.scoring.PRUNE_PREFIX`` out of reach for the call), every code scored in full.
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import tempfile
from pathlib import Path

import numpy as np

import sdfcodec
from sdfcodec import pretrained_codec
from sdfcodec.bench.harness import interleave, load, ratio
from sdfcodec.search.query import build_query
from sdfcodec.search import scoring
from sdfcodec.search.engine import search


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--blocks", type=int, default=65536)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--unpruned", action="store_true", help="also time the search with no prefix pruning")
    args = ap.parse_args(argv)
    codec = pretrained_codec("pca", 64)
    n = args.blocks
    side = math.ceil(n ** (1 / 3))
    coords = np.stack(np.meshgrid(*[np.arange(side)] * 3, indexing="ij"), -1).reshape(-1, 3)[:n]
    spread = np.sqrt(codec.explained_variance_).astype(np.float32)[:64]
    rng = np.random.default_rng(0)
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "pca64.sdfz"
        with sdfcodec.create_map(path, codec=codec, voxel_size=0.02, overwrite=True, tool="bench_disk") as w:
            for i in range(0, n, 1 << 16):
                c = coords[i:i + (1 << 16)]
                w.write_codes(c, rng.standard_normal((len(c), 64), dtype=np.float32) * spread)
        m = sdfcodec.open_map(path)
        m.codec  # the codec state loaded once, outside the timings
        model = build_query("floor", codec=codec, voxel_size=0.02, truncation=m.truncation, behind="solid")

        def scored():
            search(m, model, threshold=1.0, device="cpu", scene=False)

        def read():
            for _ in m.iter_codes(level=64):
                pass

        def unpruned():
            kept, scoring.PRUNE_PREFIX = scoring.PRUNE_PREFIX, 1 << 30
            try:
                scored()
            finally:
                scoring.PRUNE_PREFIX = kept

        l0 = load()
        fns = {"search": scored, "read": read, **({"unpruned": unpruned} if args.unpruned else {})}
        t = interleave(fns, repeats=args.repeats, min_time=0.5)
        out = {"blocks": n, "search_blocks_per_s": n / t["search"].median, "read_blocks_per_s": n / t["read"].median,
               "search_best_blocks_per_s": n / t["search"].best, "read_best_blocks_per_s": n / t["read"].best,
               **ratio(t["search"], t["read"]),
               # CPU seconds of this process per call (all threads): under load the wall clock follows the share
               # of the cores the process gets, the CPU time what the work costs
               "search_cpu_ms": 1e3 * statistics.median(t["search"].cpu_rounds),
               "read_cpu_ms": 1e3 * statistics.median(t["read"].cpu_rounds),
               "load_before": l0, "load_after": load()}
        if args.unpruned:
            out.update({"unpruned_blocks_per_s": n / t["unpruned"].median,
                        "unpruned_ratio_of_medians": t["read"].median / t["unpruned"].median,
                        "unpruned_cpu_ms": 1e3 * statistics.median(t["unpruned"].cpu_rounds)})
    print(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
