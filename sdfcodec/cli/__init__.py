"""The ``sdfcodec`` command line (typer + rich). Errors print one line on stderr and exit non-zero.

``app`` is the typer application; ``main`` runs it. Importing this package registers every command."""

from __future__ import annotations

import os
import sys

# numpy's OpenBLAS keeps its worker threads spinning for 2^28 cycles (about 0.1 s) after every product, on the
# cores that torch's threads (encode, decode) and the map reader's threads need next: on 2 cores torch's product
# of a pca-64 encode of 64 blocks, alternated with numpy products, ran 13-16x slower than alone, and the masked
# encode of 64 blocks 3x (measured on a 2-core AMD EPYC). 2^4 cycles puts them to sleep at once.
# OpenBLAS reads the variable when numpy first loads, so it is set before any command module imports numpy; a
# value the user set is kept, and none is set once numpy has loaded (the command run from a Python program),
# where it would change nothing here and the bench's record of it (``machine.thread_env``) would be wrong.
if "numpy" not in sys.modules:
    os.environ.setdefault("OPENBLAS_THREAD_TIMEOUT", "4")

from . import maps, work  # noqa: E402,F401  (each module registers its commands on the app)
from . import view  # noqa: E402,F401  (sdfcodec view: a Rerun recording of a map)
from . import interop  # noqa: E402,F401  (import, export, trajectory: other systems' maps and poses)
from .common import app, end_process  # noqa: E402

__all__ = ["app", "main"]


def main() -> None:
    """The ``sdfcodec`` command (``python -m sdfcodec``): ``app`` run in this process, which ends with it."""
    try:
        app()
    except SystemExit as e:
        end_process(e.code)  # a command that finished cleanly ends here, without Python's teardown
        raise
