# Written from sdfcodec's earlier plugin docs, which told plugin authors to define the golden-fixture flag
# themselves. Frozen: do not modernise (tests/test_plugin_compat.py runs pytest on this package).
import pytest


def pytest_addoption(parser):
    parser.addoption("--regen-golden", action="store_true", default=False,
                     help="rewrite the golden fixtures of this package")


@pytest.fixture
def regen_golden(request):
    return request.config.getoption("--regen-golden")
