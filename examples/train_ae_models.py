"""Train the shipped autoencoder models: ``plugins/sdfcodec_ae/models/ae-64.npz`` and
``plugins/sdfcodec_mixed/models/sequential-64-64.npz`` (each plugin ships its weights in its own package).

    python examples/train_ae_models.py            # add --threads 2 on an idle machine

Reproducible: fixed seeds, nothing downloaded. Steps:

1. The training data set is the one the shipped eigenshapes were fitted on (``examples/train_default_model.py``):
   60,000 synthetic primitive blocks plus sub-volumes (every 4 voxels, six axis orders) of the first half along
   x of 7-Scenes redkitchen fused at 2 cm, shuffled and split 300:50:50 by batches of 500 (68,500 train /
   11,500 validation / 11,500 test blocks). It is rebuilt here with the same settings unless ``--dataset``
   names an existing copy (e.g. ``build/default-model/synthetic-real.zarr``).
2. AE-64 (``4096-512-64-512-4096``, sigmoid) is trained with the codec's default settings (mini-batch Adam,
   early stopping on the validation split) exactly as ``sdfcodec train DATASET --codec ae --code-size 64``
   would, then stored with float16 weights (half the bytes; the evaluation uses the rounded weights).
3. The sequential 64 + 64: the shipped eigenshapes' first 64 components, and a tanh AE-64 trained on their
   residuals with the same settings. The parallel 64 + 64 needs no file of its own: it pairs the shipped
   eigenshapes with the shipped AE-64 (``sdfcodec_mixed.default_parallel``).

Checkpoints go to ``--workdir``; an interrupted run continues where it stopped when started again. Learning
curves: ``docs/codecs/<model>.curves.{json,png}``; timings and machine load: ``docs/codecs/training.json``.
``--sizes 32,128`` trains those AE sizes too (into ``--workdir``, for the evaluation), not shipped.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

import numpy as np
import torch

import sdfcodec
from sdfcodec.core.dataset import build_dataset, open_dataset

ROOT = Path(__file__).resolve().parents[1]
TRUNC, VS = (-0.04, 0.1), 0.02


def load() -> str:
    """The 1/5/15-minute load averages (other work on the machine slows training down)."""
    return " ".join(f"{v:.2f}" for v in os.getloadavg())


def build_training_set(path: Path, kitchen: str, synthetic: int = 60_000, real_stride: int = 4):
    """The data set of examples/train_default_model.py ("synthetic + real"), same sources, seeds and split."""
    from sdfcodec.data.sampler import iter_windows
    from sdfcodec.data.synthetic import synthetic_blocks
    from sdfcodec.fusion.tsdf import fuse

    fused = fuse(kitchen, voxel_size=VS, truncation=TRUNC)
    train_half = fused.select(fused.coords[:, 0] < fused.grid_shape[0] // 2)

    def synth():
        for i in range(0, synthetic, 10_000):
            yield synthetic_blocks(min(10_000, synthetic - i), seed=i, voxel_size=VS, truncation=TRUNC)

    real = list(iter_windows(train_half.to_dense(), stride=real_stride, truncation=TRUNC, seed=0))
    return build_dataset(path, [("synthetic", synth()), ("kitchen-train-half", real)], voxel_size=VS,
                         truncation=TRUNC, overwrite=True)


SHIPPED = {"ae-64": "sdfcodec_ae", "sequential-64-64": "sdfcodec_mixed"}  # shipped model -> its plugin


def round_to_float16(codec):
    """Load the float16-rounded weights, so what is evaluated is what is shipped (PCA arrays stay float32)."""
    state = {k: (v.astype(np.float16).astype(np.float32) if not k.startswith("pca.") else v)
             for k, v in codec.state_dict().items()}
    return codec.load_state_dict(state)


def split_error(codec, ds, split: str) -> dict:
    sq, n = 0.0, 0
    for b in ds.iter_batches(split):
        sq += float(((codec.decode(codec.encode(b)) - b) ** 2).sum(dtype=np.float64))
        n += len(b)
    return {"blocks": n, "mse_voxel": sq / (n * 4096), "sse_block": sq / n}


def main() -> None:
    from sdfcodec_ae import save_model_float16

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--dataset", default=None, help="existing data set (default: build it in --workdir)")
    ap.add_argument("--kitchen", default=os.environ.get("SDFCODEC_KITCHEN", "7scenes-redkitchen"),
                    help="a 7-Scenes redkitchen sequence folder (colour and depth frames, poses, gravity); default: $SDFCODEC_KITCHEN, else ./7scenes-redkitchen")
    ap.add_argument("--workdir", default=str(ROOT / "build" / "ae-models"))
    ap.add_argument("--models", default=None,
                    help="directory for the shipped models (default: each plugin's own models/ directory)")
    ap.add_argument("--report", default=str(ROOT / "docs" / "codecs"))
    ap.add_argument("--threads", type=int, default=1,
                    help="torch threads while training (1 is fastest when other work shares the cores)")
    ap.add_argument("--only", default="ae-64,sequential-64-64", help="which shipped models to (re)train")
    ap.add_argument("--max-epochs", type=int, default=None,
                    help="cap the epochs (default: the codec's 200, i.e. early stopping decides); a capped run "
                         "resumed with the epochs already done exports its best weights without training")
    ap.add_argument("--sizes", default="", help="extra AE code sizes to train into --workdir (e.g. 32,128)")
    args = ap.parse_args()
    work, report = Path(args.workdir), Path(args.report)
    shipped_dirs = {name: Path(args.models) if args.models else ROOT / "plugins" / pkg / "models"
                    for name, pkg in SHIPPED.items()}
    work.mkdir(parents=True, exist_ok=True)
    report.mkdir(parents=True, exist_ok=True)

    if args.dataset:
        ds = open_dataset(args.dataset)
    elif (work / "synthetic-real.zarr").exists():
        ds = open_dataset(work / "synthetic-real.zarr")
    else:
        t0 = time.perf_counter()
        ds = build_training_set(work / "synthetic-real.zarr", args.kitchen)
        print(f"built data set in {time.perf_counter() - t0:.0f} s: {ds.meta['splits']}")
    log_path = report / "training.json"
    log = json.loads(log_path.read_text()) if log_path.exists() else {}
    log["machine"] = {"cpus": os.cpu_count(), "processor": platform.processor() or platform.machine(),
                      "torch": torch.__version__, "threads": args.threads}
    log["dataset"] = {"path": str(Path(ds.path).relative_to(ROOT)) if ROOT in Path(ds.path).parents else ds.path,
                      "splits": ds.meta["splits"], "sources": ds.meta["sources"]}
    log.setdefault("models", {})

    jobs = [j for j in args.only.split(",") if j] + [f"ae-{k}" for k in args.sizes.split(",") if k]
    for name in jobs:
        if name.startswith("ae-"):
            codec = sdfcodec.get_codec("ae", code_size=int(name[3:]))
        elif name == "sequential-64-64":
            codec = sdfcodec.get_codec("sequential", pca_size=64, ae_size=64)
        else:
            raise SystemExit(f"unknown model {name!r}")
        shipped = name in SHIPPED
        print(f"{name}: training on {ds.meta['splits']['train']} blocks (load {load()})", flush=True)
        before = load()
        t0 = time.perf_counter()
        codec.fit_dataset(ds, checkpoint=work / f"{name}.ckpt", resume=True, report=report / name,
                          threads=args.threads,
                          **({"max_epochs": args.max_epochs} if args.max_epochs else {}))
        wall = time.perf_counter() - t0
        h = codec.history_
        out = (shipped_dirs[name] if shipped else work) / f"{name}.npz"
        out.parent.mkdir(parents=True, exist_ok=True)
        round_to_float16(codec)
        save_model_float16(codec, out, keep_float32=("pca.",))
        rec = {"file": str(out.relative_to(ROOT)) if ROOT in out.parents else str(out),
               "bytes": out.stat().st_size, "wall_seconds_this_run": wall,
               "training_seconds_all_runs": h["seconds"], "epochs": len(h["history"]),
               "best_epoch": h["best_epoch"], "stopped": h["stopped"], "best_val_mse": h["best_val_mse"],
               "n_train": h["n_train"], "n_val": h["n_val"], "config": h["config"],
               "load_before": before, "load_after": load(),
               "validation_float16": split_error(codec, ds, "validation"), "test_float16": split_error(codec, ds, "test")}
        if log_path.exists():  # other runs (other --sizes) may have written it meanwhile
            log["models"] = {**json.loads(log_path.read_text()).get("models", {}), **log["models"]}
        log["models"][name] = rec
        log_path.write_text(json.dumps(log, indent=1))
        print(f"{name}: {rec['epochs']} epochs ({rec['stopped']}, best {rec['best_epoch']}) in "
              f"{rec['training_seconds_all_runs'] / 60:.1f} min; val MSE {rec['best_val_mse']:.3e}; "
              f"wrote {out} ({rec['bytes'] / 1e6:.1f} MB); load {before} -> {rec['load_after']}", flush=True)


if __name__ == "__main__":
    main()
