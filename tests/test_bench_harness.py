"""The benchmark harness (interleaved equal rounds), the comparison of two runs, and the device check
(``sdfcodec bench --full``) as a CPU smoke test at tiny sizes: the same code and JSON keys a GPU run has."""

from __future__ import annotations

import json
import os

import pytest
import torch

from sdfcodec.bench import compare_runs, interleave, run_cases
from sdfcodec.bench.cases import CASES
from sdfcodec.errors import FormatError, InputNotFoundError, InvalidValueError


def test_interleave_alternates_equal_rounds():
    """Each round runs every callable the same calibrated number of times; the order flips every round, so the
    candidate and its baseline see the same drift of load."""
    calls = []
    tm = interleave({"cand": lambda: calls.append("c"), "base": lambda: calls.append("b")}, repeats=4,
                    min_time=0.0)
    # calibration: warm-up and one timed call of each, in order, on the configured threads and (short calls) again
    # on one thread, whose timing sets the calls per round
    assert calls[:8] == ["c", "c", "b", "b"] * 2
    rounds = calls[8:]
    assert rounds == ["c", "b", "b", "c", "c", "b", "b", "c"]  # one call per round (min_time 0), order flipped
    assert len(tm["cand"].rounds) == len(tm["base"].rounds) == 4 and tm["cand"].calls == tm["base"].calls == 1
    assert tm["cand"].best <= tm["cand"].median
    with pytest.raises(ValueError):
        interleave({"a": lambda: None}, repeats=0)


def test_rounds_take_turns_in_slices():
    """Within a round, the callables take turns in slices of their calls (a burst of load falls on both sides),
    each callable keeping its calibrated number of calls per round; the next round starts with the other."""
    from sdfcodec.bench.harness import SLICES, _rounds

    calls = []
    tm = _rounds({"c": lambda: calls.append("c"), "b": lambda: calls.append("b")}, ["c", "b"],
                 {"c": 2 * SLICES, "b": SLICES}, repeats=2, threads=None)
    first, second = calls[:3 * SLICES], calls[3 * SLICES:]
    assert first == ["c", "c", "b"] * SLICES and second == ["b", "c", "c"] * SLICES
    assert tm["c"].calls == 2 * SLICES and len(tm["c"].rounds) == len(tm["b"].rounds) == 2


def test_short_calls_are_timed_on_one_thread():
    """Calls of microseconds are timed on one thread (a parked thread at a barrier costs a time slice on a loaded
    machine); calls longer than ONE_THREAD_BELOW_S keep the configured threads, and the setting is restored."""
    import time

    from sdfcodec.bench.harness import ONE_THREAD_BELOW_S, limit_threads

    with limit_threads(2):
        seen = []
        tm = interleave({"a": lambda: seen.append(torch.get_num_threads()), "b": lambda: None}, repeats=2,
                        min_time=0.0)
        assert seen[-2:] == [1, 1] and tm["a"].threads == tm["b"].threads == 1
        assert torch.get_num_threads() == 2
        seen.clear()
        tm = interleave({"a": lambda: (seen.append(torch.get_num_threads()), time.sleep(ONE_THREAD_BELOW_S)),
                         "b": lambda: None}, repeats=2, min_time=0.0)
        assert seen[-2:] == [2, 2] and tm["a"].threads is None  # the rounds: as configured
        # work that is short on one thread but stalls on two (a barrier waiting for a parked thread) is found
        # at calibration and timed on one thread
        tm = interleave({"a": lambda: time.sleep(0.01 if torch.get_num_threads() > 1 else 0), "b": lambda: None},
                        repeats=2, min_time=0.0)
        assert tm["a"].threads == 1 and tm["a"].best < ONE_THREAD_BELOW_S


