"""Registry: eager listing, lazy loading, broken plugins reported by name, run-time registration; and the
conformance suite catches codecs that break the contract."""

from __future__ import annotations

import os
from importlib import metadata

import numpy as np
import pytest
import torch

import sdfcodec
from sdfcodec import errors, registry
from sdfcodec.testing import analytic_blocks, check_codec


def test_builtin_codecs_are_listed_with_their_package():
    entries = {e.id: e for e in sdfcodec.list_codecs()}
    assert {"pca", "raw"} <= set(entries)
    assert entries["pca"].package == "sdfcodec" and entries["pca"].target == "sdfcodec_pca:PCACodec"


def test_get_codec_by_id_and_by_config_without_mutating_it():
    c = sdfcodec.get_codec("pca", code_size=32, mean="block")
    assert c.get_config() == {"id": "pca", "code_size": 32, "mean": "block", "svd_solver": "auto",
                              "random_state": 0}
    cfg = {"id": "pca", "code_size": 128}
    c2 = sdfcodec.get_codec(cfg, mean="block")
    assert cfg == {"id": "pca", "code_size": 128}
    assert (c2.code_size, c2.mean) == (128, "block")


def test_unknown_codec_lists_what_is_installed():
    with pytest.raises(errors.UnknownCodecError, match="'nope' is not installed.*installed codecs: .*pca"):
        sdfcodec.get_codec("nope")
    with pytest.raises(errors.InvalidValueError, match="no parameter"):
        sdfcodec.get_codec("pca", colour="red")


@pytest.fixture
def broken_plugin(monkeypatch):
    real = registry._entry_points

    def with_broken():
        eps = real()
        eps["broken"] = metadata.EntryPoint("broken", "sdfcodec_does_not_exist:Codec", registry.ENTRY_POINT_GROUP)
        return eps

    monkeypatch.setattr(registry, "_entry_points", with_broken)


def test_installed_codecs_are_scanned_again_only_when_the_path_changes(tmp_path, monkeypatch):
    """The entry points are read once while sys.path and its entries are unchanged (every map written asks for its
    codec's package), and a plugin installed while the process runs (a new metadata directory in a path entry)
    is listed with its package and version."""
    scans = []
    real = metadata.entry_points
    monkeypatch.setattr(metadata, "entry_points", lambda **kw: scans.append(kw) or real(**kw))
    site = tmp_path / "site"
    site.mkdir()
    os.utime(site, ns=(0, 0))  # older than anything made below, whatever the file system's time resolution
    monkeypatch.syspath_prepend(str(site))
    assert "late" not in {e.id for e in sdfcodec.list_codecs()}
    n = len(scans)
    assert n >= 1  # the path changed: scanned again
    for _ in range(3):
        sdfcodec.list_codecs()
        registry.codec_package("pca")
    assert len(scans) == n  # nothing changed: no new scan
    dist = site / "late_codec-1.0.dist-info"  # what pip writes for a package "late-codec" 1.0
    dist.mkdir()
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: late-codec\nVersion: 1.0\n")
    (dist / "entry_points.txt").write_text("[sdfcodec.codecs]\nlate = late_codec:Late\n")
    late = {e.id: e for e in sdfcodec.list_codecs()}["late"]
    assert (late.package, late.version, late.target) == ("late-codec", "1.0", "late_codec:Late")
    assert registry.codec_package("late") == "late-codec" and len(scans) == n + 1


def test_broken_plugin_is_reported_by_name_and_others_work(broken_plugin):
    assert "broken" in {e.id for e in sdfcodec.list_codecs()}  # listing imports nothing
    with pytest.raises(errors.PluginLoadError, match="'broken'.*sdfcodec_does_not_exist"):
        sdfcodec.get_codec("broken")
    assert sdfcodec.get_codec("raw").encode(analytic_blocks(2)).shape == (2, 4096)


class Downsample(sdfcodec.Codec):
    """A tiny third-party-style codec: 2x2x2 average pooling (512 numbers), nearest upsampling."""

    codec_id = "test-downsample"
    code_size = 512

    def _encode(self, blocks):
        return torch.nn.functional.avg_pool3d(blocks[:, None], 2).reshape(len(blocks), 512)

    def _decode(self, codes):
        c = codes.reshape(len(codes), 1, 8, 8, 8)
        return c.repeat_interleave(2, 2).repeat_interleave(2, 3).repeat_interleave(2, 4)[:, 0]


