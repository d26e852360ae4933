"""Ego-motion on compressed maps: ``sdfcodec track`` and ``sdfcodec eval`` (paper section IV-C, Table 1).

:func:`track_command` tracks a depth sequence against any map (decoded lazily through
:class:`~sdfcodec.tracking.mapfield.MapField`, or densely) and writes a TUM trajectory. :func:`eval_command` runs the
whole of Table 1: for each sequence it fuses the ground-truth map from the ground-truth poses, writes it
losslessly (the ``raw`` codec: "Original data", the reference of every comparison), compresses and decompresses
it with each method, measures the reconstruction error over the non-empty (coded) blocks and the surface metrics
against the lossless map (:func:`sdfcodec.core.surface.compare_volumes`, band restricted to the observed voxels),
tracks the sequence from the ground-truth start pose in the decoded map, and reports the ATE and its ratio to
the lossless map's; then it aggregates across sequences (mean +- std among sequences), writes ``eval.json``, a
Markdown table in the paper's layout and the pictures.

Sequences are given as a path (TUM RGB-D or 7-Scenes layout, see :func:`sdfcodec.data.sequences.open_sequence`;
e.g. the paper's ``rgbd_dataset_freiburg1_teddy``) or as ``synthetic:<preset>`` (rendered on the fly by
:func:`sdfcodec.data.render.render_sequence`, presets in :data:`sdfcodec.data.render.PRESETS`).

Units: reconstruction errors are in normalised units ``v = (d - d_min) / (d_max - d_min)`` (what codecs see);
``mse`` is the mean squared error per voxel, ``block_sse`` the sum of squared errors per block (16^3 voxels),
averaged over blocks. ATE in metres, without alignment (the tracker starts in the map's frame). Surface metrics
(:data:`SURFACE_FIELDS`) in metres or fractions, ``null`` in JSON where not finite (no surface on one side).
"""

from __future__ import annotations

import json
import math
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np
import torch

from ..core._validate import BLOCK, check_device
from ..errors import InvalidValueError
from ..core.header import BlockState

__all__ = [
    "METHODS",
    "DEFAULT_METHODS",
    "EVAL_TRACKER_CONFIG",
    "Method",
    "track_command",
    "eval_command",
    "benchmark_tracking",
    "build_codec",
    "resolve_sequence",
    "markdown_table",
    "SURFACE_FIELDS",
]


@dataclass(frozen=True)
class Method:
    """One row of Table 1: ``name`` (as printed), ``codec`` (registry id or "original"), ``kwargs``."""

    key: str
    label: str
    codec: str
    size: int | None = None


#: the rows of the paper's Table 1, in order
METHODS: dict[str, Method] = {m.key: m for m in [
    Method("original", "Original data", "raw"),
    Method("pca-32", "PCA 32", "pca", 32),
    Method("pca-64", "PCA 64", "pca", 64),
    Method("pca-128", "PCA 128", "pca", 128),
    Method("ae-32", "NN 32", "ae", 32),
    Method("ae-64", "NN 64", "ae", 64),
    Method("ae-128", "NN 128", "ae", 128),
    Method("parallel-64-64", "Parallel PCA 64+NN 64", "parallel", 64),
    Method("sequential-64-64", "Sequential PCA 64+NN 64", "sequential", 64),
    Method("blur-9", "Gaussian Blur 9x9x9", "gaussian-blur", None),
]}
DEFAULT_METHODS = tuple(METHODS)
#: tracker settings of ``track`` and ``eval`` (sdfcodec.tracking.tracker.TrackerConfig fields). Why not the defaults:
#: - ``max_final_update=None``: as the original SDF Tracker, a frame that has not settled after the last
#:   level keeps its estimate (failing it would restart the next frame from the prediction);
#: - ``plateau_margin=0.02``: fused maps hold values a little below ``d_max`` in free space (averaged
#:   observations, noise); with the default 2 mm margin those points pull the pose away. Measured on 60-frame
#:   presets at 320x240 against the original map (mean ATE): slow-clean 3.3 cm at 2 mm (20 frames) -> 0.13 cm
#:   at 1 cm; fast-clean 1.23 -> 0.20 cm and slow-noisy 2.92 -> 0.94 cm going from 1 cm to 2 cm; 3 cm is
#:   better on fast-noisy but worse on slow-noisy;
#: - ``constant_velocity=True``: the camera moves smoothly; predicting the next pose keeps it in the basin.
EVAL_TRACKER_CONFIG: dict[str, Any] = {"max_final_update": None, "plateau_margin": 0.02, "constant_velocity": True}
#: the :class:`sdfcodec.core.surface.SurfaceMetrics` fields stored per method (against the lossless map)
SURFACE_FIELDS = ("chamfer_l1", "f_score_1", "f_score_2", "sign_agreement", "near_surface_rmse", "near_surface_bias")
PAPER_SEQUENCES = ("freiburg1_teddy", "freiburg1_room", "freiburg1_desk", "freiburg1_desk2", "freiburg1_360",
                   "freiburg1_plant")


