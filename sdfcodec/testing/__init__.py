"""Public test helpers: the codec conformance suite that every codec, built-in or third-party, runs.

    from sdfcodec.testing import check_codec
    def test_my_codec():
        check_codec(MyCodec(code_size=32), golden="tests/golden/mycodec")
"""

from ._check import check_codec, golden_dir_files
from ._data import analytic_blocks, analytic_scene

__all__ = ["check_codec", "analytic_blocks", "analytic_scene", "golden_dir_files"]
