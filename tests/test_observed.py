"""Observed-aware encoding: per-voxel error weights in the codec contract, PCA's weighted least squares, the
observation mask a map stores and its readers restore (sdfcodec.map.observed, spec section 6b)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from scipy import ndimage
from typer.testing import CliRunner

import sdfcodec
from sdfcodec.core.blocks import normalise
from sdfcodec.cli import app
from sdfcodec.errors import DTypeError, FormatError, InvalidValueError, ShapeError
from sdfcodec.map.observed import MASK_EXTENSION, error_weights, fill_unobserved, pack_mask, unpack_mask
from sdfcodec.core.surface import compare_volumes

TRUNC, VS = (-0.04, 0.1), 0.02


def fused_like(sdf: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """What fusion makes of an exact SDF (metres): truncated to ``[d_min, d_max]``, observed only down to
    ``d_min`` behind the surface (deeper voxels unobserved, reading ``d_max``)."""
    observed = sdf >= TRUNC[0]
    return np.where(observed, np.clip(sdf, *TRUNC), TRUNC[1]).astype(np.float32), observed


def scene(n: int = 64) -> np.ndarray:
    """Exact SDF (metres) of a floor, a wall and a box, voxel centres at index * VS."""
    p = np.stack(np.meshgrid(*[np.arange(n) * VS] * 3, indexing="ij"), -1)
    floor = p[..., 2] - 0.31
    wall = p[..., 0] - 0.23
    box = np.max(np.abs(p - np.array([0.8, 0.7, 0.5])) - np.array([0.15, 0.2, 0.12]), axis=-1)
    return np.minimum(np.minimum(floor, wall), box).astype(np.float32)


def weighted_lstsq(codec, x: np.ndarray, w: np.ndarray, ridge: float) -> np.ndarray:
    """Independent reference: ``argmin sum w (x - (c D + d))^2 + lam |c - c0|^2`` by numpy's lstsq on the
    stacked system, ``lam = ridge * mean(w)``, in float64."""
    state = codec.state_dict()
    dec_w, dec_b = state["components"].astype(np.float64), state["mean"].astype(np.float64)
    out = []
    for xi, wi in zip(x.reshape(len(x), -1).astype(np.float64), w.reshape(len(w), -1).astype(np.float64)):
        c0 = (xi - dec_b) @ dec_w.T
        lam = ridge * wi.mean()
        a = np.vstack([np.sqrt(wi)[:, None] * dec_w.T, np.sqrt(lam) * np.eye(len(dec_w))])
        b = np.concatenate([np.sqrt(wi) * (xi - dec_b), np.sqrt(lam) * c0])
        out.append(np.linalg.lstsq(a, b, rcond=None)[0])
    return np.array(out)


@pytest.fixture(scope="module")
def blocks_and_mask():
    vol, obs = fused_like(scene())
    v = normalise(vol, *TRUNC).reshape(4, 16, 4, 16, 4, 16).transpose(0, 2, 4, 1, 3, 5).reshape(-1, 16, 16, 16)
    o = obs.reshape(4, 16, 4, 16, 4, 16).transpose(0, 2, 4, 1, 3, 5).reshape(-1, 16, 16, 16)
    keep = ~(v >= 1 - 1e-6).reshape(len(v), -1).all(axis=1)
    return v[keep], o[keep]


def test_error_weights_follow_their_definition_in_metres(rng):
    # 150 blocks: more than one in-place slab; distances in metres, the band and weights as documented
    from sdfcodec.map.observed import SURFACE_BAND_VOXELS, SURFACE_WEIGHT

    d = rng.uniform(*TRUNC, size=(150, 16, 16, 16)).astype(np.float32)
    obs = rng.random(d.shape) < 0.7
    ref = np.where(obs, np.where(np.abs(d) < SURFACE_BAND_VOXELS * VS, 1 + SURFACE_WEIGHT, 1.0), 0.0)
    w = error_weights(normalise(d, *TRUNC), obs, TRUNC, VS)
    near_edge = np.abs(np.abs(d) - SURFACE_BAND_VOXELS * VS) < 1e-6  # float32 rounding of the normalisation
    assert w.dtype == np.float32 and w.shape == d.shape
    np.testing.assert_array_equal(w[~near_edge], ref[~near_edge])
    np.testing.assert_array_equal(error_weights(normalise(d, *TRUNC), obs, TRUNC, VS, surface_weight=0), obs)
    assert error_weights(d, None, TRUNC, VS) is None


def test_pca_weighted_encode_is_the_weighted_least_squares(blocks_and_mask):
    import sdfcodec_pca

    v, obs = blocks_and_mask
    codec = sdfcodec.pretrained_codec("pca", 32)
    w = error_weights(v[:6], obs[:6], TRUNC, VS)
    got = codec.encode(v[:6], weights=w)
    ref = weighted_lstsq(codec, v[:6], w, sdfcodec_pca.RIDGE)
    # float32 normal equations against float64 lstsq. A block with few observed voxels is ill-conditioned
    # (cond ~1e6 here), so the codes themselves may differ along directions the weights barely see, by how
    # much depends on the BLAS (AMD vs Intel kernels differ): compare what the weights see instead, the
    # weighted reconstructions, to 0.1 % of the block's weighted norm, and the objective to 0.1 %.
    state = codec.state_dict()
    seen = lambda c: np.sqrt(w.reshape(6, -1)) * (c @ state["components"])  # noqa: E731
    norm = np.linalg.norm(np.sqrt(w.reshape(6, -1)) * v[:6].reshape(6, -1), axis=1)
    assert np.all(np.linalg.norm(seen(got) - seen(ref), axis=1) <= 1e-3 * norm)
    err = lambda c: (w.reshape(6, -1) * (c @ state["components"] + state["mean"] - v[:6].reshape(6, -1)) ** 2  # noqa: E731
                     ).sum(axis=1)
    assert np.all(err(got) <= err(ref) * 1.001 + 1e-6)
    assert np.all(err(got) < err(codec.encode(v[:6])))  # and far better than the plain projection


@pytest.mark.parametrize("cg_steps", [0, 2])  # the exact active-set refits; conjugate-gradient steps (the default)
def test_truncation_aware_refit_minimises_the_error_a_reader_sees(blocks_and_mask, cg_steps, monkeypatch):
    """encode_truncated fits what a reader sees (it truncates to [0, 1] = [d_min, d_max]): a voxel stored at a
    bound costs nothing when decoded beyond it. Checked against scipy's L-BFGS on that convex objective (squared
    error, one-sided at the bound voxels, plus the codec's ridge), started from the plain weighted fit, with both
    refit solvers of the pca codec's compiled pass (PCACodec.cg_steps_per_refit; where numba is missing, the
    batched path runs the exact refits either way)."""
    from scipy.optimize import minimize

    import sdfcodec_pca
    from sdfcodec.map.observed import encode_truncated

    monkeypatch.setattr(sdfcodec_pca.PCACodec, "cg_steps_per_refit", cg_steps)
    exact = cg_steps == 0 or not sdfcodec_pca.truncated.available()
    v, obs = blocks_and_mask
    codec = sdfcodec.pretrained_codec("pca", 16)
    # the four blocks with the most free-space voxels the plain weighted fit decodes beyond d_max
    over = ((v >= 1 - 1e-6) & obs & (codec.decode(codec.encode(v, weights=error_weights(v, obs, TRUNC, VS))) > 1))
    pick = np.argsort(over.reshape(len(v), -1).sum(1))[-4:]
    v, obs = v[pick], obs[pick]
    w = error_weights(v, obs, TRUNC, VS)
    state = codec.state_dict()
    comp, mean = state["components"].astype(np.float64), state["mean"].astype(np.float64)

    def reader_error(c, x, wi):  # what a reader's truncated decode misses by
        return float((wi * (np.clip(c @ comp + mean, 0, 1) - x) ** 2).sum())

    plain = codec.encode(v, weights=w)
    got = encode_truncated(codec, torch.from_numpy(v), torch.from_numpy(w), rounds=50).numpy()
    gains = []
    for i in range(len(v)):
        x, wi = v[i].reshape(-1).astype(np.float64), w[i].reshape(-1).astype(np.float64)
        c0 = (x - mean) @ comp.T
        top, bot = (x >= 1 - 1e-6) & (wi > 0), (x <= 1e-6) & (wi > 0)

        def objective(c, lam):
            r = c @ comp + mean - x
            r = np.where(top, np.minimum(r, 0), np.where(bot, np.maximum(r, 0), r))
            return (wi * r * r).sum() + lam * ((c - c0) ** 2).sum(), 2 * comp @ (wi * r) + 2 * lam * (c - c0)

        # the codec's ridge is lam = RIDGE * mean of the weights it was given: the exact refits', those of the
        # final active set; the conjugate-gradient steps minimise one objective, whose ridge is the block's
        lam = sdfcodec_pca.RIDGE * (np.where(top & (got[i] @ comp + mean >= 1) | bot & (got[i] @ comp + mean <= 0),
                                             0, wi) if exact else wi).mean()
        ref = minimize(objective, plain[i].astype(np.float64), args=(lam,), jac=True, method="L-BFGS-B",
                       options={"maxiter": 5000, "gtol": 1e-10, "ftol": 1e-15}).x
        # the active-set fit reaches the optimiser's objective (to 0.5 %), never worse for a reader than the fit
        # that ignores truncation (equal where no bound voxel decodes beyond its bound), better somewhere
        assert objective(got[i], lam)[0] <= objective(ref, lam)[0] * 1.005 + 1e-6
        assert reader_error(got[i], x, wi) <= reader_error(plain[i], x, wi) + 1e-9
        gains.append(reader_error(plain[i], x, wi) - reader_error(got[i], x, wi))
    assert max(gains) > 1e-3


def test_zero_weights_keep_the_plain_code_and_torch_follows_the_device(blocks_and_mask):
    v, _ = blocks_and_mask
    codec = sdfcodec.pretrained_codec("pca", 64)
    np.testing.assert_allclose(codec.encode(v[:3], weights=np.zeros(v[:3].shape, np.float32)), codec.encode(v[:3]),
                               atol=1e-5)
    t = codec.encode(torch.from_numpy(v[:3]), weights=torch.ones(v[:3].shape, dtype=torch.bool))
    assert isinstance(t, torch.Tensor) and t.shape == (3, 64)
    # uniform weights: the projection, up to float32 rounding of the normal equations (relative to the codes'
    # scale: a code of 23 carries ~2e-6 of relative rounding per operation, more on AMD's BLAS kernels)
    plain = codec.encode(v[:3])
    np.testing.assert_allclose(t.numpy(), plain, rtol=0, atol=2e-5 * np.abs(plain).max())


@pytest.mark.parametrize("bad, error", [
    (lambda s: -np.ones(s, np.float32), InvalidValueError),
    (lambda s: np.full(s, np.nan, np.float32), InvalidValueError),
    (lambda s: np.ones((s[0], 8, 8, 8), np.float32), ShapeError),
    (lambda s: np.ones((s[0] + 1, *s[1:]), np.float32), ShapeError),
    (lambda s: np.full(s, "a"), DTypeError),
])
def test_bad_weights_are_clear_errors(blocks_and_mask, bad, error):
    v, _ = blocks_and_mask
    with pytest.raises(error, match="weights"):
        sdfcodec.pretrained_codec("pca", 32).encode(v[:2], weights=bad(v[:2].shape))


def test_codecs_without_the_hook_ignore_the_weights(blocks_and_mask):
    v, obs = blocks_and_mask
    raw = sdfcodec.get_codec("raw")
    np.testing.assert_array_equal(raw.encode(v[:2], weights=obs[:2]), raw.encode(v[:2]))


def test_mask_packing_round_trips(rng):
    m = rng.random((5, 16, 16, 16)) < 0.4
    rows = pack_mask(m)
    assert rows.shape == (5, 512) and rows.dtype == np.uint8
    np.testing.assert_array_equal(unpack_mask(rows), m)
    assert (pack_mask(np.ones((1, 16, 16, 16), bool)) == 255).all()


def write(path, vol, obs, k=64, codec=None, **kw):
    blocks = vol.reshape(4, 16, 4, 16, 4, 16).transpose(0, 2, 4, 1, 3, 5).reshape(-1, 16, 16, 16)
    o = None if obs is None else obs.reshape(4, 16, 4, 16, 4, 16).transpose(0, 2, 4, 1, 3, 5).reshape(-1, 16, 16, 16)
    coords = np.argwhere(np.ones((4, 4, 4), bool))
    with sdfcodec.create_map(path, codec=codec or sdfcodec.pretrained_codec("pca", k), voxel_size=VS,
                             truncation=TRUNC, **kw) as m:
        m.write_blocks(coords, blocks, observed=o)
    return sdfcodec.open_map(path)


def test_mask_restores_unobserved_voxels_and_keeps_the_surface(tmp_path):
    exact = scene()
    vol, obs = fused_like(exact)
    masked = write(tmp_path / "masked.sdfz", vol, obs)
    plain = write(tmp_path / "plain.sdfz", vol, None)
    assert {"name": MASK_EXTENSION, "required": True} in [e.model_dump() for e in masked.header.extensions]
    assert MASK_EXTENSION not in [e.name for e in plain.header.extensions]
    dm, dp = masked.decode_region(), plain.decode_region()
    assert (dm[~obs] == TRUNC[1]).all()  # every unobserved voxel reads d_max, exactly
    np.testing.assert_array_equal(masked.read_observed(np.argwhere(np.ones((4, 4, 4), bool))).shape, (64, 16, 16, 16))
    # surfaces against the analytic ones (the exact SDF's zero crossings), an independent expectation
    good, bad = compare_volumes(exact, dm, VS), compare_volumes(exact, dp, VS)
    assert good.chamfer_l1 < 0.25 * VS and good.f_score_1 > 0.95, good
    assert bad.chamfer_l1 > 2 * good.chamfer_l1, (good, bad)


def test_halo_codecs_leave_unobserved_voxels_unobserved(tmp_path):
    # the blur's context pass spreads observed values into unobserved space after the core decode: the reader
    # restores them again on the final values; observed voxels keep what the blur makes of them
    vol, obs = fused_like(scene())
    blur = sdfcodec.get_codec("gaussian-blur")
    masked = write(tmp_path / "masked.sdfz", vol, obs, codec=blur)
    plain = write(tmp_path / "plain.sdfz", vol, None, codec=blur)  # the same values: fused_like put d_max there
    dm, dp = masked.decode_region(), plain.decode_region()
    assert (dp[~obs] != TRUNC[1]).any()  # without the mask the blur reaches into unobserved space
    assert (dm[~obs] == TRUNC[1]).all()
    np.testing.assert_array_equal(dm[obs], dp[obs])
    part = masked.decode_region(((5, 40), (3, 64), (17, 50)))  # a region cutting through blocks
    box = np.s_[5:40, 3:64, 17:50]
    assert (part[~obs[box]] == TRUNC[1]).all()
    np.testing.assert_allclose(part, dm[box], rtol=0, atol=1e-6)  # the blur's float sums depend on the region
    for coords, blocks in masked.iter_blocks():  # block by block too
        o = masked.read_observed(coords)
        assert (blocks[~o] == TRUNC[1]).all()


def test_fill_grows_the_observed_values_into_unobserved_space(rng):
    v = rng.random((3, 16, 16, 16)).astype(np.float32)
    obs = np.zeros(v.shape, bool)
    obs[0, :, :, :8] = True  # a half observed: its last observed layer fills the rest, column by column
    obs[1] = True  # all observed: unchanged
    got = fill_unobserved(v, obs)  # block 2: nothing observed, unchanged
    np.testing.assert_array_equal(got[0, :, :, :8], v[0, :, :, :8])
    np.testing.assert_array_equal(got[0, :, :, 8:], np.repeat(v[0, :, :, 7:8], 8, axis=2))
    np.testing.assert_array_equal(got[1:], v[1:])
    assert got is not v and np.array_equal(v[0, :, :, 8:], v[0, :, :, 8:])  # the input is not touched


def test_codecs_that_ignore_weights_encode_the_filled_blocks(tmp_path):
    # a mixture ignores error weights: the writer gives it the blocks with unobserved space filled from the
    # observed band (solid behind surfaces), not the step to d_max; surfaces against the analytic ones
    exact = scene()
    vol, obs = fused_like(exact)
    codec = sdfcodec.pretrained_codec("sequential")
    m = write(tmp_path / "seq.sdfz", vol, obs, codec=codec)
    coords = np.argwhere(np.ones((4, 4, 4), bool))
    blocks = normalise(vol, *TRUNC).reshape(4, 16, 4, 16, 4, 16).transpose(0, 2, 4, 1, 3, 5).reshape(-1, 16, 16, 16)
    o = obs.reshape(4, 16, 4, 16, 4, 16).transpose(0, 2, 4, 1, 3, 5).reshape(-1, 16, 16, 16)
    unfilled = np.where(o, codec.decode(codec.encode(blocks)), 1.0) * (TRUNC[1] - TRUNC[0]) + TRUNC[0]
    unfilled = unfilled.reshape(4, 4, 4, 16, 16, 16).transpose(0, 3, 1, 4, 2, 5).reshape(64, 64, 64)
    good, bad = compare_volumes(exact, m.decode_region(), VS), compare_volumes(exact, unfilled, VS)
    assert (m.decode_region()[~obs] == TRUNC[1]).all() and m.read_observed(coords).shape == (64, 16, 16, 16)
    assert good.chamfer_l1 < 0.6 * bad.chamfer_l1 and good.f_score_1 > bad.f_score_1, (good, bad)


def test_blocks_rewritten_without_a_mask_read_as_observed(tmp_path):
    vol, obs = fused_like(scene())
    write(tmp_path / "m.sdfz", vol, obs)
    with sdfcodec.update_map(tmp_path / "m.sdfz") as m:
        m.write_blocks(np.array([[0, 0, 0]]), vol[:16, :16, :16][None])
    got = sdfcodec.open_map(tmp_path / "m.sdfz")
    assert not obs[:16, :16, :16].all() and got.read_observed(np.array([[0, 0, 0]])).all()
    partial = [b for b in np.argwhere(np.ones((4, 4, 4), bool))[1:]
               if not obs[tuple(slice(16 * i, 16 * i + 16) for i in b)].all()]
    assert partial
    b = partial[0]
    np.testing.assert_array_equal(got.read_observed(b[None])[0], obs[tuple(slice(16 * i, 16 * i + 16) for i in b)])


def test_map_without_its_mask_array_is_refused(tmp_path):
    import shutil

    vol, obs = fused_like(scene())
    write(tmp_path / "m.sdfz", vol, obs)
    shutil.rmtree(tmp_path / "m.sdfz" / "observed")
    with pytest.raises(FormatError, match="observed"):
        sdfcodec.open_map(tmp_path / "m.sdfz")


def test_fuse_stores_weights_and_transcoding_keeps_the_mask(tmp_path):
    vol, obs = fused_like(scene())
    src = tmp_path / "raw.sdfz"
    blocks = vol.reshape(4, 16, 4, 16, 4, 16).transpose(0, 2, 4, 1, 3, 5).reshape(-1, 16, 16, 16)
    weights = obs.reshape(4, 16, 4, 16, 4, 16).transpose(0, 2, 4, 1, 3, 5).reshape(-1, 16, 16, 16) * 3.0
    with sdfcodec.create_map(src, codec=sdfcodec.get_codec("raw"), voxel_size=VS, truncation=TRUNC) as m:
        m.write_blocks(np.argwhere(np.ones((4, 4, 4), bool)), blocks, weights=weights)
    res = CliRunner().invoke(app, ["encode", str(src), str(tmp_path / "p.sdfz"), "--codec", "pca", "--json"])
    assert res.exit_code == 0, res.output
    out = sdfcodec.open_map(tmp_path / "p.sdfz")
    assert MASK_EXTENSION in [e.name for e in out.header.extensions] and not out.has_weights
    assert (out.decode_region()[~obs] == TRUNC[1]).all()
    assert json.loads(res.output)["blocks"]["coded"] == out.count_states()["coded"]


def test_transcoding_a_map_without_observation_encodes_plainly(tmp_path):
    # an exact SDF stored lossless records no observation: transcoded, it is encoded as its volume is (plain
    # projection, no mask), so its code distances stay reconstruction distances
    exact = np.clip(scene(), *TRUNC)
    src = tmp_path / "exact.sdfz"
    with sdfcodec.create_map(src, codec=sdfcodec.get_codec("raw"), voxel_size=VS, truncation=TRUNC) as m:
        m.write_volume(exact)
    with sdfcodec.create_map(tmp_path / "t.sdfz", codec=sdfcodec.pretrained_codec("pca", 32), voxel_size=VS,
                             truncation=TRUNC) as t:
        t.write_map(sdfcodec.open_map(src))
    with sdfcodec.create_map(tmp_path / "d.sdfz", codec=sdfcodec.pretrained_codec("pca", 32), voxel_size=VS,
                             truncation=TRUNC) as d:
        d.write_volume(exact)
    tc, dc = (dict((tuple(c), z) for cs, zs in mm.iter_codes() for c, z in zip(cs, zs)) for mm in (t, d))
    assert MASK_EXTENSION not in [e.name for e in t.header.extensions] and tc.keys() == dc.keys()
    np.testing.assert_allclose(np.array([tc[k] for k in dc]), np.array(list(dc.values())), atol=1e-4)


def test_mesh_of_a_masked_map_has_no_false_surfaces(tmp_path):
    import open3d as o3d

    exact = scene()
    vol, obs = fused_like(exact)
    write(tmp_path / "m.sdfz", vol, obs)
    res = CliRunner().invoke(app, ["mesh", str(tmp_path / "m.sdfz"), str(tmp_path / "m.ply")])
    assert res.exit_code == 0, res.output
    verts = np.asarray(o3d.io.read_triangle_mesh(str(tmp_path / "m.ply")).vertices)
    assert len(verts) > 1000
    # every vertex lies on the analytic surface (within a voxel), none where solid meets unobserved space
    idx = np.clip(np.round(verts / VS).astype(int), 0, exact.shape[0] - 1)
    assert np.abs(exact[tuple(idx.T)]).max() < 1.5 * VS


def test_a_damaged_mask_chunk_is_found_by_verify_and_refused_by_reads(tmp_path):
    from sdfcodec.errors import ChecksumError
    from sdfcodec.map.verify import verify_map

    vol, obs = fused_like(scene())
    write(tmp_path / "m.sdfz", vol, obs)
    assert verify_map(tmp_path / "m.sdfz").ok
    chunk = next(p for p in (tmp_path / "m.sdfz" / "observed" / "c").rglob("*") if p.is_file())
    raw = bytearray(chunk.read_bytes())
    raw[len(raw) // 2] ^= 0xFF
    chunk.write_bytes(bytes(raw))
    rep = verify_map(tmp_path / "m.sdfz")
    assert not rep.ok and any("observed" in f"{p.where} {p.message}" for p in rep.problems), rep.problems
    with pytest.raises(ChecksumError, match="observed"):
        sdfcodec.open_map(tmp_path / "m.sdfz").decode_region()


def test_fill_equals_layer_by_layer_growth_by_scipy(rng):
    # an independent fill: scipy's correlation with the face-neighbour cross gives each layer's sums, in float64
    cross = ndimage.generate_binary_structure(3, 1).astype(np.float64)
    cross[1, 1, 1] = 0
    v = rng.random((70, 16, 16, 16)).astype(np.float32)  # more blocks than one group of the fill
    obs = rng.random(v.shape) < rng.uniform(0.001, 0.6, (70, 1, 1, 1))
    obs[5] = False
    obs[6] = True
    want = v.astype(np.float64)
    for b in range(len(v)):
        if not obs[b].any():
            continue
        val, known = np.where(obs[b], want[b], 0.0), obs[b].astype(np.float64)
        while not known.all():
            total = ndimage.correlate(val, cross, mode="constant")
            count = ndimage.correlate(known, cross, mode="constant")
            new = (count > 0) & (known == 0)
            val[new] = total[new] / count[new]
            known[new] = 1
        want[b] = val
    np.testing.assert_allclose(fill_unobserved(v, obs), want, rtol=1e-5, atol=1e-6)
