"""Measurements for the SDF Tracker rows of docs/results.md: frames/s per frame and ATE.

Run: ``.venv/bin/python docs/results/tracking_measure.py --kitchen DIR --work WORKDIR [--out FILE.json]`` where DIR is a
7-Scenes redkitchen sequence folder (or set ``$SDFCODEC_KITCHEN``). It fuses the kitchen into a lossless map
and transcodes it to pca-64 (once, kept in WORKDIR), fuses the synthetic presets likewise, then tracks every
frame of each sequence from the first ground-truth pose with ``sdfcodec track``'s settings
(``EVAL_TRACKER_CONFIG``) against a dense field of each map (and a warm ``MapField`` of the kitchen maps).
Every ``tracker.track`` call is timed on its own: the record holds the median and quartiles of the per-frame
times (over all frames and over the first 200), the start-up (map open + dense decode, or the cold pass of
the lazy map) apart, the ATE RMSE against the ground truth, the load before and after and the torch threads.
Only public API is used. ``--tracker OLD`` (OLD: the ``sdfcodec`` package folder of another checkout) runs the
same measurement with that checkout's tracker and dense field (the lazily decoded map stays this one's): the
"before" of an ATE comparison.

With ``--bench FILE.json`` it writes docs/results/tracking-bench.json instead: ``benchmark_tracking`` of the
kitchen's lossless and pca-64 maps (dense, cold and warm MapField; per-frame medians, start-up apart).

With ``--ab OLD`` (OLD: the ``sdfcodec`` package folder of another checkout) it tracks the first
``--lazy-frames`` kitchen frames against the lossless map's dense field with both trackers in one process,
alternating which goes first frame by frame, so both see the same load: wall and CPU time per frame, ATE.
``--ab-field warm`` compares the trackers on warm ``MapField``s instead, after one untimed warming pass over the
same frames: OLD's ``MapField.sample_with_gradient`` grafted onto this checkout's ``MapField`` (the old package
cannot load its own map reader beside this one: the codec plugins register with one package), so it measures a
change of the lookup, not of the cache. ``--ab-map pca-64`` uses the pca-64 map.
"""
import argparse
import importlib.util
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch

from sdfcodec.data.sequences import open_sequence
from sdfcodec.tracking.densefield import DenseField
from sdfcodec.evaluation.tracking import EVAL_TRACKER_CONFIG, benchmark_tracking, resolve_sequence
from sdfcodec.map import open_map
from sdfcodec.tracking.mapfield import MapField
from sdfcodec.core.metrics import ate
from sdfcodec.tracking.tracker import SDFTracker, TrackerConfig

PRESETS = ("slow-clean", "slow-noisy", "fast-clean", "fast-noisy", "poor-geometry", "rich-geometry")


def cli(*args: str) -> None:
    exe = str(Path(sys.executable).parent / "sdfcodec")
    subprocess.run([exe, *args, "--json"], check=True, stdout=subprocess.DEVNULL)


def maps_for(seq_dir: str, work: Path, name: str, pca: bool) -> dict[str, Path]:
    raw = work / f"{name}.sdfz"
    if not raw.exists():
        cli("fuse", seq_dir, str(raw))
    out = {"lossless": raw}
    if pca:
        out["pca-64"] = work / f"{name}-pca64.sdfz"
        if not out["pca-64"].exists():
            cli("encode", str(raw), str(out["pca-64"]), "--codec", "pca", "--code-size", "64")
    return out


def track_all(field, seq, depths, cfg) -> tuple[np.ndarray, np.ndarray, int]:
    k = seq.intrinsics
    poses, times, fails = [], [], 0
    with SDFTracker(field, (k.fx, k.fy, k.cx, k.cy), cfg) as tracker:
        for i, depth in enumerate(depths):
            if i == 0:
                guess = seq.poses[0]
            elif len(poses) >= 2:  # constant velocity, as sdfcodec track
                guess = poses[-1] @ (np.linalg.inv(poses[-2]) @ poses[-1])
            else:
                guess = poses[-1]
            t0 = time.perf_counter()
            res = tracker.track(depth, guess)
            times.append(time.perf_counter() - t0)
            fails += not res.success
            poses.append(np.asarray(res.pose, dtype=np.float64))
    return np.stack(poses), np.asarray(times), fails


