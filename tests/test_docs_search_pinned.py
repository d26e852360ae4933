"""docs/variable-rate.md's table of search on variable-rate maps states what docs/search/evaluate.py wrote
(eval-pca64-fused.json, eval-vr128.json, eval-vr64.json): each row it draws from a run, to the digit."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

DOCS = Path(__file__).resolve().parents[1] / "docs"
ROWS = {"fixed pca-64": "eval-pca64-fused.json", "128 B, pinned voxels where one is unobserved": "eval-vr128.json",
        "64 B, pinned voxels where one is unobserved": "eval-vr64.json"}


@pytest.mark.parametrize("row", sorted(ROWS))
def test_the_table_row_is_the_run(row):
    run = json.loads((DOCS / "search" / ROWS[row]).read_text())
    got = {(r["kind"], r["query"]): (r["precision"], r["recall"]) for r in run["rows"]}
    want = " | ".join(f"{p:.3f} / {r:.3f}" for p, r in (got[k, q] for k in ("fused", "fused-tilted")
                                                          for q in ("floor", "wall")))
    page = (DOCS / "variable-rate.md").read_text()
    line = next(ln for ln in page.splitlines() if ln.startswith(f"| {row} |"))
    assert line == f"| {row} | {want} |"
    assert run["seeds"] == [7501, 7502, 7503] and re.search(r"seeds 7501-7503", page)
