"""Reconstruction error of pca, ae, parallel and sequential on held-out real and synthetic blocks, against the
paper's Table 1 findings; optionally their throughput. Writes docs/codecs.json and docs/codecs.md.

    python examples/train_ae_models.py --only "" --sizes 32,128    # ae-32 and ae-128 (not shipped)
    python examples/eval_codecs.py                                   # add --bench for the speed table

Models: the shipped eigenshapes (pca-32/64/128 are prefixes of one 128 basis), the shipped AE-64, AE-32 and
AE-128 trained by ``train_ae_models.py --sizes 32,128`` on the same data with the same settings, the shipped
parallel 64 + 64 (shipped eigenshapes + shipped AE-64) and sequential 64 + 64; per-block mixing weights, and a
fixed weight for the whole map (parallel: the single w with the least squared error on the training data
set's validation split; sequential: w = 1, the plain "PCA + residual").

Test sets (none seen in training):

``real blocks``
    The allocated non-empty 16^3 blocks of the second half (along x) of 7-Scenes redkitchen fused at 2 cm:
    the held-out spatial split of ``examples/train_default_model.py`` (training used windows of the first
    half only, with a one-block gap).
``real windows``
    Sub-volumes of that held-out half taken like the training data (every 8 voxels, windows with a
    normalised mean above 0.85 dropped), without the axis permutations.
``synthetic blocks``
    5,000 fresh synthetic primitive blocks (a seed the training data never used).
``synthetic map``
    The non-empty blocks of an exact furnished room (``sdfcodec.data.render.room_scene(seed=0,
    geometry="rich", ceiling=True)``) sampled at 2 cm.

Errors are in normalised units (distance / 0.14 m): per-voxel MSE, and per-block sum of squared errors (SSE,
the mean over blocks of the sum over the block's 4096 voxels), which is the scale of the paper's Table 1
numbers (e.g. 33.96 for PCA 64).
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np
import torch

import sdfcodec
from sdfcodec.models import default_codec

ROOT = Path(__file__).resolve().parents[1]
TRUNC, VS = (-0.04, 0.1), 0.02

# The paper's Table 1 (average reconstruction error over all non-empty blocks of six TUM freiburg-1 maps).
PAPER = {"pca-32": 42.94, "pca-64": 33.96, "pca-128": 27.29, "ae-32": 59.65, "ae-64": 49.52, "ae-128": 46.19,
         "parallel 64+64": 33.63, "sequential 64+64": 33.95}


def non_empty(v: np.ndarray) -> np.ndarray:
    return v[~(v >= 1 - 1e-6).reshape(len(v), -1).all(axis=1)]


def test_sets(kitchen: str, n_synth: int) -> dict[str, np.ndarray]:
    from sdfcodec.blocks import normalise, split_blocks
    from sdfcodec.data.sampler import sample_windows
    from sdfcodec.data.synthetic import synthetic_blocks
    from sdfcodec.data.render import room_scene
    from sdfcodec.fusion import fuse
    from sdfcodec.sdf import sample_volume

    sets = {}
    if Path(kitchen).is_dir():
        fused = fuse(kitchen, voxel_size=VS, truncation=TRUNC)
        held = fused.select(fused.coords[:, 0] > fused.grid_shape[0] // 2)  # as train_default_model.py
        sets["real blocks"] = non_empty(held.normalised())
        sets["real windows"] = sample_windows(held.to_dense(), stride=8, truncation=TRUNC, permute=False, seed=0)
    else:
        print(f"no real data at {kitchen}: real test sets skipped")
    sets["synthetic blocks"] = synthetic_blocks(n_synth, seed=1_000_003, voxel_size=VS, truncation=TRUNC)
    # a furnished room (floor, walls, ceiling, 10 pieces of furniture), with a margin around its slabs
    room, margin = room_scene(seed=0, geometry="rich", ceiling=True), 0.16
    shape = tuple(int(round((s + 2 * margin) / VS)) for s in (4.0, 3.2, 2.5))
    vol = sample_volume(room.sdf, shape, VS, origin=(-margin,) * 3, truncation=TRUNC)
    sets["synthetic map"] = non_empty(normalise(split_blocks(vol, fill=TRUNC[1]).reshape(-1, 16, 16, 16), *TRUNC))
    return {k: np.ascontiguousarray(v, dtype=np.float32) for k, v in sets.items()}


def best_fixed_parallel_w(par, blocks: np.ndarray) -> float:
    """The single w in [0, 1] with the least total squared error of w p + (1 - w) a over ``blocks``."""
    num = den = 0.0
    for i in range(0, len(blocks), 2000):
        x = torch.from_numpy(blocks[i:i + 2000])
        p = par.pca_.decode(par.pca_.encode(x)).reshape(len(x), -1).double()
        a = par.ae_.decode(par.ae_.encode(x)).reshape(len(x), -1).double()
        d = p - a
        num += float(((x.reshape(len(x), -1).double() - a) * d).sum())
        den += float((d * d).sum())
    return float(np.clip(num / den, 0.0, 1.0))


def errors(codec, x: np.ndarray) -> tuple[dict, np.ndarray]:
    codes = np.concatenate([codec.encode(x[i:i + 4096]) for i in range(0, len(x), 4096)])
    dec = np.concatenate([codec.decode(codes[i:i + 4096]) for i in range(0, len(x), 4096)])
    sse = ((dec.astype(np.float64) - x) ** 2).reshape(len(x), -1).sum(axis=1)
    return {"blocks": len(x), "mse_voxel": float(sse.mean() / 4096), "sse_block": float(sse.mean()),
            "sse_block_std": float(sse.std())}, codes


def load_codecs(workdir: Path, data: Path | None) -> tuple[dict, dict]:
    import sdfcodec_mixed as mixed
    from sdfcodec_ae import default_ae

    codecs, notes = {}, {}
    for k in (32, 64, 128):
        codecs[f"pca-{k}"] = default_codec("pca", k)
    for k in (32, 64, 128):
        if k == 64:
            codecs["ae-64"] = default_ae(64)
        elif (workdir / f"ae-{k}.npz").exists():
            codecs[f"ae-{k}"] = sdfcodec.load_model(workdir / f"ae-{k}.npz")
        else:
            notes[f"ae-{k}"] = f"not trained: run examples/train_ae_models.py --only '' --sizes {k}"
    codecs["parallel 64+64"] = mixed.default_parallel()
    codecs["sequential 64+64"] = mixed.default_sequential()
    if data is not None and data.exists():
        from sdfcodec.dataset import open_dataset

        w = best_fixed_parallel_w(codecs["parallel 64+64"], open_dataset(data).load("validation"))
        codecs[f"parallel 64+64, fixed w={w:.3f}"] = mixed.default_parallel(weight=round(w, 3))
        notes["parallel fixed w"] = f"w = {w:.4f}: least squared error on the validation split of {data.name}"
    codecs["sequential 64+64, fixed w=1"] = mixed.default_sequential(weight=1.0)
    return codecs, notes


def findings(res: dict, sets: list[str]) -> list[dict]:
    """The paper's relative findings, checked on each test set (per-block SSE)."""
    out = []

    def e(name, s):
        return res[name]["sets"][s]["sse_block"] if name in res else None

    for s in sets:
        pca = [e(f"pca-{k}", s) for k in (32, 64, 128)]
        ae = [e(f"ae-{k}", s) for k in (32, 64, 128)]
        rows = {
            "PCA error falls with code size": pca[0] > pca[1] > pca[2],
            "PCA: diminishing returns (32->64 gains more than 64->128)": (pca[0] - pca[1]) > (pca[1] - pca[2]),
        }
        if None not in ae:
            rows["AE error falls with code size"] = ae[0] > ae[1] > ae[2]
            rows["AE: diminishing returns"] = (ae[0] - ae[1]) > (ae[1] - ae[2])
            rows["PCA beats AE at every size"] = all(p < a for p, a in zip(pca, ae))
        else:
            rows["PCA beats AE at 64"] = pca[1] < ae[1]
        for mix in ("parallel 64+64", "sequential 64+64"):
            r = e(mix, s) / pca[1]
            rows[f"{mix} on par with PCA-64 (within 5 %): ratio {r:.3f}"] = abs(r - 1) <= 0.05
        out.append({"set": s, "checks": rows})
    return out


