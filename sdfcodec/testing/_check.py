"""``check_codec``: the conformance suite of the codec contract (see :mod:`sdfcodec.codec`).

Each check raises ``AssertionError`` naming the check and what was wrong, so it reads well under pytest.
"""

from __future__ import annotations

import contextlib
import copy
import json
import re
from pathlib import Path
from typing import Any, Callable, Iterator

import numpy as np
import torch

from .. import errors
from ..codec import Codec
from ..model import load_state_file, save_state_file
from ..registry import get_codec
from ._data import analytic_blocks

__all__ = ["check_codec", "golden_dir_files"]

_ID = re.compile(r"^[a-z0-9][a-z0-9_.-]*$")
GOLDEN_FILES = ("config.json", "state.npz", "input.npy", "codes.npy", "decoded.npy")


def golden_dir_files(path: str | Path) -> list[Path]:
    """The files a golden fixture directory holds."""
    return [Path(path) / f for f in GOLDEN_FILES]


def _raises(exc: type[BaseException], fn: Callable[[], Any], what: str) -> None:
    try:
        fn()
    except exc as e:
        assert str(e), f"{what}: {exc.__name__} was raised without a message"
        return
    except Exception as e:  # noqa: BLE001 - we report the wrong type
        raise AssertionError(f"{what}: expected sdfcodec.errors.{exc.__name__}, got {type(e).__name__}: {e}") from e
    raise AssertionError(f"{what}: expected sdfcodec.errors.{exc.__name__}, nothing was raised")


@contextlib.contextmanager
def _check(name: str) -> Iterator[None]:
    """Report an unexpected exception inside a check as that check's failure."""
    try:
        yield
    except AssertionError:
        raise
    except Exception as e:  # noqa: BLE001
        raise AssertionError(f"{name}: raised {type(e).__name__}: {e}") from e


