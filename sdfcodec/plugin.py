"""The toolkit for codec plugin authors: everything a plugin needs from sdfcodec besides :mod:`sdfcodec`,
:mod:`sdfcodec.errors` and :mod:`sdfcodec.testing` (spec/codec-plugins.md, section 6).

Checked tensors
    :data:`BLOCK` (16), :func:`as_float_tensor` (check shape/dtype/finiteness, convert to float32),
    :func:`like_input` (return a result the way the input came: numpy or a tensor), :func:`empty` (an
    uninitialised float32 tensor; on the CPU allocated so that large outputs get huge pages),
    :func:`affine_into` (``scale * values + offset`` written into a buffer in one pass: ``decode_into`` of a codec
    whose decode is a reshape).
Capabilities
    :func:`capabilities` (what a codec declares in ``capabilities``, checked; spec section 4a),
    :data:`CAPABILITIES` (the names a codec may declare).
Decoding into a caller's buffer
    :class:`DecodesInto` (the optional ``decode_into`` hook's signature), :func:`decodes_into` (does a codec
    declare it).
Encoding and decoding without torch
    :class:`NumpyPath` (what the optional ``numpy_path`` hook returns), :func:`numpy_path_of` (a codec's, when
    it declares it).
Decoding in cache-sized tiles
    :func:`run_tiles` (rows split into tiles over the CPU's cores, one BLAS thread each: the optional
    ``decode_tiles`` hook of a row-wise codec), :func:`scratch` (a per-thread reusable buffer),
    :func:`decodes_tiles` (does a codec declare ``decode_tiles``).
State and model files
    :func:`save_state_file` / :func:`load_state_file` (plain-array ``.npz``, never pickled),
    :func:`load_meta_file` (a ``.npz`` with a JSON metadata entry), :func:`save_model` / :func:`load_model`.
Shipped weights
    :func:`shipped_model_file` / :func:`load_shipped_model`: model files inside the plugin's own package,
    which its :meth:`Codec.pretrained` serves.
The registry
    :func:`get_codec`, :func:`get_codec_class`, :func:`pretrained_codec`: how one plugin reaches another's
    codec (a mixture its parts), never by importing the other plugin.
Training
    :class:`TrainableCodec`, the shared base of codecs trained with early stopping on a validation split;
    :class:`Dataset` / :func:`open_dataset` (training data sets).
Error-bounded field compression
    :func:`sz3_compress` / :func:`sz3_decompress`: SZ3 streams through pysz with an absolute bound, their
    failures as :class:`~sdfcodec.errors.FormatError` (the ``sz3`` codec; maps use the same functions).
Light imports
    :func:`lazy_module` (``torch = lazy_module("torch")``: imported on first attribute access, so that listing
    codecs and reading map headers never import torch; spec/codec-plugins.md, section 6), :func:`is_tensor`.
Benchmarks
    :func:`register_bench` (a ready instance and the roofline shapes), :func:`bench_instance`,
    :func:`bench_codec_instance`, :func:`roofline_shapes`.
"""

from __future__ import annotations

import abc
import warnings
from importlib import resources
from pathlib import Path
from typing import TYPE_CHECKING, Any

from .core._lazy import is_tensor, lazy_exports, lazy_module
from .core._validate import BLOCK, affine_into, as_float_tensor, empty, like_input
from .codec import CAPABILITIES, Codec, DecodesInto, NumpyPath, capabilities, decodes_into, decodes_tiles, numpy_path_of
from .errors import InvalidValueError, ModelNotFoundError
from .model import load_meta_file, load_model, load_state_file, save_model, save_state_file
from .registry import get_codec, get_codec_class, pretrained_codec
from .core.tiling import run_tiles, scratch

if TYPE_CHECKING:
    from .core.dataset import Dataset

__all__ = ["BLOCK", "as_float_tensor", "like_input", "empty", "affine_into", "CAPABILITIES", "capabilities",
           "DecodesInto", "decodes_into", "NumpyPath", "numpy_path_of",
           "decodes_tiles", "run_tiles", "scratch",
           "save_state_file", "load_state_file", "load_meta_file", "save_model", "load_model",
           "shipped_model_file", "load_shipped_model",
           "get_codec", "get_codec_class", "pretrained_codec",
           "Codec", "TrainableCodec", "Dataset", "open_dataset",
           "register_bench", "bench_instance", "bench_codec_instance", "roofline_shapes", "sz3_compress",
           "sz3_decompress", "lazy_module", "is_tensor"]

