"""The pinned observation mask (sdfcodec.map.pinmask, stream M2): an exact integer decode decides which voxels
carry a stored bit; the bits stored there give the exact mask's surface and mesh."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

import sdfcodec
from _fused_maps import TRUNC, VS, fused_like, write_volume_map
from sdfcodec.core.blocks import split_blocks
from sdfcodec.core.sdf import sample_volume
from sdfcodec.core.surface import surface_points
from sdfcodec.errors import ChecksumError
from sdfcodec.map import pinmask as pm
from sdfcodec.map.lossymask import pinned_voxels, relax_mask
from sdfcodec.map.maskcoder import encode_mask_rows
from sdfcodec.map.observed import pack_mask
from sdfcodec.registry import pretrained_codec
from sdfcodec.testing import analytic_scene

S = 2.0 ** pm.FRACTION_BITS


@pytest.fixture(scope="module")
def codec():
    return pretrained_codec("pca", 64)


def _basis(codec, step):
    sd = codec.state_dict()
    return pm.fixed_point_basis(sd["components"], sd["mean"], np.full(len(sd["components"]), step), TRUNC)


def test_exact_decode_is_the_integer_product_and_bounds_float_decodes(codec):
    """Against int64 arithmetic (Python-exact, no floats): equal to the unit; in any summation order (reversed
    components) identical; the float32 codec decode, and a float32 product summed in another order, lie within
    the bound E of it."""
    rng = np.random.default_rng(0)
    step = 0.37
    basis = _basis(codec, step)
    q = np.zeros((50, 64), np.int64)
    for row in q:  # 10-20 non-zero codes per block, as at 64 B per block
        idx = rng.choice(64, rng.integers(10, 21), replace=False)
        row[idx] = rng.integers(-40, 41, len(idx))
    v, e = pm.exact_decode(q, basis)
    want = q @ basis[1:].astype(np.int64) + basis[0].astype(np.int64)  # int64: exact, no rounding possible
    assert np.array_equal(v.astype(np.int64), want)
    v_rev, _ = pm.exact_decode(q[:, ::-1].copy(), np.vstack([basis[:1], basis[1:][::-1]]))
    assert np.array_equal(v_rev, v)
    codes = torch.from_numpy((q * step).astype(np.float32))
    flt = codec.decode(codes).numpy().reshape(len(q), -1).astype(np.float64) * (TRUNC[1] - TRUNC[0]) + TRUNC[0]
    sd = codec.state_dict()
    alt = (((q * step).astype(np.float32)[:, ::-1] @ sd["components"][::-1]) + sd["mean"]).astype(np.float64)
    alt = alt * (TRUNC[1] - TRUNC[0]) + TRUNC[0]
    for x in (flt, alt):
        gap = np.abs(x * S - v)
        assert (gap <= e[:, None]).all()
        assert gap.max() > 0  # float32 does round: the bound is what makes the pins exact
    assert e.max() < 5e-4 * S  # and it is small: under half a millimetre, 1/40 of a voxel


def test_exact_pins_of_a_plane_by_hand():
    """A plane x = 7.5 voxels in one block, neighbours not coded (d_max): the same pins as the float rule's, by
    hand (tests/test_lossy_mask.py); a coded neighbour at -x in another chunk may take either sign, so the whole
    -x face layer is pinned, and the plane's corners stay pinned."""
    x = (np.arange(16) - 7.5) * VS
    dec = np.clip(np.broadcast_to(x[:, None, None], (16, 16, 16)), *TRUNC).reshape(1, -1)
    v = np.rint(dec * S)
    c = np.array([[3, 3, 3]])
    pin, _, _ = pm.exact_pins(c, *pm.sign_bounds(v, [1]), np.zeros((0, 3)), TRUNC)
    face = np.zeros((16, 16, 16), bool)
    face[:9, [0, 15], :] = face[:9, :, [0, 15]] = True
    want = face.copy()
    want[[0, 7, 8]] = True
    assert np.array_equal(pin[0], want)
    assert np.array_equal(pin[0], pinned_voxels(c, dec.reshape(1, 16, 16, 16).astype(np.float32), TRUNC)[0])
    pin2, _, _ = pm.exact_pins(c, *pm.sign_bounds(v, [1]), np.array([[2, 3, 3]]), TRUNC)
    assert pin2[0, 0].all() and np.array_equal(pin2[0, 1:], want[1:])


