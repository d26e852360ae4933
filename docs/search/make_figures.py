"""Make the figures and numbers of docs/search.md (descriptor search and selective expansion).

    python docs/search/make_figures.py pr        # precision/recall on synthetic rooms      (~11 min, 2 cores)
    python docs/search/make_figures.py bench     # search throughput and bytes read          (~1.5 min)
    python docs/search/make_figures.py room      # Fig. 7 on a synthetic room                (~20 s)
    python docs/search/make_figures.py kitchen   # Fig. 7 on the fused 7-Scenes kitchen      (~2 min)
    python docs/search/make_figures.py all

Outputs go to docs/search/ (JSON with every number, PNG pictures); the tables in docs/search.md are copied from
the printed output. Everything is measured in the run that writes it; nothing is downloaded.
"""

from __future__ import annotations

import argparse
import os
import json
import tempfile
import time
from pathlib import Path

import numpy as np

import sdfcodec
from sdfcodec.search.engine import expand
from sdfcodec.search.metrics import evaluate_retrieval
from sdfcodec.search.query import build_query
from sdfcodec.search.models import save_query
from sdfcodec.search.rooms import synthetic_room
from sdfcodec.bench import bench_search
from sdfcodec import pretrained_codec
from sdfcodec.view.search import format_summary, search_command

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[1]
# a 7-Scenes redkitchen sequence folder (frames, poses, gravity): --kitchen DIR, else $SDFCODEC_KITCHEN
KITCHEN = Path(os.environ["SDFCODEC_KITCHEN"]) if os.environ.get("SDFCODEC_KITCHEN") else None


def _machine() -> dict:
    """Where and under what load a run happened (this machine is shared: record the load with every timing)."""
    import os
    import platform

    import torch

    cpu = platform.processor() or platform.machine()
    try:
        cpu = next(ln.split(":", 1)[1].strip() for ln in open("/proc/cpuinfo") if ln.startswith("model name"))
    except (OSError, StopIteration):
        pass
    return {"cpu": cpu, "cores": os.cpu_count(), "torch_threads": torch.get_num_threads(),
            "numpy": np.__version__, "torch": torch.__version__, "python": platform.python_version(),
            "loadavg": list(os.getloadavg())}


def _compact_curve(curve: dict, ops: dict, points: int = 160) -> dict:
    """A PR curve down-sampled for the repository: ``points`` points evenly spaced along the curve's length in
    (recall, precision), plus its ends and the exact operating points (precision at recall >= 0.9, recall at
    precision >= 0.9, best F1), so every number in the tables can be read off the stored curve. Values rounded
    to 5 decimals (precision, recall) and 5 significant digits (thresholds)."""
    t = np.asarray(curve["thresholds"], np.float64)
    p = np.asarray(curve["precision"], np.float64)
    r = np.asarray(curve["recall"], np.float64)
    if len(t) <= points:
        keep = np.arange(len(t))
    else:
        arc = np.r_[0.0, np.cumsum(np.hypot(np.diff(r), np.diff(p)))]
        keep = np.searchsorted(arc, np.linspace(0.0, arc[-1], points))
        exact = [0, len(t) - 1]
        for k in ("precision_at_recall_threshold", "recall_at_precision_threshold", "best_f1_threshold"):
            if ops.get(k) is not None:
                exact.append(int(np.searchsorted(t, ops[k])))  # thresholds are the curve's own, ascending
        keep = np.unique(np.clip(np.r_[keep, exact], 0, len(t) - 1))
    return {"thresholds": [float(f"{v:.5g}") for v in t[keep]], "precision": np.round(p[keep], 5).tolist(),
            "recall": np.round(r[keep], 5).tolist(), "points_full": int(len(t))}


def _row(r: dict) -> str:
    f = lambda v: "-" if v is None else f"{v:.3f}"  # noqa: E731
    return (f"| {r['codec']} | {r['level']} | {r['query']} ({r['descriptors']}) | {r['rooms']} | {r['positives']} | "
            f"{f(r['precision_at_recall'])} | {f(r['recall_at_precision'])} | {f(r['ap'])} | {r['best_f1']:.3f} at "
            f"{r['best_f1_threshold']:.1f} | {r['partial_selected']} / {r['partial']} |")


