"""What ``sdfcodec encode --target-error E`` writes, measured on the maps it writes.

    python examples/error_target_study.py --kitchen KITCHEN_DIR     # kitchen half, synthetic room, rooms
    python examples/error_target_study.py --quick --out DIR         # a small synthetic corner, two targets

For each data set of examples/peers_study.py (the same blocks: the held-out kitchen half fused at 2 cm, the
furnished synthetic room and the two random rooms, both made fused-like) and each target of :data:`TARGETS`, the
real command ``sdfcodec encode LOSSLESS OUT --target-error E`` (a refusal is recorded with its one line), then on
the map it wrote: bytes per coded block (every file counted, the shipped model referenced), whether it took a
surface refinement and at what step, and the error at the voxels that place the surface, as read back:

- ``p99_mm``: the 99th percentile of ``|read - input|`` over the observed voxels touching a crossing of the input
  (inside their block or across a block's face), among those the map reads observed: the target's own definition
  (the writer measures it on a sample of up to 2,048 blocks, so it can miss on a larger map). Voxels a default
  (approximate) mask reads unobserved are left out: it sets voxels to ``d_max`` only where that moves no zero
  crossing of the decode. ``p99_inside_mm``: the same over the crossings inside a block alone.
- ``p99_all_mm``: the same over every crossing voxel, those read ``d_max`` included; ``over_share``: the share of
  those beyond E; ``max_mm``: the largest.
- Chamfer-L1 and F@1 against the lossless blocks (as docs/rate-distortion.md measures them).

Writes ``error-target.json`` and the section ``error-target`` of docs/variable-rate.md (``--out``: elsewhere).
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _page import replace_section  # noqa: E402
from peers_study import Data, encode, lossless_map, rooms_blocks  # noqa: E402
from rate_distortion import TRUNC, VS, fused_like, kitchen_blocks, normalised, synthetic_blocks  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
#: metres
TARGETS = (0.05, 0.03, 0.02, 0.01, 0.005, 0.002)
TARGETS_QUICK = (0.03, 0.005)


def measure(d: Data, path: Path, e: float) -> dict:
    """The point of the map at ``path`` (written for target ``e`` metres) on data set ``d``."""
    import sdfcodec
    from sdfcodec.map.residual import crossing_voxels

    m = sdfcodec.open_map(path)
    index = {tuple(c): i for i, c in enumerate(d.coords.tolist())}
    read = np.ones_like(d.x)
    seen = np.zeros(d.x.shape, bool)
    for c, blocks in m.iter_decoded():
        rows = [index[tuple(cc)] for cc in np.asarray(c).tolist()]
        read[rows] = normalised(np.asarray(blocks))
        seen[rows] = m.read_observed(np.asarray(c))
    total = sum(f.stat().st_size for f in path.rglob("*") if f.is_file())
    p = d.point("ours: sdfcodec encode", f"target-error {e:g}", "ours", total, read)
    x, y = (d.x * (TRUNC[1] - TRUNC[0]) + TRUNC[0], read * (TRUNC[1] - TRUNC[0]) + TRUNC[0])
    far = np.arange(d.n)[:, None] * np.array([[3, 0, 0]])  # blocks never neighbours: crossings inside a block
    inside = crossing_voxels(far, x, d.obs) & seen
    every = crossing_voxels(d.coords, x, d.obs)
    err_in, err_seen, err_all = np.abs(y - x)[inside], np.abs(y - x)[every & seen], np.abs(y - x)[every]
    vr = m.header.codes.variable_rate
    return {"target_mm": 1000 * e, "blocks": d.n, "bytes_per_block": p["bytes_per_block"], "chamfer_mm": p["chamfer_mm"],
            "f1": p["f1"],
            "refine_step_mm": None if vr.refinement is None else 1000 * vr.refinement.step * 2.0 ** -24,
            "codes_step": float(np.mean(vr.step)),
            "p99_mm": 1000 * float(np.quantile(err_seen, 0.99)), "crossing_voxels": int((every & seen).sum()),
            "p99_inside_mm": 1000 * float(np.quantile(err_in, 0.99)),
            "p99_all_mm": 1000 * float(np.quantile(err_all, 0.99)), "over_share": float(np.mean(err_all > e)),
            "max_mm": 1000 * float(err_all.max()), "crossing_voxels_all": int(every.sum())}


def markdown(res: dict) -> str:
    """The page's section from the run ``res`` (the JSON)."""
    lines = [f"Measured by `{res['command']}` ({res['cpus']} CPUs; {res['seconds']:.0f} s). Per data set and "
             "target: bytes per coded block (every file), the refinement step the writer chose (none: codes "
             "alone), the 99th percentile of the error at the crossing voxels the map reads observed (the "
             "target's definition: inside a block or across a block's face), the same inside blocks alone, and "
             "over every crossing voxel (voxels read `d_max` included) with the share beyond the target and the "
             "largest, Chamfer-L1 and F@1.", "",
             "| data set | target | B per coded block | refinement | p99 (definition) | p99 inside blocks | "
             "p99, every crossing voxel | beyond target | largest | Chamfer-L1 | F@1 |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in res["rows"]:
        if "refused" in r:
            lines.append(f"| {r['dataset']} | {r['target_mm']:g} mm | refused: {r['refused']} | | | | | | | | |")
            continue
        ref = "none" if r["refine_step_mm"] is None else f"{r['refine_step_mm']:.2f} mm"
        lines.append(f"| {r['dataset']} | {r['target_mm']:g} mm | {r['bytes_per_block']:.1f} | {ref} | "
                     f"{r['p99_mm']:.2f} mm | {r['p99_inside_mm']:.2f} mm | {r['p99_all_mm']:.2f} mm | "
                     f"{100 * r['over_share']:.2f} % | "
                     f"{r['max_mm']:.0f} mm | {r['chamfer_mm']:.2f} mm | {r['f1']:.3f} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--kitchen", type=Path, default=Path(os.environ.get("SDFCODEC_KITCHEN", "")),
                    help="folder of the 7-Scenes redkitchen frames (else $SDFCODEC_KITCHEN; skipped when absent)")
    ap.add_argument("--quick", action="store_true", help="a 64 x 64 x 48-voxel synthetic corner, two targets")
    ap.add_argument("--out", type=Path, default=None, help="where the JSON and page go (default: docs/)")
    ap.add_argument("--workdir", type=Path, default=None, help="maps and the kitchen's fused blocks (cached)")
    a = ap.parse_args(argv)
    work = a.workdir or Path(tempfile.mkdtemp(prefix="error-target-"))
    out = a.out or ROOT / "docs"
    out.mkdir(parents=True, exist_ok=True)
    sets = [("synthetic (quick)", lambda: (lambda c, t: (c, *fused_like(t)))(*synthetic_blocks(True)))]
    if not a.quick:
        sets = ([("kitchen", lambda: kitchen_blocks(a.kitchen, work))] if a.kitchen.is_dir() else []) + [
            ("synthetic", lambda: (lambda c, t: (c, *fused_like(t)))(*synthetic_blocks(False, shift=0.3))),
            ("rooms", rooms_blocks)]
        if not a.kitchen.is_dir():
            print(f"no kitchen data at {a.kitchen}: skipped", file=sys.stderr)
    t0 = time.perf_counter()
    rows = []
    for name, build in sets:
        d = Data(name, *build(), work)
        src = lossless_map(d)
        for e in TARGETS_QUICK if a.quick else TARGETS:
            path = work / f"{name}-target-error-{e:g}.sdfz".replace(" ", "_")
            refusal = encode(src, path, {"target-error": e})
            rows.append({"dataset": name, "target_mm": 1000 * e, "refused": refusal} if refusal is not None
                        else {"dataset": name, **measure(d, path, e)})
    shown = ["--quick"] * a.quick + (["--kitchen", "KITCHEN_DIR"] if not a.quick and a.kitchen.is_dir() else [])
    res = {"command": shlex.join(["python", "examples/error_target_study.py", *shown]),  # no local paths
           "cpus": os.cpu_count(), "seconds": time.perf_counter() - t0, "voxel_size": VS, "rows": rows}
    (out / "error-target.json").write_text(json.dumps(res, indent=1) + "\n")
    replace_section(out / "variable-rate.md", "error-target", markdown(res), "# Variable-rate maps")
    return res


if __name__ == "__main__":
    main()
