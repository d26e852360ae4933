"""The conformance suite itself: a small correct codec passes every check, and each deliberately broken
variant of it (one bug class each) is flagged by the check meant for it. Also the runners (one test per
check, a report of every failure, ``check_codec``) and the pytest plugin's ``--regen-golden``."""

from __future__ import annotations


import numpy as np
import pytest
import torch

import sdfcodec
from sdfcodec.testing import (CodecCheck, analytic_blocks, check_codec, codec_checks, parametrize_codec_checks,
                              prefix_levels, run_codec_checks)

pytest_plugins = ["pytester"]


class Tiny(sdfcodec.Codec):
    """A correct small codec: PCA on 4096-vectors by SVD, prefix-ordered, with a derived per-device cache."""

    codec_id = "test-conf-tiny"
    prefix_ordered = True
    requires_fit = True

    def __init__(self, code_size: int = 8):
        self.code_size = code_size

    def _fit(self, blocks):
        x = blocks.reshape(len(blocks), -1).astype(np.float64)
        mu = x.mean(axis=0)
        # the principal directions from the blocks' Gram matrix (n x n, n <= a few hundred here): the SVD of the
        # n x 4096 blocks gives the same, ~10x slower (the checks fit this codec ~30 times in the file)
        c = x - mu
        w, v = np.linalg.eigh(c @ c.T)
        top = np.argsort(w)[::-1][: self.code_size]
        basis = (v[:, top].T @ c) / np.sqrt(w[top])[:, None]
        self.load_state_dict({"mean": mu.astype(np.float32), "basis": basis.astype(np.float32)})

    def state_dict(self):
        return {"mean": self.mean_, "basis": self.basis_} if hasattr(self, "basis_") else {}

    def load_state_dict(self, state):
        self.mean_ = np.asarray(state["mean"], np.float32)
        self.basis_ = np.asarray(state["basis"], np.float32)
        self._cache = {}  # tensors derived from the state, per device: rebuilt for the new state
        return self

    def _mats(self, device):
        if device not in self._cache:
            self._cache[device] = (torch.from_numpy(self.mean_).to(device), torch.from_numpy(self.basis_).to(device))
        return self._cache[device]

    def _encode(self, blocks):
        mu, b = self._mats(blocks.device)
        return (blocks.reshape(len(blocks), -1) - mu) @ b.T

    def _decode(self, codes):
        mu, b = self._mats(codes.device)
        return (codes @ b[: codes.shape[1]] + mu).reshape(len(codes), 16, 16, 16)


# -- one broken variant per bug class -------------------------------------------------------------------
class CPUCompute(Tiny):
    """1. computes on the CPU and moves the results back to the input's device."""

    codec_id = "test-conf-cpu-compute"

    def _encode(self, blocks):
        return super()._encode(blocks.cpu()).to(blocks.device)

    def _decode(self, codes):
        return super()._decode(codes.cpu()).to(codes.device)


class AlwaysCPU(Tiny):
    """2. results always on the CPU."""

    codec_id = "test-conf-always-cpu"

    def _encode(self, blocks):
        return super()._encode(blocks).cpu()

    def _decode(self, codes):
        return super()._decode(codes).cpu()


class GarbagePrefix(Tiny):
    """3. claims prefix order, but a prefix decodes to garbage (it forgets the mean)."""

    codec_id = "test-conf-garbage-prefix"

    def _decode(self, codes):
        if codes.shape[1] == self.code_size:
            return super()._decode(codes)
        _, b = self._mats(codes.device)
        return (codes @ b[: codes.shape[1]]).reshape(len(codes), 16, 16, 16)


class GainLast(Tiny):
    """4. the last code element is a gain: a prefix, zero-padded, lacks it and decodes to the mean block."""

    codec_id = "test-conf-gain-last"

    def _encode(self, blocks):
        c = super()._encode(blocks)[:, : self.code_size - 1]
        g = c.norm(dim=1, keepdim=True) + 1e-6
        return torch.cat([c / g, g], dim=1)

    def _decode(self, codes):
        k = codes.shape[1]
        full = torch.nn.functional.pad(codes, (0, self.code_size - k))
        mu, b = self._mats(codes.device)
        return ((full[:, :-1] * full[:, -1:]) @ b[: self.code_size - 1] + mu).reshape(len(codes), 16, 16, 16)


