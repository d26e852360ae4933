"""A search on a pca map never imports torch (issue 44: its import was 1.7 s of a 3 s first search on two
cores): the pca codec's numpy path (capability ``numpy_path``) against its torch hooks, codecs without one
falling back to them, and a first search of a fused-style map in a fresh interpreter, torch-free, selecting what
the torch path selects."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap

import numpy as np
import pytest
import torch

import sdfcodec
from sdfcodec.codec import capabilities, numpy_path_of
from sdfcodec.errors import PluginError
from sdfcodec.map.observed import error_weights
from sdfcodec.search.arrays import decode_array, encode_array
from sdfcodec.testing import analytic_blocks
from test_observed import TRUNC, VS, blocks_and_mask, fused_like, scene, write  # noqa: F401 (a fixture)


@pytest.fixture(scope="module")
def fused(blocks_and_mask):
    """Normalised fused-like blocks ``(n, 16, 16, 16)`` that hold a surface, and their error weights."""
    v, o = blocks_and_mask
    v = np.ascontiguousarray(v)
    return v, error_weights(v, o, TRUNC, VS)


@pytest.mark.parametrize("mean", ["dataset", "block"])
def test_pca_numpy_path_equals_its_torch_encode_and_decode(mean):
    x = analytic_blocks(40, seed=3)
    if mean == "dataset":
        codec = sdfcodec.pretrained_codec("pca", 64)
    else:
        codec = sdfcodec.get_codec("pca", code_size=16, mean="block").fit(analytic_blocks(200, seed=4))
    path = numpy_path_of(codec)
    assert path is not None and "numpy_path" in capabilities(codec)
    flat = np.ascontiguousarray(x, np.float32).reshape(len(x), -1)
    codes = codec.encode(x)
    got = path.encode(flat)
    assert got.dtype == np.float32 and got.shape == codes.shape
    np.testing.assert_allclose(got, codes, rtol=0, atol=1e-5 * np.abs(codes).max())
    for k in (codec.code_size, codec.code_size // 2):  # the whole code and a prefix (prefix-ordered)
        want = np.asarray(codec.decode(codes[:, :k])).reshape(len(x), -1)
        back = path.decode(np.ascontiguousarray(codes[:, :k]))
        assert back.dtype == np.float32 and back.shape == want.shape
        np.testing.assert_allclose(back, want, rtol=0, atol=1e-5)
    # and against the basis itself, float64: the affine maps of the state, independent of both paths
    s = codec.state_dict()
    if mean == "dataset":
        ref = (flat.astype(np.float64) - s["mean"]) @ s["components"].T.astype(np.float64)
        np.testing.assert_allclose(got, ref, rtol=0, atol=1e-4)


def test_pca_numpy_truncated_encode_is_the_compiled_pass(fused):
    pytest.importorskip("numba")
    v, w = fused
    codec = sdfcodec.pretrained_codec("pca", 64)
    from test_fast_encode import assert_same_refits

    n = len(v)
    for rounds in (0, 3):
        got = numpy_path_of(codec).encode_truncated(v.reshape(n, -1), w.reshape(n, -1), rounds)
        want = codec.encode_truncated(torch.from_numpy(v), torch.from_numpy(w), rounds).numpy()
        assert got.dtype == np.float32 and got.shape == (n, 64)
        if rounds == 0:  # the weighted fit: continuous, equal to float32 rounding
            np.testing.assert_allclose(got, want, rtol=0, atol=1e-4 * np.abs(want).max())
        else:  # the refits' active sets may flip on a voxel within rounding of its bound: the same error then.
            # The two paths feed the pass plain codes from numpy's and torch's products (float32 rounding apart);
            # its six conjugate-gradient steps from those starts end up to 1.0 % apart on single blocks (4 of 54
            # here), 0.1 % in total as assert_same_refits checks
            assert_same_refits(codec, got, want, v, w, per_block=1.02)


def test_codecs_without_a_numpy_path_take_their_own_encode_and_decode():
    raw = sdfcodec.get_codec("raw")
    x = analytic_blocks(3, seed=1)
    assert numpy_path_of(raw) is None
    codes = encode_array(raw, x)
    np.testing.assert_array_equal(codes, np.asarray(raw.encode(x)))
    np.testing.assert_array_equal(decode_array(raw, codes), x.reshape(3, -1))


def test_a_non_finite_decode_is_refused_on_the_numpy_path():
    codec = sdfcodec.pretrained_codec("pca", 32)
    codes = np.zeros((2, 32), np.float32)
    codes[1, 3] = np.inf
    with pytest.raises(PluginError, match="NaN/Inf"):
        decode_array(codec, codes)


def _search_in_fresh_interpreter(path, cache: str) -> dict:
    code = textwrap.dedent("""
        import contextlib, io, json, os, sys
        os.environ["SDFCODEC_CACHE_DIR"] = sys.argv[2]
        from sdfcodec.cli import app
        buf = io.StringIO()
        with contextlib.redirect_stdout(buf):
            try:
                app(["search", sys.argv[1], "--query", "floor", "--up", "0,0,1", "--device", "cpu", "--json"])
            except SystemExit as e:
                assert not e.code, e.code
        print(json.dumps({"result": json.loads(buf.getvalue()), "torch": "torch" in sys.modules}))
    """)
    r = subprocess.run([sys.executable, "-c", code, str(path), cache], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    return json.loads(r.stdout.strip().splitlines()[-1])


def test_a_first_search_of_a_fused_map_imports_no_torch_and_selects_as_the_torch_path(tmp_path, monkeypatch):
    """Masked (fused-style) map of a floor at z = 0.31 m, a wall and a box: the first floor search in a fresh
    interpreter (query built, weighted-encoded, calibrated, plane-checked) never loads torch, and selects the
    blocks the torch path selects, with the same scores to float32 rounding."""
    vol, obs = fused_like(scene())
    path = tmp_path / "fused.sdfz"
    write(path, vol, obs)
    got = _search_in_fresh_interpreter(path, str(tmp_path / "cache"))
    assert got["torch"] is False
    # the torch path: every numpy path switched off, in this process (torch loaded), no cache
    import sdfcodec.map.observed as observed
    import sdfcodec.search.arrays as arrays
    from sdfcodec.search.engine import search
    from sdfcodec.search.cache import clear_memory_cache

    monkeypatch.setattr(arrays, "numpy_path_of", lambda codec: None)
    monkeypatch.setattr(observed, "numpy_path_of", lambda codec: None)
    monkeypatch.setenv("SDFCODEC_CACHE_DIR", "off")
    clear_memory_cache()
    ref = search(sdfcodec.open_map(path), "floor", up=(0, 0, 1), threshold="auto", device="cpu")
    clear_memory_cache()
    mine = {tuple(b["coords"]): b["score"] for b in got["result"]["blocks"]}
    theirs = {tuple(int(v) for v in c): float(s) for c, s in zip(ref.coords, ref.scores)}
    assert mine.keys() == theirs.keys() and len(mine) >= 4
    assert {c[2] for c in mine} <= {0, 1}  # the floor's blocks: z = 0.31 m is voxel 15.5, between those layers
    for c, s in mine.items():
        assert s == pytest.approx(theirs[c], rel=1e-3, abs=1e-3)
    assert got["result"]["threshold"] == pytest.approx(ref.threshold, rel=1e-3)


def test_plane_components_number_patches_as_scipy_does():
    """The map-level stage's patches (no scipy import on a search's path): random blocks, normals and planes,
    labelled as scipy's connected components of the same neighbour graph label them (the peer it replaced)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    from sdfcodec.search.scene import PLANE_ANGLE_DEG, PLANE_TOL_VOXELS, plane_components

    rng = np.random.default_rng(7)
    for n in (0, 1, 2, 40, 300):
        coords = np.unique(rng.integers(0, 8, (n, 3)), axis=0)
        m = len(coords)
        normals = np.tile([0.0, 0.0, 1.0], (m, 1)) + rng.normal(0, 0.15, (m, 3)) * (rng.random((m, 1)) < 0.5)
        normals /= np.linalg.norm(normals, axis=1, keepdims=True)
        points = (coords * 16 + 7.5) * VS + rng.normal(0, 0.02, (m, 3))
        got = plane_components(coords, normals, points, VS)
        # the graph by its definition, pair by pair
        cos_a, tol = np.cos(np.radians(PLANE_ANGLE_DEG)), PLANE_TOL_VOXELS * VS
        a, b = [], []
        for i in range(m):
            for j in range(i + 1, m):
                d = points[j] - points[i]
                if (np.abs(coords[i] - coords[j]).max() == 1 and normals[i] @ normals[j] >= cos_a
                        and abs(normals[i] @ d) <= tol and abs(normals[j] @ d) <= tol):
                    a.append(i)
                    b.append(j)
        want = connected_components(coo_matrix((np.ones(len(a)), (a, b)), shape=(m, m)), directed=False)[1]
        np.testing.assert_array_equal(got, want)
        assert got.dtype == np.int64