def bench(batches: list[int]) -> list[dict]:
    from sdfcodec.bench import bench_codec
    from sdfcodec_ae import bench_records

    recs = bench_codec("pca", [64], batches)
    for cid in ("ae", "parallel", "sequential"):
        recs += bench_records(cid, 64, batches)
    return recs


DISCUSSION = """
## How the codecs are built (design notes)

- **ae** (`plugins/sdfcodec_ae`): `4096-512-d-512-4096`, sigmoid everywhere (the code layer too, so codes
  lie in (0, 1)); state = the four layers' weights and biases as plain arrays. Training
  (`sdfcodec_ae.train.TrainConfig`): `optimizer="adam"` (default: mini-batches of 100, lr 1e-3) or
  `"gd"` (the paper's batch gradient descent: one step per epoch on the full-batch gradient, momentum
  0.9); early stopping when the validation MSE has not improved by 0.2 % for `patience` epochs (4 for
  adam), keeping the best epoch's weights. Inputs are standardised during training (mean block, global
  std) and the standardisation is folded into the first layer afterwards, so the stored network is the
  paper's plain one. Checkpoints are `.npz` of plain arrays (weights, best weights, Adam moments) plus
  JSON; a resumed run ends bit-identical to an uninterrupted one.
- **parallel / sequential** (`plugins/sdfcodec_mixed`): code `[pca 64 | ae 64 | w]` = 129 floats with a
  per-block `w` (the last element), or 128 with one fixed `w` stored in the codec configuration (map
  header). The per-block `w` minimises the block's squared error over [0, 1]; the error is quadratic in
  `w`, so this "line search" is exact and closed-form (clip of the unconstrained minimiser). The PCA part
  is the shipped eigenshapes (first 64 of `pca-128.npz`); the state of a mixture holds both parts' arrays
  (`pca.*`, `ae.*`) so maps stay self-contained. Neither is prefix-ordered.
- **Shipped weights**: `sdfcodec/models/ae-64.npz` and `sequential-64-64.npz` (AE weights float16, PCA
  float32), made by `python examples/train_ae_models.py`; the parallel 64 + 64 pairs the shipped
  eigenshapes with the shipped AE-64 and needs no file. AE-32 and AE-128 are trained on demand
  (`sdfcodec train DATASET --codec ae --code-size 32 -o MODEL`, or the script's `--sizes`).

## Differences from the paper's setup (why numbers need not match)

- Test data: the paper averages six TUM freiburg-1 maps fused from real Kinect sequences; we have one
  real sequence (7-Scenes redkitchen, 500 frames), of which the held-out half gives only a few hundred
  non-empty blocks, plus the held-out windows and synthetic sets. Absolute SSE depends on the maps'
  noise and on how many near-empty blocks they have, so compare ratios (second table), not raw values.
- Training data: 68,500 training blocks (60,000 synthetic + 31,529 real windows, split 300:50:50)
  against the paper's 150,000 of 200,000 (synthetic + industrial and office reconstructions).
- AE optimiser: the paper used pylearn2's batch gradient descent; our shipped AEs use mini-batch Adam
  (the time budget on 2 shared CPU cores rules out full-batch gradient descent to convergence: one step
  per pass over 68,500 blocks). `training={"optimizer": "gd"}` runs the paper's setting.
- PCA: the shipped eigenshapes keep the data-set mean in the model (all k slots are components); the
  paper's text stores a mean slot (k - 1 components). See docs/pca-choices.json.
- Mixing weight: the paper's approximate line search vs our exact minimiser; our per-block `w` costs one
  extra float per block (129 floats instead of 128).
"""


