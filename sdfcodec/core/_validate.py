"""The one place that checks and converts arrays handed to sdfcodec (kornia-style shape checks).

Codecs take numpy arrays or torch tensors on any device; results follow the input: a numpy input gives a
numpy result, a tensor gives a tensor on the same device. Everything is computed in float32. Plugin authors
use these through :mod:`sdfcodec.plugin`.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ._lazy import lazy_module
from ..errors import DTypeError, InvalidValueError, ShapeError

torch = lazy_module("torch")  # imported on first use: info, codecs, verify of a header never need it

# most are public through sdfcodec.plugin (check_device is for the map readers, writers and the CLI)
__all__ = ["BLOCK", "as_float_tensor", "check_weights", "like_input", "empty", "affine_into", "check_device", "finite_sum"]

BLOCK = 16  # voxels per block edge, fixed by the map format and the codec contract (spec/)


def as_float_tensor(x: Any, name: str, shape: tuple[int | None, ...], *, check_finite: bool = True
                    ) -> tuple[torch.Tensor, bool]:
    """Check ``x`` against ``shape`` (``None`` = any size) and return ``(float32 tensor, was_numpy)``.

    Raises:
        ShapeError: wrong rank or size (the message gives the expected and actual shape).
        DTypeError: not a floating-point array.
        InvalidValueError: NaN or infinite values (only when ``check_finite``).
    """
    was_numpy = not isinstance(x, torch.Tensor)
    if was_numpy:
        if not isinstance(x, np.ndarray):
            try:
                x = np.asarray(x)
            except Exception as exc:  # ragged lists and the like
                raise DTypeError(f"{name} must be a numpy array or torch tensor, got {type(x).__name__}") from exc
        if x.dtype.kind != "f":
            raise DTypeError(f"{name} must be floating point (float16/32/64), got dtype {x.dtype}; "
                             "convert with .astype(np.float32)")
        t = torch.from_numpy(np.ascontiguousarray(x, dtype=np.float32))
    else:
        if not x.is_floating_point():
            raise DTypeError(f"{name} must be floating point, got {x.dtype}; convert with .float()")
        t = x.to(torch.float32)
    expected = "(" + ", ".join("N" if s is None else str(s) for s in shape) + ")"
    if t.ndim != len(shape) or any(s is not None and s != d for s, d in zip(shape, t.shape)):
        hint = " (a single block needs a batch axis: x[None])" if t.ndim == len(shape) - 1 else ""
        raise ShapeError(f"{name} must have shape {expected}, got {tuple(t.shape)}{hint}")
    # fast path: one reduction (NaN/Inf propagate into the sum); the exact element test runs only when the sum
    # is not finite, which also covers finite values whose sum overflows; meta tensors hold no values to check
    if check_finite and t.numel() and t.device.type != "meta" and not finite_sum(t) and not bool(torch.isfinite(t).all()):
        bad = int((~torch.isfinite(t)).sum())
        raise InvalidValueError(f"{name} holds {bad} NaN or infinite value(s); sdfcodec needs finite input "
                                "(replace unobserved voxels with the truncation distance d_max)")
    return t, was_numpy


def finite_sum(t: torch.Tensor) -> bool:
    """Whether the sum of ``t``'s values is finite. CPU tensors are summed by numpy: torch's threaded reduction
    right after a numpy (OpenBLAS) product waits for the BLAS threads still spinning on the same cores, which
    cost 26 ms for 4096 codes of 64 on 2 cores (a third of the decode it checked)."""
    if t.device.type == "cpu":
        return bool(np.isfinite(t.detach().numpy().sum()))
    return bool(torch.isfinite(t.sum()))


def check_weights(weights: Any, n: int, device: torch.device) -> torch.Tensor:
    """Per-voxel error weights ``(n, 16, 16, 16)`` as float32 on ``device``: floating point, bool (an
    observation mask) or integer (observation counts); finite and non-negative.

    Raises:
        ShapeError, DTypeError: not ``(n, 16, 16, 16)``, or not a number type.
        InvalidValueError: NaN, infinite or negative weights.
    """
    if isinstance(weights, np.ndarray) and weights.dtype.kind in "biu":
        weights = weights.astype(np.float32)
    elif isinstance(weights, torch.Tensor) and not weights.is_floating_point() and not weights.is_complex():
        weights = weights.to(torch.float32)
    w, _ = as_float_tensor(weights, "weights", (n, BLOCK, BLOCK, BLOCK))
    if w.numel() and bool(w.min() < 0):
        raise InvalidValueError(f"weights must be non-negative (0 = unobserved), got {int((w < 0).sum())} negative "
                                "value(s)")
    return w.to(device)


def like_input(t: torch.Tensor, was_numpy: bool) -> Any:
    """Return ``t`` as numpy when the input was numpy, else as the tensor itself."""
    return t.detach().cpu().numpy() if was_numpy else t


def empty(shape: tuple[int, ...], device: torch.device) -> torch.Tensor:
    """An uninitialised float32 tensor. On the CPU it is allocated by numpy, which asks the kernel for huge
    pages on large arrays: first-touch page faults of a fresh torch allocation halve decode throughput."""
    if device.type == "cpu":
        return torch.from_numpy(np.empty(shape, dtype=np.float32))
    return torch.empty(shape, dtype=torch.float32, device=device)


def output_buffer(out: Any, shapes: tuple[tuple[int, ...], ...], *, numpy: bool, device: torch.device,
                  what: str) -> torch.Tensor:
    """A caller's float32 output buffer ``out``, checked, as a tensor sharing its memory: a writeable C-contiguous
    numpy array (``numpy``) or a contiguous tensor on ``device``, of one of ``shapes``; ``what`` names the shape
    wanted in the error (e.g. "(4, 16, 16, 16) for 4 codes")."""
    if numpy != isinstance(out, np.ndarray) or not (numpy or isinstance(out, torch.Tensor)):
        want = "a numpy array (the codes are numpy)" if numpy else f"a torch tensor on {device}"
        raise DTypeError(f"out must be {want}, got {type(out).__name__}")
    if out.dtype not in (np.float32, torch.float32):
        raise DTypeError(f"out must be float32, got {out.dtype}: decoded blocks are float32")
    if tuple(out.shape) not in shapes:
        raise ShapeError(f"out must have shape {what}, got {tuple(out.shape)}")
    if numpy:
        if not out.flags.c_contiguous or not out.flags.writeable:
            raise InvalidValueError("out must be a writeable, C-contiguous numpy array (np.empty(...)), got "
                                    + ("a read-only array" if not out.flags.writeable else "a strided view"))
        return torch.from_numpy(out)
    if out.device.type != device.type or (device.index is not None and out.device.index != device.index):
        # "cuda" names whichever CUDA device is current: a tensor on cuda:0 is on it
        raise InvalidValueError(f"out must be on the device {device}, got {out.device}")
    if not out.is_contiguous():
        raise InvalidValueError("out must be a contiguous tensor (torch.empty(...)), got a strided view")
    return out.detach()


def affine_into(values: torch.Tensor, out: torch.Tensor, scale: float, offset: float) -> None:
    """Write ``scale * values + offset`` into ``out`` in one pass (a copy when ``scale == 1, offset == 0``);
    ``values`` has ``out``'s number of elements (it is viewed as ``out``'s shape) and its device, and does not
    overlap it. What a codec's ``decode_into`` does when its decode is a reshape of the codes (raw, sz3)."""
    src = values.reshape(out.shape)
    if scale == 1.0 and offset == 0.0:
        out.copy_(src)
    else:
        torch.add(torch.tensor(offset, dtype=out.dtype, device=out.device), src, alpha=scale, out=out)


