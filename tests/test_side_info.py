"""What a map stores beside its codes (issue 42, item 3): fusion weights dropped from lossy maps unless kept,
then quantised to uint8 counts (spec section 6a, sdfcodec.map.weights); the observation mask (6b) kept exactly."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import zarr
from typer.testing import CliRunner

import sdfcodec
from sdfcodec.core.blocks import split_blocks
from sdfcodec.cli import app
from sdfcodec.map.weights import QUANT_WEIGHTS_EXTENSION, WEIGHTS_EXTENSION, quantise_weights
from sdfcodec.core.sdf import Sphere, sample_volume
from sdfcodec.map.verify import verify_map

VS, TRUNC = 0.02, (-0.04, 0.1)


def run(*args):
    return CliRunner().invoke(app, [str(a) for a in args])


def test_quantised_weights_follow_their_stated_rule():
    # hand-computed: 0 stays 0 (unobserved), anything observed reads at least 1, rounding half to even below,
    # saturating at 255 above
    w = np.array([0, 0.2, 0.5, 0.7, 1.4, 2.5, 3.5, 254.6, 255.4, 300, 1e4], np.float32)
    np.testing.assert_array_equal(quantise_weights(w), [0, 1, 1, 1, 1, 2, 4, 255, 255, 255, 255])
    rng = np.random.default_rng(0)
    w = np.where(rng.random(20000) < 0.3, 0, rng.uniform(0, 400, 20000)).astype(np.float32)
    q = quantise_weights(w).astype(np.float32)
    inside = (w >= 0.5) & (w <= 255.5)
    assert np.abs(q - w)[inside].max() <= 0.5  # within half a step (1 count) where the levels reach
    np.testing.assert_array_equal(q > 0, w > 0)  # the observation survives bit for bit


@pytest.fixture(scope="module")
def fused(tmp_path_factory):
    """A sphere fused-like: voxels deeper than |d_min| behind the surface unobserved (weight 0), integer weights
    0-299 elsewhere (some above 255), written to a raw map with its weights."""
    vol = sample_volume(Sphere((0.32, 0.32, 0.32), 0.2), (48, 48, 48), VS, truncation=TRUNC)
    rng = np.random.default_rng(3)
    weights = np.where(vol > TRUNC[0] + 1e-6, rng.integers(1, 300, vol.shape), 0).astype(np.float32)
    vol = np.where(weights > 0, vol, TRUNC[1]).astype(np.float32)
    blocks, wb = split_blocks(vol, TRUNC[1]), split_blocks(weights, 0.0)
    coords = np.argwhere(np.ones(blocks.shape[:3], bool))
    path = tmp_path_factory.mktemp("fused") / "raw.sdfz"
    with sdfcodec.create_map(path, codec=sdfcodec.get_codec("raw"), voxel_size=VS, truncation=TRUNC) as m:
        m.write_blocks(coords, blocks[tuple(coords.T)], weights=wb[tuple(coords.T)])
    return path, coords, wb[tuple(coords.T)]


def _names(m):
    """The map's extensions but the integrity manifest (every map the writer makes has it; spec 9b)."""
    return [e.name for e in m.header.extensions if e.name != "integrity-manifest"]