def test_paired_ratio_follows_each_round():
    """The paired ratio is the median of the per-round ratios: a round where load slowed both sides keeps its
    ratio, and a burst that struck one side in one round moves it less than the ratio of medians moves."""
    from sdfcodec.bench.harness import Timing, paired, ratio

    cand = Timing((1.0, 2.0, 4.0, 1.0, 1.1), 1)  # rounds 2 and 3: the machine twice and four times as busy
    base = Timing((2.0, 4.0, 8.0, 2.0, 2.2), 1)
    assert paired(cand, base) == pytest.approx(2.0) and ratio(cand, base)["ratio_paired"] == pytest.approx(2.0)
    stalled = Timing((2.0, 4.0, 8.0, 9.0, 2.2), 1)  # the baseline stalled in round 4 only
    assert paired(cand, stalled) == pytest.approx(2.0)
    assert ratio(cand, stalled)["ratio_of_medians"] == pytest.approx(4.0 / 1.1)


def _run(ratios, extra=None):
    recs = [{"codec": "pca", "code_size": 64, "operation": op, "batch": 64, "device": "cpu", "ratio_to_baseline": r,
             "blocks_per_s": 1e4} for op, r in ratios.items()]
    return {"records": recs + (extra or [])}


def test_compare_runs_reports_every_ratio(tmp_path):
    a, b = tmp_path / "a.json", tmp_path / "b.json"
    a.write_text(json.dumps(_run({"encode": 0.8, "decode": 1.0})))
    b.write_text(json.dumps(_run({"encode": 0.92, "decode": 0.95},
                                 [{"codec": "pca", "operation": "search", "ratio_to_baseline": 2.0}])))
    res = compare_runs(a, b)
    assert [(r["record"]["operation"], r["ratio"]) for r in res["rows"]] == [("encode", "ratio_to_baseline"),
                                                                            ("decode", "ratio_to_baseline")]
    assert res["rows"][0]["disagreement"] == pytest.approx(0.92 / 0.8 - 1)  # 15 %: worst first
    assert res["rows"][1]["disagreement"] == pytest.approx(1.0 / 0.95 - 1)
    assert res["unmatched"] == 1 and res["agree"] is True  # 0.15 is within 0.15
    assert compare_runs(a, b, tolerance=0.1)["agree"] is False
    per = compare_runs(a, b, tolerance=0.1)["by_ratio"]["ratio_to_baseline"]  # 15 % and 5.3 %: one of two within 10 %
    assert per["records"] == 2 and per["within"] == 1
    assert per["median"] == pytest.approx(((0.92 / 0.8 - 1) + (1.0 / 0.95 - 1)) / 2)
    with pytest.raises(InputNotFoundError):
        compare_runs(tmp_path / "nowhere.json", b)
    (tmp_path / "bad.json").write_text('{"records": 3}')
    with pytest.raises(FormatError, match="no benchmark records"):
        compare_runs(tmp_path / "bad.json", b)


TINY = {"decode_batch": 32, "read_blocks": 40, "search_batch": 256, "image": (64, 48)}


@pytest.fixture(scope="module")
def smoke():
    """The whole device check on the CPU at tiny sizes, one round each (what CI runs)."""
    return run_cases("cpu", quick=True, repeats=1, min_time=0.0, sizes=TINY)


def test_device_check_smoke_on_cpu(smoke):
    recs = smoke["records"]
    assert smoke["errors"] == []
    assert smoke["machine"]["device"] == "cpu" and len(smoke["load_before"]) == 3 and smoke["sizes"] == TINY
    assert [r["operation"] for r in recs] == ["pca-decode"] * 9 + ["decode-on-read", "search", "tracking"]
    dec = {(r["code_size"], r["dtype"]): r for r in recs if r["operation"] == "pca-decode"}
    assert set(dec) == {(k, d) for k in (32, 64, 128) for d in ("float32", "bfloat16", "float16")}
    for (k, d), r in dec.items():
        assert r["batch"] == 32 and r["blocks_per_s"] > 0 and r["baseline_blocks_per_s"] > 0
        assert r["ratio_to_baseline"] == pytest.approx(r["blocks_per_s"] / r["baseline_blocks_per_s"])
        assert r["copy_bytes_per_s"] == pytest.approx(r["copy_blocks_per_s"] * 4096 * (4 if d == "float32" else 2))
        # the error a low-precision decode adds, in metres: 0 for float32 (it is the reference); bfloat16 keeps
        # 8 bits of mantissa (relative 2^-9 per rounding) and float16 11, on values of order 1 times 0.14 m
        if d == "float32":
            assert r["max_abs_error_m"] == 0.0
        else:
            assert 0 < r["max_abs_error_m"] < (0.02 if d == "bfloat16" else 0.003)
    assert dec[(64, "bfloat16")]["max_abs_error_m"] > dec[(64, "float16")]["max_abs_error_m"]
    read = next(r for r in recs if r["operation"] == "decode-on-read")
    assert read["batch"] == 40 and read["memcpy_blocks_per_s"] > 0 and read["in_memory_decode_blocks_per_s"] > 0
    track = recs[-1]
    assert track["resolution"] == [64, 48] and track["success"] and track["frames_per_s"] > 0
    assert track["translation_error_m"] < 0.005  # started ~1.5 cm off the true pose of the ray-cast image
    assert all("load_before" in r and "ratio_to_baseline" in r for r in recs)


