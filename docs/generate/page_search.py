"""docs/search.md: floor (and wall, ceiling, edge, corner, pole) retrieval with the command line's defaults on
rooms nobody tuned on, precision/recall of the floor model across codecs and levels, the paper's Fig. 7, and the
search's speed, from the JSON of docs/search/ (written by docs/search/evaluate.py, independent.py and
make_figures.py)."""

from __future__ import annotations

from common import banner, load, measured_on, num, table

PAGE = "search.md"
DEFAULTS = ("search/eval-defaults.json", "search/eval-defaults-8201.json", "search/eval-defaults-9301.json")
INDEPENDENT = "search/independent.json"
PR = "search/pr.json"
ROOM = "search/room-floor.json"
KITCHEN = "search/kitchen-floor.json"
BENCH = "search/bench.json"
BENCH_DISK = "search/bench-disk.json"
SOURCES = (*DEFAULTS, INDEPENDENT, PR, ROOM, KITCHEN, BENCH, BENCH_DISK)


def _pr(v: float) -> str:
    return f"{v:.3f}"


def defaults() -> list[str]:
    L = ["## With the defaults, on rooms nobody tuned on", "",
         "`sdfcodec search MAP --query Q` with nothing else (automatic threshold, the map's own up direction and "
         "observation, the map-level stage) on synthetic rooms of fresh seeds, of each kind: `exact` (truncated "
         "SDFs sampled from the scene, solid behind surfaces), `-open` (no ceiling), `fused-style` (only what a "
         "camera sees is kept), `fused` (rendered and fused with open3d), `-tilted` (the whole room tilted), and "
         "the real 7-Scenes kitchen where given. Positives are the blocks whose surface is that shape by the "
         "rooms' labels; precision and recall are pooled over the maps of a kind. Only each query's default "
         "form is tabled; the JSON also holds its shape-only, pure and observed variants. The maps are the shipped "
         "pca-64 eigenshapes; variable-rate maps (`--target-bytes`, pinned observation mask) of the fused rooms: "
         "[variable-rate.md](variable-rate.md).", ""]
    for src in DEFAULTS:
        doc = load(src)
        rows = [(r["kind"], r["query"], r["maps"], f"{r['blocks']:,}", r["positives"], r["selected"], r["tp"],
                 _pr(r["precision"]), _pr(r["recall"]))
                for r in doc["rows"] if "(" not in r["query"] and "[" not in r["query"]]
        L += [f"### Seeds {', '.join(map(str, doc['seeds']))}", ""]
        L += table(("kind", "query", "maps", "blocks", "positives", "selected", "true positives", "precision",
                    "recall"), rows, right=(2, 3, 4, 5, 6, 7, 8))
        L += ["", measured_on(doc, source=src), ""]  # evaluate.py records its command
    doc = load(INDEPENDENT)
    rows = [(p["style"], f"{p['tilt_deg']:g}", f"{p['voxel_m']:g}", p["query"], p["positives"], p["selected"],
             p["tp"], p["fp"], _pr(p["precision"]), _pr(p["recall"])) for p in doc["pooled"]]
    L += ["### Rooms built by other code", "",
          "Rooms assembled by docs/search/independent.py from boxes, not by `sdfcodec.search.rooms` (the code the "
          "defaults were developed on), at two tilts and two voxel sizes, pooled over seeds "
          f"{', '.join(map(str, doc['seeds']))}; a false positive is a selected block with no surface of that "
          "shape at all (selected blocks that hold some of it are neither).", ""]
    L += table(("style", "tilt (deg)", "voxel (m)", "query", "positives", "selected", "true positives",
                "false positives", "precision", "recall"), rows, right=(1, 2, 4, 5, 6, 7, 8, 9))
    L += ["", measured_on(doc, source=INDEPENDENT,
                          command="python docs/search/independent.py --seeds 21 22 23 --tilts 0 7 --voxels 0.02 "
                                  "0.03 --jobs 2"), ""]
    return L


def quality() -> list[str]:
    doc = load(PR)
    L = ["## Precision and recall of the floor model", "",
         "Every coded block of synthetic rooms scored against the floor model, one threshold over all rooms of a "
         "set. *Truth* `floor`: clean floor blocks (at least 90 % floor, 90 % covered) against all others, so a "
         "retrieved partial block counts against; `floor-vs-none`: clean floor against blocks with no floor at "
         "all. \"P at R >= 0.9\": the best precision at any threshold with recall at least 0.9; \"R at P >= 0.9\" "
         "the converse; AP: average precision. A level below the code size compares that prefix of the codes "
         "only.", "", "![precision-recall curves](search/pr-curves.png)", ""]
    scenes = []
    for r in doc["records"]:
        if r["scenes"] not in scenes:
            scenes.append(r["scenes"])
    for sc in scenes:
        recs = [r for r in doc["records"] if r["scenes"] == sc and r["truth"] in ("floor", "floor-vs-none")]
        rows = [(r["codec"], r["level"], f"{r['query']} ({r['descriptors']})", r["truth"],
                 _pr(r["precision_at_recall"]), _pr(r["recall_at_precision"]), _pr(r["ap"]),
                 f"{r['best_f1']:.3f} ({r['best_f1_threshold']:.1f})") for r in recs]
        r0 = recs[0]
        L += [f"### {sc.capitalize()} rooms: {r0['rooms']} rooms, {r0['blocks']:,} coded blocks, "
              f"{r0['positives']:,} clean floor blocks", ""]
        L += table(("map", "level", "query (descriptors)", "truth", "P at R >= 0.9", "R at P >= 0.9", "AP",
                    "best F1 (threshold)"), rows, right=(1, 4, 5, 6, 7))
        L += ["", measured_on(doc, source=PR), ""]
    return L


