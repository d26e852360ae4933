"""The named conformance checks of the codec contract (spec/codec-plugins.md), one function per check.

Each check takes a :class:`Case` (its own copy of the codec under test, fitted, and the options) and raises
``AssertionError`` naming what was wrong; it may return measurements (a small dict) for the report. The suite
(:mod:`sdfcodec.testing._suite`) runs them one by one, each on a fresh copy, and collects every failure.
"""

from __future__ import annotations

import copy
import json
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch

from .. import errors
from ..codec import Codec, capabilities
from ..registry import get_codec
from ._compare import assert_close, assert_raises
from ._data import analytic_blocks
from ._golden import check_golden, write_golden

__all__ = ["CheckOptions", "Case", "CHECKS", "prefix_levels"]

_ID = re.compile(r"^[a-z0-9][a-z0-9_.-]*$")
#: what map readers pass to ``decode_core`` for the paper's truncation (-0.04, 0.1) m
_SCALE, _OFFSET = 0.14, -0.04


@dataclass
class CheckOptions:
    """What the checks run on.

    Attributes:
        blocks: normalised test blocks ``(N, 16, 16, 16)`` float32 (also what an unfitted codec is fitted on).
        atol: tolerance of numerical comparisons (normalised units, relative to magnitudes above 1).
        devices: torch devices whose results are compared value by value with the numpy path.
        large_batch: size of the large-batch check.
        max_levels: prefix-ordered codecs with ``code_size <= max_levels`` are decoded at every prefix level;
            longer codes at every level up to 64 and then at ``max_levels - 64`` levels spread evenly.
        golden: a golden fixture directory, or None.
    """

    blocks: np.ndarray
    atol: float = 1e-5
    devices: tuple[str, ...] = ("cpu",)
    large_batch: int = 4096
    max_levels: int = 512
    golden: Path | None = None


@dataclass
class Case:
    """One check's inputs: its own ``codec`` (a copy of the fitted reference), the options, whether the
    reference's ``fit`` returned ``self`` (None when the codec came fitted) and whether to rewrite the golden
    fixture instead of checking it."""

    codec: Codec
    options: CheckOptions
    fit_returned_self: bool | None = None
    regen_golden: bool = False
    report: dict[str, Any] = field(default_factory=dict)


def prefix_levels(k: int, max_levels: int = 512) -> list[int]:
    """The prefix lengths checked for a ``k``-element prefix-ordered code: all of ``1..k`` up to ``max_levels``
    elements, else every level up to 64 and ``max_levels - 64`` more spread evenly up to ``k``."""
    if k <= max_levels:
        return list(range(1, k + 1))
    head = list(range(1, 65))
    return sorted(set(head) | {int(v) for v in np.linspace(65, k, max_levels - 64).round()})


def _mse(a: Any, b: np.ndarray) -> float:
    """Mean squared difference, accumulated in float64 (the difference itself in the inputs' precision)."""
    d = np.asarray(a) - np.asarray(b)
    return float(np.mean(np.square(d), dtype=np.float64))


# -- the checks ---------------------------------------------------------------------------------------------
def check_attributes(case: Case) -> None:
    """Class attributes: ``codec_id`` matches the id pattern, ``prefix_ordered``/``requires_fit`` are bools,
    ``code_size`` is a positive int, ``capabilities`` names known capabilities the class implements."""
    cls = type(case.codec)
    assert isinstance(getattr(cls, "codec_id", None), str) and _ID.match(cls.codec_id), \
        f"attributes: codec_id must match {_ID.pattern}, got {getattr(cls, 'codec_id', None)!r}"
    assert isinstance(cls.prefix_ordered, bool) and isinstance(cls.requires_fit, bool), \
        "attributes: prefix_ordered and requires_fit must be bools"
    k = case.codec.code_size
    assert isinstance(k, int) and k > 0, f"attributes: code_size must be a positive int, got {k!r}"
    try:  # declared capabilities: known names, each implemented (spec section 4a)
        capabilities(cls)
    except errors.SDFCodecError as e:
        raise AssertionError(f"attributes: {e}") from e


