"""Variable-rate codes (issue 42, items 2 and 4; spec/map-format.md section 4e): the entropy coder, the prefix codes
a map stores and reads back, rate control by bytes and by surface error, the golden map, the CLI defaults."""

from __future__ import annotations

import base64
import json
import shutil
import zlib
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

import sdfcodec
from _golden_maps import check_golden_map
from sdfcodec import errors
from sdfcodec.core.blocks import split_blocks
from sdfcodec.cli import app
from sdfcodec.map.varread import STREAM_ARRAY
from sdfcodec.registry import pretrained_codec
from sdfcodec.core.sdf import Box, Plane, Scene, Sphere, sample_volume
from sdfcodec.testing import analytic_blocks, analytic_scene
from sdfcodec.core.varrate import EntropyModel, decode_chunk, encode_chunk, fit_model

VS, TRUNC = 0.02, (-0.04, 0.1)
GOLDEN = Path(__file__).parent / "golden" / "maps" / "varrate-pca-8"


def _files_per_block(path: Path) -> float:
    """Every file of a map (a referenced model's empty codec/ too) per coded block: counted here, not by sdfcodec."""
    total = sum(f.stat().st_size for f in path.rglob("*") if f.is_file())
    return total / sdfcodec.open_map(path).count_states()["coded"]


# -- the entropy coder ----------------------------------------------------------------------------------------

def test_chunk_stream_round_trip_is_exact_and_near_the_entropy():
    rng = np.random.default_rng(3)
    n, d = 700, 16
    scales = 30 * 0.8 ** np.arange(d)
    q = np.rint(rng.laplace(0, scales, (n, d))).astype(np.int64)
    k = rng.integers(0, d + 1, n)
    q[np.arange(d)[None] >= k[:, None]] = 0
    model = EntropyModel.unpack(fit_model(q, k).pack(), d)  # what a reader builds from the header
    words = encode_chunk(q, k, model)
    assert np.array_equal(decode_chunk(words, n, model), q)
    assert np.array_equal(decode_chunk(words, n, model, level=5), q[:, :5])  # a prefix level stops early
    # the ideal code length under the model (an independent sum of -log2 p), plus a few words of rANS overhead
    ideal = sum(model.bits(q)[i, :k[i]].sum() for i in range(n)) + model.length_bits()[k].sum()
    assert ideal / 8 <= words.nbytes <= ideal / 8 * 1.01 + 16
    # the same numbers give the same model: the tables are built with IEEE-exact arithmetic from what is stored
    again = EntropyModel.unpack(model.pack(), d)
    assert all(np.array_equal(again.table(j), model.table(j)) for j in range(d))


def test_rate_distortion_rounding_beats_nearest_rounding_at_the_same_step():
    """Codes rounded by rate and distortion (``rdoq``, the default) against nearest rounding, at one step and
    Lagrange multiplier: every element is rint(z / step) or one step nearer the model's centre, the streams
    encoder writes are shorter, and the weighted squared error plus lam times the stream's bits (counted in
    bytes the coder wrote, not in the model's estimate) is smaller."""
    from sdfcodec.core.varrate import choose_lengths

    rng = np.random.default_rng(5)
    n, d = 1500, 24
    z = rng.laplace(0, 4 * 0.85 ** np.arange(d), (n, d))
    g = rng.uniform(0.2, 2.0, (n, d))
    step, lam = np.full(d, 1.0), 2 * np.log(2) / 6 * 1.1
    out = {}
    for rdoq in (False, True):
        q, k, model = choose_lengths(z, g, step, lam, rdoq=rdoq)
        words = encode_chunk(q, k, EntropyModel.unpack(model.pack(), d))
        dist = float((g * (z - q * step) ** 2).sum())
        out[rdoq] = (q, words.nbytes, dist + lam * 8 * words.nbytes)
    near = np.rint(z / step)
    q = out[True][0]
    coded = np.arange(d)[None] < np.where((q != 0).any(1), d - np.argmax((q != 0)[:, ::-1], 1), 0)[:, None]
    assert (np.abs(q - near)[coded] <= 1).all() and (np.abs(q)[coded] <= np.abs(near)[coded] + 1).all()
    assert (q != near)[coded].mean() > 0.02  # it does round some elements the other way
    assert out[True][1] < out[False][1] * 0.99  # 7,544 against 7,736 bytes
    assert out[True][2] < out[False][2]


