"""Deprecated location of ``check_codec``: import it from :mod:`sdfcodec.testing` (the checks now live in
``_checks.py``, the runners in ``_suite.py``, golden fixtures in ``_golden.py``)."""

from ._golden import golden_dir_files
from ._suite import check_codec

__all__ = ["check_codec", "golden_dir_files"]
