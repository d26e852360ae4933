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
AE-64 (``sdfcodec/models/ae-64.npz``, float16 weights) loads with :func:`default_ae`.

The code is not prefix-ordered: every element of a code feeds every decoder unit.
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path
from typing import Any, Mapping

import numpy as np
import torch

from sdfcodec import Codec
from sdfcodec.errors import InvalidValueError, MapNotFoundError
from sdfcodec.model import load_model, load_state_file, save_model, save_state_file

from .network import N_VOXELS, OUTPUTS, Inference, check_state
from .train import TrainConfig, TrainResult, train_autoencoder, write_curves

__all__ = ["AECodec", "TrainConfig", "TrainResult", "train_autoencoder", "write_curves", "default_ae",
           "shipped_model_path", "save_model_float16", "bench_records"]


class AECodec(Codec):
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

    # -- fitting ------------------------------------------------------------------------------------
    def _fit(self, blocks: np.ndarray) -> None:
        self.fit_validated(blocks)

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

    def fit_dataset(self, dataset: Any, *, max_train: int | None = None, **kwargs: Any) -> "AECodec":
        """Train on an :class:`sdfcodec.dataset.Dataset`'s ``train`` split, early-stopping on its
        ``validation`` split (the paper's protocol); ``kwargs`` as :meth:`fit_validated`."""
        return self.fit_validated(dataset.load("train", max_train), dataset.load("validation"), **kwargs)

    def write_training_report(self, prefix: str | Path) -> list[Path]:
        """Write the learning curves of the last fit to ``<prefix>.curves.json`` / ``.curves.png``."""
        if not hasattr(self, "history_"):
            raise InvalidValueError("no learning curves: this codec was loaded, not trained in this process")
        return write_curves(self.history_, prefix, title=f"ae-{self.code_size} ({self.output} output)")

    # -- state --------------------------------------------------------------------------------------
    def state_dict(self) -> dict[str, np.ndarray]:
        return dict(self.state_) if hasattr(self, "state_") else {}

    def load_state_dict(self, state: Mapping[str, np.ndarray]) -> "AECodec":
        self._check_params()
        arrays = check_state(state, self.code_size, self.hidden, what=f"ae-{self.code_size}")
        self.state_ = arrays
        self._net = Inference(arrays, self.output)
        return self

    @classmethod
    def shipped(cls, code_size: int = 64) -> "AECodec":
        """The trained model shipped with sdfcodec at ``code_size`` (see :func:`default_ae`)."""
        return default_ae(code_size)

    # -- benchmark hooks (sdfcodec.bench) -----------------------------------------------------------
    @classmethod
    def bench_instance(cls, code_size: int) -> tuple["AECodec", str]:
        """For ``sdfcodec bench``: the shipped AE-64 at 64, else untrained weights of the paper's shapes
        (no training; speed does not depend on the values). Returns the codec and where its weights come from."""
        from .bench import ae_bench_instance

        return ae_bench_instance(code_size)

    def roofline_shapes(self, operation: str) -> list[tuple[int, int]]:
        """For ``sdfcodec bench``: right-hand shapes of the two matrix products of ``operation``."""
        from .bench import ae_roofline_shapes

        return ae_roofline_shapes(self.code_size, self.hidden, operation)

    # -- encode / decode ----------------------------------------------------------------------------
    def _encode(self, blocks: torch.Tensor) -> torch.Tensor:
        return self._net.encode(blocks.reshape(len(blocks), N_VOXELS))

    def _decode(self, codes: torch.Tensor) -> torch.Tensor:
        return self._net.decode(codes).reshape(len(codes), 16, 16, 16)


# -- shipped weights --------------------------------------------------------------------------------------
def shipped_model_path(name: str) -> Path:
    """Path of a model file shipped in :mod:`sdfcodec.models` (e.g. ``"ae-64.npz"``).

    Raises
    ------
    MapNotFoundError
        The file is not in the installed package.
    """
    ref = resources.files("sdfcodec.models") / name
    if not ref.is_file():
        raise MapNotFoundError(f"no shipped model {name!r} in sdfcodec.models; train one with "
                               "`python examples/train_ae_models.py` or `sdfcodec train` and pass it with --model")
    return Path(str(ref))


_SHIPPED: dict[str, Codec] = {}


def _shipped(name: str) -> Codec:
    if name not in _SHIPPED:
        _SHIPPED[name] = load_model(shipped_model_path(name))
    return _SHIPPED[name]


def default_ae(code_size: int = 64) -> AECodec:
    """The shipped trained AE (only ``code_size=64`` is shipped; train other sizes with ``sdfcodec train``).

    The weights are stored as float16 and computed in float32. Returns a fresh codec each call (sharing the
    read-only arrays), so callers may change its ``training`` without affecting others.
    """
    if code_size != 64:
        raise InvalidValueError(f"only ae-64 is shipped, not ae-{code_size}: train it with `sdfcodec train DATASET "
                                f"--codec ae --code-size {code_size} -o MODEL` and load it with --model")
    base = _shipped("ae-64.npz")
    return AECodec(**{k: v for k, v in base.get_config().items() if k != "id"}).load_state_dict(base.state_dict())


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


def __getattr__(name: str) -> Any:  # bench_records imports sdfcodec.bench lazily
    if name == "bench_records":
        from .bench import bench_records

        return bench_records
    raise AttributeError(name)
