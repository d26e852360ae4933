"""Surfaces and tracking on a compressed real map: the table of docs/surface.md ("Results").

    python examples/surface_study.py --kitchen 7scenes-redkitchen --out build/surface-study

Fuses the posed depth frames into a lossless map with fusion weights (as `sdfcodec fuse` does), then writes it
with the shipped PCA basis at 64 and 128 components two ways: **plain** (every voxel fitted alike, unobserved
voxels as if they were free space and left as the codec decodes them: what sdfcodec did before the
observation mask) and **surface-true** (the default of `sdfcodec encode MAP OUT --codec pca`: observation
mask, surface-weighted least squares). For each map: bytes on disk per coded block, the surface metrics
against the lossless map (sdfcodec.core.surface.compare_maps) and, with --track, the tracking ATE of the frames
against it from the first ground-truth pose (sdfcodec track's defaults). Then the same surface metrics for
surface-true pca-32/64/128 on the **held-out half** alone: the blocks past the middle of the map along x, which
the shipped basis never saw in training (examples/train_default_model.py trains on the other half), each half
written as its own map. Writes OUT/surface-study.json and prints two markdown tables.
"""

from __future__ import annotations

import argparse
import os
import json
import time
from pathlib import Path

import numpy as np

import sdfcodec
import sdfcodec.map.observed
from sdfcodec.evaluation.tracking import track_command
from sdfcodec.fusion.tsdf import fuse
from sdfcodec.core.surface import compare_maps

ROOT = Path(__file__).resolve().parents[1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--kitchen", default=os.environ.get("SDFCODEC_KITCHEN", "7scenes-redkitchen"),
                    help="a 7-Scenes redkitchen sequence folder (colour and depth frames, poses, gravity); default: $SDFCODEC_KITCHEN, else ./7scenes-redkitchen")
    ap.add_argument("--out", default=str(ROOT / "build" / "surface-study"))
    ap.add_argument("--track", action="store_true", help="also track every frame against each map (~1 min each)")
    args = ap.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    fused = fuse(args.kitchen, voxel_size=0.02, truncation=(-0.04, 0.1), quiet=True)
    raw_path = out / "lossless.sdfz"
    with sdfcodec.create_map(raw_path, codec=sdfcodec.get_codec("raw"), voxel_size=0.02, truncation=(-0.04, 0.1),
                             origin=tuple(fused.origin), overwrite=True) as m:
        m.write_blocks(fused.coords, fused.tsdf, weights=fused.weights)
    raw = sdfcodec.open_map(raw_path)
    rows = {}
    names = [("lossless", None, None)] + [(f"pca-{k} {mode}", k, mode) for k in (64, 128)
                                         for mode in ("plain", "surface-true")]
    for name, k, mode in names:
        path, t_enc = raw_path, time.perf_counter()
        if k is not None:
            path = out / f"pca-{k}-{mode}.sdfz"
            with sdfcodec.create_map(path, codec=sdfcodec.pretrained_codec("pca", k), voxel_size=raw.voxel_size,
                                     truncation=raw.truncation, origin=raw.origin, shape_voxels=raw.shape_voxels,
                                     overwrite=True, surface_weight=0.0 if mode == "plain" else
                                     sdfcodec.map.observed.SURFACE_WEIGHT) as m:
                if mode == "plain":
                    m.mark_empty(np.argwhere(raw.block_states() == 1))  # the same empties, no observation
                    for coords, blocks in raw.iter_blocks():
                        m.write_blocks(coords, blocks)
                else:
                    m.write_map(raw)
        t_enc = time.perf_counter() - t_enc
        got = sdfcodec.open_map(path)
        info = got.info()
        row = {"bytes_per_coded_block": info["bytes_on_disk"] / max(1, info["blocks"]["coded"]),
               "write_seconds": t_enc if k is not None else None,
               **compare_maps(raw, got).to_dict()}
        if args.track:
            row["ate_rmse_m"] = track_command(path, args.kitchen, out / f"{name.replace(' ', '-')}.txt",
                                              progress=False)["ate"]["rmse"]
        rows[name] = row
        print(name, json.dumps({key: row[key] for key in ("chamfer_l1", "f_score_1")}), flush=True)
    held = held_out(fused, out)
    base = rows["lossless"].get("ate_rmse_m")
    (out / "surface-study.json").write_text(json.dumps({"rows": rows, "held_out": held,
                                                        "seconds": time.perf_counter() - t0,
                                                        "frames": fused.frames_integrated}, indent=2))
    print("| map | bytes / coded block | Chamfer-L1 (mm) | F@1 voxel | F@2 voxels | band RMSE / bias (mm) | "
          "sign agreement | ATE (cm) | ATE / lossless |")
    print("|---|---|---|---|---|---|---|---|---|")
    for name, r in rows.items():
        ate = r.get("ate_rmse_m")
        ate_s = "" if ate is None else f"{100 * ate:.2f} | {ate / base:.2f}x"
        print(f"| {name} | {r['bytes_per_coded_block']:.0f} | {1000 * r['chamfer_l1']:.1f} | {r['f_score_1']:.3f} | "
              f"{r['f_score_2']:.3f} | {1000 * r['near_surface_rmse']:.1f} / {1000 * r['near_surface_bias']:+.1f} | "
              f"{r['sign_agreement']:.3f} | {ate_s} |")
    print(f"\nheld-out half ({held['coded_blocks']} coded blocks)\n\n| map | Chamfer-L1 (mm) | F@1 voxel | F@2 voxels |\n|---|---|---|---|")
    for name, r in held["rows"].items():
        print(f"| {name} | {1000 * r['chamfer_l1']:.2f} | {r['f_score_1']:.3f} | {r['f_score_2']:.3f} |")


def held_out(fused, out: Path) -> dict:
    """Surface metrics of surface-true pca-32/64/128 maps of the held-out half (blocks with x index past the
    middle plus one, the split of examples/train_default_model.py) against its lossless map."""
    half = fused.select(fused.coords[:, 0] > fused.grid_shape[0] // 2)
    maps = {}
    for name, codec in [("lossless", sdfcodec.get_codec("raw"))] + [
            (f"pca-{k} surface-true", sdfcodec.pretrained_codec("pca", k)) for k in (32, 64, 128)]:
        path = out / f"held-out-{name.split()[0]}.sdfz"
        with sdfcodec.create_map(path, codec=codec, voxel_size=fused.voxel_size, truncation=fused.truncation,
                                 origin=tuple(fused.origin), overwrite=True) as m:
            m.write_blocks(half.coords, half.tsdf, weights=half.weights)
        maps[name] = sdfcodec.open_map(path)
    rows = {name: compare_maps(maps["lossless"], m).to_dict() for name, m in maps.items() if name != "lossless"}
    for name, r in rows.items():
        print("held-out", name, json.dumps({key: r[key] for key in ("chamfer_l1", "f_score_1")}), flush=True)
    return {"coded_blocks": maps["lossless"].info()["blocks"]["coded"], "rows": rows}


if __name__ == "__main__":
    main()
