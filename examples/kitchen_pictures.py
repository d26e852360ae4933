"""Fuse the 7-Scenes kitchen, compress it with the shipped eigenshapes, and render both meshes.

    python examples/kitchen_pictures.py [--kitchen 7scenes-redkitchen] [--out docs/img]

Writes kitchen-raw.png (the fused field, lossless) and kitchen-pca-64.png / kitchen-pca-32.png (decoded from
64- and 32-element codes), and prints the map sizes. The same as running:

    sdfcodec fuse 7scenes-redkitchen kitchen.sdfz --voxel-size 0.02
    sdfcodec encode kitchen.sdfz kitchen-64.sdfz --code-size 64
    sdfcodec mesh kitchen-64.sdfz kitchen-64.ply
"""

from __future__ import annotations

import argparse
import os
import tempfile
from pathlib import Path

import numpy as np

import sdfcodec
from sdfcodec.fusion.tsdf import fuse, mesh_from_blocks
from sdfcodec.view.pictures import render_mesh, save_png

ROOT = Path(__file__).resolve().parents[1]


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--kitchen", default=os.environ.get("SDFCODEC_KITCHEN", "7scenes-redkitchen"),
                    help="a 7-Scenes redkitchen sequence folder (colour and depth frames, poses, gravity); default: $SDFCODEC_KITCHEN, else ./7scenes-redkitchen")
    ap.add_argument("--out", default=str(ROOT / "docs" / "img"))
    args = ap.parse_args()
    out = Path(args.out)
    kitchen = Path(args.kitchen)
    # look along the first camera's view, from 1.2 m behind it and a little above (camera y points down)
    pose = np.loadtxt(kitchen / "frame-000000.pose.txt")
    fwd, down = pose[:3, 2], pose[:3, 1]
    view = dict(eye=pose[:3, 3] - 1.2 * fwd - 0.5 * down, target=pose[:3, 3] + 1.5 * fwd, up=-down)
    fused = fuse(kitchen, voxel_size=0.02, truncation=(-0.04, 0.1))
    with tempfile.TemporaryDirectory() as tmp:
        raw_path = Path(tmp) / "kitchen.sdfz"
        with sdfcodec.create_map(raw_path, codec=sdfcodec.get_codec("raw"), voxel_size=0.02,
                                 origin=tuple(fused.origin)) as m:
            m.write_blocks(fused.coords, fused.tsdf)
        raw = sdfcodec.open_map(raw_path)
        for name, k in (("raw", None), ("pca-64", 64), ("pca-32", 32)):
            m = raw
            if k:
                path = Path(tmp) / f"kitchen-{k}.sdfz"
                with sdfcodec.create_map(path, codec=sdfcodec.pretrained_codec("pca", k), voxel_size=0.02,
                                         origin=raw.origin) as w:
                    for coords, blocks in raw.iter_blocks():
                        w.write_blocks(coords, blocks)
                m = sdfcodec.open_map(path)
            coords, blocks = zip(*m.iter_blocks())
            mesh = mesh_from_blocks(np.concatenate(coords), np.concatenate(blocks), origin=m.origin,
                                    voxel_size=m.voxel_size, truncation=m.truncation)
            save_png(render_mesh(mesh, width=800, height=600, **view), out / f"kitchen-{name}.png")
            info = m.info()
            print(f"{name}: {info['blocks']['coded']} coded blocks, {info['bytes_on_disk'] / 1024:.0f} KiB on disk "
                  f"({info['ratio_dense_to_disk']:.1f}:1), {len(mesh.triangles)} triangles")


if __name__ == "__main__":
    main()