def build_codec(method: Method, model: str | Path | None = None):
    """The fitted codec of a Table 1 row: the model file ``model`` when given (e.g. an ae-32 trained with
    ``sdfcodec train``), else the shipped model; raises with the reason when it is not available."""
    from ..registry import get_codec, pretrained_codec

    if model is not None:
        from ..model import load_model

        codec = load_model(model)
        if codec.codec_id != method.codec or codec.code_size not in (method.size, 2 * method.size + 1,
                                                                     2 * method.size):
            raise InvalidValueError(f"model {model} is a {codec!r}, not the {method.key} of this row")
        return codec

    if method.codec == "raw":
        return get_codec("raw")
    if method.codec == "gaussian-blur":
        return get_codec("gaussian-blur", size=9, sigma=4.0 / 3.0)
    if method.codec in ("pca", "ae"):
        return pretrained_codec(method.codec, method.size)  # shipped in the plugin (optional for ae)
    if method.codec in ("parallel", "sequential"):
        return pretrained_codec(method.codec)  # the shipped 64 + 64
    raise InvalidValueError(f"unknown method codec {method.codec!r}")


# ------------------------------------------------------------------------------------------------ sequences
def resolve_sequence(spec: str, work_dir: Path, *, frames: int | None = None, size: tuple[int, int] | None = None,
                     seed: int = 0) -> Path:
    """A sequence folder for ``spec``: a path as is, or ``synthetic:<preset>`` rendered into ``work_dir``
    (``frames`` frames at ``size = (width, height)``; re-used when already rendered with the same settings)."""
    if not spec.startswith("synthetic:"):
        p = Path(spec)
        if not p.is_dir():
            raise InvalidValueError(f"sequence {spec!r} is neither a directory nor 'synthetic:<preset>'")
        return p
    from ..data.render import DEFAULT_INTRINSICS, PRESETS, render_sequence

    preset = spec.split(":", 1)[1]
    if preset not in PRESETS:
        raise InvalidValueError(f"unknown synthetic preset {preset!r}; one of {sorted(PRESETS)}")
    intr = DEFAULT_INTRINSICS
    if size is not None:
        w, h = size
        s = w / intr.width
        intr = type(intr)(intr.fx * s, intr.fy * s, (w - 1) / 2, (h - 1) / 2, w, h)
    n = frames or PRESETS[preset].frames
    out = work_dir / f"{preset}-{n}f-{intr.width}x{intr.height}-s{seed}"
    if not (out / "depth.txt").is_file():
        render_sequence(out, preset, seed, frames=n, intrinsics=intr, overwrite=True)
    return out


def _open(path: Path, frames: int | None, stride: int):
    from ..data.sequences import open_sequence

    seq = open_sequence(path)
    seq = seq[::stride]
    if frames is not None:
        seq = seq[:frames]
    return seq


# ------------------------------------------------------------------------------------------------- tracking
def _progress(enabled: Any):
    if callable(enabled):  # the caller's own progress display (the CLI's: a line every ~10 s on a pipe)
        return enabled()
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    return Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(),
                    TextColumn("{task.fields[fps]:.1f} frames/s"), TimeRemainingColumn(), disable=not enabled,
                    transient=True)


def _track(field, seq, start_pose: np.ndarray, *, config=None, progress: bool = False, label: str = "tracking",
           times: list | None = None) -> tuple[np.ndarray, list, float]:
    """Track the frames of ``seq`` in ``field`` from ``start_pose``; ``(poses (N,4,4), results, seconds)``;
    each frame's ``track`` seconds are appended to ``times`` when given."""
    from ..tracking.tracker import SDFTracker, TrackerConfig

    k = seq.intrinsics
    tracker = SDFTracker(field, (k.fx, k.fy, k.cx, k.cy), config or TrackerConfig(**EVAL_TRACKER_CONFIG))
    poses: list[np.ndarray] = []
    results = []
    t_track = 0.0
    with tracker, _progress(progress) as bar:
        task = bar.add_task(label, total=len(seq), fps=0.0)
        for i in range(len(seq)):
            depth = seq[i].depth
            if i == 0:
                guess = start_pose
            elif len(poses) >= 2 and tracker.config.constant_velocity:
                guess = poses[-1] @ (np.linalg.inv(poses[-2]) @ poses[-1])
            else:
                guess = poses[-1]
            t0 = time.perf_counter()
            res = tracker.track(depth, guess)
            dt = time.perf_counter() - t0
            t_track += dt
            if times is not None:
                times.append(dt)
            poses.append(np.asarray(res.pose, dtype=np.float64))
            results.append(res)
            bar.update(task, advance=1, fps=(i + 1) / max(t_track, 1e-9))
    return np.stack(poses), results, t_track