def test_canonical_bits_by_hand():
    """Two blocks side by side along x, a plane at x = 7.5 voxels in each: the first block fully observed, the
    second observed only for x <= 4 (its plane's cells are not meshed). Stored ones: the first block's plane
    corners (x = 7, 8) and its meshed cells across the shared face (its x = 15 layer meets the second block's
    negative x = 0 layer: a crossing cell, fully observed: the second block's x = 0 layer too)."""
    x = (np.arange(16) - 7.5) * VS
    dec = np.clip(np.broadcast_to(x[:, None, None], (16, 16, 16)), *TRUNC).reshape(1, -1)
    v = np.rint(np.concatenate([dec, dec]) * S)
    coords = np.array([[3, 3, 3], [4, 3, 3]])
    obs = np.ones((2, 16, 16, 16), bool)
    obs[1, 5:] = False
    signs = pm.sign_bounds(v, [1, 1])
    bits = pm.canonical_bits(coords, obs, *signs, TRUNC)
    pin, _, _ = pm.exact_pins(coords, *signs, np.zeros((0, 3)), TRUNC)
    want = np.zeros_like(obs)
    want[0, [7, 8, 15]] = True  # the plane's cells and the cells across the face to the negative x = 0 layer
    want[1, 0] = True
    assert np.array_equal(bits & pin, want & pin)
    assert not (bits & ~obs).any()  # never marks an unobserved voxel observed
    # one block, its plane's two layers unobserved at odd y: no cell of the plane is fully observed, but the
    # crossing edges x = 7 -> 8 at even y are, so their ends keep their 1 (a crossing point), nothing else does
    obs = np.ones((1, 16, 16, 16), bool)
    obs[0, 7:9, 1::2] = False
    one = pm.sign_bounds(v[:1], [1])
    bits = pm.canonical_bits(coords[:1], obs, *one, TRUNC)
    want = np.zeros_like(obs)
    want[0, 7:9, 0::2] = True
    assert np.array_equal(bits, want)
    pin, _, _ = pm.exact_pins(coords[:1], *one, np.zeros((0, 3)), TRUNC)
    field = dec.reshape(16, 16, 16).astype(np.float32)
    read = np.where(bits[0] | ~pin[0], field, np.float32(TRUNC[1]))  # what a reader decodes
    true = np.where(obs[0], field, np.float32(TRUNC[1]))
    assert len(surface_points(true, VS)) > 50
    np.testing.assert_array_equal(surface_points(read, VS), surface_points(true, VS))


def _maps(tmp_path: Path, room, codec, step: float):
    p = tmp_path / f"exact-{step}.sdfz"
    write_volume_map(p, *room, codec, codec_state="reference", variable_rate={"step": step, "exact_mask": True})
    return sdfcodec.open_map(p)


@pytest.fixture(scope="module")
def room():
    vol, obs = fused_like(sample_volume(analytic_scene(), (96, 80, 48), VS, truncation=TRUNC))
    return vol, obs


