"""Shipped models by default, the state-outweighs-codes warning, and codec state by reference (issue 20, item 1;
spec/map-format.md section 6c), through the CLI as a user runs it (piped: CliRunner, no terminal)."""

from __future__ import annotations

import re

import json
import os
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

import sdfcodec
from sdfcodec import errors
from sdfcodec.core import header
from sdfcodec.cli import app
from sdfcodec.map import state_digest
from sdfcodec.registry import choose_codec
from sdfcodec.core.sdf import Plane, Scene, Sphere, sample_volume

runner = CliRunner()
VS = 0.02
MIB = 1 << 20


def run(*args):
    return runner.invoke(app, [str(a) for a in args])


def du(path: Path) -> int:
    """Bytes of the regular files under ``path``, counted here (not by sdfcodec)."""
    return sum(os.path.getsize(os.path.join(d, f)) for d, _, fs in os.walk(path) for f in fs)


def state_array_bytes(m: Path) -> int:
    """Bytes of the stored state arrays: everything under codec/ but the group's own metadata."""
    return du(m / "codec") - os.path.getsize(m / "codec" / "zarr.json")


def one_error_line(r) -> str:
    lines = [ln for ln in r.stderr.strip().splitlines() if ln.strip()]
    assert r.exit_code != 0 and len(lines) == 1 and lines[0].startswith("error:"), r.output
    return lines[0]


@pytest.fixture(scope="module")
def volume(tmp_path_factory) -> Path:
    scene = Scene([Plane((0, 0, 1), 0.1), Sphere((0.5, 0.6, 0.4), 0.25)])
    path = tmp_path_factory.mktemp("vol") / "scene.npy"
    np.save(path, sample_volume(scene, (64, 64, 48), VS))
    return path


@pytest.fixture(scope="module")
def ae_maps(volume, tmp_path_factory) -> dict[str, Path]:
    """The same volume encoded with ``--codec ae`` (no size, no model), state embedded and by reference."""
    d = tmp_path_factory.mktemp("ae")
    out = {}
    for how in ("embedded", "reference"):
        out[how] = d / f"{how}.sdfz"
        r = run("encode", volume, out[how], "--codec", "ae", "--voxel-size", VS, "--codec-state", how)
        assert r.exit_code == 0, r.output
        out[f"{how}-stderr"] = r.stderr
    return out


def test_encode_ae_uses_the_shipped_model_and_warns(ae_maps):
    """``--codec ae`` alone encodes with the shipped ae-64 (no fitting), and says on stderr that the 7.9 MiB of
    state it stores outweighs the codes, by how much, and to store it by reference."""
    emb = ae_maps["embedded"]
    assert "fitting" not in ae_maps["embedded-stderr"]
    shipped = sdfcodec.pretrained_codec("ae", 64).state_dict()
    stored = sdfcodec.open_map(emb).codec.state_dict()
    assert sorted(stored) == sorted(shipped)
    assert all(np.array_equal(stored[k], shipped[k]) for k in shipped)
    g = json.loads((emb / "zarr.json").read_text())["attributes"]["sdfcodec"]
    assert g["codec"]["state_sha256"] == state_digest(shipped) and "state_reference" not in g["codec"]

    state, codes = du(emb / "codec"), du(emb / "codes")
    assert state > 10 * codes  # the situation of the issue: the network outweighs the codes many times
    warning = [ln for ln in ae_maps["embedded-stderr"].splitlines() if ln.startswith("warning:")]
    assert len(warning) == 1 and f"by {(state - codes) / MIB:.2f} MiB" in warning[0]
    assert "ae-64" in warning[0] and "--codec-state reference" in warning[0]
    assert "warning" not in ae_maps["reference-stderr"]  # nothing stored, nothing to warn about
    r = run("info", emb)
    assert r.exit_code == 0 and "outweighs the codes" in r.stdout and "embedded" in r.stdout
    info = json.loads(run("info", emb, "--json").stdout)
    assert info["state_warning"] and info["codec_state"]["stored"] == "embedded"


