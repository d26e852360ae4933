"""docs/results.md: encode/decode throughput, decode on read, the start-up of `sdfcodec info`, the agreement of
two `sdfcodec bench --quick` runs and the tracker's frame rate, from the JSON `sdfcodec bench` and
docs/results/tracking_measure.py wrote into docs/results/."""

from __future__ import annotations

from statistics import median

from common import banner, load, measured_on, num, table

PAGE = "results.md"
IN_MEMORY = ("results/bench-pca.json", "results/bench-ae.json", "results/bench-parallel.json",
             "results/bench-sequential.json")
ON_READ = "results/bench-pca64-read-s9.json"
QUICK = ("results/bench-quick-idle-e.json", "results/bench-quick-idle-f.json")
TRACKING = "results/tracking-bench-s8.json"
SOURCES = (*IN_MEMORY, ON_READ, *QUICK, TRACKING)
PAPER_US = (405.0, 645.0)  # the paper's GPU, microseconds per block (sdfcodec.bench.PAPER_US_PER_BLOCK)

WHAT = {
    "decode-on-read": "decode on read, `Map.iter_decoded()` (a fresh array per group of blocks)",
    "decode-on-read-into": "decode on read into the reader's ring of buffers, `iter_decoded(copy=False)`",
    "decode-on-read-fresh": "decode on read, `iter_decoded()` against the preallocated product",
    "decode-region": "`decode_region` of the whole map into a fresh volume",
    "decode-region-into": "`decode_region(out=)` into one reused volume",
    "decode-into": "in-memory decode into a preallocated output, `decode_core(out=)`",
}


def _codec(r: dict) -> str:
    return f"{r['codec']}-{r['code_size']}" if r.get("code_size") else r["codec"]


def in_memory() -> list[str]:
    rows = []
    for src in IN_MEMORY:
        for r in load(src):
            rows.append((_codec(r), r["operation"], f"{r['batch']:,}", num(r["blocks_per_s"]),
                         num(r["baseline_blocks_per_s"]), f"{r['ratio_to_baseline']:.2f}",
                         f"{r['us_per_block']:.3g}", f"{PAPER_US[0] / r['us_per_block']:.3g}x"))
    L = ["## Encode and decode in memory", "",
         "The baseline is the chain of numpy matrix products the operation cannot avoid, for the same batch (PCA: "
         "`(B, 4096) @ (4096, k)` to encode, `(B, k) @ (k, 4096)` to decode; the autoencoder: its two layers each "
         "way). A ratio of 1 means the codec adds nothing to those products.", ""]
    L += table(("codec", "operation", "batch", "blocks/s", "baseline blocks/s", "ratio", "µs/block",
                "vs the paper's 405 µs"), rows, right=(2, 3, 4, 5, 6, 7))
    L += ["", measured_on({}, source=IN_MEMORY[0],
                          command="sdfcodec bench --codec pca --sizes 32,64,128 --batches 1,256,4096,65536 --json "
                                  "(and --codec ae, parallel, sequential --sizes 64 --batches 1,256,4096)"), ""]
    return L


def on_read() -> list[str]:
    doc = load(ON_READ)
    recs = [r for r in doc["records"] if r["operation"] != "info-startup"]
    rows = [(_codec(r), WHAT.get(r["operation"], r["operation"]), f"{r['batch']:,}", num(r["blocks_per_s"]),
             num(r["baseline_blocks_per_s"]), f"{r['ratio_to_baseline']:.2f}", f"{r['ratio_of_bests']:.2f}")
            for r in recs]
    L = ["## Decode on read, into place and by region", "",
         "A 65,536-block pca-64 map on local disk, decoded to float32 metres; the baseline is numpy's product of the "
         "same shapes (into a preallocated output where the operation writes into one), interleaved with each "
         "figure over 5 rounds: the ratio is the median round's, the best round's beside it.", ""]
    L += table(("codec", "what", "batch", "blocks/s", "baseline blocks/s", "ratio", "ratio of bests"), rows,
               right=(2, 3, 4, 5, 6))
    L += ["", measured_on(doc, source=ON_READ), ""]
    (info,) = [r for r in doc["records"] if r["operation"] == "info-startup"]
    L += ["## `sdfcodec info` start-up", "",
          f"`{info['command']}` on a {info['map_blocks']:,}-block map, {info['repeats']} rounds: "
          f"median {info['seconds_median']:.2f} s, best {info['seconds_best']:.2f} s, against "
          f"{info['baseline_seconds_median']:.3f} s for {info['baseline']} (target {info['target_seconds']} s: "
          f"{'met' if info['meets_target'] else 'not met'}).", "", measured_on(doc, source=ON_READ), ""]
    return L


