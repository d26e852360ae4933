"""The query cache (sdfcodec.search.cache): a cached model or threshold is exactly what building it gives, it is
used across processes (a fresh memory, the same directory), keyed by everything the model depends on, and a
damaged or foreign cache file is never trusted."""

from __future__ import annotations

import json

import numpy as np
import pytest

import sdfcodec
from sdfcodec import pretrained_codec
from sdfcodec.search import cache
from sdfcodec.search import calibrate, engine, models, query, scoring
from sdfcodec.search.query import build_query

#: Shipped against fresh calibration figures: the pca plugin's weighted encode has two exact solvers (the compiled
#: one with the extra 'fast', the batched torch one without it or on a GPU) that agree to the float32 rounding of
#: their active-set refits; a quantile of their residuals measured 1.7e-4 apart, so a table computed by either
#: must match the other.
RTOL = 1e-3

VS, TRUNC = 0.02, (-0.04, 0.1)


@pytest.fixture
def fresh_cache(tmp_path, monkeypatch):
    monkeypatch.setenv(cache.CACHE_ENV, str(tmp_path / "cache"))
    cache.clear_memory_cache()
    yield tmp_path / "cache" / "queries"
    cache.clear_memory_cache()


@pytest.fixture
def count_builds(monkeypatch):
    """How often shapes were sampled (each model build samples once)."""
    calls = []
    real = models.query_blocks
    monkeypatch.setattr(models, "query_blocks", lambda *a, **k: calls.append(1) or real(*a, **k))
    return calls


def _uncached(**kw):
    """The model built with the disk and memory caches off."""
    import os

    old = os.environ.get(cache.CACHE_ENV)
    os.environ[cache.CACHE_ENV] = "off"
    cache.clear_memory_cache()
    try:
        return build_query("floor", **kw)
    finally:
        cache.clear_memory_cache()
        if old is None:
            del os.environ[cache.CACHE_ENV]
        else:
            os.environ[cache.CACHE_ENV] = old


def test_cached_model_equals_a_fresh_build_and_is_reused_across_processes(fresh_cache, count_builds):
    codec = pretrained_codec("pca", 32)
    kw = dict(codec=codec, voxel_size=VS, truncation=TRUNC, up=(0.0, 0.0, 1.0), behind="solid")
    ref = _uncached(**kw)
    n0 = len(count_builds)
    first = build_query("floor", **kw)
    assert len(count_builds) == n0 + 1 and len(list(fresh_cache.glob("*.npz"))) == 1
    again = build_query("floor", **kw)  # from memory
    cache.clear_memory_cache()  # a new process: memory empty, the directory kept
    disk = build_query("floor", **kw)
    assert len(count_builds) == n0 + 1  # neither rebuilt the shapes
    for m in (first, again, disk):
        np.testing.assert_array_equal(m.descriptors, ref.descriptors)
        np.testing.assert_array_equal(m.blocks, ref.blocks)
        assert m.spec == ref.spec and m.codec_state_sha256 == ref.codec_state_sha256
    again.descriptors[:] = 0  # a caller writing into its copy changes nothing cached
    np.testing.assert_array_equal(build_query("floor", **kw).descriptors, ref.descriptors)


@pytest.mark.parametrize("change", [dict(voxel_size=0.03), dict(truncation=(-0.05, 0.1)), dict(up=(0.0, 0.6, 0.8)),
                                    dict(behind="unobserved"), dict(rotations="cone:5:16"), dict(code_size=64),
                                    dict(keep_blocks=False)])
def test_key_names_everything_the_model_depends_on(fresh_cache, change):
    kw = dict(codec=pretrained_codec("pca", 32), voxel_size=VS, truncation=TRUNC, up=(0.0, 0.0, 1.0), behind="solid")
    build_query("floor", **kw)
    if "code_size" in change:
        kw["codec"] = pretrained_codec("pca", change.pop("code_size"))
    kw.update(change)
    got = build_query("floor", **kw)
    ref = _uncached(**kw)
    np.testing.assert_array_equal(got.descriptors, ref.descriptors)
    assert got.spec == ref.spec and (got.blocks is None) == (ref.blocks is None)


def test_damaged_or_foreign_cache_files_are_rebuilt(fresh_cache, count_builds):
    codec = pretrained_codec("pca", 32)
    kw = dict(codec=codec, voxel_size=VS, truncation=TRUNC, up=(0.0, 0.0, 1.0), behind="solid")
    ref = build_query("floor", **kw)
    (path,) = fresh_cache.glob("*.npz")
    other = build_query("wall", **kw)  # a valid query file, but another model than the key names
    for content in (b"not an npz", None):
        if content is None:
            models.save_query(other, path)
        else:
            path.write_bytes(content)
        cache.clear_memory_cache()
        n = len(count_builds)
        got = build_query("floor", **kw)
        assert len(count_builds) == n + 1  # rebuilt, not trusted
        np.testing.assert_array_equal(got.descriptors, ref.descriptors)
        np.testing.assert_array_equal(models.load_query(path).descriptors, ref.descriptors)  # and replaced


