"""Measurements for docs/results.md, "Decoding in cache-sized tiles" (run:
.venv/bin/python docs/results/tiles_measure.py [WORKDIR] [REPEATS] [ROWS,...]): what each part of the tiled decode
is worth, every case interleaved with the roofline (numpy's (65536, 65) x (65, 4096) product into a preallocated
output) in the same rounds (sdfcodec.bench.harness):

- ``decode-tiles`` / ``decode-plain``: 8 groups of 8,192 codes in memory decoded to clipped metres into a ring of
  two touched buffers, through PCA's ``decode_tiles`` or the base class's (one product with all BLAS threads,
  then one clip pass): the decode side alone;
- ``ring-tiles`` / ``ring-plain``: ``Map.iter_decoded(copy=False)`` of the whole map with each;
- ``region-tiles`` / ``region-plain``: ``Map.decode_region()`` of the whole map with PCA's ``decode_tiles``
  (tiles placed from cache) and with the default (each group decoded, clipped, then placed);
- ``touch``: allocating and first touching a volume the size of the map's (what a fresh output costs alone);
- with a third argument, tile rows such as ``128,256,512``, instead of the above: ``ring-R`` and
  ``region-into-R`` for each (``TILE_ROWS`` set to R; ``decode_region(out=)`` into one reused, touched volume,
  as ``sdfcodec bench``'s ``decode-region-into``).

The map: 65,536 pca-64 blocks (float32 codes, 16^3-block chunks) written as ``sdfcodec bench`` writes its own.
Prints JSON: blocks/s (median, best) and ratios to the roofline, with the load before and after."""
import json
import os
import sys
import tempfile
from pathlib import Path

import numpy as np
import torch

import sdfcodec
import sdfcodec.core.tiling
from sdfcodec.bench.codecs import roofline_fn, roofline_shapes, write_bench_map
from sdfcodec.bench.harness import interleave, load
from sdfcodec.codec import Codec

work = Path(sys.argv[1] if len(sys.argv) > 1 else tempfile.mkdtemp(prefix="tiles-measure-"))
repeats = int(sys.argv[2]) if len(sys.argv) > 2 else 5
rows_swept = [int(r) for r in sys.argv[3].split(",")] if len(sys.argv) > 3 else []
work.mkdir(parents=True, exist_ok=True)
N = 65536
path = work / "tiles.sdfz"
codec = sdfcodec.pretrained_codec("pca", 64)
if not path.exists():
    write_bench_map(codec, N, path, (-0.04, 0.1))
m = sdfcodec.open_map(path)
pca = type(m.codec)
hooks = {name: pca.__dict__[name] for name in ("decode_tiles",)}


def use(*names):
    """PCA with only the named hooks of its own (the others: the base class's defaults)."""
    for name, fn in hooks.items():
        setattr(pca, name, fn if name in names else getattr(Codec, name))


_, codes = m.read_codes()
groups = [torch.from_numpy(codes[i:i + 8192].copy()) for i in range(0, N, 8192)]
ring = [torch.from_numpy(np.zeros((8192, 16, 16, 16), np.float32)) for _ in range(2)]


def decode(*names):
    use(*names)
    for i, c in enumerate(groups):
        m.codec.decode_tiles(c, 0.14, -0.04, (-0.04, 0.1), None, ring[i % 2])


def read(*names):
    use(*names)
    for _ in m.iter_decoded(copy=False):
        pass


def region(*names):
    use(*names)
    m.decode_region()


shape = tuple(int(n) * 16 for n in m.reader.grid_blocks)
cases = {"roofline": roofline_fn(roofline_shapes(codec, "decode"), N),
         "decode-tiles": lambda: decode("decode_tiles"), "decode-plain": lambda: decode(),
         "ring-tiles": lambda: read("decode_tiles"), "ring-plain": lambda: read(),
         "region-tiles": lambda: region("decode_tiles"), "region-plain": lambda: region(),
         "touch": lambda: np.empty(shape, np.float32).fill(0)}
if rows_swept:
    volume = np.ones(shape, np.float32)

    def rows_case(rows, run):
        def case():
            use("decode_tiles")
            sdfcodec.core.tiling.TILE_ROWS = rows
            try:
                run()
            finally:
                sdfcodec.core.tiling.TILE_ROWS = default_rows
        return case

    default_rows = sdfcodec.core.tiling.TILE_ROWS
    cases = {"roofline": cases["roofline"]}  # the sweep alone: fresh volumes' page faults disturb every round
    for r in rows_swept:
        cases[f"ring-{r}"] = rows_case(r, read)
        cases[f"region-into-{r}"] = rows_case(r, lambda: m.decode_region(out=volume))
load0 = load()
timed = interleave(cases, repeats=repeats, min_time=0.2)
load1 = load()
use("decode_tiles")
base = timed["roofline"]
res = {"load_before": load0, "load_after": load1, "cpus": os.cpu_count(), "blocks": N, "volume_voxels": shape,
       "cases": {k: {"blocks_per_s": N / t.median, "blocks_per_s_best": N / t.best,
                     "ratio_to_roofline": base.median / t.median, "ratio_of_bests": base.best / t.best}
                 for k, t in timed.items()}}
print(json.dumps(res, indent=1))