def check_config_round_trip(case: Case) -> None:
    """``get_config()`` is JSON, carries the id, and ``get_codec(config)`` rebuilds the same class and config
    without modifying the dict."""
    codec, cls = case.codec, type(case.codec)
    cfg = codec.get_config()
    assert cfg.get("id") == cls.codec_id, f"config: 'id' must be {cls.codec_id!r}, got {cfg.get('id')!r}"
    try:
        cfg_json = json.loads(json.dumps(cfg))
    except (TypeError, ValueError) as e:
        raise AssertionError(f"config: get_config() is not JSON-serialisable: {e}") from e
    assert cfg_json == cfg, "config: get_config() changes in a JSON round trip (tuples? numpy scalars?)"
    before = copy.deepcopy(cfg_json)
    rebuilt = get_codec(cfg_json)
    assert cfg_json == before, "config: get_codec(config) modified the config dict"
    assert type(rebuilt) is cls, f"config: get_codec(config) built {type(rebuilt).__name__}, not {cls.__name__}"
    assert rebuilt.get_config() == cfg, "config: get_codec(codec.get_config()).get_config() differs"


def check_fit(case: Case) -> None:
    """A codec that ``requires_fit`` refuses to encode before fitting (``NotFittedError``); ``fit`` returns
    ``self`` and leaves ``is_fitted`` True."""
    codec, x = case.codec, case.options.blocks
    if type(codec).requires_fit:
        fresh = get_codec(codec.get_config())
        assert_raises(errors.NotFittedError, lambda: fresh.encode(x[:2]), "fitting: encode before fit")
    assert case.fit_returned_self is not False, "fitting: fit() must return self"
    assert codec.is_fitted, "fitting: is_fitted is False after fit"
    if not type(codec).requires_fit:
        assert codec.fit(x) is codec, "fitting: fit() must return self (even when it learns nothing)"


def check_round_trip(case: Case) -> dict[str, Any]:
    """numpy in gives float32 numpy out of the right shapes; decoded blocks are finite and closer than half
    the mean-block baseline; encoding is deterministic; float64 input gives float32's codes."""
    codec, x, atol = case.codec, case.options.blocks, case.options.atol
    k = codec.code_size
    codes = codec.encode(x)
    assert isinstance(codes, np.ndarray) and codes.dtype == np.float32 and codes.shape == (len(x), k), \
        f"round trip: encode(numpy {x.shape}) must give float32 numpy ({len(x)}, {k}), got " \
        f"{type(codes).__name__} {getattr(codes, 'dtype', None)} {getattr(codes, 'shape', None)}"
    dec = codec.decode(codes)
    assert isinstance(dec, np.ndarray) and dec.dtype == np.float32 and dec.shape == x.shape, \
        f"round trip: decode must give float32 numpy {x.shape}, got {getattr(dec, 'dtype', None)} " \
        f"{getattr(dec, 'shape', None)}"
    assert np.isfinite(dec).all(), "round trip: decode produced NaN or Inf"
    mse = _mse(dec, x)
    baseline = _mse(x, x.mean(axis=0))
    assert mse < 0.5 * baseline, f"round trip: MSE {mse:.4g} is not below half of the mean-block baseline " \
                                 f"{baseline:.4g}; the codes carry too little of the block"
    assert_close(codec.encode(x), codes, 0.0, "determinism: encoding twice")
    assert_close(codec.encode(x.astype(np.float64)), codes, atol, "dtypes: float64 input")
    return {"mse": mse}


