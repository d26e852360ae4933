"""``sdfcodec demo``: the whole pipeline on built-in data, measured, in a few minutes.

1. Render a synthetic RGB-D sequence of a furnished room (exact geometry known), with Kinect-like noise.
2. Fuse it into a lossless ``raw`` map (open3d, 2 cm voxels, truncation [-0.04, 0.1] m).
3. Encode the map with the shipped eigenshapes at 32, 64 and 128 elements, and with the shipped AE-64 when
   the ``ae`` plugin and its model are installed.
4. Measure sizes (codes alone and the whole file on disk, against the dense float32 volume), reconstruction
   errors (against the fused map, and against the exact analytic distance of the room), the surface metrics
   of every map against the fused one (:func:`sdfcodec.core.surface.compare_volumes` with the fused map's
   observation: Chamfer-L1, F-score at 1 and 2 voxels, sign agreement, near-surface RMSE and bias) and
   timings.
5. Search the pca-64 map for floors with the codes alone and expand only the selected blocks; count the
   blocks decoded and the bytes read against the whole map, and score the selection against the room's
   analytic floor.
6. Track part of the sequence with the SDF Tracker against every map: the pca-64 map decoded on demand
   (:class:`~sdfcodec.tracking.mapfield.MapField`), the others decoded densely; report the ATE against ground truth
   beside each map's bytes and surface metrics.
7. Write ``report.md``, ``results.json``, pictures (meshes, a field slice per codec, the floor selection,
   the trajectories against ground truth, error against bytes: :mod:`sdfcodec.demo.pictures`) and, when
   rerun-sdk is installed, ``view.rrd``: a Rerun recording of the pca-64 map, its floor search and the
   tracked trajectory against ground truth (:func:`sdfcodec.view.recording.write_recording`).

Nothing is downloaded; every figure in the report is measured in the run that writes it. Progress bars go to
stderr (rich); each finished stage logs one line.
"""

from __future__ import annotations

import json
import os
import shutil
import threading
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Callable, Iterator

import numpy as np

from ..errors import InvalidValueError, SDFCodecError, UnknownCodecError
from ..map import Map, create_map, open_map
from ..registry import get_codec, pretrained_codec

__all__ = ["run_demo"]

TRUNC = (-0.04, 0.1)
_RANGE = TRUNC[1] - TRUNC[0]


# --------------------------------------------------------------------------------------------- progress
class _Bars:
    """One transient rich progress bar per stage (stderr), and log lines printed above them."""

    def __init__(self, console: Any, enabled: bool, log: Callable[[str], None] | None):
        from rich.progress import (BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn,
                                   TimeRemainingColumn)

        self.progress = Progress(TextColumn("{task.description:<34}"), BarColumn(), MofNCompleteColumn(),
                                 TimeElapsedColumn(), TextColumn("eta"), TimeRemainingColumn(), console=console,
                                 transient=True, disable=not enabled)
        self._log = log
        self.console = console

    def log(self, line: str) -> None:
        if self._log is not None:
            self._log(line)
        else:
            self.progress.console.print(line, highlight=False)

    @contextmanager
    def stage(self, description: str, total: int | None) -> Iterator[Callable[[int], None]]:
        task = self.progress.add_task(description, total=total)
        try:
            yield lambda n=1: self.progress.advance(task, n)
        finally:
            self.progress.remove_task(task)

    def __enter__(self) -> "_Bars":
        self.progress.start()
        return self

    def __exit__(self, *exc: Any) -> None:
        self.progress.stop()


# ------------------------------------------------------------------------------------------------ stages
def _render(bars: _Bars, seq_dir: Path, preset: str, frames: int) -> Path:
    """render_sequence in a thread; the bar counts the depth PNGs as they appear."""
    from ..data.render import render_sequence

    shutil.rmtree(seq_dir / "depth", ignore_errors=True)  # the demo's own folder: stale frames would miscount
    done: dict[str, Any] = {}

    def work() -> None:
        try:
            done["path"] = render_sequence(seq_dir, preset, seed=0, frames=frames, overwrite=True)
        except BaseException as e:  # re-raised in the caller's thread
            done["error"] = e

    thread = threading.Thread(target=work, name="sdfcodec-demo-render", daemon=True)
    with bars.stage(f"rendering {preset}", frames) as advance:
        thread.start()
        seen = 0
        while thread.is_alive():
            thread.join(0.2)
            d = seq_dir / "depth"
            n = sum(1 for _ in d.glob("*.png")) if d.is_dir() else 0
            advance(n - seen)
            seen = n
    if "error" in done:
        raise done["error"]
    return done["path"]


def _transcode(src: Map, path: Path, codec, advance: Callable[[int], None]) -> tuple[Map, float]:
    t0 = time.perf_counter()
    with create_map(path, codec=codec, voxel_size=src.voxel_size, truncation=src.truncation, origin=src.origin,
                    shape_voxels=src.shape_voxels, overwrite=True, tool="sdfcodec demo", source=src.location) as m:
        m.write_map(src, progress=advance)
    return open_map(path), time.perf_counter() - t0


def _shipped_ae() -> tuple[Any, str | None]:
    """The shipped AE-64, or None and why not."""
    from ..evaluation.tracking import METHODS, build_codec

    try:
        return build_codec(METHODS["ae-64"]), None
    except (ImportError, UnknownCodecError) as e:
        return None, f"the `ae` codec plugin is not installed ({e})"
    except SDFCodecError as e:
        return None, f"no shipped AE-64 model ({e})"


