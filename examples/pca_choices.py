"""Measure the two PCA design choices: where the mean lives, and float16 code storage.

    python examples/pca_choices.py [--train 30000] [--test 5000] [--kitchen 7scenes-redkitchen]

Fits pca-32/64/128 with mean="dataset" and mean="block" on synthetic blocks, and reports per-voxel MSE and
per-block sum of squared errors (normalised units) on held-out synthetic blocks, on the built-in analytic room,
and (with --kitchen) on real blocks fused from 7-Scenes; then the extra error
of storing the codes as float16 instead of float32. Prints JSON.
"""

from __future__ import annotations

import argparse
import json

import numpy as np

import sdfcodec
from sdfcodec.core.blocks import normalise, split_blocks
from sdfcodec.data.synthetic import synthetic_blocks
from sdfcodec.data.render import room_scene
from sdfcodec.core.sdf import sample_volume

TRUNC = (-0.04, 0.1)


def nonempty(v: np.ndarray) -> np.ndarray:
    return v[~(v >= 1 - 1e-6).reshape(len(v), -1).all(axis=1)]


def errors(codec, x: np.ndarray, codes: np.ndarray | None = None) -> dict:
    codes = codec.encode(x) if codes is None else codes
    sq = (codec.decode(codes) - x) ** 2
    return {"mse_voxel": float(sq.mean()), "sse_block": float(sq.reshape(len(x), -1).sum(1).mean())}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--train", type=int, default=30000)
    ap.add_argument("--test", type=int, default=5000)
    ap.add_argument("--kitchen", default=None)
    args = ap.parse_args()
    train = synthetic_blocks(args.train, seed=0)
    sets = {"synthetic held-out": synthetic_blocks(args.test, seed=1)}
    room = sample_volume(room_scene(seed=0).sdf, (200, 160, 125), 0.02, truncation=TRUNC)
    sets["analytic room"] = nonempty(normalise(split_blocks(room, TRUNC[1]).reshape(-1, 16, 16, 16), *TRUNC))
    if args.kitchen:
        from sdfcodec.fusion.tsdf import fuse

        fused = fuse(args.kitchen, voxel_size=0.02, truncation=TRUNC, quiet=True)
        sets["7-scenes kitchen (real)"] = nonempty(normalise(fused.tsdf, *TRUNC))
    out = {"train_blocks": args.train, "sets": {k: len(v) for k, v in sets.items()}, "mean": [], "float16": []}
    for k in (32, 64, 128):
        for mean in ("dataset", "block"):
            codec = sdfcodec.get_codec("pca", code_size=k, mean=mean).fit(train)
            for name, x in sets.items():
                out["mean"].append({"code_size": k, "mean": mean, "set": name, **errors(codec, x)})
            if mean == "dataset":
                for name, x in sets.items():
                    z = codec.encode(x)
                    e32 = errors(codec, x, z)
                    e16 = errors(codec, x, z.astype(np.float16).astype(np.float32))
                    out["float16"].append({"code_size": k, "set": name, "float32": e32, "float16": e16,
                                           "relative_increase": e16["mse_voxel"] / e32["mse_voxel"] - 1})
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
