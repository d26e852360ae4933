"""The ``ae`` codec: the paper's autoencoder, ``4096 - 512 - d - 512 - 4096`` with sigmoid units.

The encoder's two layers map a normalised block to a code of ``d`` values in ``(0, 1)`` (the code layer is
sigmoid too, as in the paper); the decoder's two layers map it back. The network is described in
:mod:`sdfcodec_ae.network`, its training (the paper's batch gradient descent or mini-batch Adam, early
stopping on the validation error, resumable checkpoints, learning curves) in :mod:`sdfcodec_ae.train`.

Usage::

    import sdfcodec
    ae = sdfcodec.get_codec("ae", code_size=64).fit(blocks)       # holds out 1/8 of blocks for validation
    ae = sdfcodec.get_codec("ae", code_size=64, training={"optimizer": "gd"})   # the paper's setting
    ae.fit_validated(train, validation, checkpoint="run/ae64.ckpt", resume=True, report="run/ae64")
    codes = ae.encode(blocks)                                       # (N, 64) float32 in (0, 1)

``sdfcodec train DATASET --codec ae --code-size 64 -o MODEL`` trains with the defaults (Adam). The shipped
AE-64 (``models/ae-64.npz`` in this package, float16 weights) loads with :meth:`AECodec.pretrained`
(``sdfcodec.pretrained_codec("ae", 64)``).

The code is not prefix-ordered: every element of a code feeds every decoder unit.
"""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from sdfcodec import Codec
from sdfcodec.errors import InvalidValueError, ModelNotFoundError
from sdfcodec.plugin import (TrainableCodec, lazy_module, load_shipped_model, load_state_file, register_bench,
                             save_model, save_state_file, shipped_model_file)

from .network import N_VOXELS, OUTPUTS, Inference, build_module, check_state, export_state, module_state
from .train import TrainConfig, TrainResult, train_autoencoder, write_curves

torch = lazy_module("torch")  # imported on first use: listing codecs and reading headers never need it

__all__ = ["AECodec", "TrainConfig", "TrainResult", "train_autoencoder", "write_curves", "default_ae",
           "shipped_model_path", "save_model_float16", "bench_records", "SHIPPED_MODEL"]

SHIPPED_MODEL = "ae-64.npz"  # in this package's models/