# Names that import Zarr, or the benchmarks (an HTTP server and ssl: 30 ms), loaded on first use (PEP 562): a
# plugin module imports this one, and `sdfcodec info` (which loads a plugin to name a map's shipped model) must
# stay light
_LAZY = {"Dataset": ".core.dataset", "open_dataset": ".core.dataset", "sz3_compress": ".map.field",
         "sz3_decompress": ".map.field", "register_bench": ".bench", "bench_instance": ".bench",
         "bench_codec_instance": ".bench", "roofline_shapes": ".bench"}


__getattr__, __dir__ = lazy_exports(__name__, _LAZY, "sdfcodec")

_SHIPPED: dict[tuple[str, str], Codec] = {}


def shipped_model_file(package: str, name: str) -> Path:
    """Path of the model file ``models/<name>`` shipped inside the installed package ``package`` (a plugin
    passes its own ``__name__``; the file is package data, e.g. ``"sdfcodec_ae"``, ``"ae-64.npz"``).

    Raises:
        ModelNotFoundError: the package does not hold that file (not trained yet, or not installed with it).
    """
    ref = resources.files(package) / "models" / name
    if not ref.is_file():
        raise ModelNotFoundError(f"no shipped model {name!r} in {package}/models; train one with `sdfcodec train` "
                                 "(or the plugin's training script) and pass it with --model")
    return Path(str(ref))


def load_shipped_model(package: str, name: str) -> Codec:
    """The codec saved in :func:`shipped_model_file` ``(package, name)``, loaded once per process and shared:
    do not fit or change it; derive fresh codecs from its ``get_config()`` / ``state_dict()``."""
    key = (package, name)
    if key not in _SHIPPED:
        _SHIPPED[key] = load_model(shipped_model_file(package, name))
    return _SHIPPED[key]


class TrainableCodec(Codec):
    """Shared base of codecs trained by gradient descent with early stopping on a validation split (the
    built-in ``ae``, ``parallel`` and ``sequential``).

    A subclass implements :meth:`fit_validated` and :meth:`write_training_report`; :meth:`fit` (through
    ``_fit``) trains with a held-out part of the blocks, :meth:`fit_dataset` with a data set's splits. After
    training, ``history_`` holds the learning curves (it is not state: a loaded codec has none).
    """

    requires_fit = True

    def _fit(self, blocks: Any) -> None:
        self.fit_validated(blocks)

    @abc.abstractmethod
    def fit_validated(self, train: Any, validation: Any | None = None, *, checkpoint: str | Path | None = None,
                      resume: bool = False, report: str | Path | None = None, progress: bool | None = None,
                      **overrides: Any) -> "TrainableCodec":
        """Train on normalised blocks ``train`` ``(N, 16, 16, 16)`` float, early-stopping on ``validation``
        (None: a seeded held-out part of ``train``); resumable from ``checkpoint`` (``resume``); learning
        curves written to ``report`` when given; ``overrides`` are training settings for this run only (not
        part of the configuration). Returns ``self``."""

    @abc.abstractmethod
    def write_training_report(self, prefix: str | Path) -> list[Path]:
        """Write the learning curves of the last fit under ``prefix``; returns the files written.

        Raises:
            InvalidValueError: the codec was loaded, not trained in this process (no ``history_``).
        """

    def fit_dataset(self, dataset: Dataset, *, max_train: int | None = None, **kwargs: Any) -> "TrainableCodec":
        """Train on a :class:`Dataset`'s ``train`` split (at most ``max_train`` blocks), early-stopping on its
        ``validation`` split (the paper's protocol); ``kwargs`` as :meth:`fit_validated`."""
        return self.fit_validated(dataset.load("train", max_train), dataset.load("validation"), **kwargs)

    def _require_history(self) -> Any:
        if not hasattr(self, "history_"):
            raise InvalidValueError("no learning curves: this codec was loaded, not trained in this process")
        return self.history_

    @classmethod
    def shipped(cls, *args: Any, **kwargs: Any) -> "Codec":
        """Deprecated name of :meth:`Codec.pretrained`."""
        warnings.warn(f"{cls.__qualname__}.shipped is deprecated: use {cls.__qualname__}.pretrained",
                      DeprecationWarning, stacklevel=2)
        return cls.pretrained(*args, **kwargs)
