import os

import sdfcodec
from sdfcodec.testing import parametrize_codec_checks
from sdfcodec_oldstyle import VoxelCodec

sdfcodec.register_codec(VoxelCodec, replace=True)


@parametrize_codec_checks([VoxelCodec()])
def test_conformance(codec, check, regen_golden):
    check(codec, regen_golden=regen_golden)


def test_flag_reaches_the_tests(regen_golden):
    assert regen_golden is (os.environ.get("EXPECT_REGEN_GOLDEN") == "1")