class AECodec(TrainableCodec):
    """Autoencoder codec.

    Parameters
    ----------
    code_size : int
        Width ``d`` of the code layer (the paper: 32, 64, 128).
    hidden : int
        Width of the two hidden layers (the paper: 512).
    output : {"sigmoid", "tanh"}
        Output activation: sigmoid for normalised blocks in ``[0, 1]``; tanh for zero-centred inputs such
        as the residuals the sequential codec feeds it.
    training : dict or None
        Overrides of :class:`~sdfcodec_ae.train.TrainConfig` used by :meth:`fit` (JSON values only, e.g.
        ``{"optimizer": "gd", "seed": 3}``). They do not change the format of codes.

    Notes
    -----
    Learned state (``state_dict``): ``enc1.weight (hidden, 4096)``, ``enc1.bias (hidden,)``,
    ``enc2.weight (d, hidden)``, ``enc2.bias (d,)``, ``dec1.weight (hidden, d)``, ``dec1.bias (hidden,)``,
    ``dec2.weight (4096, hidden)``, ``dec2.bias (4096,)``: float32 (float16 arrays load and are widened).
    After fitting, ``history_`` holds the learning curves (:meth:`TrainResult.summary`); it is not state.
    """

    codec_id = "ae"
    prefix_ordered = False
    requires_fit = True
    code_sizes = (32, 64, 128)
    capabilities = frozenset({"pretrained"})  # spec/codec-plugins.md, section 4a

    def __init__(self, code_size: int = 64, hidden: int = 512, output: str = "sigmoid",
                 training: dict | None = None):
        self.code_size = code_size
        self.hidden = hidden
        self.output = output
        self.training = training

    # -- parameters ---------------------------------------------------------------------------------
    def _check_params(self) -> None:
        for name in ("code_size", "hidden"):
            v = getattr(self, name)
            if not isinstance(v, int) or isinstance(v, bool) or not 1 <= v <= N_VOXELS:
                raise InvalidValueError(f"ae {name} must be an int in [1, {N_VOXELS}], got {v!r}")
        if self.output not in OUTPUTS:
            raise InvalidValueError(f"ae output must be one of {OUTPUTS}, got {self.output!r}")
        if self.training is not None and not isinstance(self.training, dict):
            raise InvalidValueError(f"ae training must be a dict of TrainConfig settings or None, "
                                    f"got {type(self.training).__name__}")

    def train_config(self, **overrides: Any) -> TrainConfig:
        """The :class:`TrainConfig` :meth:`fit` uses: defaults, then ``training``, then ``overrides``."""
        self._check_params()
        return TrainConfig.from_dict({**(self.training or {}), **overrides})

    # -- fitting (fit and fit_dataset come from TrainableCodec) ----------------------------------------
    def fit_validated(self, train: Any, validation: Any | None = None, *, checkpoint: str | Path | None = None,
                      resume: bool = False, report: str | Path | None = None, progress: bool | None = None,
                      **overrides: Any) -> "AECodec":
        """Train on ``train`` with early stopping on ``validation``; returns ``self``.

        Parameters
        ----------
        train : array_like
            Normalised blocks ``(N, 16, 16, 16)`` (or ``(N, 4096)``), numpy or torch, any float dtype.
        validation : array_like or None
            Held-out blocks for early stopping; None: a seeded ``val_fraction`` (1/8) of ``train``.
        checkpoint : path or None
            Checkpoint prefix (overrides the ``training`` setting); files ``<prefix>.npz`` / ``.json``.
        resume : bool
            Continue from ``checkpoint`` when it exists.
        report : path or None
            Write learning curves to ``<report>.curves.json`` and ``<report>.curves.png``.
        progress : bool or None
            Show progress bars (None: the ``training`` setting, default True).
        **overrides
            Further :class:`TrainConfig` settings for this run only (e.g. ``threads=1``); unlike ``training``
            they are not part of the codec's configuration, so they do not end up in maps or model files.
        """
        over: dict[str, Any] = dict(overrides)
        if checkpoint is not None:
            over["checkpoint"] = str(checkpoint)
        if progress is not None:
            over["progress"] = progress
        cfg = self.train_config(**over)
        result = train_autoencoder(train, validation, code_size=self.code_size, hidden=self.hidden,
                                   output=self.output, config=cfg, resume=resume)
        self.load_state_dict(result.state)
        self.history_ = result.summary()
        if report is not None:
            self.write_training_report(report)
        return self

    def write_training_report(self, prefix: str | Path) -> list[Path]:
        """Write the learning curves of the last fit to ``<prefix>.curves.json`` / ``.curves.png``."""
        return write_curves(self._require_history(), prefix, title=f"ae-{self.code_size} ({self.output} output)")

    # -- state --------------------------------------------------------------------------------------
    def state_dict(self) -> dict[str, np.ndarray]:
        return dict(self.state_) if hasattr(self, "state_") else {}

    def load_state_dict(self, state: Mapping[str, np.ndarray]) -> "AECodec":
        self._check_params()
        arrays = check_state(state, self.code_size, self.hidden, what=f"ae-{self.code_size}")
        self.state_ = arrays
        self._net = Inference(arrays, self.output)
        return self

    # -- ready-made weights -------------------------------------------------------------------------
    @classmethod
    def pretrained(cls, code_size: int | None = None, **options: Any) -> "AECodec":
        """The shipped trained AE (``models/ae-64.npz``; only ``code_size=64``, the default, is shipped: train
        other sizes with ``sdfcodec train``). The weights are stored as float16 and computed in float32. A
        fresh codec each call (sharing the read-only arrays), so callers may change its ``training``.

        Raises:
            InvalidValueError: another size, or options given.
            ModelNotFoundError: the model file is not installed.
        """
        k = 64 if code_size is None else code_size
        if k != 64:
            raise InvalidValueError(f"only ae-64 is shipped, not ae-{k}: train it with `sdfcodec train DATASET "
                                    f"--codec ae --code-size {k} -o MODEL` and load it with --model")
        if options:
            raise InvalidValueError(f"the shipped ae-64 takes no options, got {sorted(options)}")
        base = load_shipped_model(__name__, SHIPPED_MODEL)
        return cls(**{n: v for n, v in base.get_config().items() if n != "id"}).load_state_dict(base.state_dict())

    @classmethod
    def shipped_models(cls) -> dict[str, tuple[int, ...]]:
        """``{"ae-64": (64,)}`` (``{}`` when the file is not installed); nothing is loaded."""
        try:
            shipped_model_file(__name__, SHIPPED_MODEL)
        except ModelNotFoundError:
            return {}
        return {SHIPPED_MODEL.removesuffix(".npz"): (64,)}

    @classmethod
    def untrained(cls, code_size: int = 64, hidden: int = 512, output: str = "sigmoid", seed: int = 0) -> "AECodec":
        """A ready codec with the network's initial (untrained) weights, deterministic by ``seed`` (seeds
        torch's global generator, as training does): for timing, where the values do not matter."""
        torch.manual_seed(seed)
        state = export_state(module_state(build_module(code_size, hidden, output)))
        return cls(code_size=code_size, hidden=hidden, output=output).load_state_dict(state)

    # -- encode / decode ----------------------------------------------------------------------------
    def _encode(self, blocks: torch.Tensor) -> torch.Tensor:
        return self._net.encode(blocks.reshape(len(blocks), N_VOXELS))

    def _decode(self, codes: torch.Tensor) -> torch.Tensor:
        return self._net.decode(codes).reshape(len(codes), 16, 16, 16)


