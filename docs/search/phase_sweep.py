"""A floor search with the defaults on one analytic room at every sub-block floor height.

    PYTHONPATH=. .venv/bin/python docs/search/phase_sweep.py solid|unobserved [K ...]

The room: a floor over solid ground, a thick shelf and a wall (96^3 voxels of 2 cm, pca-64), the floor's top K
voxels above the face of block layer 1 (default K = 0, 0.5, ..., 15.5). ``unobserved``: every voxel more than
|d_min| behind a surface reads d_max (a fused-style field). A level floor has one offset to the block grid for
all its blocks, so a failure at one offset loses the whole floor; the evaluation's rooms draw their floor heights
at random and meet a given offset rarely. Prints, per K: the clean floor blocks (away from the wall), how many
the search found and selected, the blocks under the automatic threshold, what anchored the floor's level.
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import numpy as np

import sdfcodec
from sdfcodec import pretrained_codec
from sdfcodec.search.engine import search
from sdfcodec.core.sdf import Box, Plane, Scene, grid_points, sample_volume

VS, TRUNC, SHAPE = 0.02, (-0.04, 0.1), (96, 96, 96)


def main(argv: list[str]) -> int:
    behind = argv[0] if argv else "solid"
    ks = [float(x) for x in argv[1:]] or [float(k) for k in np.arange(0, 16, 0.5)]
    codec = pretrained_codec("pca", 64)
    with tempfile.TemporaryDirectory() as tmp:
        for k in ks:
            h = (16 + k) * VS
            scene = Scene([Box((1.0, 1.0, h - 1.0), (3.0, 3.0, 1.0)), Box((1.28, 0.96, 0.95), (0.48, 0.64, 0.1)),
                           Box((0.45 - 1.0, 1.0, 1.0), (1.0, 3.0, 2.0))])
            vol = sample_volume(scene, SHAPE, VS, truncation=TRUNC)
            if behind == "unobserved":
                vol = np.where(vol <= TRUNC[0] + 1e-6, TRUNC[1], vol).astype(np.float32)
            path = Path(tmp) / f"room-{k}.sdfz"
            with sdfcodec.create_map(path, codec=codec, voxel_size=VS, truncation=TRUNC) as w:
                w.write_volume(vol)
            with sdfcodec.open_map(path) as m:
                res = search(m, "floor", threshold="auto")
            got = {tuple(c) for c in res.coords.tolist()}
            d = np.abs(Plane((0, 0, 1), h)(grid_points(SHAPE, VS)))
            idx, cnt = np.unique(np.argwhere(d <= 0.6 * VS) // 16, axis=0, return_counts=True)
            clean = {tuple(int(v) for v in r) for r, c in zip(idx, cnt) if c >= 128 and r[0] >= 2}
            sc = res.stats["scene"]
            print(f"K={k:5.2f} clean floor blocks {len(clean):3d} found {len(got & clean):3d} selected {len(got):3d} "
                  f"under threshold {sc.get('under_threshold')} anchored by: {sc.get('anchored_by', '-')}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
