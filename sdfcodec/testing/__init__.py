"""Public test helpers: the codec conformance suite that every codec, built-in or third-party, runs.

One test per named check (a pytest parametrisation; ``regen_golden`` comes from the pytest plugin
``sdfcodec.testing.pytest_plugin``, loaded automatically when sdfcodec is installed)::

    from sdfcodec.testing import parametrize_codec_checks

    @parametrize_codec_checks([MyCodec(code_size=32)], golden=[GOLDEN / "mycodec-32"])
    def test_conformance(codec, check, regen_golden):
        check(codec, regen_golden=regen_golden)

or all checks at once: ``run_codec_checks(codec)`` returns a report of every failure, and
``check_codec(codec, golden=DIR)`` raises one ``AssertionError`` listing them.
"""

from ._checks import prefix_levels
from ._data import analytic_blocks, analytic_scene
from ._golden import golden_dir_files
from ._suite import (CheckReport, CheckResult, CodecCheck, check_codec, codec_checks, parametrize_codec_checks,
                     run_codec_checks)

__all__ = ["check_codec", "codec_checks", "run_codec_checks", "parametrize_codec_checks", "CodecCheck",
           "CheckResult", "CheckReport", "prefix_levels", "analytic_blocks", "analytic_scene", "golden_dir_files"]