def quick_agreement() -> list[str]:
    a, b = (load(s) for s in QUICK)
    key = lambda r: (r.get("codec"), r.get("code_size"), r["operation"], r.get("batch"))  # noqa: E731
    rb = {key(r): r for r in b["records"] if "ratio_to_baseline" in r}
    diffs = []
    for r in a["records"]:
        o = rb.get(key(r))
        if o is not None and "ratio_to_baseline" in r:
            x, y = r["ratio_to_baseline"], o["ratio_to_baseline"]
            diffs.append(max(x, y) / min(x, y))
    within = sum(d <= 1.15 for d in diffs)
    L = ["## Do two runs agree?", "",
         "Two runs of `sdfcodec bench --quick`, one after the other, compared record by record on "
         "`ratio_to_baseline` (a figure divided by its same-run baseline, which is what should carry from one run "
         "to the next on a shared machine):", "",
         *table(("records compared", "within 15 %", "median difference", "worst"),
                [(len(diffs), within, f"{(median(diffs) - 1) * 100:.0f} %", f"{max(diffs):.2f}x")],
                right=(0, 1, 2, 3)),
         "", measured_on(a, source=QUICK[0]), measured_on(b, source=QUICK[1]), ""]
    return L


def tracking() -> list[str]:
    doc = load(TRACKING)
    rows = []
    for name, label in (("raw", "lossless"), ("pca64", "pca-64")):
        t = doc[name]
        rows.append((label, f"{t['image'][0]} x {t['image'][1]}", t["frames"], f"{t['dense_fps_median']:.1f}",
                     f"{t['lazy_warm_fps_median']:.1f}", f"{t['lazy_cold_fps_median']:.1f}",
                     f"{t['startup_s']:.2f}", f"{t['ate_m']['dense'] * 1000:.3f}"))
    L = ["## The tracker at camera rate", "",
         "The SDF Tracker on the real 7-Scenes kitchen (frames 0-199) against the fused map, lossless and pca-64: "
         "median frames per second with the map decoded to a dense field first, and decoded on demand "
         "(`MapField`, warm and cold cache); target 30 frames/s.", ""]
    L += table(("map", "image", "frames", "dense frames/s", "on demand, warm", "on demand, cold", "start-up s",
                "ATE mm"), rows, right=(2, 3, 4, 5, 6, 7))
    L += ["", measured_on(doc, source=TRACKING,
                          command="python docs/results/tracking_measure.py --kitchen KITCHEN --work WORK "
                                  "--bench FILE"), ""]
    return L


def render() -> str:
    L = ["# Throughput", "", banner("page_results.py", SOURCES), "",
         "Speeds of encoding, decoding, reading and tracking on CPU, each beside a baseline measured in the same "
         "run: absolute numbers on a shared virtual machine move by tens of per cent between runs, ratios to a "
         "same-run baseline much less. The paper's GPU implementation took "
         f"{PAPER_US[0]:.0f}-{PAPER_US[1]:.0f} microseconds per block. Where a measurement's machine, load or date "
         "is not recorded in its JSON, the line under its table says so.", "",
         "To measure on your machine: `sdfcodec bench` (encode/decode, decode on read, search, tracking, "
         "`--json`/`--out FILE` for the records); `sdfcodec bench --quick` for a short run; "
         "[its options](reference/cli.md#sdfcodec-bench).", ""]
    L += in_memory() + on_read() + quick_agreement() + tracking()
    return "\n".join(L).rstrip() + "\n"
