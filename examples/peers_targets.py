"""The targets we hold our maps to against the peers, computed from the points of examples/peers_study.py (JSON
dicts, one per measured map or stream) and rendered for docs/rate-distortion.md. Pure functions:
tests/test_peers_targets.py checks them against hand computations.

A point has at least ``bytes_per_block`` (every stored byte per coded block), ``chamfer_mm``, ``f1`` and
``max_error_cm``. A peer's value "at equal bytes" is read off its measured curve at our point's exact byte count
by :func:`peer_at` (the peers are measured on a grid of byte counts around each ratio, so the two points read
are at most 1.5x apart in bytes; beyond a curve that stops short, its largest point).
"""

from __future__ import annotations

import math

__all__ = ["LOG_KEYS", "at_bytes", "peer_at", "bytes_at_chamfer", "equal_bytes_rows", "equal_chamfer", "decode_on_read",
           "markdown_targets"]

#: error measures read in log(value) (they fall as a power of the bytes); F@1 is read linearly
LOG_KEYS = frozenset({"chamfer_mm", "max_error_cm", "mse"})
#: the target ratios to dense float32 (16^3 x 4 B = 16,384 B a block): 32:1 .. 256:1
BUDGETS = (512, 256, 128, 64)
KEYS = ("f1", "chamfer_mm", "max_error_cm")


def _lerp(x0: float, x1: float, y0: float, y1: float, x: float, log_y: bool) -> float:
    t = 0.0 if x1 == x0 else (x - x0) / (x1 - x0)
    if log_y and y0 > 0 and y1 > 0:
        return math.exp(math.log(y0) + t * (math.log(y1) - math.log(y0)))
    return y0 + t * (y1 - y0)


def at_bytes(points: list[dict], b: float, key: str) -> float | None:
    """``key`` of one method's curve at ``b`` bytes per coded block: between the two measured points either side
    of ``b``, linear in log(bytes), and in log(value) for :data:`LOG_KEYS` (linear in the value for F@1). A point
    measured at exactly ``b`` is returned as is. None outside the measured range (nothing is extrapolated)."""
    P = sorted((p for p in points if p.get(key) is not None), key=lambda p: p["bytes_per_block"])
    for p in P:
        if p["bytes_per_block"] == b:
            return float(p[key])
    for lo, hi in zip(P, P[1:]):
        if lo["bytes_per_block"] < b < hi["bytes_per_block"]:
            return _lerp(math.log(lo["bytes_per_block"]), math.log(hi["bytes_per_block"]), lo[key], hi[key],
                         math.log(b), key in LOG_KEYS)
    return None


def peer_at(points: list[dict], b: float, key: str) -> float | None:
    """A peer's ``key`` at ``b`` bytes: :func:`at_bytes`, or beyond its largest point (a curve that stops short:
    SZ3 reaches float precision on exact synthetic fields and gives no more bytes) that point's value, read with
    fewer bytes than ``b``. None below its smallest point."""
    v = at_bytes(points, b, key)
    P = [p for p in points if p.get(key) is not None]
    if v is None and P and b > max(p["bytes_per_block"] for p in P):
        v = float(max(P, key=lambda p: p["bytes_per_block"])[key])
    return v


def bytes_at_chamfer(points: list[dict], chamfer: float) -> float | None:
    """The bytes per coded block at which a curve first reaches ``chamfer`` (mm), walking up in bytes: the first
    measured point at or below it, or between it and the point before (log-log). None if no point reaches it."""
    P = sorted((p for p in points if p.get("chamfer_mm") is not None), key=lambda p: p["bytes_per_block"])
    for i, p in enumerate(P):
        if p["chamfer_mm"] <= chamfer:
            if i == 0 or p["chamfer_mm"] == chamfer:
                return float(p["bytes_per_block"])
            q = P[i - 1]  # q above the Chamfer asked, p at or below it: log(bytes) linear in log(Chamfer)
            return math.exp(_lerp(math.log(q["chamfer_mm"]), math.log(p["chamfer_mm"]), math.log(q["bytes_per_block"]),
                                  math.log(p["bytes_per_block"]), math.log(chamfer), False))
    return None


def _brief(p: dict | None) -> dict | None:
    return None if p is None else {k: p.get(k) for k in ("setting", "bytes_per_block", *KEYS, "decode_vs_memcpy",
                                                         "decode_blocks_per_s")}