def _ate(seq, poses: np.ndarray) -> dict[str, Any] | None:
    from ..core.metrics import ate
    from ..core.trajectory import Trajectory

    gt = seq.poses
    ok = np.isfinite(gt).all(axis=(1, 2))
    if not ok.any():
        return None
    st = ate(Trajectory.from_poses(gt[ok]), Trajectory.from_poses(poses[ok]))
    out = st.as_dict()
    out["errors"] = st.errors.tolist()
    return out


def _rpe(seq, poses: np.ndarray) -> dict[str, Any] | None:
    """Frame-to-frame translational RPE (metres) over consecutive frames that both have ground truth."""
    from ..core.metrics import rpe
    from ..core.trajectory import Trajectory

    gt = seq.poses
    ok = np.isfinite(gt).all(axis=(1, 2))
    if ok.sum() < 2:
        return None
    return rpe(Trajectory.from_poses(gt[ok]), Trajectory.from_poses(poses[ok]), delta=1).as_dict()


def track_command(map_path: str | Path, sequence: str | Path, output: str | Path, *, level: int | None = None,
                  device: str | None = None, cache_mb: float = 256.0, dense: bool = False,
                  start: str = "groundtruth", frames: int | None = None, stride: int = 1,
                  progress: Any = True) -> dict[str, Any]:
    """Track a depth sequence against a map and write the trajectory (``sdfcodec track``).

    Parameters
    ----------
    map_path : str or Path
        Any map (raw, pca, ae...; path or URL).
    sequence : str or Path
        TUM RGB-D or 7-Scenes folder, or ``synthetic:<preset>``.
    output : str or Path
        TUM trajectory to write (``timestamp tx ty tz qx qy qz qw``; overwritten).
    level : int, optional
        Decode only the first ``level`` code elements (prefix-ordered codecs).
    device : str, optional
        ``"cpu"`` (default) or ``"cuda"``.
    cache_mb : float
        Bound of the decoded-block cache in MiB (lazy decoding).
    dense : bool
        Decode the whole map up front instead (:class:`~sdfcodec.tracking.densefield.DenseField`).
    start : {"groundtruth", "identity"}
        Start pose: the first frame's ground truth (as the paper does; falls back to identity with no
        ground truth) or the identity.
    frames, stride : optional
        Track only every ``stride``-th frame, at most ``frames`` of them.
    progress : bool or callable
        Show a progress bar with frames/s; a callable returns the progress display to use (the CLI's).

    Returns
    -------
    dict
        ``output, frames, seconds`` (tracking only), ``frames_per_s`` (frames over seconds),
        ``frames_per_s_median`` (one over the median frame time), ``startup_s`` (opening the map and, with
        ``dense``, decoding it: apart from the frames), ``failures, ate`` and ``rpe`` (frame-to-frame
        translation; both metres, when the sequence has ground truth; ``None`` otherwise), ``cache``
        (MapField statistics; ``None`` when dense).
    """
    from ..data.sequences import open_sequence
    from ..tracking.mapfield import MapField
    from ..map import open_map
    from ..core.trajectory import Trajectory, write_tum
    from ..tracking.densefield import DenseField

    if start not in ("groundtruth", "identity"):
        raise InvalidValueError(f"start must be 'groundtruth' or 'identity', got {start!r}")
    if not (isinstance(stride, int) and stride >= 1):
        raise InvalidValueError(f"stride must be an int >= 1, got {stride!r}")
    # checked before the sequence is rendered or read: --frames -1 once silently dropped the last frame (a
    # Python slice), --frames 0 and --cache-mb nan ended in tracebacks after minutes of work
    if frames is not None and not (isinstance(frames, int) and frames >= 1):
        raise InvalidValueError(f"frames must be a whole number >= 1 (the first N frames; leave it out for all), "
                                f"got {frames!r}")
    if not (isinstance(cache_mb, (int, float)) and math.isfinite(cache_mb) and cache_mb > 0):
        raise InvalidValueError(f"cache_mb (--cache-mb) must be a positive number of MiB, got {cache_mb!r}")
    if device is not None:
        check_device(device, "device (--device)")
    path = resolve_sequence(str(sequence), Path(output).parent / ".sdfcodec-sequences")
    seq = open_sequence(path, missing_pose="keep")[::stride]
    if frames is not None:
        seq = seq[:frames]
    t0 = time.perf_counter()
    m = open_map(map_path)
    if dense:
        field = DenseField(m.decode_region(level=level, device=device), m.voxel_size, m.origin, m.truncation,
                           device=device)
    else:
        field = MapField(m, level=level, device=device, cache_bytes=int(cache_mb * 2**20))
    startup = time.perf_counter() - t0
    p0 = seq.entries[0].pose
    start_pose = p0 if (start == "groundtruth" and p0 is not None) else np.eye(4)
    times: list[float] = []
    poses, results, secs = _track(field, seq, start_pose, progress=progress, label=f"tracking {Path(path).name}",
                                  times=times)
    write_tum(output, Trajectory.from_poses(poses, seq.timestamps),
              header=f"sdfcodec track {map_path} {sequence}")
    return {"output": str(output), "frames": len(seq), "seconds": secs, "frames_per_s": len(seq) / max(secs, 1e-9),
            "frames_per_s_median": 1 / max(float(np.median(times)), 1e-9), "startup_s": startup,
            "failures": [i for i, r in enumerate(results) if not r.success],
            "start": "groundtruth" if start_pose is p0 else "identity",
            "ate": _ate(seq, poses), "rpe": _rpe(seq, poses), "cache": None if dense else field.stats()}


