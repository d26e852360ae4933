"""The codec contract in brief; the whole, normative text is ``spec/codec-plugins.md`` (version 2).

A codec turns normalised TSDF blocks ``(N, 16, 16, 16)`` float32 (``v = (d - d_min) / (d_max - d_min)``,
free and unobserved space 1.0) into code vectors ``(N, code_size)`` float32 and back. A codec is a subclass
of :class:`Codec` that sets ``codec_id``, ``prefix_ordered``, ``requires_fit`` (and SHOULD set
``code_sizes``), has an ``__init__`` that only stores its JSON keyword arguments (its configuration), and
implements ``_encode`` / ``_decode`` (and ``_fit`` plus ``state_dict`` / ``load_state_dict`` when it learns).
The public ``fit`` / ``encode`` / ``decode`` of this base class check and convert input and return results
that follow it (numpy in, numpy out; a tensor in, a tensor on its device out).

Optional public hooks, each with a default that is correct for every codec (spec section 4):
:meth:`Codec.decode_affine`, :meth:`Codec.decode_into`, :meth:`Codec.decode_bound` (decode on read),
:meth:`Codec.encode_weighted`
(per-voxel error weights: unobserved voxels and surfaces) and :meth:`Codec.fit_batches` (streamed fitting). A codec declares the
hooks it provides in ``capabilities`` (:data:`CAPABILITIES`, :func:`capabilities`; spec section 4a). Shipped weights are offered by :meth:`Codec.pretrained` and listed by
:meth:`Codec.shipped_models` / :meth:`Codec.shipped_state`. Benchmark shapes are
registered with :func:`sdfcodec.bench.register_bench`, not declared here. Plugin authors import their tools
from :mod:`sdfcodec.plugin`; :func:`sdfcodec.testing.check_codec` checks the contract.
"""

from __future__ import annotations

import abc
import contextlib
import copy
import inspect
import warnings
import weakref
from typing import Any, Callable, ClassVar, Iterable, Iterator, Mapping, Protocol, runtime_checkable

import numpy as np

from .core._lazy import lazy_module
from .core._validate import BLOCK, affine_into, as_float_tensor, check_weights, finite_sum, like_input, output_buffer
from .core._validate import empty as _empty  # not `empty`: sdfcodec.codec.empty is a deprecated name (see __getattr__)
from .errors import (DTypeError, InvalidValueError, ModelNotFoundError, NotFittedError, PluginError,
                     RegistrationError, SDFCodecError, ShapeError)

torch = lazy_module("torch")  # imported on first use: info, codecs, verify of a header never need it

__all__ = ["Codec", "BLOCK", "CAPABILITIES", "capabilities", "check_capabilities", "DecodesInto", "decodes_into",
           "decodes_tiles", "uses_weights", "learns_weights", "plugin_calls", "checked_decode_output", "FINITE_BOUND",
           "NumpyPath", "numpy_path_of"]

#: Decoded values a codec bounds below this are finite however float32 rounding goes (float32 max ~3.4e38).
FINITE_BOUND = 1e37
#: Spec-1 names of the optional hooks -> their public names since spec 2 (spec/codec-plugins.md, change log).
LEGACY_HOOKS = {"_decode_affine": "decode_affine", "_decode_bound": "decode_bound", "_fit_stream": "fit_batches"}
#: What a codec may declare in ``Codec.capabilities`` (spec/codec-plugins.md, section 4a): each capability is
#: named after the optional hook that provides it; True where declaring it requires overriding that hook (the
#: weighted hooks' defaults are right for a codec whose plain encode or fit already minimises every weighted
#: error: a lossless one).
CAPABILITIES: dict[str, bool] = {"decode_affine": True, "decode_into": True, "decode_tiles": True,
                                 "encode_truncated": True, "encode_weighted": False, "fit_weighted": False,
                                 "numpy_path": True, "pretrained": True}


def _forward_to(old: str) -> Callable[..., Any]:
    """The public hook of a codec that implements only its spec-1 name ``old``: calls that method."""
    def hook(self: "Codec", *args: Any) -> Any:
        return getattr(self, old)(*args)
    hook.__sdfcodec_legacy__ = True  # type: ignore[attr-defined]  # marks it for _legacy_alias
    hook.__name__ = LEGACY_HOOKS[old]
    return hook


def _legacy_alias(old: str) -> Callable[..., Any]:
    """``Codec.<old>``, kept for callers of the spec-1 names: warns and calls the public hook (its default when
    the codec's own hook is an old-style override calling up to the base class, so that cannot loop)."""
    new = LEGACY_HOOKS[old]

    def alias(self: "Codec", *args: Any) -> Any:
        warnings.warn(f"Codec.{old} is deprecated since codec spec 2: call {new} instead", DeprecationWarning,
                      stacklevel=2)
        hook = getattr(type(self), new)
        if getattr(hook, "__sdfcodec_legacy__", False):
            hook = getattr(Codec, new)
        return hook(self, *args)
    alias.__name__ = old
    return alias


