"""Figures the README quotes agree with the committed results they come from (issue 44, item 4): a re-run that
changes docs/search/*.json, or an edit of the README, cannot leave the two apart unnoticed."""

from __future__ import annotations

import json
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def _readme_row(start: str) -> str:
    rows = [line for line in (ROOT / "README.md").read_text(encoding="utf-8").splitlines()
            if line.startswith(f"| {start}")]
    assert len(rows) == 1, f"README has {len(rows)} rows starting {start!r}"
    return rows[0]


def test_floor_search_figures_match_the_committed_runs():
    row = _readme_row("floor search, pca-64")
    pr = json.loads((ROOT / "docs/search/pr.json").read_text())
    (rec,) = [r for r in pr["records"] if r["codec"] == "pca-64" and r["query"] == "floor" and r["level"] == 64
              and r["truth"] == "floor" and r["scenes"] == "level"]
    assert re.search(r"precision (\d\.\d+) at recall 0\.9", row)[1] == f"{rec['precision_at_recall']:.3f}"
    assert f"{rec['rooms']} level synthetic rooms" in row
    bench = json.loads((ROOT / "docs/search/bench.json").read_text())["records"]
    (kernel,) = [r for r in bench if r["operation"] == "search" and r["code_size"] == 64 and r["batch"] == 65536]
    assert re.search(r"scoring kernel (\d+\.\d) M blocks/s", row)[1] == f"{kernel['blocks_per_s'] / 1e6:.1f}"
    (whole,) = [r for r in bench if r["operation"] == "search-map" and r["code_size"] == 64]
    quoted = int(re.search(r"from disk ([\d,]+) blocks/s", row)[1].replace(",", ""))
    assert quoted == round(whole["blocks_per_s"], -3) and f"({whole['batch']:,} blocks)" in row


def test_the_lossless_kitchen_is_the_size_fuse_writes():
    """The kitchen row and the opening paragraph quote the same lossless size, the one with the fusion weights
    (what `sdfcodec fuse` writes by default; 2.51 MiB measured for frames 0-499)."""
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    assert "1.7 MiB" not in text
    assert "2.5 MiB as the lossless map `sdfcodec fuse` writes (fusion weights included)" in text
    # the pca-32 map as `encode --code-size 32` writes it (the shipped model by reference), from the recorded
    # walk-through of the kitchen (docs/how-to/kitchen.json); 0.5 MiB is that map with the basis embedded
    walk = json.loads((ROOT / "docs/how-to/kitchen.json").read_text())["records"]
    (pca32,) = [r for r in walk if r["command"] == "sdfcodec encode kitchen.sdfz kitchen-pca32.sdfz --code-size 32"]
    kib = float(re.search(r"([\d.]+) KiB on disk", pca32["stdout"])[1])
    assert f"/ 2.5 MiB / {kib:.0f} KiB; 0.5 MiB" in _readme_row("real kitchen at 2 cm")
    assert f"{kib:.0f} KiB with 32-element PCA codes" in text