class LevelBump(Tiny):
    """5. error grows at one level between those a sparse test decodes (1, k/4, k/2, k)."""

    codec_id = "test-conf-level-bump"

    def _decode(self, codes):
        return super()._decode(codes * 2.0 if codes.shape[1] == 3 else codes)


class StaleCache(Tiny):
    """6. load_state_dict keeps the tensors derived from the previous state."""

    codec_id = "test-conf-stale-cache"

    def load_state_dict(self, state):
        self.mean_ = np.asarray(state["mean"], np.float32)
        self.basis_ = np.asarray(state["basis"], np.float32)
        self.__dict__.setdefault("_cache", {})
        return self


class ForgetsGain(Tiny):
    """7. a learned attribute (``gain_``) missing from ``state_dict``: a rebuild uses the class default."""

    codec_id = "test-conf-forgets-gain"
    gain_ = 1.0

    def _fit(self, blocks):
        super()._fit(blocks)
        self.gain_ = float(np.std(blocks)) * 4

    def _encode(self, blocks):
        return super()._encode(blocks) / self.gain_

    def _decode(self, codes):
        return super()._decode(codes * self.gain_)


class ClampsInput(Tiny):
    """8. an idempotent in-place change of the input (normalised blocks are already in [0, 1])."""

    codec_id = "test-conf-clamps-input"

    def _encode(self, blocks):
        blocks.clamp_(0.0, 1.0)
        return super()._encode(blocks)


class FitReturnsNone(Tiny):
    """fit must return self."""

    codec_id = "test-conf-fit-none"

    def fit(self, blocks):
        super().fit(blocks)


class StaleNumpyPath(Tiny):
    """a torch-free path (capability numpy_path) that decodes without the mean: searches would score wrong blocks."""

    codec_id = "test-conf-stale-numpy"
    capabilities = frozenset({"numpy_path"})

    def numpy_path(self):
        codec = self

        class Path:
            def encode(self, x):
                return ((x - codec.mean_) @ codec.basis_.T).astype(np.float32)

            def decode(self, c):
                return (c @ codec.basis_[: c.shape[1]]).astype(np.float32)

            def encode_truncated(self, x, w, rounds):
                return None

        return Path()


BROKEN = [(CPUCompute, "meta_device"), (AlwaysCPU, "meta_device"), (GarbagePrefix, "prefix_decoding"),
          (GainLast, "prefix_decoding"), (LevelBump, "prefix_decoding"), (StaleCache, "load_state_after_use"),
          (ForgetsGain, "state_round_trip"), (ClampsInput, "inputs_untouched"), (FitReturnsNone, "fit"),
          (StaleNumpyPath, "numpy_path")]
for _cls in [Tiny] + [c for c, _ in BROKEN]:
    sdfcodec.register_codec(_cls, replace=True)


# small test blocks and a small "large batch" keep each run of the suite to about a second
OPTS = {"blocks": analytic_blocks(48, seed=3), "large_batch": 128}


def test_correct_codec_passes_every_check():
    codec = Tiny()
    report = run_codec_checks(codec, **OPTS)
    assert report.ok, report.summary()
    assert [r.name for r in report.results] == [name for name, _ in codec_checks(codec)]
    assert not codec.is_fitted, "the runner fits a copy, never the codec it is given"
    assert report.as_dict()["prefix_mse"].keys() == set(range(1, 9))


@pytest.mark.parametrize("cls, check", BROKEN, ids=[c.__name__ for c, _ in BROKEN])
def test_each_bug_class_is_flagged(cls, check):
    report = run_codec_checks(cls(), **OPTS)
    failed = {r.name for r in report.failures}
    assert check in failed, f"{cls.__name__}: expected {check!r} to fail, failed: {sorted(failed)}\n{report.summary()}"
    if check == "meta_device":  # the message names the cause
        msg = next(r.message for r in report.failures if r.name == check)
        assert "input's device" in msg and "meta" in msg


