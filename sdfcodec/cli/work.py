"""The commands that do work on sequences and data sets: fuse, track, eval, dataset, train, bench, demo."""

from __future__ import annotations

import contextlib
import time
from pathlib import Path
from typing import Any, Optional

import numpy as np
import typer
from .common import reads_maps
from .common import (app, check_code_size, cli, err, fail, heartbeat, live_progress, load_volume,
                     parse_truncation, print_json, print_table, progress_bar, refuse_existing, report, say, working)
from .common import human_bytes, json_option, overwrite_option  # the --json and --overwrite every command shares

__all__: list[str] = []  # commands register on the app; nothing to import from here


@app.command("fuse")
@cli
def fuse_cmd(
    sequence: str = typer.Argument(..., metavar="SEQUENCE", help="TUM RGB-D or 7-Scenes directory."),
    output: Path = typer.Argument(..., metavar="OUTPUT", help="Map to write (e.g. kitchen.sdfz)."),
    voxel_size: float = typer.Option(0.02, "--voxel-size", help="Voxel edge in metres."),
    truncation: str = typer.Option("-0.04,0.1", "--truncation", help="d_min,d_max in metres."),
    depth_max: float = typer.Option(4.0, "--depth-max", help="Ignore depth beyond this (metres)."),
    code_dtype: str = typer.Option("float32", "--code-dtype", help="float32, float16 or int8 storage of the field (int8: per-block offset and scale)."),
    weights: Optional[bool] = typer.Option(None, "--keep-weights/--no-keep-weights", help="Store the per-voxel fusion weights (default: yes with raw, as float16; no with a lossy --codec, whose map keeps only the observation mask; kept there, they are uint8 counts)."),
    codec_id: str = typer.Option("raw", "--codec", help="Codec of the map: raw (lossless), pca (the shipped eigenshapes), or another fitted one."),
    code_size: Optional[int] = typer.Option(None, "--code-size", help="Code length of --codec pca (default 64)."),
    working_set_mb: Optional[float] = typer.Option(None, "--working-set-mb", help="Fuse online: at most this many MiB of dense blocks in memory, the rest paged out into the map (32 KiB a block)."),
    overwrite: bool = overwrite_option(),
    as_json: bool = json_option(),
    # the older spelling, still taken; hidden so that the options column stays narrow (at 80 columns all four
    # names truncated the column and squeezed every option's help)
    weights_alias: Optional[bool] = typer.Option(None, "--weights/--no-weights", hidden=True,
                                                 help="Same as --keep-weights/--no-keep-weights."),
) -> None:
    """Fuse a posed depth sequence (Curless-Levoy, open3d VoxelBlockGrid) into a map (lossless `raw` by default).

    SEQUENCE may be synthetic:PRESET (e.g. synthetic:building). With --working-set-mb the fusion is online and
    memory-bounded (sdfcodec.fusion.online): blocks leave the working set into the map, encoded with --codec, and come
    back when the camera returns. Otherwise transcode afterwards with `sdfcodec encode OUTPUT SMALLER.sdfz`.
    """
    trunc = parse_truncation(truncation)  # before open3d and torch load: a reversed range is refused at once
    if weights is not None and weights_alias is not None and weights != weights_alias:
        fail("--keep-weights and --no-weights (or the reverse) contradict each other: pass one")
    weights = weights if weights is not None else weights_alias
    refuse_existing(output, overwrite, map_output=True)
    from ..evaluation.tracking import resolve_sequence
    from ..fusion.tsdf import fuse
    from ..map import create_map
    from ..fusion.online import fusion_codec, fuse_to_map

    sequence = str(resolve_sequence(sequence, Path(output).parent / ".sdfcodec-sequences"))
    codec = fusion_codec(codec_id, code_size)
    if working_set_mb is not None:
        with heartbeat(f"fusing {sequence} online", as_json):
            summary = fuse_to_map(sequence, output, codec=codec, working_set_mb=working_set_mb, keep_weights=weights,
                                  voxel_size=voxel_size, truncation=trunc, depth_max=depth_max, code_dtype=code_dtype,
                                  overwrite=overwrite, quiet=as_json or not live_progress())
        report(summary, as_json, lambda: (
            f"wrote {output}: {summary['frames_integrated']} frames ({summary['frames_per_s']:.1f} frames/s), "
            f"{summary['blocks']['coded']} coded blocks; paged out {summary['blocks_paged_out']}, in "
            f"{summary['blocks_paged_in']}; peak working set {summary['peak_working_set_blocks']} blocks "
            f"({summary['peak_working_set_mib']:.0f} MiB), peak RSS {summary['peak_rss_mib']:.0f} MiB"))
        return
    # fusion draws its own bar (frames done of all) on a terminal; without one, the CLI's lines count the frames
    with (contextlib.nullcontext() if live_progress() or as_json else progress_bar("frames")) as prog:
        task = None if prog is None else prog.add_task(f"fusing {sequence}", total=None, rate="")
        fused = fuse(sequence, voxel_size=voxel_size, truncation=trunc, depth_max=depth_max,
                     quiet=as_json or not live_progress(),
                     progress=None if prog is None else (lambda total: prog.update(task, advance=1, total=total)))
    with create_map(output, codec=codec, voxel_size=voxel_size, truncation=trunc,
                    origin=tuple(fused.origin), code_dtype=code_dtype, overwrite=overwrite, tool="sdfcodec fuse", up=fused.up,
                    source=str(sequence), keep_weights=weights) as m:
        # weights the map would drop at commit are not written at all
        keep = weights if weights is not None else codec.codec_id == "raw"
        m.write_blocks(fused.coords, fused.tsdf, **({"weights": fused.weights} if keep else {"observed": fused.weights > 0}))
    info = m.info()
    summary = {"output": str(output), "frames_integrated": fused.frames_integrated,
               "frames_skipped": fused.frames_skipped, "allocated_blocks": len(fused), "blocks": info["blocks"],
               "fusion_seconds": fused.seconds, "frames_per_s": fused.frames_integrated / max(fused.seconds, 1e-9),
               "bytes_on_disk": info["bytes_on_disk"]}
    skipped = f", {fused.frames_skipped} skipped" if fused.frames_skipped else ""  # e.g. no pose: said, not silent
    report(summary, as_json, lambda: (
        f"wrote {output}: {fused.frames_integrated} frames{skipped} ({summary['frames_per_s']:.0f} frames/s) at "
        f"{voxel_size:g} m voxels, truncation [{trunc[0]:g}, {trunc[1]:g}] m; {len(fused)} allocated blocks "
        f"({info['blocks']['coded']} coded, {info['blocks']['empty']} empty), {human_bytes(info['bytes_on_disk'])} "
        + ("with the fusion weights" if keep else "with the observation mask")))