def test_lossy_map_drops_weights_by_default_and_keeps_them_quantised_when_asked(fused, tmp_path):
    raw_path, coords, weights = fused
    raw = sdfcodec.open_map(raw_path)
    assert _names(raw) == [WEIGHTS_EXTENSION, "observation-mask"]  # lossless raw keeps float16, as before
    np.testing.assert_array_equal(raw.read_weights(coords), weights)
    codec = sdfcodec.pretrained_codec("pca", 32)
    blocks = np.concatenate([b for _, b in raw.iter_blocks()])
    order = np.concatenate([c for c, _ in raw.iter_blocks()])
    w_of = {tuple(c): w for c, w in zip(coords.tolist(), weights)}
    w_ordered = np.stack([w_of[tuple(c)] for c in order.tolist()])
    for keep, path in ((None, tmp_path / "drop.sdfz"), (True, tmp_path / "keep.sdfz")):
        with sdfcodec.create_map(path, codec=codec, voxel_size=VS, truncation=TRUNC, keep_weights=keep) as m:
            m.write_blocks(order, blocks, weights=w_ordered)
    drop, keep = sdfcodec.open_map(tmp_path / "drop.sdfz"), sdfcodec.open_map(tmp_path / "keep.sdfz")
    assert not drop.has_weights and _names(drop) == ["observation-mask"]
    assert not (tmp_path / "drop.sdfz" / "weights").exists()
    assert keep.has_weights and QUANT_WEIGHTS_EXTENSION in _names(keep) and WEIGHTS_EXTENSION not in _names(keep)
    assert zarr.open_group(tmp_path / "keep.sdfz", mode="r")["weights"].dtype == np.uint8
    # integer counts: exact up to 255, 255 above (the rule, computed independently here)
    np.testing.assert_array_equal(keep.read_weights(order), np.minimum(w_ordered, 255))
    # both know exactly which voxels were observed, and decode alike: the weights never change a decode
    for m in (drop, keep):
        np.testing.assert_array_equal(m.read_observed(order), w_ordered > 0)
    np.testing.assert_array_equal(drop.decode_region(), keep.decode_region())
    assert verify_map(tmp_path / "keep.sdfz").ok


def test_transcode_keeps_weights_only_when_asked(fused, tmp_path):
    raw_path, coords, weights = fused
    assert run("encode", raw_path, tmp_path / "a.sdfz", "--code-size", 32).exit_code == 0
    r = run("encode", raw_path, tmp_path / "b.sdfz", "--code-size", 32, "--keep-weights")
    assert r.exit_code == 0, r.output
    a, b = sdfcodec.open_map(tmp_path / "a.sdfz"), sdfcodec.open_map(tmp_path / "b.sdfz")
    assert not a.has_weights and a.records_observation
    np.testing.assert_array_equal(b.read_weights(coords), np.minimum(weights, 255))
    # a volume has no weights to keep: one line, no traceback
    np.save(tmp_path / "v.npy", np.full((16, 16, 16), 0.1, np.float32))
    r = run("encode", tmp_path / "v.npy", tmp_path / "c.sdfz", "--voxel-size", VS, "--keep-weights")
    assert r.exit_code != 0 and "--keep-weights" in r.output and "Traceback" not in r.output


def test_old_readers_ignore_quantised_weights(fused, tmp_path):
    """The extension is optional: a reader that knows only the format before it (fusion-weights, float16) opens
    the map and reads its mask. Simulated by listing the weights under an extension name nobody knows."""
    raw_path, coords, weights = fused
    path = tmp_path / "k.sdfz"
    assert run("encode", raw_path, path, "--code-size", 32, "--keep-weights").exit_code == 0
    g = zarr.open_group(path, mode="r+")
    h = dict(g.attrs["sdfcodec"])
    h["extensions"] = [dict(e, name="some-later-weights") if e["name"] == QUANT_WEIGHTS_EXTENSION else e
                       for e in h["extensions"]]
    g.attrs["sdfcodec"] = h
    m = sdfcodec.open_map(path)
    assert not m.has_weights
    np.testing.assert_array_equal(m.read_observed(coords), weights > 0)


