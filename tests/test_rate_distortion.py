"""examples/rate_distortion.py: its --quick path runs on a small synthetic map, and what it measures holds up
against expectations computed here independently (ZFP's error bound, DCT losslessness and Parseval, bytes on
disk, float16 and int8 storage, the surface metrics of the fused-like quick map against compare_volumes and
the map's own decode; the int8 quantiser itself is tested in test_int8_codes.py)."""

from __future__ import annotations

import importlib.util
import json
import os
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def rd():
    spec = importlib.util.spec_from_file_location("example_rate_distortion", ROOT / "examples" / "rate_distortion.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def quick(rd, tmp_path_factory):
    work = tmp_path_factory.mktemp("rd")
    res = rd.main(["--quick", "--workdir", str(work), "--out", str(work)])
    return rd, work, res


@pytest.fixture(scope="module")
def blocks(rd):
    coords, tsdf = rd.synthetic_blocks(True)
    v = rd.normalised(rd.fused_like(tsdf)[0])  # the quick data set is fused-like
    return np.ascontiguousarray(v[rd.nonempty_mask(v)])


def test_quick_writes_outputs(quick):
    rd, work, res = quick
    saved = json.loads((work / "rate-distortion.json").read_text())
    assert saved["points"] == json.loads(json.dumps(res["points"]))
    assert (work / "rate-distortion.png").stat().st_size > 10_000
    md = (work / "rate-distortion.md").read_text()
    assert "int8" in md and "simulated" in md and "64:1" in md
    kinds = {p["codec"] for p in res["points"]}
    assert {"pca-16", "pca-64", "zfp fixed-rate", "zfp fixed-accuracy", "dct float16", "blosc float16 raw"} <= kinds
    for p in res["points"]:
        assert set(p) >= {"codec", "setting", "bytes_per_block", "mse_voxel", "sse_block", "dataset"}
        assert p["sse_block"] == pytest.approx(4096 * p["mse_voxel"], rel=1e-9)
        assert p["bytes_per_block"] > 0 and p["mse_voxel"] >= 0
    assert res["wall_s"] > 0 and len(res["load_before"]) == 3


def test_map_bytes_match_disk(quick):
    """The bytes counted per map are the files on disk: codes + state + mask + codec state + metadata = du."""
    rd, work, res = quick
    maps = [p for p in res["points"] if p["kind"] == "map"]
    assert len(maps) == 12  # pca-16, pca-64 x float32, float16, int8 x plain, surface-true
    for p in maps:
        path = work / p["map"]
        total = sum(os.path.getsize(os.path.join(d, f)) for d, _, fs in os.walk(path) for f in fs)
        b = p["map_bytes"]
        assert b["total"] == total and b["other"] == 0
        assert b["codes"] + b["state"] + b["mask"] + b["codec_state"] + b["metadata"] == total
        assert p["bytes_per_block"] * p["blocks"] == pytest.approx(b["codes"] + b["state"] + b["mask"])
        # the mask: one bit per voxel before compression, stored only by the surface-true maps
        assert (b["mask"] > 0) == p["surface_true"] and b["mask"] < 512 * p["blocks"] + 4096
        # the codec state is the PCA basis (k x 4096), mean and variances, at least their raw float32 bytes
        assert b["codec_state"] >= 4 * (p["code_size"] * 4096 + 4096) * 0.5
    maps = [p for p in maps if not p["surface_true"]]
    # float16 codes take about half the bytes of float32 ones for the same codec
    for k in (16, 64):
        f32 = next(p for p in maps if p["codec"] == f"pca-{k}" and p["setting"] == "float32")
        f16 = next(p for p in maps if p["codec"] == f"pca-{k}" and p["setting"] == "float16")
        assert 0.35 < f16["bytes_per_block"] / f32["bytes_per_block"] < 0.65
        assert f16["mse_voxel"] >= f32["mse_voxel"] * (1 - 1e-3)
        # int8: a quarter of the code bytes plus 8 per block of offset and scale; a little more error
        i8 = next(p for p in maps if p["codec"] == f"pca-{k}" and p["setting"] == "int8 per-block")
        assert i8["bytes_per_block"] < 0.5 * f32["bytes_per_block"]
        assert f32["mse_voxel"] * (1 - 1e-3) <= i8["mse_voxel"] < 1.2 * f32["mse_voxel"]


def test_map_error_matches_codec(quick, blocks):
    """The error read back from the float32 map is the codec's own round-trip error on the same blocks."""
    from sdfcodec import pretrained_codec

    rd, work, res = quick
    c = pretrained_codec("pca", 64)
    # maps truncate decoded distances to [d_min, d_max]: [0, 1] in the codec's normalised units
    y = np.clip(np.asarray(c.decode(c.encode(blocks))), 0.0, 1.0)
    mse = float(((y.astype(np.float64) - blocks) ** 2).mean())
    p = next(p for p in res["points"] if p["codec"] == "pca-64" and p["setting"] == "float32")
    assert p["blocks"] == len(blocks)
    assert p["mse_voxel"] == pytest.approx(mse, rel=1e-4)


def test_zfp_bounds(rd, blocks):
    for tol in (0.05, 0.005):
        y, n = rd.zfp_roundtrip(blocks, tolerance=tol)
        assert np.abs(y.astype(np.float64) - blocks).max() <= tol  # ZFP's fixed-accuracy guarantee
    for rate in (0.25, 0.5):
        y, n = rd.zfp_roundtrip(blocks, rate=rate)
        assert (n == rate * 4096 / 8 + rd.ZFP_HEADER).all()  # fixed rate: payload exactly rate bits per value
    with pytest.raises(ValueError):
        rd.zfp_roundtrip(blocks[:1], rate=0.125)


def test_dct(rd, blocks):
    x = blocks.astype(np.float64)
    # all 4096 coefficients as float16: orthonormal, so the error's L2 norm is at most float16's relative
    # rounding (2^-11) times the block's norm, per block
    y = rd.dct_truncate(blocks, 4096).astype(np.float64)
    err = np.linalg.norm((y - x).reshape(len(x), -1), axis=1)
    assert (err <= 2.0 ** -11 * np.linalg.norm(x.reshape(len(x), -1), axis=1) * 1.001 + 1e-6).all()
    assert err.max() > 0  # float16 does round
    # Parseval: keeping K float64 coefficients, the SSE is the energy of the dropped ones
    from scipy.fft import dctn

    c = dctn(x, axes=(1, 2, 3), norm="ortho").reshape(len(x), -1)
    order = rd.dct_order()
    assert sorted(order) == list(range(4096)) and order[0] == 0
    for k in (64, 500):
        y = rd.dct_truncate(blocks, k, dtype=np.float64).astype(np.float64)
        sse = ((y - x) ** 2).reshape(len(x), -1).sum(1)
        assert sse == pytest.approx((c[:, order[k:]] ** 2).sum(1), rel=1e-4, abs=1e-6)


def test_surface_metrics_fused_like(quick, blocks):
    """Every point of the fused-like quick map has surface metrics; a map point's equal compare_volumes on the
    map's own dense decode (an independent path: Map.decode_region, not the script's block scatter), a
    near-lossless point has no surface moved, and the surface-true maps keep surfaces closer than plain ones."""
    import sdfcodec
    from sdfcodec.core.surface import compare_volumes

    rd, work, res = quick
    P = res["points"]
    assert all(set(p["surface"]) >= {"chamfer_l1", "f_score_1", "f_score_2", "sign_agreement"} for p in P)
    n = {p["surface"]["n_original"] for p in P}
    assert len(n) == 1 and n.pop() > 1000  # one reference for every point
    # the reference: the data set's blocks as a dense volume, with the fused-like observation
    coords, tsdf = rd.synthetic_blocks(True)
    tsdf, observed = rd.fused_like(tsdf)
    shape = tuple(int(k) * 16 for k in coords.max(axis=0) + 1)
    original, obs = np.full(shape, 0.1, np.float32), np.zeros(shape, bool)
    for c, t, o in zip(coords, tsdf, observed):
        sl = tuple(slice(16 * int(k), 16 * int(k) + 16) for k in c)
        original[sl], obs[sl] = t, o
    for setting in ("float32", "float32 surface-true", "int8 per-block surface-true"):
        p = next(p for p in P if p["codec"] == "pca-64" and p["setting"] == setting)
        m = sdfcodec.open_map(work / p["map"])
        dec = np.full(shape, 0.1, np.float32)
        d = m.decode_region()
        dec[tuple(slice(0, k) for k in d.shape)] = d
        # blocks the map does not code decode to d_max both ways (the map's extent may stop short of the grid)
        want = compare_volumes(original, dec, 0.02, observed=obs).to_dict()
        for key, v in want.items():
            assert p["surface"][key] == pytest.approx(v, rel=1e-5, abs=1e-7), (setting, key)
    blosc = next(p for p in P if p["codec"] == "blosc float16 raw")["surface"]
    assert blosc["chamfer_l1"] < 1e-4 and blosc["f_score_1"] == 1.0  # float16 rounding moves no surface
    for k in (16, 64):
        plain = next(p for p in P if p["codec"] == f"pca-{k}" and p["setting"] == "float32")
        true = next(p for p in P if p["codec"] == f"pca-{k}" and p["setting"] == "float32 surface-true")
        assert true["surface"]["chamfer_l1"] < plain["surface"]["chamfer_l1"]
        assert true["surface"]["f_score_1"] > plain["surface"]["f_score_1"]
    md = (work / "rate-distortion.md").read_text()
    assert "## Surfaces" in md and "Chamfer-L1 (mm) | F@1 voxel" in md