def _coded_mask(m: Map) -> np.ndarray:
    """Voxel mask of the map's coded blocks, at the map's voxel shape."""
    s = m.block_states() == 2
    full = s.repeat(16, 0).repeat(16, 1).repeat(16, 2)
    return full[:m.shape_voxels[0], :m.shape_voxels[1], :m.shape_voxels[2]]


def _observed_mask(m: Map) -> np.ndarray:
    """Voxel mask of what the map observed (fusion weights above 0 or its observation mask) in its coded
    blocks, at the map's voxel shape; empty and unobserved blocks are False (they hold no surface)."""
    coords = np.argwhere(m.block_states() == 2)
    nb = m.block_states().shape
    full = np.zeros((nb[0], 16, nb[1], 16, nb[2], 16), bool)
    if len(coords):
        full[coords[:, 0], :, coords[:, 1], :, coords[:, 2], :] = m.read_observed(coords)
    full = full.reshape(nb[0] * 16, nb[1] * 16, nb[2] * 16)
    return full[:m.shape_voxels[0], :m.shape_voxels[1], :m.shape_voxels[2]]


def _floor_truth(scene: Any, m: Map, coords: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The floor blocks a search of ``m`` can be scored against, from the analytic room and the map's observation
    alone (never from search output): three ``(N,)`` bool masks over ``coords`` ``(N, 3)``.

    - floor: the voxels the map observed within half a voxel diagonal of the room's surface are at least half
      floor, and at least ``MIN_OBSERVED_FLOOR`` of them are (``RoomScene.floor_blocks`` with ``observed``); the
      floor slab's underside and floor the camera never saw do not count.
    - clean: floor blocks whose observed surface voxels are at least 90 % floor (not where the floor meets a wall
      or furniture).
    - seam: blocks with no such floor but observed floor within one voxel of their face: a floor on the boundary
      between two layers of blocks, whose zero crossing lies between the two (marching cubes needs both). Either
      block may be said to hold it, so they are left out of precision and recall."""
    from ..data.render import LABELS

    observed = m.read_observed(coords)
    vs = m.voxel_size
    floor = scene.floor_blocks(coords, m.origin, vs, observed=observed)
    within_step = scene.floor_blocks(coords, m.origin, vs, observed=observed, band=vs * (1 + 1e-6))
    frac = scene.block_label_fractions(coords, m.origin, vs, observed=observed)[:, LABELS.index("floor")]
    return floor, floor & (frac >= 0.9), within_step & ~floor


def _stores_mask(m: Map) -> bool:
    """Whether the map stores an observation (fusion weights or a mask)."""
    return any(a is not None for a in m.reader.observation_arrays())


# --------------------------------------------------------------------------------------------------- demo
def run_demo(out: Path, *, voxel_size: float = 0.02, code_sizes=(32, 64, 128), preset: str = "slow-noisy",
             frames: int = 120, track_frames: int = 60, track_stride: int = 2, ae: bool = True,
             progress: bool = True, console: Any = None, log: Callable[[str], None] | None = None) -> dict:
    """Run the demo into ``out``: maps, ``report.md``, ``results.json`` and PNG pictures.

    Parameters
    ----------
    out : Path
        Output folder (created; the demo's own files in it are replaced).
    voxel_size : float
        Metres per voxel of the fused map.
    code_sizes : sequence of int
        PCA code sizes (prefixes of the shipped 128-element eigenshapes); 64 must be among them (it is the
        map that is searched, and tracked against with blocks decoded on demand).
    preset, frames : str, int
        The synthetic sequence (:data:`sdfcodec.data.render.PRESETS`) and its length.
    track_frames, track_stride : int
        Track every ``track_stride``-th rendered frame, at most ``track_frames`` of them, against every map.
    ae : bool
        Also encode with the shipped AE-64 (skipped, with a note in the report, when it is not installed).
    progress : bool
        Show progress bars on ``console`` (default: a rich console on stderr).
    log : callable, optional
        Where the one-line stage summaries go (default: printed on ``console`` above the bars).

    Returns
    -------
    dict
        What ``results.json`` holds.
    """
    from rich.console import Console

    if 64 not in code_sizes:
        raise InvalidValueError("code_sizes must include 64 (the map the demo searches and tracks against)")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    console = console if console is not None else Console(stderr=True)
    load_start = os.getloadavg()
    t_start = time.perf_counter()
    with _Bars(console, progress, log) as bars:
        summary = _run(out, bars, voxel_size=voxel_size, code_sizes=tuple(code_sizes), preset=preset, frames=frames,
                       track_frames=track_frames, track_stride=track_stride, ae=ae, t_start=t_start,
                       load_start=load_start)
    return summary


def _run(out: Path, bars: _Bars, *, voxel_size: float, code_sizes: tuple, preset: str, frames: int,
         track_frames: int, track_stride: int, ae: bool, t_start: float, load_start: tuple) -> dict:
    from ..data.render import RoomScene
    from ..data.sequences import open_sequence
    from ..fusion.tsdf import fuse, mesh_from_blocks
    from ..tracking.mapfield import MapField
    from ..core.metrics import Trajectory, ate
    from ..search.engine import expand, search
    from ..view.search import search_picture
    from ..core.surface import compare_volumes
    from ..tracking.tracker import DenseField, SDFTracker, TrackerConfig
    from ..evaluation.tracking import EVAL_TRACKER_CONFIG
    from .pictures import error_bytes_picture, mesh_figure, slice_picture, trajectory_picture

    timings: dict[str, float] = {}
    log = bars.log

    # 1. render ------------------------------------------------------------------------------------------
    t0 = time.perf_counter()
    seq_dir = _render(bars, out / "sequence", preset, frames)
    timings["render_s"] = time.perf_counter() - t0
    log(f"rendered {frames} frames ({preset}, 320x240) in {timings['render_s']:.1f} s -> {seq_dir}")

    # 2. fuse --------------------------------------------------------------------------------------------
    t0 = time.perf_counter()
    seq = open_sequence(seq_dir)

    def frames_with_bar(advance):
        for f in seq:
            yield f
            advance()

    with bars.stage("fusing (open3d)", len(seq)) as advance:
        fused = fuse(frames_with_bar(advance), voxel_size=voxel_size, truncation=TRUNC, intrinsics=seq.intrinsics,
                     quiet=True)
    raw_path = out / "room-raw.sdfz"
    with create_map(raw_path, codec=get_codec("raw"), voxel_size=voxel_size, truncation=TRUNC,
                    origin=tuple(fused.origin), overwrite=True, tool="sdfcodec demo", source=str(seq_dir)) as m:
        m.write_blocks(fused.coords, fused.tsdf, weights=fused.weights)
    raw = open_map(raw_path)
    timings["fuse_s"] = time.perf_counter() - t0
    log(f"fused into {len(fused)} blocks in {timings['fuse_s']:.1f} s -> {raw_path}")

    # 3. encode and measure ------------------------------------------------------------------------------
    t0 = time.perf_counter()
    dense_raw = raw.decode_region()
    coded_voxels = _coded_mask(raw)
    # the exact distance of the analytic room, truncated, at observed voxels close to a fused surface (where
    # geometry lives): an independent ground truth for every map, the fused one included
    scene = RoomScene.load(seq_dir / "scene.json")
    near = np.abs(dense_raw) < 0.5 * TRUNC[1]
    near_idx = np.argwhere(near)
    front, behind = near & (dense_raw > 0), near & (dense_raw < 0)
    exact = np.clip(scene(np.asarray(raw.origin) + voxel_size * near_idx), *TRUNC).astype(np.float32)
    timings["exact_sdf_s"] = time.perf_counter() - t0
    counts = raw.count_states()
    coded = counts["coded"]
    dense_bytes = int(np.prod(raw.shape_voxels)) * 4
    raw_info = raw.info()

    def rmse_exact_mm(vol: np.ndarray) -> float:
        return 1000 * float(np.sqrt(np.mean((vol[near] - exact) ** 2)))

    # surfaces against the fused (lossless) map, its unobserved voxels left out of the band
    observed = _observed_mask(raw)
    timings["surface_s"] = 0.0

    def surface(vol: np.ndarray) -> dict:
        t1 = time.perf_counter()
        got = compare_volumes(dense_raw, vol, voxel_size, origin=raw.origin, observed=observed).to_dict()
        timings["surface_s"] += time.perf_counter() - t1
        return got

    rows = [{"map": "raw", "codec": "raw (fused, float32)", "code_size": 4096, "bytes_on_disk": raw_info["bytes_on_disk"],
             "code_bytes": raw_info["bytes_on_disk"] - raw_info["codec_state_bytes"], "codec_state_bytes": raw_info["codec_state_bytes"],
             "encode_s": timings["fuse_s"], "decode_s": None, "mse_vs_fused": 0.0,
             "rmse_near_vs_exact_mm": rmse_exact_mm(dense_raw), "stores_observation": _stores_mask(raw),
             "surface": surface(dense_raw)}]
    fields = {"fused (raw)": dense_raw}
    maps: dict[str, Map] = {"raw": raw}
    codecs: list[tuple[str, Any]] = [(f"pca-{k}", pretrained_codec("pca", k)) for k in code_sizes]
    ae_note = None
    if ae:
        ae_codec, ae_note = _shipped_ae()
        if ae_codec is not None:
            codecs.append(("ae-64", ae_codec))
    else:
        ae_note = "skipped (--no-ae)"
    if ae_note:
        log(f"ae-64: {ae_note}")
    for name, codec in codecs:
        with bars.stage(f"encoding {name}", coded) as advance:
            m, t_enc = _transcode(raw, out / f"room-{name}.sdfz", codec, advance)
        t1 = time.perf_counter()
        dense = m.decode_region()
        t_dec = time.perf_counter() - t1
        info = m.info()
        rows.append({
            "map": name, "codec": info["codec"]["id"], "code_size": m.code_size, "bytes_on_disk": info["bytes_on_disk"],
            "code_bytes": info["bytes_on_disk"] - info["codec_state_bytes"], "codec_state_bytes": info["codec_state_bytes"], "encode_s": t_enc,
            "decode_s": t_dec, "decode_blocks_per_s": coded / t_dec,
            "mse_vs_fused": float(np.mean(((dense[coded_voxels] - dense_raw[coded_voxels]) / _RANGE) ** 2)),
            "rmse_near_vs_exact_mm": rmse_exact_mm(dense),
            # where the error sits: mean decoded-minus-fused within 5 cm in front of / behind fused surfaces
            "bias_front_mm": 1000 * float(np.mean((dense - dense_raw)[front])),
            "bias_behind_mm": 1000 * float(np.mean((dense - dense_raw)[behind])),
            "stores_observation": _stores_mask(m), "surface": surface(dense),
        })
        fields[name] = dense
        maps[name] = m
        r = rows[-1]
        log(f"{name}: codes {dense_bytes / r['code_bytes']:.0f}:1, file {dense_bytes / r['bytes_on_disk']:.0f}:1 against "
            f"dense float32; MSE {r['mse_vs_fused']:.2e} vs fused (in units of the {_RANGE:g} m truncation range), {r['rmse_near_vs_exact_mm']:.1f} mm RMSE vs exact; "
            f"surfaces vs fused: Chamfer-L1 {_mm(r['surface']['chamfer_l1'])}, F@1 {r['surface']['f_score_1']:.3f}; "
            f"encode {t_enc:.1f} s, decode {t_dec:.2f} s")
    timings["encode_s"] = sum(r["encode_s"] for r in rows[1:])

    # 4. search the floors in pca-64, expand only them ----------------------------------------------------
    t0 = time.perf_counter()
    pca64 = open_map(out / "room-pca-64.sdfz")  # a fresh reader: the bytes it reads are all counted
    with bars.stage("searching floors in pca-64", 3) as advance:
        res = search(pca64, "floor", threshold="auto", keep_scores=True, device="cpu")
        advance()
        exp = expand(pca64, res, as_="mesh", device="cpu")
        advance()
        truth, clean, seam = _floor_truth(scene, raw, res.all_coords)  # the fused map's observation
        advance()
    selected = np.zeros(len(res.all_coords), bool)
    sel_keys = {tuple(c) for c in res.coords.tolist()}
    selected[[i for i, c in enumerate(res.all_coords.tolist()) if tuple(c) in sel_keys]] = True
    # one truth, search.metrics.TRUTH["floor"]'s: the floor blocks are the clean ones; a block where the floor meets
    # a wall or furniture is a block of both and counts against precision when selected, as the benchmarks of
    # docs/search.md count it (the floor query's plane check leaves such blocks out by design); seam blocks are
    # neither floor nor not floor, left out (_floor_truth). Blocks at least half floor: reported beside it.
    judged = ~seam
    n_sel = int((selected & judged).sum())
    found, tp_half = int((selected & clean).sum()), int((selected & truth).sum())
    bytes_search = sum(res.stats["bytes_read"].values())
    bytes_expand = sum(exp.stats["bytes_read"].values())
    search_info = {
        "query": res.query.name, "level": res.level, "threshold": res.threshold, "descriptors": len(res.query),
        "coded_blocks": res.stats["blocks_scored"], "selected": len(res),
        "floor_truth": "clean",  # earlier runs: "observed" (precision/recall of blocks at least half floor)
        "floor_blocks_truth": int(clean.sum()), "true_positives": found,
        "precision": found / max(n_sel, 1), "recall": found / max(int(clean.sum()), 1),
        "seam_blocks": int(seam.sum()), "seam_selected": int((selected & seam).sum()),
        "half_floor_blocks": int(truth.sum()), "half_floor_found": tp_half,
        "precision_half_floor": tp_half / max(n_sel, 1), "recall_half_floor": tp_half / max(int(truth.sum()), 1),
        "search_seconds": res.stats["seconds"], "expand_seconds": exp.stats["seconds"],
        "blocks_decoded": exp.stats["blocks_decoded"], "search_bytes_read": res.stats["bytes_read"],
        "expand_bytes_read": exp.stats["bytes_read"], "bytes_read_total": bytes_search + bytes_expand,
        "map_bytes_on_disk": pca64.info()["bytes_on_disk"], "code_bytes_full": res.stats["code_bytes_full"],
        "triangles": len(exp.mesh.triangles),
        # the selection is not "score <= threshold": the map-level stage and the plane check change it (the report
        # says so beside the threshold sweep, which counts scores alone)
        "scored_under_threshold": int((res.all_scores <= res.threshold).sum()),
        "threshold_method": (res.stats.get("threshold_info") or {}).get("method"),
        # the same scores at other thresholds: the precision/recall trade-off, with no further reads
        "pr_at": [{"threshold": th, "selected": int((res.all_scores <= th).sum()),
                   "precision": float(((res.all_scores <= th) & clean).sum()
                                      / max(int(((res.all_scores <= th) & judged).sum()), 1)),
                   "recall": float(((res.all_scores <= th) & clean).sum() / max(int(clean.sum()), 1))}
                  for th in sorted({round(float(res.threshold) * f, 1) for f in (0.5, 1, 2, 4, 8)})],
    }
    timings["search_s"] = time.perf_counter() - t0
    log(f"floor search: {len(res)} of {coded} blocks selected (precision {search_info['precision']:.2f}, recall "
        f"{search_info['recall']:.2f} against the {int(clean.sum())} floor blocks), {exp.stats['blocks_decoded']} "
        "decoded; read "
        f"{res.stats['bytes_read'].get('codes', 0) / 1024:.0f} KiB of codes to search and "
        f"{bytes_expand / 1024:.0f} KiB to expand (map: {search_info['map_bytes_on_disk'] / 1024:.0f} KiB on disk, "
        f"{res.stats['bytes_read'].get('codec', 0) / 1024:.0f} KiB of it the basis)")

    # 5. track against the original and the compressed map -----------------------------------------------
    t0 = time.perf_counter()
    tseq = open_sequence(seq_dir)[::track_stride][:track_frames]
    gt = tseq.poses
    with bars.stage("reading depth frames", len(tseq)) as advance:
        depths = []
        for f in tseq:
            depths.append(f.depth)
            advance()
    k = tseq.intrinsics
    cfg = TrackerConfig(**EVAL_TRACKER_CONFIG)
    # every map: pca-64 with blocks decoded on demand into a bounded cache (what a robot would run), the
    # others from their dense decodes (cheaper on a small room; the same field values)
    tracks: dict[str, dict] = {}
    for name in maps:
        if name == "pca-64":
            label, field = "pca-64, decoded on demand", MapField(pca64, cache_bytes=64 << 20)
        else:
            label = f"{name} (dense)" if name != "raw" else "raw, the fused map (dense)"
            field = DenseField(fields["fused (raw)" if name == "raw" else name], voxel_size, raw.origin,
                               raw.truncation)
        with bars.stage(f"tracking against {name}", len(depths)) as advance:
            def bar_depths():
                for d in depths:
                    yield d
                    advance()

            t1 = time.perf_counter()
            with SDFTracker(field, (k.fx, k.fy, k.cx, k.cy), cfg) as tracker:
                tracked = tracker.track_sequence(bar_depths(), gt[0])
            secs = time.perf_counter() - t1
        st = ate(Trajectory.from_poses(gt), Trajectory.from_poses(tracked.poses))
        tracks[name] = {"label": label, "poses": tracked.poses, "errors": st.errors.tolist(),
                        "frame_index": (np.arange(len(depths)) * track_stride).tolist(),
                        "ate_rmse": float(st.rmse), "ate_mean": float(st.mean), "ate_max": float(st.max),
                        "failures": tracked.failures, "seconds": secs, "frames_per_s": len(depths) / secs,
                        "cache": field.stats() if isinstance(field, MapField) else None}
        next(r for r in rows if r["map"] == name)["ate_rmse"] = float(st.rmse)
        log(f"tracked {len(depths)} frames against {label}: ATE RMSE {1000 * st.rmse:.1f} mm, "
            f"{len(depths) / secs:.1f} frames/s, {len(tracked.failures)} failed")
    timings["track_s"] = time.perf_counter() - t0

    # 6. pictures ----------------------------------------------------------------------------------------
    t0 = time.perf_counter()
    pics: dict[str, str] = {}
    meshes: dict[str, Any] = {}
    with bars.stage("drawing pictures", 6) as advance:
        for name in ("raw", "pca-64"):
            m = maps[name]
            cs, bs = zip(*m.iter_blocks())
            meshes[name] = mesh_from_blocks(np.concatenate(cs), np.concatenate(bs), origin=m.origin,
                                            voxel_size=m.voxel_size, truncation=m.truncation)
            pics[f"mesh-{name}"] = mesh_figure(m, out / f"mesh-{name}.png", title=_mesh_title(
                next(r for r in rows if r["map"] == name)), mesh=meshes[name]).name
            advance()
        z = min(max(int(round((1.0 - raw.origin[2]) / voxel_size)), 0), raw.shape_voxels[2] - 1)
        slice_picture(fields, z, raw.origin[2] + z * voxel_size, out / "slice.png", origin=raw.origin,
                      voxel_size=voxel_size, truncation=TRUNC)
        pics["slice"] = "slice.png"
        advance()
        pics["floors"] = search_picture(pca64, res, out / "floors.png", mesh=exp.mesh, device="cpu",
                                        title="floor search in the pca-64 map").name
        advance()
        trajectory_picture(gt, tracks, out / "trajectory.png")
        pics["trajectory"] = "trajectory.png"
        error_bytes_picture(rows, dense_bytes, out / "error-vs-bytes.png")
        pics["error_vs_bytes"] = "error-vs-bytes.png"
        advance()
        view_note = _write_view(out / "view.rrd", pca64, res, tracks["pca-64"]["poses"], gt, meshes["pca-64"])
        if view_note is None:
            pics["view"] = "view.rrd"
        advance()
    timings["pictures_s"] = time.perf_counter() - t0
    timings["total_s"] = time.perf_counter() - t_start

    # 7. report ------------------------------------------------------------------------------------------
    machine = {"cpus": os.cpu_count(), "load_avg_1min_start": load_start[0], "load_avg_1min_end": os.getloadavg()[0]}
    summary = {"preset": preset, "frames": frames, "voxel_size": voxel_size, "shape_voxels": list(raw.shape_voxels),
               "coded_blocks": coded, "empty_blocks": counts["empty"], "dense_float32_bytes": dense_bytes,
               "timings": timings, "machine": machine, "maps": rows, "ae_note": ae_note, "search": search_info,
               "tracking": {"frames": len(depths), "stride": track_stride, "maps": list(tracks),
                            **{n: {k2: v for k2, v in t.items() if k2 != "poses"} for n, t in tracks.items()}},
               "pictures": pics, "view_note": view_note}
    (out / "results.json").write_text(json.dumps(summary, indent=2))
    (out / "report.md").write_text(_report(summary, raw))
    return summary


def _mesh_title(r: dict) -> str:
    """Which map, its size on disk and its surfaces' Chamfer-L1 against the fused map."""
    sf = r["surface"]
    what = "the fused map (lossless)" if r["map"] == "raw" else f"the {r['map']} map"
    chamfer = "reference" if r["map"] == "raw" else f"Chamfer-L1 {_mm(sf['chamfer_l1'])} vs fused"
    return f"{what}: {_kib(r['bytes_on_disk'])} on disk, {chamfer}"


def _write_view(path: Path, m: Map, res: Any, tracked: np.ndarray, gt: np.ndarray, mesh: Any) -> str | None:
    """The demo's Rerun recording: the pca-64 map, its floor search, the tracked trajectory against ground truth.
    Returns None when written, else why not (rerun-sdk, an optional extra, not installed)."""
    from ..errors import MissingDependencyError
    from ..core.metrics import Trajectory
    from ..view.recording import write_recording

    tmp = path.with_name(f".tmp-{path.name}")
    try:
        write_recording(m, tmp, search_result=res, trajectory=Trajectory.from_poses(tracked),
                        groundtruth=Trajectory.from_poses(gt), mesh=mesh, application_id="sdfcodec-demo")
    except MissingDependencyError as e:
        tmp.unlink(missing_ok=True)
        path.unlink(missing_ok=True)  # a recording from an earlier run would not match this report
        return str(e)
    tmp.replace(path)
    return None


def _kib(n: float | None) -> str:
    return "-" if n is None else f"{n / 1024:,.0f} KiB"


def _mm(metres: float | None, fmt: str = ".2f") -> str:
    """Metres as millimetres; None (a non-finite metric of ``SurfaceMetrics.to_dict``) as "n/a"."""
    return "n/a" if metres is None else f"{1000 * metres:{fmt}} mm"


def _frac(x: float | None) -> str:
    return "n/a" if x is None else f"{x:.3f}"


def _ate_cell(r: dict, base: float | None) -> str:
    a = r.get("ate_rmse")
    if a is None:
        return "-"
    return f"{1000 * a:.1f} mm" + ("" if base is None or r["map"] == "raw" or base <= 0 else f" ({a / base:.1f}x)")


def _selection_sentence(se: dict) -> str:
    """Why the search selected a different number of blocks than scored under its threshold (older results.json
    files lack the fields: then nothing is said)."""
    if "scored_under_threshold" not in se:
        return ""
    how = ("calibrated on this map (it keeps 99 % of simulated clean floor blocks encoded the map's way)"
           if se.get("threshold_method") == "calibrated" else "automatic")
    return (f"The threshold {se['threshold']:.2f} is {how}; {se['scored_under_threshold']} blocks scored at or "
            f"under it, and the map-level stage (the lowest large level of up-facing patches is the floor) and the "
            f"plane check that follows it (docs/search.md) made that {se['selected']}: blocks on the floor plane "
            "join it even over the threshold, blocks under it elsewhere leave.")


def _truth_sentence(se: dict) -> str:
    """What precision and recall count, and their values."""
    edges = se["half_floor_blocks"] - se["floor_blocks_truth"]
    return (
        "Scored against the room's analytic floor as the fused map observed it (a block's surface voxels are its "
        "voxels within half a voxel diagonal of the exact room surface that the map observed: the slab's "
        "underside and floor the camera never saw are not counted, no map holds them). The floor blocks are the "
        f"{se['floor_blocks_truth']} blocks whose observed surface is floor: at least 64 observed floor voxels, "
        ">= 90 % of their observed surface voxels, the truth `search.metrics.TRUTH[\"floor\"]` and the benchmarks "
        "of docs/search.md use. Against them the search has "
        f"**precision {se['precision']:.2f}, recall {se['recall']:.2f}** ({se['true_positives']} found). A block "
        "where the floor meets a wall or furniture holds both, and the `floor` query leaves it out by design (its "
        "plane check keeps blocks whose decoded surface lies >= 90 % on the floor plane); selected, it counts "
        f"against precision. With those {edges} blocks counted as floor too (every block at least half floor, "
        f"{se['half_floor_blocks']}): precision {se['precision_half_floor']:.2f}, recall "
        f"{se['recall_half_floor']:.2f}. Left out of both: {se['seam_blocks']} *seam* blocks ({se['seam_selected']} "
        "of them selected), where the floor lies on the boundary between two layers of blocks, its zero crossing "
        "between the top voxels of the lower block and the bottom ones of the upper, so either may be said to "
        "hold it. The sweep below counts the floor blocks.")


def _looser(se: dict) -> str:
    """A clause on the looser thresholds that found more floor at no loss of precision, if any did."""
    better = [p for p in se["pr_at"] if p["threshold"] > se["threshold"] and p["precision"] >= se["precision"]
              and p["recall"] > se["recall"]]
    if not better:
        return ""
    b = max(better, key=lambda p: p["recall"])
    return (f"; on this fused room a looser one found more floor at no loss of precision ({b['threshold']:g}: "
            f"recall {b['recall']:.2f}, precision {b['precision']:.2f})")


def _report(s: dict, raw: Map) -> str:
    rows, t, se, tr, mc = s["maps"], s["timings"], s["search"], s["tracking"], s["machine"]
    dense = s["dense_float32_bytes"]
    nx, ny, nz = s["shape_voxels"]
    L = [
        "# sdfcodec demo report", "",
        f"A synthetic furnished room rendered as {s['frames']} noisy 320x240 depth frames (`{s['preset']}`), fused at "
        f"{s['voxel_size']} m into {s['coded_blocks']} coded 16^3 blocks ({nx} x {ny} x {nz} voxels, "
        f"{dense / 2**20:.1f} MiB as dense float32), then encoded with the shipped eigenshapes"
        + (" and the shipped AE-64." if any(r["map"] == "ae-64" for r in rows) else "."), "",
        f"Whole run: **{t['total_s']:.0f} s** on {mc['cpus']} CPU cores (1-minute load average "
        f"{mc['load_avg_1min_start']:.1f} at the start, {mc['load_avg_1min_end']:.1f} at the end; other processes "
        "share the machine when it is above the core count).", "",
        "## Compression, surfaces and tracking", "",
        "| map | codes | file on disk | dense : codes | dense : file | MSE vs fused | RMSE vs exact | Chamfer-L1 | "
        "F@1 voxel | F@2 voxels | sign agreement | band RMSE / bias | ATE RMSE |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    base = next((r.get("ate_rmse") for r in rows if r["map"] == "raw"), None)
    for r in rows:
        sf = r["surface"]
        L.append(f"| {r['map']} | {_kib(r['code_bytes'])} | {_kib(r['bytes_on_disk'])} | "
                 f"{dense / r['code_bytes']:.0f} : 1 | {dense / r['bytes_on_disk']:.0f} : 1 | {r['mse_vs_fused']:.2e} | "
                 f"{r['rmse_near_vs_exact_mm']:.1f} mm | {_mm(sf['chamfer_l1'])} | {_frac(sf['f_score_1'])} | "
                 f"{_frac(sf['f_score_2'])} | {_frac(sf['sign_agreement'])} | {_mm(sf['near_surface_rmse'], '.1f')} / "
                 f"{_mm(sf['near_surface_bias'], '+.1f')} | {_ate_cell(r, base)} |")
    pca = [r for r in rows if r["codec"] == "pca"]
    n_orig, n_band = rows[0]["surface"]["n_original"], rows[0]["surface"]["n_band"]
    L += ["", "*codes*: the map on disk without the codec's state (compressed float32 code chunks, block states, "
          "the observation mask, metadata; `ratio_dense_to_codes` of `sdfcodec info`); "
          "*file on disk*: the whole self-contained map directory, codes plus the codec's state "
          + (f"(the {pca[0]['code_size']}-component basis alone is {_kib(pca[0]['codec_state_bytes'])}; in a small "
             "room it dominates the file, in a building it is a fixed cost next to the codes). " if pca else ". ")
          + "*MSE vs fused*: per-voxel squared error over the coded blocks in normalised units "
          "(distance / 0.14 m), the codec's own loss. *RMSE vs exact*: against the analytic distance of the room at "
          "voxels within 5 cm of a fused surface, so it includes the fusion's own error (the raw row). "
          f"*Surfaces* (docs/surface.md), against the fused map's {n_orig:,} surface points (zero crossings along "
          "the grid axes): *Chamfer-L1* is the mean of the two directed mean nearest-neighbour distances, *F@1 "
          f"voxel* / *F@2 voxels* the F-score at {1000 * s['voxel_size']:.0f} / {2000 * s['voxel_size']:.0f} mm; "
          f"*sign agreement* and *band RMSE / bias* (decoded minus fused) are over the {n_band:,} observed voxels "
          f"within {2000 * s['voxel_size']:.0f} mm of the fused surface. *ATE RMSE*: the tracking error of "
          "the next section against the renderer's ground truth (in brackets: against the raw map's).", ""]
    masked = [r["map"] for r in rows[1:] if r.get("stores_observation")]
    lossy = rows[1:]
    if lossy:
        best = min(lossy, key=lambda r: np.inf if r["surface"]["chamfer_l1"] is None else r["surface"]["chamfer_l1"])
        worst = max(lossy, key=lambda r: abs(r["bias_behind_mm"]) + abs(r["bias_front_mm"]))
        L += [f"Closest surfaces: {best['map']} (Chamfer-L1 {_mm(best['surface']['chamfer_l1'])}, F@1 "
              f"{_frac(best['surface']['f_score_1'])} at {_kib(best['bytes_on_disk'])} on disk). Where the error "
              f"sits: averaged over voxels within 5 cm of a fused surface, the largest bias is {worst['map']}'s, "
              f"{worst['bias_behind_mm']:+.1f} mm behind surfaces and {worst['bias_front_mm']:+.1f} mm in front; "
              + ", ".join(f"{r['map']} {r['bias_behind_mm']:+.1f} / {r['bias_front_mm']:+.1f} mm"
                          for r in lossy if r is not worst)
              + " (behind / in front; `bias_behind_mm`, `bias_front_mm` in results.json)."
              + ((" " + ("Every compressed map" if len(masked) == len(lossy) else ", ".join(masked))
                  + " stores the fused map's observation mask: its unobserved voxels decode to d_max, so the step "
                  "from the band behind a surface to unobserved space is no surface, and the PCA codes are fitted "
                  "to the observed voxels only (surface-weighted least squares, docs/surface.md).") if masked else ""),
              ""]
    L += ["Code length and speed (encode: transcoding the fused map into a new map file, for PCA with the "
          "surface-weighted fit; decode: the whole map to a dense volume):", "",
          "| map | code elements | encode | decode |", "|---|---|---|---|"]
    for r in rows:
        dec = f"{r['decode_s']:.2f} s" if r["decode_s"] is not None else "-"
        enc = f"{r['encode_s']:.1f} s" + (" (fusion)" if r["map"] == "raw" else "")
        L.append(f"| {r['map']} | {r['code_size']} | {enc} | {dec} |")
    L.append("")
    if s["ae_note"]:
        L += [f"AE-64: {s['ae_note']}.", ""]
    L += ["![error against bytes](error-vs-bytes.png)", "",
          "A horizontal slice through the field, per map (top), and each decoded map minus the fused one (bottom):",
          "", "![slice](slice.png)", "",
          "The fused map and the pca-64 map, marching cubes of the decoded field:", "",
          "![mesh raw](mesh-raw.png) ![mesh pca-64](mesh-pca-64.png)", "",
          "## Searching the compressed map", "",
          f"The pca-64 map's codes were compared with the built-in `{se['query']}` query ({se['descriptors']} "
          f"descriptors, level {se['level']}, automatic threshold {se['threshold']:.2f}) without decoding anything; "
          f"only the selected blocks were then decoded and meshed.", "",
          "| | blocks | bytes read |", "|---|---|---|",
          f"| whole map | {se['coded_blocks']} coded | {_kib(se['map_bytes_on_disk'])} on disk "
          f"({_kib(se['code_bytes_full'])} of code chunks) |",
          f"| search (codes only) | {se['coded_blocks']} scored, {se['selected']} selected | "
          f"{_kib(sum(se['search_bytes_read'].values()))} (codes {_kib(se['search_bytes_read'].get('codes', 0))}, "
          f"basis {_kib(se['search_bytes_read'].get('codec', 0))}, read once per reader) |",
          f"| expand (selected only) | {se['blocks_decoded']} decoded | {_kib(sum(se['expand_bytes_read'].values()))} |",
          "",
          _truth_sentence(se) + f" Search {se['search_seconds']:.2f} s, "
          f"expansion {se['expand_seconds']:.2f} s ({se['triangles']:,} triangles). "
          + _selection_sentence(se) + " The scores alone at other thresholds (no further reads, no map-level "
          "stage): "
          + "; ".join(f"{p['threshold']:g}: {p['selected']} scored at or under it, precision {p['precision']:.2f}, "
                      f"recall {p['recall']:.2f}" for p in se["pr_at"])
          + _looser(se) + ".", "",
          "![floor selection](floors.png)", "",
          "## Tracking against the compressed map", "",
          f"The SDF Tracker followed {tr['frames']} frames (stride {tr['stride']} through the sequence) from the first "
          "ground-truth pose in every map: the pca-64 map with blocks decoded on demand into a bounded cache, the "
          "others decoded densely. ATE: absolute trajectory error against the renderer's ground truth, no "
          "alignment.", "",
          "| map | ATE RMSE | ATE mean | ATE max | failed frames | frames/s | blocks decoded |",
          "|---|---|---|---|---|---|---|"]
    for name in tr["maps"]:
        x = tr[name]
        dec = "all (dense)" if x["cache"] is None else f"{x['cache']['blocks_decoded']} ({x['cache']['misses']} misses, hit rate {x['cache']['hit_rate']:.3f})"
        L.append(f"| {x['label']} | {1000 * x['ate_rmse']:.1f} mm | {1000 * x['ate_mean']:.1f} mm | "
                 f"{1000 * x['ate_max']:.1f} mm | {len(x['failures'])} | {x['frames_per_s']:.1f} | {dec} |")
    L += ["", "![trajectory](trajectory.png)", "", "## 3-D view", ""]
    if s.get("view_note") is None:
        L += ["[view.rrd](view.rrd) is a Rerun recording of the pca-64 map: its mesh coloured by each block's floor "
              "score, every block's score as a point, the selected blocks as boxes, and the pca-64 tracked "
              "trajectory (blue) against ground truth (green) with each pose's error (red), in metres. Open it "
              "with `rerun view.rrd` (the viewer comes with `pip install 'sdfcodec[view]'`); `sdfcodec view` "
              "writes one for any map.", ""]
    else:
        L += [f"No 3-D recording was written: {s['view_note']}.", ""]
    L += ["## Timings", "",
          "| stage | seconds |", "|---|---|"]
    for key, label in (("render_s", "render"), ("fuse_s", "fuse"), ("exact_sdf_s", "exact distance (reference)"),
                       ("encode_s", "encode (all codecs)"), ("search_s", "search + expand + floor truth"),
                       ("surface_s", "surface metrics (all maps)"), ("track_s", f"tracking ({len(tr['maps'])} maps)"),
                       ("pictures_s", "pictures and the 3-D recording"), ("total_s", "total")):
        L.append(f"| {label} | {t[key]:.1f} |")
    L += ["", "Everything here is measured in the run that wrote this report (`sdfcodec demo`); the numbers are "
          "also in `results.json`.", ""]
    return "\n".join(L)
