"""Shared fixtures. Tests that need the real data in ../shared/data skip with a reason when it is absent."""

from __future__ import annotations

from contextlib import contextmanager
from pathlib import Path

import os
import shutil
import signal

# As the command line does (sdfcodec/cli/__init__.py): numpy's OpenBLAS threads go to sleep after a product
# instead of spinning 0.1 s on the cores the next torch call needs. Set here unconditionally, not by importing
# the command line: pytest loads plugins (ours among them) that import numpy before this file, and the xdist
# workers, which inherit the variable, load numpy after it is set.
os.environ.setdefault("OPENBLAS_THREAD_TIMEOUT", "4")


def _memory_temp_root() -> None:
    """Temporary files (pytest's tmp_path, tempfile, every subprocess) in /dev/shm where it is a tmpfs with room,
    unless TMPDIR is set. The suite writes and removes tens of thousands of map directories; on the project's
    VM (ext4 mounted with ``discard``) removing a directory takes ~2 ms against 0.04 ms in memory, and the
    waits were most of some tests' time: test_reliability.py + test_mapfile.py 158 s -> 85 s, the fault
    injection of test_writes.py 42 s -> 24 s, the same CPU time (pytest -n 0, load 5-7). What the tests check
    does not depend on the file system: the crash tests kill processes, never the machine, and the disk-full
    test mounts a small tmpfs of its own. Set here, at import, before pytest picks its base directory (the
    xdist workers, started later, inherit the variable and get their directories from the controller)."""
    import tempfile

    if os.environ.get("TMPDIR") or os.environ.get("PYTEST_DEBUG_TEMPROOT"):
        return
    try:
        with open("/proc/mounts") as f:
            tmpfs = any(line.split()[1:3] == ["/dev/shm", "tmpfs"] for line in f)
        free = shutil.disk_usage("/dev/shm").free
    except OSError:
        return
    if tmpfs and free > 4 << 30 and os.access("/dev/shm", os.W_OK | os.X_OK):
        os.environ["TMPDIR"] = tempfile.tempdir = "/dev/shm"


_memory_temp_root()

import numpy as np  # noqa: E402
import pytest
from hypothesis import settings

# Property tests run the same examples on every run (a suite that passes once passes again; CI never meets a
# new random case in someone else's change). Explore new random cases locally with HYPOTHESIS_PROFILE=explore.
settings.register_profile("deterministic", derandomize=True, database=None)
settings.register_profile("explore", derandomize=False)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "deterministic"))

# --regen-golden and the regen_golden fixture: the plugin sdfcodec ships for every codec package. Installed,
# its pytest11 entry point (named like the module) loads it first and this line is a no-op; from a bare
# checkout it loads it here.
pytest_plugins = ["sdfcodec.testing.pytest_plugin"]

ROOT = Path(__file__).resolve().parents[1]

# A shell without job control starts a background job (`make test &`, `nohup ... &`) with SIGINT ignored, and an
# ignored signal stays ignored across exec: the Ctrl-C tests' child interpreters would then get no
# KeyboardInterrupt at all. A handler of this process's own is reset to the default in every child it starts.
if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)