def benchmark_tracking(map_path: str | Path, sequence: str | Path, *, frames: int = 30, level: int | None = None,
                       cache_mb: float = 256.0, threads: int | None = None) -> dict[str, Any]:
    """Tracker frames/s against one map, dense and lazily decoded (the issue's speed benchmark).

    Tracks the first ``frames`` frames of ``sequence`` from ground truth (each frame predicted by constant
    velocity, as ``sdfcodec track``) three times: against :class:`~sdfcodec.tracking.densefield.DenseField` on the
    map's dense decode, against a fresh :class:`~sdfcodec.tracking.mapfield.MapField` (cold: every block decoded on
    first touch) and against the same MapField again (warm cache). Only ``SDFTracker.track`` is timed, frame
    by frame; start-up (opening the map and decoding it whole) is reported apart.

    Returns
    -------
    dict
        ``{"image": [W, H], "frames", "dense_fps", "lazy_cold_fps", "lazy_warm_fps"`` (frames over the summed
        per-frame times), ``"dense_fps_median", "lazy_cold_fps_median", "lazy_warm_fps_median"`` (one over the
        median per-frame time), ``"warm_over_dense"`` (time ratio, lower is better), ``"ate_m"`` (dense,
        warm: ATE RMSE against the ground truth), ``"cache_cold", "cache_warm"`` (MapField.stats()),
        ``"startup_s"`` (open + dense decode), ``"dense_decode_s"`` (the decode alone), ``"threads"``,
        ``"load"`` (1-minute load average before and after)}``.
    """
    from ..data.sequences import open_sequence
    from ..tracking.mapfield import MapField
    from ..map import open_map
    from ..tracking.densefield import DenseField
    from ..tracking.tracker import TrackerConfig

    seq = open_sequence(resolve_sequence(str(sequence), Path(".sdfcodec-sequences")))[:frames]
    gt = seq.poses
    k = seq.intrinsics
    cfg = TrackerConfig(**EVAL_TRACKER_CONFIG, threads=threads)
    load0 = os.getloadavg()[0]

    def run(field) -> tuple[float, float, float]:
        """(summed seconds, median seconds per frame, ATE RMSE metres)."""
        times: list[float] = []
        poses, _, secs = _track(field, seq, gt[0], config=cfg, times=times)
        return secs, float(np.median(times)), float(_ate(seq, poses)["rmse"])

    t0 = time.perf_counter()
    m = open_map(map_path)
    t1 = time.perf_counter()
    dense = DenseField(m.decode_region(level=level), m.voxel_size, m.origin, m.truncation)
    t2 = time.perf_counter()
    t_dense, med_dense, ate_dense = run(dense)
    del dense
    lazy = MapField(m, level=level, cache_bytes=int(cache_mb * 2**20))
    t_cold, med_cold, _ = run(lazy)
    cold = lazy.stats()
    lazy.reset_stats()
    t_warm, med_warm, ate_warm = run(lazy)
    n = len(seq)
    return {"image": [k.width, k.height], "frames": n, "dense_fps": n / t_dense, "lazy_cold_fps": n / t_cold,
            "lazy_warm_fps": n / t_warm, "dense_fps_median": 1 / med_dense, "lazy_cold_fps_median": 1 / med_cold,
            "lazy_warm_fps_median": 1 / med_warm, "warm_over_dense": t_warm / t_dense,
            "ate_m": {"dense": ate_dense, "warm": ate_warm}, "cache_cold": cold, "cache_warm": lazy.stats(),
            "startup_s": t2 - t0, "dense_decode_s": t2 - t1, "threads": cfg.threads or torch.get_num_threads(),
            "load": [load0, os.getloadavg()[0]]}