def test_disk_cache_off_and_unwritable(tmp_path, monkeypatch, count_builds):
    codec = pretrained_codec("pca", 32)
    kw = dict(codec=codec, voxel_size=VS, truncation=TRUNC, up=(0.0, 0.0, 1.0), behind="solid")
    monkeypatch.setenv(cache.CACHE_ENV, "off")
    cache.clear_memory_cache()
    build_query("floor", **kw)
    assert cache.cache_dir() is None
    blocker = tmp_path / "file"
    blocker.write_text("a file where the cache directory would go")
    monkeypatch.setenv(cache.CACHE_ENV, str(blocker))
    cache.clear_memory_cache()
    n = len(count_builds)
    m = build_query("floor", **kw)  # cannot write: works, from memory afterwards
    build_query("floor", **kw)
    assert len(count_builds) == n + 1 and len(m) > 1
    cache.clear_memory_cache()


def test_calibrated_threshold_is_cached_and_equal(fresh_cache, tmp_path, monkeypatch):
    import torch

    from sdfcodec.core.sdf import Plane, Scene, sample_volume
    from sdfcodec.search import shapes

    codec = pretrained_codec("pca", 64)
    vol = sample_volume(Scene([Plane((0, 0, 1), 0.31)]), (32, 32, 32), VS)
    with sdfcodec.create_map(tmp_path / "p.sdfz", codec=codec, voxel_size=VS, truncation=TRUNC, up=(0, 0, 1)) as w:
        w.write_volume(vol)
    model = build_query("floor", map=sdfcodec.open_map(tmp_path / "p.sdfz"))
    calls = []
    real = shapes.sample_shapes
    monkeypatch.setattr(calibrate, "sample_shapes", lambda *a, **k: calls.append(1) or real(*a, **k))
    cpu = torch.device("cpu")
    t1, info1 = calibrate.calibrate_threshold(model, codec, 64, scoring.Scorer(model.descriptors, cpu))
    cache.clear_memory_cache()
    t2, info2 = calibrate.calibrate_threshold(model, codec, 64, scoring.Scorer(model.descriptors, cpu))  # the disk
    t3, _ = calibrate.calibrate_threshold(model, codec, 32, scoring.Scorer(model.descriptors[:, :32], cpu))
    assert calls == [1, 1]  # level 64 once, level 32 once
    assert t1 == t2 and info1 == info2 and info1["method"] == "calibrated" and t3 != t1
    cache.clear_memory_cache()
    monkeypatch.setenv(cache.CACHE_ENV, "off")
    t4, info4 = calibrate.calibrate_threshold(model, codec, 64, scoring.Scorer(model.descriptors, cpu))
    assert (t4, info4) == (t1, info1) and calls == [1, 1, 1]  # what the cache held is what calibrating gives


def test_plane_check_calibration_is_cached_and_equal(fresh_cache, tmp_path, monkeypatch):
    """The plane check's simulated clean blocks (a weighted encode per checked plane) are calibrated once per key:
    a repeated search reads them from the cache (memory, then disk) and selects what an uncached one selects."""
    from sdfcodec.map import state_digest
    from sdfcodec.core.sdf import Plane, Scene, sample_volume
    from sdfcodec.search import plane_check
    from sdfcodec.search.engine import search

    codec = pretrained_codec("pca", 64)
    vol = sample_volume(Scene([Plane((0, 0, 1), 0.31)]), (48, 48, 32), VS)
    path = tmp_path / "p.sdfz"
    with sdfcodec.create_map(path, codec=codec, voxel_size=VS, truncation=TRUNC, up=(0, 0, 1)) as w:
        w.write_volume(vol)
    calls = []
    real = plane_check.verify_threshold
    monkeypatch.setattr(plane_check, "verify_threshold", lambda *a, **k: calls.append(1) or real(*a, **k))
    first = search(path, "floor")
    n = len(calls)
    assert n >= 1 and len(first.coords)  # the plane was checked
    cache.clear_memory_cache()
    again = search(path, "floor")  # from the disk
    assert len(calls) == n and np.array_equal(again.coords, first.coords)
    monkeypatch.setenv(cache.CACHE_ENV, "off")
    cache.clear_memory_cache()
    fresh = search(path, "floor")
    assert len(calls) == 2 * n and np.array_equal(fresh.coords, first.coords)

    # the cached figures are verify_threshold's own, and the key names the plane's normal
    kw = dict(voxel_size=VS, truncation=TRUNC, behind="solid", weighted=False, stretches=np.array([1.0]), tol=1.0,
              samples=64, seed=0)
    sha = state_digest(codec.state_dict())
    monkeypatch.setenv(cache.CACHE_ENV, str(fresh_cache.parent))
    up, tilted = np.array([0.0, 0.0, 1.0]), np.array([0.0, 0.6, 0.8])
    t, med = plane_check.clean_residuals(up, codec, sha, quantile=0.9, **kw)
    sim, _ = real(up, codec, quantile=0.9, **kw)
    assert (t, med) == (float(np.quantile(sim, 0.9)), float(np.median(sim)))
    before = len(calls)
    assert plane_check.clean_residuals(up, codec, sha, quantile=0.9, **kw) == (t, med) and len(calls) == before
    assert plane_check.clean_residuals(tilted, codec, sha, quantile=0.9, **kw) != (t, med)
    assert len(calls) == before + 1
    # a cache file with a valid threshold but no median (foreign, or damaged) is recomputed and replaced
    for f in fresh_cache.glob("*.json"):
        doc = json.loads(f.read_text())
        if "median" in doc["info"]:
            f.write_text(json.dumps({"threshold": doc["threshold"], "info": {}}))
    cache.clear_memory_cache()
    assert plane_check.clean_residuals(up, codec, sha, quantile=0.9, **kw) == (t, med)
    assert len(calls) == before + 2
    cache.clear_memory_cache()
    assert plane_check.clean_residuals(up, codec, sha, quantile=0.9, **kw) == (t, med)
    assert len(calls) == before + 2  # the replaced file serves again