@pytest.mark.parametrize("vr", [{"step": 0.6}, {"step": 0.6, "refine_step": 0.004}], ids=["pinned", "refined"])
def test_a_pinned_mask_is_read_without_torch_as_through_it_and_exactly(tmp_path, monkeypatch, vr):
    """A variable-rate map's pinned mask (spec/map-format.md 6g) is told from the codes' float decode: on the
    codec's numpy ``decode_affine`` (no torch) that decode equals the torch path's to float32 rounding, and the
    mask read is the torch path's and the exact read's (numba off: every voxel's exact integer decode), bit for
    bit; then (pinned map) a first floor search in a fresh interpreter loads no torch and selects what the torch
    path does."""
    from sdfcodec.core import ans
    from sdfcodec.map import pinstore
    from sdfcodec.map.observed import read_block_rows

    if not ans.available():
        pytest.skip("numba is not installed: the mask is read by its exact decode, with no float decode")
    path = tmp_path / "vr.sdfz"
    write(path, *fused_like(scene()), k=128, codec_state="reference", variable_rate=vr)
    m = sdfcodec.open_map(path)
    assert (m.header.codes.variable_rate.refinement is not None) == ("refine_step" in vr)
    r, arr = m.reader, m.reader.mask_array
    coords = np.argwhere(r.vr.states() == 2)
    key = np.zeros(3, np.int64)  # the map's one chunk
    own = pinstore.chunk_blocks(r.vr.states(), key, arr.cb)[0]
    q = type(arr)(r)._codes(key)
    rows, fast = {}, type(arr)(r)._float_decode(q, own)
    rows["numpy"] = read_block_rows(r, type(arr)(r), coords)
    with monkeypatch.context() as mp:
        mp.setattr(pinstore, "numpy_decode_affine", lambda codec: None)
        slow = type(arr)(r)._float_decode(q, own)
        rows["torch"] = read_block_rows(r, type(arr)(r), coords)
    with monkeypatch.context() as mp:
        mp.setattr(ans, "available", lambda: False)
        rows["exact"] = read_block_rows(r, type(arr)(r), coords)
    assert fast.dtype == np.float32 and fast.shape == slow.shape == (len(own), 4096)
    np.testing.assert_allclose(fast, slow, rtol=0, atol=1e-6)
    assert TRUNC[0] <= fast.min() and fast.max() <= TRUNC[1]  # truncated, as the read's metres
    assert np.array_equal(rows["numpy"], rows["torch"]) and np.array_equal(rows["numpy"], rows["exact"])
    assert 0 < np.unpackbits(rows["exact"]).mean() < 1  # a mask with observed and unobserved voxels
    if "refine_step" in vr:
        return  # the search's path is the same on a refined map (the mask's float decode before its refinement)
    got = _search_in_fresh_interpreter(path, str(tmp_path / "cache"))
    assert got["torch"] is False
    from sdfcodec.search.cache import clear_memory_cache
    from sdfcodec.search.engine import search

    monkeypatch.setattr(pinstore, "numpy_decode_affine", lambda codec: None)
    monkeypatch.setenv("SDFCODEC_CACHE_DIR", "off")
    clear_memory_cache()
    ref = search(sdfcodec.open_map(path), "floor", up=(0, 0, 1), threshold="auto", device="cpu")
    clear_memory_cache()
    assert sorted(tuple(b["coords"]) for b in got["result"]["blocks"]) == sorted(map(tuple, ref.coords.tolist()))
    assert len(ref.coords) >= 4
