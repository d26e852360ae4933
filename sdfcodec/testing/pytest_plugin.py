"""pytest plugin for codec packages: the ``--regen-golden`` option and the ``regen_golden`` fixture.

It is registered under the ``pytest11`` entry point, so any package's tests get it once sdfcodec is
installed; without the entry point load it with ``pytest -p sdfcodec.testing.pytest_plugin`` or
``pytest_plugins = ["sdfcodec.testing.pytest_plugin"]`` in a top-level conftest. The entry point carries
the module's own name, so loading it both ways registers it once.

A package that defines ``--regen-golden`` itself in its ``conftest.py`` (as our earlier docs told plugin
authors to) keeps working: the option is added only after the initial conftests were read, and only when none
of them added it (pytest refuses an option added twice, and the entry point loads this plugin before any
conftest). The package's own definition is then the one used; the ``regen_golden`` fixture reads it all the
same (a fixture of the package's conftest overrides this one).
"""

from __future__ import annotations

from typing import Any, Iterator

import pytest

__all__ = ["pytest_addoption", "pytest_load_initial_conftests", "regen_golden"]


def _add_option(parser: pytest.Parser) -> None:
    try:
        parser.addoption("--regen-golden", action="store_true", default=False,
                         help="rewrite golden fixture files instead of checking against them (format changes only)")
    except ValueError:  # a package's own conftest.py defines it (our earlier docs said to): keep theirs
        pass


def pytest_addoption(parser: pytest.Parser, pluginmanager: pytest.PytestPluginManager) -> None:
    # loaded early (the entry point, -p): wait for the package's conftests (pytest_load_initial_conftests below);
    # loaded by a conftest's pytest_plugins, the initial conftests are being read now: add it unless one did
    if any(str(getattr(p, "__file__", "")).endswith("conftest.py") for p in pluginmanager.get_plugins()):
        _add_option(parser)


@pytest.hookimpl(hookwrapper=True)
def pytest_load_initial_conftests(early_config: pytest.Config, parser: pytest.Parser, args: list[str]
                                  ) -> Iterator[Any]:
    yield  # the package's conftest.py files define their options first
    _add_option(parser)


@pytest.fixture
def regen_golden(request: pytest.FixtureRequest) -> bool:
    """True under ``pytest --regen-golden``: tests rewrite their golden fixtures instead of checking them."""
    return bool(request.config.getoption("--regen-golden", default=False))
