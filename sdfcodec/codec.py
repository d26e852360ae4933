"""The codec contract: what every sdfcodec codec is and promises.

A codec turns normalised TSDF blocks into short code vectors and back. Normalised means
``v = (d - d_min) / (d_max - d_min)`` so values lie in ``[0, 1]`` and free or unobserved space is 1.0.

A codec is a subclass of :class:`Codec` that:

* sets the class attributes ``codec_id`` (the registry name, ``[a-z0-9][a-z0-9_.-]*``), ``prefix_ordered``
  (True when the first ``k' < k`` code elements still decode, coarser: PCA), ``requires_fit`` (True when
  it learns state from data) and optionally ``code_sizes`` (the sizes it is meant to be used at);
* has an ``__init__`` that only stores its keyword arguments, under attributes of the same names
  (scikit-learn style). Those arguments, plus ``"id"``, are its JSON configuration: ``get_config()``
  returns them and ``from_config`` / :func:`sdfcodec.get_codec` rebuild an equal codec;
* has ``code_size`` (an ``__init__`` argument or a property), implements ``_encode`` and ``_decode`` on float32 torch tensors
  ``(N, 16, 16, 16) -> (N, code_size)`` and ``(N, k) -> (N, 16, 16, 16)``, computing on the tensor's device;
* if ``requires_fit``: implements ``_fit`` and keeps learned state in attributes ending in ``_``, exposed as
  plain arrays through ``state_dict`` / ``load_state_dict`` (no pickles, ever).

The public ``encode``/``decode``/``fit`` of the base class check shapes, dtypes and finiteness (raising
:mod:`sdfcodec.errors` types), convert numpy or any-float input to float32, and return a result that
follows the input: numpy in, numpy out; a tensor in, a tensor on the same device out. Both are batched.

``sdfcodec.testing.check_codec`` verifies all of this for any codec; plugins run it in their own tests.
"""

from __future__ import annotations

import abc
import copy
import inspect
from typing import Any, ClassVar, Iterable, Iterator, Mapping

import numpy as np
import torch

from ._validate import BLOCK, as_float_tensor, empty, like_input
from .errors import InvalidValueError, NotFittedError, ShapeError

__all__ = ["Codec", "BLOCK", "empty"]


