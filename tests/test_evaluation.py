"""`sdfcodec track` / `sdfcodec eval` logic (sdfcodec.evaluation.tracking) on a tiny synthetic sequence (10 frames at
160 x 120): outputs exist and are consistent, unavailable methods are skipped with a reason, the tracker stays
within 1 cm of the ground truth on the original map, and lazy decoding tracks like dense decoding."""

from __future__ import annotations

import json

import numpy as np
import pytest

pytest.importorskip("open3d")
pytest.importorskip("matplotlib")

from sdfcodec.errors import InvalidValueError  # noqa: E402
from sdfcodec.evaluation.tracking import METHODS, eval_command, markdown_table, track_command  # noqa: E402
from sdfcodec.core.metrics import read_tum  # noqa: E402


@pytest.fixture(scope="module")
def tiny_eval(tmp_path_factory):
    out = tmp_path_factory.mktemp("eval")
    docs = out / "docs"
    res = eval_command(["synthetic:slow-clean"], out, methods=["original", "pca-32", "blur-9", "ae-32"], frames=10,
                       size=(160, 120), docs_dir=docs, progress=False, log=None)
    return out, docs, res


def test_eval_end_to_end(tiny_eval):
    out, docs, res = tiny_eval
    seq = res["sequences"]["slow-clean"]
    assert seq["frames"] == 10 and seq["blocks"] > 0
    rows = seq["methods"]
    assert set(rows) == {"original", "pca-32", "blur-9"}
    assert "ae-32" in res["skipped"] and res["skipped"]["ae-32"]  # only ae-64 could be shipped: a reason
    assert rows["original"]["mse"] == 0.0 and rows["original"]["block_sse"] == 0.0
    assert 0 < rows["pca-32"]["mse"] < 0.1 and 0 < rows["blur-9"]["mse"] < 0.1
    # per-block SSE is the per-voxel MSE times the 4096 voxels of a block
    assert rows["pca-32"]["block_sse"] == pytest.approx(4096 * rows["pca-32"]["mse"], rel=1e-6)
    # started from ground truth, the tracker stays within 1 cm mean ATE on the original map
    assert rows["original"]["ate_mean"] < 0.01, rows["original"]
    assert len(rows["original"]["ate_errors"]) == 10 and rows["original"]["ate_errors"][0] < 0.005
    agg = res["aggregate"]
    assert agg["pca-32"]["sequences"] == 1 and agg["pca-32"]["ate_mean_std"] == 0.0
    # the files
    data = json.loads((out / "eval.json").read_text())
    assert data["aggregate"].keys() == agg.keys() and (docs / "eval.json").is_file()
    md = (out / "eval.md").read_text()
    assert md == markdown_table(res)
    assert "| PCA 32 |" in md and "| NN 32 | skipped:" in md and "Reconstruction Error" in md
    assert "| Chamfer-L1 [mm] ± σ | F@1 voxel | ATE / lossless ± σ |" in md
    assert "| Chamfer-L1 [mm] | F@1 voxel |" in md and "| ATE / lossless |" in md
    # the lossless row against itself: Chamfer 0, F = 1, ATE ratio 1 (aggregate and per sequence)
    assert "| 0.00 ± 0.00 | 1.000 | 1.00 ± 0.00 |" in md.split("| Original data |")[1].splitlines()[0]
    for name in ("reconstruction_error.png", "ate_slow-clean.png", "slice_slow-clean.png"):
        assert (out / "eval" / name).stat().st_size > 1000 and (docs / "eval" / name).is_file()


def test_eval_surface_metrics_and_ate_ratio(tiny_eval):
    """The surface metrics of a row are compare_volumes of its decoded map against the lossless map, the band
    restricted to the voxels the lossless map records as observed; ate_ratio is over the lossless row's ATE."""
    import sdfcodec
    from sdfcodec.core.surface import compare_volumes
    from sdfcodec.evaluation.tracking import SURFACE_FIELDS
    from sdfcodec.core.header import BlockState

    out, _, res = tiny_eval
    rows = res["sequences"]["slow-clean"]["methods"]
    maps = out / "maps" / "slow-clean"
    ref = sdfcodec.open_map(maps / "original.sdfz")
    a = ref.decode_region()
    coded = np.argwhere(ref.block_states() == BlockState.CODED)
    obs = np.zeros(tuple(16 * g for g in ref.grid_blocks), dtype=bool)
    for c, o in zip(coded, ref.read_observed(coded)):
        obs[16 * c[0]:16 * c[0] + 16, 16 * c[1]:16 * c[1] + 16, 16 * c[2]:16 * c[2] + 16] = o
    obs = obs[:a.shape[0], :a.shape[1], :a.shape[2]]
    assert 0 < obs.sum() < obs.size
    for k in ("pca-32", "blur-9"):
        b = sdfcodec.open_map(maps / f"{k}.sdfz").decode_region()
        want = compare_volumes(a, b, ref.voxel_size, origin=ref.origin, observed=obs).to_dict()
        for f in SURFACE_FIELDS:
            assert rows[k][f] == pytest.approx(want[f], rel=1e-9, abs=1e-12), (k, f)
        assert rows[k]["ate_ratio"] == pytest.approx(rows[k]["ate_mean"] / rows["original"]["ate_mean"])
    assert 0 < rows["pca-32"]["chamfer_l1"] < 0.02 and 0.5 < rows["pca-32"]["f_score_1"] < 1
    # the 9^3 blur lifts the thin negative band ([-4, 0] cm) above zero: its surfaces all but vanish
    assert rows["blur-9"]["chamfer_l1"] > rows["pca-32"]["chamfer_l1"] and rows["blur-9"]["f_score_1"] < 0.5
    o = rows["original"]
    assert o["chamfer_l1"] == 0.0 and o["f_score_1"] == o["f_score_2"] == o["sign_agreement"] == 1.0
    assert o["near_surface_rmse"] == 0.0 and o["ate_ratio"] == 1.0
    agg = res["aggregate"]["pca-32"]  # one sequence: the mean is the row, the std 0
    assert agg["chamfer_l1_mean"] == rows["pca-32"]["chamfer_l1"] and agg["chamfer_l1_std"] == 0.0
    assert agg["ate_ratio_mean"] == rows["pca-32"]["ate_ratio"] and agg["f_score_1_std"] == 0.0