def record(name: str, map_name: str, field_kind: str, seq, depths, field, startup_s: float) -> dict:
    cfg = TrackerConfig(**EVAL_TRACKER_CONFIG)
    load0 = [round(x, 2) for x in os.getloadavg()]
    poses, times, fails = track_all(field, seq, depths, cfg)
    err = ate(seq.poses, poses)
    q = lambda t: [float(x) for x in np.percentile(t, [25, 50, 75])]
    r = {"sequence": name, "map": map_name, "field": field_kind, "frames": len(depths),
         "image": [seq.intrinsics.width, seq.intrinsics.height], "startup_s": startup_s,
         "frame_s_quartiles": q(times), "fps_median": 1 / float(np.median(times)),
         "fps_median_first200": 1 / float(np.median(times[:200])), "fps_mean": len(times) / float(times.sum()),
         "first_frame_s": float(times[0]), "failures": fails, "ate_rmse_m": float(err.rmse),
         "ate_max_m": float(err.max), "torch_threads": torch.get_num_threads(), "load_before": load0,
         "load_after": [round(x, 2) for x in os.getloadavg()]}
    print(json.dumps({k: r[k] for k in ("sequence", "map", "field", "fps_median", "ate_rmse_m", "failures",
                                        "load_before")}), flush=True)
    return r


def load_old(src: Path):
    """The tracking and densefield modules of the package folder ``src``, imported as ``sdfcodec_old``."""
    spec = importlib.util.spec_from_file_location("sdfcodec_old", src / "__init__.py",
                                                  submodule_search_locations=[str(src)])
    pkg = importlib.util.module_from_spec(spec)
    sys.modules["sdfcodec_old"] = pkg  # the package's own __init__ is not run: only the two modules are needed
    import importlib as il
    return il.import_module("sdfcodec_old.tracking"), il.import_module("sdfcodec_old.densefield")


def old_map_field(src: Path) -> type:
    """This checkout's MapField with the ``sample_with_gradient`` of the MapField in the package folder ``src``
    (its source compiled in this ``sdfcodec.tracking.mapfield``'s namespace)."""
    import ast
    import sdfcodec.tracking.mapfield as mf

    text = (src / "mapfield.py").read_text()
    cls = next(n for n in ast.parse(text).body if isinstance(n, ast.ClassDef) and n.name == "MapField")
    fn = next(n for n in cls.body if isinstance(n, ast.FunctionDef) and n.name == "sample_with_gradient")
    ns = dict(vars(mf))
    exec(compile(ast.Module([fn], []), str(src / "mapfield.py"), "exec"), ns)
    return type("OldMapField", (MapField,), {"sample_with_gradient": ns["sample_with_gradient"]})