def test_registered_codec_passes_conformance():
    sdfcodec.register_codec(Downsample, replace=True)
    assert "test-downsample" in {e.id for e in sdfcodec.list_codecs()}
    report = check_codec(sdfcodec.get_codec("test-downsample"))
    assert "bad input" in report["checks"] and report["mse"] > 0


class WrongShape(Downsample):
    codec_id = "test-wrong-shape"

    def _decode(self, codes):
        return super()._decode(codes)[:, :8]


class ForgetfulState(sdfcodec.Codec):
    """Claims to need fitting but loses its state on a round trip."""

    codec_id = "test-forgetful"
    requires_fit = True
    code_size = 4

    def _fit(self, blocks):
        self.scale_ = np.float32(blocks.mean())

    def state_dict(self):
        return {"scale": np.asarray(self.scale_)} if hasattr(self, "scale_") else {}

    def load_state_dict(self, state):
        self.scale_ = np.float32(1.0)  # ignores what it was given
        return self

    def _encode(self, blocks):
        m = blocks.reshape(len(blocks), 8, -1).mean(-1)[:, :4]
        return m * float(self.scale_)

    def _decode(self, codes):
        return (codes.mean(1) / float(self.scale_))[:, None, None, None].expand(-1, 16, 16, 16).contiguous()


class NotPrefix(Downsample):
    codec_id = "test-not-prefix"
    prefix_ordered = True  # a false claim: it cannot decode a prefix


@pytest.mark.parametrize("cls, match", [
    (WrongShape, "decode must give float32 numpy|returned shape"),
    (ForgetfulState, "round trip|state"),
    (NotPrefix, "prefix"),
])
def test_conformance_suite_catches_broken_codecs(cls, match):
    sdfcodec.register_codec(cls, replace=True)
    with pytest.raises(AssertionError, match=match):
        check_codec(sdfcodec.get_codec(cls.codec_id))


def test_register_codec_validates():
    class NoId(sdfcodec.Codec):
        code_size = 1

        def _encode(self, b):
            return b

        def _decode(self, c):
            return c

    with pytest.raises(errors.RegistrationError, match="codec_id"):
        sdfcodec.register_codec(NoId)
    with pytest.raises(errors.CodecTypeError):
        sdfcodec.register_codec(object)  # type: ignore[arg-type]


def test_model_file_round_trip_and_no_pickles(tmp_path):
    codec = sdfcodec.get_codec("pca", code_size=32).fit(analytic_blocks(200))
    path = sdfcodec.save_model(codec, tmp_path / "m.npz")
    back = sdfcodec.load_model(path)
    x = analytic_blocks(5, seed=9)
    assert back.get_config() == codec.get_config() and np.array_equal(back.encode(x), codec.encode(x))
    np.savez(tmp_path / "evil.npz", payload=np.array([{"a": 1}], dtype=object))
    with pytest.raises(errors.FormatError, match="never unpickles"):
        sdfcodec.load_model(tmp_path / "evil.npz")
    np.savez(tmp_path / "plain.npz", a=np.zeros(3))
    with pytest.raises(errors.FormatError, match="not an sdfcodec model"):
        sdfcodec.load_model(tmp_path / "plain.npz")
    assert back == codec


def test_registry_and_model_errors_are_sdfcodec_errors(tmp_path):
    """Every deliberate error of the registry and of model files is an SDFCodecError that still derives from
    the built-in it replaced (ValueError, TypeError, FileNotFoundError); a missing model is not a missing map."""
    class Dup(sdfcodec.Codec):
        codec_id = "test-dup"
        code_size = 1
        _encode = _decode = staticmethod(lambda x: x)

    class Dup2(Dup):
        pass

    sdfcodec.register_codec(Dup, replace=True)
    with pytest.raises(errors.RegistrationError, match="already registered") as e:
        sdfcodec.register_codec(Dup2)
    assert isinstance(e.value, ValueError)
    with pytest.raises(errors.CodecTypeError) as e:
        sdfcodec.get_codec(3)  # type: ignore[arg-type]
    assert isinstance(e.value, TypeError)
    with pytest.raises(errors.ModelNotFoundError, match="no such file") as e:
        sdfcodec.load_model(tmp_path / "missing.npz")
    assert isinstance(e.value, FileNotFoundError) and not isinstance(e.value, errors.MapNotFoundError)
    with pytest.raises(errors.NotFittedError):
        sdfcodec.save_model(sdfcodec.get_codec("pca"), tmp_path / "unfitted.npz")


