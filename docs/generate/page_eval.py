"""docs/eval.md: the paper's Table 1 (reconstruction error and tracking ATE per codec), from docs/eval.json as
`sdfcodec eval ... --docs docs` wrote it; the tables are `sdfcodec.evaluation.tracking.markdown_table`'s, the one the
command prints."""

from __future__ import annotations

from common import banner, load, measured_on, table

from sdfcodec.evaluation.tracking import markdown_table

PAGE = "eval.md"
SOURCE = "eval.json"
COMMAND = ("sdfcodec eval synthetic:slow-clean synthetic:slow-noisy synthetic:fast-clean synthetic:fast-noisy "
           "synthetic:poor-geometry synthetic:rich-geometry 7scenes-redkitchen --frames 60 --size 320x240 "
           "-o eval-out --docs docs --overwrite")
# The paper's Table 1 (Canelhas et al.), for the comparison below: MSE +- sigma, mean ATE +- sigma, median ATE.
PAPER = {"original": ("-", "0.70 ± 0.67", "0.59"), "pca-32": ("42.94 ± 2.63", "0.29 ± 0.45", "0.06"),
         "pca-64": ("33.96 ± 2.01", "0.48 ± 0.53", "0.16"), "pca-128": ("27.29 ± 1.87", "0.65 ± 0.54", "0.62"),
         "ae-64": ("49.52", "0.083", "0.06"), "parallel-64-64": ("33.63", "0.27", "0.07"),
         "sequential-64-64": ("33.95", "0.49", "0.16"), "blur-9": ("-", "0.05 ± 0.04", "0.04")}


def targets(doc: dict) -> list[str]:
    rows = []
    for name, s in doc["sequences"].items():
        m = s["methods"]
        o, p64, p128 = m["original"]["ate_mean"], m["pca-64"]["ate_mean"], m["pca-128"]["ate_mean"]
        rows.append((name, f"{o * 100:.3f}", f"{p64 * 100:.3f}", f"{p64 / o:.2f}", "yes" if p64 <= 1.1 * o else "**no**",
                     f"{p128 * 100:.3f}", "yes" if p128 <= p64 else "**no**",
                     f"{m['pca-64']['chamfer_l1'] * 1000:.2f} / {m['pca-64']['f_score_1']:.3f}"))
    return ["### Targets: PCA 64 within 1.1x of the lossless map's ATE, PCA 128 at most PCA 64", "",
            *table(("sequence", "Original ATE [cm]", "PCA 64 ATE [cm]", "PCA 64 / Original", "<= 1.1x?",
                    "PCA 128 ATE [cm]", "PCA 128 <= PCA 64?", "PCA 64 Chamfer [mm] / F@1"), rows,
                   right=(1, 2, 3, 5)), ""]


def paper(doc: dict) -> list[str]:
    agg = doc["aggregate"]
    rows = []
    for k, (mse, ate, med) in PAPER.items():
        a = agg.get(k)
        if a is None:
            continue
        here_sse = "-" if k == "original" else f"{a['block_sse_mean']:.1f} ± {a['block_sse_std']:.1f}"
        rows.append((k, mse, ate, med, here_sse, f"{a['ate_mean_mean']:.3f} ± {a['ate_mean_std']:.3f}",
                     f"{a['ate_median_mean']:.3f}"))
    return ["## Against the paper's Table 1", "",
            "The paper's ATEs are tens of centimetres over whole TUM fr1 sequences of hundreds of frames; these are "
            "centimetres over 60 frames, so the ranking, not the magnitude, is what compares. The reconstruction "
            "errors do not compare either: here only observed voxels count (unobserved ones are restored exactly on "
            "reading) and PCA fits them by weighted least squares; the paper's MSE was over every voxel.", "",
            *table(("method", "paper: MSE ± σ", "paper: mean ATE [m]", "paper: median ATE [m]",
                    "here: block SSE ± σ", "here: mean ATE [m] ± σ", "here: median ATE [m]"), rows), ""]


def render() -> str:
    doc = load(SOURCE)
    st = doc["settings"]
    line = measured_on(doc, source=SOURCE, command=COMMAND)
    L = ["# Tracking on compressed maps (the paper's Table 1)", "", banner("page_eval.py", (SOURCE,)), "",
         "How well the SDF Tracker follows the camera in a map that was compressed and decompressed. Per sequence: "
         "fuse the lossless map from the ground-truth poses, write it with each codec (surface-true) and decode "
         "it back, measure the reconstruction error over the coded blocks (normalised units) and the surfaces "
         "against the lossless map ([surface.md](surface.md)), then track every frame from the first ground-truth "
         "pose; ATE is the camera-position error against ground truth, no alignment, and `ATE / lossless` the "
         "mean of the per-sequence ratios to the lossless map's ATE. How the tracker works: "
         "[explanation/tracker.md](explanation/tracker.md).", "",
         f"Settings: {st['frames']} frames per sequence, synthetic frames rendered at {st['size'][0]} x "
         f"{st['size'][1]}, {st['voxel_size'] * 100:g} cm voxels, truncation [{st['truncation'][0]:g}, "
         f"{st['truncation'][1]:g}] m, depth up to {st['depth_max']:g} m.", "",
         "To reproduce (7scenes-redkitchen: the folder of the 7-Scenes sequence; `--model ae-32=FILE` adds a "
         "trained model):", "", "```bash", COMMAND, "```", "",
         f"## Table 1 ({len(doc['sequences'])} sequences)", "", markdown_table(doc).rstrip(), "", line, "",
         "![reconstruction error](eval/reconstruction_error.png)", ""]
    L += targets(doc) + [line, ""] + paper(doc) + [line, ""]
    L += ["## Pictures", "", "ATE over time per method, and a slice through the decoded field (the paper's Fig. 5), "
          "for the real kitchen and the hardest preset; every sequence has both in [eval/](eval/).", "",
          "![ATE redkitchen](eval/ate_7scenes-redkitchen.png)", "![slice redkitchen](eval/slice_7scenes-redkitchen.png)",
          "![ATE fast-noisy](eval/ate_fast-noisy.png)", "![slice fast-noisy](eval/slice_fast-noisy.png)", ""]
    return "\n".join(L).rstrip() + "\n"
