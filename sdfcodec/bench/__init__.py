"""Benchmarks: every figure beside baselines measured in the same run, interleaved with them.

``sdfcodec bench`` (the CLI) and the functions here time codecs, decode on read, search and tracking, each
figure interleaved with its roofline (a preallocated matrix product, a memory copy) in ``repeats`` equal
rounds, reporting best and median, with the machine and its load (``os.getloadavg()``) recorded.

- :mod:`~sdfcodec.bench.harness`: interleaved timing, machine and load.
- :mod:`~sdfcodec.bench.codecs`: codec encode/decode and decode on read; the benchmark registrations of
  plugins (:func:`register_bench`, spec/codec-plugins.md section 5).
- :mod:`~sdfcodec.bench.search`: the search kernel and whole searches.
- :mod:`~sdfcodec.bench.cases`: the device check (``sdfcodec bench --full``): one table of cases, one JSON.
- :mod:`~sdfcodec.bench.compare`: how far two runs' ratios agree.
"""

from __future__ import annotations

from .codecs import (PAPER_US_PER_BLOCK, BenchSpec, bench_codec, bench_codec_instance, bench_decode_in_place,
                     bench_decode_on_read,
                     bench_instance, fused_style_weights, memcpy_bytes_per_s, register_bench, roofline_shapes, vs_paper)
from .compare import compare_runs
from .cases import run_cases
from .harness import interleave, time_call
from .search import bench_search

__all__ = ["time_call", "interleave", "bench_codec", "fused_style_weights", "bench_codec_instance",
           "bench_decode_on_read", "bench_decode_in_place", "memcpy_bytes_per_s", "roofline_shapes", "register_bench", "bench_instance",
           "BenchSpec", "vs_paper", "PAPER_US_PER_BLOCK", "bench_search", "compare_runs", "run_cases"]
