"""examples/peers_targets.py: peers read at our exact bytes, the whole-map equal-Chamfer reading, the issue's
targets and the decode-on-read ratio, each against a hand computation on made-up points."""

from __future__ import annotations

import importlib.util
import math
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
_spec = importlib.util.spec_from_file_location("peers_targets", ROOT / "examples" / "peers_targets.py")
pt = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(pt)


def P(b, chamfer, f1=1.0, mx=1.0, **kw):
    return {"bytes_per_block": b, "chamfer_mm": chamfer, "f1": f1, "max_error_cm": mx, "setting": f"{b} B", **kw}


def test_at_bytes_reads_log_log_for_errors_and_linear_for_f1():
    curve = [P(400, 1.0, f1=1.0, mx=0.5), P(100, 4.0, f1=0.8, mx=2.0)]  # unsorted on purpose
    # 200 B is half-way between 100 and 400 in log(bytes): the geometric mean of the errors, the mean of F@1
    assert pt.at_bytes(curve, 200, "chamfer_mm") == pytest.approx(2.0)
    assert pt.at_bytes(curve, 200, "max_error_cm") == pytest.approx(1.0)
    assert pt.at_bytes(curve, 200, "f1") == pytest.approx(0.9)
    # a quarter of the way in log(bytes): 100 * 4 ** 0.25
    assert pt.at_bytes(curve, 100 * 4 ** 0.25, "chamfer_mm") == pytest.approx(4.0 * 0.25 ** 0.25)
    assert pt.at_bytes(curve, 100, "chamfer_mm") == 4.0  # a measured point as is
    assert pt.at_bytes(curve, 99, "chamfer_mm") is None and pt.at_bytes(curve, 401, "f1") is None  # never extrapolated
    assert pt.at_bytes([P(100, None), P(400, 1.0)], 200, "chamfer_mm") is None  # a point without the value is skipped


def test_bytes_at_chamfer_first_crossing_in_log_log():
    curve = [P(100, 8.0), P(200, 4.0), P(400, 2.0), P(800, 2.5)]
    # 2 sqrt(2) mm lies half-way (in log) between 4 mm at 200 B and 2 mm at 400 B: 200 sqrt(2) B
    assert pt.bytes_at_chamfer(curve, 2 * math.sqrt(2)) == pytest.approx(200 * math.sqrt(2))
    assert pt.bytes_at_chamfer(curve, 4.0) == 200
    assert pt.bytes_at_chamfer(curve, 9.0) == 100  # the smallest map already reaches it: its bytes
    assert pt.bytes_at_chamfer(curve, 1.0) is None  # never reached


def test_equal_bytes_rows_ratios_and_verdicts():
    ours = [P(127.0, 3.9, f1=0.97, options={"target-bytes": 128}),
            P(255.0, 3.0, f1=0.98, options={"target-bytes": 256})]
    peers = {"sz3": [P(64, 16.0), P(256, 4.0)], "sperr": [P(64, 12.0), P(512, 12.0)], "zfp": [P(512, 30.0)]}
    refused = [{"dataset": "d", "options": {"target-bytes": 64}, "message": "below: at least 70.1"}]
    rows = {r["budget"]: r for r in pt.equal_bytes_rows(ours, peers, refused, budgets=(256, 128, 64))}
    r = rows[128]
    sz3 = 16.0 * (4.0 / 16.0) ** (math.log(127 / 64) / math.log(4))  # SZ3 read at 127 B, log-log
    assert r["sz3"]["chamfer_mm"] == pytest.approx(sz3)
    assert r["chamfer_over_sz3"] == pytest.approx(3.9 / sz3) and r["chamfer_over_sperr"] == pytest.approx(3.9 / 12)
    assert r["zfp"]["chamfer_mm"] is None and r["chamfer_over_zfp"] is None  # 127 B is outside ZFP's points
    assert r["met"] is True and r["absolute_met"] is True  # 3.9 / 8.0 <= 0.5 and 0.325 <= 0.5; F 0.97, 3.9 mm
    sz3_255 = 16.0 * (4.0 / 16.0) ** (math.log(255 / 64) / math.log(4))
    assert rows[256]["chamfer_over_sz3"] == pytest.approx(3.0 / sz3_255) and rows[256]["met"] is False  # ~0.75
    assert rows[256]["ratio"] == 64 and rows[128]["ratio"] == 128
    assert rows[64]["ours"] is None and rows[64]["refused"]["message"] == "below: at least 70.1"
    assert rows[64]["met"] is None and rows[64]["absolute_met"] is None
    assert "within_budget" not in rows[64]  # nothing of ours fits in 64 B