def test_device_check_errors(monkeypatch):
    with pytest.raises(InvalidValueError, match="unknown bench case"):
        run_cases("cpu", quick=True, cases=["nope"])
    assert list(CASES) == ["pca-decode", "decode-on-read", "search", "tracking"]

    def broken(setup):
        raise RuntimeError("no such kernel")

    monkeypatch.setitem(CASES, "tracking", broken)  # one case failing on a device costs only its own figures
    seen = []
    doc = run_cases("cpu", quick=True, repeats=1, min_time=0.0, sizes=TINY, cases=["search", "tracking"],
                    checkpoint=lambda d: seen.append(len(d["records"])))
    assert [r["operation"] for r in doc["records"]] == ["search"] and seen == [1, 1]
    assert doc["errors"] == [{"case": "tracking", "error": "RuntimeError: no such kernel"}]


def test_cli_bench_full_and_compare(tmp_path, smoke):
    """``--full --cases`` writes the document; ``--compare`` reads two and says how far they agree."""
    from typer.testing import CliRunner

    from sdfcodec.cli import app

    out = tmp_path / "run.json"
    r = CliRunner().invoke(app, ["bench", "--full", "--quick", "--cases", "search", "--repeats", "2", "--threads", "1",
                                 "--out", str(out)])
    assert r.exit_code == 0, r.output
    doc = json.loads(out.read_text())
    assert doc["schema"] == "sdfcodec-bench/1" and [x["operation"] for x in doc["records"]] == ["search"]
    assert doc["records"][0]["repeats"] == 2 and doc["mode"] == "quick" and doc["machine"]["torch_threads"] == 1
    assert doc["machine"]["thread_env"]["OPENBLAS_THREAD_TIMEOUT"] == os.environ["OPENBLAS_THREAD_TIMEOUT"]
    assert {"ratio_to_baseline", "ratio_of_bests", "ratio_paired", "ratio_cpu"} <= set(doc["records"][0])
    (tmp_path / "smoke.json").write_text(json.dumps(smoke))
    r = CliRunner().invoke(app, ["bench", "--compare", str(out), str(tmp_path / "smoke.json"), "--json"])
    assert r.exit_code == 0, r.output
    res = json.loads(r.stdout)
    # the search record differs in batch between the runs: nothing matches, both sides counted unmatched
    assert res["rows"] == [] and res["unmatched"] == 1 + len(smoke["records"]) and res["agree"] is False
    same = json.loads(CliRunner().invoke(app, ["bench", "--compare", str(out), str(out), "--json"]).stdout)
    assert same["agree"] and same["worst"] == 0 and same["by_ratio"]["ratio_cpu"]["records"] == 1


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_device_check_on_cuda_writes_the_cpu_keys(smoke):
    """Where a GPU is present: the device check runs there at tiny sizes, without errors, with the keys the CPU
    run writes (the H100/H200 figures themselves come from `sdfcodec bench --full --device cuda`)."""
    doc = run_cases("cuda", quick=True, repeats=1, min_time=0.0, sizes=TINY)
    assert doc["errors"] == [] and "device_name" in doc["machine"]
    keys = lambda recs: [sorted(set(r) - {"ratio_cpu"}) for r in recs]  # noqa: E731 (CPU time may read 0)
    assert keys(doc["records"]) == keys(smoke["records"])
    assert all(r["device"].startswith("cuda") for r in doc["records"])
