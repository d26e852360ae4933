"""The pca plugin's compiled encode gives the same codes in every process: one that compiles the kernels itself and
one that loads them from numba's on-disk cache (they differed while the kernels let the code generator reorder
sums, so the first map written after an install differed from the next), and the fixed-order dot product it rests
on (:mod:`sdfcodec_pca.vecdot`)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest

pytest.importorskip("numba")

from numba import njit  # noqa: E402

from sdfcodec_pca.vecdot import dot, dot4  # noqa: E402


@njit(cache=False)
def _dot(x, y, n):
    return dot(x, y, n)


@njit(cache=False)
def _dot4(x, r, n):
    return dot4(x, r[0], r[1], r[2], r[3], n)


def _lane_order(x: np.ndarray, y: np.ndarray, n: int) -> np.float32:
    """The documented order in numpy float32: eight lanes over the full groups, a fixed tree, then the tail."""
    lanes = np.zeros(8, np.float32)
    full = n // 8
    for i in range(full):
        lanes = lanes + x[8 * i:8 * i + 8] * y[8 * i:8 * i + 8]
    p = [np.float32(lanes[i] + lanes[i + 1]) for i in range(0, 8, 2)]
    total = np.float32(np.float32(p[0] + p[1]) + np.float32(p[2] + p[3]))
    for j in range(8 * full, n):
        total = np.float32(total + x[j] * y[j])
    return total


def _exact_products(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Float32 vectors of length ``n`` (seeded by ``n``) whose products are exact: integers of very different sizes
    times powers of two, so a sum of them depends on the order of its additions only."""
    rng = np.random.default_rng(n)
    x = (rng.integers(-999, 999, n) * 2.0 ** rng.integers(-6, 26, n)).astype(np.float32)
    y = (2.0 ** rng.integers(-3, 3, n) * rng.choice([-1, 1], n)).astype(np.float32)
    return x, y


@pytest.mark.parametrize("n", [0, 1, 7, 8, 9, 15, 16, 17, 33, 63, 64, 65, 128])
def test_dot_adds_in_its_documented_order(n):
    # integers of very different sizes times powers of two: every product is exact, so the result is fixed by
    # the order of the additions alone (a fused multiply-add rounds as a multiply and an add do), and orders differ
    x, y = _exact_products(n)
    got = _dot(x, y, n)
    assert got == _lane_order(x, y, n)
    rows = np.stack([y, -y, y[::-1], 2 * y]) if n else np.zeros((4, 0), np.float32)
    assert _dot4(x, rows, n) == tuple(_lane_order(x, r, n) for r in rows)
    exact = float(x.astype(np.float64) @ y.astype(np.float64))
    assert abs(float(got) - exact) <= 1e-6 * float(np.abs(x * y).sum())


def test_the_order_test_tells_orders_apart():
    # the data above distinguish the lane order from a plain running sum (so the test above can fail)
    differs = 0
    for n in (33, 63, 64, 65, 128):
        x, y = _exact_products(n)
        running = np.float32(0)
        for a, b in zip(x, y):
            running = np.float32(running + a * b)
        differs += running != _lane_order(x, y, n)
    assert differs >= 3


def test_dot_is_a_dot_product_on_any_floats():
    rng = np.random.default_rng(5)
    for n in (3, 64, 100, 4096):
        x, y = rng.standard_normal((2, n)).astype(np.float32)
        ref = float(x.astype(np.float64) @ y.astype(np.float64))
        assert abs(float(_dot(x, y, n)) - ref) <= 8 * n * 2.0 ** -24 * float(np.abs(x * y).sum())
    assert _dot(x, y, 10) == _dot(x[:10].copy(), y[:10].copy(), 10)  # reads only the first n


_ENCODE = textwrap.dedent("""
    import json, sys
    import numpy as np, torch
    from sdfcodec.bench.codecs import bench_instance, fused_style_weights
    from sdfcodec.map.observed import encode_truncated
    from sdfcodec.testing import analytic_blocks
    from sdfcodec_pca import kernels
    codec, _ = bench_instance("pca", 64)
    x = torch.from_numpy(analytic_blocks(256, seed=11))
    w = torch.from_numpy(fused_style_weights(x.numpy()))
    np.save(sys.argv[1], encode_truncated(codec, x, w).numpy())
    stats = kernels.kernel.stats
    print(json.dumps({"hits": sum(stats.cache_hits.values()), "misses": sum(stats.cache_misses.values())}))
""")


@pytest.mark.slow
def test_codes_are_the_same_compiled_or_loaded_from_the_cache(tmp_path):
    # two processes on an empty numba cache: the first compiles the kernels (and writes the cache), the second
    # loads them; the codes must agree bit for bit (they did not while the kernels' sums were 'reassoc')
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "numba-cache")}
    runs = []
    for i in range(2):
        out = tmp_path / f"codes{i}.npy"
        done = subprocess.run([sys.executable, "-c", _ENCODE, str(out)], env=env, capture_output=True, text=True,
                              timeout=600, check=True)
        runs.append((json.loads(done.stdout.strip().splitlines()[-1]), np.load(out)))
    (first, a), (second, b) = runs
    assert first == {"hits": 0, "misses": 1} and second == {"hits": 1, "misses": 0}
    assert np.array_equal(a, b), f"codes differ by up to {np.abs(a - b).max()}"