def test_markdown_table_without_a_surface():
    """A decoded map with no surface (Chamfer-L1 inf: null in the record) prints '-', not inf or nan."""
    row = {"mse": 0.01, "block_sse": 41.0, "chamfer_l1": None, "f_score_1": 0.0, "ate_mean": 0.02,
           "ate_std": 0.001, "ate_median": 0.02, "ate_ratio": None, "failures": 0, "frames_per_s": 10.0}
    res = {"sequences": {"s": {"frames": 3, "blocks": 1, "methods": {"pca-64": row}}}, "skipped": {}}
    from sdfcodec.evaluation.tracking import _aggregate

    res["aggregate"] = _aggregate(res, ["pca-64"])
    md = markdown_table(res)
    assert "| PCA 64 | 41.00 | 0.01000 | - | 0.000 | 0.0200 |" in md
    assert md.splitlines()[2].endswith("| - | 0.000 | - |") and "nan" not in md and "inf" not in md


def test_eval_rejects_unknown_method(tmp_path):
    with pytest.raises(InvalidValueError, match="unknown method"):
        eval_command(["synthetic:slow-clean"], tmp_path, methods=["jpeg"], log=None)
    assert "sequential-64-64" in METHODS and len(METHODS) == 10


def test_track_command_lazy_and_dense(tiny_eval, tmp_path):
    out, _, res = tiny_eval
    seq_path = res["sequences"]["slow-clean"]["path"]
    raw = out / "maps" / "slow-clean" / "pca-32.sdfz"
    lazy = track_command(raw, seq_path, tmp_path / "lazy.txt", progress=False)
    dense = track_command(raw, seq_path, tmp_path / "dense.txt", dense=True, progress=False)
    assert lazy["frames"] == 10 and lazy["start"] == "groundtruth" and lazy["frames_per_s"] > 0
    assert dense["startup_s"] > 0 and dense["frames_per_s_median"] > 0 and dense["seconds"] > 0
    a, b = read_tum(tmp_path / "lazy.txt"), read_tum(tmp_path / "dense.txt")
    assert len(a) == 10 and np.array_equal(a.timestamps, b.timestamps)
    np.testing.assert_allclose(a.positions, b.positions, atol=1e-4)  # same field, same poses
    c = lazy["cache"]
    assert c["misses"] > 0 and c["hits"] > c["misses"] and c["blocks_decoded"] > 0 and dense["cache"] is None
    assert lazy["ate"]["mean"] == pytest.approx(res["sequences"]["slow-clean"]["methods"]["pca-32"]["ate_mean"],
                                                abs=1e-3)
    with pytest.raises(InvalidValueError, match="start"):
        track_command(raw, seq_path, tmp_path / "x.txt", start="nowhere", progress=False)


def test_rows_take_model_files(tmp_path):
    """A row's codec can come from a model file (ae-32 and ae-128 are not shipped); a file of another codec or
    size is refused."""
    import sdfcodec
    from sdfcodec.evaluation.tracking import build_codec
    from sdfcodec.testing import analytic_blocks

    pca = sdfcodec.get_codec("pca", code_size=32).fit(analytic_blocks(100, seed=1))
    path = sdfcodec.save_model(pca, tmp_path / "pca-32.npz")
    got = build_codec(METHODS["pca-32"], path)
    x = analytic_blocks(5, seed=2)
    assert np.array_equal(got.encode(x), pca.encode(x))
    with pytest.raises(InvalidValueError, match="not the ae-32"):
        build_codec(METHODS["ae-32"], path)
    with pytest.raises(InvalidValueError, match="not the pca-64"):
        build_codec(METHODS["pca-64"], path)