def _f(v: float) -> str:
    return f"{v:.2f}"


def markdown(res: dict) -> str:
    """docs/codecs.md from the results (every number in it comes from docs/codecs.json)."""
    sets = list(res["test_sets"])
    L = ["# Codecs: reconstruction error and speed", "",
         f"Made by `{res['command']}` (after `python examples/train_ae_models.py` and "
         "`python examples/train_ae_models.py --only '' --sizes 32,128`); numbers in `docs/codecs.json`. Errors "
         "are in normalised units (distance / 0.14 m). **SSE/block** is the mean over blocks of the sum of squared "
         "errors over the block's 4096 voxels, the scale of the paper's Table 1; **MSE/voxel** = SSE/block / 4096.",
         "", "Test sets (none seen in training): " + "; ".join(f"{k}: {n} blocks" for k, n in res["test_sets"].items())
         + ". See the docstring of `examples/eval_codecs.py` for how each is made.", "",
         "## Per-block SSE (MSE/voxel in parentheses)", "",
         "| codec | code | " + " | ".join(sets) + " | paper Table 1 |", "|---|---|" + "---|" * (len(sets) + 1)]
    for name, rec in res["codecs"].items():
        cells = [f"{_f(rec['sets'][s]['sse_block'])} ({rec['sets'][s]['mse_voxel']:.2e})" for s in sets]
        L.append(f"| {name} | {rec['code_size']} | " + " | ".join(cells) + f" | {PAPER.get(name, '')} |")
    L += ["", "Relative to PCA-64 on each set (the paper's ratios in the last column):", "",
          "| codec | " + " | ".join(sets) + " | paper |", "|---|" + "---|" * (len(sets) + 1)]
    for name, rec in res["codecs"].items():
        ratios = [rec["sets"][s]["sse_block"] / res["codecs"]["pca-64"]["sets"][s]["sse_block"] for s in sets]
        paper = f"{PAPER[name] / PAPER['pca-64']:.3f}" if name in PAPER else ""
        L.append(f"| {name} | " + " | ".join(f"{r:.3f}" for r in ratios) + f" | {paper} |")
    L += ["", "## The paper's findings, checked", "", "| finding | " + " | ".join(sets) + " |",
          "|---|" + "---|" * len(sets)]
    keys: list[str] = []
    for f in res["findings"]:
        for k in f["checks"]:
            base = k.split(": ratio")[0]
            if base not in keys:
                keys.append(base)
    for k in keys:
        cells = []
        for f in res["findings"]:
            hit = [(kk, v) for kk, v in f["checks"].items() if kk.split(": ratio")[0] == k]
            if not hit:
                cells.append("")
                continue
            kk, v = hit[0]
            extra = kk.split(": ratio")[1].strip() if ": ratio" in kk else ""
            cells.append(("agrees" if v else "**differs**") + (f" ({extra})" if extra else ""))
        L.append(f"| {k} | " + " | ".join(cells) + " |")
    L += ["", "## Mixing weights (per-block w)", "",
          "The paper: parallel mostly picks one part (most often PCA); sequential mostly w = 0 or near 0.", "",
          "| codec | set | w = 0 | w = 1 | in between | w <= 0.05 | w >= 0.95 | median w |", "|---|---|---|---|---|---|---|---|"]
    for name, rec in res["codecs"].items():
        for s, w in rec.get("weights", {}).items():
            L.append(f"| {name} | {s} | {w['at_0']:.1%} | {w['at_1']:.1%} | {w['between']:.1%} | {w['near_0']:.1%} "
                     f"| {w['near_1']:.1%} | {w['median']:.3f} |")
    if res.get("notes"):
        L += ["", "Notes: " + "; ".join(f"{k}: {v}" for k, v in res["notes"].items()) + "."]
    tr = res.get("training", {}).get("models", {})
    if tr:
        L += ["", "## Training", "", "| model | blocks (train / val) | epochs (best) | stopped | wall time | load "
              "before -> after | val MSE/voxel | test MSE/voxel (float16 weights) | file |", "|---|---|---|---|---|---|---|---|---|"]
        for name, r in tr.items():
            L.append(f"| {name} | {r['n_train']} / {r['n_val']} | {r['epochs']} ({r['best_epoch']}) | {r['stopped']} | "
                     f"{r['training_seconds_all_runs'] / 60:.1f} min | {r['load_before']} -> {r['load_after']} | "
                     f"{r['best_val_mse']:.3e} | {r['test_float16']['mse_voxel']:.3e} | "
                     f"{r['file']} ({r['bytes'] / 1e6:.1f} MB) |")
        m = res["training"].get("machine", {})
        L += ["", f"Machine: {m.get('cpus')} CPUs ({m.get('processor')}), torch {m.get('torch')}, "
              f"{m.get('threads')} torch thread(s) for training. Load averages are `os.getloadavg()` (1, 5, 15 min) "
              "when each run started and ended: other jobs shared the cores.",
              "Learning curves: `docs/codecs/<model>.curves.png` and `.json`."]
    if "bench" in res:
        b = res["bench"]
        L += ["", "## Throughput (CPU)", "", f"torch threads {b['torch_threads']}, load "
              f"{' '.join(f'{v:.2f}' for v in b['load_before'])} before, "
              f"{' '.join(f'{v:.2f}' for v in b['load_after'])} after. Baseline: numpy matrix products of the codec's "
              "layer shapes in the same run (pca: its one product).", "",
              "| codec | op | batch | blocks/s | roofline blocks/s | ratio | us/block |", "|---|---|---|---|---|---|---|"]
        for r in b["records"]:
            L.append(f"| {r['codec']}-{r['code_size']} | {r['operation']} | {r['batch']} | {r['blocks_per_s']:,.0f} | "
                     f"{r['baseline_blocks_per_s']:,.0f} | {r['ratio_to_baseline']:.2f} | {r['us_per_block']:.1f} |")
    return "\n".join(L) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--kitchen", default=str(ROOT.parent / "shared" / "data" / "7scenes-redkitchen"))
    ap.add_argument("--workdir", default=str(ROOT / "build" / "ae-models"))
    ap.add_argument("--dataset", default=None, help="training data set, for the fixed parallel w (default: "
                    "WORKDIR/synthetic-real.zarr, else build/default-model/synthetic-real.zarr)")
    ap.add_argument("--synthetic", type=int, default=5000)
    ap.add_argument("--out", default=str(ROOT / "docs" / "codecs"))
    ap.add_argument("--bench", action="store_true", help="also measure encode/decode throughput")
    ap.add_argument("--bench-batches", default="1,64,4096,16384")
    args = ap.parse_args()
    workdir = Path(args.workdir)
    data = Path(args.dataset) if args.dataset else next(
        (p for p in (workdir / "synthetic-real.zarr", ROOT / "build" / "default-model" / "synthetic-real.zarr")
         if p.exists()), None)
    t0 = time.perf_counter()
    sets = test_sets(args.kitchen, args.synthetic)
    codecs, notes = load_codecs(workdir, data)
    results: dict = {"command": "python examples/eval_codecs.py" + (" --bench" if args.bench else ""),
                     "units": "normalised (distance / 0.14 m)", "test_sets": {k: len(v) for k, v in sets.items()},
                     "paper_table1_sse": PAPER, "notes": notes, "codecs": {}}
    for name, codec in codecs.items():
        rec = {"config": codec.get_config(), "code_size": codec.code_size, "sets": {}, "weights": {}}
        for s, x in sets.items():
            rec["sets"][s], codes = errors(codec, x)
            if getattr(codec, "per_block", False):
                import sdfcodec_mixed as mixed

                rec["weights"][s] = mixed.weight_stats(codes)
        results["codecs"][name] = rec
        print(name, {s: round(v["sse_block"], 2) for s, v in rec["sets"].items()}, flush=True)
    names = list(sets)
    results["findings"] = findings(results["codecs"], names)
    training = ROOT / "docs" / "codecs" / "training.json"
    if training.exists():
        results["training"] = json.loads(training.read_text())
    if args.bench:
        results["bench"] = {"load_before": os.getloadavg(), "records": bench([int(b) for b in args.bench_batches.split(",")]),
                            "torch_threads": torch.get_num_threads()}
        results["bench"]["load_after"] = os.getloadavg()
    results["seconds"] = time.perf_counter() - t0
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (ROOT / "docs" / "codecs.json").write_text(json.dumps(results, indent=1))
    (ROOT / "docs" / "codecs.md").write_text(markdown(results) + DISCUSSION)
    print(f"wrote docs/codecs.json and docs/codecs.md in {results['seconds']:.0f} s")


if __name__ == "__main__":
    main()