@app.command("track")
@cli
@reads_maps
def track_cmd(
    map_path: str = typer.Argument(..., metavar="MAP", help="Map path or URL."),
    sequence: str = typer.Argument(..., metavar="SEQUENCE", help="TUM RGB-D or 7-Scenes directory."),
    output: Path = typer.Option(..., "-o", "--output", help="TUM-format trajectory to write."),
    level: Optional[int] = typer.Option(None, "--level", help="Decode only the first K code elements."),
    device: Optional[str] = typer.Option(None, "--device", help="Torch device."),
    cache_mb: float = typer.Option(256.0, "--cache-mb", help="Decoded-block cache bound (MiB)."),
    dense: bool = typer.Option(False, "--dense", help="Decode the whole map first instead of on demand."),
    start: str = typer.Option("groundtruth", "--start", help="Start pose: groundtruth (the paper) or identity."),
    frames: Optional[int] = typer.Option(None, "--frames", help="Track only the first N frames."),
    stride: int = typer.Option(1, "--stride", help="Use every K-th frame."),
    overwrite: bool = overwrite_option("OUTPUT"),
    as_json: bool = json_option(),
) -> None:
    """Track a depth sequence against a (compressed) map from the ground-truth start pose; write TUM poses."""
    refuse_existing(output, overwrite)  # before the sequence is read and the map opened
    from ..evaluation.tracking import track_command

    summary = track_command(map_path, sequence, output, level=level, device=device, cache_mb=cache_mb, dense=dense,
                            start=start, frames=frames, stride=stride,
                            progress=False if as_json else (lambda: progress_bar("frames")))
    report(summary, as_json, lambda: _track_sentence(summary, map_path, sequence))