def ab(old_src: Path, kitchen: str, path: Path, frames: int, field: str = "dense") -> dict:
    ot, od = load_old(old_src)
    seq = open_sequence(kitchen)[:frames]
    depths = [seq[i].depth for i in range(len(seq))]
    m = open_map(path)
    k = seq.intrinsics
    kk = (k.fx, k.fy, k.cx, k.cy)
    if field == "warm":
        fields = {"old": old_map_field(old_src)(m), "new": MapField(m)}
    else:
        vol = m.decode_region()
        fields = {"old": od.DenseField(vol, m.voxel_size, m.origin, m.truncation),
                  "new": DenseField(vol, m.voxel_size, m.origin, m.truncation)}
    trackers = {"old": ot.SDFTracker(fields["old"], kk, ot.TrackerConfig(**EVAL_TRACKER_CONFIG)),
                "new": SDFTracker(fields["new"], kk, TrackerConfig(**EVAL_TRACKER_CONFIG))}
    if field == "warm":  # one untimed pass: every block the frames touch decoded and cached
        for name, tr in trackers.items():
            pose = seq.poses[0]
            for depth in depths:
                pose = tr.track(depth, pose).pose
    st = {n: {"poses": [], "wall": [], "cpu": []} for n in trackers}
    load0 = [round(x, 2) for x in os.getloadavg()]
    for i, depth in enumerate(depths):
        for name in (("old", "new") if i % 2 == 0 else ("new", "old")):
            s = st[name]
            p = s["poses"]
            guess = seq.poses[0] if i == 0 else (p[-1] if len(p) < 2 else p[-1] @ np.linalg.inv(p[-2]) @ p[-1])
            c0, t0 = time.process_time(), time.perf_counter()
            res = trackers[name].track(depth, guess)
            s["wall"].append(time.perf_counter() - t0)
            s["cpu"].append(time.process_time() - c0)
            p.append(np.asarray(res.pose, dtype=np.float64))
    out = {"frames": len(depths), "field": field, "map": path.name, "torch_threads": torch.get_num_threads(),
           "load_before": load0,
           "load_after": [round(x, 2) for x in os.getloadavg()]}
    for name, s in st.items():
        out[name] = {"ate_rmse_m": float(ate(seq.poses, np.stack(s["poses"])).rmse),
                     "fps_median": 1 / float(np.median(s["wall"])),
                     "cpu_s_per_frame_median": float(np.median(s["cpu"]))}
    out["speedup_paired_median"] = float(np.median(np.array(st["old"]["wall"]) / np.array(st["new"]["wall"])))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--kitchen", default=os.environ.get("SDFCODEC_KITCHEN"),
                    help="a 7-Scenes redkitchen sequence folder (default: $SDFCODEC_KITCHEN)")
    ap.add_argument("--work", type=Path, required=True, help="where the maps and rendered sequences are kept")
    ap.add_argument("--out", type=Path, help="JSON file to write")
    ap.add_argument("--only", default="kitchen,synthetic", help="kitchen, synthetic or both")
    ap.add_argument("--threads", type=int, default=None, help="torch.set_num_threads (default: torch's)")
    ap.add_argument("--label", default="", help="what was measured (e.g. the commit), stored in the JSON")
    ap.add_argument("--ab", type=Path, help="the sdfcodec package folder of an older checkout to compare with")
    ap.add_argument("--ab-field", choices=("dense", "warm"), default="dense",
                    help="--ab against a dense field (default) or each checkout's warm MapField")
    ap.add_argument("--ab-map", choices=("lossless", "pca-64"), default="lossless", help="the kitchen map of --ab")
    ap.add_argument("--bench", type=Path, help="write benchmark_tracking of the kitchen maps here instead")
    ap.add_argument("--lazy-frames", type=int, default=200, help="frames of the warm MapField runs")
    ap.add_argument("--tracker", type=Path, help="the sdfcodec package folder of a checkout whose tracker and "
                    "dense field to measure instead of this one's (sequence mode)")
    a = ap.parse_args()
    if a.tracker:
        global SDFTracker, TrackerConfig, DenseField
        ot, od = load_old(a.tracker)
        SDFTracker, TrackerConfig, DenseField = ot.SDFTracker, ot.TrackerConfig, od.DenseField
    if a.threads:
        torch.set_num_threads(a.threads)
    a.work.mkdir(parents=True, exist_ok=True)
    if a.ab:
        if not a.kitchen:
            ap.error("give the kitchen sequence with --kitchen DIR or $SDFCODEC_KITCHEN")
        doc = {"command": f"docs/results/tracking_measure.py --ab OLD --ab-field {a.ab_field} --ab-map {a.ab_map} "
                          f"--lazy-frames {a.lazy_frames}", "label": a.label,
               **ab(a.ab, a.kitchen, maps_for(a.kitchen, a.work, "redkitchen", a.ab_map == "pca-64")[a.ab_map],
                    a.lazy_frames, a.ab_field)}
        print(json.dumps(doc), flush=True)
        if a.out:
            a.out.write_text(json.dumps(doc, indent=1))
        return
    if a.bench:
        if not a.kitchen:
            ap.error("give the kitchen sequence with --kitchen DIR or $SDFCODEC_KITCHEN")
        maps = maps_for(a.kitchen, a.work, "redkitchen", True)
        doc = {"command": f"benchmark_tracking(MAP, KITCHEN, frames={a.lazy_frames})",
               "load_before": list(os.getloadavg()), "label": a.label}
        for key, name in (("raw", "lossless"), ("pca64", "pca-64")):
            doc[key] = benchmark_tracking(maps[name], a.kitchen, frames=a.lazy_frames)
            print(key, json.dumps({k: v for k, v in doc[key].items() if "cache" not in k}), flush=True)
        doc["load_after"] = list(os.getloadavg())
        a.bench.write_text(json.dumps(doc, indent=1))
        return
    records = []
    todo = []
    if "kitchen" in a.only:
        if not a.kitchen:
            ap.error("give the kitchen sequence with --kitchen DIR or $SDFCODEC_KITCHEN")
        todo.append(("redkitchen", a.kitchen, True))
    if "synthetic" in a.only:
        todo += [(p, str(resolve_sequence(f"synthetic:{p}", a.work / "sequences")), False) for p in PRESETS]
    for name, seq_dir, is_kitchen in todo:
        seq = open_sequence(seq_dir)
        depths = [seq[i].depth for i in range(len(seq))]
        for map_name, path in maps_for(seq_dir, a.work, name, is_kitchen).items():
            t0 = time.perf_counter()
            m = open_map(path)
            dense = DenseField(m.decode_region(), m.voxel_size, m.origin, m.truncation)
            records.append(record(name, map_name, "dense", seq, depths, dense, time.perf_counter() - t0))
            del dense
            if is_kitchen:  # the lazily decoded map, warmed by one pass over the sequence first
                t0 = time.perf_counter()
                lazy = MapField(open_map(path))
                sub, few = seq[:a.lazy_frames], depths[:a.lazy_frames]
                track_all(lazy, sub, few, TrackerConfig(**EVAL_TRACKER_CONFIG))
                records.append(record(name, map_name, "mapfield-warm", sub, few, lazy, time.perf_counter() - t0))
    doc = {"command": f"docs/results/tracking_measure.py --kitchen KITCHEN --work WORK --only {a.only}"
                      + (" --tracker OLD" if a.tracker else ""),
           "label": a.label, "cpus": os.cpu_count(), "records": records}
    if a.out:
        a.out.write_text(json.dumps(doc, indent=1))


if __name__ == "__main__":
    main()