def pytest_configure(config):
    """Query models the search builds are cached on disk (sdfcodec.search.cache): the suite keeps them in a
    directory of its own, made fresh per run (xdist workers inherit it), never in the user's ~/.cache.

    Under pytest-xdist each worker gets its share of the cores as torch's and OpenBLAS's default threads
    (``OMP_NUM_THREADS``, unless set): two workers with two threads each on two cores wait on each other's
    spinning threads (the suite on the 2-core machine: 484 s with 2 threads a worker, 411 s with 1). Tests that
    need more threads ask for them (``torch.set_num_threads``, threadpoolctl). So do numba's parallel kernels
    (``NUMBA_NUM_THREADS``; numba's default is every core, whatever ``OMP_NUM_THREADS`` says): with two threads
    in each of two workers, the writer's parallel encode in one worker slowed the other's work
    (test_conformance.py + test_fast_encode.py + test_observed.py, -n 2, load ~2, twice each, alternated:
    29.3-29.6 s -> 16.8-17.1 s, 43.3-43.8 -> 35.1-36.0 CPU-s)."""
    import tempfile

    workers = getattr(config.option, "numprocesses", None)
    if isinstance(workers, int) and workers > 1:
        share = str(max(1, (os.cpu_count() or 1) // workers))
        os.environ.setdefault("OMP_NUM_THREADS", share)
        os.environ.setdefault("NUMBA_NUM_THREADS", share)
        if not os.environ.get("PYTEST_XDIST_WORKER"):
            _start_numba_warm()

    from sdfcodec.search.cache import CACHE_ENV

    if CACHE_ENV not in os.environ:
        os.environ[CACHE_ENV] = config._sdfcodec_cache = tempfile.mkdtemp(prefix="sdfcodec-test-cache-")  # noqa: SLF001


# The numba kernels and the sources whose on-disk cache (numba's, in the __pycache__ beside each) the jobs of
# tests/numba_warm.py fill.
NUMBA_WARM_JOBS = {"pca": ["plugins/sdfcodec_pca/kernels.py"],
                   "pinned": ["sdfcodec/core/anskernels.py", "sdfcodec/core/pinkernels.py"]}


def _numba_cached(sources: list[str]) -> bool:
    """Whether numba's cache beside each source holds entries written after the source last changed (a cheap
    test: an entry numba finds stale, or a kernel not yet cached, is compiled where it is used, as always).

    Only the entries of the source's functions as they are now count: numba names an index file
    ``STEM.FUNCTION-LINE.pyXY.nbi`` (LINE: the function's first decorator) and never removes those of earlier
    versions, so in a checkout that has seen a kernel move, the oldest entry was always older than the source and
    the warm-up ran before every run (~15 s of a file's run with -n 2, kernels loaded from the cache all the same)."""
    import ast

    for src in (ROOT / s for s in sources):
        now = {f"{src.stem}.{f.name}-{min([f.lineno] + [d.lineno for d in f.decorator_list])}"
               for f in ast.walk(ast.parse(src.read_text())) if isinstance(f, ast.FunctionDef)}
        entries = [e for e in (src.parent / "__pycache__").glob(f"{src.stem}.*.nbi")
                   if e.name.rsplit(".", 2)[0] in now]
        if not entries or min(e.stat().st_mtime for e in entries) < src.stat().st_mtime:
            return False
    return True


def _start_numba_warm() -> None:
    """The controller of an xdist run starts tests/numba_warm.py's jobs while the workers import and collect,
    and waits for them before the first test is handed out (pytest_xdist_node_collection_finished). In a fresh
    checkout (CI's clean clone) nothing is compiled: each worker compiled the same kernels (~70 CPU-s), and so
    did every subprocess a test started before a worker had saved them; run once, split over the two cores,
    the workers load them. Skipped without numba, with the cache filled (the next runs), or with
    SDFCODEC_TEST_NO_WARM set."""
    import importlib.util
    import subprocess
    import sys

    if os.environ.get("SDFCODEC_TEST_NO_WARM") or importlib.util.find_spec("numba") is None:
        return
    custom = bool(os.environ.get("NUMBA_CACHE_DIR"))  # another cache directory: not checked, warmed
    _WARMING.extend(
        subprocess.Popen([sys.executable, str(ROOT / "tests" / "numba_warm.py"), job], cwd=ROOT,
                         stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        for job, sources in NUMBA_WARM_JOBS.items() if custom or not _numba_cached(sources))


_WARMING: list = []  # the controller's running warm-up jobs


@pytest.hookimpl(optionalhook=True)
def pytest_xdist_node_collection_finished(node, ids):
    """Wait for the numba warm-up (:func:`_start_numba_warm`) before the controller hands out tests; a job that
    fails or hangs only leaves its kernels to be compiled where they are used."""
    import subprocess

    while _WARMING:
        job = _WARMING.pop()
        try:
            job.wait(timeout=300)
        except subprocess.TimeoutExpired:
            job.kill()
            job.wait()


# Modules whose module-scoped fixtures are expensive (a fork server preloading torch, a pip install, trained
# networks, a whole study's run, fused sequences), or whose few tests are long. Under pytest-xdist's default
# distribution (`-n 2`: load) each of these modules runs on one worker, so its fixtures are built once instead
# of in both workers, and these modules are handed out (most tests first) before the single tests, so that no
# long test is left alone at the end of the run while the other worker idles. Every other test is handed out
# one by one, as xdist does. (xdist's own `--dist loadgroup` does not group tests under pytest 9.) The two
# modules reading the one `sdfcodec bench` run (bench_run, ~20 s of CPU) share a worker: in two workers asking
# for it at once, RunShared built it twice. test_architecture's checks share one parse of every module (~3 s),
# test_conformance_builtin's one fit of each codec (sdfcodec.testing fits a reference once per process).
# test_variable_rate: handed out one test at a time, its ~9 s rate-control test came among the run's last (they go
# in collection order) and ended the run alone on one worker, the other idle 7-9 s; its module fixtures (a pca-32
# fit, the analytic scene) were built in both workers.
WORKER_GROUPS = {name: name for name in (
    "test_reliability", "test_writes", "test_plugin_package", "test_plugin_compat", "test_codecs_nn",
    "test_rate_distortion", "test_peers_study", "test_bench_harness", "test_search", "test_building",
    "test_shards", "test_tracking", "test_evaluation", "test_view", "test_architecture",
    "test_conformance_builtin", "test_variable_rate")} | {
    "test_cli": "bench_run", "test_bench_progress": "bench_run"}


@pytest.hookimpl(optionalhook=True)
def pytest_xdist_make_scheduler(config, log):
    if config.getvalue("dist") != "load":
        return None  # a distribution asked for by name
    from xdist.scheduler import LoadScopeScheduling

    class GroupedScheduling(LoadScopeScheduling):
        """xdist's scope scheduling with a scope per grouped module, and one per test elsewhere."""

        def _split_scope(self, nodeid: str) -> str:
            group = WORKER_GROUPS.get(Path(nodeid.split("::", 1)[0]).stem)
            return f"group {group}" if group else nodeid

    return GroupedScheduling(config, log)


@pytest.hookimpl(trylast=True)
def pytest_collection_finish(session):
    """Everything imported by now (the test modules, torch, zarr, open3d...: ~350k objects) lives for the whole
    session: moved out of the cyclic collector's reach (``gc.freeze``), so that each of its full passes scans only
    what the tests made. Measured on tests/test_manifest.py + test_mapfile.py (-n 0, load 7-9, two runs each):
    full passes 2.7-2.9 -> 1.7-1.9 CPU-s, the files 36.4-39.2 -> 35.9-36.2 CPU-s. A forked child
    (tests/test_hostile_local.py's probes) also no longer touches those objects' pages when it collects."""
    import gc

    gc.freeze()


def pytest_unconfigure(config):
    import shutil

    made = getattr(config, "_sdfcodec_cache", None)
    if made:
        shutil.rmtree(made, ignore_errors=True)
        os.environ.pop("SDFCODEC_CACHE_DIR", None)

SHARED_DATA = ROOT.parent / "shared" / "data"


def _pin_examples() -> bool:
    """Keep Hypothesis from mining literals out of the loaded modules (deterministic profile only).

    Hypothesis (>= 6.131) draws a few percent of its integers, floats and strings from the literals of the
    *local modules loaded at that moment*. Which modules are loaded depends on the tests that ran before, so a
    derandomized test drew other examples alone than late in the full suite: there test_fuzz_geometry drew
    grids of 5 x 2^20 x 3 blocks that took 20-40 s each, alone it drew others (10 s for the whole test). Any
    edit that adds or moves a literal anywhere in the package changed the examples too. The tests list their own
    special values (test_fuzz.SPECIAL), so nothing is lost. There is no public switch; where the hook is missing
    (another Hypothesis), tests/test_fuzz.py::test_examples_are_pinned fails and says so.
    """
    try:
        from hypothesis.internal.conjecture import providers
    except ImportError:  # pragma: no cover - a Hypothesis without the provider module
        return False
    empty = getattr(providers, "_local_constants", None)
    if not hasattr(providers, "_get_local_constants") or empty is None or len(empty):
        return False  # pragma: no cover - another Hypothesis
    providers._get_local_constants = lambda: empty  # noqa: SLF001 - no public switch exists
    return True


EXAMPLES_PINNED = os.environ.get("HYPOTHESIS_PROFILE", "deterministic") == "deterministic" and _pin_examples()


@pytest.fixture
def examples_pinned() -> bool:
    """Whether Hypothesis's examples are independent of the modules loaded (see _pin_examples)."""
    return EXAMPLES_PINNED


@pytest.fixture
def shared_data() -> Path:
    """Path to ../shared/data; skips the test when it is not there (users do not have it)."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"real data not found at {SHARED_DATA} (only present in the project's dev/CI checkout)")
    return SHARED_DATA


# The two fixtures below are built once per session (five modules use them): the volume is read-only so a test
# that changed it in place would fail there instead of leaking into the next module; tests only encode and
# decode with the codec, never refit it.
@pytest.fixture(scope="session")
def volume() -> np.ndarray:
    """The exact analytic scene (sdfcodec.testing.analytic_scene) sampled at 2 cm, truncation (-0.04, 0.1) m:
    float32 metres, 90 x 70 x 45 voxels, a multiple neither of 16 (padding, true extent) nor of small chunks;
    read-only."""
    from sdfcodec.core.sdf import sample_volume
    from sdfcodec.testing import analytic_scene

    vol = sample_volume(analytic_scene(), (90, 70, 45), 0.02, truncation=(-0.04, 0.1))
    vol.setflags(write=False)
    return vol


@pytest.fixture(scope="session")
def pca64():
    """A pca-64 codec fitted on 800 analytic blocks (seed 11)."""
    import sdfcodec
    from sdfcodec.testing import analytic_blocks

    return sdfcodec.get_codec("pca", code_size=64).fit(analytic_blocks(800, seed=11))


class RunShared:
    """What one process of the run builds for all: under pytest-xdist a session or module fixture is built again
    in every worker that runs one of its tests; through this, a worker takes what another one already built
    (saved in the run's directory, above every worker's own). A worker that asks while another is still
    building builds its own copy rather than wait: a waiting worker would leave its core idle (measured with a
    shared benchmark run: one worker waited 10 s), so sharing saves only what the workers need at different
    times, and never costs more than a fixture per worker did."""

    def __init__(self, tmp_path_factory):
        self.factory = tmp_path_factory
        # the run's directory; None outside xdist (one process: nothing to share)
        self.shared = tmp_path_factory.getbasetemp().parent if os.environ.get("PYTEST_XDIST_WORKER") else None

    @contextmanager
    def _lock(self, name: str):
        """Yields whether this process holds ``name``'s lock (False: another process is building it)."""
        import fcntl

        with open(self.shared / f"{name}.lock", "w") as lock:
            try:
                fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)  # released when the file closes
            except BlockingIOError:
                yield False
                return
            yield True

    def once(self, name: str, make):
        """``make()``'s JSON-able result, computed once in the run where the workers need it at different
        times."""
        import json

        if self.shared is None:
            return make()
        saved = self.shared / f"{name}.json"
        with self._lock(name) as held:
            if not held:
                return make()
            if not saved.is_file():
                saved.write_text(json.dumps(make()))
            return json.loads(saved.read_text())

    def built(self, name: str, build) -> Path:
        """A directory that ``build(directory)`` fills, once in the run where the workers need it at different
        times: workers get the same directory, so tests only read what is in it (a test that changes a map
        copies it first)."""
        if self.shared is not None:
            d, done = self.shared / name, self.shared / f"{name}.built"
            with self._lock(name) as held:
                if held:
                    if not done.is_file():
                        shutil.rmtree(d, ignore_errors=True)  # what a failed build left
                        d.mkdir()
                        build(d)
                        done.touch()
                    return d
        d = self.factory.mktemp(name)
        build(d)
        return d


@pytest.fixture(scope="session")
def run_shared(tmp_path_factory) -> RunShared:
    """Results and directories built once per run, whichever xdist worker asks first (:class:`RunShared`)."""
    return RunShared(tmp_path_factory)


def golden_round_trip(codec, golden: Path | None, regen_golden: bool) -> dict:
    """The ``golden_fixture`` and ``round_trip`` conformance checks of ``codec`` (fitted): the frozen fixture in
    ``golden`` (rewritten with ``regen_golden``), and the round trip's measurements (``mse``). Every other check
    of each built-in codec runs in test_conformance_builtin.py, one test per check; running all of them again
    here cost the suite ~25 s of worker time."""
    from sdfcodec.testing import codec_checks

    checks = dict(codec_checks(codec, golden=golden))
    if golden is not None:
        checks["golden_fixture"](regen_golden=regen_golden)
    return checks["round_trip"]()


@pytest.fixture(name="golden_round_trip")
def _golden_round_trip_fixture():
    """:func:`golden_round_trip`, for test modules (conftest is not imported by name)."""
    return golden_round_trip


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(1234)


# frozen third-party codec packages: run by tests/test_plugin_compat.py in their own pytest, never collected here
collect_ignore = ["plugin_packages"]


# The arguments of the one `sdfcodec bench` run two test files read: test_cli checks its records,
# test_bench_progress its progress lines (stderr, one every 0.05 s). A bench run costs seconds of timing
# rounds, fresh `sdfcodec info` processes and an HTTP server; one run serves both.
BENCH_ARGS = ["bench", "--quick", "--sizes", "32", "--batches", "1,64", "--read", "300", "--repeats", "2", "--json"]


@pytest.fixture(scope="session")
def bench_run(run_shared) -> dict:
    """``sdfcodec BENCH_ARGS`` in process, once per run: {"exit_code", "stdout", "stderr", "output"}."""

    def make() -> dict:
        from typer.testing import CliRunner

        from sdfcodec.cli import app

        r = CliRunner().invoke(app, BENCH_ARGS, env={"SDFCODEC_PROGRESS_SECONDS": "0.05"})
        return {"exit_code": r.exit_code, "stdout": r.stdout, "stderr": r.stderr, "output": r.output}

    return run_shared.once("bench-cli", make)