def _same_array(a: Any, b: Any) -> bool:
    a, b = np.asarray(a), np.asarray(b)
    return a.dtype == b.dtype and a.shape == b.shape and bool(np.array_equal(a, b))


def _plugin_name(codec: Codec | type[Codec]) -> str:
    cls = codec if isinstance(codec, type) else type(codec)
    return f"codec {getattr(cls, 'codec_id', cls.__qualname__)!r} (module {cls.__module__.split('.')[0]})"


@contextlib.contextmanager
def plugin_calls(codec: Codec | type[Codec], doing: str) -> Iterator[None]:
    """Around calls into a codec plugin's own code: an exception that is not an ``SDFCodecError`` (a bug in the
    plugin, or its reaction to input it did not expect) becomes one :class:`PluginError` line naming the codec,
    its module and what it was doing, the original chained. Every decode path goes through it (the codec's
    public methods, map readers calling hooks, ``verify``), so a failing plugin reads the same everywhere."""
    try:
        yield
    except SDFCodecError:
        raise
    except Exception as e:  # noqa: BLE001 - a plugin may raise anything; the user gets one line naming it
        text = " ".join(str(e).split()) or "(no message)"
        raise PluginError(f"{_plugin_name(codec)} failed while {doing}: {type(e).__name__}: {text}; this is a "
                          "fault of the codec's plugin: report it to its authors (or upgrade it)") from e


def checked_decode_output(codec: Codec, out: Any, n: int, device: Any, doing: str = "decoding") -> torch.Tensor:
    """What a plugin's decode returned for ``n`` codes, checked against the contract: a tensor (a numpy array is
    taken as one) on ``device``, ``n * 4096`` values of a float type (float16/bfloat16/float64 are converted to
    float32; integers or booleans are refused: an int32 decode once read 6.6 cm off), returned as
    ``(n, 16, 16, 16)`` float32. Finite values are checked by the callers (map readers name the block).

    Raises:
        PluginError: naming the codec, what it returned and what was expected."""
    if isinstance(out, np.ndarray):
        out = torch.from_numpy(out)
    if not isinstance(out, torch.Tensor):
        raise PluginError(f"{_plugin_name(codec)} returned {type(out).__name__} while {doing}, not a tensor of "
                          f"({n}, 16, 16, 16) float32 blocks: a fault of the codec's plugin")
    if not out.dtype.is_floating_point:
        raise PluginError(f"{_plugin_name(codec)} returned {str(out.dtype).removeprefix('torch.')} values while "
                          f"{doing}, not float32 blocks: a fault of the codec's plugin (report it to its authors)")
    if out.ndim < 1 or out.shape[0] != n or out.numel() != n * BLOCK ** 3:
        raise PluginError(f"{_plugin_name(codec)} returned shape {tuple(out.shape)} while {doing} {n} codes, "
                          f"expected ({n}, 16, 16, 16): a fault of the codec's plugin (report it to its authors)")
    if out.device != torch.device(device) and not (out.device.type == torch.device(device).type == "cuda"):
        out = out.to(device)
    if out.dtype != torch.float32:
        out = out.float()
    return out.reshape(n, BLOCK, BLOCK, BLOCK)