_START_WORDS = {"groundtruth": "ground-truth first pose", "identity": "identity pose (--start identity)"}


def _track_sentence(s: dict[str, Any], map_path: str, sequence: str) -> str:
    """``sdfcodec track``'s summary: frames, ATE/RPE against the ground truth when there is one, speed, file."""
    text = f"tracked {s['frames']} frames of {sequence} in {map_path} ({s['frames_per_s']:.1f} frames/s, " \
           f"{s['seconds']:.1f} s, from the {_START_WORDS.get(s['start'], s['start'])})"
    if s.get("failures"):
        text += f", {len(s['failures'])} frame(s) lost"
    if s.get("ate"):
        text += f": ATE RMSE {1000 * s['ate']['rmse']:.1f} mm (max {1000 * s['ate']['max']:.1f} mm)"
        if s.get("rpe"):
            text += f", RPE {1000 * s['rpe']['rmse']:.2f} mm/frame"
        text += " against the ground truth"
    else:
        text += ": no ground truth in the sequence, so no ATE"
    return text + f"; wrote {s['output']}"


@app.command("eval")
@cli
@reads_maps
def eval_cmd(
    sequences: list[str] = typer.Argument(..., metavar="SEQUENCE...",
                                          help="synthetic:PRESET (e.g. synthetic:fast-noisy) or a sequence folder."),
    out_dir: Path = typer.Option(Path("eval-out"), "-o", "--out", help="Results JSON, table and pictures go here."),
    methods: Optional[str] = typer.Option(None, "--methods", help="Comma-separated (default: all of Table 1)."),
    frames: int = typer.Option(60, "--frames", help="Frames per sequence (0: all)."),
    stride: int = typer.Option(1, "--stride", help="Use every K-th frame."),
    size: str = typer.Option("320x240", "--size", help="Image size of rendered synthetic sequences, WxH."),
    voxel_size: float = typer.Option(0.02, "--voxel-size", help="Voxel edge in metres."),
    docs_dir: Optional[Path] = typer.Option(None, "--docs", help="Also write eval.md/eval.json/eval/ here."),
    model: list[str] = typer.Option([], "--model", metavar="KEY=FILE",
                                    help="Model file for a row, e.g. ae-32=ae-32.npz (repeatable)."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace the results of an earlier run in --out "
                                   "(and --docs)."),
    as_json: bool = json_option(),
) -> None:
    """Reproduce the paper's Table 1: reconstruction error and tracking ATE per compression method."""
    refuse_existing(out_dir, overwrite, files=("eval.json", "eval.md"))
    if docs_dir is not None:
        refuse_existing(docs_dir, overwrite, files=("eval.json", "eval.md"))
    from ..evaluation.tracking import eval_command, markdown_table

    if any("=" not in m for m in model):
        fail(f"--model must look like ae-32=ae-32.npz, got {[m for m in model if '=' not in m]}")
    models = dict(m.split("=", 1) for m in model)

    try:
        wh = tuple(int(v) for v in size.lower().split("x"))
        assert len(wh) == 2
    except (ValueError, AssertionError):
        fail(f"--size must look like 320x240, got {size!r}")
    with heartbeat("evaluating", as_json):
        results = eval_command(sequences, out_dir, methods=methods.split(",") if methods else None,
                               frames=frames or None, stride=stride, size=wh, voxel_size=voxel_size,
                               docs_dir=docs_dir, progress=not as_json,
                               log=None if as_json else (lambda s_: err.print(s_, highlight=False)), models=models)
    report(results, as_json, lambda: markdown_table(results))


