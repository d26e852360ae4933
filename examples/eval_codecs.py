"""Reconstruction error of pca, ae, parallel and sequential on held-out real and synthetic blocks, against the
paper's Table 1 findings; optionally their throughput. Writes docs/codecs.json; `make docs` renders docs/codecs.md from it
(docs/generate/page_codecs.py).

    python examples/train_ae_models.py                               # shipped ae-64, sequential-64-64
    python examples/train_ae_models.py --only '' --sizes 32,128      # ae-32 and ae-128 (not shipped)
    python examples/eval_codecs.py                                   # add --bench for the speed table

Models: the shipped eigenshapes (pca-32/64/128 are prefixes of one 128 basis), the shipped AE-64, AE-32 and
AE-128 trained by ``train_ae_models.py --sizes 32,128`` on the same data with the same settings (in
``--workdir``), the shipped parallel 64 + 64 (shipped eigenshapes + shipped AE-64) and sequential 64 + 64. The
mixtures are evaluated with per-block mixing weights and with one fixed weight for the whole map: the single w
with the least total squared error on the training data set's validation split (both), and for sequential also
w = 1 (the plain "PCA + AE residual"). A model that is not trained yet is skipped with a note in the results,
so the script runs at any stage.

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
import shlex
import sys
import time
from pathlib import Path

import numpy as np
import torch

import sdfcodec

ROOT = Path(__file__).resolve().parents[1]
TRUNC, VS = (-0.04, 0.1), 0.02

# The paper's Table 1 (the eigenshapes paper, Canelhas et al.): reconstruction error "MSE" +- the standard
# deviation among data sets, averaged over all non-empty blocks of six TUM freiburg-1 maps.
PAPER_TABLE1 = {"pca-32": (42.94, 2.63), "pca-64": (33.96, 2.01), "pca-128": (27.29, 1.87),
                "ae-32": (59.65, 2.78), "ae-64": (49.52, 2.19), "ae-128": (46.19, 2.23),
                "parallel 64+64": (33.63, 1.98), "sequential 64+64": (33.95, 2.01)}
PAPER = {k: v[0] for k, v in PAPER_TABLE1.items()}
ON_PAR = 0.05  # "on par with PCA-64": per-block SSE within 5 % of PCA-64's (the paper's are within 1 %)


def non_empty(v: np.ndarray) -> np.ndarray:
    return v[~(v >= 1 - 1e-6).reshape(len(v), -1).all(axis=1)]


def test_sets(kitchen: str, n_synth: int) -> dict[str, np.ndarray]:
    from sdfcodec.core.blocks import normalise, split_blocks
    from sdfcodec.data.sampler import sample_windows
    from sdfcodec.data.synthetic import synthetic_blocks
    from sdfcodec.data.render import room_scene
    from sdfcodec.fusion.tsdf import fuse
    from sdfcodec.core.sdf import sample_volume

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


def best_fixed_w(mix, blocks: np.ndarray) -> float:
    """The single w in [0, 1] with the least total squared error over ``blocks``: of ``w p + (1 - w) a``
    (parallel) or of ``p + w a`` (sequential, ``a`` the AE's reconstruction of the PCA residual). The error
    is quadratic in w, so the minimiser is closed-form (clipped to [0, 1])."""
    num = den = 0.0
    for i in range(0, len(blocks), 2000):
        x = torch.from_numpy(blocks[i:i + 2000])
        n = len(x)
        p = mix.pca_.decode(mix.pca_.encode(x))
        if mix.codec_id == "parallel":
            a = mix.ae_.decode(mix.ae_.encode(x)).reshape(n, -1).double()
            d, t = p.reshape(n, -1).double() - a, x.reshape(n, -1).double() - a
        else:
            r = x - p
            d, t = mix.ae_.decode(mix.ae_.encode(r)).reshape(n, -1).double(), r.reshape(n, -1).double()
        num += float((t * d).sum())
        den += float((d * d).sum())
    return float(np.clip(num / den, 0.0, 1.0))


def errors(codec, x: np.ndarray) -> tuple[dict, np.ndarray]:
    codes = np.concatenate([codec.encode(x[i:i + 4096]) for i in range(0, len(x), 4096)])
    dec = np.concatenate([codec.decode(codes[i:i + 4096]) for i in range(0, len(x), 4096)])
    sse = ((dec.astype(np.float64) - x) ** 2).reshape(len(x), -1).sum(axis=1)
    return {"blocks": len(x), "mse_voxel": float(sse.mean() / 4096), "sse_block": float(sse.mean()),
            "sse_block_std": float(sse.std())}, codes


def mixing_gain(codec, x: np.ndarray, codes: np.ndarray) -> dict:
    """What the per-block w buys over the better of its two end points (w = 0 and w = 1: one part alone for
    parallel; PCA alone and PCA + the whole AE residual for sequential), block by block."""
    def sse(c):
        dec = np.concatenate([codec.decode(c[i:i + 4096]) for i in range(0, len(c), 4096)])
        return ((dec.astype(np.float64) - x) ** 2).reshape(len(x), -1).sum(axis=1)

    ends = []
    for w in (0.0, 1.0):
        c = codes.copy()
        c[:, -1] = w
        ends.append(sse(c))
    best_end, mixed = np.minimum(*ends), sse(codes)
    return {"sse_block_best_end": float(best_end.mean()), "sse_block_mixed": float(mixed.mean()),
            "gain": float(1 - mixed.mean() / best_end.mean()),
            "blocks_gaining_5pct": float(np.mean(mixed < 0.95 * best_end))}


def load_codecs(workdir: Path, data: Path | None, val_blocks: int) -> tuple[dict, dict]:
    """The codecs to evaluate (name -> codec) and notes (why a codec is missing, how a fixed w was chosen).
    Models that are not there yet (trained on demand) are skipped with a note."""
    import sdfcodec_mixed as mixed
    from sdfcodec.errors import SDFCodecError
    from sdfcodec_ae import default_ae

    codecs, notes = {}, {}
    for k in (32, 64, 128):
        codecs[f"pca-{k}"] = sdfcodec.pretrained_codec("pca", k)
    for k in (32, 64, 128):
        if k == 64:
            codecs["ae-64"] = default_ae(64)
        elif (workdir / f"ae-{k}.npz").exists():
            codecs[f"ae-{k}"] = sdfcodec.load_model(workdir / f"ae-{k}.npz")
        else:
            where = workdir.resolve().relative_to(ROOT) if ROOT in workdir.resolve().parents else workdir
            notes[f"ae-{k}"] = (f"skipped, {where}/ae-{k}.npz is not trained yet: run "
                                f"`python examples/train_ae_models.py --only '' --sizes {k}`")
    val = None
    if data is not None and data.exists():
        from sdfcodec.core.dataset import open_dataset

        val = open_dataset(data).load("validation", val_blocks)
    for name, make in (("parallel", mixed.default_parallel), ("sequential", mixed.default_sequential)):
        try:
            per_block = make()
        except SDFCodecError as exc:
            what = "sequential-64-64" if name == "sequential" else "ae-64"
            notes[f"{name} 64+64"] = (f"skipped, the shipped {what}.npz is not trained yet "
                                      f"({type(exc).__name__}): run `python examples/train_ae_models.py --only {what}`")
            continue
        codecs[f"{name} 64+64"] = per_block
        if val is not None:
            w = round(best_fixed_w(per_block, val), 3)
            codecs[f"{name} 64+64, fixed w={w:.3f}"] = make(weight=w)
            notes[f"{name} fixed w"] = (f"w = {w:.3f}: least total squared error on {len(val)} blocks of the "
                                        f"validation split of {data.name}")
        if name == "sequential":
            codecs["sequential 64+64, fixed w=1"] = make(weight=1.0)
    if val is None:
        notes["fixed w"] = "no training data set found, so no best fixed w (pass --dataset)"
    return codecs, notes


def _check(finding: str, s: str, ok: bool, detail: str, paper: str) -> dict:
    return {"finding": finding, "set": s, "agrees": bool(ok), "ours": detail, "paper": paper}


def findings(res: dict, sets: list[str]) -> list[dict]:
    """The paper's relative findings checked on each test set (per-block SSE), with the numbers behind each."""
    out = []

    def e(name, s):
        return res[name]["sets"][s]["sse_block"] if name in res else None

    P = PAPER
    for s in sets:
        for fam, label in (("pca", "PCA"), ("ae", "AE")):
            v = [e(f"{fam}-{k}", s) for k in (32, 64, 128)]
            pv = [P[f"{fam}-{k}"] for k in (32, 64, 128)]
            if None in v:
                continue
            out.append(_check(f"{label} error falls with code size (32 > 64 > 128)", s, v[0] > v[1] > v[2],
                              " > ".join(f"{x:.2f}" for x in v), " > ".join(f"{x:.2f}" for x in pv)))
            out.append(_check(f"{label}: diminishing returns (32->64 gains more than 64->128)", s,
                              (v[0] - v[1]) > (v[1] - v[2]), f"gains {v[0] - v[1]:.2f}, {v[1] - v[2]:.2f}",
                              f"gains {pv[0] - pv[1]:.2f}, {pv[1] - pv[2]:.2f}"))
        pairs = [(k, e(f"pca-{k}", s), e(f"ae-{k}", s)) for k in (32, 64, 128) if e(f"ae-{k}", s) is not None]
        sizes = "/".join(str(k) for k, _, _ in pairs)
        out.append(_check(f"PCA beats AE at every size (AE/PCA SSE at {sizes})", s, all(p < a for _, p, a in pairs),
                          ", ".join(f"{a / p:.2f}" for _, p, a in pairs),
                          ", ".join(f"{P[f'ae-{k}'] / P[f'pca-{k}']:.2f}" for k, _, _ in pairs)))
        for mix in ("parallel 64+64", "sequential 64+64"):
            if e(mix, s) is None:
                continue
            r = e(mix, s) / e("pca-64", s)
            out.append(_check(f"{mix} (per-block w) on par with PCA-64 (SSE ratio within {ON_PAR:.0%})", s,
                              abs(r - 1) <= ON_PAR, f"{r:.3f}", f"{P[mix] / P['pca-64']:.3f}"))
        w = res.get("parallel 64+64", {}).get("weights", {}).get(s)
        if w:
            out.append(_check("parallel: w mostly 0 or 1, i.e. one part or the other (over half the blocks), "
                              "most often PCA (w = 1)", s, w["at_0"] + w["at_1"] > 0.5 and w["at_1"] > w["at_0"],
                              f"w=1 {w['at_1']:.0%}, w=0 {w['at_0']:.0%}, between {w['between']:.0%}",
                              "mostly either/or, most often PCA"))
        for mix in ("parallel 64+64", "sequential 64+64"):
            w = res.get(mix, {}).get("weights", {}).get(s)
            if w:
                out.append(_check(f"{mix}: mixing rarely pays (under half the blocks gain > 5 % over the better "
                                  "of w = 0 and w = 1)", s, w["blocks_gaining_5pct"] < 0.5,
                                  f"{w['blocks_gaining_5pct']:.0%} of blocks gain, SSE {-w['gain']:+.1%}",
                                  "mixing is rarely advantageous"))
        w = res.get("sequential 64+64", {}).get("weights", {}).get(s)
        if w:
            out.append(_check("sequential: w mostly 0 or near 0 (<= 0.05, over half the blocks)", s,
                              w["near_0"] > 0.5, f"w<=0.05 {w['near_0']:.0%} (w=0 {w['at_0']:.0%}), "
                              f"median {w['median']:.2f}", "mostly w = 0 or near 0"))
    return out


def bench(batches: list[int]) -> list[dict]:
    from sdfcodec.bench import bench_codec

    recs = bench_codec("pca", [64], batches)
    for cid in ("ae", "parallel", "sequential"):
        recs += bench_codec(cid, [64], batches)
    return recs


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--kitchen", default=os.environ.get("SDFCODEC_KITCHEN", "7scenes-redkitchen"),
                    help="a 7-Scenes redkitchen sequence folder (colour and depth frames, poses, gravity); default: $SDFCODEC_KITCHEN, else ./7scenes-redkitchen")
    ap.add_argument("--workdir", default=str(ROOT / "build" / "ae-models"))
    ap.add_argument("--dataset", default=None, help="training data set, for the best fixed w (default: "
                    "WORKDIR/synthetic-real.zarr, else build/default-model/synthetic-real.zarr)")
    ap.add_argument("--val-blocks", type=int, default=11500,
                    help="validation blocks used to choose the fixed w (default: the whole split)")
    ap.add_argument("--synthetic", type=int, default=5000)
    ap.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's)")
    ap.add_argument("--bench", action="store_true", help="also measure encode/decode throughput")
    ap.add_argument("--bench-batches", default="1,64,4096", help="batch sizes of --bench")
    ap.add_argument("--out", default=str(ROOT / "docs"),
                    help="directory for codecs.json (default: docs/)")
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    workdir = Path(args.workdir)
    data = Path(args.dataset) if args.dataset else next(
        (p for p in (workdir / "synthetic-real.zarr", ROOT / "build" / "default-model" / "synthetic-real.zarr")
         if p.exists()), None)
    t0 = time.perf_counter()
    load_before = os.getloadavg()
    sets = test_sets(args.kitchen, args.synthetic)
    codecs, notes = load_codecs(workdir, data, args.val_blocks)
    cmd = " ".join(["python examples/eval_codecs.py"] + [shlex.quote(a) for a in sys.argv[1:]])
    results: dict = {"command": cmd, "units": "normalised (distance / 0.14 m)",
                     "test_sets": {k: len(v) for k, v in sets.items()}, "paper_table1_sse": PAPER,
                     "paper_table1_sse_std": {k: v[1] for k, v in PAPER_TABLE1.items()}, "on_par_tolerance": ON_PAR,
                     "notes": notes, "load_before": load_before, "torch_threads": torch.get_num_threads(),
                     "codecs": {}}
    for name, codec in codecs.items():
        rec = {"config": codec.get_config(), "code_size": codec.code_size, "sets": {}, "weights": {}}
        for s, x in sets.items():
            rec["sets"][s], codes = errors(codec, x)
            if getattr(codec, "per_block", False):
                import sdfcodec_mixed as mixed

                rec["weights"][s] = {**mixed.weight_stats(codes), **mixing_gain(codec, x, codes)}
        results["codecs"][name] = rec
        print(name, {s: round(v["sse_block"], 2) for s, v in rec["sets"].items()}, flush=True)
    results["findings"] = findings(results["codecs"], list(sets))
    training = ROOT / "docs" / "codecs" / "training.json"
    if training.exists():
        results["training"] = json.loads(training.read_text())
    if args.bench:
        results["bench"] = {"load_before": os.getloadavg(), "torch_threads": torch.get_num_threads(),
                            "records": bench([int(b) for b in args.bench_batches.split(",")])}
        results["bench"]["load_after"] = os.getloadavg()
    results["load_after"] = os.getloadavg()
    results["seconds"] = time.perf_counter() - t0
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "codecs.json").write_text(json.dumps(results, indent=1))
    for k, v in notes.items():
        print(f"note: {k}: {v}")
    print(f"wrote {out / 'codecs.json'} in {results['seconds']:.0f} s; `make docs` renders docs/codecs.md from it")


if __name__ == "__main__":
    main()
