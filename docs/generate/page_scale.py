"""docs/scale.md: decode on read from local disk and HTTP, chunk sizes, and dask, from the JSON
docs/results/scale_measure.py wrote (docs/results/scale-measure.json)."""

from __future__ import annotations

from common import banner, load, measured_on, num, table

PAGE = "scale.md"
SOURCE = "results/scale-measure.json"
ROWS = (("`codec.decode` alone, codes in memory (the decode's own ceiling)", "decode_only_in_memory", None),
        ("`iter_codes` (fetch, decompress, CRC32C; no decode)", "c16_iter_codes", "c8_iter_codes"),
        ("`iter_decoded()` end to end, local store, `prefetch=0`", "c16_iter_decoded_prefetch0",
         "c8_iter_decoded_prefetch0"),
        ("`iter_decoded()` end to end, local store, `prefetch=2` (the default)", "c16_iter_decoded_prefetch2",
         "c8_iter_decoded_prefetch2"),
        ("`iter_decoded(level=32)`", "c16_iter_decoded_level32", "c8_iter_decoded_level32"),
        ("`iter_decoded()` over HTTP (in-process `http.server`, loopback)", "c16_http_iter_decoded",
         "c8_http_iter_decoded"))


def render() -> str:
    d = load(SOURCE)
    best_median = lambda v: f"{num(v[0])} / {num(v[1])}"  # noqa: E731
    rows = [(what, best_median(d[a]), best_median(d[b]) if b else "(same)") for what, a, b in ROWS]
    rows.append(("bytes fetched over HTTP for a 32^3-voxel region",
                 f"{d['c16_http_region_bytes']:,} of {d['c16_map_bytes']:,}",
                 f"{d['c8_http_region_bytes']:,} of {d['c8_map_bytes']:,}"))
    doc = {"load_before": d["loadavg_start"], "load_after": d["loadavg_end"]}
    machine = {"cpus": d["cpus"]}
    cmd = "python docs/results/scale_measure.py WORKDIR"
    L = ["# Scale: measured", "", banner("page_scale.py", (SOURCE,)), "",
         "How fast a map decodes as it is read, locally and over HTTP, with the default 16^3-block chunks and with "
         "8^3, and what dask adds. How the decode-on-read pipeline, remote stores, dask and sharded maps work: "
         "[explanation/large-maps.md](explanation/large-maps.md).", "",
         "## Decode on read", "",
         f"A pca-64 map of {d['coded_blocks']:,} coded blocks (float32 codes near real block codes), written with "
         "16^3-block chunks and again with 8^3; blocks per second, best / median of 5 runs, "
         f"torch on {d['torch_threads']} threads.", ""]
    L += table(("what", "16^3-block chunks", "8^3-block chunks"), rows)
    L += ["", measured_on(doc, machine=machine, source=SOURCE, command=cmd), "",
          "## Dask", "",
          f"A 256 x 256 x 128 scene ({d['coded_blocks_scene']:,} coded blocks): the dask path is for volumes that do "
          "not fit in memory, not for speed on a few cores.", ""]
    L += table(("what", "seconds"), [
        ("`write_volume`, one process", f"{d['write_volume_single_s']:.3f}"),
        ("`encode_volume_dask` on a `LocalCluster(processes=False)` of 2 workers", f"{d['encode_volume_dask_s']:.3f}"),
        ("`to_dask().compute()`", f"{d['to_dask_compute_s']:.3f}"),
        ("`decode_region()`", f"{d['decode_region_s']:.3f}")], right=(1,))
    L += ["", f"`to_dask()` and `decode_region()` agree to {d['to_dask_vs_decode_region_maxdiff']:g} (largest "
          "difference).", "", measured_on(doc, machine=machine, source=SOURCE, command=cmd), ""]
    return "\n".join(L).rstrip() + "\n"
