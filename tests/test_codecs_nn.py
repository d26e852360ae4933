"""The neural and mixed codecs (``ae``, ``parallel``, ``sequential``): conformance with golden fixtures, training
(early stopping, determinism, resumable checkpoints, the paper's gd setting), the mixing-weight line search,
plain-array state, shipped weights. Small networks (hidden 16, code 8) keep the suite fast; the paper-sized
evaluation is ``examples/eval_codecs.py`` (and the ``slow`` test at the end)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

import sdfcodec
from sdfcodec.data.synthetic import synthetic_blocks
from sdfcodec import errors
from sdfcodec.errors import FormatError, InvalidValueError, NotFittedError, ShapeError
from sdfcodec.testing import analytic_blocks, check_codec

GOLDEN = Path(__file__).parent / "golden"
ROOT = Path(__file__).resolve().parents[1]
# small, quick settings: one thread (much faster than two on a busy 2-core machine), no progress bars
FAST = {"progress": False, "threads": 1, "batch_size": 100, "lr": 1e-2}


def mse(a, b) -> float:
    return float(np.mean((np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2))


def per_block_sse(a, b) -> np.ndarray:
    return ((np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2).reshape(len(a), -1).sum(axis=1)


@pytest.fixture(scope="module")
def blocks() -> np.ndarray:
    return np.concatenate([synthetic_blocks(900, seed=11), analytic_blocks(300, seed=5)])


@pytest.fixture(scope="module")
def tiny() -> np.ndarray:
    return synthetic_blocks(240, seed=4)


@pytest.fixture(scope="module")
def small_ae(blocks):
    return sdfcodec.get_codec("ae", code_size=8, hidden=16,
                              training={**FAST, "max_epochs": 30, "patience": 100}).fit(blocks)


@pytest.fixture(scope="module")
def small_seq(blocks):
    return sdfcodec.get_codec("sequential", pca_size=8, ae_size=8, hidden=16,
                              training={**FAST, "max_epochs": 12, "patience": 100}).fit(blocks)


# -- golden fixtures (every conformance check of ae, parallel and sequential: test_conformance_builtin.py) ----
def test_ae_golden_and_round_trip(small_ae, regen_golden, golden_round_trip):
    report = golden_round_trip(small_ae, GOLDEN / "ae-8-h16", regen_golden)
    assert report["mse"] < 0.06


def test_parallel_golden_and_round_trip(small_ae, regen_golden, golden_round_trip):
    par = type(sdfcodec.get_codec("parallel")).from_parts(sdfcodec.pretrained_codec("pca", 8), small_ae)
    assert par.code_size == 8 + 8 + 1 and not par.prefix_ordered
    report = golden_round_trip(par, GOLDEN / "parallel-8-8", regen_golden)
    assert report["mse"] < 0.02


def test_sequential_golden_and_round_trip(small_seq, regen_golden, golden_round_trip):
    assert small_seq.code_size == 17
    report = golden_round_trip(small_seq, GOLDEN / "sequential-8-8", regen_golden)
    assert report["mse"] < 0.02


@pytest.mark.parametrize("codec_id,weight", [("parallel", 0.7), ("sequential", 1.0)])
def test_fixed_weight(codec_id, weight, small_ae, small_seq, blocks):
    """A fixed w makes the code two plain codes (no w slot) and decodes with that w."""
    if codec_id == "parallel":
        mix = type(sdfcodec.get_codec("parallel")).from_parts(sdfcodec.pretrained_codec("pca", 8), small_ae,
                                                              weight=weight)
    else:
        mix = sdfcodec.get_codec({**small_seq.get_config(), "weight": weight}).load_state_dict(small_seq.state_dict())
    assert mix.code_size == 16 and mix.get_config()["weight"] == weight
    # every check: on 64 blocks (of the default 256) and test_conformance_builtin.py's large batch, and with 4
    # training epochs in the configuration (the state checks fit rival instances of it; the mixture's weights
    # stay small_ae's and small_seq's): a third of the time, the same comparisons
    mix = sdfcodec.get_codec({**mix.get_config(), "training": {**FAST, "max_epochs": 4}}).load_state_dict(
        mix.state_dict())
    check_codec(mix, blocks=analytic_blocks(64), large_batch=1024)
    x = blocks[:50]
    codes = mix.encode(x)
    p = mix.pca_.decode(codes[:, :8])
    a = mix.ae_.decode(codes[:, 8:16])
    expect = weight * p + (1 - weight) * a if codec_id == "parallel" else p + weight * a
    assert np.allclose(mix.decode(codes), expect, atol=1e-5)


# -- the mixing weight -------------------------------------------------------------------------------------
def test_parallel_weight_is_the_best_per_block(small_ae, blocks):
    """Per-block w beats (or ties) both parts alone and every w of a fine grid, block by block."""
    par = type(sdfcodec.get_codec("parallel")).from_parts(sdfcodec.pretrained_codec("pca", 8), small_ae)
    x = blocks[::3]
    codes = par.encode(x)
    err = per_block_sse(par.decode(codes), x)
    p, a = par.pca_.decode(codes[:, :8]), par.ae_.decode(codes[:, 8:16])
    for w in np.linspace(0, 1, 41):
        assert np.all(err <= per_block_sse(w * p + (1 - w) * a, x) + 1e-3), f"w = {w} beats the line search"
    assert np.all(err <= per_block_sse(p, x) + 1e-3) and np.all(err <= per_block_sse(a, x) + 1e-3)
    stats = sdfcodec_mixed().weight_stats(codes)
    assert stats["n"] == len(x) and abs(stats["at_0"] + stats["at_1"] + stats["between"] - 1) < 1e-9
    assert np.all((codes[:, -1] >= 0) & (codes[:, -1] <= 1))


def test_sequential_beats_its_pca_part(small_seq, blocks):
    codes = small_seq.encode(blocks)
    pca_only = small_seq.pca_.decode(small_seq.pca_.encode(blocks))
    seq = small_seq.decode(codes)
    assert np.all(per_block_sse(seq, blocks) <= per_block_sse(pca_only, blocks) + 1e-3)
    assert mse(seq, blocks) < 0.97 * mse(pca_only, blocks)
    # its weight search: w = 0 reproduces the PCA part exactly
    codes0 = codes.copy()
    codes0[:, -1] = 0
    assert np.allclose(small_seq.decode(codes0), pca_only, atol=1e-5)


def test_weight_functions_edge_cases():
    import sdfcodec_mixed as m

    x = torch.rand(3, 4096)
    same = torch.rand(3, 4096)
    assert torch.equal(m.parallel_weight(x, same, same), torch.ones(3))  # parts agree: PCA
    assert torch.equal(m.sequential_weight(x, torch.zeros(3, 4096)), torch.zeros(3))
    # the unconstrained optimum of parallel is recovered when inside [0, 1]
    p, a = torch.rand(2, 4096), torch.rand(2, 4096)
    assert torch.allclose(m.parallel_weight(0.3 * p + 0.7 * a, p, a), torch.full((2,), 0.3), atol=1e-5)


# -- training -------------------------------------------------------------------------------------------------
def _ae(**training):
    return sdfcodec.get_codec("ae", code_size=4, hidden=8, training={**FAST, "max_epochs": 4, "patience": 100,
                                                                     **training})


def test_training_reduces_validation_error(small_ae):
    h = small_ae.history_
    assert h["best_val_mse"] < 0.5 * h["initial_val_mse"]
    assert h["n_train"] + h["n_val"] == 1200 and h["n_val"] == 150  # a held-out 1/8
    assert [r["epoch"] for r in h["history"]] == list(range(1, 31))


def test_early_stopping_keeps_the_best_epoch(tiny):
    # demand a 50 % improvement per epoch: training stops after `patience` epochs without one
    c = _ae(max_epochs=50, patience=2, min_improvement=0.5).fit_validated(tiny[:200], tiny[200:])
    h = c.history_
    assert h["stopped"] == "early stopping" and len(h["history"]) < 50
    vals = [r["val_mse"] for r in h["history"]]
    assert h["best_epoch"] == (1 + int(np.argmin(vals)) if min(vals) < h["initial_val_mse"] else 0)
    kept = h["history"][h["best_epoch"] - 1]["val_mse"] if h["best_epoch"] else h["initial_val_mse"]
    assert mse(c.decode(c.encode(tiny[200:])), tiny[200:]) == pytest.approx(kept, rel=1e-4)


def test_training_is_deterministic_by_seed(tiny):
    a, b = _ae(seed=3).fit(tiny), _ae(seed=3).fit(tiny)
    c = _ae(seed=4).fit(tiny)
    sa, sb, sc = a.state_dict(), b.state_dict(), c.state_dict()
    assert all(np.array_equal(sa[k], sb[k]) for k in sa)
    assert not np.array_equal(sa["enc1.weight"], sc["enc1.weight"])


@pytest.mark.parametrize("optimizer", ["adam", "gd"])
def test_resume_equals_uninterrupted(tiny, tmp_path, optimizer):
    from sdfcodec_ae import train_autoencoder
    from sdfcodec.plugin import load_state_file

    cfg = _ae(optimizer=optimizer, lr=1e-2 if optimizer == "adam" else 2.0).train_config(
        checkpoint=str(tmp_path / "run"), max_epochs=4)
    whole = train_autoencoder(tiny, code_size=4, hidden=8, config=_ae().train_config(
        **{**cfg.__dict__, "checkpoint": None}))

    class Stop(Exception):
        pass

    def interrupt(rec):
        if rec["epoch"] == 2:
            raise Stop

    with pytest.raises(Stop):
        train_autoencoder(tiny, code_size=4, hidden=8, config=cfg, on_epoch=interrupt)
    meta = json.loads((tmp_path / "run.json").read_text())
    assert meta["epoch"] == 2 and meta["format"] == "sdfcodec-ae-checkpoint"
    arrays = load_state_file(tmp_path / "run.npz")  # plain arrays, read without pickle
    assert any(k.startswith("opt.") for k in arrays) and all(v.dtype != object for v in arrays.values())
    resumed = train_autoencoder(tiny, code_size=4, hidden=8, config=cfg, resume=True)
    assert [r["epoch"] for r in resumed.history] == [1, 2, 3, 4]
    assert [r["val_mse"] for r in resumed.history] == [r["val_mse"] for r in whole.history]
    assert all(np.array_equal(whole.state[k], resumed.state[k]) for k in whole.state)
    # resuming on other data is refused
    with pytest.raises(InvalidValueError, match="data"):
        train_autoencoder(tiny[:100], code_size=4, hidden=8, config=cfg, resume=True)


def test_resume_with_other_stopping_settings(tiny, tmp_path):
    """Early-stopping state is replayed from the history: resuming with a stricter max_epochs continues, and a
    criterion that would have stopped earlier says so and returns the best weights."""
    from sdfcodec_ae import train_autoencoder
    from sdfcodec.errors import SDFCodecWarning

    cfg = _ae().train_config(checkpoint=str(tmp_path / "run"), max_epochs=2)
    first = train_autoencoder(tiny, code_size=4, hidden=8, config=cfg)
    more = train_autoencoder(tiny, code_size=4, hidden=8, config=_ae().train_config(
        checkpoint=str(tmp_path / "run"), max_epochs=3), resume=True)
    assert len(first.history) == 2 and len(more.history) == 3
    with pytest.warns(SDFCodecWarning, match="past epoch 1"):
        late = train_autoencoder(tiny, code_size=4, hidden=8, config=_ae().train_config(
            checkpoint=str(tmp_path / "run"), max_epochs=3, min_improvement=0.99, patience=1), resume=True)
    assert late.stopped == "early stopping" and len(late.history) == 3


def test_checkpoint_mismatch_is_refused(tiny, tmp_path):
    from sdfcodec_ae import train_autoencoder

    cfg = _ae().train_config(checkpoint=str(tmp_path / "run"), max_epochs=1)
    train_autoencoder(tiny, code_size=4, hidden=8, config=cfg)
    (tmp_path / "run.json").write_text((tmp_path / "run.json").read_text().replace('"epoch": 1', '"epoch": 7'))
    with pytest.raises(FormatError, match="epoch"):
        train_autoencoder(tiny, code_size=4, hidden=8, config=cfg, resume=True)


def test_paper_gd_setting_learns(tiny):
    """Batch gradient descent: one full-batch step per epoch; it lowers the validation error (slowly)."""
    c = _ae(optimizer="gd", lr=2.0, batch_size=None, max_epochs=5).fit_validated(tiny[:200], tiny[200:])
    h = c.history_
    assert h["config"]["optimizer"] == "gd" and h["config"]["batch_size"] is None
    assert h["best_val_mse"] < h["initial_val_mse"]


def test_learning_curves_written(small_ae, tmp_path):
    files = small_ae.write_training_report(tmp_path / "ae8")
    data = json.loads((tmp_path / "ae8.curves.json").read_text())
    assert len(data["history"]) == 30 and "best_epoch" in data
    pytest.importorskip("matplotlib")
    assert (tmp_path / "ae8.curves.png").stat().st_size > 1000 and len(files) == 2


# -- state, models, errors --------------------------------------------------------------------------------------
def test_state_round_trip_without_pickles(small_seq, small_ae, tmp_path, blocks):
    from sdfcodec_ae import save_model_float16

    for codec in (small_ae, small_seq):
        path = sdfcodec.save_model(codec, tmp_path / f"{codec.codec_id}.npz")
        with np.load(path, allow_pickle=False) as z:
            assert all(z[k].dtype.kind in "fiub" for k in z.files)
        back = sdfcodec.load_model(path)
        assert np.array_equal(back.encode(blocks[:20]), codec.encode(blocks[:20]))
        half = sdfcodec.load_model(save_model_float16(codec, tmp_path / f"{codec.codec_id}-f16.npz",
                                                      keep_float32=("pca.",)))
        assert half.state_dict()["ae.enc1.weight" if codec.codec_id == "sequential" else "enc1.weight"].dtype \
            == np.float32
        assert mse(half.decode(half.encode(blocks)), blocks) == pytest.approx(
            mse(codec.decode(codec.encode(blocks)), blocks), rel=0.02)
    assert set(small_seq.state_dict()) == {"pca.components", "pca.mean", "pca.explained_variance"} | {
        f"ae.{n}.{p}" for n in ("enc1", "enc2", "dec1", "dec2") for p in ("weight", "bias")}


def test_bad_parameters_and_state(small_ae, blocks):
    with pytest.raises(InvalidValueError, match="output"):
        sdfcodec.get_codec("ae", output="relu").fit(blocks[:10])
    with pytest.raises(InvalidValueError, match="unknown ae training"):
        sdfcodec.get_codec("ae", code_size=4, hidden=8, training={"epochs": 3}).fit(blocks[:10])
    with pytest.raises(InvalidValueError, match="optimizer"):
        sdfcodec.get_codec("ae", code_size=4, hidden=8, training={"optimizer": "sgd"}).fit(blocks[:10])
    with pytest.raises(InvalidValueError, match="weight"):
        sdfcodec.get_codec("parallel", weight=1.5).code_size
    with pytest.raises(InvalidValueError, match="pca must be"):
        sdfcodec.get_codec("sequential", pca="pretrained").fit(blocks[:10])
    with pytest.raises(ShapeError, match="another code_size"):
        sdfcodec.get_codec("ae", code_size=16, hidden=16).load_state_dict(small_ae.state_dict())
    with pytest.raises(InvalidValueError, match="lacks"):
        sdfcodec.get_codec("ae", code_size=8, hidden=16).load_state_dict({})
    with pytest.raises(InvalidValueError, match="neither"):
        sdfcodec.get_codec("parallel").load_state_dict({"weights": np.zeros(3)})
    with pytest.raises(NotFittedError):
        sdfcodec.get_codec("parallel").encode(blocks[:2])
    with pytest.raises(InvalidValueError, match="output='tanh'"):
        type(sdfcodec.get_codec("sequential")).from_parts(sdfcodec.get_codec("pca", code_size=8).fit(blocks),
                                                          small_ae)


@pytest.mark.parametrize("which", ["ae", "sequential"])
def test_map_round_trip(which, small_ae, small_seq, tmp_path):
    """A map stores the whole codec (PCA arrays included) and decodes with no other file."""
    from sdfcodec.core.sdf import Box, Plane, Scene, Sphere, sample_volume

    codec = small_ae if which == "ae" else small_seq
    scene = Scene([Plane((0, 0, -1), -0.1), Box((0.3, 0.3, 0.2), (0.1, 0.15, 0.1)), Sphere((0.45, 0.2, 0.3), 0.08)])
    vol = sample_volume(scene, (32, 32, 32), 0.02, truncation=(-0.04, 0.1))
    with sdfcodec.create_map(tmp_path / "m.sdfz", codec=codec, voxel_size=0.02) as m:
        m.write_volume(vol)
    back = sdfcodec.open_map(tmp_path / "m.sdfz")
    assert back.code_size == codec.code_size
    dec = back.decode_region()
    v = (vol - -0.04) / 0.14
    blocks = v.reshape(2, 16, 2, 16, 2, 16).transpose(0, 2, 4, 1, 3, 5).reshape(-1, 16, 16, 16)
    ref = codec.decode(codec.encode(blocks.astype(np.float32)))
    ref_vol = ref.reshape(2, 2, 2, 16, 16, 16).transpose(0, 3, 1, 4, 2, 5).reshape(32, 32, 32) * 0.14 - 0.04
    coded = ~(v >= 1 - 1e-6).reshape(2, 16, 2, 16, 2, 16).all(axis=(1, 3, 5))
    mask = np.repeat(np.repeat(np.repeat(coded, 16, 0), 16, 1), 16, 2)
    assert np.allclose(dec[mask], np.clip(ref_vol, -0.04, 0.1)[mask], atol=1e-4)  # reads are truncated


def test_mixture_with_fitted_pca(tiny):
    seq = sdfcodec.get_codec("sequential", pca_size=6, ae_size=4, hidden=8, pca="fit",
                             training={**FAST, "max_epochs": 2}).fit(tiny)
    ref = sdfcodec.get_codec("pca", code_size=6).fit(tiny)
    assert np.allclose(seq.pca_.components_, ref.components_, atol=1e-5)


def sdfcodec_mixed():
    import sdfcodec_mixed as m

    return m


# -- shipped weights, benchmark -----------------------------------------------------------------------------------
SHIPPED = {"sdfcodec_ae": "ae-64.npz", "sdfcodec_mixed": "sequential-64-64.npz"}


def test_shipped_models():
    """Each plugin ships its weights in its own package, served by its codec's ``pretrained`` through the
    registry; the old names keep working, deprecated."""
    from sdfcodec.plugin import shipped_model_file

    files = [ROOT / "plugins" / pkg / "models" / name for pkg, name in SHIPPED.items()]
    if not all(f.exists() for f in files):
        pytest.skip("shipped AE models not built yet (python examples/train_ae_models.py)")
    assert not list((ROOT / "sdfcodec" / "models").glob("*.npz"))  # none left in the core package
    assert sum(f.stat().st_size for f in files) < 30e6
    with np.load(shipped_model_file("sdfcodec_ae", "ae-64.npz"), allow_pickle=False) as z:
        assert z["enc1.weight"].dtype == np.float16
    x = synthetic_blocks(300, seed=123)
    ae, par, seq = (sdfcodec.pretrained_codec(c) for c in ("ae", "parallel", "sequential"))
    pca = sdfcodec.pretrained_codec("pca", 64)
    e = {n: mse(c.decode(c.encode(x)), x) for n, c in (("pca", pca), ("ae", ae), ("par", par), ("seq", seq))}
    assert e["ae"] < 0.02 and e["par"] <= min(e["pca"], e["ae"]) + 1e-6 and e["seq"] <= e["pca"] + 1e-6
    with pytest.raises(InvalidValueError, match="only ae-64"):
        sdfcodec.pretrained_codec("ae", 32)
    assert sdfcodec.pretrained_codec("sequential", weight=0.5).code_size == 128

    # the former names: same codecs, with a DeprecationWarning where the name itself is deprecated
    from sdfcodec_ae import AECodec, default_ae, shipped_model_path

    m = sdfcodec_mixed()
    assert default_ae(64) == ae and m.default_parallel() == par and m.default_sequential() == seq
    with pytest.warns(DeprecationWarning, match="shipped_model_file"):
        assert shipped_model_path("ae-64.npz") == shipped_model_file("sdfcodec_ae", "ae-64.npz")
    with pytest.warns(DeprecationWarning, match="pretrained"):
        assert AECodec.shipped(64) == ae
    with pytest.raises(errors.ModelNotFoundError, match="no shipped model"):
        shipped_model_file("sdfcodec_ae", "ae-7.npz")


def test_plugins_import_only_the_public_toolkit():
    """Plugins import only sdfcodec, sdfcodec.errors, sdfcodec.testing and sdfcodec.plugin (and their own
    modules); the mixtures reach the autoencoder through the registry, never by importing sdfcodec_ae."""
    import ast

    allowed = {"sdfcodec", "sdfcodec.errors", "sdfcodec.testing", "sdfcodec.plugin"}
    roots = [*(ROOT / "plugins").iterdir(), ROOT / "examples" / "sdfcodec-dct" / "sdfcodec_dct"]
    for path, pkg in [(f, r.name) for r in roots if r.is_dir() for f in r.rglob("*.py")]:
        for node in ast.walk(ast.parse(path.read_text())):
            names = ([a.name for a in node.names] if isinstance(node, ast.Import) else
                     [node.module] if isinstance(node, ast.ImportFrom) and node.level == 0 and node.module else [])
            for name in names:
                if name.startswith("sdfcodec"):
                    assert name in allowed or name.split(".")[0] == pkg, f"{path}: imports {name}"
    from sdfcodec.plugin import TrainableCodec
    from sdfcodec.registry import get_codec_class

    assert all(issubclass(get_codec_class(c), TrainableCodec) for c in ("ae", "parallel", "sequential"))


def test_bench_records_quick():
    from sdfcodec_ae import bench_records

    recs = bench_records("ae", 16, [8], min_time=0.01)
    assert [r["operation"] for r in recs] == ["encode", "decode"]
    assert recs[0]["roofline_shapes"] == [[4096, 512], [512, 16]]
    assert all(r["blocks_per_s"] > 0 and r["baseline_blocks_per_s"] > 0 for r in recs)
    seq = bench_records("sequential", 16, [4], min_time=0.01)
    assert seq[0]["roofline_shapes"][0] == [4096, 16] and seq[0]["code_size"] == 33
    # a fixed w: no w slot; sequential still decodes its PCA part at encode time (the residual), parallel not
    from sdfcodec.bench import bench_instance, roofline_shapes

    for cid, enc in (("sequential", [(4096, 8), (8, 4096), (4096, 512), (512, 8)]),
                     ("parallel", [(4096, 8), (4096, 512), (512, 8)])):
        mix, _ = bench_instance(cid, 8, weight=0.5)
        assert mix.code_size == 16 and roofline_shapes(mix, "encode") == enc
        assert roofline_shapes(mix, "decode") == [(8, 4096), (8, 512), (512, 4096)]
    ae, _ = bench_instance("ae", 8, weight=0.5)  # an option the ae's instance does not take is not passed
    assert ae.code_size == 8
    pca = bench_records("pca", 8, [2], min_time=0.005)  # any codec: no codec id is special-cased
    assert pca[0]["code_size"] == 8 and "roofline_shapes" not in pca[0]


def _bench_cli(*args: str):
    from typer.testing import CliRunner

    from sdfcodec.cli import app

    res = CliRunner().invoke(app, ["bench", "--quick", "--read", "0", "--no-search", "--repeats", "2", *args])
    assert res.exit_code == 0, res.output
    return res


def _check_timing_fields(recs):
    for r in recs:
        assert r["blocks_per_s"] > 0 and r["baseline_blocks_per_s"] > 0
        assert r["us_per_block"] == pytest.approx(1e6 / r["blocks_per_s"], rel=1e-9)
        assert r["ratio_to_baseline"] == pytest.approx(r["blocks_per_s"] / r["baseline_blocks_per_s"], rel=1e-9)


def test_cli_bench_ae_and_mixtures_quick(monkeypatch):
    """`sdfcodec bench --codec ae|parallel|sequential`: blocks/s beside the roofline of the paper network's layer
    shapes (4096-512-d-512-4096), with no training (shipped weights at 64, untrained ones elsewhere)."""
    from sdfcodec_ae import AECodec

    def no_training(*a, **k):
        raise AssertionError("bench must not train")

    monkeypatch.setattr(AECodec, "fit_validated", no_training)
    recs = json.loads(_bench_cli("--codec", "ae", "--sizes", "16,64", "--batches", "3", "--json").stdout)
    assert [(r["code_size"], r["operation"], r["batch"]) for r in recs] == [
        (16, "encode", 3), (16, "decode", 3), (64, "encode", 3), (64, "decode", 3)]
    assert recs[0]["roofline_shapes"] == [[4096, 512], [512, 16]]
    assert recs[1]["roofline_shapes"] == [[16, 512], [512, 4096]]
    assert recs[2]["roofline_shapes"] == [[4096, 512], [512, 64]]
    assert "untrained" in recs[0]["weights"] and "ae-64.npz" in recs[2]["weights"]
    _check_timing_fields(recs)

    pca_enc, pca_dec = [[4096, 8], [8, 4096]]
    ae_enc, ae_dec = [[4096, 512], [512, 8]], [[8, 512], [512, 4096]]
    par = json.loads(_bench_cli("--codec", "parallel", "--sizes", "8", "--batches", "2", "--json").stdout)
    assert [r["code_size"] for r in par] == [17, 17]  # 8 + 8 + the per-block w
    assert par[0]["roofline_shapes"] == [pca_enc] + ae_enc + [pca_dec] + ae_dec
    assert par[1]["roofline_shapes"] == [pca_dec] + ae_dec
    _check_timing_fields(par)
    # the table: the layer shapes and where the weights come from are printed under it
    out = " ".join(_bench_cli("--codec", "sequential", "--sizes", "8", "--batches", "2").stdout.split())  # unwrap
    assert "layer shapes" in out and "code 17 encode: (B,4096)x(4096,8) + (B,8)x(8,4096) + (B,4096)x(4096,512)" in out
    assert "untrained" in out


class _TwoStage(sdfcodec.Codec):
    codec_id = "test-bench-two-stage"
    code_size = 3

    def _encode(self, blocks):
        return blocks.reshape(len(blocks), -1)[:, :3].clone()

    def _decode(self, codes):
        return codes.mean(dim=1)[:, None, None, None].expand(len(codes), 16, 16, 16).clone()


def test_bench_registration_is_generic_and_linear_default_unchanged():
    """The benchmark uses what a plugin registers whatever its id; a codec without a registration (pca) keeps
    the single (4096, k) product as its baseline and the plain record keys (no registration fields)."""
    from sdfcodec.bench import bench_codec, roofline_shapes
    from sdfcodec.plugin import register_bench

    sdfcodec.register_codec(_TwoStage, replace=True)
    register_bench(_TwoStage, instance=lambda code_size: (_TwoStage(), f"nothing to learn ({code_size})"),
                   roofline_shapes=lambda c, op: [(4096, 7), (7, 3)] if op == "encode" else [(3, 4096)])
    recs = bench_codec("test-bench-two-stage", [5], [2], min_time=0.005)
    assert [r["roofline_shapes"] for r in recs] == [[[4096, 7], [7, 3]], [[3, 4096]]]
    assert recs[0]["weights"] == "nothing to learn (5)" and recs[0]["code_size"] == 3
    _check_timing_fields(recs)
    with pytest.raises(errors.RegistrationError):
        register_bench("test-bench-two-stage")
    with pytest.raises(errors.CodecTypeError):
        register_bench(3, instance=lambda k: None)

    pca = bench_codec("pca", [32], [2], min_time=0.005)
    # timed_threads: 1 when its calls were short enough to be timed on one thread (sdfcodec.bench.harness)
    assert set(pca[0]) - {"timed_threads"} == {"codec", "code_size", "operation", "batch", "device", "blocks_per_s", "baseline",
                           "baseline_blocks_per_s", "ratio_to_baseline", "us_per_block", "paper_us_per_block",
                           "speedup_vs_paper",  # and the interleaved timing's bests, rounds and load (issue 19)
                           "blocks_per_s_best", "baseline_blocks_per_s_best", "ratio_of_bests", "ratio_paired",
                           "ratio_cpu", "repeats", "load_before", "load_after"}
    assert pca[0]["baseline"] == "numpy matmul"
    # pca overrides encode_weighted: its weighted fit, and a map writer's (refitted for the truncation)
    weighted = [r for r in pca if r["operation"] in ("encode-weighted", "encode-masked")]
    assert len(weighted) == 2 and all(r["roofline_shapes"] == [[4096, 32], [4096, 528], [4096, 32]] for r in weighted)
    assert [r["operation"] for r in recs] == ["encode", "decode"]  # no weighted encode: no weighted record
    assert roofline_shapes(sdfcodec.get_codec("raw"), "encode") == [(4096, 4096)]
    _check_timing_fields(pca)


def test_spec1_bench_hooks_on_the_class_still_work_deprecated():
    """Spec 1 let a codec declare ``bench_instance``/``roofline_shapes`` methods; they keep working, warned."""
    from sdfcodec.bench import bench_codec

    class Legacy(sdfcodec.Codec):
        codec_id = "test-bench-legacy"
        code_size = 3
        _encode, _decode = _TwoStage._encode, _TwoStage._decode

        @classmethod
        def bench_instance(cls, code_size):
            return cls(), "legacy"

        def roofline_shapes(self, operation):
            return [(4096, 5)] if operation == "encode" else [(5, 4096)]

    sdfcodec.register_codec(Legacy, replace=True)
    with pytest.warns(DeprecationWarning, match="register_bench"):
        recs = bench_codec("test-bench-legacy", [3], [2], min_time=0.005)
    assert [r["roofline_shapes"] for r in recs] == [[[4096, 5]], [[5, 4096]]] and recs[0]["weights"] == "legacy"


@pytest.mark.slow
def test_cli_trains_ae(tmp_path):
    """`sdfcodec train DATASET --codec ae` (default hyper-parameters: paper-sized network, Adam)."""
    from typer.testing import CliRunner

    from sdfcodec.cli import app
    from sdfcodec.core.dataset import build_dataset

    ds = tmp_path / "ds.zarr"
    build_dataset(ds, [("synthetic", [synthetic_blocks(3000, seed=1)])])
    res = CliRunner().invoke(app, ["train", str(ds), "--codec", "ae", "--code-size", "32", "-o",
                                   str(tmp_path / "ae.npz"), "--json"])
    assert res.exit_code == 0, res.output
    assert sdfcodec.load_model(tmp_path / "ae.npz").code_size == 32
