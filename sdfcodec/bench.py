"""Throughput benchmarks, each beside a baseline measured in the same run (never as timed unit tests).

For a codec of code size ``k`` the baseline of encode is a plain numpy matrix product ``(B, 4096) @ (4096, k)``
and of decode ``(B, k) @ (k, 4096)``: the work a linear codec cannot avoid. A ratio near 1 means the codec adds
no overhead to the matrix product; the paper's GPU implementation took 405-645 microseconds per block.
"""

from __future__ import annotations

import time
from typing import Callable, Iterable

import numpy as np
import torch

from .registry import get_codec
from .testing import analytic_blocks

__all__ = ["time_call", "bench_codec", "PAPER_US_PER_BLOCK"]

PAPER_US_PER_BLOCK = (405.0, 645.0)


def time_call(fn: Callable[[], object], min_time: float = 0.2, repeats: int = 3) -> float:
    """Best seconds per call of ``fn`` over ``repeats`` rounds, each running at least ``min_time``."""
    fn()  # warm-up: allocations, kernel selection, caches
    best = float("inf")
    for _ in range(repeats):
        n, t0 = 0, time.perf_counter()
        while True:
            fn()
            n += 1
            dt = time.perf_counter() - t0
            if dt >= min_time:
                break
        best = min(best, dt / n)
    return best


def bench_codec(codec_id: str, code_sizes: Iterable[int], batches: Iterable[int], *, device: str = "cpu",
                min_time: float = 0.2, progress: Callable[[str], None] | None = None) -> list[dict]:
    """Encode/decode blocks/s of ``codec_id`` at each code size and batch, beside the numpy matmul baseline.

    Returns one record per (code_size, operation, batch) with ``codec``, ``code_size``, ``operation``,
    ``batch``, ``device``, ``blocks_per_s``, ``baseline_blocks_per_s``, ``ratio_to_baseline`` and
    ``us_per_block``.
    """
    train = analytic_blocks(512, seed=3)
    records = []
    dev = torch.device(device)
    for k in code_sizes:
        codec = get_codec(codec_id, code_size=k) if codec_id != "raw" else get_codec(codec_id)
        if codec.requires_fit:
            codec.fit(train)
        k = codec.code_size
        rng = np.random.default_rng(0)
        w_enc = rng.standard_normal((4096, k), dtype=np.float32)
        w_dec = rng.standard_normal((k, 4096), dtype=np.float32)
        for b in batches:
            reps = -(-b // len(train))
            x_np = np.concatenate([train] * reps)[:b]
            x = torch.from_numpy(x_np).to(dev)
            codes = codec.encode(x)
            x_flat = x_np.reshape(b, 4096)
            c_np = codes.cpu().numpy()
            sync = torch.cuda.synchronize if dev.type == "cuda" else (lambda: None)
            for op, fn, base in (
                ("encode", lambda: (codec.encode(x), sync()), lambda: x_flat @ w_enc),
                ("decode", lambda: (codec.decode(codes), sync()), lambda: c_np @ w_dec),
            ):
                if progress:
                    progress(f"{codec_id}-{k} {op} batch {b}")
                t = time_call(fn, min_time)
                tb = time_call(base, min_time)
                records.append({
                    "codec": codec_id, "code_size": k, "operation": op, "batch": b, "device": str(dev),
                    "blocks_per_s": b / t, "baseline": "numpy matmul", "baseline_blocks_per_s": b / tb,
                    "ratio_to_baseline": tb / t, "us_per_block": 1e6 * t / b,
                })
    return records