@app.command("dataset")
@cli
def dataset_cmd(
    output: Path = typer.Argument(..., metavar="OUTPUT", help="Data set to write (a Zarr directory)."),
    synthetic: int = typer.Option(0, "--synthetic", help="Number of synthetic primitive blocks."),
    sequence: list[str] = typer.Option([], "--sequence", help="RGB-D sequence (TUM or 7-Scenes) to fuse and sample."),
    map_paths: list[str] = typer.Option([], "--map", help="Map to decode and sample."),
    volume: list[Path] = typer.Option([], "--volume", help="Dense .npy TSDF (metres) to sample."),
    voxel_size: float = typer.Option(0.02, "--voxel-size", help="Voxel edge (synthetic blocks, fusion)."),
    truncation: str = typer.Option("-0.04,0.1", "--truncation", help="d_min,d_max in metres."),
    stride: int = typer.Option(8, "--stride", help="Sub-volume stride in voxels (the paper: 8)."),
    max_mean: float = typer.Option(0.85, "--max-mean", help="Drop windows whose normalised mean is above this."),
    empty_fraction: float = typer.Option(0.02, "--empty-fraction", help="Share of dropped windows kept anyway."),
    batch_size: int = typer.Option(500, "--batch-size", help="Blocks per batch (the paper: 500)."),
    seed: int = typer.Option(0, "--seed", help="Seed of the sampling and the split."),
    overwrite: bool = overwrite_option(),
    as_json: bool = json_option(),
) -> None:
    """Build a training data set: synthetic blocks plus sub-volumes of real maps, split 300:50:50 by batches."""
    trunc = parse_truncation(truncation)
    refuse_existing(output, overwrite, directory=True)  # build_dataset replaces only a data set
    from ..data.sampler import iter_windows
    from ..data.synthetic import synthetic_blocks
    from ..core.dataset import build_dataset
    from ..map import open_map

    window_kw = dict(stride=stride, truncation=trunc, max_mean=max_mean, empty_fraction=empty_fraction, seed=seed)

    def synth(n: int):
        for i in range(0, n, 10_000):  # chunks of 10k keep memory flat and the bar moving
            yield synthetic_blocks(min(10_000, n - i), seed=seed + i, voxel_size=voxel_size, truncation=trunc)

    def fused(path: str):
        from ..fusion.tsdf import fuse

        yield from iter_windows(fuse(path, voxel_size=voxel_size, truncation=trunc, quiet=True).to_dense(),
                                **window_kw)

    sources = ([("synthetic", synth(synthetic))] if synthetic else []) \
        + [(f"sequence:{p}", fused(p)) for p in sequence] \
        + [(f"map:{p}", iter_windows(open_map(p).decode_region(), **window_kw)) for p in map_paths] \
        + [(f"volume:{p}", iter_windows(load_volume(p, None)[0], **window_kw)) for p in volume]
    if not sources:
        fail("give at least one source: --synthetic N, --sequence PATH, --map MAP or --volume X.npy")
    with progress_bar() as prog:
        task = prog.add_task("collecting blocks", total=None, rate="")
        ds = build_dataset(output, sources, batch_size=batch_size, seed=seed, voxel_size=voxel_size,
                           truncation=trunc, overwrite=overwrite, progress=lambda n: prog.advance(task, n))
    if as_json:
        print_json(ds.meta)
    else:
        say(f"wrote {output}: {ds.meta['splits']} blocks from {ds.meta['sources']}")