class Codec(abc.ABC):
    """Abstract base of all codecs. See the module docstring for the contract."""

    codec_id: ClassVar[str]
    prefix_ordered: ClassVar[bool] = False
    requires_fit: ClassVar[bool] = False
    code_sizes: ClassVar[tuple[int, ...]] = ()
    #: Voxels of neighbour context the decoder needs on each side (0: blocks decode on their own). A codec
    #: with ``halo > 0`` also implements ``_decode_context``; map readers then decode neighbouring blocks and
    #: hand it the assembled neighbourhood, so block seams vanish (spec/codec-plugins.md, "Halo").
    halo: ClassVar[int] = 0

    #: Length ``k`` of one block's code vector: an ``__init__`` argument or a property of the subclass.
    code_size: int

    # -- what subclasses implement -------------------------------------------------------------------

    @abc.abstractmethod
    def _encode(self, blocks: torch.Tensor) -> torch.Tensor:
        """``(N, 16, 16, 16)`` float32 -> ``(N, code_size)`` float32, on ``blocks.device``."""

    @abc.abstractmethod
    def _decode(self, codes: torch.Tensor) -> torch.Tensor:
        """``(N, k)`` float32 -> ``(N, 16, 16, 16)`` float32 on ``codes.device``; ``k < code_size`` only
        when ``prefix_ordered``."""

    def _decode_context(self, padded: torch.Tensor) -> torch.Tensor:  # pragma: no cover - halo codecs only
        """``(N, X + 2 halo, Y + 2 halo, Z + 2 halo)`` normalised values assembled from ``_decode`` outputs of
        neighbouring blocks (1.0 where there is none) -> ``(N, X, Y, Z)`` final values."""
        raise NotImplementedError

    def _fit(self, blocks: np.ndarray) -> None:  # pragma: no cover - codecs without state never call it
        """Learn state from ``(N, 16, 16, 16)`` float32 numpy blocks."""
        raise NotImplementedError

    @property
    def is_fitted(self) -> bool:
        """True when the codec can encode and decode (always, for codecs that need no fitting)."""
        return not self.requires_fit or bool(self.state_dict())

    def state_dict(self) -> dict[str, np.ndarray]:
        """Learned state as plain numpy arrays (empty for codecs without state)."""
        return {}

    def load_state_dict(self, state: Mapping[str, np.ndarray]) -> "Codec":
        """Restore learned state written by :meth:`state_dict`; returns ``self``."""
        if state:
            raise InvalidValueError(f"codec {self.codec_id!r} has no learned state, got arrays {sorted(state)}")
        return self

    # -- the public, checked surface -----------------------------------------------------------------
    def fit(self, blocks: Any) -> "Codec":
        """Learn the codec's state from normalised blocks ``(N, 16, 16, 16)``; returns ``self``."""
        if self.requires_fit:
            t, _ = as_float_tensor(blocks, "blocks", (None, BLOCK, BLOCK, BLOCK))
            if t.shape[0] == 0:
                raise ShapeError("fit needs at least one block, got an empty batch")
            self._fit(t.cpu().numpy())
        return self

    def fit_stream(self, batches: Iterable[Any]) -> "Codec":
        """Learn from an iterable of normalised block batches ``(N_i, 16, 16, 16)``, for data sets larger than
        memory; returns ``self``. Codecs that learn incrementally implement ``_fit_stream(iterator of float32
        numpy batches)``; for the others the batches are concatenated and passed to :meth:`fit`."""
        if not self.requires_fit:
            return self
        checked = (as_float_tensor(b, "blocks", (None, BLOCK, BLOCK, BLOCK))[0].cpu().numpy() for b in batches)
        if type(self)._fit_stream is Codec._fit_stream:
            return self.fit(np.concatenate(list(checked)))
        self._fit_stream(checked)
        return self

    def _fit_stream(self, batches: Iterator[np.ndarray]) -> None:  # pragma: no cover - see fit_stream
        raise NotImplementedError

    def encode(self, blocks: Any) -> Any:
        """Encode normalised blocks ``(N, 16, 16, 16)`` to codes ``(N, code_size)`` (float32).

        numpy in gives numpy out; a torch tensor gives a tensor on the same device.
        """
        self._check_fitted()
        t, was_numpy = as_float_tensor(blocks, "blocks", (None, BLOCK, BLOCK, BLOCK))
        if t.shape[0] == 0:
            return like_input(t.new_zeros((0, self.code_size)), was_numpy)
        return like_input(self._encode(t), was_numpy)

    def _checked_codes(self, codes: Any) -> tuple[torch.Tensor, bool]:
        """``codes`` as a float32 tensor, checked: finite, ``(N, k)`` with ``k == code_size`` or, for prefix-ordered
        codecs, ``1 <= k <= code_size``."""
        self._check_fitted()
        t, was_numpy = as_float_tensor(codes, "codes", (None, None))
        k = t.shape[1]
        if self.prefix_ordered:
            if not 1 <= k <= self.code_size:
                raise ShapeError(f"codes for {self!r} must have 1..{self.code_size} elements, got {k}")
        elif k != self.code_size:
            raise ShapeError(f"codes for {self!r} must have {self.code_size} elements, got {k}"
                             " (this codec is not prefix-ordered, so a shorter code cannot be decoded)")
        return t, was_numpy

    def decode(self, codes: Any) -> Any:
        """Decode codes ``(N, k)`` to normalised blocks ``(N, 16, 16, 16)`` (float32).

        ``k`` must equal ``code_size``, or, for prefix-ordered codecs, be any ``1 <= k <= code_size``
        (a prefix decodes to a coarser block). Output follows the input like :meth:`encode`.
        """
        t, was_numpy = self._checked_codes(codes)
        if t.shape[0] == 0:
            return like_input(t.new_zeros((0, BLOCK, BLOCK, BLOCK)), was_numpy)
        out = self._decode(t)
        if self.halo:
            # alone, a block has no neighbours: repeat its faces as the context (maps give the real ones)
            h = self.halo
            out = self._decode_context(torch.nn.functional.pad(out[:, None], (h,) * 6, mode="replicate")[:, 0])
        return like_input(out, was_numpy)

    def decode_context(self, padded: Any) -> Any:
        """Finish decoding with neighbour context: ``(N, X + 2h, Y + 2h, Z + 2h)`` normalised values (blocks
        decoded by :meth:`decode_core`, assembled; 1.0 where there is no block) -> ``(N, X, Y, Z)``, with
        ``h = halo``. For ``halo == 0`` it is the identity."""
        t, was_numpy = as_float_tensor(padded, "padded", (None, None, None, None))
        h = self.halo
        if min(t.shape[1:]) <= 2 * h:
            raise ShapeError(f"padded volumes for {self!r} need more than {2 * h} voxels per axis, got {tuple(t.shape)}")
        return like_input(self._decode_context(t) if h else t, was_numpy)

    def decode_core(self, codes: Any, *, scale: float = 1.0, offset: float = 0.0) -> Any:
        """Decode without neighbour context (what :meth:`decode_context` assembles), as ``scale * v + offset``:
        ``(N, k) -> (N, 16, 16, 16)``. With the defaults it equals :meth:`decode` for codecs with ``halo == 0``;
        map readers pass ``scale = d_max - d_min, offset = d_min`` to get metres in the same pass (codecs whose
        last step is linear fold it into their weights, see :meth:`_decode_affine`)."""
        if not self.halo and scale == 1.0 and offset == 0.0:
            return self.decode(codes)
        t, was_numpy = self._checked_codes(codes)
        if t.shape[0] == 0:
            return like_input(t.new_zeros((0, BLOCK, BLOCK, BLOCK)), was_numpy)
        return like_input(self._decode_affine(t, float(scale), float(offset)), was_numpy)

    # -- optional hooks (the defaults are correct for every codec; overriding only makes them faster) --------
    def _decode_affine(self, codes: torch.Tensor, scale: float, offset: float) -> torch.Tensor:
        """``scale * _decode(codes) + offset`` for checked float32 codes ``(N, k)``. The default adds one fused
        pass over the output (in place unless the output is a view of ``codes``); a codec whose decode ends in
        a linear layer MAY override it to fold ``scale`` and ``offset`` into that layer (PCA does)."""
        out = self._decode(codes)
        if scale == 1.0 and offset == 0.0:
            return out
        aliased = out.untyped_storage().data_ptr() == codes.untyped_storage().data_ptr()
        base = torch.tensor(offset, dtype=out.dtype, device=out.device)
        return torch.add(base, out, alpha=scale) if aliased else torch.add(base, out, alpha=scale, out=out)

    def _decode_bound(self, codes: torch.Tensor) -> float | None:
        """An upper bound on ``|_decode(codes)|`` over all outputs, or None (the default) when the codec cannot
        give one cheaply. Map readers check decoded blocks for NaN/Inf (a broken learned state) with a pass
        over the output; a finite bound proves them finite without it (PCA: from the codes and its basis)."""
        return None

    # -- configuration -------------------------------------------------------------------------------
    @classmethod
    def _param_names(cls) -> list[str]:
        sig = inspect.signature(cls.__init__)
        return [p.name for p in sig.parameters.values()
                if p.name != "self" and p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY)]

    def get_config(self) -> dict[str, Any]:
        """JSON-serialisable configuration: ``{"id": codec_id, **init arguments}``."""
        cfg: dict[str, Any] = {"id": self.codec_id}
        for name in self._param_names():
            cfg[name] = copy.deepcopy(getattr(self, name))
        return cfg

    @classmethod
    def from_config(cls, config: Mapping[str, Any]) -> "Codec":
        """Build an (unfitted) codec from :meth:`get_config` output. ``config`` is not modified."""
        params = dict(config)
        cid = params.pop("id", cls.codec_id)
        if cid != cls.codec_id:
            raise InvalidValueError(f"config is for codec {cid!r}, not {cls.codec_id!r}")
        unknown = set(params) - set(cls._param_names())
        if unknown:
            raise InvalidValueError(f"codec {cls.codec_id!r} has no parameter(s) {sorted(unknown)}; "
                                    f"it takes {cls._param_names()}")
        return cls(**copy.deepcopy(params))

    # -- helpers -------------------------------------------------------------------------------------
    def _check_fitted(self) -> None:
        if not self.is_fitted:
            raise NotFittedError(f"{self!r} needs fitting: call fit(blocks), load_state_dict(...), "
                                 "or pass a trained model (--model PATH)")

    def __repr__(self) -> str:
        args = ", ".join(f"{k}={v!r}" for k, v in self.get_config().items() if k != "id")
        return f"{type(self).__name__}({args})"