def test_refused_above_the_ceiling_reads_our_largest_map_against_the_peers_at_the_budget():
    ours = [P(100.0, 4.0, options={"target-bytes": 100}), P(279.0, 3.0, options={"target-bytes": 280})]
    peers = {"sz3": [P(256, 8.0), P(1024, 2.0)], "sperr": [P(512, 6.0)]}
    refused = [{"dataset": "d", "options": {"target-bytes": 512}, "message": "above: at most 279.0"}]
    (r,) = pt.equal_bytes_rows(ours, peers, refused, budgets=(512,))
    assert r["ours"] is None and r["met"] is None
    w = r["within_budget"]
    assert w["ours"]["bytes_per_block"] == 279.0
    assert w["chamfer_over_sz3_at_budget"] == pytest.approx(3.0 / 4.0)  # SZ3 at 512 B: half-way in log, 4 mm
    assert w["chamfer_over_sperr_at_budget"] == pytest.approx(0.5)


def test_equal_chamfer_whole_map():
    ours = [P(96, 5.0), P(128, 4.0), P(192, 3.0)]
    sz3 = [P(374, 3.79), P(200, 6.0), P(500, 2.0)]
    rows = pt.equal_chamfer(ours, sz3)
    assert [r["ref"]["bytes_per_block"] for r in rows] == [200, 374, 500]
    b = 128 * 1.5 ** (math.log(4 / 3.79) / math.log(4 / 3))  # between 128 B (4 mm) and 192 B (3 mm), log-log
    assert rows[1]["bytes_at_equal_chamfer"] == pytest.approx(b)
    assert rows[1]["bytes_ratio"] == pytest.approx(b / 374) and rows[1]["met"] is True
    assert rows[1]["smallest_reaching"]["bytes_per_block"] == 192
    assert rows[0]["bytes_at_equal_chamfer"] == 96 and rows[0]["bytes_ratio"] == pytest.approx(0.48)
    assert rows[2]["bytes_at_equal_chamfer"] is None and rows[2]["met"] is None  # ours never reach 2 mm
    back = pt.equal_chamfer(sz3, ours)  # the reverse reading: SZ3's bytes at 4 mm lie between 200 B and 374 B
    b4 = 200 * (374 / 200) ** (math.log(6 / 4) / math.log(6 / 3.79))
    assert back[1]["bytes_at_equal_chamfer"] == pytest.approx(b4) and back[1]["met"] is False


def test_decode_on_read_is_best_time_over_best_time():
    times = {"fixed": [0.2, 0.1, 0.15], "vr": [0.3, 0.25], "fast": [0.05]}
    assert pt.decode_on_read(times, "fixed") == pytest.approx({"vr": 0.4, "fast": 2.0})


def test_peer_at_holds_a_curve_that_stops_short_at_its_largest_point():
    sz3 = [P(64, 0.8), P(221.8, 0.001)]  # SZ3 at float precision: no more bytes to give
    assert pt.peer_at(sz3, 512, "chamfer_mm") == 0.001
    assert pt.peer_at(sz3, 128, "chamfer_mm") == pytest.approx(pt.at_bytes(sz3, 128, "chamfer_mm"))
    assert pt.peer_at(sz3, 32, "chamfer_mm") is None  # below its smallest point: nothing