def check_batch_sizes(case: Case) -> None:
    """One block alone, a large batch and an empty batch give the codes and blocks of the whole batch."""
    codec, x, atol, large = case.codec, case.options.blocks, case.options.atol, case.options.large_batch
    k = codec.code_size
    codes = codec.encode(x)
    dec = codec.decode(codes)
    # other batch sizes take other BLAS kernels (blocking, threads): float32 sums of 4096 terms in another order
    # (measured: 1.5e-5 for a small autoencoder's codes of magnitude 1, batch 4096 vs 256)
    atol = 4 * atol
    for i in (0, len(x) - 1):
        assert_close(codec.encode(x[i:i + 1]), codes[i:i + 1], atol, f"batch: encode of block {i} alone")
        assert_close(codec.decode(codes[i:i + 1]), dec[i:i + 1], atol, f"batch: decode of block {i} alone")
    big = np.concatenate([x] * -(-large // len(x)))[:large]
    assert_close(codec.encode(big)[: len(x)], codes[: min(len(x), large)], atol, f"batch: batch of {large}")
    empty = codec.encode(x[:0])
    assert empty.shape == (0, k), f"batch: encode of 0 blocks must give (0, {k}), got {empty.shape}"
    assert codec.decode(codes[:0]).shape == (0, 16, 16, 16), "batch: decode of 0 codes"


def check_devices(case: Case) -> None:
    """Tensors in give float32 tensors on the same device out, with the numpy path's values (CPU, and CUDA
    where available); float16 tensors are accepted."""
    codec, x, atol = case.codec, case.options.blocks, case.options.atol
    codes = codec.encode(x)
    dec = codec.decode(codes)
    for dev in case.options.devices:
        t = torch.from_numpy(x).to(dev)
        tc = codec.encode(t)
        assert isinstance(tc, torch.Tensor) and tc.device.type == torch.device(dev).type \
            and tc.dtype == torch.float32, f"devices: encode(tensor on {dev}) must return a float32 tensor on {dev}"
        td = codec.decode(tc)
        assert isinstance(td, torch.Tensor) and td.device.type == torch.device(dev).type \
            and td.dtype == torch.float32, f"devices: decode(tensor on {dev}) must return a float32 tensor on {dev}"
        # GPU matrix products may use TF32/other orders of summation: compare loosely but meaningfully
        tol = atol if dev == "cpu" else max(atol, 1e-3)
        assert_close(tc, codes, tol, f"devices: codes on {dev} vs numpy")
        assert_close(td, dec, tol, f"devices: decoded on {dev} vs numpy")
        assert_close(codec.encode(t.half()), codec.encode(x.astype(np.float16).astype(np.float32)),
                     tol, f"devices: float16 tensor input on {dev}")


def check_meta_device(case: Case) -> None:
    """Results follow the input's device even without a GPU: on torch's ``meta`` device (shapes, no values)
    encode, decode, prefix decodes and ``decode_core`` return meta tensors. A codec that computes on the
    CPU and moves results back, or always returns CPU tensors, fails here."""
    codec, n = case.codec, 4
    k = codec.code_size
    hint = "; a codec must compute on the input's device (torch ops on the tensor, no .cpu()/.numpy())"

    def on_meta(what: str, fn: Callable[[], Any], shape: tuple[int, ...]) -> Any:
        try:
            out = fn()
        except Exception as e:  # noqa: BLE001 - the failure is the finding
            raise AssertionError(f"meta device: {what} raised {type(e).__name__}: {e}{hint}") from e
        assert isinstance(out, torch.Tensor) and out.device.type == "meta", \
            f"meta device: {what} must return a tensor on meta, got " \
            f"{type(out).__name__} on {getattr(out, 'device', None)}{hint}"
        assert tuple(out.shape) == shape and out.dtype == torch.float32, \
            f"meta device: {what} gave {out.dtype} {tuple(out.shape)}, not float32 {shape}"
        return out

    blocks = torch.empty((n, 16, 16, 16), device="meta")
    codes = on_meta("encode(blocks on meta)", lambda: codec.encode(blocks), (n, k))
    on_meta("decode(codes on meta)", lambda: codec.decode(codes), (n, 16, 16, 16))
    on_meta("decode_core(codes on meta, scale, offset)",
            lambda: codec.decode_core(codes, scale=_SCALE, offset=_OFFSET), (n, 16, 16, 16))
    if type(codec).prefix_ordered and k > 1:
        on_meta(f"decode of a {k // 2 or 1}-element prefix on meta", lambda: codec.decode(codes[:, : max(1, k // 2)]),
                (n, 16, 16, 16))


def check_decode_on_read(case: Case) -> None:
    """The decode-on-read hooks (spec/codec-plugins.md 3b): ``decode_core(codes, scale, offset)`` equals
    ``scale * decode_core(codes) + offset`` and leaves the codes alone (whether or not the codec folds the affine
    step into its weights through the ``decode_affine`` hook); ``decode_bound`` is None or bounds every decoded
    magnitude."""
    codec, x, atol = case.codec, case.options.blocks, case.options.atol
    codes = codec.encode(x)
    kept = codes.copy()
    core = codec.decode_core(codes)
    metres = codec.decode_core(codes, scale=_SCALE, offset=_OFFSET)
    assert_close(metres, np.asarray(core, np.float64) * _SCALE + _OFFSET, atol * _SCALE,
                 "decode on read: decode_core(codes, scale, offset) vs scale * decode_core(codes) + offset")
    assert_close(codes, kept, 0.0, "decode on read: decode_core(scale=...) modified the codes")
    bound = codec.decode_bound(torch.from_numpy(codes))
    if bound is not None:
        peak = float(np.abs(core).max())
        assert bound >= peak * (1 - 1e-5), f"decode on read: decode_bound gave {bound:.6g} below the " \
                                           f"largest decoded magnitude {peak:.6g}"


def check_decode_out(case: Case) -> None:
    """Decoding into a caller's buffer (spec/codec-plugins.md 4, ``decode_into``): ``decode(codes, out=buf)`` and
    ``decode_core(codes, scale, offset, out=buf)`` fill ``buf`` (``(N, 16, 16, 16)`` or ``(N, 4096)``, numpy or a
    tensor) with what they return without it, at a few prefix levels for prefix-ordered codecs, and return
    ``buf`` itself; a buffer of the wrong shape, dtype, kind or layout, or overlapping the codes, is refused."""
    codec, x, atol = case.codec, case.options.blocks, case.options.atol
    codes = codec.encode(x)
    n, k = codes.shape
    levels = [k]
    if type(codec).prefix_ordered:
        lv = prefix_levels(k, case.options.max_levels)
        levels = sorted({lv[0], lv[len(lv) // 2], k})
    for level in levels:
        c = np.ascontiguousarray(codes[:, :level])
        for shape in ((n, 16, 16, 16), (n, 4096)):
            buf = np.full(shape, np.nan, np.float32)  # NaN: a voxel left unwritten cannot pass
            got = codec.decode(c, out=buf)
            assert got is buf, f"decode out=: returned a {type(got).__name__}, not the buffer given"
            assert_close(buf.reshape(n, 16, 16, 16), codec.decode(c), atol,
                         f"decode out=: a {level}-element code into a {shape} buffer vs decode without out")
        buf = np.full((n, 16, 16, 16), np.nan, np.float32)
        assert codec.decode_core(c, scale=_SCALE, offset=_OFFSET, out=buf) is buf, "decode_core out=: not the buffer"
        assert_close(buf, codec.decode_core(c, scale=_SCALE, offset=_OFFSET), atol * _SCALE,
                     f"decode_core out=: a {level}-element code in metres vs decode_core without out")
    t = torch.from_numpy(codes.copy())
    tbuf = torch.full((n, 4096), float("nan"))
    assert codec.decode(t, out=tbuf) is tbuf, "decode out=: a tensor buffer was not returned as given"
    assert_close(tbuf.reshape(n, 16, 16, 16), codec.decode(codes), atol, "decode out=: tensor codes and buffer")
    empty_buf = np.empty((0, 16, 16, 16), np.float32)
    assert codec.decode(codes[:0], out=empty_buf) is empty_buf, "decode out=: an empty batch's buffer not returned"
    refusals = (
        (errors.ShapeError, np.empty((n + 1, 16, 16, 16), np.float32), "a buffer for one block more"),
        (errors.ShapeError, np.empty((n, 16, 16), np.float32), "a buffer of 16^2 blocks"),
        (errors.DTypeError, np.empty((n, 4096), np.float64), "a float64 buffer"),
        (errors.DTypeError, torch.empty((n, 4096)), "a tensor buffer for numpy codes"),
        (errors.InvalidValueError, np.empty((n, 8192), np.float32)[:, ::2], "a strided buffer"),
    )
    for exc, bad, what in refusals:
        assert_raises(exc, lambda: codec.decode(codes, out=bad), f"decode out=: {what}")
    shared = np.empty(n * 4096, np.float32)  # codes stored inside the buffer they would be decoded into
    inside = shared[: n * k].reshape(n, k)
    inside[:] = codes
    assert_raises(errors.InvalidValueError, lambda: codec.decode(inside, out=shared.reshape(n, 4096)),
                  "decode out=: a buffer overlapping the codes")


def check_decode_tiles(case: Case) -> None:
    """Decoding, clipping and handing out tiles (spec/codec-plugins.md 4, ``decode_tiles``; what map readers use
    for a truncated decode): against ``decode_core(codes, scale, offset)`` clipped by numpy, into a NaN-filled
    buffer and without one, the tiles handed to ``each`` cover the batch once each, hold the same values as the
    buffer's rows, and the codes are left untouched. Clip bounds inside the decoded range make the clip count."""
    codec, x, atol = case.codec, case.options.blocks, case.options.atol
    codes = codec.encode(x)
    n = len(codes)
    ref = np.asarray(codec.decode_core(codes, scale=_SCALE, offset=_OFFSET), np.float32)
    lo, hi = (float(v) for v in np.quantile(ref, [0.2, 0.8]))  # 40 % of the voxels clipped
    want = np.clip(ref, lo, hi)
    kept = codes.copy()
    for given in (True, False):
        out = torch.full((n, 16, 16, 16), float("nan")) if given else None
        seen = np.zeros(n, np.int64)
        tiles = np.full((n, 16, 16, 16), np.nan, np.float32)

        def each(a: int, b: int, tile: torch.Tensor) -> None:
            seen[a:b] += 1  # disjoint tiles: no two threads write the same rows
            tiles[a:b] = tile.numpy()

        codec.decode_tiles(torch.from_numpy(codes), _SCALE, _OFFSET, (lo, hi), each, out)
        what = "into a buffer" if given else "without a buffer"
        assert (seen == 1).all(), f"decode_tiles {what}: rows handed out {sorted(set(seen.tolist()))} times, not once"
        assert_close(tiles, want, atol * _SCALE, f"decode_tiles {what}: tiles vs np.clip(decode_core(codes), lo, hi)")
        if given:
            assert_close(out.numpy(), want, atol * _SCALE, "decode_tiles: the buffer vs np.clip(decode_core(codes))")
            assert_close(out.numpy(), tiles, 0.0, "decode_tiles: the tiles handed out vs the buffer's rows")
    assert_close(codes, kept, 0.0, "decode_tiles: modified the codes")


def check_numpy_path(case: Case) -> None:
    """The torch-free path (spec/codec-plugins.md 4, ``numpy_path``; what searches use) of a codec declaring
    it: float32 numpy codes and blocks equal to ``encode`` and ``decode`` (and a prefix's decode, for
    prefix-ordered codecs), and its optional ``decode_affine`` equal to ``decode_core`` with a map's scaling.
    Codecs without the capability pass."""
    codec, x, atol = case.codec, case.options.blocks, case.options.atol
    if "numpy_path" not in capabilities(codec):
        return
    path = codec.numpy_path()
    assert path is not None, "numpy_path: declared, but a fitted codec returned None"
    n = len(x)
    codes = np.asarray(codec.encode(x))
    got = path.encode(np.ascontiguousarray(x, np.float32).reshape(n, -1))
    assert isinstance(got, np.ndarray) and got.dtype == np.float32 and got.shape == codes.shape, \
        f"numpy_path encode: got {type(got).__name__} {getattr(got, 'dtype', '')} {getattr(got, 'shape', '')}"
    assert_close(got, codes, atol * max(1.0, float(np.abs(codes).max())), "numpy_path encode vs encode")
    for k in sorted({codec.code_size, max(1, codec.code_size // 2)} if codec.prefix_ordered else {codec.code_size}):
        want = np.asarray(codec.decode(codes[:, :k])).reshape(n, -1)
        back = path.decode(np.ascontiguousarray(codes[:, :k]))
        assert isinstance(back, np.ndarray) and back.dtype == np.float32 and back.shape == want.shape, \
            f"numpy_path decode of {k} elements: got {getattr(back, 'dtype', '')} {getattr(back, 'shape', '')}"
        assert_close(back, want, atol, f"numpy_path decode of {k} elements vs decode")
        affine = getattr(path, "decode_affine", None)  # optional: readers fall back to torch without it
        if affine is not None:
            scale, offset = 0.14, -0.04  # a map's truncation range and d_min, the scaling readers fold in
            want = np.asarray(codec.decode_core(codes[:, :k], scale=scale, offset=offset)).reshape(n, -1)
            got = affine(np.ascontiguousarray(codes[:, :k]), scale, offset)
            assert isinstance(got, np.ndarray) and got.dtype == np.float32 and got.shape == want.shape, \
                f"numpy_path decode_affine of {k} elements: got {getattr(got, 'dtype', '')} " \
                f"{getattr(got, 'shape', '')}"
            assert_close(got, want, atol, f"numpy_path decode_affine of {k} elements vs decode_core")


def _outputs(codec: Codec, x: np.ndarray, max_levels: int) -> dict[str, Any]:
    """Everything a codec computes from ``x``: codes, decoded blocks (numpy and CPU tensors), decodes at a few
    prefix levels, and ``decode_core`` in metres; used to compare two codecs that must be the same."""
    k = codec.code_size
    codes = codec.encode(x)
    out = {"codes": codes, "decoded": codec.decode(codes),
           "tensor codes": codec.encode(torch.from_numpy(x.copy())),
           "tensor decoded": codec.decode(torch.from_numpy(codes.copy())),
           "decode_core in metres": codec.decode_core(codes, scale=_SCALE, offset=_OFFSET)}
    if type(codec).prefix_ordered:
        levels = prefix_levels(k, max_levels)
        for lv in sorted({levels[0], levels[len(levels) // 2], levels[-1]}):
            out[f"decode of a {lv}-element prefix"] = codec.decode(codes[:, :lv])
    return out


def _same_outputs(a: dict[str, Any], b: dict[str, Any], what: str) -> None:
    for name in a:
        assert_close(a[name], b[name], 0.0, f"{what}: {name}")


def check_state_round_trip(case: Case) -> None:
    """``state_dict`` holds plain numeric numpy arrays, and a codec rebuilt from ``get_config()`` and the state
    alone encodes and decodes exactly like the original (a learned attribute missing from the state fails)."""
    codec, x = case.codec, case.options.blocks
    state = codec.state_dict()
    for name, arr in state.items():
        assert isinstance(arr, np.ndarray) and arr.dtype.kind in "fiub", \
            f"state: {name!r} must be a plain numeric numpy array, got {type(arr).__name__} {getattr(arr, 'dtype', '')}"
    cfg = codec.get_config()
    fresh = get_codec(json.loads(json.dumps(cfg))).load_state_dict(copy.deepcopy(state))
    assert fresh.get_config() == cfg, "state: the rebuilt codec's get_config() differs"
    again = fresh.state_dict()
    assert sorted(again) == sorted(state), f"state: the rebuilt codec's state has arrays {sorted(again)}, " \
                                           f"not {sorted(state)}"
    for name in state:
        assert np.array_equal(np.asarray(again[name]), state[name]), f"state: array {name!r} changed in a round trip"
    # the spec promises that config + state rebuild an *equal* codec (Codec.__eq__: class, config, state)
    assert fresh == codec, "state: get_codec(get_config()).load_state_dict(state_dict()) != the original codec"
    lv = case.options.max_levels
    before = _outputs(codec, x, lv)
    _same_outputs(before, _outputs(fresh, x, lv), "state: rebuilt from get_config() + state_dict() vs the original")
    if not state:
        return
    # learned state kept outside the instance (a class attribute, a module-level cache) passes the comparison
    # above in one process and is lost in any other (a map decoded elsewhere): fit another instance of the same
    # configuration on other blocks and give it another state, then rebuild again; the original must not change
    # and the rebuild must still match it
    rival = get_codec(json.loads(json.dumps(cfg)))
    if type(codec).requires_fit:
        rival.fit(analytic_blocks(max(len(x), 256), seed=4243))
    other = _other_state(codec, x)
    if other is not None:
        rival.load_state_dict(copy.deepcopy(other))
    rebuilt = get_codec(json.loads(json.dumps(cfg))).load_state_dict(copy.deepcopy(state))
    where = "state: learned state outside state_dict() (a class attribute or module cache?)"
    _same_outputs(before, _outputs(rebuilt, x, lv), f"{where}: rebuilt after another instance was fitted")
    _same_outputs(before, _outputs(codec, x, lv), f"{where}: the original after another instance was fitted")


def _other_state(codec: Codec, x: np.ndarray) -> dict[str, np.ndarray] | None:
    """A valid learned state different from ``codec``'s: its float arrays scaled and shifted, or, where the
    codec refuses that, the state of a copy fitted on other blocks. None for codecs without state."""
    state = codec.state_dict()
    if not state:
        return None
    other = {k: (v * 1.125 + 0.01).astype(v.dtype) if v.dtype.kind == "f" else v.copy() for k, v in state.items()}
    try:
        get_codec(codec.get_config()).load_state_dict(copy.deepcopy(other))
        return other
    except errors.SDFCodecError:
        refit = get_codec(codec.get_config()).fit(analytic_blocks(max(len(x), 256), seed=4242))
        return refit.state_dict()


def check_load_state_after_use(case: Case) -> None:
    """``load_state_dict`` on a codec that has already encoded and decoded (on every path, so derived caches
    are filled) gives exactly the codec that a fresh rebuild with that state is: no stale derived cache."""
    codec, x, lv = case.codec, case.options.blocks, case.options.max_levels
    _outputs(codec, x, lv)  # use it: fill whatever the codec derives and caches from its state
    other = _other_state(codec, x)
    if other is None:
        case.report["load_state_after_use"] = "no learned state"
        return
    assert codec.load_state_dict(copy.deepcopy(other)) is codec, "state: load_state_dict() must return self"
    fresh = get_codec(codec.get_config()).load_state_dict(copy.deepcopy(other))
    _same_outputs(_outputs(codec, x, lv), _outputs(fresh, x, lv),
                  "state: a used codec after load_state_dict(other) vs a fresh codec with that state")


def check_inputs_untouched(case: Case) -> None:
    """encode, decode and ``decode_core`` leave their inputs alone (compared with copies taken before, and for
    tensors their version counter, which also catches in-place writes of the same values), and a result is
    not overwritten by a later call (a reused buffer)."""
    codec, k = case.codec, case.codec.code_size
    # values outside [0, 1]: an in-place clamp or similar "harmless" normalisation shows
    x = (case.options.blocks * 1.5 - 0.25).astype(np.float32)
    levels = [k] + ([max(1, k // 2)] if type(codec).prefix_ordered and k > 1 else [])

    def untouched(what: str, fn: Callable[[Any], Any], arg: np.ndarray) -> Any:
        a, kept = arg.copy(), arg.copy()
        out = fn(a)
        assert np.array_equal(a, kept), f"inputs: {what} modified its numpy input"
        t = torch.from_numpy(arg.copy())
        version = t._version
        fn(t)
        assert t._version == version, f"inputs: {what} wrote into its tensor input in place"
        assert torch.equal(t, torch.from_numpy(kept)), f"inputs: {what} modified its tensor input"
        return out

    codes = untouched("encode", codec.encode, x)
    for lv in levels:
        untouched(f"decode of {lv} code elements", codec.decode, codes[:, :lv])
        untouched(f"decode_core of {lv} code elements (scale, offset)",
                  lambda c: codec.decode_core(c, scale=_SCALE, offset=_OFFSET), codes[:, :lv])
    first = codec.encode(x[:4])
    kept = first.copy()
    dec = codec.decode(first)
    dec_kept = dec.copy()
    codec.decode(codec.encode(x[-4:][::-1].copy()))
    assert np.array_equal(first, kept) and np.array_equal(dec, dec_kept), \
        "inputs: a later encode/decode overwrote an earlier result (a reused output buffer)"


def check_prefix_decoding(case: Case) -> dict[str, Any]:
    """Prefix-ordered codecs: every prefix level (all of them, or a dense set for long codes) decodes to
    finite blocks of the right shape, no worse than the next shorter level and better than the best constant
    block (one block for every input: what a level lacking its gain element decodes to); the whole code
    decodes as ``decode`` does. Other codecs refuse a prefix with ``ShapeError``."""
    codec, x = case.codec, case.options.blocks
    k = codec.code_size
    codes = codec.encode(x)
    if not type(codec).prefix_ordered:
        if k > 1:
            assert_raises(errors.ShapeError, lambda: codec.decode(codes[:, : k - 1]),
                          "prefix: decoding a prefix of a codec that is not prefix-ordered")
        return {}
    # the best constant block: the per-voxel mean of the test blocks, the most a decode ignoring its code gives
    constant = _mse(x, x.mean(axis=0, dtype=np.float64))
    levels = prefix_levels(k, case.options.max_levels)
    errs: dict[int, float] = {}
    for lv in levels:
        d = codec.decode(codes[:, :lv])
        assert isinstance(d, np.ndarray) and d.shape == x.shape and d.dtype == np.float32, \
            f"prefix: decode of a {lv}-element prefix gave {getattr(d, 'dtype', None)} {getattr(d, 'shape', None)}"
        assert np.isfinite(d).all(), f"prefix: decode of a {lv}-element prefix produced NaN or Inf"
        errs[lv] = _mse(d, x)
    bad = [lv for lv in levels if not errs[lv] < constant]
    assert not bad, f"prefix: a {bad[0]}-element prefix decodes with MSE {errs[bad[0]]:.4g}, no better than the " \
                    f"best constant block ({constant:.4g}); levels failing: {bad[:10]}"
    for a, b in zip(levels, levels[1:]):
        assert errs[b] <= errs[a] * (1 + 1e-4) + 1e-7, \
            f"prefix: error grows from a {a}-element prefix (MSE {errs[a]:.6g}) to {b} elements ({errs[b]:.6g})"
    assert_close(codec.decode(codes[:, :k]), codec.decode(codes), 0.0, "prefix: the whole code vs decode")
    return {"prefix_mse": errs}


def check_bad_input(case: Case) -> None:
    """Wrong shapes, integer dtypes and non-finite values raise the project's errors with a message."""
    codec, x = case.codec, case.options.blocks
    k = codec.code_size
    codes = codec.encode(x[:2])
    assert_raises(errors.ShapeError, lambda: codec.encode(x[0]), "bad input: a block without batch axis")
    assert_raises(errors.ShapeError, lambda: codec.encode(np.ones((2, 8, 8, 8), np.float32)), "bad input: 8^3 blocks")
    assert_raises(errors.DTypeError, lambda: codec.encode(x[:2].astype(np.int32)), "bad input: integer blocks")
    nan = x[:2].copy()
    nan[0, 3, 4, 5] = np.nan
    assert_raises(errors.InvalidValueError, lambda: codec.encode(nan), "bad input: NaN in blocks")
    inf = codes.copy()
    inf[1, 0] = np.inf
    assert_raises(errors.InvalidValueError, lambda: codec.decode(inf), "bad input: Inf in codes")
    assert_raises(errors.ShapeError, lambda: codec.decode(np.zeros((2, k + 1), np.float32)),
                  "bad input: code too long")
    assert_raises(errors.ShapeError, lambda: codec.decode(np.zeros((k,), np.float32)),
                  "bad input: codes without batch axis")


def check_golden_fixture(case: Case) -> None:
    """The codec rebuilt from the golden fixture reproduces its frozen codes and decoded blocks (or, with
    ``regen_golden``, the fixture is rewritten from the codec under test)."""
    path = case.options.golden
    assert path is not None, "golden: no fixture directory given"
    if case.regen_golden:
        write_golden(case.codec, path)
    else:
        check_golden(path, case.options.atol)


#: (name, function) of every check, in the order they run
CHECKS: tuple[tuple[str, Callable[[Case], Any]], ...] = (
    ("attributes", check_attributes),
    ("config_round_trip", check_config_round_trip),
    ("fit", check_fit),
    ("round_trip", check_round_trip),
    ("decode_on_read", check_decode_on_read),
    ("decode_out", check_decode_out),
    ("decode_tiles", check_decode_tiles),
    ("numpy_path", check_numpy_path),
    ("batch_sizes", check_batch_sizes),
    ("devices", check_devices),
    ("meta_device", check_meta_device),
    ("state_round_trip", check_state_round_trip),
    ("load_state_after_use", check_load_state_after_use),
    ("inputs_untouched", check_inputs_untouched),
    ("prefix_decoding", check_prefix_decoding),
    ("bad_input", check_bad_input),
    ("golden_fixture", check_golden_fixture),
)