# -- shipped weights --------------------------------------------------------------------------------------
def shipped_model_path(name: str) -> Path:
    """Deprecated: :func:`sdfcodec.plugin.shipped_model_file` ``("sdfcodec_ae", name)``, the path of a model
    file in this package's ``models/`` (raises :class:`~sdfcodec.errors.ModelNotFoundError` when absent)."""
    warnings.warn("sdfcodec_ae.shipped_model_path is deprecated: use "
                  "sdfcodec.plugin.shipped_model_file('sdfcodec_ae', name)", DeprecationWarning, stacklevel=2)
    return shipped_model_file(__name__, name)


def default_ae(code_size: int = 64) -> AECodec:
    """The shipped trained AE: :meth:`AECodec.pretrained` (only ``code_size=64`` is shipped)."""
    return AECodec.pretrained(code_size)


def save_model_float16(codec: Codec, path: str | Path, keep_float32: tuple[str, ...] = ()) -> Path:
    """Save ``codec`` like :func:`sdfcodec.save_model`, with its float32 arrays stored as float16 (half the
    size; loaders widen them back). Arrays whose names start with a prefix in ``keep_float32`` stay float32.
    The codec itself is not changed: round its weights first (``load_state_dict`` of the float16 arrays) if
    you want to evaluate exactly what is shipped."""
    path = Path(save_model(codec, path))
    arrays = load_state_file(path)
    out = {k: (v.astype(np.float16) if v.dtype == np.float32 and not k.startswith(keep_float32) else v)
           for k, v in arrays.items()}
    save_state_file(path, out)
    return path


# -- benchmark registration (spec/codec-plugins.md, section 5) --------------------------------------------
def _bench_instance(code_size: int) -> tuple[Codec, str]:
    from .bench import ae_bench_instance

    return ae_bench_instance(code_size)


def _roofline(codec: Codec, operation: str) -> list[tuple[int, int]]:
    from .bench import ae_roofline_shapes

    return ae_roofline_shapes(codec.code_size, codec.hidden, operation)  # type: ignore[attr-defined]


register_bench(AECodec, instance=_bench_instance, roofline_shapes=_roofline)


def __getattr__(name: str) -> Any:  # bench_records imports this plugin's bench module lazily
    if name == "bench_records":
        from .bench import bench_records

        return bench_records
    raise AttributeError(name)