@pytest.mark.parametrize("step", [0.05, 0.6])
def test_stored_bits_round_trip_and_give_the_exact_masks_surface_and_mesh(tmp_path, room, codec, step):
    """A fused room written with the exact mask: the pins of the exact decode cover the float decode's; the M2
    stream returns the stored bits bit for bit; decoding the blocks with the M2 mask gives the exact mask's
    surface points and open3d marching-cubes triangles; and it is smaller than M1 of the lossy mask."""
    from sdfcodec.fusion.tsdf import mesh_from_blocks

    m = _maps(tmp_path, room, codec, step)
    r = m.reader
    coords, codes = r.read_codes()
    q = np.rint(codes / np.float32(step)).astype(np.int64)
    assert np.abs(q * step - codes).max() < 1e-5
    truth = m.read_observed(coords)
    v, e = pm.exact_decode(q, _basis(codec, step))
    signs = pm.sign_bounds(v, e)
    pin, _, _ = pm.exact_pins(coords, *signs, np.zeros((0, 3)), TRUNC)
    dec = codec.decode(torch.from_numpy(codes)).numpy() * (TRUNC[1] - TRUNC[0]) + TRUNC[0]
    dec = np.clip(dec, *TRUNC)
    assert not (pinned_voxels(coords, dec, TRUNC) & ~pin).any()
    bits = pm.canonical_bits(coords, truth, *signs, TRUNC)
    stream = pm.encode_pinned(coords, bits, pin)
    back = pm.decode_pinned(stream, coords, pin)
    assert np.array_equal(back[pin], bits[pin]) and back[~pin].all()
    assert (back != truth).mean() > 0.01  # a different mask ...
    grid = r.grid_blocks
    vols, meshes = [], []
    for mask in (truth, back):
        blocks = np.where(mask, dec, TRUNC[1]).astype(np.float32)
        full = np.full((*grid, 16, 16, 16), TRUNC[1], np.float32)
        full[tuple(coords.T)] = blocks
        vols.append(full.transpose(0, 3, 1, 4, 2, 5).reshape(grid[0] * 16, grid[1] * 16, grid[2] * 16))
        mesh = mesh_from_blocks(coords, blocks, origin=(0, 0, 0), voxel_size=VS, truncation=TRUNC)
        vv, t = np.asarray(mesh.vertices), np.asarray(mesh.triangles)
        meshes.append(sorted(tuple(sorted(map(tuple, vv[tri]))) for tri in t))
    assert np.array_equal(split_blocks(vols[0], fill=TRUNC[1])[tuple(coords.T)], np.where(truth, dec, TRUNC[1]))
    np.testing.assert_array_equal(surface_points(vols[0], VS), surface_points(vols[1], VS))  # ... the same surface
    assert len(meshes[0]) > 1000 and meshes[0] == meshes[1]
    m1 = encode_mask_rows(pack_mask(relax_mask(truth, pinned_voxels(coords, dec, TRUNC))))
    assert len(stream) < len(m1)


def _canonical(tmp_path, room, codec, step):
    """A room written with the exact mask at ``step``, read back: ``(map, coords, codes, truth, pin, neg, pos,
    canonical bits, decode in metres clipped)``."""
    m = _maps(tmp_path, room, codec, step)
    coords, codes = m.reader.read_codes()
    q = np.rint(codes / np.float32(step)).astype(np.int64)
    truth = m.read_observed(coords)
    signs = pm.sign_bounds(*pm.exact_decode(q, _basis(codec, step)))
    pin, neg, pos = pm.exact_pins(coords, *signs, np.zeros((0, 3)), TRUNC)
    bits = pm.canonical_bits(coords, truth, *signs, TRUNC)
    dec = np.clip(codec.decode(torch.from_numpy(codes)).numpy() * (TRUNC[1] - TRUNC[0]) + TRUNC[0], *TRUNC)
    return m, coords, truth, pin, neg, pos, bits, dec


def _surfaces(coords, dec, grid, masks):
    """Per mask ``(n, 16, 16, 16)`` bool: the surface points of the blocks ``dec`` with unobserved voxels at
    ``d_max`` and the open3d marching-cubes triangles (sorted vertex triples)."""
    from sdfcodec.fusion.tsdf import mesh_from_blocks

    out = []
    for mask in masks:
        blocks = np.where(mask, dec, TRUNC[1]).astype(np.float32)
        full = np.full((*grid, 16, 16, 16), TRUNC[1], np.float32)
        full[tuple(coords.T)] = blocks
        pts = surface_points(full.transpose(0, 3, 1, 4, 2, 5).reshape(*(g * 16 for g in grid)), VS)
        mesh = mesh_from_blocks(coords, blocks, origin=(0, 0, 0), voxel_size=VS, truncation=TRUNC)
        vv, t = np.asarray(mesh.vertices), np.asarray(mesh.triangles)
        out.append((pts, sorted(tuple(sorted(map(tuple, vv[tri]))) for tri in t)))
    return out


def test_cheapest_bits_are_shorter_and_keep_the_exact_masks_surface_and_mesh(tmp_path, room, codec):
    """The writer's choice of the free bits (truly observed voxels the canonical bits leave 0): set to what the
    coder's adaptive model finds more probable. They change only free voxels, the stream is shorter than the
    canonical bits', and decoding with them gives the true mask's surface points and open3d triangles."""
    m, coords, truth, pin, _, _, bits, dec = _canonical(tmp_path, room, codec, 0.6)
    free = truth & ~bits
    cheap = pm.cheapest_bits(coords, bits, free, pin)
    changed = (cheap != bits) & pin
    assert changed.any() and not (changed & ~free).any()
    short, long = pm.encode_pinned(coords, cheap, pin), pm.encode_pinned(coords, bits, pin)
    assert len(short) < len(long)
    back = pm.decode_pinned(short, coords, pin)
    assert np.array_equal(back[pin], cheap[pin])
    (p0, m0), (p1, m1) = _surfaces(coords, dec, m.reader.grid_blocks, (truth, back))
    np.testing.assert_array_equal(p0, p1)
    assert len(m0) > 1000 and m0 == m1