def test_shipped_calibrations_equal_a_fresh_calibration(fresh_cache, monkeypatch):
    """The plane-check calibrations shipped for the shipped pca sizes (examples/ship_calibrations.py) are found
    under the keys a search computes for a fused map at the default voxel size and truncation, so a first search
    calibrates none of them; every entry is keyed for the eigenshapes shipped today (a retrained model needs
    `make calibrations`), and one recomputed from its recorded arguments gives the shipped figures."""
    from sdfcodec.map import state_digest
    from sdfcodec.search import plane_check
    from sdfcodec.search.calibrate import CALIBRATION_QUANTILE, CALIBRATION_SAMPLES
    from sdfcodec.search.query import FUSED_STRETCH

    doc = json.loads(cache.SHIPPED_FILE.read_text())
    assert doc["build"] == cache.BUILD_VERSION and len(doc["entries"]) == len(cache.shipped_thresholds()) >= 12
    codecs = {}
    for key, e in doc["entries"].items():
        size = e["codec"]["code_size"]
        codec = codecs.setdefault(size, pretrained_codec("pca", size))
        a = dict(e["args"])
        quantile = a.pop("quantile")
        a["stretches"] = np.asarray(a["stretches"])
        assert plane_check.plane_check_key(None, codec, state_digest(codec.state_dict()), quantile=quantile,
                                           **a)[0] == key
    calls = []
    real = plane_check.verify_threshold
    monkeypatch.setattr(plane_check, "verify_threshold", lambda *a, **k: calls.append(1) or real(*a, **k))
    codec = codecs[64]
    sha = state_digest(codec.state_dict())
    kw = dict(voxel_size=VS, truncation=TRUNC, behind="unobserved", weighted=True, stretches=np.asarray(FUSED_STRETCH),
              samples=CALIBRATION_SAMPLES)
    got = plane_check.clean_residuals(np.array([0.1, -0.9, -0.4]), codec, sha, quantile=CALIBRATION_QUANTILE,
                                      tol=1.8, seed=2, **kw)
    assert calls == []  # shipped: no weighted encode
    key, args = plane_check.plane_check_key(None, codec, sha, quantile=CALIBRATION_QUANTILE, tol=1.8, **kw)
    assert args["tol"] == 2.0 and got == (doc["entries"][key]["threshold"], doc["entries"][key]["info"]["median"])
    sim, _ = real(None, codec, quantile=CALIBRATION_QUANTILE, **args)
    # RTOL: the table may have been computed by the other of the pca plugin's two exact solvers
    assert np.allclose(got, (np.quantile(sim, CALIBRATION_QUANTILE), np.median(sim)), rtol=RTOL, atol=0)
    # a table that does not load ships nothing: the calibration is computed, with the same figures
    monkeypatch.setattr(cache, "SHIPPED_FILE", cache.SHIPPED_FILE.with_name("no-such-file.json"))
    monkeypatch.setattr(cache, "_shipped", None)
    cache.clear_memory_cache()
    again = plane_check.clean_residuals(np.array([0.0, 0.0, 1.0]), codec, sha, quantile=CALIBRATION_QUANTILE, tol=2.0,
                                        **kw)
    assert calls == [1] and np.allclose(again, got, rtol=RTOL, atol=0)


def test_ship_calibrations_script_rewrites_the_shipped_entries(fresh_cache):
    """examples/ship_calibrations.py (`make calibrations`) computes, for pca-32, the very entries shipped: same keys,
    thresholds and medians to float tolerance."""
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "examples" / "ship_calibrations.py"
    spec = importlib.util.spec_from_file_location("ship_calibrations", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    got = module.entries(sizes=(32,))
    shipped = json.loads(cache.SHIPPED_FILE.read_text())["entries"]
    assert len(got) == 4 and set(got) <= set(shipped)
    for key, e in got.items():
        assert e["args"] == shipped[key]["args"] and e["codec"] == shipped[key]["codec"]
        assert np.isclose(e["threshold"], shipped[key]["threshold"], rtol=RTOL, atol=0)
        assert np.isclose(e["info"]["median"], shipped[key]["info"]["median"], rtol=RTOL, atol=0)
