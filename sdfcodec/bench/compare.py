"""How far two benchmark runs agree: every ratio of one run's records against the same record of the other.

A run is the JSON document ``sdfcodec bench --out FILE`` writes (or its bare list of records, ``--json``).
Records match on their identity (every field that is not a measurement: codec, code size, operation, batch,
device, dtype, level...). For each ratio field (``ratio_*``) present in both, the disagreement is
``max(a, b) / min(a, b) - 1``: 0.15 means the two runs differ by 15 % on that ratio.
"""

from __future__ import annotations

import json
import statistics
from pathlib import Path
from typing import Any, Iterable

from ..errors import FormatError, InputNotFoundError

__all__ = ["compare_runs", "load_run", "record_key"]

#: fields that name what was measured (the rest are measurements, or depend on the machine's state)
IDENTITY = ("codec", "code_size", "operation", "batch", "device", "dtype", "level", "descriptors", "resolution",
            "prefetch")


def record_key(rec: dict[str, Any]) -> tuple:
    """What a record measured, as a hashable key (its :data:`IDENTITY` fields)."""
    return tuple((k, json.dumps(rec[k])) for k in IDENTITY if k in rec)


def load_run(path: str | Path) -> list[dict[str, Any]]:
    """The records of a run file: a document with ``records`` or a bare list of records.

    Raises:
        InputNotFoundError: no such file. FormatError: not a benchmark run.
    """
    p = Path(path)
    if not p.is_file():
        raise InputNotFoundError(f"no benchmark run at {p}: write one with `sdfcodec bench --out {p.name}`")
    try:
        doc = json.loads(p.read_text())
    except (ValueError, UnicodeDecodeError) as e:
        raise FormatError(f"{p} is not JSON ({e}); pass a file written by `sdfcodec bench --out`") from e
    recs = doc.get("records") if isinstance(doc, dict) else doc
    if not isinstance(recs, list) or not all(isinstance(r, dict) for r in recs):
        raise FormatError(f"{p} holds no benchmark records (a list, or a document with 'records'); pass a file "
                          "written by `sdfcodec bench --out`")
    return recs


def compare_runs(a: Iterable[dict[str, Any]] | str | Path, b: Iterable[dict[str, Any]] | str | Path, *,
                 tolerance: float = 0.15) -> dict[str, Any]:
    """Compare the ratios of two runs (records, or paths of run files).

    Returns:
        ``{"rows": [...], "worst": ..., "tolerance": ..., "agree": bool, "unmatched": n}``: one row per
        (record, ratio field) present in both runs, ``{"record": identity, "ratio": field, "a": .., "b": ..,
        "disagreement": max/min - 1}``, sorted worst first; ``agree`` is True when every row is within
        ``tolerance``; ``by_ratio`` gives each ratio field's worst and median disagreement, whether the worst
        is within ``tolerance``, over how many records and how many of them are within it; ``unmatched`` counts records of either run missing from the
        other.
    """
    ra = load_run(a) if isinstance(a, (str, Path)) else list(a)
    rb = load_run(b) if isinstance(b, (str, Path)) else list(b)
    ia, ib = {record_key(r): r for r in ra}, {record_key(r): r for r in rb}
    rows = []
    for key in ia.keys() & ib.keys():
        x, y = ia[key], ib[key]
        for field in sorted(k for k in x if k.startswith("ratio") and k in y):
            va, vb = x[field], y[field]
            if not (isinstance(va, (int, float)) and isinstance(vb, (int, float))) or va <= 0 or vb <= 0:
                continue
            rows.append({"record": {k: json.loads(v) for k, v in key}, "ratio": field, "a": va, "b": vb,
                         "disagreement": max(va, vb) / min(va, vb) - 1})
    rows.sort(key=lambda r: -r["disagreement"])
    worst = rows[0]["disagreement"] if rows else None
    by_ratio: dict[str, list[float]] = {}
    for r in rows:  # worst first
        by_ratio.setdefault(r["ratio"], []).append(r["disagreement"])
    return {"rows": rows, "worst": worst, "tolerance": tolerance,
            "agree": bool(rows) and worst is not None and worst <= tolerance,
            "by_ratio": {k: {"worst": v[0], "agree": v[0] <= tolerance, "records": len(v),
                             "within": sum(d <= tolerance for d in v), "median": statistics.median(v)}
                         for k, v in sorted(by_ratio.items())},
            "unmatched": len(ia.keys() ^ ib.keys())}
