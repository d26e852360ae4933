"""Timing that holds on a loaded machine: every figure interleaved with its baselines, N equal repetitions.

A figure is a candidate callable and one or more baseline callables (the roofline: a preallocated matrix
product, a memory copy...). :func:`interleave` times them in rounds: each round runs every callable for the
same fixed number of calls (calibrated once, before the first round, so that a call group lasts about
``min_time``), alternating the order from round to round (candidate first, then baselines first) and, within a
round, taking turns in up to :data:`SLICES` slices of calls, so that a burst of load from another process falls
on both sides of the ratio. It returns per-round seconds per call;
:class:`Timing` gives best and median, and :func:`ratio` the ratio of medians (what records call
``ratio_to_baseline``) and of bests.

The machine (:func:`machine`) and its load (``os.getloadavg()``, :func:`load`) are recorded with every run.
"""

from __future__ import annotations

import contextlib
import gc
import os
import platform
import statistics
import sys
import time
from dataclasses import dataclass
from typing import Any, Callable, Iterator, Mapping

from ..errors import InvalidValueError

__all__ = ["Timing", "interleave", "ratio", "paired", "time_call", "load", "machine", "run_document", "limit_threads"]


@dataclass(frozen=True)
class Timing:
    """Seconds per call of one callable, one value per round (``rounds``: wall clock; ``cpu_rounds``: CPU time
    of this process, all its threads), and the calls timed per round."""

    rounds: tuple[float, ...]
    calls: int
    cpu_rounds: tuple[float, ...] = ()
    threads: int | None = None  # 1: timed on one thread (short calls, see interleave); None: as configured

    @property
    def best(self) -> float:
        return min(self.rounds)

    @property
    def median(self) -> float:
        return statistics.median(self.rounds)

    def summary(self, per_call: float = 1.0, unit: str = "blocks") -> dict[str, Any]:
        """``{unit}_per_s`` (from the median) and ``{unit}_per_s_best`` for ``per_call`` units of work per call,
        with the seconds per call of every round."""
        return {f"{unit}_per_s": per_call / self.median, f"{unit}_per_s_best": per_call / self.best,
                "seconds_median": self.median, "seconds_best": self.best, "seconds_rounds": list(self.rounds),
                "calls_per_round": self.calls}


#: Figures whose calls all take less than this on one thread (seconds, at calibration) are timed on one thread
#: by :func:`interleave`: a multi-threaded call waits at its barriers for a thread the scheduler has parked, which
#: on a loaded machine costs a time slice (milliseconds) per barrier, so its time follows the load, not the code.
#: Two `bench --quick` runs at load 6-7 disagreed 100-500-fold on batch 1 and 64 ratios timed on two threads; with
#: a 2 ms bound, calls of 2-150 ms (weighted encodes of 1 and 64 blocks, whose baselines read a 4096 x 2080 Gram
#: table) still stalled in one run and not the other: 15 against 1,097 blocks/s, median and best of one figure.
ONE_THREAD_BELOW_S = 0.1
#: Calls up to this long on the configured threads are timed once more on one thread before that choice (the
#: stall the rule avoids also strikes the calibration: pca-64 encode of one block took 21-36 ms a call on two
#: threads at load 7 for a whole run, against 0.1 ms on one); longer work keeps the configured threads without
#: paying for a one-thread calibration.
_RECHECK_BELOW_S = 1.0


#: A warm-up call longer than this (seconds) is the calibration itself: first-call costs (allocations, page
#: faults, kernel selection) are small beside it, and a second call would add seconds per figure (a masked encode
#: of 4096 pca-128 blocks takes 16 s a call at load 5).
_WARM_ENOUGH_S = 1.0


def _one_call(fn: Callable[[], object]) -> float:
    """Seconds of one call of ``fn`` after a warm-up call (allocations, page faults, kernel selection), or of the
    warm-up call when it took longer than :data:`_WARM_ENOUGH_S`."""
    t0 = time.perf_counter()
    fn()
    warm = time.perf_counter() - t0
    if warm > _WARM_ENOUGH_S:
        return warm
    t0 = time.perf_counter()
    fn()
    return max(time.perf_counter() - t0, 1e-7)