def test_by_reference_decodes_identically_smaller_and_verifies(ae_maps, tmp_path):
    emb, ref = ae_maps["embedded"], ae_maps["reference"]
    assert not (ref / "codec").exists()  # no state arrays, and no group to hold them (spec 2, 6c)
    # smaller by exactly the codec group's bytes, less the few bytes the reference changes in the header (the
    # reference in, the list of arrays and the digest out: spec 6c)
    grown = os.path.getsize(ref / "zarr.json") - os.path.getsize(emb / "zarr.json")
    listed = os.path.getsize(emb / "manifest.json") - os.path.getsize(ref / "manifest.json")  # the state's entries
    assert -400 < grown < 400 and 0 < listed < 2000 and state_array_bytes(emb) > 7 * MIB
    assert du(emb) - du(ref) == du(emb / "codec") - grown + listed
    h = json.loads((ref / "zarr.json").read_text())["attributes"]["sdfcodec"]
    digest = state_digest(sdfcodec.pretrained_codec("ae", 64).state_dict())
    assert h["codec"]["state_reference"] == {"model": "ae-64", "sha256": digest}
    assert "state_arrays" not in h["codec"] and "state_sha256" not in h["codec"]  # what the reference says
    assert {"name": "codec-state-reference", "required": True} in h["extensions"]
    assert sdfcodec.open_map(ref).header.codec.state_sha256 == digest

    for how, m in (("e", emb), ("r", ref)):
        r = run("decode", m, tmp_path / f"{how}.npy")
        assert r.exit_code == 0, r.output
    assert np.array_equal(np.load(tmp_path / "e.npy"), np.load(tmp_path / "r.npy"))
    for m in (emb, ref):
        r = run("verify", m)
        assert r.exit_code == 0 and "OK" in r.stdout, r.output
    r = run("info", ref)
    assert r.exit_code == 0 and "not stored: the shipped model ae-64 at code size 64, by reference" in r.stdout
    assert json.loads(run("info", ref, "--json").stdout)["codec_state"] == {"stored": "reference", "model": "ae-64",
                                                                           "sha256": digest}

    # back to a self-contained map where the model is installed: the same codec, so the codes are copied
    r = run("encode", ref, tmp_path / "back.sdfz", "--codec", "ae", "--code-size", 64, "--codec-state", "embedded")
    assert r.exit_code == 0, r.output
    back = sdfcodec.open_map(tmp_path / "back.sdfz")
    assert back.header.codec.state_arrays and back.header.codec.state_reference is None
    (c1, z1), (c2, z2) = sdfcodec.open_map(emb).read_codes(), back.read_codes()
    assert np.array_equal(c1, c2) and np.array_equal(z1, z2)


def _tampered(src: Path, dst: Path, **ref) -> Path:
    """A copy of map ``src`` whose state reference says ``ref`` (state_sha256 kept consistent with it)."""
    import shutil

    shutil.copytree(src, dst)
    doc = json.loads((dst / "zarr.json").read_text())
    codec = doc["attributes"]["sdfcodec"]["codec"]
    codec["state_reference"].update(ref)
    codec["state_sha256"] = codec["state_reference"]["sha256"]
    (dst / "zarr.json").write_text(json.dumps(doc))
    return dst


def test_a_reference_that_does_not_resolve_is_one_clear_error(ae_maps, tmp_path):
    ref = ae_maps["reference"]
    bad = "0" * 64
    tampered = _tampered(ref, tmp_path / "t.sdfz", sha256=bad)
    line = one_error_line(run("decode", tampered, tmp_path / "t.npy"))
    assert "'ae-64'" in line and bad in line and "ships it with another state" in line
    assert "--codec ae --code-size 64 --codec-state embedded" in line
    r = run("verify", tampered)
    assert r.exit_code != 0 and "codec.state_reference" in r.stdout and bad in r.stdout, r.output
    # issue 42: the line names the package and version to install, the one that wrote the map (its header)
    wrote = f"{sdfcodec.open_map(tampered).header.codec.package}=={sdfcodec.open_map(tampered).header.codec.package_version}"
    with pytest.raises(errors.StateReferenceError, match=f"install {re.escape(wrote)} \\(the plugin version that wrote"):
        sdfcodec.open_map(tampered).codec

    unknown = _tampered(ref, tmp_path / "u.sdfz", model="ae-64-v9", sha256=bad)  # a later plugin's model
    line = one_error_line(run("decode", unknown, tmp_path / "u.npy"))
    assert "'ae-64-v9'" in line and bad in line and "ships: ae-64 (code size 64)" in line

    # content-addressed: a model renamed by a later plugin version still resolves by its digest
    renamed = _tampered(ref, tmp_path / "n.sdfz", model="ae-64-renamed")
    assert np.array_equal(sdfcodec.open_map(renamed).decode_region(), sdfcodec.open_map(ref).decode_region())

    # the name is a name, never a path: the header cannot point a reader at a file
    pathlike = _tampered(ref, tmp_path / "p.sdfz", model="../../ae-64.npz")
    assert "state_reference.model" in one_error_line(run("info", pathlike))


def test_a_reader_without_the_extension_refuses(ae_maps, monkeypatch):
    """A reader that predates the extension (simulated: its list of known extensions lacks it) refuses the map,
    naming the extension, rather than looking for state under codec/."""
    monkeypatch.setattr(header, "KNOWN_EXTENSIONS", header.KNOWN_EXTENSIONS - {"codec-state-reference"})
    line = one_error_line(run("info", ae_maps["reference"]))
    assert "needs extension 'codec-state-reference'" in line and "upgrade sdfcodec" in line
    assert run("info", ae_maps["embedded"]).exit_code == 0  # maps that store their state are unaffected