def _close(a: np.ndarray, b: np.ndarray, atol: float, what: str) -> None:
    """``a`` equals ``b`` to ``atol`` times the magnitude of ``b`` (at least 1): float32 sums of 4096 terms
    in another order (batch of 1 vs many, another BLAS kernel) differ in the last bits of large codes."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    assert a.shape == b.shape, f"{what}: shape {a.shape} != {b.shape}"
    if not a.size:
        return
    err, tol = float(np.max(np.abs(a - b))), atol * max(1.0, float(np.max(np.abs(b))))
    assert err <= tol, f"{what}: max abs difference {err:.3g} > {tol:.3g}"


def check_codec(codec: Codec, *, blocks: np.ndarray | None = None, golden: str | Path | None = None,
                regen_golden: bool = False, devices: list[str] | None = None, large_batch: int = 4096,
                atol: float = 1e-5) -> dict[str, Any]:
    """Run the conformance suite on ``codec``; return a small report (checks run, measured errors).

    Args:
        codec: an instance. If it ``requires_fit`` and is not fitted, it is fitted on ``blocks``.
        blocks: normalised test blocks ``(N, 16, 16, 16)``; default: 256 exact analytic blocks.
        golden: a directory with a frozen fixture (config, state, input, codes, decoded). The codec rebuilt
            from it must reproduce the codes and decoded blocks. Missing files fail unless ``regen_golden``.
        regen_golden: (re)write the fixture from ``codec`` instead of checking it. Only for format changes.
        devices: torch devices to check; default ``cpu`` plus ``cuda`` when available.
        large_batch: size of the large-batch check.
        atol: tolerance of numerical comparisons (normalised units).
    """
    report: dict[str, Any] = {"codec": repr(codec), "checks": []}
    done = report["checks"].append
    x = analytic_blocks(256) if blocks is None else np.asarray(blocks, dtype=np.float32)
    cls = type(codec)

    # 1. class attributes
    assert isinstance(getattr(cls, "codec_id", None), str) and _ID.match(cls.codec_id), \
        f"attributes: codec_id must match {_ID.pattern}, got {getattr(cls, 'codec_id', None)!r}"
    assert isinstance(cls.prefix_ordered, bool) and isinstance(cls.requires_fit, bool), \
        "attributes: prefix_ordered and requires_fit must be bools"
    k = codec.code_size
    assert isinstance(k, int) and k > 0, f"attributes: code_size must be a positive int, got {k!r}"
    done("attributes")

    # 2. configuration: JSON only, rebuilt by get_codec, the dict not mutated
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
    done("config round trip")

    # 3. fitting
    with _check("fitting"):
        if cls.requires_fit:
            _raises(errors.NotFittedError, lambda: rebuilt.encode(x[:2]), "fitting: encode before fit")
            if not codec.is_fitted:
                assert codec.fit(x) is codec, "fitting: fit() must return self"
            assert codec.is_fitted, "fitting: is_fitted is False after fit"
        else:
            assert codec.fit(x) is codec, "fitting: fit() must return self (even when it learns nothing)"
        done("fit")

    # 4. round trip, shapes, dtypes, numpy in -> numpy out, determinism
    with _check("round trip"):
        codes = codec.encode(x)
        assert isinstance(codes, np.ndarray) and codes.dtype == np.float32 and codes.shape == (len(x), k), \
            f"round trip: encode(numpy {x.shape}) must give float32 numpy ({len(x)}, {k}), got " \
            f"{type(codes).__name__} {getattr(codes, 'dtype', None)} {getattr(codes, 'shape', None)}"
        dec = codec.decode(codes)
        assert isinstance(dec, np.ndarray) and dec.dtype == np.float32 and dec.shape == x.shape, \
            f"round trip: decode must give float32 numpy {x.shape}, got {getattr(dec, 'dtype', None)} {dec.shape}"
        assert np.isfinite(dec).all(), "round trip: decode produced NaN or Inf"
        mse = float(np.mean((dec - x) ** 2))
        baseline = float(np.mean((x - x.mean(axis=0)) ** 2))
        assert mse < 0.5 * baseline, f"round trip: MSE {mse:.4g} is not below half of the mean-block baseline " \
                                     f"{baseline:.4g}; the codes carry too little of the block"
        report["mse"] = mse
        _close(codec.encode(x), codes, 0.0, "determinism: encoding twice")
        _close(codec.encode(x.astype(np.float64)), codes, atol, "dtypes: float64 input")
        done("round trip")

    # 4b. decode-on-read hooks (spec/codec-plugins.md 3b): scaled core decodes, the codec's output bound
    with _check("decode on read"):
        scale, offset = 0.14, -0.04  # a map's truncation (-0.04, 0.1) m: what readers pass
        kept = codes.copy()
        core = codec.decode_core(codes)
        metres = codec.decode_core(codes, scale=scale, offset=offset)
        _close(metres, np.asarray(core, np.float64) * scale + offset, atol * scale,
               "decode on read: decode_core(codes, scale, offset) vs scale * decode_core(codes) + offset")
        _close(codes, kept, 0.0, "decode on read: decode_core(scale=...) modified the codes")
        bound = codec._decode_bound(torch.from_numpy(codes))
        if bound is not None:
            peak = float(np.abs(core).max())
            assert bound >= peak * (1 - 1e-5), f"decode on read: _decode_bound gave {bound:.6g} below the " \
                                               f"largest decoded magnitude {peak:.6g}"
        done("decode on read")

    # 5. batch independence: one block at a time and a large batch give the same codes
    with _check("batch"):
        for i in (0, len(x) - 1):
            _close(codec.encode(x[i:i + 1]), codes[i:i + 1], atol, f"batch: encode of block {i} alone")
            _close(codec.decode(codes[i:i + 1]), dec[i:i + 1], atol, f"batch: decode of block {i} alone")
        reps = -(-large_batch // len(x))
        big = np.concatenate([x] * reps)[:large_batch]
        _close(codec.encode(big)[: len(x)], codes[: min(len(x), large_batch)], atol, f"batch: batch of {large_batch}")
        empty = codec.encode(x[:0])
        assert empty.shape == (0, k), f"batch: encode of 0 blocks must give (0, {k}), got {empty.shape}"
        assert codec.decode(codes[:0]).shape == (0, 16, 16, 16), "batch: decode of 0 codes"
        done("batch sizes")

    # 6. torch input, devices follow the input
    with _check("devices"):
        devs = devices or (["cpu"] + (["cuda"] if torch.cuda.is_available() else []))
        for dev in devs:
            t = torch.from_numpy(x).to(dev)
            tc = codec.encode(t)
            assert isinstance(tc, torch.Tensor) and tc.device.type == torch.device(dev).type and tc.dtype == torch.float32, \
                f"devices: encode(tensor on {dev}) must return a float32 tensor on {dev}"
            td = codec.decode(tc)
            assert isinstance(td, torch.Tensor) and td.device.type == torch.device(dev).type, \
                f"devices: decode(tensor on {dev}) must return a tensor on {dev}"
            # GPU matrix products may use TF32/other orders of summation: compare loosely but meaningfully
            tol = atol if dev == "cpu" else max(atol, 1e-3)
            _close(tc.cpu().numpy(), codes, tol, f"devices: codes on {dev} vs numpy")
            _close(td.cpu().numpy(), dec, tol, f"devices: decoded on {dev} vs numpy")
            _close(codec.encode(t.half()).cpu().numpy(), codec.encode(x.astype(np.float16).astype(np.float32)),
                   tol, f"devices: float16 tensor input on {dev}")
        done("devices")

    # 7. state round trip into a fresh codec built from the config
    with _check("state"):
        state = codec.state_dict()
        for name, arr in state.items():
            assert isinstance(arr, np.ndarray) and arr.dtype.kind in "fiub", \
                f"state: {name!r} must be a plain numeric numpy array, got {type(arr).__name__} {getattr(arr, 'dtype', '')}"
        fresh = get_codec(cfg).load_state_dict(copy.deepcopy(state))
        _close(fresh.encode(x), codes, 0.0, "state: codes after load_state_dict")
        _close(fresh.decode(codes), dec, 0.0, "state: decoded after load_state_dict")
        done("state round trip")

    # 8. prefix decoding
    with _check("prefix"):
        _check_prefix(codec, cls, x, codes, k, report)
    done("prefix decoding")

    # 9. bad input gives the project's errors
    _raises(errors.ShapeError, lambda: codec.encode(x[0]), "bad input: a block without batch axis")
    _raises(errors.ShapeError, lambda: codec.encode(np.ones((2, 8, 8, 8), np.float32)), "bad input: 8^3 blocks")
    _raises(errors.DTypeError, lambda: codec.encode(x[:2].astype(np.int32)), "bad input: integer blocks")
    nan = x[:2].copy()
    nan[0, 3, 4, 5] = np.nan
    _raises(errors.InvalidValueError, lambda: codec.encode(nan), "bad input: NaN in blocks")
    inf = codes[:2].copy()
    inf[1, 0] = np.inf
    _raises(errors.InvalidValueError, lambda: codec.decode(inf), "bad input: Inf in codes")
    _raises(errors.ShapeError, lambda: codec.decode(np.zeros((2, k + 1), np.float32)), "bad input: code too long")
    _raises(errors.ShapeError, lambda: codec.decode(np.zeros((k,), np.float32)), "bad input: codes without batch axis")
    done("bad input")

    # 10. golden fixture: written once, decoded forever
    if golden is not None:
        with _check("golden"):
            _golden(codec, Path(golden), regen_golden, atol)
        done("golden fixture")
    return report


def _golden(codec: Codec, path: Path, regen: bool, atol: float) -> None:
    cfg_p, state_p, in_p, codes_p, dec_p = golden_dir_files(path)
    if regen:
        path.mkdir(parents=True, exist_ok=True)
        x = analytic_blocks(8, seed=2024)
        codes = codec.encode(x)
        cfg_p.write_text(json.dumps(codec.get_config(), indent=2, sort_keys=True) + "\n")
        save_state_file(state_p, codec.state_dict())
        np.save(in_p, x)
        np.save(codes_p, codes)
        np.save(dec_p, codec.decode(codes))
        return
    missing = [p.name for p in golden_dir_files(path) if not p.exists()]
    assert not missing, f"golden: {path} lacks {missing}; create it once with regen_golden=True " \
                        "(pytest --regen-golden) and commit it"
    g = get_codec(json.loads(cfg_p.read_text())).load_state_dict(load_state_file(state_p))
    x = np.load(in_p, allow_pickle=False)
    codes = np.load(codes_p, allow_pickle=False)
    _close(g.encode(x), codes, atol, f"golden: codes of {path}")
    _close(g.decode(codes), np.load(dec_p, allow_pickle=False), atol, f"golden: decoded blocks of {path}")


def _check_prefix(codec: Codec, cls: type, x: np.ndarray, codes: np.ndarray, k: int, report: dict) -> None:
    if cls.prefix_ordered:
        levels = sorted({1, max(1, k // 4), max(1, k // 2), k})
        errs = []
        for lv in levels:
            d = codec.decode(codes[:, :lv])
            assert d.shape == x.shape, f"prefix: decode of a {lv}-element prefix has shape {d.shape}"
            errs.append(float(np.mean((d - x) ** 2)))
        assert all(a >= b - 1e-7 for a, b in zip(errs, errs[1:])), \
            f"prefix: error must not grow with the prefix length; levels {levels} gave MSE {errs}"
        report["prefix_mse"] = dict(zip(levels, errs))
    elif k > 1:
        _raises(errors.ShapeError, lambda: codec.decode(codes[:, : k - 1]), "prefix: decoding a prefix of a "
                "codec that is not prefix-ordered")
