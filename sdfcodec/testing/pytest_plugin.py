"""pytest plugin for codec packages: the ``--regen-golden`` option and the ``regen_golden`` fixture.

It is registered under the ``pytest11`` entry point, so any package's tests get it once sdfcodec is
installed; without the entry point load it with ``pytest -p sdfcodec.testing.pytest_plugin`` or
``pytest_plugins = ["sdfcodec.testing.pytest_plugin"]`` in a top-level conftest. The entry point carries
the module's own name, so loading it both ways registers it once.
"""

from __future__ import annotations

import pytest

__all__ = ["pytest_addoption", "regen_golden"]


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption("--regen-golden", action="store_true", default=False,
                     help="rewrite golden fixture files instead of checking against them (format changes only)")


@pytest.fixture
def regen_golden(request: pytest.FixtureRequest) -> bool:
    """True under ``pytest --regen-golden``: tests rewrite their golden fixtures instead of checking them."""
    return bool(request.config.getoption("--regen-golden"))
