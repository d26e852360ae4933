"""Comparisons shared by the conformance checks; each raises ``AssertionError`` saying what differed."""

from __future__ import annotations

from typing import Any, Callable

import numpy as np

__all__ = ["assert_close", "assert_raises"]


def assert_close(a: Any, b: Any, atol: float, what: str) -> None:
    """``a`` equals ``b`` to ``atol`` times the magnitude of ``b`` (at least 1): float32 sums of 4096 terms
    in another order (batch of 1 vs many, another BLAS kernel) differ in the last bits of large codes.
    Torch tensors are compared on the CPU."""
    a, b = (np.asarray(v.detach().cpu() if hasattr(v, "detach") else v, np.float64) for v in (a, b))
    assert a.shape == b.shape, f"{what}: shape {a.shape} != {b.shape}"
    if not a.size:
        return
    err, tol = float(np.max(np.abs(a - b))), atol * max(1.0, float(np.max(np.abs(b))))
    assert err <= tol, f"{what}: max abs difference {err:.3g} > {tol:.3g}"


def assert_raises(exc: type[BaseException], fn: Callable[[], Any], what: str) -> None:
    """``fn()`` raises ``exc`` (an :mod:`sdfcodec.errors` type) with a message."""
    try:
        fn()
    except exc as e:
        assert str(e), f"{what}: {exc.__name__} was raised without a message"
        return
    except Exception as e:  # noqa: BLE001 - we report the wrong type
        raise AssertionError(f"{what}: expected sdfcodec.errors.{exc.__name__}, got {type(e).__name__}: {e}") from e
    raise AssertionError(f"{what}: expected sdfcodec.errors.{exc.__name__}, nothing was raised")