# --------------------------------------------------------------------------------------------------- eval
def _blocks_of(vol: np.ndarray, coords: np.ndarray) -> np.ndarray:
    """Blocks ``(N, 16, 16, 16)`` at block indices ``coords`` of a dense volume (padded to whole blocks)."""
    pad = [(0, -n % BLOCK) for n in vol.shape]
    if any(p for _, p in pad):
        vol = np.pad(vol, pad, constant_values=np.float32(vol.max()))
    v = vol.reshape(vol.shape[0] // BLOCK, BLOCK, vol.shape[1] // BLOCK, BLOCK, vol.shape[2] // BLOCK, BLOCK)
    v = v.transpose(0, 2, 4, 1, 3, 5)
    return v[coords[:, 0], coords[:, 1], coords[:, 2]]


def _roundtrip(codec, fused, work: Path, name: str):
    """Compress the fused blocks into a map ``work/<name>.sdfz`` with ``codec``; returns it opened."""
    from ..map import create_map, open_map

    path = work / f"{name}.sdfz"
    with create_map(path, codec=codec, voxel_size=fused.voxel_size, truncation=fused.truncation,
                    origin=tuple(fused.origin), overwrite=True, tool="sdfcodec eval") as m:
        m.write_blocks(fused.coords, fused.tsdf, observed=fused.weights > 0)
    return open_map(path)


def _observed_volume(fused, shape: tuple[int, ...]) -> np.ndarray:
    """The fused voxels with weight > 0, as a dense ``shape`` bool volume on the map's lattice."""
    grid = [-(-n // BLOCK) for n in shape]
    obs = np.zeros((grid[0], grid[1], grid[2], BLOCK, BLOCK, BLOCK), dtype=bool)
    c = fused.coords
    obs[c[:, 0], c[:, 1], c[:, 2]] = fused.weights > 0
    obs = obs.transpose(0, 3, 1, 4, 2, 5).reshape(grid[0] * BLOCK, grid[1] * BLOCK, grid[2] * BLOCK)
    return obs[: shape[0], : shape[1], : shape[2]]


def _finite(x: float | None) -> float | None:
    """``x`` as a float, ``None`` where it is not finite (JSON has no inf/NaN)."""
    return float(x) if x is not None and np.isfinite(x) else None


def eval_command(sequences: Sequence[str], out_dir: str | Path, *, methods: Sequence[str] | None = None,
                 frames: int | None = 60, stride: int = 1, size: tuple[int, int] | None = (320, 240),
                 voxel_size: float = 0.02, truncation: tuple[float, float] = (-0.04, 0.1),
                 depth_max: float = 4.0, docs_dir: str | Path | None = None, progress: bool = True,
                 log: Callable[[str], None] | None = print,
                 models: dict[str, str | Path] | None = None) -> dict[str, Any]:
    """Table 1 of the paper on ``sequences`` (``sdfcodec eval``).

    Parameters
    ----------
    sequences : list of str
        Sequence folders (TUM RGB-D, 7-Scenes) or ``synthetic:<preset>``.
    out_dir : str or Path
        Working and output folder: rendered sequences, maps, ``eval.json``, ``eval.md``, ``eval/*.png``.
    methods : list of str, optional
        Keys of :data:`METHODS` (default: all ten rows). Unavailable codecs are reported as skipped.
    frames, stride : optional
        Use every ``stride``-th frame, at most ``frames`` of them (``None``: all); synthetic presets are
        rendered with ``frames`` frames.
    size : (width, height), optional
        Image size of rendered synthetic sequences (default 320 x 240).
    voxel_size, truncation, depth_max :
        Fusion settings (metres), the shipped models' 0.02 m and (-0.04, 0.1) m.
    docs_dir : optional
        Also write ``eval.md``, ``eval.json`` and the pictures there (``docs/``).
    progress : bool
        Rich progress bars. ``log``: a function taking status lines (None: quiet).
    models : dict, optional
        Model files for rows by key, e.g. ``{"ae-32": "ae-32.npz"}``, used instead of the shipped models (rows
        with no shipped model, such as ae-32 and ae-128, need one).

    Returns
    -------
    dict
        ``{"sequences": {name: {"frames", "blocks", "methods": {key: {...}}}}, "aggregate": {key: {...}},
        "skipped": {key: reason}, "settings": {...}}``. Per method: reconstruction error (``mse``,
        ``block_sse``), the :data:`SURFACE_FIELDS` against the lossless map, ATE statistics and ``ate_ratio``
        (mean ATE over the lossless map's mean ATE on the same sequence; ``None`` when "original" is not run).
    """
    from ..fusion.tsdf import fuse
    from ..tracking.densefield import DenseField
    from ..registry import get_codec
    from ..core.surface import compare_volumes

    say = log or (lambda s: None)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    keys = list(methods or DEFAULT_METHODS)
    for k in keys:
        if k not in METHODS:
            raise InvalidValueError(f"unknown method {k!r}; one of {list(METHODS)}")
    codecs, skipped = {}, {}
    for k in keys:
        try:
            codecs[k] = build_codec(METHODS[k], (models or {}).get(k))
        except Exception as exc:  # noqa: BLE001 - optional plugins/models: report why, go on
            skipped[k] = f"{type(exc).__name__}: {exc}"
            say(f"skipping {k}: {skipped[k]}")
    results: dict[str, Any] = {"sequences": {}, "skipped": skipped, "settings": {
        "frames": frames, "stride": stride, "size": list(size) if size else None, "voxel_size": voxel_size,
        "truncation": list(truncation), "depth_max": depth_max, "methods": keys,
        "models": {k: str(v) for k, v in (models or {}).items()}}}
    slices: dict[str, dict[str, np.ndarray]] = {}
    for spec in sequences:
        path = resolve_sequence(spec, out / "sequences", frames=frames, size=size)
        seq = _open(path, frames, stride)
        name = spec.split(":", 1)[1] if spec.startswith("synthetic:") else Path(spec).name
        say(f"{name}: fusing {len(seq)} frames")
        fused = fuse(seq, voxel_size=voxel_size, truncation=truncation, depth_max=depth_max, quiet=True)
        work = out / "maps" / name
        work.mkdir(parents=True, exist_ok=True)
        d_min, d_max = truncation
        entry: dict[str, Any] = {"path": str(path), "frames": len(seq), "methods": {}}
        # the reference of every row: the lossless map (its coded blocks are the non-empty ones)
        t_ref = time.perf_counter()
        lossless = _roundtrip(codecs.get("original") or get_codec("raw"), fused, work, "original")
        orig_vol = lossless.decode_region()
        coded = np.argwhere(lossless.block_states() == BlockState.CODED)
        observed = _observed_volume(fused, orig_vol.shape)
        entry["blocks"] = int(len(coded))
        t_ref = time.perf_counter() - t_ref
        for k in keys:
            if k not in codecs:
                continue
            t0 = time.perf_counter()
            m = lossless if k == "original" else _roundtrip(codecs[k], fused, work, k)
            vol = orig_vol if k == "original" else m.decode_region()
            a = (_blocks_of(vol, coded) - d_min) / (d_max - d_min)
            b = (_blocks_of(orig_vol, coded) - d_min) / (d_max - d_min)
            sq = ((a - b) ** 2).reshape(len(coded), -1)
            surf = compare_volumes(orig_vol, vol, voxel_size, origin=m.origin, observed=observed).to_dict()
            field = DenseField(vol, voxel_size, m.origin, truncation)
            poses, res, secs = _track(field, seq, seq.poses[0], progress=progress, label=f"{name} {k}")
            ate = _ate(seq, poses)
            entry["methods"][k] = {
                "mse": float(sq.mean()), "block_sse": float(sq.sum(1).mean()),
                "block_sse_std": float(sq.sum(1).std()),
                **{f: surf[f] for f in SURFACE_FIELDS},
                "ate_mean": ate["mean"], "ate_std": ate["std"], "ate_median": ate["median"],
                "ate_rmse": ate["rmse"], "ate_max": ate["max"], "ate_errors": ate["errors"],
                "failures": sum(not r.success for r in res), "tracking_s": secs,
                "frames_per_s": len(seq) / max(secs, 1e-9), "bytes_on_disk": m.info().get("bytes_on_disk"),
                "seconds": time.perf_counter() - t0 + (t_ref if k == "original" else 0.0)}
            ch = surf["chamfer_l1"]
            say(f"  {k:18s} mse {sq.mean():.5f}  Chamfer {'-' if ch is None else f'{ch * 1000:.2f}'} mm  "
                f"F@1 {surf['f_score_1']:.3f}  ATE mean {ate['mean'] * 100:.2f} cm  median "
                f"{ate['median'] * 100:.2f} cm  ({len(seq) / max(secs, 1e-9):.1f} frames/s)")
            slices.setdefault(name, {})[k] = _slice(vol, voxel_size, m.origin)
        ref = entry["methods"].get("original", {}).get("ate_mean")
        for r in entry["methods"].values():
            r["ate_ratio"] = _finite(r["ate_mean"] / ref) if ref else None
        results["sequences"][name] = entry
    results["aggregate"] = _aggregate(results, keys)
    from ..core._atomic import write_file  # each output whole or not at all; a refused write names its file

    text = json.dumps(results, indent=1)
    write_file(out / "eval.json", lambda tmp: tmp.write_text(text), "writing the results")
    figs = _figures(results, slices, out / "eval", truncation)
    md = markdown_table(results)
    write_file(out / "eval.md", lambda tmp: tmp.write_text(md), "writing the results")
    results["figures"] = [str(f) for f in figs]
    if docs_dir is not None:
        import shutil

        d = Path(docs_dir)
        text = json.dumps(results, indent=1)
        write_file(d / "eval.json", lambda tmp: tmp.write_text(text), "writing the results")
        for f in figs:
            write_file(d / "eval" / Path(f).name, lambda tmp, f=f: shutil.copy(f, tmp), "copying the figure")
    return results


def _slice(vol: np.ndarray, voxel_size: float, origin) -> np.ndarray:
    """A horizontal slice (z = 0.5 m above the map origin's z, clamped) for Fig. 5."""
    k = int(np.clip(round(0.5 / voxel_size), 0, vol.shape[2] - 1))
    return vol[:, :, k].copy()


#: the per-method fields that :func:`_aggregate` averages over sequences
AGGREGATED = ("mse", "block_sse", "ate_mean", "ate_median", "ate_ratio") + SURFACE_FIELDS


def _aggregate(results: dict, keys: list[str]) -> dict[str, Any]:
    """Mean and population std among sequences of each :data:`AGGREGATED` field; ``None`` where a sequence has
    no finite value (e.g. no surface on one side: Chamfer-L1 inf)."""
    agg = {}
    for k in keys:
        rows = [s["methods"][k] for s in results["sequences"].values() if k in s["methods"]]
        if not rows:
            continue
        col = {f: np.array([np.nan if r.get(f) is None else r[f] for r in rows], dtype=np.float64)
               for f in AGGREGATED}
        agg[k] = {f"{f}_mean": _finite(v.mean()) for f, v in col.items()}
        agg[k].update({f"{f}_std": _finite(v.std()) for f, v in col.items()})
        agg[k]["sequences"] = len(rows)
    return agg


def _fmt(x: float | None, spec: str, scale: float = 1.0) -> str:
    """``x * scale`` formatted with ``spec``; ``-`` for None (not finite)."""
    return "-" if x is None else f"{x * scale:{spec}}"


def markdown_table(results: dict) -> str:
    """Table 1 in the paper's layout: method, reconstruction error (per-block SSE, normalised) +- sigma among
    sequences, mean ATE +- sigma among sequences, median ATE, then the surface metrics against the lossless map
    (Chamfer-L1 in mm +- sigma, F-score at one voxel) and the mean ATE over the lossless map's (mean +- sigma of
    the per-sequence ratios); then one table per sequence."""
    lines = ["| Reconstruction Method | Reconstruction Error (block SSE) ± σ | MSE per voxel | Mean ATE [m] ± σ "
             "| Median ATE [m] | Chamfer-L1 [mm] ± σ | F@1 voxel | ATE / lossless ± σ |",
             "|---|---|---|---|---|---|---|---|"]
    agg = results["aggregate"]
    for k, a in agg.items():
        rec = "-" if k in ("original",) else f"{a['block_sse_mean']:.2f} ± {a['block_sse_std']:.2f}"
        mse = "-" if k in ("original",) else f"{a['mse_mean']:.5f}"
        ch = "-" if a["chamfer_l1_mean"] is None else (f"{a['chamfer_l1_mean'] * 1000:.2f} ± "
                                                         f"{a['chamfer_l1_std'] * 1000:.2f}")
        ratio = "-" if a["ate_ratio_mean"] is None else f"{a['ate_ratio_mean']:.2f} ± {a['ate_ratio_std']:.2f}"
        lines.append(f"| {METHODS[k].label} | {rec} | {mse} | {a['ate_mean_mean']:.4f} ± {a['ate_mean_std']:.4f} "
                     f"| {a['ate_median_mean']:.4f} | {ch} | {_fmt(a['f_score_1_mean'], '.3f')} | {ratio} |")
    for k, why in results["skipped"].items():
        lines.append(f"| {METHODS[k].label} | skipped: {why.splitlines()[0][:120]} | | | | | | |")
    out = ["\n".join(lines), ""]
    for name, s in results["sequences"].items():
        rows = [f"**{name}** ({s['frames']} frames, {s.get('blocks', 0)} non-empty blocks)", "",
                "| Method | block SSE | MSE | Chamfer-L1 [mm] | F@1 voxel | ATE mean [m] | ATE std [m] "
                "| ATE median [m] | ATE / lossless | failed frames | frames/s |",
                "|---|---|---|---|---|---|---|---|---|---|---|"]
        for k, r in s["methods"].items():
            rows.append(f"| {METHODS[k].label} | {r['block_sse']:.2f} | {r['mse']:.5f} | "
                        f"{_fmt(r['chamfer_l1'], '.2f', 1000)} | {_fmt(r['f_score_1'], '.3f')} | {r['ate_mean']:.4f} | "
                        f"{r['ate_std']:.4f} | {r['ate_median']:.4f} | {_fmt(r.get('ate_ratio'), '.2f')} | "
                        f"{r['failures']} | {r['frames_per_s']:.1f} |")
        out += ["\n".join(rows), ""]
    return "\n".join(out)


def _figures(results: dict, slices: dict, fig_dir: Path, truncation) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ..core._atomic import write_file

    fig_dir.mkdir(parents=True, exist_ok=True)
    paths = []
    agg = results["aggregate"]
    ks = [k for k in agg if k != "original"]
    if ks:
        fig, ax = plt.subplots(1, 3, figsize=(15, 3.8))
        x = np.arange(len(ks))

        def col(f: str, scale: float = 1.0) -> list[float]:  # None (not finite) plots as no bar
            return [np.nan if agg[k][f] is None else agg[k][f] * scale for k in ks]

        ax[0].bar(x, col("block_sse_mean"), yerr=col("block_sse_std"))
        ax[0].set_ylabel("per-block SSE (normalised)")
        ax[1].bar(x, col("mse_mean"), yerr=col("mse_std"), color="C1")
        ax[1].set_ylabel("MSE per voxel (normalised)")
        ax[2].bar(x, col("chamfer_l1_mean", 1000), yerr=col("chamfer_l1_std", 1000), color="C2")
        ax[2].set_ylabel("Chamfer-L1 vs lossless [mm]")
        ax[2].set_yscale("log")  # the blur's vanished surfaces are two orders above the codecs
        for a in ax:
            a.set_xticks(x, [METHODS[k].label.replace("PCA 64+NN 64", "64+64") for k in ks], rotation=35,
                         ha="right", fontsize=8)
        fig.suptitle("Reconstruction error over non-empty blocks, surface error against the lossless map "
                     "(mean ± std among sequences)")
        fig.tight_layout()
        p = fig_dir / "reconstruction_error.png"
        write_file(p, lambda tmp, fig=fig: fig.savefig(tmp, dpi=110), "writing the figure")
        plt.close(fig)
        paths.append(p)
    for name, s in results["sequences"].items():
        fig, ax = plt.subplots(figsize=(8, 3.8))
        for i, (k, r) in enumerate(s["methods"].items()):
            ax.plot(np.asarray(r["ate_errors"]) * 100, label=METHODS[k].label, lw=1.2,
                    ls="-" if i < 10 else "--")
        ax.set_xlabel("frame")
        ax.set_ylabel("position error [cm]")
        ax.set_yscale("symlog", linthresh=1.0)
        ax.set_title(f"ATE over time: {name}")
        ax.legend(fontsize=7, ncol=2)
        fig.tight_layout()
        p = fig_dir / f"ate_{name}.png"
        write_file(p, lambda tmp, fig=fig: fig.savefig(tmp, dpi=110), "writing the figure")
        plt.close(fig)
        paths.append(p)
    for name, sl in slices.items():
        show = [k for k in ("original", "blur-9", "pca-64", "ae-64", "pca-128") if k in sl][:4]  # the paper's Fig. 5
        if not show:
            continue
        fig, ax = plt.subplots(1, len(show), figsize=(3.2 * len(show), 3.4))
        ax = np.atleast_1d(ax)
        for a, k in zip(ax, show):
            im = a.imshow(sl[k].T, origin="lower", cmap="RdBu", vmin=truncation[0], vmax=truncation[1])
            a.set_title(METHODS[k].label, fontsize=9)
            a.set_xticks([])
            a.set_yticks([])
        fig.colorbar(im, ax=list(ax), shrink=0.8, label="distance [m]")
        fig.suptitle(f"{name}: slice z = 0.5 m through the decoded field (cf. the paper's Fig. 5)", fontsize=9)
        p = fig_dir / f"slice_{name}.png"
        write_file(p, lambda tmp, fig=fig: fig.savefig(tmp, dpi=110), "writing the figure")
        plt.close(fig)
        paths.append(p)
    return paths
