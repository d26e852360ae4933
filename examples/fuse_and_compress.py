"""Fuse a real RGB-D sequence (TUM RGB-D or 7-Scenes layout) into a map, then compress it with the shipped
eigenshapes and see what it costs.

    python examples/fuse_and_compress.py                                  # 7scenes-redkitchen
    python examples/fuse_and_compress.py rgbd_dataset_freiburg1_desk --frames 100 --stride 2

Writes OUT/raw.sdfz (the fused map, lossless) and OUT/pca-K.sdfz, and prints blocks, bytes, ratios and the
reconstruction error. The same as ``sdfcodec fuse SEQ raw.sdfz`` followed by ``sdfcodec encode``.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

import numpy as np

import sdfcodec
from sdfcodec.data.sequences import open_sequence
from sdfcodec.fusion.tsdf import fuse

# a TUM RGB-D or 7-Scenes sequence folder: $SDFCODEC_KITCHEN (the 7-Scenes redkitchen), else ./7scenes-redkitchen
DEFAULT_SEQUENCE = Path(os.environ.get("SDFCODEC_KITCHEN", "7scenes-redkitchen"))
TRUNC = (-0.04, 0.1)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sequence", type=Path, nargs="?", default=DEFAULT_SEQUENCE,
                    help=f"TUM RGB-D or 7-Scenes folder (default {DEFAULT_SEQUENCE})")
    ap.add_argument("--frames", type=int, default=None, help="fuse at most this many frames (default: all)")
    ap.add_argument("--stride", type=int, default=1, help="use every N-th frame")
    ap.add_argument("--voxel-size", type=float, default=0.02, help="metres (default 0.02)")
    ap.add_argument("--code-size", type=int, default=64, help="PCA code size, 1..128 (default 64)")
    ap.add_argument("--out", type=Path, help="output folder (default: a temporary one)")
    args = ap.parse_args(argv)
    if not args.sequence.is_dir():
        raise SystemExit(f"no sequence folder at {args.sequence}: give a TUM RGB-D or 7-Scenes folder")
    out = args.out or Path(tempfile.mkdtemp(prefix="sdfcodec-fuse-"))
    out.mkdir(parents=True, exist_ok=True)

    seq = open_sequence(args.sequence)[::args.stride]
    if args.frames is not None:
        seq = seq[:args.frames]
    t0 = time.perf_counter()
    fused = fuse(seq, voxel_size=args.voxel_size, truncation=TRUNC)             # open3d, progress bar on stderr
    print(f"{seq.layout} sequence {args.sequence.name}: {len(seq)} frames fused into {len(fused)} blocks "
          f"in {time.perf_counter() - t0:.1f} s")

    # the lossless map, then the compressed one (all-free blocks are stored as empty: no code)
    maps = {"raw": sdfcodec.get_codec("raw"), f"pca-{args.code_size}": sdfcodec.pretrained_codec("pca", args.code_size)}
    for name, codec in maps.items():
        t0 = time.perf_counter()
        with sdfcodec.create_map(out / f"{name}.sdfz", codec=codec, voxel_size=args.voxel_size, truncation=TRUNC,
                                 origin=tuple(fused.origin), overwrite=True, source=str(args.sequence)) as m:
            m.write_blocks(fused.coords, fused.tsdf)
        info = sdfcodec.open_map(out / f"{name}.sdfz").info()
        print(f"{name:>8}: {info['blocks']['coded']} coded blocks, codes {(info['bytes_on_disk'] - info['codec_state_bytes']) / 1024:,.0f} KiB "
              f"({info['ratio_dense_to_codes']:.0f}:1 against {info['dense_float32_bytes'] / 2**20:.1f} MiB dense), "
              f"with the codec's state {info['bytes_on_disk'] / 1024:,.0f} KiB ({info['ratio_dense_to_disk']:.1f}:1), "
              f"written in {time.perf_counter() - t0:.1f} s")

    raw = sdfcodec.open_map(out / "raw.sdfz").decode_region()
    dec = sdfcodec.open_map(out / f"pca-{args.code_size}.sdfz").decode_region()
    near = np.abs(raw) < 0.05
    mse = np.mean(((dec[near] - raw[near]) / (TRUNC[1] - TRUNC[0])) ** 2)
    print(f"pca-{args.code_size} near surfaces: RMSE {1000 * np.sqrt(np.mean((dec[near] - raw[near]) ** 2)):.1f} mm, "
          f"normalised MSE {mse:.2e}")
    print(f"maps in {out}")


if __name__ == "__main__":
    main()
