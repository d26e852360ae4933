"""Search with the CLI's defaults on rooms built by other code: a second room generator, written apart from
``sdfcodec.search.rooms`` (its own layout, furniture, voxel sizes, extents that are not multiples of 16, its own
truth), so that what the evaluation in ``evaluate.py`` measures is not a property of one generator.

    PYTHONPATH=. .venv/bin/python docs/search/independent.py [--seeds 21 22 23] [--jobs 2] [--out FILE.json]

Each room: a floor slab over ground, four walls, a ceiling slab, 2-3 tables (a top on four legs), 1-2 cabinets
against a wall, a sphere and a yawed box on the floor, all ``sdfcodec.core.sdf`` primitives, the whole room tilted by
``--tilts`` degrees about a horizontal axis, sampled at ``--voxels`` metres with a truncation of -2 and +5 voxels.
It is stored two ways through the public API: ``exact`` (the truncated SDF, ``create_map`` + ``write_blocks``,
what ``sdfcodec encode room.npy`` writes) and ``fused-style`` (voxels more than |d_min| behind a surface never
observed: ``d_max`` with the observation mask). Then ``sdfcodec search MAP --query Q --json`` with no other flag.

Truth per block (its own, cruder than ``LabelledRoom.block_labels``): the surface voxels are those within 0.87
voxel of the exact surface, each labelled by its nearest primitive. A block is a *positive* of a query when at
least 24 surface voxels lie in it and at least 90 % of them belong to one primitive of the query's kind; a
*negative* when under half of them belong to the query's kind, or when it holds no surface voxel and no voxel
within 1.5 voxels of a surface; other blocks (mixed, or a surface just past a block face) are left out.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

import sdfcodec
from sdfcodec.core.blocks import split_blocks
from sdfcodec.core.sdf import Box, Cylinder, Sphere, grid_points

QUERIES = ("floor", "wall", "ceiling")


def room(seed: int, tilt_deg: float, voxel: float, dims=(4.2, 3.4, 2.5)):
    """``(distances (X, Y, Z, P), labels (P,))``: every primitive's exact distance at every voxel."""
    rng = np.random.default_rng(seed)
    lx, ly, h = dims
    z0 = 0.05 + rng.uniform(0.0, 0.3)
    m = 0.15 + rng.uniform(0, 0.1)
    prims = [("floor", Box([lx / 2, ly / 2, z0 - 0.5], [lx / 2 + 1, ly / 2 + 1, 0.5])),
             ("ceiling", Box([lx / 2, ly / 2, z0 + h + 0.5], [lx / 2 + 1, ly / 2 + 1, 0.5])),
             ("wall", Box([m - 0.5, ly / 2, z0 + h / 2], [0.5, ly / 2 + 1, h / 2 + 1])),
             ("wall", Box([lx - m + 0.5, ly / 2, z0 + h / 2], [0.5, ly / 2 + 1, h / 2 + 1])),
             ("wall", Box([lx / 2, m - 0.5, z0 + h / 2], [lx / 2 + 1, 0.5, h / 2 + 1])),
             ("wall", Box([lx / 2, ly - m + 0.5, z0 + h / 2], [lx / 2 + 1, 0.5, h / 2 + 1]))]
    for _ in range(rng.integers(2, 4)):  # tables: a top on four legs
        cx, cy = rng.uniform(1.0, lx - 1.0), rng.uniform(1.0, ly - 1.0)
        hx, hy, ht = rng.uniform(0.3, 0.6), rng.uniform(0.25, 0.45), rng.uniform(0.6, 0.8)
        rz = Rotation.from_euler("z", rng.uniform(0, np.pi)).as_matrix()
        prims.append(("furniture", Box([cx, cy, z0 + ht - 0.02], [hx, hy, 0.02], rz)))
        for sx in (-1, 1):
            for sy in (-1, 1):
                p = np.array([cx, cy, 0]) + rz @ np.array([sx * (hx - 0.05), sy * (hy - 0.05), 0])
                prims.append(("furniture", Cylinder([p[0], p[1], z0 + ht / 2], 0.03, ht / 2)))
    for _ in range(rng.integers(1, 3)):  # cabinets against a wall
        w = rng.uniform(0.4, 1.0)
        prims.append(("furniture", Box([m + 0.25, rng.uniform(0.8, ly - 0.8), z0 + 0.45], [0.25, w / 2, 0.45])))
    prims.append(("furniture", Sphere([rng.uniform(1, lx - 1), rng.uniform(1, ly - 1), z0 + 0.25], 0.25)))
    prims.append(("furniture", Box([rng.uniform(1, lx - 1), rng.uniform(1, ly - 1), z0 + 0.2], [0.4, 0.2, 0.2],
                                   Rotation.from_euler("z", rng.uniform(0, np.pi)).as_matrix())))
    shape = tuple(int(np.ceil((d + 0.6) / voxel)) for d in (lx, ly, h + z0))
    rot = Rotation.from_rotvec(np.deg2rad(tilt_deg) * np.array([np.cos(seed), np.sin(seed), 0.0])).as_matrix()
    centre = np.array(shape) * voxel / 2
    local = (grid_points(shape, voxel) - centre) @ rot + centre  # the room turned by rot about the grid's centre
    return np.stack([p(local) for _, p in prims], axis=-1), np.array([lab for lab, _ in prims])