def test_a_map_without_weights_tracks_and_searches_as_one_with_them(tmp_path):
    """`fuse --codec pca` now writes no weights by default: tracking and search on that map give exactly what
    they give on the same map fused with --keep-weights (weights never enter a decode)."""
    from sdfcodec.data.render import render_sequence
    from sdfcodec.data.sequences import Intrinsics
    from sdfcodec.core.metrics import read_tum

    seq = render_sequence(tmp_path / "seq", "slow-clean", frames=6,
                          intrinsics=Intrinsics(fx=131.25, fy=131.25, cx=79.5, cy=59.5, width=160, height=120))
    out = {}
    for name, flag in (("plain", []), ("kept", ["--keep-weights"])):
        path = tmp_path / f"{name}.sdfz"
        r = run("fuse", seq, path, "--codec", "pca", "--code-size", 32, *flag)
        assert r.exit_code == 0, r.output
        assert sdfcodec.open_map(path).has_weights == bool(flag)
        r = run("track", path, seq, "-o", tmp_path / f"{name}.txt", "--json")
        assert r.exit_code == 0, r.output
        s = run("search", path, "--query", "floor", "--json")
        assert s.exit_code == 0, s.output
        res = json.loads(s.stdout)
        out[name] = (read_tum(tmp_path / f"{name}.txt"), res.get("blocks", res.get("matches")))
    (tp, sp), (tk, sk) = out["plain"], out["kept"]
    assert len(tp) == 6
    np.testing.assert_array_equal(tp.positions, tk.positions)
    np.testing.assert_array_equal(tp.quaternions, tk.quaternions)
    assert sp == sk


GOLDEN = Path(__file__).parent / "golden" / "maps" / "quantised-weights-pca-4"


def _golden_weights(shape) -> np.ndarray:
    """Deterministic integer counts 0-299 (0 where ``(i + j + k) % 7 == 0``): some above the 255 uint8 counts keep."""
    i, j, k = np.indices(shape)
    return np.where((i + j + k) % 7 == 0, 0, (i * 31 + j * 17 + k * 7) % 300).astype(np.float32)


def _golden_map(path: Path) -> None:
    from sdfcodec.testing import analytic_blocks

    codec = sdfcodec.get_codec("pca", code_size=4).fit(analytic_blocks(64, seed=5))
    vol = sample_volume(Sphere((0.2, 0.2, 0.2), 0.12), (32, 32, 32), VS, truncation=TRUNC)
    blocks, wb = split_blocks(vol, TRUNC[1]), split_blocks(_golden_weights(vol.shape), 0.0)
    coords = np.argwhere(np.ones(blocks.shape[:3], bool))
    with sdfcodec.create_map(path, codec=codec, voxel_size=VS, truncation=TRUNC, chunk_blocks=2, keep_weights=True,
                             tool="tests/test_side_info.py golden") as m:
        m.write_blocks(coords, blocks[tuple(coords.T)], weights=wb[tuple(coords.T)])


def test_golden_quantised_weights_map_reads_forever(regen_golden):
    """A small pca-4 map with uint8 weight counts (extension quantised-fusion-weights), written once: today's
    reader opens, verifies and decodes it, and reads the counts the rule gives for its (integer) weights."""
    from _golden_maps import check_golden_map

    m = check_golden_map(GOLDEN, _golden_map, regen_golden)
    assert {"name": QUANT_WEIGHTS_EXTENSION, "required": False} in [e.model_dump() for e in m.header.extensions]
    coords = np.argwhere(m.block_states() == 2)
    w = split_blocks(_golden_weights((32, 32, 32)), 0.0)[tuple(coords.T)]
    np.testing.assert_array_equal(m.read_weights(coords), np.minimum(w, 255))
    np.testing.assert_array_equal(m.read_observed(coords), w > 0)