def test_optional_hooks_are_public_and_spec1_names_still_work():
    """The decode-on-read and streamed-fit hooks are public methods (decode_affine, decode_bound, fit_batches);
    a codec written against spec 1's underscore names keeps working, with a DeprecationWarning, and so do
    callers of the old names."""
    import warnings

    with pytest.warns(DeprecationWarning) as record:
        class Old(sdfcodec.Codec):
            codec_id = "test-old-hooks"
            code_size = 4096
            requires_fit = True

            def _encode(self, b):
                return b.reshape(len(b), -1).clone()

            def _decode(self, c):
                return c.reshape(len(c), 16, 16, 16).clone()

            def _decode_bound(self, codes):
                return max(float(codes.abs().max()), super()._decode_bound(codes) or 0.0)

            def _decode_affine(self, codes, scale, offset):
                return super()._decode_affine(codes, scale, offset)  # the default, through the old name

            def _fit_stream(self, batches):
                self.seen_ = sum(len(b) for b in batches)

            def state_dict(self):
                return {"seen": np.array(self.seen_)} if hasattr(self, "seen_") else {}

    said = " ".join(str(w.message) for w in record)
    for name, public in (("_decode_bound", "decode_bound"), ("_decode_affine", "decode_affine"),
                         ("_fit_stream", "fit_batches")):  # one warning per old hook, naming the new name
        assert f"'{name}', whose name since codec spec 2 is '{public}'" in said
    codec = Old().fit_stream([analytic_blocks(3), analytic_blocks(2)])
    assert codec.seen_ == 5
    codes = torch.from_numpy(codec.encode(analytic_blocks(2)))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        assert codec.decode_bound(codes) == float(codes.abs().max())
        out = codec.decode_core(codes, scale=2.0, offset=-1.0)
    assert torch.allclose(out, 2 * codes.reshape(-1, 16, 16, 16) - 1)
    with pytest.warns(DeprecationWarning, match="call decode_bound"):  # a caller of the old name
        assert sdfcodec.pretrained_codec("pca", 8)._decode_bound(codes[:, :8]) > 0

    pca = sdfcodec.pretrained_codec("pca", 8)
    with warnings.catch_warnings():
        warnings.simplefilter("error", DeprecationWarning)  # the built-in codecs use the public names only
        assert pca.decode_bound(codes[:, :8]) > 0 and sdfcodec.get_codec("raw").decode_bound(codes) is None
        pca.decode_core(codes[:, :8], scale=0.14, offset=-0.04)
        # and implements the streamed fit under its public name (fitting it here would cost a 4096^2 eigh;
        # test_codecs_builtin.py::test_streamed_pca_equals_sklearn fits it)
        pca_cls = type(sdfcodec.get_codec("pca"))
        assert "fit_batches" in pca_cls.__dict__ and "_fit_stream" not in pca_cls.__dict__


def test_toolkit_is_the_plugin_authors_import():
    """sdfcodec.plugin holds what plugins need; the huge-page allocator left codec.__all__ (still reachable
    from sdfcodec.codec, deprecated)."""
    import sdfcodec.codec
    import sdfcodec.plugin as plugin

    assert "empty" not in sdfcodec.codec.__all__ and set(plugin.__all__) <= set(dir(plugin))
    with pytest.warns(DeprecationWarning, match="sdfcodec.plugin.empty"):
        assert sdfcodec.codec.empty is plugin.empty
    t = plugin.empty((2, 3), torch.device("cpu"))
    assert t.shape == (2, 3) and t.dtype == torch.float32
    x, was_numpy = plugin.as_float_tensor(np.zeros((1, 2)), "x", (None, 2))
    assert was_numpy and isinstance(plugin.like_input(x, was_numpy), np.ndarray)
