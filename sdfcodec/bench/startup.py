"""How long a light command takes in a fresh process (held to ``sdfcodec info MAP`` <= 0.5 s).

Each call starts a new interpreter, as a user's shell does; the baseline, interleaved with it, is the bare
interpreter start-up (``python -c pass``), the floor no command can go under here. The map is a small one
written for the run (the command reads its header and block states, whatever the map's size)."""

from __future__ import annotations

import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

from .harness import interleave, load

__all__ = ["bench_info_startup", "startup_steps", "INFO_TARGET_S"]

#: The issue's target for ``sdfcodec info MAP``, seconds.
INFO_TARGET_S = 0.5


def _runner(argv: list[str]):
    def run() -> None:
        subprocess.run(argv, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return run


def startup_steps(repeats: int) -> int:
    """The progress steps :func:`bench_info_startup` reports: writing its map, then each fresh ``info`` process up
    to the first of the timed rounds' (the calibration's call, then one per round)."""
    return int(repeats) + 2


def bench_info_startup(*, repeats: int = 5, n_blocks: int = 4096, progress=None) -> list[dict]:
    """One ``"info-startup"`` record: seconds of ``sdfcodec info MAP`` in a fresh interpreter (median and best of
    ``repeats`` interleaved rounds), beside the interpreter's own start-up, and whether it meets
    :data:`INFO_TARGET_S`. ``progress(what)``, when given, is called :func:`startup_steps` times at most, as each
    step begins (a bar's estimate stays true through the fresh processes, a tenth of a quick bench)."""
    from ..registry import pretrained_codec
    from .codecs import write_bench_map

    tmp = Path(tempfile.mkdtemp(prefix="sdfcodec-bench-"))
    try:
        path = tmp / "info.sdfz"
        if progress is not None:
            progress(f"sdfcodec info start-up: writing a {n_blocks}-block map")
        write_bench_map(pretrained_codec("pca", 64), n_blocks, path, (-0.04, 0.1))
        load0 = load()
        # what the `sdfcodec` console script runs (its entry point), without depending on where it is installed
        cmd = [sys.executable, "-c", "import sys; from sdfcodec.cli import main; sys.exit(main())"]
        info_run, calls = _runner([*cmd, "info", str(path)]), [0]

        def counted() -> None:
            calls[0] += 1
            if progress is not None and calls[0] < startup_steps(repeats):
                progress(f"sdfcodec info start-up: fresh process {calls[0]}")
            info_run()

        t = interleave({"info": counted,
                        "interpreter": _runner([sys.executable, "-c", "pass"])}, repeats=repeats, min_time=0.0)
        load1 = load()
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    info, base = t["info"], t["interpreter"]
    return [{"operation": "info-startup", "command": "sdfcodec info MAP (a fresh process)",
             "seconds_median": info.median, "seconds_best": info.best, "seconds_rounds": list(info.rounds),
             "baseline": "the interpreter's start-up (python -c pass)", "baseline_seconds_median": base.median,
             "baseline_seconds_best": base.best, "target_seconds": INFO_TARGET_S,
             "meets_target": info.median <= INFO_TARGET_S, "map_blocks": n_blocks, "repeats": repeats,
             "load_before": load0, "load_after": load1}]
