"""Train the shipped default eigenshapes (plugins/sdfcodec_pca/models/pca-128.npz) and report their error on
real blocks.

    make default-model        # = python examples/train_default_model.py

Reproducible: fixed seeds, nothing downloaded. Steps:

1. Fuse ../shared/data/7scenes-redkitchen at 2 cm (truncation [-0.04, 0.1] m) and split the map in two halves
   along x, one block apart: windows sampled from the first half (the paper's sub-volume sampler, every 4
   voxels by default here, six axis orders) join the training data; the allocated non-empty blocks of the second half are
   the held-out real test set. A spatial split, so no held-out surface was seen in training.
2. Build a data set (sdfcodec.dataset, split 300:50:50 by batches of 500) of synthetic primitive blocks plus
   those real windows, and fit pca-128 on its training split: the shipped model. Fused blocks are observed only
   in part (nothing behind the thin band behind each surface): the real windows are cut from the training half
   with its unobserved voxels filled by the current basis's weighted least-squares reconstruction (what the map
   writer encodes, sdfcodec.map.observed), and the basis is refitted on them, ``--em-iterations`` times
   (expectation-maximisation for missing data: the basis learns the surfaces, not the step to unobserved).
3. Fit the same on the synthetic blocks alone, and report both at 32/64/128 (prefixes of the 128 basis) on
   the held-out real blocks: per-voxel MSE and per-block sum of squared errors, normalised units.

Writes plugins/sdfcodec_pca/models/pca-128.npz, docs/default-model.json and docs/default-model.md.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import numpy as np

import sdfcodec
from sdfcodec.blocks import denormalise
from sdfcodec.data.sampler import iter_windows
from sdfcodec.map.observed import error_weights
from sdfcodec.surface import compare_volumes
from sdfcodec.data.synthetic import synthetic_blocks
from sdfcodec.dataset import build_dataset
from sdfcodec.fusion import fuse

ROOT = Path(__file__).resolve().parents[1]
TRUNC, VS = (-0.04, 0.1), 0.02


def errors(codec, x: np.ndarray) -> dict:
    sq = (codec.decode(codec.encode(x)) - x) ** 2
    return {"mse_voxel": float(sq.mean()), "sse_block": float(sq.reshape(len(x), -1).sum(1).mean())}


def surface_errors(codec, part) -> dict:
    """Surface metrics (sdfcodec.surface) of fused blocks ``part`` encoded as a map writer encodes them (weighted,
    unobserved voxels restored to d_max) against the blocks themselves."""
    obs = part.weights > 0
    v = part.normalised()
    rec = np.where(obs, codec.decode(codec.encode(v, weights=error_weights(v, obs, TRUNC, VS))), 1.0)
    got = compare_volumes(part.to_dense(), dataclasses.replace(part, tsdf=denormalise(rec, *TRUNC)).to_dense(), VS)
    return {"chamfer_l1_mm": 1000 * got.chamfer_l1, "f_score_1": got.f_score_1, "f_score_2": got.f_score_2}


def filled(part, codec) -> np.ndarray:
    """Dense volume (metres) of fused blocks ``part`` whose unobserved voxels hold ``codec``'s weighted
    reconstruction of their block (as a map writer encodes it); ``d_max`` there when ``codec`` is None."""
    if codec is None:
        return part.to_dense()
    obs = part.weights > 0
    v = part.normalised()
    w = error_weights(v, obs, TRUNC, VS)
    rec = codec.decode(codec.encode(v, weights=w))
    v = np.where(obs, v, np.clip(rec, 0.0, 1.0))
    return dataclasses.replace(part, tsdf=denormalise(v, *TRUNC)).to_dense()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--kitchen", default=str(ROOT.parent / "shared" / "data" / "7scenes-redkitchen"))
    ap.add_argument("--synthetic", type=int, default=60_000)
    ap.add_argument("--real-stride", type=int, default=4,
                    help="window stride on the real half (4: overlapping windows, 8x the paper's 8-voxel count)")
    ap.add_argument("--em-iterations", type=int, default=0,
                    help="refits on real windows whose unobserved voxels the previous basis filled (0, the shipped model: 2 measured worse on the held-out half, docs/surface.md)")
    ap.add_argument("--workdir", default=str(ROOT / "build" / "default-model"))
    ap.add_argument("--model", default=str(ROOT / "plugins" / "sdfcodec_pca" / "models" / "pca-128.npz"))
    ap.add_argument("--report", default=str(ROOT / "docs" / "default-model"))
    args = ap.parse_args()
    work = Path(args.workdir)
    work.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()

    fused = fuse(args.kitchen, voxel_size=VS, truncation=TRUNC)
    split_x = fused.grid_shape[0] // 2
    train_half = fused.select(fused.coords[:, 0] < split_x)
    held = fused.select(fused.coords[:, 0] > split_x)  # one block column between the halves
    held_v = held.normalised()
    held_v = held_v[~(held_v >= 1 - 1e-6).reshape(len(held_v), -1).all(axis=1)]
    print(f"kitchen: {len(fused)} blocks; training half {len(train_half)}, held-out non-empty {len(held_v)}")

    def synth():
        for i in range(0, args.synthetic, 10_000):
            yield synthetic_blocks(min(10_000, args.synthetic - i), seed=i, voxel_size=VS, truncation=TRUNC)

    results: dict = {"kitchen_blocks": len(fused), "held_out_blocks": len(held_v), "real_windows": 0,
                     "synthetic_blocks": args.synthetic, "em_iterations": args.em_iterations, "models": {}}
    for name in ("synthetic + real", "synthetic only"):
        codec, t1 = None, time.perf_counter()
        for it in range(args.em_iterations + 1 if name == "synthetic + real" else 1):
            sources = [("synthetic", synth())]
            if name == "synthetic + real":
                real_windows = list(iter_windows(filled(train_half, codec), stride=args.real_stride,
                                                 truncation=TRUNC, seed=0))
                results["real_windows"] = sum(len(b) for b in real_windows)
                sources.append(("kitchen-train-half", real_windows))
            ds = build_dataset(work / f"{name.replace(' ', '').replace('+', '-')}.zarr", sources, voxel_size=VS,
                               truncation=TRUNC, overwrite=True)
            codec = sdfcodec.get_codec("pca", code_size=128).fit(ds.load("train"))
            print(f"{name}: fit {it + 1} done")
        fit_s = time.perf_counter() - t1
        rec = {"train_blocks": ds.meta["splits"]["train"], "fit_seconds": fit_s, "held_out_real": {},
               "test_split": {}}
        test = ds.load("test")
        for k in (32, 64, 128):
            c = codec.prefix(k)
            rec["held_out_real"][k] = {**errors(c, held_v), **surface_errors(c, held)}
            rec["test_split"][k] = errors(c, test)
        results["models"][name] = rec
        print(name, json.dumps(rec["held_out_real"]))
        if name == "synthetic + real":
            sdfcodec.save_model(codec, args.model)
    results["seconds"] = time.perf_counter() - t0
    Path(args.report + ".json").write_text(json.dumps(results, indent=2))
    lines = ["# Default eigenshapes", "",
             "Made by `make default-model` (`python examples/train_default_model.py`). Errors in normalised units "
             f"(distance / {TRUNC[1] - TRUNC[0]:.2f} m) on {len(held_v)} held-out real blocks: the non-empty blocks "
             "of the half of the 7-Scenes redkitchen map (fused at 2 cm) that training never saw.", "",
             "Surface metrics (sdfcodec.surface; docs/surface.md) of the same held-out half encoded as a map writer "
             "encodes it (observation mask, surface-weighted least squares), against the lossless blocks.", "",
             "| model | code size | per-voxel MSE | per-block SSE | test-split MSE | Chamfer-L1 (mm) | F@1 voxel | "
             "F@2 voxels |", "|---|---|---|---|---|---|---|---|"]
    for name, rec in results["models"].items():
        for k in (32, 64, 128):
            h, t = rec["held_out_real"][k], rec["test_split"][k]
            lines.append(f"| {name} | {k} | {h['mse_voxel']:.3e} | {h['sse_block']:.2f} | {t['mse_voxel']:.3e} | "
                         f"{h['chamfer_l1_mm']:.2f} | {h['f_score_1']:.3f} | {h['f_score_2']:.3f} |")
    n_real = results["real_windows"]
    fit_times = ", ".join(f"{n}: {r['fit_seconds']:.0f} s" for n, r in results["models"].items())
    lines += ["", f"Training: {args.synthetic} synthetic blocks and {n_real} real windows ({args.em_iterations} "
              f"refits on windows filled by the previous basis); fit times {fit_times}.", ""]
    Path(args.report + ".md").write_text("\n".join(lines))
    print(f"done in {results['seconds']:.0f} s")


if __name__ == "__main__":
    main()