def check_device(device: Any, what: str = "device") -> torch.device:
    """``device`` (``"cpu"``, ``"cuda"``, ``"cuda:1"``, a :class:`torch.device`) as a torch device that exists
    here, checked before any work starts (a map writer checks it before making its temporary directory).

    Raises:
        InvalidValueError: not a device name torch knows (``"foo"``), or a device this machine or this torch
            build does not have (``"cuda"`` on a CPU-only torch, ``"cuda:3"`` with one GPU), naming ``what``
            (e.g. ``--device``) and what to pass instead.
    """
    if isinstance(device, torch.device):
        dev = device
    else:
        try:
            dev = torch.device(device)
        except (RuntimeError, TypeError, ValueError):
            raise InvalidValueError(f"{what} {device!r} is not a torch device; use cpu, cuda or cuda:N") from None
    if dev.type == "cuda":
        if not torch.cuda.is_available():
            why = "this torch is a CPU-only build" if torch.version.cuda is None else "no CUDA GPU is visible"
            raise InvalidValueError(f"{what} {device!r}: {why}; use {what} cpu (or install a CUDA build of torch "
                                    "on a machine with a GPU)")
        if dev.index is not None and dev.index >= torch.cuda.device_count():
            raise InvalidValueError(f"{what} {device!r}: this machine has {torch.cuda.device_count()} CUDA "
                                    f"device(s), cuda:0 to cuda:{torch.cuda.device_count() - 1}")
    elif dev.type not in ("cpu", "meta"):
        try:  # any other backend (mps, xpu...): usable only if a tensor can be made there
            torch.empty(1, device=dev)
        except Exception as e:  # noqa: BLE001 - torch raises RuntimeError, AssertionError... per backend
            raise InvalidValueError(f"{what} {device!r} is not available here ({type(e).__name__}: "
                                    f"{' '.join(str(e).split())[:200]}); use {what} cpu") from None
    return dev
