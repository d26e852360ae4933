"""Every built-in codec passes every conformance check, one test per (codec, check). Small configurations,
fitted once each by the suite on its analytic test blocks, keep the file fast; golden fixtures of the
built-ins are checked in test_codecs_builtin.py and test_codecs_nn.py."""

from __future__ import annotations

import sdfcodec
from sdfcodec.testing import parametrize_codec_checks

# one thread, no progress bars, a few epochs on the suite's 256 blocks: enough to beat the round-trip baseline
FAST = {"progress": False, "threads": 1, "batch_size": 64, "lr": 1e-2, "max_epochs": 40, "patience": 100}
# the mixtures' PCA part carries most of a block: 4 epochs leave their round trip at 0.07 of the mean-block
# baseline (0.5 needed), and every fit of theirs (the reference, the state checks' rivals) costs a fifth
MIX = {**FAST, "max_epochs": 4}

CODECS = [
    sdfcodec.get_codec("pca", code_size=32),
    sdfcodec.get_codec("pca", code_size=16, mean="block"),
    sdfcodec.get_codec("raw"),
    sdfcodec.get_codec("gaussian-blur"),
    sdfcodec.get_codec("ae", code_size=8, hidden=16, training=FAST),
    sdfcodec.get_codec("parallel", pca_size=8, ae_size=8, hidden=16, training=MIX),
    sdfcodec.get_codec("sequential", pca_size=8, ae_size=8, hidden=16, training=MIX),
]
IDS = ["pca-32", "pca-16-block", "raw", "gaussian-blur", "ae-8", "parallel-8-8", "sequential-8-8"]


@parametrize_codec_checks(CODECS, ids=IDS, large_batch=1024)
def test_builtin_codec(codec, check, regen_golden):
    check(codec, regen_golden=regen_golden)
