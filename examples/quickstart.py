"""The README's "Python in ten lines", runnable: write a TSDF into a compressed map, read it back.

    python examples/quickstart.py                   # makes a small room.npy of exact distances first
    python examples/quickstart.py --tsdf my.npy     # your own (X, Y, Z) TSDF in metres, 2 cm voxels

Everything goes to --out (default: a temporary folder).
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np
import torch

import sdfcodec


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--tsdf", type=Path, help="a .npy (X, Y, Z) float TSDF in metres (default: a synthetic room)")
    ap.add_argument("--size", type=float, default=2.0, help="floor edge of the synthetic room in metres (default 2)")
    ap.add_argument("--out", type=Path, help="output folder (default: a temporary one)")
    args = ap.parse_args(argv)
    out = args.out or Path(tempfile.mkdtemp(prefix="sdfcodec-quickstart-"))
    out.mkdir(parents=True, exist_ok=True)
    room_npy = args.tsdf
    if room_npy is None:  # a floor, two walls, a box and a ball, sampled with exact distances
        from sdfcodec.core.sdf import Box, Plane, Scene, Sphere, sample_volume

        e = args.size
        room = Scene([Plane((0, 0, 1), 0.1), Plane((1, 0, 0), 0.1), Plane((0, 1, 0), 0.1),
                      Box((0.6 * e, 0.5 * e, 0.35), (0.3, 0.2, 0.25)), Sphere((0.3 * e, 0.7 * e, 0.4), 0.2)])
        room_npy = out / "room.npy"
        np.save(room_npy, sample_volume(room, [round(e / 0.02)] * 2 + [round(0.6 * e / 0.02)], 0.02))

    # --- the README's ten lines ----------------------------------------------------------------------
    tsdf = np.load(room_npy)                                      # (X, Y, Z) metres, truncated to [-0.04, 0.1]
    with sdfcodec.create_map(out / "room.sdfz", codec=sdfcodec.pretrained_codec("pca", 64), voxel_size=0.02) as m:
        m.write_volume(tsdf)                                      # written atomically when the block ends
    room = sdfcodec.open_map(out / "room.sdfz")                   # a path, file:// or http(s):// URL
    coarse = room.decode_region(((0, 64), (0, 64), (0, 32)), level=32)   # reads only the first 32 code elements
    coords, codes = room.read_codes()                             # (N, 3) block indices, (N, 64) codes
    if torch.cuda.is_available():
        tsdf_gpu = room.decode_region(device="cuda")              # a torch tensor on the GPU, where there is one
    # ---------------------------------------------------------------------------------------------------

    full = room.decode_region()
    info = room.info()
    surface = np.abs(tsdf) < 0.05
    print(f"map: {out / 'room.sdfz'}")
    print(f"volume {tsdf.shape}, {info['blocks']['coded']} coded blocks, codes {codes.shape}, coarse region {coarse.shape}")
    print(f"dense float32 {info['dense_float32_bytes'] / 1024:.0f} KiB -> codes {(info['bytes_on_disk'] - info['codec_state_bytes']) / 1024:.0f} KiB "
          f"({info['ratio_dense_to_codes']:.0f}:1), file on disk {info['bytes_on_disk'] / 1024:.0f} KiB "
          f"({info['ratio_dense_to_disk']:.1f}:1, with the 64 x 4096 basis)")
    print(f"RMSE near surfaces: {1000 * np.sqrt(np.mean((full[surface] - tsdf[surface]) ** 2)):.1f} mm")
    if torch.cuda.is_available():
        print(f"decoded on {tsdf_gpu.device}: {tuple(tsdf_gpu.shape)}")


if __name__ == "__main__":
    main()