def fig7() -> list[str]:
    room, kit = load(ROOM), load(KITCHEN)
    k = kit["pca-64"]
    horiz = sum(1 for d in k["selected_normal_dot_up"] if d is not None and d >= 0.98)
    L = ["## The paper's Fig. 7: what a floor search finds", "",
         f"A synthetic room (seed 3, `rich`) written as {room['codec']}-{room['code_size']}, searched at level "
         f"{room['level']} with the {room['threshold_mode']} threshold ({room['threshold']:.2f}): "
         f"{room['selected']} of {room['coded_blocks']:,} coded blocks selected, the expansion decoded "
         f"{room['expanded']['blocks_decoded']} blocks and read {room['expanded']['code_bytes_read'] / 1024:.1f} "
         "KiB of codes. (a) the map from above, each cell coloured by its best block's distance to the floor "
         "model, the selection outlined; (b) the mesh of the expanded blocks.", "",
         "![room floor search](search/room-floor.png)", "", measured_on(room, source=ROOM,
                                                                       command="python docs/search/make_figures.py "
                                                                               "room"), "",
         f"The real 7-Scenes kitchen fused at 2 cm ({k['coded_blocks']} coded blocks), pca-64, the "
         f"{k['top']} best blocks for a floor model along the kitchen's up "
         f"({', '.join(f'{u:.3f}' for u in kit['up'])}), sampled over a cone ({k['descriptors']} descriptors). "
         f"Read back from the lossless map, {horiz} of the {k['selected']} have a mean normal within 11.5 degrees "
         "of up (normal . up >= 0.98): the floor and the horizontal tops of furniture, which a floor model "
         "matches too. The same search on the lossless map: [kitchen-floor-raw.png](search/kitchen-floor-raw.png).",
         "", "![kitchen floor search](search/kitchen-floor-pca-64.png)", "",
         measured_on(kit, source=KITCHEN, command="python docs/search/make_figures.py kitchen --kitchen DIR"), ""]
    return L


def speed() -> list[str]:
    doc = load(BENCH)
    rows = []
    for r in doc["records"]:
        whole = r["operation"] == "search-map"
        read = (f"{r['code_bytes_read'] / 2**20:.1f} of {r['code_bytes_full'] / 2**20:.1f} MiB"
                if whole else "")
        rows.append(("whole search of a map on disk" if whole else "scoring kernel", r["code_size"],
                     r.get("level", r["code_size"]), f"{r['batch']:,}", num(r["blocks_per_s"]),
                     num(r["baseline_blocks_per_s"]), f"{r['ratio_to_baseline']:.3g}", read))
    disk = load(BENCH_DISK)
    L = ["## Speed", "",
         "The scoring kernel (squared distances of every code to the model's descriptors, then the minimum) "
         "against numpy's bare product of the same shapes, `(N, k) @ (k, 15)`, measured in the same run; a "
         "whole search streams a 200,000-block map's codes from disk. Random codes with the shipped "
         "eigenshapes' per-component spread, the paper's 15-plane floor model.", ""]
    L += table(("operation", "code size", "level", "blocks", "blocks/s", "numpy product blocks/s", "ratio",
                "code bytes read"), rows, right=(1, 2, 3, 4, 5, 6))
    L += ["", measured_on(doc, source=BENCH), "",
          f"A whole search against a plain read of the same {disk['blocks']:,}-block map's codes (local disk, "
          "same run, interleaved): search "
          f"{num(disk['search_blocks_per_s'])} blocks/s, read {num(disk['read_blocks_per_s'])} blocks/s, ratio "
          f"{disk['ratio_of_medians']:.2f} (paired {disk['ratio_paired']:.2f}, CPU time "
          f"{disk['ratio_cpu']:.2f}).", "",
          measured_on(disk, source=BENCH_DISK, command="python docs/search/bench_disk.py"), ""]
    return L


def render() -> str:
    L = ["# Search: measured", "", banner("page_search.py", SOURCES), "",
         "How well a code-space search finds floors, walls and other shapes in a compressed map, and how fast. "
         "How search works, its Python and command-line use: [explanation/search.md](explanation/search.md).", ""]
    L += defaults() + quality() + fig7() + speed()
    return "\n".join(L).rstrip() + "\n"