def test_every_failure_is_reported_and_check_codec_lists_them():
    class TwoBugs(ClampsInput, StaleCache):
        codec_id = "test-conf-two-bugs"

    sdfcodec.register_codec(TwoBugs, replace=True)
    failed = {r.name for r in run_codec_checks(TwoBugs(), **OPTS).failures}
    assert {"inputs_untouched", "load_state_after_use"} <= failed
    listing = r"(?s)2 of 16 conformance checks failed.*load_state_after_use.*inputs_untouched"
    with pytest.raises(AssertionError, match=listing):
        check_codec(TwoBugs(), **OPTS)


def test_check_codec_fits_in_place_and_returns_the_old_report():
    codec = Tiny()
    report = check_codec(codec, **OPTS)
    assert codec.is_fitted  # as before: an unfitted codec is fitted on the test blocks
    assert {"round trip", "state round trip", "prefix decoding", "bad input"} <= set(report["checks"])
    assert 0 < report["mse"] < 0.1 and report["failed"] == []


def test_checks_run_on_copies_of_one_fitted_reference():
    built = []

    def tiny():
        built.append(1)
        return Tiny()

    checks = dict(codec_checks(tiny, **OPTS))
    assert "golden_fixture" not in checks and isinstance(checks["round_trip"], CodecCheck)
    checks["round_trip"](tiny)
    checks["prefix_decoding"](tiny)
    assert len(built) == 1  # built (and fitted) once, each check on its own copy
    with pytest.raises(AssertionError, match="inputs_untouched: inputs: encode"):
        dict(codec_checks(ClampsInput(), **OPTS))["inputs_untouched"]()


def test_prefix_levels_are_dense():
    assert prefix_levels(8) == list(range(1, 9))
    long = prefix_levels(4096, max_levels=512)
    assert long[:64] == list(range(1, 65)) and long[-1] == 4096 and len(long) <= 512
    assert max(np.diff(long)) <= 10


@parametrize_codec_checks([Tiny(code_size=6)], blocks=analytic_blocks(64, seed=5))
def test_parametrised(codec, check):
    check(codec)


def test_parametrisation_ids():
    mark = parametrize_codec_checks([Tiny(code_size=6), Tiny(code_size=6)], ids=None)
    ids = [p.id for p in mark.args[1]]
    assert "test-conf-tiny-6-0-round_trip" in ids and "test-conf-tiny-6-1-meta_device" in ids
    with pytest.raises(ValueError, match="one directory"):
        parametrize_codec_checks([Tiny(), Tiny()], golden=["a"])


def test_regen_golden_plugin(pytester):
    """``-p sdfcodec.testing.pytest_plugin`` gives --regen-golden: a parametrised golden check fails while the
    fixture is missing, writes it under --regen-golden, then checks it; a conftest loading the plugin as
    well registers it once."""
    pytester.makeconftest('pytest_plugins = ["sdfcodec.testing.pytest_plugin"]\n')
    pytester.makepyfile(test_it="""
        from pathlib import Path
        from test_conformance import Tiny
        from sdfcodec.testing import analytic_blocks, parametrize_codec_checks

        @parametrize_codec_checks([Tiny()], golden=[Path(__file__).parent / "golden" / "tiny"],
                                  blocks=analytic_blocks(64, seed=1))
        def test_conformance(codec, check, regen_golden):
            check(codec, regen_golden=regen_golden)
        """)
    args = ("-p", "sdfcodec.testing.pytest_plugin", "-p", "no:cacheprovider", "-k", "golden")
    r = pytester.runpytest_inprocess(*args)
    r.assert_outcomes(failed=1)
    assert "lacks" in r.stdout.str() and "--regen-golden" in r.stdout.str()
    pytester.runpytest_inprocess(*args, "--regen-golden").assert_outcomes(passed=1)
    assert (pytester.path / "golden" / "tiny" / "codes.npy").is_file()
    pytester.runpytest_inprocess(*args).assert_outcomes(passed=1)
