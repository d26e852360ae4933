"""The ``parallel`` and ``sequential`` codecs: the paper's mixtures of PCA eigenshapes and an autoencoder
(section IV-B).

``parallel``
    Both encoders see the block. The code is ``[pca code | ae code | w]``; decoding gives
    ``w * PCA(pca code) + (1 - w) * AE(ae code)``.
``sequential``
    PCA first; an autoencoder with a tanh output (residuals are zero-centred) encodes the residual
    ``r = x - PCA(x)``. The code is ``[pca code | ae code | w]``; decoding gives ``PCA + w * AE``.

The mixing weight ``w`` (``weight=`` parameter):

``"block"`` (default)
    One ``w`` per block, chosen at encode time to minimise that block's squared error over ``w in [0, 1]``.
    The error is a quadratic in ``w``, so the line search is exact and closed-form: the unconstrained
    minimiser (``<x - a, p - a> / |p - a|^2`` for parallel, ``<r, a> / |a|^2`` for sequential) clipped to
    ``[0, 1]``. It is stored as the code's last element, so ``code_size = pca_size + ae_size + 1``
    (64 + 64 + 1 = 129 by default). The paper's "approximate line search" can only do as well as this.
a number in ``[0, 1]``
    One fixed ``w`` for the whole map, recorded in the codec's configuration (the map header);
    ``code_size = pca_size + ae_size``. Encoding is then two plain encoders, with no decode at encode time.

With a per-block ``w`` the decoded block is never worse than either part alone (``w = 0`` and ``w = 1`` are
candidates; for sequential, ``w = 0`` is the PCA part alone). :func:`weight_stats` reports how often ``w``
ends at 0 or 1; the paper found mixing rarely pays (mostly one part or the other).

The PCA part defaults to the shipped eigenshapes (``pca="default"``: the first ``pca_size`` components of
``sdfcodec.pretrained_codec("pca", ...)``), so fitting only trains the autoencoder; ``pca="fit"`` fits
the PCA part on the training blocks instead. Either way the learned state holds the PCA arrays as well as
the network's, so a map is self-contained. State names: ``pca.components``, ``pca.mean``,
``pca.explained_variance`` (see the ``pca`` codec) and ``ae.<layer>.weight`` / ``ae.<layer>.bias`` (see the
``ae`` codec). These codecs are not prefix-ordered.

Both parts come from the public registry (``sdfcodec.get_codec("pca" | "ae")``,
``sdfcodec.pretrained_codec``), as any third-party mixture would build them: this plugin never imports
another. Shipped weights: the parallel 64 + 64 pairs the shipped eigenshapes with the shipped AE-64; the
sequential 64 + 64 is ``models/sequential-64-64.npz`` in this package. ``pretrained()`` serves both.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, ClassVar, Mapping

import numpy as np

import sdfcodec
from sdfcodec import Codec
from sdfcodec.errors import InvalidValueError, ModelNotFoundError, SDFCodecError, ShapeError
from sdfcodec.plugin import (TrainableCodec, get_codec_class, lazy_module, load_shipped_model, pretrained_codec,
                             register_bench, shipped_model_file)

torch = lazy_module("torch")  # imported on first use: listing codecs and reading headers never need it

__all__ = ["ParallelCodec", "SequentialCodec", "weight_stats", "parallel_weight", "sequential_weight",
           "default_parallel", "default_sequential", "SHIPPED_SEQUENTIAL"]

_N = 16 ** 3
SHIPPED_SEQUENTIAL = "sequential-64-64.npz"  # in this package's models/
UNTRAINED = "untrained (random init; speed does not depend on the values)"
_EPS = 1e-12  # |p - a|^2 (or |a|^2) below this: the parts agree, any w gives the same block


def parallel_weight(x: torch.Tensor, p: torch.Tensor, a: torch.Tensor) -> torch.Tensor:
    """Per-block ``w in [0, 1]`` minimising ``|x - (w p + (1 - w) a)|^2``.

    Parameters
    ----------
    x, p, a : torch.Tensor
        ``(N, 4096)`` float32 on one device: input, PCA reconstruction, AE reconstruction.

    Returns
    -------
    torch.Tensor
        ``(N,)`` float32 on the same device. Where ``p`` and ``a`` coincide, ``w = 1`` (PCA).
    """
    d = p - a
    den = (d * d).sum(dim=1)
    num = ((x - a) * d).sum(dim=1)
    w = torch.where(den > _EPS, num / den.clamp_min(_EPS), torch.ones_like(den))
    return w.clamp_(0.0, 1.0)


def sequential_weight(r: torch.Tensor, a: torch.Tensor) -> torch.Tensor:
    """Per-block ``w in [0, 1]`` minimising ``|r - w a|^2`` (``r`` the PCA residual, ``a`` its AE
    reconstruction), both ``(N, 4096)`` float32; returns ``(N,)`` float32, 0 where ``a`` vanishes."""
    den = (a * a).sum(dim=1)
    num = (r * a).sum(dim=1)
    w = torch.where(den > _EPS, num / den.clamp_min(_EPS), torch.zeros_like(den))
    return w.clamp_(0.0, 1.0)


def weight_stats(codes: Any, tol: float = 1e-6) -> dict[str, float]:
    """How the per-block weights of ``parallel``/``sequential`` codes (last column) are distributed.

    Returns
    -------
    dict
        ``n``, ``at_0`` / ``at_1`` (fractions with ``w`` within ``tol`` of 0 / 1), ``between``,
        ``near_0`` / ``near_1`` (within 0.05), ``mean`` and ``median`` of ``w``.
    """
    w = np.asarray(codes.detach().cpu().numpy() if torch.is_tensor(codes) else codes, dtype=np.float64)[:, -1]
    n = max(len(w), 1)
    return {"n": int(len(w)), "at_0": float(np.sum(w <= tol) / n), "at_1": float(np.sum(w >= 1 - tol) / n),
            "between": float(np.sum((w > tol) & (w < 1 - tol)) / n),
            "near_0": float(np.sum(w <= 0.05) / n), "near_1": float(np.sum(w >= 0.95) / n),
            "mean": float(w.mean()) if len(w) else math.nan, "median": float(np.median(w)) if len(w) else math.nan}


class _Mixture(TrainableCodec):
    """Shared machinery of :class:`ParallelCodec` and :class:`SequentialCodec` (see the module docstring).

    Parameters
    ----------
    pca_size : int
        Code elements of the PCA part (the paper: 64).
    ae_size : int
        Code elements of the autoencoder part (the paper: 64).
    weight : "block" or float
        ``"block"``: per-block ``w`` stored as the last code element; a number in ``[0, 1]``: fixed ``w``.
    pca : {"default", "fit"}
        Take the PCA part from the shipped eigenshapes, or fit it on the training blocks.
    hidden : int
        Hidden width of the autoencoder (the paper: 512).
    training : dict or None
        :class:`sdfcodec_ae.TrainConfig` overrides for the autoencoder part.
    """

    prefix_ordered = False
    requires_fit = True
    code_sizes = (129,)
    capabilities = frozenset({"pretrained"})  # spec/codec-plugins.md, section 4a
    _ae_output: ClassVar[str]
    _shipped_phrase: ClassVar[str]  # where the shipped 64 + 64's weights come from, for benchmark records

    def __init__(self, pca_size: int = 64, ae_size: int = 64, weight: str | float = "block",
                 pca: str = "default", hidden: int = 512, training: dict | None = None):
        self.pca_size = pca_size
        self.ae_size = ae_size
        self.weight = weight
        self.pca = pca
        self.hidden = hidden
        self.training = training

    # -- parameters ---------------------------------------------------------------------------------
    @property
    def per_block(self) -> bool:
        """True when each code carries its own ``w`` (``weight="block"``)."""
        return self.weight == "block"

    @property
    def code_size(self) -> int:  # type: ignore[override]
        self._check_params()
        return self.pca_size + self.ae_size + int(self.per_block)

    def _check_params(self) -> None:
        cid = self.codec_id
        for name in ("pca_size", "ae_size"):
            v = getattr(self, name)
            if not isinstance(v, int) or isinstance(v, bool) or not 1 <= v <= _N:
                raise InvalidValueError(f"{cid} {name} must be an int in [1, {_N}], got {v!r}")
        if self.weight != "block" and not (isinstance(self.weight, (int, float)) and not isinstance(self.weight, bool)
                                           and 0.0 <= self.weight <= 1.0):
            raise InvalidValueError(f"{cid} weight must be 'block' (per-block w in the code) or a number in [0, 1] "
                                    f"(one w for the whole map), got {self.weight!r}")
        if self.pca not in ("default", "fit"):
            raise InvalidValueError(f"{cid} pca must be 'default' (shipped eigenshapes) or 'fit', got {self.pca!r}")

    def _new_pca(self) -> Codec:
        return sdfcodec.get_codec("pca", code_size=self.pca_size)

    def _new_ae(self) -> Codec:
        return sdfcodec.get_codec("ae", code_size=self.ae_size, hidden=self.hidden, output=self._ae_output,
                                  training=self.training)

    # -- assembling and fitting ---------------------------------------------------------------------
    @classmethod
    def from_parts(cls, pca_codec: Codec, ae_codec: Codec, *, weight: str | float = "block",
                   pca: str = "default") -> "_Mixture":
        """Assemble a fitted mixture from a fitted ``pca`` codec (``mean="dataset"``) and a fitted ``ae``
        codec (sigmoid output for parallel, tanh for sequential, trained on PCA residuals)."""
        if pca_codec.codec_id != "pca" or ae_codec.codec_id != "ae":
            raise InvalidValueError(f"{cls.codec_id} needs a 'pca' and an 'ae' codec, got "
                                    f"{pca_codec.codec_id!r} and {ae_codec.codec_id!r}")
        pcfg, acfg = pca_codec.get_config(), ae_codec.get_config()
        if pcfg.get("mean", "dataset") != "dataset":
            raise InvalidValueError(f"{cls.codec_id} uses a PCA part with mean='dataset', got {pcfg['mean']!r}")
        if acfg["output"] != cls._ae_output:
            raise InvalidValueError(f"{cls.codec_id} needs an ae part with output={cls._ae_output!r}, got "
                                    f"{acfg['output']!r}")
        out = cls(pca_size=pca_codec.code_size, ae_size=ae_codec.code_size, weight=weight, pca=pca,
                  hidden=acfg["hidden"], training=acfg.get("training"))
        return out._set_parts(pca_codec, ae_codec)

    def _set_parts(self, pca_codec: Codec, ae_codec: Codec) -> "_Mixture":
        self._check_params()
        self.pca_, self.ae_ = pca_codec, ae_codec
        return self

    def _pca_part(self, blocks: np.ndarray | None) -> Codec:
        if self.pca == "default":
            return pretrained_codec("pca", self.pca_size)
        if blocks is None:
            raise InvalidValueError(f"{self.codec_id} with pca='fit' needs training blocks")
        return self._new_pca().fit(blocks)

    def fit_validated(self, train: Any, validation: Any | None = None, *, checkpoint: str | Path | None = None,
                      resume: bool = False, report: str | Path | None = None, progress: bool | None = None,
                      **overrides: Any) -> "_Mixture":
        """Fit the PCA part (``pca="fit"``) and train the autoencoder part with early stopping on
        ``validation`` (None: a held-out 1/8 of ``train``); arguments as
        :meth:`sdfcodec_ae.AECodec.fit_validated`. ``train`` and ``validation``: normalised blocks
        ``(N, 16, 16, 16)`` float (numpy). Returns ``self``."""
        self._check_params()
        train = np.asarray(train, dtype=np.float32)
        if train.ndim != 4 or train.shape[1:] != (16, 16, 16):
            raise ShapeError(f"{self.codec_id} training blocks must have shape (N, 16, 16, 16), got {train.shape}")
        pca_codec = self._pca_part(train)
        ae = self._new_ae()
        ae_train, ae_val = self._ae_inputs(pca_codec, train), None
        if validation is not None:
            validation = np.asarray(validation, dtype=np.float32)
            ae_val = self._ae_inputs(pca_codec, validation)
        ae.fit_validated(ae_train, ae_val, checkpoint=checkpoint, resume=resume, report=report, progress=progress,
                         **overrides)
        self._set_parts(pca_codec, ae)
        self.history_ = ae.history_
        return self

    def write_training_report(self, prefix: str | Path) -> list[Path]:
        """Learning curves of the autoencoder part's last fit (the ``ae`` codec's ``write_training_report``)."""
        return self.ae_.write_training_report(prefix)

    @classmethod
    def pretrained(cls, code_size: int | None = None, weight: str | float = "block", **options: Any) -> "_Mixture":
        """The shipped 64 + 64 model with mixing ``weight``. ``code_size``: None, 64 (the size of each part), or
        the full code size (129 with ``weight="block"``, 128 with a fixed weight). A fresh codec each call.

        Raises:
            InvalidValueError: another size, or unknown options.
            ModelNotFoundError: a shipped model file is not installed.
        """
        full = 64 + 64 + int(weight == "block")
        if code_size not in (None, 64, full):
            raise InvalidValueError(f"only {cls.codec_id} 64 + 64 is shipped (code size {full} with weight="
                                    f"{weight!r}), not code size {code_size}; train other sizes with "
                                    f"sdfcodec.get_codec({cls.codec_id!r}, pca_size=..., ae_size=...).fit(...)")
        if options:
            raise InvalidValueError(f"the shipped {cls.codec_id} 64 + 64 takes only weight=, got {sorted(options)}")
        return cls._shipped_model(weight)

    @classmethod
    def shipped_models(cls) -> dict[str, tuple[int, ...]]:
        """``{"<id>-64-64": (128, 129)}``: the shipped 64 + 64 with a fixed or a per-block weight (``{}`` when its
        parts are not installed); nothing is loaded."""
        return {f"{cls.codec_id}-64-64": (128, 129)} if cls._shipped_installed() else {}

    @classmethod
    def shipped_state(cls, model: str, code_size: int) -> dict[str, np.ndarray]:
        """The shipped 64 + 64's arrays (the same for every weight, hence for code sizes 128 and 129)."""
        if code_size not in cls.shipped_models().get(model, ()):
            raise ModelNotFoundError(f"codec {cls.codec_id!r} ships no model {model!r} at code size {code_size}")
        return cls._shipped_model("block").state_dict()

    @classmethod
    def _shipped_installed(cls) -> bool:
        raise NotImplementedError

    @classmethod
    def _shipped_model(cls, weight: str | float) -> "_Mixture":
        raise NotImplementedError

    def _ae_inputs(self, pca_codec: Codec, blocks: np.ndarray) -> np.ndarray:
        """What the autoencoder part trains on: the blocks (parallel) or their PCA residuals (sequential)."""
        return blocks

    # -- state --------------------------------------------------------------------------------------
    def state_dict(self) -> dict[str, np.ndarray]:
        if not hasattr(self, "ae_"):
            return {}
        out = {f"pca.{k}": v for k, v in self.pca_.state_dict().items()}
        out.update({f"ae.{k}": v for k, v in self.ae_.state_dict().items()})
        return out

    def load_state_dict(self, state: Mapping[str, np.ndarray]) -> "_Mixture":
        self._check_params()
        parts: dict[str, dict[str, np.ndarray]] = {"pca": {}, "ae": {}}
        for k, v in state.items():
            head, _, rest = k.partition(".")
            if head not in parts or not rest:
                raise InvalidValueError(f"{self.codec_id} state array {k!r} is neither 'pca.*' nor 'ae.*'")
            parts[head][rest] = v
        return self._set_parts(self._new_pca().load_state_dict(parts["pca"]),
                               self._new_ae().load_state_dict(parts["ae"]))

    def _encode_shapes(self, p_enc: list, p_dec: list, a_enc: list, a_dec: list) -> list:
        raise NotImplementedError

    # -- encode / decode ----------------------------------------------------------------------------
    def _split(self, codes: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        k_p, k_a = self.pca_size, self.ae_size
        if self.per_block:
            w = codes[:, k_p + k_a]
        else:
            w = torch.full((len(codes),), float(self.weight), dtype=codes.dtype, device=codes.device)
        return codes[:, :k_p], codes[:, k_p:k_p + k_a], w

    def _join(self, cp: torch.Tensor, ca: torch.Tensor, w: torch.Tensor | None) -> torch.Tensor:
        return torch.cat([cp, ca] + ([w[:, None]] if w is not None else []), dim=1)


class ParallelCodec(_Mixture):
    """``w * PCA + (1 - w) * AE`` of a PCA and a sigmoid autoencoder, both fed the block.

    Codes ``(N, pca_size + ae_size [+ 1])``: PCA code, AE code, and (``weight="block"``) the block's ``w``.
    See the module docstring for the parameters and the line search.
    """

    codec_id = "parallel"
    _ae_output = "sigmoid"
    _shipped_phrase = "shipped (eigenshapes + ae-64.npz)"

    @classmethod
    def _shipped_installed(cls) -> bool:
        return all(get_codec_class(c).shipped_models() for c in ("pca", "ae"))

    @classmethod
    def _shipped_model(cls, weight: str | float) -> "ParallelCodec":
        return default_parallel(weight)

    def _encode_shapes(self, p_enc: list, p_dec: list, a_enc: list, a_dec: list) -> list:
        return p_enc + a_enc + ((p_dec + a_dec) if self.per_block else [])

    def _encode(self, blocks: torch.Tensor) -> torch.Tensor:
        cp, ca = self.pca_.encode(blocks), self.ae_.encode(blocks)
        if not self.per_block:
            return self._join(cp, ca, None)
        n = len(blocks)
        p = self.pca_.decode(cp).reshape(n, _N)
        a = self.ae_.decode(ca).reshape(n, _N)
        return self._join(cp, ca, parallel_weight(blocks.reshape(n, _N), p, a))

    def _decode(self, codes: torch.Tensor) -> torch.Tensor:
        cp, ca, w = self._split(codes)
        p, a = self.pca_.decode(cp), self.ae_.decode(ca)
        w = w[:, None, None, None]
        return w * p + (1.0 - w) * a


class SequentialCodec(_Mixture):
    """``PCA + w * AE(residual)``: a tanh autoencoder trained on the residuals of the PCA part.

    Codes ``(N, pca_size + ae_size [+ 1])``: PCA code, code of the residual ``x - PCA(x)``, and
    (``weight="block"``) the block's ``w``. See the module docstring.
    """

    codec_id = "sequential"
    _ae_output = "tanh"
    _shipped_phrase = "shipped (sequential-64-64.npz)"

    @classmethod
    def _shipped_installed(cls) -> bool:
        try:
            return bool(shipped_model_file(__name__, SHIPPED_SEQUENTIAL))
        except ModelNotFoundError:
            return False

    @classmethod
    def _shipped_model(cls, weight: str | float) -> "SequentialCodec":
        return default_sequential(weight)

    def _encode_shapes(self, p_enc: list, p_dec: list, a_enc: list, a_dec: list) -> list:
        return p_enc + p_dec + a_enc + (a_dec if self.per_block else [])

    def _ae_inputs(self, pca_codec: Codec, blocks: np.ndarray) -> np.ndarray:
        out = np.empty_like(blocks)
        for i in range(0, len(blocks), 4096):  # chunks: the residual set is as large as the data, not 2x
            b = blocks[i:i + 4096]
            out[i:i + 4096] = b - pca_codec.decode(pca_codec.encode(b))
        return out

    def _encode(self, blocks: torch.Tensor) -> torch.Tensor:
        n = len(blocks)
        cp = self.pca_.encode(blocks)
        r = blocks - self.pca_.decode(cp)
        ca = self.ae_.encode(r)
        if not self.per_block:
            return self._join(cp, ca, None)
        a = self.ae_.decode(ca).reshape(n, _N)
        return self._join(cp, ca, sequential_weight(r.reshape(n, _N), a))

    def _decode(self, codes: torch.Tensor) -> torch.Tensor:
        cp, ca, w = self._split(codes)
        return self.pca_.decode(cp) + w[:, None, None, None] * self.ae_.decode(ca)


# -- shipped 64 + 64 models -------------------------------------------------------------------------------
def default_parallel(weight: str | float = "block") -> ParallelCodec:
    """The shipped parallel 64 + 64: the shipped eigenshapes (first 64) beside the shipped AE-64."""
    return ParallelCodec.from_parts(pretrained_codec("pca", 64), pretrained_codec("ae", 64), weight=weight)


def default_sequential(weight: str | float = "block") -> SequentialCodec:
    """The shipped sequential 64 + 64 (``models/sequential-64-64.npz`` in this package: the shipped
    eigenshapes' first 64 and a tanh AE-64 trained on their residuals)."""
    base = load_shipped_model(__name__, SHIPPED_SEQUENTIAL)
    cfg = {k: v for k, v in base.get_config().items() if k != "id"}
    cfg["weight"] = weight
    return SequentialCodec(**cfg).load_state_dict(base.state_dict())


# -- benchmark registration (spec/codec-plugins.md, section 5; the table is in sdfcodec_ae.bench) ------------
def _bench_instance(cls: type[_Mixture]) -> Any:
    def build(code_size: int = 64, weight: str | float = "block") -> tuple[_Mixture, str]:
        """A ready ``code_size + code_size`` mixture without training: at 64 the shipped model when installed;
        else the shipped eigenshapes' first ``code_size`` components beside an untrained autoencoder of the
        paper's shapes (speed does not depend on the values)."""
        if code_size == 64:
            try:
                return cls.pretrained(weight=weight), cls._shipped_phrase
            except SDFCodecError:
                pass
        ae = get_codec_class("ae").untrained(code_size, 512, cls._ae_output)  # type: ignore[attr-defined]
        mix = cls.from_parts(pretrained_codec("pca", code_size), ae, weight=weight)
        return mix, f"shipped eigenshapes; ae {UNTRAINED}"
    return build


def _roofline(codec: Codec, operation: str) -> list[tuple[int, int]]:
    """Right-hand shapes of the matrix products of ``operation``: the PCA part's and the autoencoder's."""
    assert isinstance(codec, _Mixture)
    kp, ka, h = codec.pca_size, codec.ae_size, codec.hidden
    p_enc, p_dec = [(_N, kp)], [(kp, _N)]
    a_enc, a_dec = [(_N, h), (h, ka)], [(ka, h), (h, _N)]
    if operation == "decode":
        return p_dec + a_dec
    return codec._encode_shapes(p_enc, p_dec, a_enc, a_dec)


for _cls in (ParallelCodec, SequentialCodec):
    register_bench(_cls, instance=_bench_instance(_cls), roofline_shapes=_roofline)
