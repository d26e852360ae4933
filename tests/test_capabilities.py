"""Codec capabilities are declared (``Codec.capabilities``, spec/codec-plugins.md section 4a), not inferred from
overrides: a declared capability is used, an undeclared override (a plugin written from the earlier docs) warns
and keeps working, a declaration without its hook or with an unknown name is refused by name."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

import sdfcodec
from sdfcodec import errors
from sdfcodec.codec import CAPABILITIES, capabilities, decodes_into, uses_weights
from sdfcodec.map.observed import encode_blocks
from sdfcodec.registry import get_codec_class
from sdfcodec.testing import analytic_blocks


class _Identity(sdfcodec.Codec):
    """The block is its code (as ``raw``), declaring nothing."""

    codec_id = "test-identity"
    code_size = 4096

    def _encode(self, blocks):
        return blocks.reshape(len(blocks), 4096).clone()

    def _decode(self, codes):
        return codes.reshape(len(codes), 16, 16, 16).clone()


class _LosslessWeighted(_Identity):
    codec_id = "test-lossless-weighted"
    capabilities = frozenset({"encode_weighted"})  # lossless: the default weighted encode is the best one


def _affine_codec(declare: bool) -> type[sdfcodec.Codec]:
    """An identity codec whose own ``decode_affine`` counts its calls, declared or (as earlier docs had it) not."""
    body = {"codec_id": "test-affine", "calls": 0,
            "decode_affine": lambda self, codes, scale, offset: (
                setattr(type(self), "calls", type(self).calls + 1) or scale * self._decode(codes) + offset)}
    if declare:
        body["capabilities"] = frozenset({"decode_affine"})
    return type("Affine", (_Identity,), body)


def test_builtin_codecs_declare_what_they_provide():
    assert capabilities(get_codec_class("pca")) == {"decode_affine", "decode_into", "decode_tiles",
                                                    "encode_truncated", "encode_weighted", "fit_weighted",
                                                    "numpy_path", "pretrained"}
    # raw keeps the default encode_weighted (it is lossless) and declares it, no override needed
    assert capabilities(get_codec_class("raw")) == {"decode_into", "encode_weighted"}
    assert "encode_weighted" not in get_codec_class("raw").__dict__
    assert capabilities(get_codec_class("ae")) == {"pretrained"} == capabilities(get_codec_class("parallel"))
    for cid in ("sz3", "gaussian-blur"):
        assert capabilities(get_codec_class(cid)) == {"decode_into"}


def test_a_declared_capability_is_used(tmp_path):
    """Declared ``encode_weighted`` without an override: the writer's encode hands it the blocks as they are
    (identity: the codes are the input voxels, unobserved ones included); undeclared, it gets them filled."""
    v = analytic_blocks(3).astype(np.float32)
    observed = np.ones_like(v, bool)
    observed[:, :, :, 8:] = False  # half of each block never seen
    v[~observed] = 0.25  # a value filling would not keep (it grows the observed band into the unseen half)
    args = (v, observed, (-0.04, 0.1), 0.02, 4.0, "cpu")
    assert uses_weights(_LosslessWeighted) and not uses_weights(_Identity)
    kept = encode_blocks(_LosslessWeighted(), *args).reshape(v.shape)
    np.testing.assert_array_equal(kept, v)
    filled = encode_blocks(_Identity(), *args).reshape(v.shape)
    np.testing.assert_array_equal(filled[observed], v[observed])
    assert not np.any(filled[~observed] == 0.25)

    codec = _affine_codec(declare=True)()
    buf = np.empty((len(v), 16, 16, 16), np.float32)
    codec.decode_core(codec.encode(v), scale=2.0, offset=1.0, out=buf)
    assert type(codec).calls == 1  # decode_into's default went through the declared decode_affine
    np.testing.assert_allclose(buf, 2.0 * v + 1.0, rtol=1e-6)


def test_an_undeclared_override_warns_naming_the_declaration_and_still_works():
    with pytest.warns(DeprecationWarning, match=r"capabilities = frozenset\(\{'decode_affine'\}\)"):
        cls = _affine_codec(declare=False)
    assert "decode_affine" in capabilities(cls)
    codec, v = cls(), analytic_blocks(2)
    buf = np.empty((2, 16, 16, 16), np.float32)
    codec.decode_core(codec.encode(v), scale=0.14, offset=-0.04, out=buf)
    assert cls.calls == 1
    np.testing.assert_allclose(buf, 0.14 * v - 0.04, rtol=1e-6, atol=1e-7)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        _affine_codec(declare=True)  # declared: no warning


def test_a_capability_declared_without_its_hook_is_refused():
    cls = type("NoTiles", (_Identity,), {"codec_id": "test-no-tiles", "capabilities": frozenset({"decode_tiles"})})
    with pytest.raises(errors.RegistrationError, match=r"NoTiles\.capabilities declares \['decode_tiles'\] but "
                                                       r"the class does not implement decode_tiles\(\)"):
        sdfcodec.register_codec(cls)
    codec = cls()
    with pytest.raises(errors.RegistrationError, match="decode_tiles"):  # first use, never registered
        codec.decode_core(codec.encode(analytic_blocks(1)), out=np.empty((1, 4096), np.float32))
    assert not decodes_into(_Identity)

    typo = type("Typo", (_Identity,), {"codec_id": "test-typo", "capabilities": frozenset({"decode_fast"})})
    with pytest.raises(errors.RegistrationError, match=r"unknown capabilities \['decode_fast'\]; known: "):
        sdfcodec.register_codec(typo)
    assert set(CAPABILITIES) >= {"decode_into", "decode_tiles", "encode_weighted"}