class Codec(abc.ABC):
    """Abstract base of all codecs: the contract is spec/codec-plugins.md (summary in the module docstring).

    Two codecs are equal when they have the same class, configuration and learned state (arrays compared
    exactly: dtype, shape and values). Codecs are mutable (``fit``, ``load_state_dict``), so they are not
    hashable: key caches by ``id(codec)`` or by ``get_config()``, never by the codec.
    """

    codec_id: ClassVar[str]
    prefix_ordered: ClassVar[bool] = False
    requires_fit: ClassVar[bool] = False
    code_sizes: ClassVar[tuple[int, ...]] = ()
    #: Voxels of neighbour context the decoder needs on each side (0: none; spec section 3, "Halo").
    halo: ClassVar[int] = 0
    #: The optional fast paths and promises this codec declares (names from :data:`CAPABILITIES`; spec section
    #: 4a). Readers, writers and the registry act on this set (:func:`capabilities`), never on which methods a
    #: class happens to override.
    capabilities: ClassVar[frozenset[str]] = frozenset()

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        # spec 1 promised its optional hooks under underscore names: a codec still written that way keeps working
        for old, new in LEGACY_HOOKS.items():
            if old in cls.__dict__ and new not in cls.__dict__:
                warnings.warn(f"{cls.__module__}.{cls.__qualname__} implements the optional hook {old!r}, whose "
                              f"name since codec spec 2 is {new!r}; rename it (spec/codec-plugins.md, section 4)",
                              DeprecationWarning, stacklevel=3)  # the class statement (past ABCMeta)
                setattr(cls, new, _forward_to(old))
        _warn_undeclared(cls)

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

    def validate_state(self) -> None:
        """Hook: check that the learned state just loaded (:meth:`load_state_dict`) is one this codec's decode
        can be trusted with, beyond the shapes and finiteness ``load_state_dict`` checks, and raise an
        :class:`~sdfcodec.errors.InvalidValueError` saying what is wrong otherwise (PCA: the basis is
        orthonormal). Map readers call it on every codec state they load, stored or shipped, and so do
        :func:`sdfcodec.model.load_model` and ``sdfcodec verify``: a map is untrusted input, and a state digest
        proves only that the header and the arrays agree, not that the arrays are sane (a PCA basis scaled by 3
        with its digest recomputed decodes centimetres off). The default accepts every state. It must be cheap
        (it runs on every open) and use only numpy."""

    # -- the public, checked surface -----------------------------------------------------------------
    def fit(self, blocks: Any, weights: Any = None) -> "Codec":
        """Learn the codec's state from normalised blocks ``(N, 16, 16, 16)``; returns ``self``.

        ``weights``, optional: per-voxel error weights of the blocks, as :meth:`encode` takes them (0 where a
        voxel was not observed); a codec that can learn from them (hook :meth:`fit_weighted`) minimises the
        weighted error of its weighted encode, the others ignore them."""
        if self.requires_fit:
            t, _ = as_float_tensor(blocks, "blocks", (None, BLOCK, BLOCK, BLOCK))
            if t.shape[0] == 0:
                raise ShapeError("fit needs at least one block, got an empty batch")
            if weights is None:
                self._fit(t.cpu().numpy())
            else:
                w = check_weights(weights, len(t), torch.device("cpu"))
                self.fit_weighted(t.cpu().numpy(), np.ascontiguousarray(w.numpy()))
        return self

    def fit_stream(self, batches: Iterable[Any]) -> "Codec":
        """Learn from an iterable of normalised block batches ``(N_i, 16, 16, 16)``, for data sets larger than
        memory; returns ``self``. Each batch is checked and handed, as float32 numpy, to :meth:`fit_batches`."""
        if not self.requires_fit:
            return self
        checked = (as_float_tensor(b, "blocks", (None, BLOCK, BLOCK, BLOCK))[0].cpu().numpy() for b in batches)
        self.fit_batches(checked)
        return self

    def encode(self, blocks: Any, weights: Any = None) -> Any:
        """Encode normalised blocks ``(N, 16, 16, 16)`` to codes ``(N, code_size)`` (float32).

        ``weights``, optional: ``(N, 16, 16, 16)`` finite, non-negative per-voxel weights of the error (spec
        section 4a): the codec makes the error small where the weight is large, and a voxel of weight 0 (not
        observed) does not matter at all; they go to :meth:`encode_weighted`. numpy in gives numpy out; a torch
        tensor gives a tensor on the same device.
        """
        self._check_fitted()
        t, was_numpy = as_float_tensor(blocks, "blocks", (None, BLOCK, BLOCK, BLOCK))
        w = None if weights is None else check_weights(weights, len(t), t.device)
        if t.shape[0] == 0:
            return like_input(t.new_zeros((0, self.code_size)), was_numpy)
        with plugin_calls(self, "encoding"):
            return like_input(self._encode(t) if w is None else self.encode_weighted(t, w), was_numpy)

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

    def decode(self, codes: Any, *, out: Any = None) -> Any:
        """Decode codes ``(N, k)`` to normalised blocks ``(N, 16, 16, 16)`` (float32).

        ``k`` must equal ``code_size``, or, for prefix-ordered codecs, be any ``1 <= k <= code_size``
        (a prefix decodes to a coarser block, so the code length is the prefix level). Output follows the input
        like :meth:`encode`.

        ``out``, optional: a caller's buffer to decode into, of the kind the result would be (a numpy array for
        numpy codes, a tensor on the codes' device for tensor codes), float32, C-contiguous, shape
        ``(N, 16, 16, 16)`` or ``(N, 4096)``, not overlapping the codes; it is filled and returned (the same
        object), so a loop decoding batch after batch allocates nothing. A codec implementing the optional hook
        :meth:`decode_into` writes there directly; the others decode and copy (spec section 4).

        Raises:
            ShapeError, DTypeError, InvalidValueError: bad codes, or an ``out`` of the wrong shape, dtype, kind,
                device or layout (the message says which).
        """
        t, was_numpy = self._checked_codes(codes)
        if out is not None:
            dst = self._checked_out(out, t, was_numpy)
            if len(t):
                with plugin_calls(self, "decoding"):
                    if self.halo:  # blocks alone have their own faces as context: the plain decode, copied
                        dst.copy_(self._decode_alone(t))
                    else:
                        self.decode_into(t, dst, 1.0, 0.0)
                self._check_finite(t, dst)
            return out
        if t.shape[0] == 0:
            return like_input(t.new_zeros((0, BLOCK, BLOCK, BLOCK)), was_numpy)
        with plugin_calls(self, "decoding"):
            res = self._decode_alone(t)
        return like_input(self._check_finite(t, res), was_numpy)

    def _decode_checked(self, t: torch.Tensor) -> torch.Tensor:
        """``_decode`` of checked codes ``(N, k)``, its output checked against the contract (shape, float type:
        :func:`checked_decode_output`)."""
        return checked_decode_output(self, self._decode(t), len(t), t.device)

    def _check_finite(self, codes: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
        """``v``, the decode of ``codes``, refused when it holds NaN/Inf (a corrupted state or a faulty plugin:
        spec/map-format.md section 9a refuses them on every decode path) unless :meth:`decode_bound` proves it
        finite (then no pass over it)."""
        if v.device.type == "meta":  # shapes only, no values to check
            return v
        bound = self.decode_bound(codes)
        if bound is not None and bound <= FINITE_BOUND:
            return v
        # NaN/Inf propagate into the sum: one cheap pass (0.2 ms for 256 blocks where torch's isfinite + all took
        # 10-20 ms on the 2-core VM); the per-row test runs only when the sum is not finite
        if finite_sum(v):
            return v
        finite = torch.isfinite(v.reshape(len(v), -1)).all(dim=1)
        if bool(finite.all()):
            return v
        bad = (~finite).nonzero().flatten().cpu().numpy()
        raise PluginError(f"{_plugin_name(self)} decoded NaN/Inf values for {len(bad)} of {len(v)} codes (e.g. row "
                          f"{int(bad[0])}): the codes or the codec's learned state are corrupted, or the plugin is "
                          "faulty")

    def _decode_alone(self, t: torch.Tensor) -> torch.Tensor:
        """``_decode`` of checked codes, halo codecs given each block's own faces, repeated, as context."""
        out = self._decode_checked(t)
        if self.halo:
            # alone, a block has no neighbours: repeat its faces as the context (maps give the real ones)
            h = self.halo
            out = checked_decode_output(self, self._decode_context(
                torch.nn.functional.pad(out[:, None], (h,) * 6, mode="replicate")[:, 0]), len(t), t.device)
        return out

    def _checked_out(self, out: Any, codes: torch.Tensor, was_numpy: bool) -> torch.Tensor:
        """The caller's output buffer ``out`` for checked ``codes`` ``(N, k)``, checked (see :meth:`decode`), as a
        float32 tensor ``(N, 16, 16, 16)`` sharing its memory."""
        n = len(codes)
        dst = output_buffer(out, ((n, BLOCK, BLOCK, BLOCK), (n, BLOCK ** 3)), numpy=was_numpy, device=codes.device,
                            what=f"({n}, 16, 16, 16) or ({n}, 4096) for {n} codes")
        lo, hi = dst.data_ptr(), dst.data_ptr() + 4 * dst.numel()
        clo, chi = codes.data_ptr(), codes.data_ptr() + codes.element_size() * codes.numel()
        if dst.numel() and codes.numel() and dst.device.type != "meta" and lo < chi and clo < hi:
            raise InvalidValueError("out overlaps the codes: decode into a separate buffer")
        return dst.view(n, BLOCK, BLOCK, BLOCK)

    def decode_context(self, padded: Any) -> Any:
        """Finish decoding with neighbour context: ``(N, X + 2h, Y + 2h, Z + 2h)`` normalised values (blocks
        decoded by :meth:`decode_core`, assembled; 1.0 where there is no block) -> ``(N, X, Y, Z)``, with
        ``h = halo``. For ``halo == 0`` it is the identity."""
        t, was_numpy = as_float_tensor(padded, "padded", (None, None, None, None))
        h = self.halo
        if min(t.shape[1:]) <= 2 * h:
            raise ShapeError(f"padded volumes for {self!r} need more than {2 * h} voxels per axis, "
                             f"got {tuple(t.shape)}")
        return like_input(self._decode_context(t) if h else t, was_numpy)

    def decode_core(self, codes: Any, *, scale: float = 1.0, offset: float = 0.0, out: Any = None) -> Any:
        """Decode without neighbour context (what :meth:`decode_context` assembles), as ``scale * v + offset``:
        ``(N, k) -> (N, 16, 16, 16)``. With the defaults it equals :meth:`decode` for codecs with ``halo == 0``;
        map readers pass ``scale = d_max - d_min, offset = d_min`` to get metres in the same pass (codecs whose
        last step is linear fold it into their weights, see :meth:`decode_affine`). ``out``: a buffer to decode
        into, as for :meth:`decode` (filled and returned; the codec's :meth:`decode_into` writes it)."""
        t, was_numpy = self._checked_codes(codes)
        if out is not None:
            dst = self._checked_out(out, t, was_numpy)
            if len(t):
                with plugin_calls(self, "decoding"):
                    self.decode_into(t, dst, float(scale), float(offset))
            return out
        if t.shape[0] == 0:
            return like_input(t.new_zeros((0, BLOCK, BLOCK, BLOCK)), was_numpy)
        with plugin_calls(self, "decoding"):
            if not self.halo and scale == 1.0 and offset == 0.0:
                return like_input(self._decode_checked(t), was_numpy)
            res = checked_decode_output(self, self.decode_affine(t, float(scale), float(offset)), len(t), t.device)
        return like_input(res, was_numpy)

    # -- optional public hooks (spec section 4): the defaults are correct for every codec; overriding one only
    # makes it faster. They take already checked input: callers are the base class and map readers.
    def decode_affine(self, codes: torch.Tensor, scale: float, offset: float) -> torch.Tensor:
        """Hook: ``scale * _decode(codes) + offset`` ``(N, 16, 16, 16)`` float32 for checked float32 codes
        ``(N, k)``, on their device (:meth:`decode_core` calls it). The default adds one fused pass over the
        output (in place unless the output is a view of ``codes``); a codec whose decode ends in a linear layer
        MAY override it to fold ``scale`` and ``offset`` into that layer (PCA does)."""
        out = self._decode_checked(codes)
        if scale == 1.0 and offset == 0.0:
            return out
        aliased = out.untyped_storage().data_ptr() == codes.untyped_storage().data_ptr()
        base = torch.tensor(offset, dtype=out.dtype, device=out.device)
        return torch.add(base, out, alpha=scale) if aliased else torch.add(base, out, alpha=scale, out=out)

    def decode_into(self, codes: torch.Tensor, out: torch.Tensor, scale: float, offset: float) -> None:
        """Hook: write ``scale * _decode(codes) + offset`` into ``out`` ``(N, 16, 16, 16)`` (float32, contiguous,
        on the codes' device, not overlapping them) for checked float32 codes ``(N, k)``, ``N >= 1``
        (:meth:`decode` and :meth:`decode_core` call it when given ``out``; map readers decode into reused buffers
        and into the volumes they fill through it). The default is decode-then-copy (:meth:`decode_affine`, then
        one copy into ``out``): correct for every codec. A codec that can write its output where it is told
        SHOULD override it (PCA: one matrix product into ``out``, scale and offset folded in; raw: one fused
        pass); :class:`DecodesInto` declares the signature, :func:`decodes_into` tells whether a codec does."""
        if "decode_affine" in capabilities(self):  # the codec's own affine decode (folded, say), then one copy
            out.copy_(self.decode_affine(codes, scale, offset))
        else:  # the plain decode, scaled into ``out`` in the one pass the default decode_affine would spend
            affine_into(self._decode_checked(codes), out, scale, offset)

    def decode_tiles(self, codes: torch.Tensor, scale: float, offset: float, clip: tuple[float, float],
                     each: Callable[[int, int, torch.Tensor], None] | None = None, out: torch.Tensor | None = None
                     ) -> None:
        """Hook: decode checked float32 codes ``(N, k)``, ``N >= 1``, to ``scale * _decode(codes) + offset``
        clipped to ``clip = (lo, hi)``, tile by tile: for consecutive row ranges ``[a, b)`` covering ``[0, N)``
        once each, the tile's blocks ``(b - a, 16, 16, 16)`` (written into ``out[a:b]`` when ``out`` is given, a
        buffer as for :meth:`decode_into`; else into scratch memory valid only during the call) are handed to
        ``each(a, b, tile)`` when given, while they are still in cache. Tiles MAY be decoded on several threads
        at once, in any order: ``each`` must be safe on disjoint tiles. Map readers call it for truncated decodes
        (metres, the bound of :meth:`decode_bound` proving the output finite) so that the product, the clip and
        the placing of a block into a volume cost one pass over memory. The default is one tile: :meth:`decode_into`
        into ``out`` (or a fresh buffer), one clip pass, ``each(0, N, out)``. A codec whose decode is a row-wise
        product MAY override it (PCA: cache-sized tiles on every core, :func:`sdfcodec.core.tiling.run_tiles`);
        :func:`decodes_tiles` tells whether a codec does."""
        n = len(codes)
        dst = out if out is not None else _empty((n, BLOCK, BLOCK, BLOCK), codes.device)
        self.decode_into(codes, dst, scale, offset)
        if dst.device.type == "cpu":  # numpy's: torch's threaded clamp after a numpy product waits for BLAS threads
            a = dst.numpy()
            np.clip(a, clip[0], clip[1], out=a)
        else:
            dst.clamp_(clip[0], clip[1])
        if each is not None:
            each(0, n, dst.view(n, BLOCK, BLOCK, BLOCK))

    def decode_bound(self, codes: torch.Tensor) -> float | None:
        """Hook: an upper bound on ``|_decode(codes)|`` over all outputs for checked float32 codes ``(N, k)``,
        or None (the default) when the codec cannot give one cheaply. Map readers check decoded blocks for
        NaN/Inf (a broken learned state) with a pass over the output; a finite bound proves them finite
        without it (PCA: from the codes and its basis)."""
        return None

    def encode_weighted(self, blocks: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
        """Hook: codes ``(N, code_size)`` for checked blocks ``(N, 16, 16, 16)`` float32 that minimise the
        weighted error ``sum_j weights_j (x_j - decode(code)_j)^2`` of each block as well as the codec can, for
        checked weights of the same shape (finite, >= 0; a block of all-zero weights gets ``_encode``'s code).
        :meth:`encode` calls it when given weights. The default ignores the weights (``_encode(blocks)``): every
        codec accepts them; a codec that can use them overrides it (PCA solves the weighted least squares)."""
        return self._encode(blocks)

    def encode_truncated(self, blocks: torch.Tensor, weights: torch.Tensor, rounds: int, shrink: float = 0.0
                         ) -> torch.Tensor | None:
        """Hook: the codes ``(N, code_size)`` that :func:`sdfcodec.map.observed.encode_truncated` computes from
        :meth:`encode_weighted` (the weighted fit, then at most ``rounds`` refits without the bound voxels a
        reader's truncation makes exact), to float32 rounding, for checked blocks ``(N, 16, 16, 16)`` float32 and
        checked weights of the same shape; or None where the codec has no faster way for these inputs (that
        function then runs its batched refits). The default is None; a codec declaring the capability
        ``encode_truncated`` overrides it (PCA: one compiled pass per block on the CPU). ``shrink`` (optional
        keyword, > 0 only at low rates of variable-rate maps): a ridge towards the zero code of that weight
        relative to the mean weight added to the problem; a hook without the keyword is called without it."""
        return None

    def numpy_path(self) -> "NumpyPath | None":
        """Hook: this fitted codec's encode and decode on the CPU in numpy, without torch (a :class:`NumpyPath`),
        or None (the default) where it has none. Callers holding numpy arrays only (searches) take it, so that a
        command on such a codec never imports torch: its import alone costs 1.7 s of a search's start on two
        cores. Results equal :meth:`encode`, :meth:`decode` and :meth:`encode_truncated` to float32 rounding."""
        return None

    def fit_weighted(self, blocks: np.ndarray, weights: np.ndarray) -> None:
        """Hook: learn from checked float32 numpy blocks ``(N, 16, 16, 16)`` and checked weights of the same
        shape (finite, >= 0) the state whose weighted encode (:meth:`encode_weighted`) makes the weighted error
        small; :meth:`fit` calls it when given weights. The default ignores the weights (``_fit(blocks)``); PCA
        overrides it (weighted alternating least squares)."""
        self._fit(blocks)

    def field_compression(self) -> dict[str, Any] | None:
        """Hook: how a map stores this codec's codes as a field, or None (the default: codes are stored as they
        are). A codec whose codes are the block's voxels (``code_size`` 4096, float32, ``_decode`` a reshape)
        MAY return ``{"name": "sz3", "max_error": e}``: map writers then store each coded block's normalised
        voxels exactly as given (not ``encode``'s output) and compress the ``codes`` array with SZ3 at the
        absolute bound ``e`` (normalised units), a chunk's blocks as one 3-D field (spec/map-format.md section
        4c). The built-in ``sz3`` codec does."""
        return None

    def fit_batches(self, batches: Iterator[np.ndarray]) -> None:
        """Hook: learn from an iterator of checked float32 numpy batches ``(N_i, 16, 16, 16)``
        (:meth:`fit_stream` calls it). The default concatenates them and calls :meth:`fit`, so it needs memory
        for all of them; a codec that learns incrementally overrides it (PCA accumulates moments)."""
        self.fit(np.concatenate(list(batches)))

    # spec-1 names of the hooks, for callers not yet renamed (each warns once per call site)
    _decode_affine = _legacy_alias("_decode_affine")
    _decode_bound = _legacy_alias("_decode_bound")
    _fit_stream = _legacy_alias("_fit_stream")

    # -- shipped weights ------------------------------------------------------------------------------
    @classmethod
    def pretrained(cls, code_size: int | None = None, **options: Any) -> "Codec":
        """A fitted codec with the weights its plugin ships (in the plugin's own package), at ``code_size``
        (None: the codec's default size) with codec-specific ``options``; a fresh codec each call.

        Raises:
            ModelNotFoundError: this codec (or this size) ships no trained model; the message says how to
                train one (the default, for codecs that ship none).
        """
        raise ModelNotFoundError(f"codec {getattr(cls, 'codec_id', cls.__qualname__)!r} ships no trained model: "
                                 "train one with `sdfcodec train` and pass it with --model")

    @classmethod
    def shipped_models(cls) -> dict[str, tuple[int, ...]] | None:
        """The trained models this codec's plugin ships and :meth:`pretrained` serves: stable model name (e.g.
        ``"pca-128"``) -> the code sizes (``code_size`` of the codec served) it gives, without loading any of them.
        The default: ``{}`` (none) for a codec that does not override :meth:`pretrained`, ``None`` (cannot tell)
        for one that does. Maps that store their codec state by reference name these models (spec/map-format.md,
        section 6c), so a name MUST NOT be reused for other weights."""
        return None if "pretrained" in capabilities(cls) else {}

    @classmethod
    def shipped_state(cls, model: str, code_size: int) -> dict[str, np.ndarray]:
        """The learned state (read-only arrays) a codec of ``code_size`` gets from shipped ``model``: what
        ``pretrained(code_size).state_dict()`` holds. The default builds that codec when :meth:`shipped_models`
        lists the model at that size; a plugin MAY override it to cut the arrays without building a codec.

        Raises:
            ModelNotFoundError: the plugin does not ship ``model``, or not at ``code_size``, or its file is missing.
        """
        sizes = (cls.shipped_models() or {}).get(model)
        if sizes is None or code_size not in sizes:
            raise ModelNotFoundError(f"codec {cls.codec_id!r} ships no model {model!r} at code size {code_size}")
        return cls.pretrained(code_size).state_dict()

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

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Codec):
            return NotImplemented
        if type(self) is not type(other) or self.get_config() != other.get_config():
            return False
        mine, theirs = self.state_dict(), other.state_dict()
        return mine.keys() == theirs.keys() and all(_same_array(mine[k], theirs[k]) for k in mine)

    __hash__ = None  # type: ignore[assignment]  # mutable, compared by value: see the class docstring

    def __repr__(self) -> str:
        args = ", ".join(f"{k}={v!r}" for k, v in self.get_config().items() if k != "id")
        return f"{type(self).__name__}({args})"


def __getattr__(name: str) -> Any:
    if name == "empty":  # the huge-page allocator moved to the plugin toolkit
        warnings.warn("sdfcodec.codec.empty is deprecated: use sdfcodec.plugin.empty", DeprecationWarning,
                      stacklevel=2)
        from .core._validate import empty

        return empty
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


@runtime_checkable
class DecodesInto(Protocol):
    """The optional fast path of decoding into a caller's buffer (spec/codec-plugins.md, section 4): what a
    codec overriding :meth:`Codec.decode_into` provides. Every :class:`Codec` matches it structurally (the base
    class falls back to decode-then-copy); :func:`decodes_into` tells whether a codec writes in place."""

    def decode_into(self, codes: torch.Tensor, out: torch.Tensor, scale: float, offset: float) -> None:
        """Write ``scale * decode(codes) + offset`` into ``out`` ``(N, 16, 16, 16)`` float32."""


class NumpyPath(Protocol):
    """A codec's encode and decode in numpy on the CPU (:meth:`Codec.numpy_path`, capability ``numpy_path``).
    Inputs are checked by the caller: float32, C-contiguous, finite.

    It MAY also give ``decode_affine(codes, scale, offset)``: codes ``(N, k)`` -> ``scale * decode(codes) +
    offset`` ``(N, 4096)`` float32, as :meth:`Codec.decode_affine` computes it on the CPU (a scaling folded into
    the decode layer, folded alike). Map readers take it where they have no other use for torch
    (:func:`numpy_decode_affine`); without it they decode through torch."""

    def encode(self, blocks: np.ndarray) -> np.ndarray:
        """Normalised blocks ``(N, 4096)`` -> codes ``(N, code_size)`` float32, as :meth:`Codec.encode`."""

    def decode(self, codes: np.ndarray) -> np.ndarray:
        """Codes ``(N, k)`` (``k < code_size`` for prefix-ordered codecs only) -> normalised blocks
        ``(N, 4096)`` float32, as :meth:`Codec.decode`."""

    def encode_truncated(self, blocks: np.ndarray, weights: np.ndarray, rounds: int, shrink: float = 0.0
                         ) -> np.ndarray | None:
        """Codes ``(N, code_size)`` float32 as :meth:`Codec.encode_truncated` computes them, for blocks and weights
        ``(N, 4096)``; None where it has no numpy way for them (the caller then takes the torch path)."""


def numpy_path_of(codec: Codec) -> NumpyPath | None:
    """``codec``'s :class:`NumpyPath` when it declares the capability ``numpy_path`` and gives one, else None."""
    return codec.numpy_path() if "numpy_path" in capabilities(codec) else None


def numpy_decode_affine(codec: Codec) -> Callable[[np.ndarray, float, float], np.ndarray] | None:
    """The optional ``decode_affine`` of ``codec``'s :class:`NumpyPath` (see there), else None."""
    return getattr(numpy_path_of(codec), "decode_affine", None)


def decodes_into(codec: Codec | type[Codec]) -> bool:
    """Whether ``codec`` (an instance or a class) declares ``decode_into``: it decodes straight into a caller's
    buffer rather than decoding and copying."""
    return "decode_into" in capabilities(codec)


def decodes_tiles(codec: Codec | type[Codec]) -> bool:
    """Whether ``codec`` (an instance or a class) declares ``decode_tiles``: it decodes, clips and hands out
    cache-sized tiles rather than decoding, clipping and handing out the whole batch."""
    return "decode_tiles" in capabilities(codec)


def uses_weights(codec: Codec | type[Codec]) -> bool:
    """Whether ``codec`` (an instance or a class) declares ``encode_weighted``: its encode fits the error weights
    it is given (or is lossless), so map writers give it weights rather than filled blocks."""
    return "encode_weighted" in capabilities(codec)


def learns_weights(codec: Codec | type[Codec]) -> bool:
    """Whether ``codec`` (an instance or a class) declares ``fit_weighted``: its fit minimises the weighted
    error rather than ignoring the weights."""
    return "fit_weighted" in capabilities(codec)


_resolved: "weakref.WeakKeyDictionary[type, frozenset[str]]" = weakref.WeakKeyDictionary()


def capabilities(codec: Codec | type[Codec]) -> frozenset[str]:
    """What ``codec`` (an instance or a class) can do beyond the contract's defaults (spec section 4a): its
    declared ``capabilities``, checked (:func:`check_capabilities`), plus, for a plugin written before
    declarations (codec spec 2 before capabilities were declared), each optional hook it overrides without declaring it (its
    class warned when it was defined). Worked out once per class."""
    cls = codec if isinstance(codec, type) else type(codec)
    found = _resolved.get(cls)
    if found is None:
        declared = check_capabilities(cls)
        found = declared | {hook for hook in CAPABILITIES if hook not in declared and _overrides(cls, hook)}
        _resolved[cls] = found
    return found


def check_capabilities(cls: type[Codec]) -> frozenset[str]:
    """``cls.capabilities``, checked: a set of names from :data:`CAPABILITIES`, each of those that need a method
    provided by the class (overridden, not the base class's default). The registry checks it when a codec is
    registered or loaded, :func:`capabilities` on first use, and the conformance check ``attributes``.

    Raises:
        RegistrationError: naming the class, the declaration and what to do."""
    declared = getattr(cls, "capabilities", frozenset())
    where = f"{cls.__module__}.{cls.__qualname__}.capabilities"
    if not isinstance(declared, (frozenset, set)) or not all(isinstance(c, str) for c in declared):
        raise RegistrationError(f"{where} must be a frozenset of capability names, got {declared!r}")
    unknown = sorted(set(declared) - CAPABILITIES.keys())
    if unknown:
        raise RegistrationError(f"{where} names unknown capabilities {unknown}; known: {sorted(CAPABILITIES)} "
                                "(spec/codec-plugins.md, section 4a)")
    missing = sorted(c for c in declared if CAPABILITIES[c] and not _overrides(cls, c))
    if missing:
        raise RegistrationError(f"{where} declares {missing} but the class does not implement "
                                f"{', '.join(m + '()' for m in missing)}: implement the hook or drop the "
                                "declaration (spec/codec-plugins.md, section 4a)")
    return frozenset(declared)


def _warn_undeclared(cls: type[Codec]) -> None:
    """The one place a codec that overrides an optional hook without declaring it (written from the docs before
    declarations) is told what to add; :func:`capabilities` keeps using the override until codec spec 3."""
    declared = getattr(cls, "capabilities", frozenset())
    if not isinstance(declared, (frozenset, set)):
        return  # refused with a clear error by check_capabilities
    undeclared = sorted(hook for hook in CAPABILITIES if hook in cls.__dict__ and hook not in declared
                        and not getattr(cls.__dict__[hook], "__sdfcodec_legacy__", False))  # legacy names warned
    if undeclared:
        wanted = ", ".join(repr(c) for c in sorted(set(declared) | set(undeclared)))
        warnings.warn(f"{cls.__module__}.{cls.__qualname__} overrides the optional hook(s) {undeclared} without "
                      f"declaring them: add `capabilities = frozenset({{{wanted}}})` to the class (spec/codec-"
                      "plugins.md, section 4a); undeclared overrides are used until codec spec 3",
                      DeprecationWarning, stacklevel=4)  # the class statement (past __init_subclass__, ABCMeta)


def _overrides(codec: Codec | type[Codec], hook: str) -> bool:
    cls = codec if isinstance(codec, type) else type(codec)
    # classmethods are bound anew on each access: compare the functions underneath
    mine, base = getattr(cls, hook), getattr(Codec, hook)
    return getattr(mine, "__func__", mine) is not getattr(base, "__func__", base)