def equal_bytes_rows(ours: list[dict], peers: dict[str, list[dict]], refused: list[dict],
                     budgets: tuple[int, ...] = BUDGETS) -> list[dict]:
    """One row per budget B: our ``--target-bytes B`` point (``options["target-bytes"] == B``) or its refusal,
    each peer's F@1, Chamfer and max error at our exact bytes (:func:`at_bytes`), our Chamfer over each peer's,
    and whether it is <= 0.5x both SZ3's and SPERR's (None when a peer has no value there or we were refused)."""
    rows = []
    for B in budgets:
        row: dict = {"budget": B, "ratio": 16384 // B}
        o = next((p for p in ours if p.get("options", {}).get("target-bytes") == B), None)
        ref = next((r for r in refused if r["options"].get("target-bytes") == B), None)
        row["ours"], row["refused"] = _brief(o), ref
        ratios = {}
        for name, P in peers.items():
            v = None if o is None else {k: peer_at(P, o["bytes_per_block"], k) for k in KEYS}
            row[name] = v
            c = None if v is None or v["chamfer_mm"] is None or o["chamfer_mm"] is None else o["chamfer_mm"] / v["chamfer_mm"]
            row[f"chamfer_over_{name}"] = ratios[name] = c
        half = [ratios.get(n) for n in ("sz3", "sperr")]
        row["met"] = None if any(c is None for c in half) else all(c <= 0.5 for c in half)
        fit = [p for p in ours if p["bytes_per_block"] <= B and p["chamfer_mm"] is not None]
        if o is None and fit:  # refused: our largest map within B against the peers given all of B (their favour)
            w = max(fit, key=lambda p: p["bytes_per_block"])
            row["within_budget"] = {"ours": _brief(w), **{f"chamfer_over_{n}_at_budget": (
                None if (c := peer_at(P, B, "chamfer_mm")) is None else w["chamfer_mm"] / c) for n, P in peers.items()}}
        if B == 128:
            row["absolute"] = "F@1 >= 0.95 and Chamfer <= 5 mm"
            row["absolute_met"] = None if o is None else bool(o["f1"] >= 0.95 and o["chamfer_mm"] <= 5)
        if B == 64:
            row["absolute"] = "F@1 >= 0.9"
            row["absolute_met"] = None if o is None else bool(o["f1"] >= 0.9)
        rows.append(row)
    return rows


def equal_chamfer(curve: list[dict], refs: list[dict]) -> list[dict]:
    """The whole-map target "smaller than SZ3's at equal Chamfer": for each map of ``refs`` (SZ3's), the bytes at
    which ``curve`` (ours) reaches its Chamfer (:func:`bytes_at_chamfer`), the smallest measured map of ``curve``
    at or below its Chamfer, and those bytes over the reference's (< 1: smaller). None where no map of ``curve``
    reaches that Chamfer. Swap the arguments for the reverse reading (SZ3's bytes at our Chamfer)."""
    out = []
    for s in sorted(refs, key=lambda p: p["bytes_per_block"]):
        b = bytes_at_chamfer(curve, s["chamfer_mm"])
        reach = [p for p in curve if p["chamfer_mm"] is not None and p["chamfer_mm"] <= s["chamfer_mm"]]
        smallest = min(reach, key=lambda p: p["bytes_per_block"]) if reach else None
        out.append({"ref": _brief(s), "bytes_at_equal_chamfer": b, "smallest_reaching": _brief(smallest),
                    "bytes_ratio": None if b is None else b / s["bytes_per_block"],
                    "met": None if b is None else b < s["bytes_per_block"]})
    return out


def decode_on_read(times: dict[str, list[float]], reference: str) -> dict[str, float]:
    """Decode-on-read speed of each map over ``reference``'s: best (shortest) time of the reference over the
    map's, from times taken interleaved in one run (> 1: faster than the reference)."""
    return {name: min(times[reference]) / min(t) for name, t in times.items() if name != reference}


def _f(v, f: str = "{:.2f}") -> str:
    return "-" if v is None else f.format(v)


def _cell(v: dict | None) -> str:
    return "-" if v is None else f"{_f(v['f1'], '{:.3f}')} / {_f(v['chamfer_mm'])} / {_f(v['max_error_cm'])}"


def markdown_targets(t: dict, measured: str) -> list[str]:
    """The targets of one data set (``t``: ``equal_bytes`` rows, optional ``decode_on_read``) as markdown lines."""
    L = ["| ratio (B/block) | ours: `--target-bytes B` (B, F@1 / Chamfer mm / max cm) | SZ3 at our bytes | SPERR "
         "at our bytes | ZFP at our bytes | Chamfer ours / SZ3 | ours / SPERR | <= 0.5x both? | absolute target |",
         "|---|---|---|---|---|---:|---:|---|---|"]
    for r in t["equal_bytes"]:
        o, ref = r["ours"], r["refused"]
        ours = (f"refused: {ref['message']}" if o is None and ref else "-" if o is None else
                f"{o['bytes_per_block']:.1f} B: {_cell(o)}")
        met = {True: "**met**", False: "**missed**", None: "not measurable"}[r["met"]]
        ab = "" if "absolute" not in r else f"{r['absolute']}: " + {True: "**met**", False: "**missed**",
                                                                    None: "refused"}[r["absolute_met"]]
        w = r.get("within_budget")
        if w:
            ours += (f"; our largest map within it, {w['ours']['setting']} ({w['ours']['bytes_per_block']:.1f} B, "
                     f"{_cell(w['ours'])}), has {_f(w['chamfer_over_sz3_at_budget'])}x SZ3's and "
                     f"{_f(w['chamfer_over_sperr_at_budget'])}x SPERR's Chamfer at {r['budget']} B")
        L.append(f"| {r['ratio']}:1 ({r['budget']}) | {ours} | {_cell(r.get('sz3'))} | {_cell(r.get('sperr'))} | "
                 f"{_cell(r.get('zfp'))} | {_f(r.get('chamfer_over_sz3'))} | {_f(r.get('chamfer_over_sperr'))} | "
                 f"{met} | {ab} |")
    L += ["", measured, ""]
    d = t.get("decode_on_read")
    if d:
        L += [f"Decode on read (open the map, decode every block; best of {d['repeat']} rounds, the maps timed in "
              f"turn within each round, each round starting one map further on, load {d['load']:.1f}): "
              f"fixed-length pca-64 (`encode --codec pca --code-size 64`) {d['reference_blocks_per_s']:,.0f} blocks/s; variable-rate maps over it (target: "
              ">= 0.5x):", "", "| map | B/block | decode on read, x fixed pca-64 | >= 0.5x? |", "|---|---:|---:|---|"]
        for name, r in d["ratios"].items():
            L.append(f"| {name} | {d['bytes'][name]:.1f} | {r:.2f} | {'yes' if r >= 0.5 else '**no**'} |")
        L.append("")
    return L