def test_pca_reference_names_the_cut_state(volume, tmp_path):
    """pca-64 cut from the shipped pca-128 references model pca-128 with the digest of the 64-component state
    (another state than pca-128's or pca-32's); decoding matches the embedded map bit for bit."""
    pca64 = sdfcodec.pretrained_codec("pca", 64)
    maps = {}
    for how in ("embedded", "reference"):
        maps[how] = tmp_path / f"{how}.sdfz"
        with sdfcodec.create_map(maps[how], codec=pca64, voxel_size=VS, codec_state=how) as m:
            m.write_volume(np.load(volume))
    ref = sdfcodec.open_map(maps["reference"]).header.codec.state_reference
    digest = state_digest(pca64.state_dict())
    assert ref.model == "pca-128" and ref.sha256 == digest
    assert digest not in {state_digest(sdfcodec.pretrained_codec("pca", k).state_dict()) for k in (32, 128)}
    assert np.array_equal(sdfcodec.open_map(maps["embedded"]).decode_region(),
                          sdfcodec.open_map(maps["reference"]).decode_region())
    # an update keeps the reference (and its required extension)
    with sdfcodec.update_map(maps["reference"]) as m:
        m.mark_empty([[0, 0, 0]])
    h = sdfcodec.open_map(maps["reference"]).header
    assert h.codec.state_reference == ref and "codec-state-reference" in [e.name for e in h.extensions]

    # a state no shipped model has cannot be referenced
    other = sdfcodec.get_codec(pca64.get_config()).load_state_dict(
        {k: v * np.float32(1.001) if k == "mean" else v for k, v in pca64.state_dict().items()})
    with pytest.raises(errors.InvalidValueError, match="cannot be stored by reference"):
        sdfcodec.create_map(tmp_path / "x.sdfz", codec=other, voxel_size=VS, codec_state="reference")
    assert not (tmp_path / "x.sdfz").exists()
    # a codec without state has nothing to reference: a plain map, readable by readers without the extension
    with sdfcodec.create_map(tmp_path / "raw.sdfz", codec=sdfcodec.get_codec("raw"), voxel_size=VS,
                             codec_state="reference") as m:
        m.write_volume(np.load(volume)[:16, :16, :16])
    h = sdfcodec.open_map(tmp_path / "raw.sdfz").header
    assert [e.name for e in h.extensions] == ["integrity-manifest"] and h.codec.state_reference is None
    assert h.codec.state_arrays == []
    # the CLI refuses before fitting anything
    line = one_error_line(run("encode", volume, tmp_path / "y.sdfz", "--voxel-size", VS, "--fit",
                              "--codec-state", "reference"))
    assert "needs a shipped model" in line and "--fit" in line and not (tmp_path / "y.sdfz").exists()


def test_choose_codec_fits_only_without_a_shipped_model():
    """The rule encode follows: the shipped model at the asked size; else an unfitted codec and one line saying
    why, naming the sizes shipped; codecs that learn nothing need neither."""
    for cid, size, expect in (("ae", None, "ae"), ("ae", 64, "ae"), ("pca", 32, "pca"), ("parallel", None, "parallel"),
                              ("sequential", 64, "sequential")):
        codec, why = choose_codec(cid, size)
        assert why is None and codec == sdfcodec.pretrained_codec(expect, size)
    codec, why = choose_codec("ae", 32)
    assert not codec.is_fitted and codec.code_size == 32 and "ships no model at code size 32" in why
    assert "shipped: ae-64 (code size 64)" in why
    codec, why = choose_codec("pca", 200)
    assert not codec.is_fitted and "pca-128 (code sizes 1-128)" in why
    codec, why = choose_codec("pca", 32, fit=True)
    assert not codec.is_fitted and "--fit" in why
    codec, why = choose_codec("raw")
    assert codec.is_fitted and why is None
    assert sdfcodec.get_codec("raw").shipped_models() == {}
    assert type(sdfcodec.get_codec("ae")).shipped_models() == {"ae-64": (64,)}


def test_listed_shipped_states_are_what_pretrained_gives():
    """Each built-in plugin's listing (what references resolve through) gives exactly the state ``pretrained``
    serves at that size, the 64 + 64 mixtures at both code sizes (per-block and fixed weight)."""
    from sdfcodec.registry import get_codec_class

    cases = [("pca", "pca-128", 1, {}), ("pca", "pca-128", 64, {}), ("pca", "pca-128", 128, {}),
             ("ae", "ae-64", 64, {}), ("parallel", "parallel-64-64", 129, {}),
             ("sequential", "sequential-64-64", 129, {}), ("sequential", "sequential-64-64", 128, {"weight": 0.5})]
    for cid, model, k, opts in cases:
        cls = get_codec_class(cid)
        assert k in cls.shipped_models()[model]
        served = sdfcodec.pretrained_codec(cid, None if opts else k, **opts)
        assert served.code_size == k
        assert state_digest(cls.shipped_state(model, k)) == state_digest(served.state_dict()), (cid, k)
    with pytest.raises(errors.ModelNotFoundError, match="no model 'ae-64' at code size 32"):
        get_codec_class("ae").shipped_state("ae-64", 32)
