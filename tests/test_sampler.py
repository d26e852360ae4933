"""Sub-volume sampling (sdfcodec.data.sampler): window layout, the axis-permutation "reflections", the
mostly-empty filter, and the memory-bounded generator. Expectations are built here by brute-force loops."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from sdfcodec.core.blocks import normalise
from sdfcodec.data import sampler
from sdfcodec.data.sampler import PERMUTATIONS, iter_windows, sample_windows, window_origins
from sdfcodec.errors import DTypeError, InvalidValueError, ShapeError
from sdfcodec.core.sdf import Plane, sample_volume

TRUNC = (-0.04, 0.1)
D_MIN, D_MAX = TRUNC
KEEP_ALL = dict(max_mean=2.0)  # every mean is <= 1, so nothing is discarded


def _norm(w):
    return np.clip(normalise(np.clip(w, *TRUNC), *TRUNC), 0.0, 1.0)


def _brute_windows(vol, stride=8):
    """(origin, normalised window) for every whole 16^3 window, origins in C order, by plain loops."""
    out = []
    for x in range(0, vol.shape[0] - 15, stride):
        for y in range(0, vol.shape[1] - 15, stride):
            for z in range(0, vol.shape[2] - 15, stride):
                out.append(((x, y, z), _norm(vol[x:x + 16, y:y + 16, z:z + 16])))
    return out


@settings(max_examples=60, deadline=None)
@given(shape=st.tuples(*[st.integers(0, 70)] * 3), stride=st.integers(1, 20))
def test_window_origins_count_and_bounds(shape, stride):
    origins = window_origins(shape, stride)
    expected = np.prod([max(0, (n - 16) // stride + 1) for n in shape])
    assert origins.shape == (expected, 3)
    if expected:
        assert np.all(origins % stride == 0) and np.all(origins + 16 <= np.asarray(shape))
        assert [tuple(o) for o in origins] == sorted(tuple(o) for o in origins)  # C order


def test_windows_and_permutations_exact(rng):
    vol = rng.uniform(-0.06, 0.12, size=(40, 33, 24)).astype(np.float32)  # also beyond the truncation
    got = sample_windows(vol, **KEEP_ALL)
    brute = _brute_windows(vol)
    assert len(brute) == 4 * 3 * 2
    assert got.shape == (6 * len(brute), 16, 16, 16) and got.dtype == np.float32
    assert PERMUTATIONS[0] == (0, 1, 2) and sorted(PERMUTATIONS) == sorted(itertools.permutations(range(3)))
    expected = np.stack([w.transpose(p) for _, w in brute for p in PERMUTATIONS])
    np.testing.assert_array_equal(got, expected)
    # the six are the distinct transposes of one window, e.g. the second swaps y and z
    np.testing.assert_array_equal(got[1], np.swapaxes(got[0], 1, 2))
    assert len({g.tobytes() for g in got[:6]}) == 6
    assert got.min() == 0.0 and got.max() == 1.0  # truncated and normalised
    only = sample_windows(vol, permute=False, **KEEP_ALL)
    np.testing.assert_array_equal(only, np.stack([w for _, w in brute]))


def test_stride_parameter(rng):
    vol = rng.uniform(*TRUNC, size=(20, 21, 16))
    got = sample_windows(vol, stride=4, permute=False, **KEEP_ALL)
    np.testing.assert_array_equal(got, np.stack([w for _, w in _brute_windows(vol, stride=4)]))


def test_mostly_empty_windows_discarded():
    # free space everywhere except a solid slab x < 8: along x the windows at origins 0, 8, 16, 24, 32
    # have means 0.5, 1, 1, 1, 1 (a y-z window row of 2 x 2 origins each)
    vol = np.full((48, 24, 24), D_MAX, dtype=np.float32)
    vol[:8] = D_MIN
    got = sample_windows(vol, empty_fraction=0.0)
    expected = np.stack([w.transpose(p) for (x, _, _), w in _brute_windows(vol) if x == 0 for p in PERMUTATIONS])
    np.testing.assert_array_equal(got, expected)
    assert np.allclose(got.mean(axis=(1, 2, 3)), 0.5)
    # nothing near a surface at all: nothing kept
    assert sample_windows(np.full((32, 32, 32), D_MAX), empty_fraction=0.0).shape == (0, 16, 16, 16)
    # empty_fraction = 1 keeps everything
    assert len(sample_windows(vol, empty_fraction=1.0)) == 6 * len(_brute_windows(vol))


def test_threshold_against_brute_force_means():
    # a tilted plane through a volume: windows range from solid to free; keep exactly those with mean <= 0.85
    vol = sample_volume(Plane((0.3, 0.5, 0.8), 0.25), (48, 40, 56), 0.02, truncation=TRUNC)
    brute = _brute_windows(vol)
    means = np.array([w.mean(dtype=np.float64) for _, w in brute])
    assert np.all(np.abs(means - 0.85) > 1e-4)  # no window sits on the threshold
    assert 0 < np.sum(means <= 0.85) < len(brute)  # both kinds occur
    got = sample_windows(vol, permute=False, empty_fraction=0.0)
    np.testing.assert_array_equal(got, np.stack([w for (_, w), m in zip(brute, means) if m <= 0.85]))
    low = sample_windows(vol, permute=False, empty_fraction=0.0, max_mean=0.5)
    assert len(low) == np.sum(means <= 0.5) < len(got)


def test_empty_fraction_share_and_seed():
    vol = np.full((16, 16 + 8 * 99, 16 + 8 * 19), D_MAX, dtype=np.float32)  # 100 x 20 window origins
    vol[:, :16, :16] = D_MIN  # one solid corner: a few windows near it are kept, the rest are empty
    means = np.array([w.mean(dtype=np.float64) for _, w in _brute_windows(vol)])
    n_surface, n_empty = 6 * np.sum(means <= 0.85), 6 * np.sum(means > 0.85)
    assert n_surface > 0 and n_empty > 10_000
    got = sample_windows(vol, empty_fraction=0.1, seed=3)
    got_means = got.mean(axis=(1, 2, 3), dtype=np.float64)
    assert np.sum(got_means <= 0.85) == n_surface  # every surface window, whatever the draw
    extra = np.sum(got_means > 0.85)
    assert abs(extra - 0.1 * n_empty) < 5 * np.sqrt(0.1 * 0.9 * n_empty)  # Bernoulli(0.1) per discarded window
    np.testing.assert_array_equal(got, sample_windows(vol, empty_fraction=0.1, seed=3))
    other = sample_windows(vol, empty_fraction=0.1, seed=4)
    assert len(other) != len(got) or not np.array_equal(other, got)


def test_generator_equals_array_and_batches(rng):
    vols = [rng.uniform(-0.05, 0.11, size=s).astype(np.float32) for s in [(40, 24, 32), (16, 16, 16), (10, 40, 40)]]
    # a share of the windows are mostly free so the random empty-keeping matters
    vols[0][:, :, 16:] = D_MAX
    whole = sample_windows(vols, empty_fraction=0.3, seed=9)
    assert len(whole) > 0
    for batch_size in (1, 7, 100, 100_000):
        batches = list(iter_windows(vols, empty_fraction=0.3, seed=9, batch_size=batch_size))
        assert all(len(b) == batch_size for b in batches[:-1]) and 1 <= len(batches[-1]) <= batch_size
        np.testing.assert_array_equal(np.concatenate(batches), whole)


def test_sequence_and_stack_of_volumes(rng):
    a = rng.uniform(*TRUNC, size=(24, 24, 24))
    b = rng.uniform(*TRUNC, size=(24, 24, 24))
    both = np.concatenate([sample_windows(a, **KEEP_ALL), sample_windows(b, **KEEP_ALL)])
    np.testing.assert_array_equal(sample_windows([a, b], **KEEP_ALL), both)
    np.testing.assert_array_equal(sample_windows((a, b), **KEEP_ALL), both)
    np.testing.assert_array_equal(sample_windows(np.stack([a, b]), **KEEP_ALL), both)
    assert sample_windows([], **KEEP_ALL).shape == (0, 16, 16, 16)
    assert sample_windows(np.zeros((15, 40, 40)), **KEEP_ALL).shape == (0, 16, 16, 16)  # too thin for a window


class _RecordingVolume:
    """A lazily indexed volume that records the size of every read (what a memmap or Zarr array does)."""

    def __init__(self, data):
        self._data = data
        self.shape, self.ndim, self.dtype = data.shape, data.ndim, data.dtype
        self.reads: list[int] = []

    def __getitem__(self, key):
        out = self._data[key]
        self.reads.append(out.size)
        return out


def test_reads_are_bounded_tiles_and_output_does_not_depend_on_tiling(rng, monkeypatch):
    data = rng.uniform(-0.05, 0.12, size=(40, 64, 48)).astype(np.float32)
    data[:, 32:] = D_MAX
    reference = sample_windows(data, empty_fraction=0.25, seed=2)
    budget = 16 * 32 * 48  # room for 3 rows of windows along y per tile
    monkeypatch.setattr(sampler, "_TILE_VOXELS", budget)
    vol = _RecordingVolume(data)
    gen = iter_windows(vol, empty_fraction=0.25, seed=2, batch_size=16)
    first = next(gen)
    reads_before_first = len(vol.reads)
    rest = list(gen)
    assert max(vol.reads) <= budget and len(vol.reads) > reads_before_first  # read lazily, a tile at a time
    np.testing.assert_array_equal(np.concatenate([first, *rest]), reference)


def test_bad_inputs(rng):
    good = rng.uniform(*TRUNC, size=(16, 16, 16))
    with pytest.raises(ShapeError):
        sample_windows(np.zeros((16, 16)))
    with pytest.raises(ShapeError):
        sample_windows([good, np.zeros((16, 16))])
    with pytest.raises(DTypeError):
        sample_windows(np.zeros((16, 16, 16), dtype=np.int32))
    bad = good.copy()
    bad[3, 4, 5] = np.nan
    with pytest.raises(InvalidValueError, match="NaN"):
        sample_windows(bad)
    for kwargs in (dict(stride=0), dict(stride=2.5), dict(empty_fraction=1.5), dict(max_mean=float("nan")),
                   dict(truncation=(0.1, -0.04)), dict(truncation=None)):
        with pytest.raises(InvalidValueError):
            sample_windows(good, **kwargs)
    with pytest.raises(InvalidValueError):
        next(iter_windows(good, batch_size=0))
    with pytest.raises(InvalidValueError):
        window_origins((16, 16, 16), stride=-1)