def interleave(fns: Mapping[str, Callable[[], object]], *, repeats: int = 5, min_time: float = 0.2
               ) -> dict[str, Timing]:
    """Time every callable of ``fns`` (name -> callable; by convention the candidate first, then its baselines)
    in ``repeats`` interleaved rounds of equal length; see the module docstring. Returns name -> :class:`Timing`.
    When every callable's call takes less than :data:`ONE_THREAD_BELOW_S` on one thread, all of them are timed
    on one thread (torch and numpy's BLAS; ``Timing.threads`` says so). A callable that runs asynchronously
    (CUDA) must synchronise before it returns."""
    if repeats < 1:
        raise InvalidValueError(f"repeats must be >= 1, got {repeats}")
    names = list(fns)
    one = {n: _one_call(fns[n]) for n in names}
    threads = None
    if max(one.values()) < _RECHECK_BELOW_S:  # short on one thread? (a barrier stall may have made it look long)
        with limit_threads(1):
            one1 = {n: _one_call(fns[n]) for n in names}
        if max(one1.values()) < ONE_THREAD_BELOW_S:  # the calls per round from the one-thread calibration
            one, threads = one1, 1
    with limit_threads(threads), _no_gc():  # calibrated on the configured threads: a one-thread round may run longer
        return _rounds(fns, names, {n: max(1, round(min_time / t)) for n, t in one.items()}, repeats, threads)


@contextlib.contextmanager
def _no_gc() -> Iterator[None]:
    """The rounds without Python's cyclic garbage collector (as :mod:`timeit` times): a collection pass costs
    in proportion to every object the whole process holds, not to the call that triggered it, and lands on
    whichever side allocates Python objects (a codec's call, not numpy's product). No collection first (timeit
    makes none either): disabled, none runs in the rounds anyway, and a full pass costs 0.15-0.5 CPU-s in a
    process holding torch and a test session (42 passes were 22 % of test_bench_harness.py and
    test_bench_progress.py's CPU time)."""
    was = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if was:
            gc.enable()


#: A round is cut into up to this many slices, each running every callable's share of its calls in turn, so that
#: a burst of load (another process taking the core for a few time slices) falls on the candidate and its
#: baselines alike rather than on whichever ran a 50 ms block of calls at that moment; a slice still runs each
#: callable several calls in a row (warm caches), and calls longer than a slice are not cut.
SLICES = 8


def _rounds(fns: Mapping[str, Callable[[], object]], names: list[str], calls: dict[str, int], repeats: int,
            threads: int | None) -> dict[str, Timing]:
    rounds: dict[str, list[float]] = {n: [] for n in names}
    cpu: dict[str, list[float]] = {n: [] for n in names}
    slices = max(1, min(SLICES, *calls.values()))
    for r in range(repeats):
        order = names if r % 2 == 0 else names[::-1]  # alternate the order: drifting load hits both sides
        wall = dict.fromkeys(names, 0.0)
        spent = dict.fromkeys(names, 0.0)
        for s in range(slices):
            for n in order:
                fn, k = fns[n], calls[n] * (s + 1) // slices - calls[n] * s // slices
                c0, t0 = time.process_time(), time.perf_counter()
                for _ in range(k):
                    fn()
                wall[n] += time.perf_counter() - t0
                spent[n] += time.process_time() - c0
        for n in names:
            rounds[n].append(wall[n] / calls[n])
            cpu[n].append(spent[n] / calls[n])
    return {n: Timing(tuple(rounds[n]), calls[n], tuple(cpu[n]), threads) for n in names}


def ratio(candidate: Timing, baseline: Timing) -> dict[str, float]:
    """Candidate speed over baseline speed (> 1: the candidate is faster), several ways:

    ``ratio_of_medians`` and ``ratio_of_bests`` (wall clock); ``ratio_paired``, the median over rounds of the
    ratio within a round (a round's candidate and baseline ran back to back, under the same load); and
    ``ratio_cpu``, of the median CPU seconds per call (the work done, whatever share of the cores the process
    got: on a loaded machine the steadiest, but it counts every thread's time, so it measures cost, not
    latency)."""
    out = {"ratio_of_medians": baseline.median / candidate.median, "ratio_of_bests": baseline.best / candidate.best,
           "ratio_paired": paired(candidate, baseline)}
    if candidate.cpu_rounds and baseline.cpu_rounds:
        c, b = statistics.median(candidate.cpu_rounds), statistics.median(baseline.cpu_rounds)
        if c > 0 and b > 0:
            out["ratio_cpu"] = b / c
    return out