def test_mask_is_stored_at_zstd_9_and_older_masks_still_read(tmp_path):
    """The observation mask of an analytic sphere fused-like (unobserved exactly where the SDF is below d_min)
    reads back bit for bit, stored with the final chain (zstd 9, recompressed at commit); the same map with its
    mask stored by the previous chain (zstd 5, as older writers did) reads the same bits."""
    import shutil

    from _fused_maps import fused_like, write_volume_map
    from zarr.codecs import BloscCodec, Crc32cCodec

    vol = sample_volume(Sphere((0.32, 0.32, 0.32), 0.2), (48, 48, 48), VS, truncation=TRUNC)
    fused_vol, observed = fused_like(vol)
    np.testing.assert_array_equal(observed, vol > TRUNC[0] + 1e-6)
    # no integrity manifest: the old copy's mask is rewritten below, as an older writer (before manifests) stored it
    write_volume_map(tmp_path / "new.sdfz", fused_vol, observed, sdfcodec.pretrained_codec("pca", 32), manifest=False)
    shutil.copytree(tmp_path / "new.sdfz", tmp_path / "old.sdfz")
    g = zarr.open_group(tmp_path / "old.sdfz", mode="r+")
    rows, a = g["observed"][...], g["observed"]
    del g["observed"]
    g.create_array("observed", shape=rows.shape, dtype="uint8", fill_value=255, chunks=a.chunks,
                   compressors=[BloscCodec(cname="zstd", clevel=5, shuffle="noshuffle"), Crc32cCodec()],
                   dimension_names=["bx", "by", "bz", "byte"])[...] = rows
    for name, level in (("new", 9), ("old", 5)):
        blosc = [c for c in zarr.open_group(tmp_path / f"{name}.sdfz", mode="r")["observed"].metadata.codecs
                 if isinstance(c, BloscCodec)]
        assert [(b.cname.value, b.clevel, b.shuffle.value) for b in blosc] == [("zstd", level, "noshuffle")]
    split = split_blocks(observed.astype(np.float32), 1.0).reshape(-1, 16, 16, 16) > 0.5
    coords = np.argwhere(np.ones((3, 3, 3), bool))
    for name in ("new", "old"):
        m = sdfcodec.open_map(tmp_path / f"{name}.sdfz")
        coded = m.block_states()[tuple(coords.T)] == 2
        np.testing.assert_array_equal(m.read_observed(coords[coded]), split[coded])
        assert verify_map(tmp_path / f"{name}.sdfz").ok


def test_an_update_recompresses_only_the_mask_chunks_it_wrote(tmp_path):
    """Mask chunks are written fast and recompressed at commit: an update recompresses the chunks it wrote and
    leaves the others' files byte for byte (links to the version readers hold), which still read the same."""
    codec = sdfcodec.pretrained_codec("pca", 32)
    vol = sample_volume(Sphere((0.64, 0.64, 0.64), 0.2), (96, 96, 96), VS, truncation=TRUNC)  # over 2^3 chunks
    blocks = split_blocks(vol, TRUNC[1])
    obs = split_blocks((vol > 0.0).astype(np.float32), 1.0) > 0.5  # the solid side unobserved
    coords = np.argwhere(np.ones(blocks.shape[:3], bool))
    path = tmp_path / "m.sdfz"
    with sdfcodec.create_map(path, codec=codec, voxel_size=VS, truncation=TRUNC, chunk_blocks=2) as m:
        m.write_blocks(coords, blocks[tuple(coords.T)], observed=obs[tuple(coords.T)])
    before = sdfcodec.open_map(path)
    coded = coords[before.block_states()[tuple(coords.T)] == 2]
    files = {f.relative_to(path): f.read_bytes() for f in (path / "observed" / "c").rglob("*") if f.is_file()}
    assert len(files) >= 2
    # rewrite the coded blocks of chunk (0, 0, 0) only, their voxel layer x = 12 (inside the sphere) now observed
    mine = coded[(coded // 2 == 0).all(axis=1)]
    new = obs[tuple(mine.T)].copy()
    new[:, 12] = True
    assert len(mine) and not new.all()
    with sdfcodec.update_map(path) as m:
        m.write_blocks(mine, blocks[tuple(mine.T)], observed=new)
    after = sdfcodec.open_map(path)
    changed = {k for k, v in files.items() if (path / k).read_bytes() != v}
    assert changed == {Path("observed/c/0/0/0/0")}
    expect = obs[tuple(coded.T)].copy()
    expect[(coded // 2 == 0).all(axis=1)] = new
    np.testing.assert_array_equal(after.read_observed(coded), expect)
    np.testing.assert_array_equal(before.read_observed(coded), obs[tuple(coded.T)])  # the old version, intact
