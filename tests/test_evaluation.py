"""`sdfcodec track` / `sdfcodec eval` logic (sdfcodec.evaluation) on a tiny synthetic sequence (10 frames at
160 x 120): outputs exist and are consistent, unavailable methods are skipped with a reason, the tracker stays
within 1 cm of the ground truth on the original map, and lazy decoding tracks like dense decoding."""

from __future__ import annotations

import json

import numpy as np
import pytest

pytest.importorskip("open3d")
pytest.importorskip("matplotlib")

from sdfcodec.errors import InvalidValueError  # noqa: E402
from sdfcodec.evaluation import METHODS, eval_command, markdown_table, track_command  # noqa: E402
from sdfcodec.metrics import read_tum  # noqa: E402


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
    for name in ("reconstruction_error.png", "ate_slow-clean.png", "slice_slow-clean.png"):
        assert (out / "eval" / name).stat().st_size > 1000 and (docs / "eval" / name).is_file()


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
    from sdfcodec.evaluation import build_codec
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
