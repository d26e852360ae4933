"""Shared fixtures. Tests that need the real data in ../shared/data skip with a reason when it is absent."""

from __future__ import annotations

from pathlib import Path

import os

import numpy as np
import pytest
from hypothesis import settings

# Property tests run the same examples on every run (a suite that passes once passes again; CI never meets a
# new random case in someone else's change). Explore new random cases locally with HYPOTHESIS_PROFILE=explore.
settings.register_profile("deterministic", derandomize=True, database=None)
settings.register_profile("explore", derandomize=False)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "deterministic"))

# --regen-golden and the regen_golden fixture: the plugin sdfcodec ships for every codec package. Installed,
# its pytest11 entry point (named like the module) loads it first and this line is a no-op; from a bare
# checkout it loads it here.
pytest_plugins = ["sdfcodec.testing.pytest_plugin"]

ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = ROOT.parent / "shared" / "data"


@pytest.fixture
def shared_data() -> Path:
    """Path to ../shared/data; skips the test when it is not there (users do not have it)."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"real data not found at {SHARED_DATA} (only present in the project's dev/CI checkout)")
    return SHARED_DATA


@pytest.fixture(scope="module")
def volume() -> np.ndarray:
    """The exact analytic scene (sdfcodec.testing.analytic_scene) sampled at 2 cm, truncation (-0.04, 0.1) m:
    90 x 70 x 45 voxels, a multiple neither of 16 (padding, true extent) nor of small chunks."""
    from sdfcodec.sdf import sample_volume
    from sdfcodec.testing import analytic_scene

    return sample_volume(analytic_scene(), (90, 70, 45), 0.02, truncation=(-0.04, 0.1))


@pytest.fixture(scope="module")
def pca64():
    """A pca-64 codec fitted on 800 analytic blocks (seed 11)."""
    import sdfcodec
    from sdfcodec.testing import analytic_blocks

    return sdfcodec.get_codec("pca", code_size=64).fit(analytic_blocks(800, seed=11))


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(1234)