def truth(d: np.ndarray, labels: np.ndarray, voxel: float, kind: str) -> tuple[np.ndarray, np.ndarray]:
    """``(positive, negative)`` per block of the grid (module docstring)."""
    dist, which = d.min(-1), d.argmin(-1)
    surf, near = np.abs(dist) < 0.87 * voxel, np.abs(dist) < 1.5 * voxel
    # padding beyond the room's extent holds no surface (zeros: False, and a label nothing counts)
    sb, wb, nb = (split_blocks(a, 0) for a in (surf, which, near))
    sb, wb, nb = (b.reshape(*b.shape[:3], -1) for b in (sb, wb, nb))
    pos, neg = np.zeros(sb.shape[:3], bool), np.zeros(sb.shape[:3], bool)
    for idx in np.ndindex(*sb.shape[:3]):
        s = sb[idx]
        if not s.any():
            neg[idx] = not nb[idx].any()
            continue
        lab, cnt = np.unique(wb[idx][s], return_counts=True)
        top = cnt.argmax()
        pos[idx] = labels[lab[top]] == kind and cnt[top] >= 24 and cnt[top] >= 0.9 * s.sum()
        neg[idx] = cnt[labels[lab] == kind].sum() < 0.5 * s.sum()
    return pos, neg


def run(seed: int, tilt: float, voxel: float, style: str, tmp: str) -> list[dict]:
    d, labels = room(seed, tilt, voxel)
    trunc = (-2 * voxel, 5 * voxel)
    dist = d.min(-1)
    vol = np.clip(dist, *trunc).astype(np.float32)
    obs = None
    if style == "fused-style":
        obs = dist >= trunc[0]
        vol[~obs] = trunc[1]
    path = Path(tmp) / f"{style}-{seed}-{tilt}-{voxel}.sdfz"
    b = split_blocks(vol)
    coords = np.argwhere(np.ones(b.shape[:3], bool))
    with sdfcodec.create_map(path, codec=sdfcodec.pretrained_codec("pca", 64), voxel_size=voxel, truncation=trunc,
                             shape_voxels=vol.shape, overwrite=True, tool="docs/search/independent.py") as m:
        m.write_blocks(coords, b.reshape(-1, 16, 16, 16),
                       observed=None if obs is None else split_blocks(obs, False).reshape(-1, 16, 16, 16))
    rows = []
    for q in QUERIES:
        pos, neg = truth(d, labels, voxel, q)
        r = subprocess.run([sys.executable, "-m", "sdfcodec", "search", str(path), "--query", q, "--json",
                            "--no-mesh"], capture_output=True, text=True, check=True)
        sel = [tuple(b["coords"]) for b in json.loads(r.stdout).get("blocks", [])]
        tp = sum(bool(pos[c]) for c in sel)
        fp = sum(bool(neg[c]) for c in sel)
        rows.append({"style": style, "seed": seed, "tilt_deg": tilt, "voxel_m": voxel, "query": q, "tp": tp,
                     "fp": fp, "selected": len(sel), "positives": int(pos.sum()),
                     "false_positives": [list(c) for c in sel if neg[c]]})
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", type=int, nargs="+", default=[21, 22, 23])
    ap.add_argument("--tilts", type=float, nargs="+", default=[0.0, 7.0])
    ap.add_argument("--voxels", type=float, nargs="+", default=[0.02])
    ap.add_argument("--styles", nargs="+", default=["exact", "fused-style"])
    ap.add_argument("--jobs", type=int, default=1)
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    tasks = [(s, t, v, st) for s in args.seeds for t in args.tilts for v in args.voxels for st in args.styles]
    with tempfile.TemporaryDirectory() as tmp, ProcessPoolExecutor(max(1, args.jobs)) as pool:
        rows = [r for part in pool.map(run, *zip(*tasks), [tmp] * len(tasks)) for r in part]
    print("| style | tilt | voxel | query | selected | positives | precision | recall |")
    print("|---|---|---|---|---|---|---|---|")
    pooled = {}
    for r in rows:
        k = (r["style"], r["tilt_deg"], r["voxel_m"], r["query"])
        p = pooled.setdefault(k, {"tp": 0, "fp": 0, "selected": 0, "positives": 0})
        for f in p:
            p[f] += r[f]
    for (style, tilt, voxel, q), p in pooled.items():
        prec = p["tp"] / (p["tp"] + p["fp"]) if p["tp"] + p["fp"] else float("nan")
        rec = p["tp"] / p["positives"] if p["positives"] else float("nan")
        p.update(precision=prec, recall=rec)
        print(f"| {style} | {tilt:g} | {voxel:g} | {q} | {p['selected']} | {p['positives']} | {prec:.3f} | {rec:.3f} |")
    out = {"seeds": args.seeds, "rows": rows, "pooled": [{"style": k[0], "tilt_deg": k[1], "voxel_m": k[2],
                                                          "query": k[3], **v} for k, v in pooled.items()],
           "seconds": time.perf_counter() - t0}
    if args.out:
        args.out.write_text(json.dumps(out, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
