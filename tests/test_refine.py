"""The surface refinement of variable-rate maps (spec section 6h, sdfcodec/map/refine.py): corrections bounded by
their step on an analytic scene, streams that plain constriction reads to what a numpy reference computes, rate
control with the refinement, the golden map, and corruption."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import sdfcodec
from _fused_maps import TRUNC, VS, fused_like, write_volume_map
from sdfcodec import errors
from sdfcodec.core.blocks import split_blocks
from sdfcodec.core.sdf import sample_volume
from sdfcodec.core.surface import compare_volumes
from sdfcodec.map import pinmask as pm
from sdfcodec.registry import pretrained_codec
from sdfcodec.testing import analytic_scene

S = 2.0 ** pm.FRACTION_BITS
GOLDEN = Path(__file__).parent / "golden" / "maps" / "refined-pca-8"


@pytest.fixture(scope="module")
def codec():
    return pretrained_codec("pca", 64)


@pytest.fixture(scope="module")
def room():
    return fused_like(sample_volume(analytic_scene(), (96, 80, 48), VS, truncation=TRUNC))


def _blocks(vol: np.ndarray, coords: np.ndarray, fill: float) -> np.ndarray:
    return split_blocks(vol.astype(np.float32), fill=fill)[tuple(coords.T)].reshape(len(coords), -1)


def _reference(m: sdfcodec.Map, codec, vol: np.ndarray, obs: np.ndarray):
    """A plain numpy reference of the refinement (spec 6h) from the map's codes and the true volume: per coded
    block (the reader's coords order) the clipped exact decode, the selected voxels and their corrections."""
    h = m.header.codes.variable_rate
    ref = h.refinement
    coords, codes = m.reader.read_codes()
    step = h.step[0]
    q = np.rint(codes / np.float32(step)).astype(np.int64)
    sd = codec.state_dict()
    basis = pm.fixed_point_basis(sd["components"], sd["mean"], np.full(len(sd["components"]), step), TRUNC)
    v, bound = pm.exact_decode(q, basis)
    v = np.clip(v, TRUNC[0] * S, TRUNC[1] * S)
    sel = np.abs(v) < ref.tau
    truth = _blocks(vol, coords, TRUNC[1]).astype(np.float64) * S
    seen = _blocks(obs, coords, 1.0) > 0.5
    c = np.where(seen, np.rint((truth - v) / ref.step), 0) * sel
    return coords, v, sel, c, bound


def test_refined_voxels_decode_within_half_a_step_and_the_surface_improves(tmp_path, room, codec):
    """An analytic room at a coarse step: every observed voxel the refinement selects decodes within half the
    correction step (plus float32 rounding) of the exact SDF, the rest as the plain codes; the surface against the
    exact field is better than the same codes' without refinement."""
    vol, obs = room
    r = 0.002
    plain, refined = tmp_path / "plain.sdfz", tmp_path / "refined.sdfz"
    write_volume_map(plain, vol, obs, codec, codec_state="reference", variable_rate={"step": 0.6, "refine": False})
    write_volume_map(refined, vol, obs, codec, codec_state="reference",
                     variable_rate={"step": 0.6, "refine_step": r})
    a, b = sdfcodec.open_map(plain), sdfcodec.open_map(refined)
    assert "surface-refinement" in {e.name for e in b.header.extensions}
    assert b.header.codes.variable_rate.refinement.step == round(r * S)
    assert "surface-refinement" not in {e.name for e in a.header.extensions}
    assert b.info()["refinement"]["step"] == pytest.approx(r, abs=2.0 ** -24) and a.info()["refinement"] is None
    coords, v, sel, _, bound = _reference(b, codec, vol, obs)
    dec = _blocks(b.decode_region(), coords, TRUNC[1])
    truth = _blocks(vol, coords, TRUNC[1])
    seen = _blocks(obs, coords, 1.0) > 0.5
    read = b.read_observed(coords).reshape(len(coords), -1)
    at = sel & seen & read
    assert at.sum() > 5000
    # half a step, plus how far a float32 decode may lie from the exact one (the proven bound, spec 6g)
    slack = bound.max() / S + 1e-6
    assert np.abs(dec[at] - truth[at]).max() <= r / 2 + slack
    assert np.abs(dec[at] - truth[at]).mean() < 0.3 * r
    untouched = ~sel & read
    np.testing.assert_allclose(dec[untouched], np.clip(v[untouched] / S, *TRUNC), atol=slack)
    ma = compare_volumes(vol, a.decode_region(), VS, observed=obs)
    mb = compare_volumes(vol, b.decode_region(), VS, observed=obs)
    assert mb.chamfer_l1 < 0.6 * ma.chamfer_l1 and mb.f_score_1 >= ma.f_score_1, (ma, mb)
    # prefix levels ignore the refinement: level 32 of both maps reads the same codes, no corrections
    lvl_a, lvl_b = a.decode_region(level=32), b.decode_region(level=32)
    both = (_blocks(lvl_a, coords, TRUNC[1]) < TRUNC[1]) & (_blocks(lvl_b, coords, TRUNC[1]) < TRUNC[1])
    np.testing.assert_array_equal(_blocks(lvl_a, coords, 0)[both], _blocks(lvl_b, coords, 0)[both])


def test_streams_are_what_constriction_reads_and_a_numpy_reference_computes(tmp_path, room, codec):
    """Each chunk's row, decoded by constriction's own AnsCoder and Categorical under the header's law, holds the
    corrections the numpy reference computes from the true volume, block by block in C order."""
    import base64
    import zlib

    import constriction

    vol, obs = room
    p = tmp_path / "m.sdfz"
    write_volume_map(p, vol, obs, codec, codec_state="reference", chunk_blocks=2,
                     variable_rate={"step": 0.3, "refine_step": 0.004})
    m = sdfcodec.open_map(p)
    coords, v, sel, c, bound = _reference(m, codec, vol, obs)
    raw = zlib.decompress(base64.b64decode(m.header.codes.variable_rate.refinement.model))
    assert raw[:2] == b"R1"
    vals, x, shift = [], 0, 0  # LEB128 varints, decoded here by hand
    for byte in raw[2:]:
        x |= (byte & 0x7F) << shift
        shift += 7
        if not byte & 0x80:
            vals.append(x)
            x, shift = 0, 0
    mm, counts = vals[0], np.asarray(vals[1:], np.float64)
    probs = np.where(counts > 0, counts, 0.5)
    model = constriction.stream.model.Categorical(probs / probs.sum(), perfect=False)
    arr = m.reader.member("refine_streams")
    keys = np.unique(coords // 2, axis=0)
    assert len(keys) > 4
    for key in keys:
        inside = np.flatnonzero((coords // 2 == key).all(axis=1))
        inside = inside[np.lexsort(tuple(coords[inside].T[::-1]))]  # C order inside the chunk
        row = np.asarray(arr[tuple(int(k) for k in key)])
        nw = int(row[:4].view("<u4")[0])
        coder = constriction.stream.stack.AnsCoder(row[4:4 + 4 * nw].view("<u4").copy())
        want = c[inside][sel[inside]]
        got = coder.decode(model, len(want)) - mm
        np.testing.assert_array_equal(got, want)
        assert coder.is_empty()
    # the decode of many chunks, whole and by a region across chunk faces: the reference's refined values
    whole = m.decode_region()
    want = np.clip((v + c * m.header.codes.variable_rate.refinement.step) / S, *TRUNC)
    read = m.read_observed(coords).reshape(len(coords), -1)
    np.testing.assert_allclose(_blocks(whole, coords, TRUNC[1])[read], want[read], atol=bound.max() / S + 1e-6)
    box = ((20, 70), (10, 60), (5, 40))
    # float32 rounding apart (a block decoded in another batch, as decode_region documents)
    np.testing.assert_allclose(m.decode_region(box), whole[20:70, 10:60, 5:40], rtol=0, atol=1e-6)


@pytest.mark.parametrize("target", [256.0, 384.0])
def test_target_bytes_with_a_refinement_lands_within_five_percent(tmp_path, target):
    """Rate control on a synthetic fused room whose codes alone top out below the target: the map takes the
    target within 5 % (every file counted) and spends the rest on a refinement."""
    from sdfcodec.search.rooms import synthetic_room

    vol, obs = fused_like(synthetic_room(0, size=(2.2, 2.0, 1.8)).volume)
    p = tmp_path / "room.sdfz"
    write_volume_map(p, vol, obs, pretrained_codec("pca", 128), codec_state="reference",
                     variable_rate={"target_bytes": target})
    m = sdfcodec.open_map(p)
    assert m.header.codes.variable_rate.refinement is not None
    n = m.count_states()["coded"]
    got = sum(f.stat().st_size for f in p.rglob("*") if f.is_file()) / n  # every file, counted here
    assert 0.95 * target <= got <= target * 1.0005, got


def test_a_corrupted_refinement_stream_fails_with_one_line(tmp_path, room, codec):
    vol, obs = room
    p = tmp_path / "m.sdfz"
    write_volume_map(p, vol, obs, codec, codec_state="reference", manifest=False,
                     variable_rate={"step": 0.3, "refine_step": 0.004})
    chunk = next(f for f in sorted((p / "refine_streams" / "c").rglob("*")) if f.is_file())
    chunk.unlink()
    with pytest.raises(errors.FormatError, match="refine_streams"):
        sdfcodec.open_map(p).decode_region()
    from sdfcodec.map.verify import verify_map

    rep = verify_map(p)
    assert not rep.ok and any("refine_streams" in str(x) for x in rep.problems), rep.problems


def test_golden_refined_map(regen_golden):
    """The frozen refined map (a fitted pca-8, embedded): verified and decoded to its frozen values, corrections
    included."""
    from _golden_maps import check_golden_map

    vol, obs = fused_like(sample_volume(analytic_scene(), (48, 48, 32), VS, truncation=TRUNC))  # 18 blocks
    codec8 = sdfcodec.get_codec("pca", code_size=8).fit(
        split_blocks(vol, fill=0.1).reshape(-1, 16, 16, 16)[:64].astype(np.float32))

    def make(path: Path) -> None:
        write_volume_map(path, vol, obs, codec8, variable_rate={"step": 0.2, "refine_step": 0.004})

    m = check_golden_map(GOLDEN, make, regen_golden)
    ext = {e.name: e.required for e in m.header.extensions}
    assert ext["surface-refinement"] is True and ext["pinned-observation-mask"] is True


def test_conflicting_refinement_options_fail_with_one_line(codec):
    from sdfcodec.map.varrate import VariableRateWriter

    with pytest.raises(errors.InvalidValueError, match="give one"):
        VariableRateWriter(codec, target_bytes=256.0, refine_step=0.004)
    with pytest.raises(errors.InvalidValueError, match="refinement step"):
        VariableRateWriter(codec, step=0.3, refine_step=2.0)