@app.command("train")
@cli
def train_cmd(
    dataset: Path = typer.Argument(..., metavar="DATASET", help="Data set from `sdfcodec dataset`."),
    output: Path = typer.Option(..., "-o", "--output", help="Model file to write (.npz)."),
    codec_id: str = typer.Option("pca", "--codec", help="Codec id."),
    code_size: Optional[int] = typer.Option(None, "--code-size", help="Code length."),
    max_memory_gb: float = typer.Option(4.0, "--max-memory-gb",
                                        help="Train in memory below this; stream the data set above it."),
    overwrite: bool = overwrite_option("--output"),
    as_json: bool = json_option(),
) -> None:
    """Train a codec on a data set and save it as a model (.npz of plain arrays); report validation/test error."""
    from ..core.dataset import open_dataset
    from ..model import save_model
    from ..registry import get_codec

    if code_size is not None:  # 0 or -1 is an error, never the default
        code_size = check_code_size(codec_id, code_size)
    refuse_existing(output, overwrite)
    ds = open_dataset(dataset)
    codec = get_codec(codec_id, **({"code_size": code_size} if code_size else {}))
    n = ds.split("train").shape[0]
    t0 = time.perf_counter()
    with progress_bar() as prog:
        if n * 4096 * 4 <= max_memory_gb * 2**30:
            prog.add_task(f"fitting {codec!r} on {n} blocks (in memory)", total=None, rate="")
            codec.fit(ds.load("train"))
        else:
            task = prog.add_task(f"fitting {codec!r} on {n} blocks (streamed)", total=n, rate="")

            def batches():
                for b in ds.iter_batches("train"):
                    prog.advance(task, len(b))
                    yield b

            codec.fit_stream(batches())
    seconds = time.perf_counter() - t0
    save_model(codec, output)
    result: dict[str, Any] = {"model": str(output), "codec": codec.get_config(), "train_blocks": n,
                              "fit_seconds": seconds}
    for split in ("validation", "test"):
        sq, count = 0.0, 0
        for b in ds.iter_batches(split):
            err2 = (codec.decode(codec.encode(b)) - b) ** 2
            sq += float(err2.sum(dtype=np.float64))
            count += len(b)
        result[split] = {"blocks": count, "mse_voxel": sq / (count * 4096), "sse_block": sq / count}
    report(result, as_json, lambda: (
        f"wrote {output} ({codec!r}, {n} blocks, {seconds:.1f} s): validation MSE/voxel "
        f"{result['validation']['mse_voxel']:.3e}, test {result['test']['mse_voxel']:.3e}"))