def test_chosen_bits_set_unobserved_pins_yet_keep_the_exact_masks_surface_and_mesh(tmp_path, room, codec):
    """The writer's choice of every pinned bit the canonical bits leave 0, truly unobserved ones included: only
    such voxels change (0 -> 1), unobserved ones among them; the stream is shorter than with only the observed
    ones chosen (cheapest_bits, where it starts); decoding it gives the true mask's surface points and open3d triangles, while
    setting, unchecked, the unobserved pinned voxels it left 0 beside an observed 1 changes the mesh (the check
    is what keeps it)."""
    # coarse codes, as at 64 B per block: spurious sign changes where the room is not observed
    m, coords, truth, pin, neg, pos, bits, dec = _canonical(tmp_path, room, codec, 2.5)
    start = pm.cheapest_bits(coords, bits, truth & ~bits, pin)  # as the writer does
    chosen = pm.chosen_bits(coords, bits, pin, neg, pos, np.zeros((0, 3)), TRUNC, start=start)
    changed = chosen != bits
    assert not (changed & (~pin | bits)).any()  # only pinned zeros, and only to 1
    assert (changed & ~truth).any() and (changed & truth).any()
    short = pm.encode_pinned(coords, chosen, pin)
    assert len(short) < len(pm.encode_pinned(coords, start, pin))
    back = pm.decode_pinned(short, coords, pin)
    assert np.array_equal(back[pin], chosen[pin])
    # unchecked: the unobserved pinned voxels the choice left 0 beside a meshed cell's corner, all set
    meshed = back & pin & truth
    beside = np.zeros_like(meshed)
    for ax in (1, 2, 3):
        beside |= np.roll(meshed, 1, axis=ax) | np.roll(meshed, -1, axis=ax)
    blind = back | (pin & ~back & beside)
    (p0, m0), (p1, m1), (_, m2) = _surfaces(coords, dec, m.reader.grid_blocks, (truth, back, blind))
    np.testing.assert_array_equal(p0, p1)
    assert len(m0) > 1000 and m0 == m1
    assert m2 != m0


