"""docs/rate-distortion.md: bytes against error for every codec of the registry and the peers (SZ3, ZFP, SPERR,
a DCT, a NanoVDB-style quantiser), quantised codes, and the storage formats of the learned codecs. Each section
is rendered by the `markdown` function of the script that measures it (examples/peers_study.py,
examples/quantised_codes.py, examples/rate_distortion.py) from the JSON that script committed; the section
markers let each script rewrite its own section after a new measurement, with the same text this renders."""

from __future__ import annotations

import importlib
import sys

from common import ROOT, banner, load, measured_on

PAGE = "rate-distortion.md"
PEERS, QUANTISED, QUANTISED_IDLE, CODECS = ("rd-peers.json", "quantised-codes.json",
                                            "quantised-codes-speed-idle.json", "rate-distortion.json")
SOURCES = (PEERS, QUANTISED, QUANTISED_IDLE, CODECS)


def _example(name: str):
    sys.path.insert(0, str(ROOT / "examples"))
    try:
        return importlib.import_module(name)
    finally:
        sys.path.remove(str(ROOT / "examples"))


def _section(name: str, text: str) -> list[str]:
    return [f"<!-- section {name} -->", text.rstrip(), f"<!-- end {name} -->", ""]


def _quantised_meta(doc: dict, src: str) -> str:
    m = doc["meta"]
    return measured_on({"load_before": m["load_avg"]}, machine={"cpus": m["cpus"]}, source=src,
                       command="python examples/quantised_codes.py KITCHEN.sdfz ...")


def quantised() -> str:
    qc = _example("quantised_codes")
    doc, idle = load(QUANTISED), load(QUANTISED_IDLE)
    L = ["## Quantised codes", "",
         "Step-quantised int16 codes (map extension `quantised-codes`, spec/map-format.md section 4b) against "
         "float32, float16 and int8 code storage, and SZ3 for reference, on the whole fused kitchen (507 coded "
         "blocks). B/block all-in: every file of the map but `codec/`, per coded block; codes: the `codes/` files "
         "alone; MSE in normalised units and max error over observed voxels; Chamfer-L1 and F@1 against the "
         "lossless map. \"int16 step s\": one step for every component; \"allocated\": steps scaled by the "
         "codec's explained variance. The speed columns are ratios to float32 measured in the same run.", "",
         "```", "python examples/quantised_codes.py KITCHEN.sdfz --sizes 32,64,128 --repeat 2 --allocated "
         "--speed-tiles 16 --sz3 --mask-rooms ROOM1.npz,ROOM2.npz,ROOM3.npz --out docs/quantised-codes.json",
         "python examples/quantised_codes.py docs/quantised-codes.json --render", "```", "",
         qc.markdown(doc), "", _quantised_meta(doc, QUANTISED), "",
         "### Speed of pca-64 codes, idle", "", qc.markdown(idle), "", _quantised_meta(idle, QUANTISED_IDLE)]
    return "\n".join(L)


def render() -> str:
    peers, rd = _example("peers_study"), _example("rate_distortion")
    L = ["# Rate-distortion", "", banner("page_rate_distortion.py", SOURCES), "",
         "What a coded block costs and what it loses, for every codec of the registry against the peers (SZ3, ZFP, "
         "SPERR, a DCT, a NanoVDB-style quantiser). Each section is measured by its own command and rendered from "
         "the JSON it writes:", "",
         "| section | command | what |", "|---|---|---|",
         "| peers | `python examples/peers_study.py` (`--quick`: the CI test's tiny map; `--ours-only`: rerun "
         "our maps only, keeping the committed peers' points) | our `sdfcodec encode --target-bytes B` maps "
         "against SZ3, ZFP and SPERR at equal bytes, surfaces included, on the held-out kitchen half, a synthetic "
         "room, two posed rooms and a building, against the targets we hold our maps to |",
         "| quantised | `python examples/quantised_codes.py ...` | int16 step codes against float32/float16/int8 "
         "on the whole kitchen |",
         "| codecs | `python examples/rate_distortion.py` | float32/float16/int8 maps of every learned codec "
         "against ZFP, DCT truncation and Blosc |", "",
         "Why the registry's `sz3` codec and how it stores unobserved space: "
         "[spec/map-format.md](../spec/map-format.md) section 4c.", ""]
    L += _section("peers", peers.markdown(load(PEERS)))
    L += _section("quantised", quantised())
    L += _section("codecs", rd.markdown(load(CODECS)))
    return "\n".join(L).rstrip() + "\n"