def paired(candidate: Timing, baseline: Timing) -> float:
    """Baseline seconds over candidate seconds within each round, the median over rounds (> 1: the candidate is
    faster): the two ran back to back in a round, so a burst of load that slows one round of both leaves its
    ratio, where a ratio of medians can pair a quiet round of one with a loaded round of the other. Both must
    come from the same :func:`interleave` call."""
    return statistics.median(b / c for b, c in zip(baseline.rounds, candidate.rounds))


def time_call(fn: Callable[[], object], min_time: float = 0.2, repeats: int = 3) -> float:
    """Best seconds per call of ``fn`` alone over ``repeats`` equal rounds of about ``min_time`` each (for a
    figure without a baseline; figures with one use :func:`interleave`)."""
    return interleave({"fn": fn}, repeats=repeats, min_time=min_time)["fn"].best


def load() -> list[float]:
    """``os.getloadavg()`` (1, 5 and 15 minute load averages) as a list; [] where the OS has none."""
    try:
        return [round(x, 2) for x in os.getloadavg()]
    except OSError:
        return []


#: The environment variables that set how the BLAS and OpenMP threads run (recorded with every run: an OpenBLAS
#: left spinning after its products slows whatever runs next on the same cores; ``sdfcodec``'s command line sets
#: ``OPENBLAS_THREAD_TIMEOUT``).
THREAD_ENV = ("OPENBLAS_THREAD_TIMEOUT", "OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "OMP_WAIT_POLICY",
              "GOMP_SPINCOUNT", "MKL_NUM_THREADS")


def machine(device: str = "cpu") -> dict[str, Any]:
    """What the figures were measured on: CPU, cores, the torch threads and version, the variables of
    :data:`THREAD_ENV` that are set (``thread_env``), and the device's name."""
    info: dict[str, Any] = {"platform": platform.platform(), "processor": platform.processor() or platform.machine(),
                            "cpus": os.cpu_count(), "python": platform.python_version()}
    try:
        with open("/proc/cpuinfo") as f:
            model = next((ln.split(":", 1)[1].strip() for ln in f if ln.startswith("model name")), None)
        if model:
            info["processor"] = model
    except OSError:
        pass
    import numpy as np
    import torch

    info.update(numpy=np.__version__, torch=torch.__version__, torch_threads=torch.get_num_threads(),
                device=device, thread_env={k: os.environ[k] for k in THREAD_ENV if k in os.environ})
    if device.startswith("cuda") and torch.cuda.is_available():
        p = torch.cuda.get_device_properties(torch.device(device))
        info.update(device_name=p.name, device_memory_bytes=p.total_memory, cuda=torch.version.cuda)
    return info


def run_document(mode: str, device: str = "cpu") -> dict[str, Any]:
    """The head of a run's JSON document (``sdfcodec bench --out``, ``--full``): ``schema``, ``command``,
    ``mode``, ``machine`` and ``load_before``; the caller adds ``records``, ``load_after`` and ``seconds``."""
    return {"schema": "sdfcodec-bench/1", "command": " ".join(["sdfcodec", *sys.argv[1:]]), "mode": mode,
            "machine": machine(device), "load_before": load()}


@contextlib.contextmanager
def limit_threads(n: int | None) -> Iterator[None]:
    """Run the block with ``n`` threads in torch and in numpy's BLAS (None: as configured). On a loaded machine
    one thread measures steadier: a multi-threaded kernel whose threads are not scheduled together waits at its
    barriers for the slowest, which a busy machine makes arbitrarily slow."""
    if n is None:
        yield
        return
    import torch
    from threadpoolctl import threadpool_limits

    before = torch.get_num_threads()
    torch.set_num_threads(n)
    try:
        with threadpool_limits(n):
            yield
    finally:
        torch.set_num_threads(before)