def test_a_corrupted_or_mismatched_stream_fails_with_one_line():
    rng = np.random.default_rng(1)
    pin = rng.random((3, 16, 16, 16)) < 0.2
    bits = rng.random((3, 16, 16, 16)) < 0.3
    coords = np.array([[0, 0, 0], [0, 0, 1], [3, 1, 2]])  # two blocks face to face, one apart
    stream = pm.encode_pinned(coords, bits, pin)
    assert np.array_equal(pm.decode_pinned(stream, coords, pin)[pin], bits[pin])
    with pytest.raises(ChecksumError, match="not an M2 stream"):
        pm.decode_pinned(b"M1" + stream[2:], coords, pin)
    with pytest.raises(ChecksumError, match="not an M2 stream"):
        pm.decode_pinned(stream[:-1], coords, pin)
    other = pin.copy()
    other[0, 0, 0, 0] = ~other[0, 0, 0, 0]
    with pytest.raises(ChecksumError, match="pinned voxels"):  # a reader whose codes pin differently
        pm.decode_pinned(stream, coords, other)
    with pytest.raises(ChecksumError):
        pm.decode_pinned(stream[:-8], coords, pin)  # words missing: exhausted, or left over in the wrong place
    bad = bytearray(stream)
    bad[len(bad) // 2] ^= 0xFF
    try:
        got = pm.decode_pinned(bytes(bad), coords, pin)
    except ChecksumError:
        pass
    else:  # an ANS stream with a flipped word may still decode; then it decodes other bits (the CRC guards it)
        assert not np.array_equal(got[pin], bits[pin])


def _mesh(coords, blocks):
    from sdfcodec.fusion.tsdf import mesh_from_blocks

    mesh = mesh_from_blocks(coords, blocks, origin=(0, 0, 0), voxel_size=VS, truncation=TRUNC)
    v, t = np.asarray(mesh.vertices), np.asarray(mesh.triangles)
    return sorted(tuple(sorted(map(tuple, v[tri]))) for tri in t)


def test_a_pinned_map_reads_the_exact_masks_surface_and_is_smaller(tmp_path, room, codec):
    """Three maps of the fused room, the same codes (a fixed step): exact mask, M1 lossy mask, pinned mask (the
    default). The pinned map lists pinned-observation-mask (required) and no observed array, verifies, decodes to
    the exact map's surface points and open3d mesh, reads a mask that differs from the truth, takes fewer mask
    bytes than the M1 lossy map, and `info` says how its mask is stored."""
    from typer.testing import CliRunner

    from sdfcodec.cli import app
    from sdfcodec.map.verify import verify_map

    maps = {}
    for name, extra in (("exact", {"exact_mask": True}), ("m1", {"pinned_mask": False}), ("pinned", {})):
        p = tmp_path / f"{name}.sdfz"
        write_volume_map(p, *room, codec, codec_state="reference", variable_rate={"step": 0.3, **extra})
        maps[name] = sdfcodec.open_map(p)
    pinned = maps["pinned"]
    ext = {e.name: e.required for e in pinned.header.extensions}
    assert ext["pinned-observation-mask"] is True and ext["approximate-observation-mask"] is False
    assert "observation-mask" not in ext and "coded-observation-mask" not in ext
    root = Path(pinned.reader.local_root())
    assert not (root / "observed").exists() and (root / "mask_streams").is_dir()
    assert verify_map(root).ok
    coords = np.argwhere(pinned.block_states() == 2)
    truth = maps["exact"].read_observed(coords)
    assert (pinned.read_observed(coords) != truth).mean() > 0.01
    a, b = maps["exact"].decode_region(), pinned.decode_region()
    np.testing.assert_array_equal(surface_points(a, VS), surface_points(b, VS))
    ma = _mesh(coords, split_blocks(a, fill=TRUNC[1])[tuple(coords.T)])
    assert len(ma) > 1000 and ma == _mesh(coords, split_blocks(b, fill=TRUNC[1])[tuple(coords.T)])

    def mask_bytes(m, sub):
        return sum(f.stat().st_size for f in (Path(m.reader.local_root()) / sub).rglob("*") if f.is_file())

    assert mask_bytes(pinned, "mask_streams") < mask_bytes(maps["m1"], "observed")
    out = CliRunner().invoke(app, ["info", str(root)])
    assert out.exit_code == 0 and "pinned-observation-mask" in out.output, out.output
    copy = tmp_path / "copy.sdfz"  # a fixed-rate transcode stores the mask the pinned map reads, as 6b rows
    with sdfcodec.create_map(copy, codec=codec, voxel_size=VS, truncation=TRUNC, shape_voxels=pinned.shape_voxels,
                             codec_state="reference") as m:
        m.write_map(pinned)
    copied = sdfcodec.open_map(copy)
    assert "approximate-observation-mask" in [e.name for e in copied.header.extensions]
    assert np.array_equal(copied.read_observed(coords), pinned.read_observed(coords))


def test_the_known_voxels_are_where_the_mask_is_stored_and_a_search_scores_only_observed_ones(tmp_path, room, codec):
    """read_observation of a pinned map: every voxel outside what it knows reads observed (the format's rule,
    whatever the cameras saw), what it knows holds every corner of every 2^3 cell whose float decode changes sign
    (numpy, from the codes), and where it says observed the exact mask does too. A search scores, in blocks with
    an unobserved pin, only voxels the exact mask observed (read_observed alone gives it thousands it did not)."""
    from sdfcodec.map.observed import read_observation
    from sdfcodec.search.scoring import scored_voxels

    maps = {}
    for name, extra in (("exact", {"exact_mask": True}), ("pinned", {})):
        p = tmp_path / f"{name}.sdfz"
        write_volume_map(p, *room, codec, codec_state="reference", variable_rate={"step": 0.3, **extra})
        maps[name] = sdfcodec.open_map(p)
    pinned = maps["pinned"]
    coords = np.argwhere(pinned.block_states() == 2)
    truth = maps["exact"].read_observed(coords)
    assert read_observation(maps["exact"].reader, coords)[1] is None  # an exact mask knows every voxel
    obs, known = read_observation(pinned.reader, coords)
    assert np.array_equal(obs, pinned.read_observed(coords))
    assert obs[~known].all() and not (obs & known & ~truth).any()
    c, z = pinned.read_codes()
    assert np.array_equal(c, coords)  # both in C order
    v = np.asarray(pinned.codec.decode(torch.from_numpy(np.ascontiguousarray(z, np.float32)))).reshape(-1, 16, 16, 16)
    neg = v < (0 - TRUNC[0]) / (TRUNC[1] - TRUNC[0])  # normalised decode below the surface
    cells = [neg[:, a:a + 15, b:b + 15, d:d + 15] for a in (0, 1) for b in (0, 1) for d in (0, 1)]
    crossing = np.any(cells, axis=0) & ~np.all(cells, axis=0)
    corners = np.zeros_like(neg)
    for a in (0, 1):
        for b in (0, 1):
            for d in (0, 1):
                corners[:, a:a + 15, b:b + 15, d:d + 15] |= crossing
    assert corners.sum() > 10000 and not (corners & ~known).any()
    hidden = (known & ~obs).reshape(len(coords), -1).any(axis=1)
    assert hidden.sum() > 10 and (obs & ~truth)[hidden].sum() > 1000
    assert not (scored_voxels(pinned, coords) & ~truth)[hidden].any()


def test_a_reader_without_the_extension_refuses_and_a_flipped_byte_is_caught(tmp_path, room, codec, monkeypatch):
    from sdfcodec import errors
    from sdfcodec.core import header

    p = tmp_path / "pinned.sdfz"
    write_volume_map(p, *room, codec, codec_state="reference", variable_rate={"step": 0.3}, manifest=False)
    chunk = next(f for f in (p / "mask_streams").rglob("*") if f.is_file() and f.name != "zarr.json")
    raw = bytearray(chunk.read_bytes())
    raw[len(raw) // 2] ^= 0x10
    chunk.write_bytes(bytes(raw))
    with pytest.raises(errors.ChecksumError, match="mask_streams"):
        sdfcodec.open_map(p).decode_region()
    with pytest.raises(errors.ChecksumError, match="mask_streams"):  # its row read during the float decode
        list(sdfcodec.open_map(p).iter_decoded())
    monkeypatch.setattr(header, "KNOWN_EXTENSIONS", header.KNOWN_EXTENSIONS - {"pinned-observation-mask"})
    with pytest.raises(errors.SDFCodecError, match="pinned-observation-mask"):
        sdfcodec.open_map(p)


GOLDEN = Path(__file__).parent / "golden" / "maps" / "pinned-mask-pca-8"


def test_golden_pinned_mask_map(regen_golden):
    """The frozen pinned-mask map (a fitted pca-8, embedded): verified and decoded to its frozen values, and its
    surface is the one the true mask gives with the same codes."""
    from _golden_maps import check_golden_map, check_true_mask_surface

    vol, obs = fused_like(sample_volume(analytic_scene(), (48, 48, 32), VS, truncation=TRUNC))  # 18 blocks
    codec8 = sdfcodec.get_codec("pca", code_size=8).fit(
        split_blocks(vol, fill=0.1).reshape(-1, 16, 16, 16)[:64].astype(np.float32))

    def make(path: Path) -> None:
        write_volume_map(path, vol, obs, codec8, variable_rate={"step": 0.2})

    m = check_golden_map(GOLDEN, make, regen_golden)
    ext = {e.name: e.required for e in m.header.extensions}
    assert ext["pinned-observation-mask"] is True and "observation-mask" not in ext
    check_true_mask_surface(m, obs)


def test_chunks_decode_alone_and_agree_across_their_faces(tmp_path, room, codec):
    """Chunks of 2^3 blocks (18 on the room, 6 x 5 x 3 blocks): each stream decodes from its own codes, coded neighbours in
    other chunks counted as either sign; the surface and mesh are still the exact mask's, and a fresh reader of
    one block reads the same mask there as the whole map's read (and values equal but for the float rounding
    that makes an exact decode necessary)."""
    maps = {}
    for name, extra in (("exact", {"exact_mask": True}), ("pinned", {})):
        p = tmp_path / f"{name}.sdfz"
        write_volume_map(p, *room, codec, codec_state="reference", chunk_blocks=2,
                         variable_rate={"step": 0.3, **extra})
        maps[name] = sdfcodec.open_map(p)
    pinned = maps["pinned"]
    assert len([f for f in (Path(pinned.reader.local_root()) / "mask_streams").rglob("*") if f.is_file()]) > 12
    coords = np.argwhere(pinned.block_states() == 2)
    a, b = maps["exact"].decode_region(), pinned.decode_region()
    np.testing.assert_array_equal(surface_points(a, VS), surface_points(b, VS))
    assert _mesh(coords, split_blocks(a, fill=TRUNC[1])[tuple(coords.T)]) == _mesh(
        coords, split_blocks(b, fill=TRUNC[1])[tuple(coords.T)])
    i = len(coords) // 2
    box = tuple(slice(int(x) * 16, int(x) * 16 + 16) for x in coords[i])
    fresh = sdfcodec.open_map(Path(pinned.reader.local_root()))
    assert np.array_equal(fresh.read_observed(coords[i:i + 1])[0], pinned.read_observed(coords)[i])
    np.testing.assert_allclose(fresh.decode_region(box), b[box], atol=1e-6)  # BLAS rounds by batch: 2e-8


def test_a_truncation_below_the_jump_pins_all_negative_cells_too(tmp_path, codec):
    """d_max 0.06 m < the crossing rule's jump (0.1 m): a d_max corner next to a negative one would count as a
    crossing, so every cell that may be negative is relevant; surface points and mesh still equal the exact
    mask's."""
    trunc = (-0.04, 0.06)
    vol = sample_volume(analytic_scene(), (96, 80, 48), VS, truncation=trunc)
    observed = vol > trunc[0] + 1e-6
    vol = np.where(observed, vol, np.float32(trunc[1])).astype(np.float32)
    blocks = split_blocks(vol, fill=trunc[1]).reshape(-1, 16, 16, 16)
    obs = split_blocks(observed.astype(np.float32), fill=1.0).reshape(-1, 16, 16, 16) > 0.5
    coords = np.argwhere(np.ones(split_blocks(vol, fill=trunc[1]).shape[:3], bool))
    decoded = {}
    for name, extra in (("exact", {"exact_mask": True}), ("pinned", {})):
        p = tmp_path / f"{name}.sdfz"
        with sdfcodec.create_map(p, codec=codec, voxel_size=VS, truncation=trunc, shape_voxels=vol.shape,
                                 codec_state="reference", variable_rate={"step": 0.3, **extra}) as m:
            m.write_blocks(coords, blocks, observed=obs)
        decoded[name] = sdfcodec.open_map(p)
    assert "pinned-observation-mask" in [e.name for e in decoded["pinned"].header.extensions]
    a, b = (decoded[k].decode_region() for k in ("exact", "pinned"))
    assert not np.array_equal(a, b)
    np.testing.assert_array_equal(surface_points(a, VS), surface_points(b, VS))
    c = np.argwhere(decoded["pinned"].block_states() == 2)
    from sdfcodec.fusion.tsdf import mesh_from_blocks

    meshes = []
    for v in (a, b):
        mesh = mesh_from_blocks(c, split_blocks(v, fill=trunc[1])[tuple(c.T)], origin=(0, 0, 0), voxel_size=VS,
                                truncation=trunc)
        vv, t = np.asarray(mesh.vertices), np.asarray(mesh.triangles)
        meshes.append(sorted(tuple(sorted(map(tuple, vv[tri]))) for tri in t))
    assert len(meshes[0]) > 1000 and meshes[0] == meshes[1]


def test_the_golden_pinned_map_verifies_and_decodes_over_http():
    """Over HTTP (a store that cannot list: verify asks for the streams' chunks by position) the golden map
    verifies and decodes to the same values as from disk."""
    import functools
    import http.server
    import threading

    from sdfcodec.map.verify import verify_map

    class Quiet(http.server.SimpleHTTPRequestHandler):
        def log_message(self, *args) -> None:
            pass

    srv = http.server.ThreadingHTTPServer(("127.0.0.1", 0), functools.partial(Quiet, directory=str(GOLDEN)))
    threading.Thread(target=srv.serve_forever, daemon=True).start()
    try:
        url = f"http://127.0.0.1:{srv.server_address[1]}/map.zarr"
        rep = verify_map(url)
        assert rep.ok, rep.problems
        np.testing.assert_array_equal(sdfcodec.open_map(url).decode_region(),
                                      sdfcodec.open_map(GOLDEN / "map.zarr").decode_region())
    finally:
        srv.shutdown()