@app.command("bench")
@cli
def bench_cmd(
    codec_id: str = typer.Option("pca", "--codec", help="Codec to measure."),
    sizes: Optional[str] = typer.Option(None, "--sizes", help="Code sizes (default 32,64,128; --quick: 64)."),
    batches: Optional[str] = typer.Option(None, "--batches", help="Batch sizes (default 1..65536 by x4; --quick: "
                                          "1,64,256)."),
    device: str = typer.Option("cpu", "--device", help="Torch device."),
    quick: bool = typer.Option(False, "--quick", help="Fewer, smaller measurements, the same kinds of figures: "
                               "code size 64, batches 1, 64, 256, a 4,096-block map, 3 rounds (under a minute "
                               "on 2 cores)."),
    read: Optional[int] = typer.Option(None, "--read", help="Blocks in the map timed for decode-on-read "
                                       "(default 65536, --quick 4096; 0: skip)."),
    http: bool = typer.Option(True, "--http/--no-http", help="Also time decode-on-read over HTTP (loopback)."),
    search: bool = typer.Option(True, "--search/--no-search", help="Also time the descriptor search kernel "
                                "(pca only: search scores pca codes)."),
    as_json: bool = typer.Option(False, "--json", help="Print records as JSON."),
    repeats: Optional[int] = typer.Option(None, "--repeats", min=1, help="Equal rounds per figure, each "
                                          "interleaved with its baselines (best and median reported; default 5, "
                                          "--quick 3)."),
    out: Optional[Path] = typer.Option(None, "--out", help="Write the run (machine, load, command, records) as one "
                                       "JSON document (--full: default bench-DEVICE.json)."),
    full: bool = typer.Option(False, "--full", help="The device check instead: pca decode (fp32/bf16/fp16) beside "
                              "the GEMM roofline and a device copy, decode on read into the device, search scoring, "
                              "tracking (sdfcodec.bench.cases); with --quick tiny sizes."),
    cases: Optional[str] = typer.Option(None, "--cases", help="--full: the cases to run (default all: "
                                        "pca-decode, decode-on-read, search, tracking)."),
    compare: Optional[tuple[Path, Path]] = typer.Option(None, "--compare", help="Compare two run files (A B, from "
                                                        "--out) instead: how far every ratio agrees."),
    tolerance: float = typer.Option(0.15, "--tolerance", help="--compare: the disagreement counted as agreeing."),
    threads: Optional[int] = typer.Option(None, "--threads", min=1, help="Threads for torch and numpy's BLAS "
                                          "(default: as configured; 1 measures steadier on a loaded machine)."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace the --out file if it exists."),
) -> None:
    """Encode/decode throughput (blocks/s) beside numpy matrix products of the codec's shapes, same run.

    Every figure is timed interleaved with its baselines in --repeats equal rounds; blocks/s and ratios are
    medians (JSON: also the bests, ratio_of_bests), and the load average before and after is recorded.

    Decode-on-read times a whole map read and decoded to float32 metres by Map.iter_decoded, from local disk
    and over HTTP from a server on loopback, beside the same roofline, the memory-copy bandwidth of this
    machine (as blocks/s of 16 KiB) and the codec's decode of the same codes in memory (JSON:
    memcpy_blocks_per_s, in_memory_decode_blocks_per_s). Decoding into place is timed beside the decode product
    into a preallocated output, in the same --repeats rounds: decode-on-read-into
    (iter_decoded(copy=False)), decode-on-read-fresh (the default copy=True), decode-region (the whole map into
    a fresh volume), decode-region-into (into one reused volume, out=) and decode-into (decode_core(..., out=)
    in batches of 4096). For pca, the search kernel (15 floor descriptors)
    is timed beside a numpy product of its shape. Tracking is benchmarked by `sdfcodec eval` instead (it needs
    a sequence and a map of it). Every record has speedup_vs_paper (405 and 645 us/block over ours).

    The baseline is the codec's "roofline": one (B,4096)x(4096,k) product for a linear codec (pca), or the
    layer shapes a codec declares (ae, parallel, sequential; see sdfcodec.bench). Those are timed with the
    shipped weights where they exist (ae-64, parallel/sequential 64+64), else untrained ones; for the
    mixtures --sizes is the size of each part (64: code 64+64+1).
    """
    from ..bench.harness import limit_threads

    if compare and all(compare):
        return _bench_compare(compare, tolerance, as_json)
    repeats = repeats or (3 if quick else 5)
    sizes = sizes or ("64" if quick else "32,64,128")
    if full and out is None:
        out = Path(f"bench-{device.replace(':', '-')}.json")
    if out is not None:  # before minutes of measuring
        refuse_existing(out, overwrite)
    with limit_threads(threads):
        if full:
            return _bench_full(device, quick, repeats, out, cases, as_json)
        return _bench_codec(codec_id, sizes, batches, device, quick, read, http, search, as_json, repeats, out)


def _times(x: float) -> str:
    """A speed-up for the bench table: two significant figures below 10 (an encode 40x slower than the paper's
    decode is 0.025x, not "0x"), whole numbers above."""
    return f"{x:.2g}x" if x < 10 else f"{x:,.0f}x"


def _bench_codec(codec_id: str, sizes: str, batches: str | None, device: str, quick: bool, read: int | None,
                 http: bool, search: bool, as_json: bool, repeats: int, out: Path | None) -> None:
    """``sdfcodec bench`` without --full or --compare: a codec's figures (see bench_cmd)."""
    from ..bench import PAPER_US_PER_BLOCK, bench_codec, vs_paper
    from ..bench.codecs import bench_steps

    ks = [int(s) for s in sizes.split(",")]
    bs = [int(b) for b in batches.split(",")] if batches else ([1, 64, 256] if quick else
                                                               [1, 16, 256, 1024, 4096, 16384, 65536])
    n_read = (4096 if quick else 65536) if read is None else read
    if n_read < 0:
        fail(f"--read must be >= 0, got {n_read}")
    do_search = search and codec_id == "pca"
    n_search = 8192 if quick else 65536
    from ..bench.harness import load, run_document

    doc = run_document("quick" if quick else "codec", device)
    t0 = time.perf_counter()
    with progress_bar("steps") as prog:
        # every step counted (the final ones too: decode on read, search, the start-up of `info`), so that the
        # bar and its "about N s left" stay true to the end
        searched = [k for k in ks if 1 <= k <= 128] if do_search else []  # one search kernel step per size
        from ..bench.startup import startup_steps

        total = (bench_steps(codec_id, ks, bs, read_blocks=n_read, http=http) + len(searched)
                 + (startup_steps(repeats) if n_read > 0 else 0))
        task = prog.add_task("bench", total=total, rate="")
        begun: list[str] = []

        def step(what: str) -> None:  # a step is counted done when the next begins: the last one shows as running
            prog.update(task, advance=1 if begun else 0, description=what)
            begun.append(what)

        records = bench_codec(codec_id, ks, bs, device=device, min_time=0.05 if quick else 0.2, progress=step,
                              read_blocks=n_read, http=http, repeats=repeats)
        if do_search:
            from ..bench import bench_search

            found = bench_search(searched, batches=[n_search], device=device,
                                 min_time=0.05 if quick else 0.2, progress=step, repeats=repeats)
            records += [dict(r, **vs_paper(r["us_per_block"])) for r in found]  # the same paper comparison
        if n_read > 0:  # with the map benchmarks: a light command's start-up
            from ..bench.startup import bench_info_startup

            records += bench_info_startup(repeats=repeats, progress=step)
        prog.update(task, advance=1 if begun else 0)
    doc.update(load_after=load(), seconds=round(time.perf_counter() - t0, 1), records=records)
    if out is not None:
        _write_run(out, doc)
    if as_json:
        print_json(records)
        return
    layered = any("roofline_shapes" in r for r in records)  # codecs with benchmark hooks (sdfcodec.bench)
    if layered:
        lines: dict[tuple, str] = {}
        for r in records:
            if "roofline_shapes" not in r:
                continue
            lines.setdefault((r["code_size"], r["operation"]), f"code {r['code_size']} {r['operation']}: " + " + ".join(
                f"(B,{m})x({m},{n})" for m, n in r["roofline_shapes"]))
            if "weights" in r:  # registered codecs: where the timed weights come from
                lines.setdefault((r["code_size"], "weights"), f"code {r['code_size']} weights: {r['weights']}")
        title = f"{codec_id} throughput on {device} (baseline: numpy matmuls of the codec's layer shapes, same run)"
    else:
        lines, title = {}, f"{codec_id} throughput on {device} (baseline: numpy matmul of the same shape, same run)"
    starts = [f"sdfcodec info MAP in a fresh process: {r['seconds_median']:.2f} s median, {r['seconds_best']:.2f} s best "
              f"(the interpreter alone {r['baseline_seconds_median']:.2f} s; target {r['target_seconds']} s)"
              for r in records if r["operation"] == "info-startup"]
    records = [r for r in records if "blocks_per_s" in r]
    reads = [f"{r['operation']} code {r['code_size']}: memory-copy roofline {r['memcpy_blocks_per_s']:,.0f} "
             f"blocks/s (ratio {r['ratio_to_memcpy']:.2f}), in-memory decode {r['in_memory_decode_blocks_per_s']:,.0f} "
             f"blocks/s (ratio {r['ratio_to_in_memory_decode']:.2f})" for r in records if "memcpy_blocks_per_s" in r]
    rows = [(str(r["code_size"]), r["operation"], str(r["batch"]), f"{r['blocks_per_s']:,.0f}",
             f"{r['baseline_blocks_per_s']:,.0f}", f"{r['ratio_to_baseline']:.2f}", f"{r['us_per_block']:.2f}",
             _times(PAPER_US_PER_BLOCK[0] / r["us_per_block"])) for r in records]
    loads = f"load average {doc['load_before'][:1]} before, {doc['load_after'][:1]} after; {repeats} rounds, medians"
    print_table(("code", "op", "batch", "blocks/s", "baseline blocks/s", "ratio", "us/block",
                 f"vs paper's {PAPER_US_PER_BLOCK[0]:g} us/block"), rows,
                title=title, caption="\n".join([*lines.values(), *reads, *starts, loads]), justify="right",
                min_width=120)  # ~120 columns on a terminal; on a pipe tab-separated, never cut


def _write_run(path: Path, doc: dict) -> None:
    import json

    from ..core._atomic import write_file

    text = json.dumps(doc, indent=1, default=str) + "\n"
    write_file(path, lambda tmp: tmp.write_text(text) and None, "writing the benchmark run")


def _bench_full(device: str, quick: bool, repeats: int, out: Path, cases: str | None, as_json: bool) -> None:
    """``sdfcodec bench --full``: the device check (sdfcodec.bench.cases) into one JSON document."""
    from ..bench import run_cases

    with working(f"device check on {device}"):
        doc = run_cases(device, quick=quick, repeats=repeats, cases=cases.split(",") if cases else None,
                        checkpoint=lambda d: _write_run(out, d))  # what is measured survives a later failure
    _write_run(out, doc)
    if as_json:
        print_json(doc)
    if doc["errors"]:
        fail("; ".join(f"case {e['case']} failed: {e['error']}" for e in doc["errors"]) + f" (the rest: {out})")
    if as_json:
        return
    rows = []
    for r in doc["records"]:
        unit = "frames" if "frames_per_s" in r else "blocks"
        what = " ".join(str(r[k]) for k in ("code_size", "dtype", "batch") if k in r)
        rows.append((r["operation"], what, f"{r[unit + '_per_s']:,.0f} {unit}/s",
                     f"{r['baseline_' + unit + '_per_s']:,.0f}", f"{r['ratio_to_baseline']:.2f}",
                     r.get("baseline", "")))
    print_table(("case", "what", "median", "baseline", "ratio", "baseline is"), rows,
                title=f"device check on {device} ({doc['machine'].get('device_name', doc['machine']['processor'])})",
                caption=f"{doc['seconds']} s, load {doc['load_before'][:1]} -> {doc['load_after'][:1]}; JSON: {out}")


def _bench_compare(paths: tuple[Path, Path], tolerance: float, as_json: bool) -> None:
    """``sdfcodec bench --compare A B``: how far every ratio of two runs agrees."""
    from ..bench import compare_runs

    res = compare_runs(*paths, tolerance=tolerance)
    if as_json:
        print_json(res)
        return
    rows = [(" ".join(f"{v}" for v in r["record"].values()), r["ratio"], f"{r['a']:.3f}", f"{r['b']:.3f}",
             f"{100 * r['disagreement']:.1f} %") for r in res["rows"]]
    kinds = "; ".join(f"{k} {v['within']} / {v['records']} within, median {100 * v['median']:.1f} %, worst "
                      f"{100 * v['worst']:.1f} %" for k, v in res["by_ratio"].items())
    print_table(("record", "ratio", "A", "B", "disagreement"), rows, title=f"{paths[0]} against {paths[1]}",
                caption=(f"worst {100 * (res['worst'] or 0):.1f} %; within {100 * tolerance:.0f} %: "
                         f"{'yes' if res['agree'] else 'no'}; {res['unmatched']} record(s) in one run only\n{kinds}"))


@app.command("demo")
@cli
def demo_cmd(
    out_dir: Path = typer.Option(Path("demo-out"), "--out", help="Directory for the maps, pictures and report.md."),
    voxel_size: float = typer.Option(0.02, "--voxel-size", help="Voxel edge in metres."),
    frames: int = typer.Option(120, "--frames", min=2, help="Frames to render and fuse."),
    track_frames: int = typer.Option(60, "--track-frames", min=2, help="Frames to track (every --track-stride-th)."),
    track_stride: int = typer.Option(2, "--track-stride", min=1, help="Track every N-th rendered frame."),
    ae: bool = typer.Option(True, "--ae/--no-ae", help="Also encode with the shipped AE-64 when installed."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace the results of an earlier run in --out."),
    as_json: bool = typer.Option(False, "--json", help="Print the results (results.json) as JSON."),
) -> None:
    """Render, fuse, compress, search and track a synthetic room; write OUT/report.md with tables and pictures.

    Built-in data only, nothing downloaded. Encodes with the shipped eigenshapes at 32/64/128 (and the shipped
    AE-64 when its plugin is installed), measures every map's surfaces against the original, searches the
    pca-64 map for floors and expands only them, and tracks the sequence against every map (pca-64 on demand).
    """
    refuse_existing(out_dir, overwrite, files=("report.md", "results.json"))
    from ..demo.run import run_demo

    t0 = time.perf_counter()
    with heartbeat("demo", as_json):
        summary = run_demo(out_dir, voxel_size=voxel_size, frames=frames, track_frames=track_frames,
                           track_stride=track_stride, ae=ae, console=err)
    if as_json:
        print_json(summary)
        return
    say(f"report: {out_dir / 'report.md'} ({time.perf_counter() - t0:.0f} s)")
