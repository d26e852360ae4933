"""The ``sdfcodec`` command line (typer + rich). Errors print one line on stderr and exit non-zero.

``app`` is the typer application; ``main`` runs it. Importing this package registers every command."""

from __future__ import annotations

from . import maps, work  # noqa: F401  (each module registers its commands on the app)
from . import view  # noqa: F401  (sdfcodec view: a Rerun recording of a map)
from .common import app

__all__ = ["app", "main"]


def main() -> None:
    app()
