"""The observation mask exact only where it decides the surface (sdfcodec/map/lossymask.py, spec section 6f)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import sdfcodec
from _fused_maps import TRUNC, VS, fused_like, write_volume_map
from _golden_maps import check_golden_map, check_true_mask_surface
from sdfcodec.core.blocks import split_blocks
from sdfcodec.core.sdf import sample_volume
from sdfcodec.core.surface import compare_volumes, surface_points
from sdfcodec.map.lossymask import pinned_voxels, relax_mask
from sdfcodec.registry import pretrained_codec
from sdfcodec.testing import analytic_scene

GOLDEN = Path(__file__).parent / "golden" / "maps" / "lossy-mask-pca-8"


@pytest.fixture(scope="module")
def room():
    vol, obs = fused_like(sample_volume(analytic_scene(), (96, 80, 48), VS, truncation=TRUNC))
    assert 0.05 < (~obs).mean() < 0.5
    return vol, obs


def test_pinned_voxels_of_a_plane_are_the_corners_of_its_crossing_cells():
    """A plane x = 7.5 voxels in one block with no coded neighbour (they read d_max): the cells that change sign
    are those between x = 7 and 8 and those between an empty neighbour (d_max) and the block's negative side
    (x <= 7): across the -x face, and across the four y and z faces next to a voxel with x <= 7. The pinned
    voxels are their corners, by hand: x in {0, 7, 8}, and the y/z face voxels with x <= 8."""
    x = (np.arange(16) - 7.5) * VS
    dec = np.clip(np.broadcast_to(x[:, None, None], (16, 16, 16)), *TRUNC).astype(np.float32)[None]
    pin = pinned_voxels(np.array([[3, 3, 3]]), dec, TRUNC)
    face = np.zeros((16, 16, 16), bool)
    face[:9, [0, 15], :] = face[:9, :, [0, 15]] = True
    want = face.copy()
    want[[0, 7, 8]] = True
    assert np.array_equal(pin[0], want)
    # a coded neighbour at -x, as negative as the block's first layer, lends its values instead of d_max
    pin2 = pinned_voxels(np.array([[3, 3, 3], [2, 3, 3]]), np.concatenate([dec, np.full_like(dec, TRUNC[0])]), TRUNC)
    want = face.copy()
    want[[7, 8]] = True
    assert np.array_equal(pin2[0], want)


def test_relax_mask_keeps_pinned_bits_and_fills_sub_cubes_by_hand():
    obs = np.zeros((1, 16, 16, 16), bool)
    obs[0, :2, :2, :2] = [[[1, 0], [1, 1]], [[0, 1], [1, 0]]]  # a mixed sub-cube, 5 of 8 observed
    pin = np.zeros_like(obs)
    pin[0, 15, 15, 15] = True  # an unobserved pinned voxel far away: the block is not made fully observed
    got = relax_mask(obs, pin)  # sub-cubes without pinned voxels take the majority of their true bits
    assert got[0, :2, :2, :2].all() and not got[0, 2:].any() and not got[0, :, 2:].any()
    obs[0, 0, 1, 0] = False  # 4 of 8: a tie reads observed
    assert relax_mask(obs, pin)[0, :2, :2, :2].all()
    obs[0, 0, 1, 1] = False  # 3 of 8: unobserved
    assert not relax_mask(obs, pin)[0, :2, :2, :2].any()
    pin[0, 0, 0, 0] = pin[0, 0, 0, 1] = True  # pinned bits disagree (1, 0): the free voxels keep the truth
    assert np.array_equal(relax_mask(obs, pin)[0, :2, :2, :2], obs[0, :2, :2, :2])
    pin[0, 0, 0, 0] = False  # one pinned voxel there, unobserved: its sub-cube becomes unobserved
    assert not relax_mask(obs, pin)[0, :2, :2, :2].any()
    pin[0] = False
    pin[0, 0, 0, 0] = True  # the block's only pinned voxel is observed: observed everywhere (a row of 255)
    assert relax_mask(obs, pin).all()
    assert relax_mask(obs, np.zeros_like(pin)).all()  # nothing pinned: the same
    assert np.array_equal(relax_mask(obs, np.ones_like(pin)), obs)  # everything pinned: the truth


def _pair(tmp_path: Path, room, codec, step: float) -> tuple[sdfcodec.Map, sdfcodec.Map]:
    maps = []
    for exact in (True, False):
        p = tmp_path / f"exact{exact}.sdfz"
        write_volume_map(p, *room, codec, codec_state="reference",
                         variable_rate={"step": step, "exact_mask": exact, "pinned_mask": False})
        maps.append(sdfcodec.open_map(p))
    return maps[0], maps[1]


@pytest.mark.parametrize("step", [0.05, 0.6])
def test_lossy_mask_gives_the_exact_masks_surface_and_mesh(tmp_path, room, step):
    """Same codes (a fixed step), the two masks: the masks differ and the lossy one is smaller, yet the surface
    points (every zero crossing of the dense decode) and open3d's marching-cubes mesh of the decoded blocks are
    identical, bit for bit (triangle corners), and so are F-score and Chamfer distance against the input."""
    from sdfcodec.fusion.tsdf import mesh_from_blocks

    exact, lossy = _pair(tmp_path, room, pretrained_codec("pca", 64), step)
    names = [e.name for e in lossy.header.extensions]
    assert "approximate-observation-mask" in names
    assert "approximate-observation-mask" not in [e.name for e in exact.header.extensions]
    coords = np.argwhere(exact.block_states() == 2)
    m_exact, m_lossy = exact.read_observed(coords), lossy.read_observed(coords)
    assert (m_exact != m_lossy).mean() > 0.01
    size = {m: sum(f.stat().st_size for f in (Path(m.reader.local_root()) / "observed").rglob("*") if f.is_file())
            for m in (exact, lossy)}
    assert size[lossy] < 0.9 * size[exact], size
    a, b = exact.decode_region(), lossy.decode_region()
    assert not np.array_equal(a, b)  # voxels far from the surface read differently
    np.testing.assert_array_equal(surface_points(a, VS), surface_points(b, VS))
    meshes = []
    for vol in (a, b):
        blocks = split_blocks(vol, fill=TRUNC[1])[tuple(coords.T)]
        mesh = mesh_from_blocks(coords, blocks, origin=(0, 0, 0), voxel_size=VS, truncation=TRUNC)
        v, t = np.asarray(mesh.vertices), np.asarray(mesh.triangles)
        # open3d lists vertices in a thread-dependent order: compare the triangles as sets of corner positions
        meshes.append(sorted(tuple(sorted(map(tuple, v[tri]))) for tri in t))
    assert len(meshes[0]) > 1000
    assert meshes[0] == meshes[1]
    vol = room[0]
    ra, rb = (compare_volumes(vol, v, VS) for v in (a, b))
    assert (ra.chamfer_l1, ra.f_score_1) == (rb.chamfer_l1, rb.f_score_1)


def test_rate_control_spends_what_the_mask_saves_on_the_codes(tmp_path, room):
    """At the same byte target the lossy mask leaves more bytes to the codes: a finer step, a better surface."""
    reports = {}
    for exact in (True, False):
        p = tmp_path / f"t{exact}.sdfz"
        write_volume_map(p, *room, pretrained_codec("pca", 64), codec_state="reference",
                         variable_rate={"target_bytes": 110.0, "exact_mask": exact})
        from sdfcodec.map.rate import stored_bytes
        got = stored_bytes(p)
        assert 110.0 * 0.95 <= got["total"] <= 110.0, got
        reports[exact] = got
    saved = reports[True]["mask"] - reports[False]["mask"]
    # most of it goes to the codes (the rest: the header's extension entry and the model, on 70 coded blocks)
    assert saved > 3 and reports[False]["codes"] - reports[True]["codes"] > 0.5 * saved, reports


def test_golden_lossy_mask_map(regen_golden):
    vol, obs = fused_like(sample_volume(analytic_scene(), (48, 48, 32), VS, truncation=TRUNC))  # 18 blocks
    codec = sdfcodec.get_codec("pca", code_size=8).fit(
        split_blocks(vol, fill=0.1).reshape(-1, 16, 16, 16)[:64].astype(np.float32))

    def make(path: Path) -> None:
        write_volume_map(path, vol, obs, codec, variable_rate={"step": 0.2, "pinned_mask": False})

    m = check_golden_map(GOLDEN, make, regen_golden)
    ext = {e.name: e.required for e in m.header.extensions}
    assert ext["approximate-observation-mask"] is False and ext["coded-observation-mask"] is True
    check_true_mask_surface(m, obs)  # the frozen surface is the one the exact mask gives with the same codes


def test_info_and_a_transcode_say_the_mask_is_approximate(tmp_path, room):
    from typer.testing import CliRunner

    from sdfcodec.cli import app

    exact, lossy = _pair(tmp_path, room, pretrained_codec("pca", 16), 0.3)
    out = CliRunner().invoke(app, ["info", lossy.reader.local_root()])
    assert out.exit_code == 0 and "exact only where it decides the surface" in out.output, out.output
    out = CliRunner().invoke(app, ["info", exact.reader.local_root()])
    assert out.exit_code == 0 and "exact only where" not in out.output, out.output
    for src, want in ((lossy, True), (exact, False)):  # a fixed-rate copy keeps what its source's mask is
        p = tmp_path / f"copy{want}.sdfz"
        with sdfcodec.create_map(p, codec=pretrained_codec("pca", 16), voxel_size=VS, truncation=TRUNC,
                                 shape_voxels=src.shape_voxels, codec_state="reference") as m:
            m.write_map(src)
        copy = sdfcodec.open_map(p)
        assert ("approximate-observation-mask" in [e.name for e in copy.header.extensions]) is want
        coords = np.argwhere(copy.block_states() == 2)
        assert np.array_equal(copy.read_observed(coords), src.read_observed(coords))


def test_pins_in_batches_equal_the_whole_maps():
    """Batches of 5 blocks, each decoded with its coded neighbours, pin exactly what one pass over all does."""
    from sdfcodec.map.lossymask import pinned_in_batches

    vol, _ = fused_like(sample_volume(analytic_scene(), (64, 64, 48), VS, truncation=TRUNC))
    blocks = split_blocks(vol, fill=TRUNC[1])
    coords = np.argwhere((blocks < 0).reshape(*blocks.shape[:3], -1).any(axis=3))  # blocks with a surface
    dec = blocks[tuple(coords.T)] + np.float32(0.004)  # a decode that moves the surface a little
    whole = pinned_voxels(coords, dec, TRUNC)
    assert 0.05 < whole.mean() < 0.9
    np.testing.assert_array_equal(pinned_in_batches(coords, lambda idx: dec[idx], TRUNC, batch=5), whole)