def pr(rooms_n: int = 12, tilted_n: int = 8, solid_n: int = 6) -> None:
    """PR curves of floor retrieval: shipped pca-32/64/128 maps (levels 32..128) and a PCA fitted on 20000
    synthetic blocks, 15 vs 17 plane offsets; tilted rooms with and without rotation sampling; rooms sampled
    as exact truncated SDFs (solid behind surfaces) instead of as fusion sees them."""
    t0 = time.perf_counter()
    machine = _machine()
    log = lambda m: print(f"[{time.perf_counter() - t0:6.0f} s] {m}", flush=True)  # noqa: E731
    rooms = [synthetic_room(s, geometry="normal" if s % 2 == 0 else "rich") for s in range(rooms_n)]
    log(f"{rooms_n} rooms")
    from sdfcodec.data.synthetic import synthetic_blocks

    fitted = sdfcodec.get_codec("pca", code_size=128).fit(synthetic_blocks(20000, seed=0))
    log("pca-128 fitted on 20000 synthetic blocks")
    codecs = {"pca-32": pretrained_codec("pca", 32), "pca-64": pretrained_codec("pca", 64),
              "pca-128": pretrained_codec("pca", 128), "synthetic-fit pca-64": fitted.prefix(64)}
    levels = {"pca-32": [32], "pca-64": [32, 64], "pca-128": [32, 64, 128], "synthetic-fit pca-64": [64]}
    queries = {"floor": {"shape": "floor"}, "floor, paper's 15 offsets": {"shape": "floor", "offsets": 15}}
    truths = ("floor", "floor-vs-none", "floor-majority", "up")
    records = evaluate_retrieval(rooms, codecs, queries=queries, levels=levels, truths=truths, progress=log)
    for r in records:
        r["scenes"] = "level"
    tilted = [synthetic_room(100 + s, geometry="normal" if s % 2 == 0 else "rich", tilt_deg=10.0)
              for s in range(tilted_n)]
    log(f"{tilted_n} tilted rooms")
    tq = {"floor": {"shape": "floor"}, "floor, cone 10 deg x 16": {"shape": "floor", "rotations": "cone:10:16"},
          "floor, cone 10 deg x 48": {"shape": "floor", "rotations": "cone:10:48"},
          "floor, true up": {"shape": "floor", "up": "room"}}
    trecs = evaluate_retrieval(tilted, {"pca-64": pretrained_codec("pca", 64)}, queries=tq,
                                 truths=("floor", "floor-vs-none"), progress=log)
    for r in trecs:
        r["scenes"] = "tilted up to 10 deg"
    records += trecs
    solid = [synthetic_room(200 + s, geometry="normal" if s % 2 == 0 else "rich", behind="solid")
             for s in range(solid_n)]
    log(f"{solid_n} rooms sampled as exact truncated SDFs (solid behind surfaces)")
    sq = {"floor, solid, paper's 15 offsets": {"shape": "floor", "behind": "solid"},
          "floor, solid, 17 offsets": {"shape": "floor", "behind": "solid", "offsets": "lattice"},
          "floor (unobserved-behind model)": {"shape": "floor"}}
    srecs = evaluate_retrieval(solid, {"pca-64": pretrained_codec("pca", 64)}, queries=sq,
                                 truths=("floor", "floor-vs-none"), progress=log)
    for r in srecs:
        r["scenes"] = "solid-behind"
    records += srecs
    _pr_figure(records)  # from the full curves
    for r in records:
        r["curve"] = _compact_curve(r["curve"], r)
    import os

    out = {"command": "python docs/search/make_figures.py pr", "machine": machine,
           "loadavg_end": list(os.getloadavg()), "seconds": time.perf_counter() - t0,
           "note": "curves down-sampled (see _compact_curve); operating points computed on the full curves",
           "records": records}
    (HERE / "pr.json").write_text(json.dumps(out, separators=(",", ":")))
    log(f"pr.json: {(HERE / 'pr.json').stat().st_size / 1024:.0f} KiB")
    print("\n| map | level | query (descriptors) | rooms | clean floor blocks | P at R >= 0.9 | R at P >= 0.9 | AP | "
          "best F1 at threshold | partial selected / all |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for scenes in ("level", "tilted up to 10 deg", "solid-behind"):
        for truth in truths:
            rows = [r for r in records if r["scenes"] == scenes and r["truth"] == truth]
            if rows:
                print(f"| **{scenes} rooms, truth: {truth}** | | | | | | | | | |")
                for r in rows:
                    print(_row(r))
    log("done")


def _pr_figure(records: list[dict]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(15, 4.6), constrained_layout=True)
    panels = [
        ("level rooms, clean floor vs all others", "level", "floor", "floor"),
        ("level rooms, 17 vs the paper's 15 offsets", "level", "floor", None),
        ("rooms tilted up to 10 deg (pca-64)", "tilted up to 10 deg", "floor", None),
    ]
    for ax, (title, scenes, truth, query) in zip(axes, panels):
        for r in records:
            if r["scenes"] != scenes or r["truth"] != truth or (query and r["query"] != query):
                continue
            if scenes == "level" and query is None and r["codec"] != "pca-64":
                continue
            c = r["curve"]
            ax.plot(c["recall"], c["precision"], label=f"{r['codec']} L{r['level']} {r['query']}", lw=1.2)
        ax.axhline(0.9, color="grey", lw=0.6, ls=":")
        ax.axvline(0.9, color="grey", lw=0.6, ls=":")
        ax.set(title=title, xlabel="recall", ylabel="precision", xlim=(0, 1.01), ylim=(0, 1.01))
        ax.legend(fontsize=7, loc="lower left")
    fig.savefig(HERE / "pr-curves.png", dpi=90)
    plt.close(fig)


def bench() -> None:
    """Search throughput (kernel and whole-map) and bytes read at level 32 of a 128-element map."""
    machine = _machine()
    recs = bench_search((64, 128), batches=(65536, 1 << 20), map_blocks=200_000,
                        map_levels={64: [64], 128: [32, 128]}, progress=print)
    import os

    (HERE / "bench.json").write_text(json.dumps({"command": "python docs/search/make_figures.py bench",
                                                 "machine": machine, "loadavg_end": list(os.getloadavg()),
                                                 "records": recs}, indent=1))
    print(f"machine: {machine}")
    print("\n| operation | code size | level | blocks | blocks/s | numpy matmul blocks/s | ratio to matmul | "
          "load (1 min) | code bytes read |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r in recs:
        lvl = r.get("level", r["code_size"])
        read = f"{r['code_bytes_read'] / 2**20:.1f} of {r['code_bytes_full'] / 2**20:.1f} MiB" if "code_bytes_read" in r else "-"
        print(f"| {r['operation']} | {r['code_size']} | {lvl} | {r['batch']:,} | {r['blocks_per_s']:,.0f} | "
              f"{r['baseline_blocks_per_s']:,.0f} | {r['ratio_to_baseline']:.2f} | "
              f"{r['load_before'][0]:.2f} -> {r['load_after'][0]:.2f} | {read} |")


def room() -> None:
    """Fig. 7 on a synthetic room (pca-64 map, full-level search, automatic threshold)."""
    lab = synthetic_room(3, geometry="rich")
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "room-64.sdfz"
        with sdfcodec.create_map(path, codec=pretrained_codec("pca", 64), voxel_size=lab.voxel_size,
                                 origin=tuple(lab.origin)) as w:
            w.write_volume(lab.volume)
        out = Path(tmp) / "out"
        s = search_command(path, "floor", None, None, None, out, False, "cpu")
        (HERE / "room-floor.png").write_bytes((out / "search.png").read_bytes())
    s.pop("map")
    s.pop("picture")
    s.pop("mesh", None)
    s["machine"] = _machine()
    (HERE / "room-floor.json").write_text(json.dumps(s, indent=1))
    print(format_summary({**s, "map": "synthetic room (seed 3, rich)"}))


def kitchen() -> None:
    """Fuse the 7-Scenes kitchen, encode it with the shipped pca-64, search floors along the true up
    direction (minus gravity), and draw Fig. 7. Also searches the lossless raw map for comparison."""
    from sdfcodec.fusion.tsdf import fuse

    if KITCHEN is None or not KITCHEN.is_dir():
        raise SystemExit(f"no kitchen data at {KITCHEN or '(none given)'}: pass --kitchen DIR (a 7-Scenes "
                         "redkitchen sequence folder) or set $SDFCODEC_KITCHEN")
    g_cam = np.loadtxt(KITCHEN / "gravity-direction.txt")
    pose0 = np.loadtxt(KITCHEN / "frame-000000.pose.txt")
    up = -(pose0[:3, :3] @ g_cam)
    up /= np.linalg.norm(up)
    t0 = time.perf_counter()
    fused = fuse(KITCHEN, voxel_size=0.02, truncation=(-0.04, 0.1), quiet=True)
    print(f"fused {len(fused)} blocks in {time.perf_counter() - t0:.0f} s; up = {np.round(up, 3).tolist()}")
    out_json = {}
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        raw = tmp / "kitchen-raw.sdfz"
        with sdfcodec.create_map(raw, codec=sdfcodec.get_codec("raw"), voxel_size=0.02,
                                 origin=tuple(fused.origin)) as w:
            w.write_blocks(fused.coords, fused.tsdf)
        m_raw = sdfcodec.open_map(raw)
        p64 = tmp / "kitchen-64.sdfz"
        with sdfcodec.create_map(p64, codec=pretrained_codec("pca", 64), voxel_size=0.02, origin=m_raw.origin) as w:
            for coords, blocks in m_raw.iter_blocks():
                w.write_blocks(coords, blocks)
        for name, path in (("pca-64", p64), ("raw", raw)):
            m = sdfcodec.open_map(path)
            model = build_query("floor", map=m, up=up, rotations="cone:5:16")
            qpath = tmp / f"floor-{name}.npz"
            save_query(model, qpath)
            out = tmp / f"out-{name}"
            auto = search_command(path, str(qpath), None, None, None, None, False, "cpu")
            # the automatic threshold selects only the few cleanest blocks of this noisy real map: show the
            # 25 best, and report both
            s = search_command(path, str(qpath), None, None, 25, out, True, "cpu")
            s["auto_threshold"], s["auto_selected"] = auto["threshold"], auto["selected"]
            c = np.array([b["coords"] for b in s.pop("blocks")])
            s["selected_heights_m"] = np.round((np.asarray(m.origin) + 0.02 * (16 * c + 7.5)) @ up, 3).tolist()
            # independent check on the lossless fused blocks: the mean surface normal of each selected block
            lossless = expand(m_raw, c).blocks
            cosines = []
            for b in lossless:
                grads = np.stack(np.gradient(b), -1)[(np.abs(b) < 0.02)]
                n = grads.mean(axis=0)
                cosines.append(float(n @ up / (np.linalg.norm(n) + 1e-12)))
            s["selected_normal_dot_up"] = np.round(cosines, 3).tolist()
            s["selected_horizontal_up"] = int(np.sum(np.asarray(cosines) >= 0.98))
            (HERE / f"kitchen-floor-{name}.png").write_bytes((out / "search.png").read_bytes())
            for k in ("map", "picture", "mesh"):
                s.pop(k, None)
            out_json[name] = s
            print(f"{name}: " + format_summary({**s, "map": f"kitchen ({name})"}))
            print(f"  auto threshold {s['auto_threshold']:.1f} selects {s['auto_selected']}; of the top 25, "
                  f"{s['selected_horizontal_up']} are upward-facing horizontal surfaces (normal . up >= 0.98)")
    (HERE / "kitchen-floor.json").write_text(json.dumps({"up": up.tolist(), "machine": _machine(), **out_json},
                                                        indent=1))


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("what", choices=["pr", "bench", "room", "kitchen", "all"])
    ap.add_argument("--kitchen", type=Path, default=None, help="a 7-Scenes redkitchen sequence folder "
                                                                "(default: $SDFCODEC_KITCHEN)")
    args = ap.parse_args()
    if args.kitchen is not None:
        KITCHEN = args.kitchen
    for name in (["pr", "bench", "room", "kitchen"] if args.what == "all" else [args.what]):
        globals()[name]()