def _spec_decay(b: np.ndarray) -> np.ndarray:
    """Spec section 4e, written out here: decay byte ``b`` stands for ``(65536 - u) / 65536``."""
    b = b.astype(np.int64)
    u = np.where(b < 16, b, (16 + b % 16) * 2.0 ** (b // 16 - 1))
    return (65536 - u) / 65536


def test_model_compact_layout_and_the_fixed_width_one_of_older_maps():
    # one column per mean distance m from a median of 0 (n - c zeros, c values a): ML decay (sqrt(1 + m^2) - 1) / m
    n, plan = 1000, [(1, 30), (1, 120), (2, 300), (5, 400), (20, 450), (60, 490)]
    q = np.zeros((n, len(plan)), np.int64)
    for j, (a, c) in enumerate(plan):
        q[:c, j] = a
    k = np.full(n, len(plan))
    model = fit_model(q, k)
    raw = zlib.decompress(base64.b64decode(model.pack()))
    d = len(plan)
    assert raw[:5] == b"\xff\xff\xff\x02" + bytes([d])  # magic, D as a one-byte varint
    assert np.array_equal(model.decay, _spec_decay(np.frombuffer(raw[5:5 + d], np.uint8)))
    m = np.array([a * c / n for a, c in plan])
    ml = (np.sqrt(1 + m * m) - 1) / m
    assert np.all(np.abs(np.log((1 - model.decay) / (1 - ml))) <= np.log(1.031)), (model.decay, ml)
    # the fixed-width layout maps written before still carry: the same model, built by hand from the spec
    old = b"".join([np.uint32(d).tobytes(), np.rint(model.decay * 65536).astype("<u2").tobytes(),
                    model.center.astype("<i4").tobytes(), model.extent.astype("<u4").tobytes(),
                    model.lengths.astype("<u4").tobytes()])
    old_text = base64.b64encode(zlib.compress(old, 9)).decode()
    again = EntropyModel.unpack(old_text, d)
    assert all(np.array_equal(again.table(j), model.table(j)) for j in range(d))
    assert np.array_equal(again.lengths, model.lengths)
    # the kitchen-like case: 128 elements, mostly zero centres, extents and lengths under 128
    rng = np.random.default_rng(5)
    q = np.rint(rng.laplace(0, 40 * 0.97 ** np.arange(128), (300, 128))).astype(np.int64)
    big = fit_model(q, rng.integers(100, 129, 300))
    fixed = b"".join([np.uint32(128).tobytes(), np.rint(big.decay * 65536).astype("<u2").tobytes(),
                      big.center.astype("<i4").tobytes(), big.extent.astype("<u4").tobytes(),
                      big.lengths.astype("<u4").tobytes()])
    assert len(big.pack()) < 0.8 * len(base64.b64encode(zlib.compress(fixed, 9)))
    with pytest.raises(errors.FormatError, match="does not unpack"):  # a trailing byte
        EntropyModel.unpack(base64.b64encode(zlib.compress(raw + b"\x00")).decode(), d)
    with pytest.raises(errors.FormatError, match="does not unpack"):  # a decay byte outside 1..207
        EntropyModel.unpack(base64.b64encode(zlib.compress(raw[:5] + b"\xd0" + raw[6:])).decode(), d)


def test_model_refuses_a_malformed_or_oversized_header_field():
    with pytest.raises(errors.FormatError, match="does not unpack"):
        EntropyModel.unpack("bm90IGEgbW9kZWw=", 8)
    with pytest.raises(errors.FormatError, match="above the limit"):
        EntropyModel([0], [0.5], [1 << 25], [1, 1])


# -- maps -------------------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def scene_volume() -> np.ndarray:
    return sample_volume(analytic_scene(), (90, 70, 45), VS, truncation=TRUNC)


@pytest.fixture(scope="module")
def pca32():
    return sdfcodec.get_codec("pca", code_size=32).fit(analytic_blocks(800, seed=11))


def _write(path: Path, codec, volume: np.ndarray, **kw) -> sdfcodec.Map:
    with sdfcodec.create_map(path, codec=codec, voxel_size=VS, truncation=TRUNC, overwrite=True, **kw) as m:
        m.write_volume(volume)
    return sdfcodec.open_map(path)


def test_stored_prefixes_are_the_dequantised_codes(tmp_path, scene_volume, pca32):
    step = 0.05
    vr = _write(tmp_path / "vr.sdfz", pca32, scene_volume, variable_rate={"step": step})
    ref = _write(tmp_path / "f.sdfz", pca32, scene_volume)  # float32 codes: the writer's same encode, unquantised
    (c1, z1), (c2, z2) = vr.read_codes(), ref.read_codes()
    assert np.array_equal(c1, c2) and z1.shape == z2.shape == (len(c1), 32)
    assert vr.header.codes.variable_rate.step == [step] and not (tmp_path / "vr.sdfz" / "codes" / "c").exists()
    q = z1 / step
    assert np.abs(q - np.rint(q)).max() < 1e-4  # every stored value a whole number of steps
    nz = z1 != 0
    length = np.where(nz.any(1), 32 - np.argmax(nz[:, ::-1], axis=1), 0)
    inside = np.arange(32)[None] < length[:, None]
    # inside its prefix every element is the float code's nearest step or, where rate-distortion rounding chose
    # it, the neighbouring step toward its law's centre; beyond it, zero
    off = np.rint(z1 / step) - np.rint(z2 / step)
    assert np.abs(off)[inside].max() <= 1 and (off[inside] == 0).any()
    assert (z1[~inside] == 0).all() and length.min() < 32 and length.mean() > 2
    # a level reads the first elements; decoding is the codec's decode of the zero-padded codes
    cl, zl = vr.read_codes(level=8)
    assert np.array_equal(zl, z1[:, :8])
    want = np.clip(pca32.decode(z1[:, :8]) * (TRUNC[1] - TRUNC[0]) + TRUNC[0], *TRUNC)
    got = dict(zip(map(tuple, c1), want))
    dec = vr.decode_region(level=8)
    for c in c1[:20]:
        sl = tuple(slice(16 * int(v), 16 * int(v) + 16) for v in c)
        part = dec[sl]
        np.testing.assert_allclose(part, got[tuple(c)][tuple(slice(0, s) for s in part.shape)], atol=1e-5)
    # the streaming decode (blocks regrouped by prefix length inside) yields each block with its own decode
    full = dict(zip(map(tuple, c1), np.clip(pca32.decode(z1) * (TRUNC[1] - TRUNC[0]) + TRUNC[0], *TRUNC)))
    seen = 0
    for cs, blocks in vr.iter_decoded():
        for c, b in zip(cs, np.asarray(blocks)):
            np.testing.assert_allclose(b, full[tuple(c)], atol=1e-5)
            seen += 1
    assert seen == len(c1)
    # search reads codes: on the variable-rate map it selects mostly what it selects on the float map
    from sdfcodec.search.engine import search
    a = search(vr, "floor", top=10)
    b = search(ref, "floor", top=10)
    ca, cb = {tuple(c) for c in np.asarray(a.coords)}, {tuple(c) for c in np.asarray(b.coords)}
    assert len(ca) == 10 and len(ca & cb) >= 6, (ca, cb)
    # what it read of codes: every code stream's chunk file (a row holds every prefix), as the disk holds them
    streams = sum(f.stat().st_size for f in (tmp_path / "vr.sdfz" / "code_streams" / "c").rglob("*") if f.is_file())
    assert a.stats["code_bytes_read"] == a.stats["code_bytes_full"] == a.stats["code_bytes_level"] == streams > 0


@pytest.mark.parametrize("merge", [0, 10 ** 9])
def test_runs_of_prefix_lengths_decode_each_block_alike_merged_or_not(tmp_path, scene_volume, pca32, monkeypatch,
                                                                       merge):
    """decode_runs decodes runs of like prefix lengths apart (RUN_MERGE 0) or joined into the wider run (a large
    RUN_MERGE: one product at the longest prefix): either way every block is the codec's decode of its own
    zero-padded code, and the groups come back in the order of their coordinates."""
    from sdfcodec.map import varread

    monkeypatch.setattr(varread, "RUN_MERGE", merge)
    monkeypatch.setattr(varread, "RUN_WIDTH", 4)  # runs of 4 elements: the scene's prefixes (26-32) span several
    vr = _write(tmp_path / "vr.sdfz", pca32, scene_volume, variable_rate={"step": 0.3})
    coords, z = vr.read_codes()
    lengths = np.where((z != 0).any(1), 32 - np.argmax((z != 0)[:, ::-1], axis=1), 0)
    assert len(np.unique(-(-lengths // varread.RUN_WIDTH))) > 1  # blocks of more than one run width
    full = dict(zip(map(tuple, coords), np.clip(pca32.decode(z) * (TRUNC[1] - TRUNC[0]) + TRUNC[0], *TRUNC)))
    seen = 0
    for cs, blocks in vr.iter_decoded():
        for c, b in zip(cs, np.asarray(blocks)):
            np.testing.assert_allclose(b, full[tuple(c)], atol=1e-5)
            seen += 1
    assert seen == len(coords)


def test_a_missing_or_corrupt_stream_is_one_clear_error(tmp_path, scene_volume, pca32):
    root = tmp_path / "vr.sdfz"
    # without the integrity manifest, which would refuse the missing chunk first (tests/test_manifest.py): the
    # reader's own check of the streams is what maps written without one rely on
    _write(root, pca32, scene_volume, variable_rate={"step": 0.1}, chunk_blocks=2, manifest=False)
    chunk = next(p for p in sorted((root / STREAM_ARRAY / "c").rglob("*")) if p.is_file())
    chunk.unlink()
    with pytest.raises(errors.FormatError, match="holds no stream"):
        sdfcodec.open_map(root).read_codes()
    with_manifest = tmp_path / "vr-manifest.sdfz"
    _write(with_manifest, pca32, scene_volume, variable_rate={"step": 0.1}, chunk_blocks=2)
    next(p for p in sorted((with_manifest / STREAM_ARRAY / "c").rglob("*")) if p.is_file()).unlink()
    with pytest.raises(errors.IntegrityError, match="code_streams.*missing"):
        sdfcodec.open_map(with_manifest).read_codes()
    from sdfcodec.map.verify import verify_map
    assert not verify_map(root).ok
    with pytest.raises(errors.InvalidValueError, match="not updated in place"):
        sdfcodec.update_map(root)


def _fused_room(seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A synthetic room as fusion leaves it (unobserved behind surfaces): block coords, blocks, observation."""
    from _fused_maps import fused_like
    from sdfcodec.search.rooms import synthetic_room

    vol, observed = fused_like(synthetic_room(seed, size=(2.2, 2.0, 1.8)).volume)
    blocks = split_blocks(vol, fill=TRUNC[1])
    obs = split_blocks(observed.astype(np.float32), fill=1.0).reshape(-1, 16, 16, 16) > 0.5
    return np.argwhere(np.ones(blocks.shape[:3], bool)), blocks.reshape(-1, 16, 16, 16), obs


# pca-64 takes at most ~103.5 B on the scene. Both targets are below core.varrate.SHRINK_BELOW (the low-rate
# path with the shrunk second encode); 60 B on one room stays in CI, 100 B (the same bisection near the codes'
# top) on two rooms on demand
@pytest.mark.parametrize("target,seeds", [(60.0, (0,)), pytest.param(100.0, (0, 1), marks=pytest.mark.slow)])
def test_target_bytes_lands_at_or_just_below_the_target(tmp_path, target, seeds):
    """Rate control on synthetic fused rooms (masked) and an analytic scene: every file counted (the manifest
    and its record in the header too), within 1 % below the target and never above it, so that every byte the
    side information saves goes to the codes."""
    codec = pretrained_codec("pca", 64)
    for i, seed in enumerate(seeds):
        coords, blocks, obs = _fused_room(seed)
        p = tmp_path / f"room{i}.sdfz"
        with sdfcodec.create_map(p, codec=codec, voxel_size=VS, truncation=TRUNC, overwrite=True,
                                 codec_state="reference", variable_rate={"target_bytes": target}) as m:
            m.write_blocks(coords, blocks, observed=obs)
        assert 0.99 * target <= _files_per_block(p) <= target, (seed, _files_per_block(p))
    p = tmp_path / "scene.sdfz"
    vol = sample_volume(Scene([Plane((0, 0, 1), 0.3), Box((1.0, 1.2, 0.6), (0.3, 0.2, 0.25)),
                               Sphere((2.0, 0.8, 0.7), 0.35)]), (128, 96, 64), VS, truncation=TRUNC)
    _write(p, codec, vol, codec_state="reference", variable_rate={"target_bytes": target})
    assert 0.99 * target <= _files_per_block(p) <= target, _files_per_block(p)


def _crossing_voxels(x: np.ndarray) -> np.ndarray:
    """The voxels of a dense volume ``x`` (metres) touching a crossing between axis neighbours, in one 16^3 block or
    across the face of two: ``target_error``'s definition, computed here from the volume itself."""
    from sdfcodec.core.surface import crossing_edges

    touch = np.zeros(x.shape, bool)
    for ax in range(3):
        a, b = np.moveaxis(x, ax, 0)[:-1], np.moveaxis(x, ax, 0)[1:]
        edge = crossing_edges(a, b)
        t = np.moveaxis(touch, ax, 0)
        t[:-1] |= edge
        t[1:] |= edge
    return touch


def test_surface_at_a_fixed_rate_and_the_error_target(tmp_path, scene_volume):
    """The analytic scene at 100 B per coded block: surface metrics against the exact field above a bound;
    ``target_error`` keeps 99 % of the voxels touching a crossing of the exact field within E, and a tighter
    target makes a larger map. (The error target's scene fills whole blocks: a volume's last blocks are padded
    by repeating its last voxels, and the writer's sample counts the crossings there too.)"""
    from sdfcodec.core.surface import compare_volumes
    from sdfcodec.map.errortarget import ERROR_QUANTILE

    codec = pretrained_codec("pca", 128)
    m = _write(tmp_path / "b.sdfz", codec, scene_volume, codec_state="reference",
               variable_rate={"target_bytes": 100.0})
    met = compare_volumes(scene_volume, m.decode_region(), VS)
    assert met.f_score_1 >= 0.9 and met.chamfer_l1 <= 0.01, met
    vol = sample_volume(analytic_scene(), (96, 80, 48), VS, truncation=TRUNC)
    touch = _crossing_voxels(vol)
    sizes = []
    for e in (0.02, 0.005):
        p = tmp_path / f"e{e}.sdfz"
        m = _write(p, codec, vol, codec_state="reference", variable_rate={"target_error": e})
        # the scene's coded blocks are all in the writer's sample (2048), so the quantile is the whole map's
        err = np.abs(m.decode_region() - vol)[touch]
        assert np.quantile(err, ERROR_QUANTILE) <= e + 1e-6, (e, np.quantile(err, ERROR_QUANTILE))
        sizes.append(_files_per_block(p))
    assert sizes[0] < sizes[1], sizes


def test_an_error_target_below_what_the_codes_reach_takes_a_surface_refinement(tmp_path):
    """A wall, a floor and a 3 cm cube no eigenshape holds: 4 mm is below what the codes alone reach at their
    finest step (the writer refused it); the map takes a surface refinement beside coarser codes and keeps 99 %
    of the crossing voxels within 4 mm, the cube's (under 1 % of them) included in the count."""
    from sdfcodec.map.errortarget import ERROR_QUANTILE

    vol = sample_volume(Scene([Plane((0, 0, 1), 0.3), Plane((1, 0, 0), 0.35), Box((1.3, 0.9, 0.75), (0.015,) * 3)]),
                        (96, 96, 64), VS, truncation=TRUNC)
    touch = _crossing_voxels(vol)
    codec = pretrained_codec("pca", 128)
    e = 0.004
    m = _write(tmp_path / "e.sdfz", codec, vol, codec_state="reference", variable_rate={"target_error": e})
    assert m.header.codes.variable_rate.refinement is not None
    err = np.abs(m.decode_region() - vol)[touch]
    assert np.quantile(err, ERROR_QUANTILE) <= e + 1e-6, np.quantile(err, ERROR_QUANTILE)


def test_the_error_samples_face_crossings_weigh_what_the_sample_lacks():
    """Two blocks side by side along x, a plane between voxel 15 of the first and voxel 0 of the second: every
    crossing lies across their face. Both kept: those voxels count (weight 1, a plain quantile); with a sample of
    2 of 5 blocks, each weighs (5 - 1) / (2 - 1) = 4 against 1 for a crossing inside a block; a block alone has no
    crossing."""
    from sdfcodec.map.errortarget import ErrorSample

    xs = (np.arange(32) - 15.5) * VS
    vol = np.broadcast_to(xs[:, None, None], (32, 16, 16)).astype(np.float32)
    v = ((np.clip(vol, *TRUNC) - TRUNC[0]) / (TRUNC[1] - TRUNC[0])).reshape(2, 16, 16, 16)
    coords = np.array([[0, 0, 0], [1, 0, 0]])
    codec = pretrained_codec("pca", 8)
    for seen, weight in ((2, None), (5, 4.0)):
        sample = ErrorSample(codec, 2)
        sample.add(coords, v, None, np.zeros((2, 8)), np.ones((2, 8)))
        sample._seen = seen  # as if 3 more blocks had been added and not kept
        sample.coarsest_step(0.05, TRUNC, lambda z, g, s: z)
        _, _, _, _, _, (x, cross, w) = sample._arrays
        kept = [int(t[1][0]) for t in sample._kept]  # the sample's order: its random priorities
        for i, bx in enumerate(kept):  # the face's layers: x = 15 of block 0, x = 0 of block 1
            assert cross.reshape(2, 16, 16, 16)[i, 15 if bx == 0 else 0].all()
        assert cross.sum() == 2 * 256
        assert (w is None) if weight is None else np.array_equal(w, np.full(512, weight))
    alone = ErrorSample(codec, 2)
    alone.add(coords[:1], v[:1], None, np.zeros((1, 8)), np.ones((1, 8)))
    assert alone.coarsest_step(0.05, TRUNC, lambda z, g, s: z)[1] == 0.0
    # where the writer keeps every block's input (a TrueValues), a kept block's faces read their neighbours there,
    # kept or not: a sample of one of the two blocks counts its 256 face voxels, unweighted, observed ones only
    from sdfcodec.map.refine import TrueValues

    metres = v.reshape(2, -1) * np.float32(TRUNC[1] - TRUNC[0]) + np.float32(TRUNC[0])
    seen_mask = np.ones((2, 16, 16, 16), bool)
    seen_mask[1, 0, :8] = False  # half the second block's facing layer unobserved: no crossing there
    for keep in (0, 1):
        truth = TrueValues()
        truth.add(coords, metres, seen_mask)
        one = ErrorSample(codec, 1)
        one.add(coords[keep:keep + 1], v[keep:keep + 1], seen_mask[keep:keep + 1], np.zeros((1, 8)),
                np.ones((1, 8)), truth)
        one.coarsest_step(0.05, TRUNC, lambda z, g, s: z)
        _, _, _, _, _, (x, cross, w) = one._arrays
        layer = cross.reshape(16, 16, 16)[15 if keep == 0 else 0]
        assert w is None and cross.sum() == 128 and layer[8:].all() and not layer[:8].any()
        truth.close()


def test_a_sampled_maps_error_holds_for_the_map_with_the_stated_confidence():
    """A population of 2,000 blocks whose voxel errors cluster by block (some blocks much worse, as codes make
    them): over 200 uniform samples of 1,000 blocks, the sample's plain p99 falls under the population's about
    half the time, the bounded one (``sampled=(k, N)``: CONFIDENCE_Z standard errors, blocks as the unit, the
    finite population corrected) at most 10 % of the time; with every block sampled it is the plain quantile."""
    from sdfcodec.map.errortarget import ERROR_QUANTILE, _bounded_quantile

    rng = np.random.default_rng(11)
    n_blocks = 2000
    per = rng.integers(20, 300, n_blocks)
    block = np.repeat(np.arange(n_blocks), per)
    err = rng.gamma(2.0, 1.0, len(block)) * np.where(rng.random(n_blocks) < 0.05, 4.0, 1.0)[block]
    truth = np.quantile(err, ERROR_QUANTILE, method="inverted_cdf")
    under = {"plain": 0, "bounded": 0}
    for _ in range(200):
        pick = np.sort(rng.choice(n_blocks, 1000, replace=False))
        sel = np.isin(block, pick)
        e, b = err[sel], np.searchsorted(pick, block[sel])
        under["plain"] += np.quantile(e, ERROR_QUANTILE, method="inverted_cdf") < truth
        under["bounded"] += _bounded_quantile(e, b, len(pick), None, ERROR_QUANTILE, len(pick), n_blocks) < truth
    assert 60 <= under["plain"] <= 140 and under["bounded"] <= 20, under
    all_in = _bounded_quantile(err, block, n_blocks, None, ERROR_QUANTILE, n_blocks, n_blocks)
    assert all_in == np.quantile(err, ERROR_QUANTILE, method="inverted_cdf")


def test_an_error_target_below_the_refinement_ladder_takes_its_finest_step(tmp_path):
    """0.12 mm: every step of the ladder (at most 1.5 E, 0.18 mm) lies below the finest refinement step rate control
    takes (0.2 mm), which was refused; that step keeps a corrected voxel within 0.1 mm, so the map takes it and
    meets the target. 0.05 mm is refused naming what the refinement reaches."""
    from sdfcodec.map.errortarget import ERROR_QUANTILE, REFINE_RANGE, refine_steps

    assert refine_steps(1.2e-4) == [REFINE_RANGE[0]] and refine_steps(100.0) == []
    vol = sample_volume(Scene([Plane((0, 0, 1), 0.3), Plane((1, 0, 0), 0.35)]), (64, 64, 48), VS, truncation=TRUNC)
    touch = _crossing_voxels(vol)
    codec = pretrained_codec("pca", 128)
    m = _write(tmp_path / "e.sdfz", codec, vol, codec_state="reference", variable_rate={"target_error": 1.2e-4})
    assert m.header.codes.variable_rate.refinement.step * 2.0 ** -24 == pytest.approx(REFINE_RANGE[0], rel=1e-3)
    err = np.abs(m.decode_region() - vol)[touch]
    assert np.quantile(err, ERROR_QUANTILE) <= 1.2e-4, np.quantile(err, ERROR_QUANTILE)
    with pytest.raises(errors.InvalidValueError, match=r"0\.05 mm is below .* mm at its finest step with a surface"):
        _write(tmp_path / "f.sdfz", codec, vol, codec_state="reference", variable_rate={"target_error": 5e-5})


# -- golden -------------------------------------------------------------------------------------------------------

def _golden_map(path: Path) -> None:
    codec = sdfcodec.get_codec("pca", code_size=8).fit(analytic_blocks(64, seed=5))
    vol = sample_volume(analytic_scene(), (40, 24, 20), VS, truncation=TRUNC)
    with sdfcodec.create_map(path, codec=codec, voxel_size=VS, truncation=TRUNC, chunk_blocks=2,
                             variable_rate={"step": 0.05}, tool="tests/test_variable_rate.py golden") as m:
        m.write_volume(vol)


@pytest.mark.parametrize("golden, magic", [(GOLDEN, False), (GOLDEN.with_name("varrate-compact-pca-8"), True)])
def test_golden_variable_rate_map_decodes_forever(regen_golden, golden, magic):
    """Small variable-rate maps written once: today's reader must open them, verify them and decode them to the
    frozen values. ``varrate-pca-8`` holds the fixed-width model layout no writer writes any more, so it is never
    regenerated; ``varrate-compact-pca-8`` the compact one (regenerate only with --regen-golden, for a format
    change)."""
    m = check_golden_map(golden, _golden_map, regen_golden and magic)
    vr = m.header.codes.variable_rate
    assert vr.step == [0.05] and vr.coder == "constriction-ans-1"
    assert any(e.name == "variable-rate-codes" and e.required for e in m.header.extensions)
    assert (zlib.decompress(base64.b64decode(vr.model))[:4] == b"\xff\xff\xff\x02") == magic


# -- CLI ------------------------------------------------------------------------------------------------------------

def test_encode_target_bytes_alone_references_the_shipped_model(tmp_path, scene_volume):
    src = tmp_path / "scene.npy"
    np.save(src, scene_volume)
    out = tmp_path / "s.sdfz"
    r = CliRunner().invoke(app, ["encode", str(src), str(out), "--voxel-size", str(VS), "--target-bytes", "90",
                                 "--json"])
    assert r.exit_code == 0, r.output
    q = json.loads(r.stdout[r.stdout.index("{"):])["quantisation"]
    m = sdfcodec.open_map(out)
    h = m.header
    assert q["variable_rate"] and h.codes.size == 128 and h.codec.state_reference is not None
    assert abs(_files_per_block(out) - 90) <= 0.05 * 90
    # a fitted codec is embedded: its state is not shipped anywhere
    r = CliRunner().invoke(app, ["encode", str(src), str(tmp_path / "f.sdfz"), "--voxel-size", str(VS),
                                 "--code-size", "8", "--fit"])
    assert r.exit_code == 0, r.output
    assert sdfcodec.open_map(tmp_path / "f.sdfz").header.codec.state_arrays
    for args, msg in ((["--target-bytes", "1"], "below what this map can take"),
                      (["--target-error", "-1"], "finite number of metres > 0"),
                      (["--target-error", "0.00005"], "below what this codec reaches"),
                      (["--target-bytes", "5000", "--no-refine"], "or take longer codes (--code-size)"),
                      (["--target-error", "0.02", "--target-bytes", "90"], "drop --target-bytes"),
                      (["--target-error", "0.02", "--step", "0.1"], "drop --step"),
                      (["--target-error", "0.02", "--codec", "sz3"], "codes are not prefix-ordered"),
                      (["--variable-rate", "--step", "0.1", "--codec", "ae"], "codes are not prefix-ordered")):
        r = CliRunner().invoke(app, ["encode", str(src), str(tmp_path / "bad.sdfz"), "--voxel-size", str(VS), *args])
        assert r.exit_code == 1 and msg in r.output, (args, r.output)
        assert not (tmp_path / "bad.sdfz").exists()
    shutil.rmtree(out)


def test_chunk_codes_of_many_chunks_keeps_those_it_had_cached(tmp_path, pca32, scene_volume):
    """A request for more chunks than the reader caches, some of them cached already, returns every chunk's codes
    (decoding the others once evicted the cached ones before they were returned: a KeyError), equal to a fresh
    reader's."""
    m = _write(tmp_path / "many.sdfz", pca32, scene_volume, variable_rate={"step": 0.1}, chunk_blocks=2)
    coded = np.argwhere(m.block_states() == 2)
    keys = np.unique(coded // 2, axis=0)
    assert len(keys) > 12
    vr = m.reader.vr
    vr.chunk_codes(keys[:3], pca32.code_size)
    got = vr.chunk_codes(keys, pca32.code_size)
    fresh = sdfcodec.open_map(tmp_path / "many.sdfz").reader.vr
    for (la, qa), key in zip(got, keys):
        (lb, qb), = fresh.chunk_codes(key[None], pca32.code_size)
        np.testing.assert_array_equal(la, lb)
        np.testing.assert_array_equal(qa, qb)
