"""The autoencoder network: layer names, plain-array state, and the inference path.

The paper's network (section IV-C) is ``4096 - h - d - h - 4096`` with sigmoid units (``h = 512``,
``d`` the code size). Every layer is affine, ``y = act(x W^T + b)``, with ``W`` stored in torch's
``nn.Linear`` layout ``(out, in)``:

=============  ================  ===================  ==================================
name           weight shape      activation           role
=============  ================  ===================  ==================================
``enc1``       ``(h, 4096)``     sigmoid              encoder hidden layer
``enc2``       ``(d, h)``        sigmoid              code layer: codes lie in ``(0, 1)``
``dec1``       ``(h, d)``        sigmoid              decoder hidden layer
``dec2``       ``(4096, h)``     sigmoid or tanh      output (tanh: residuals of the sequential codec)
=============  ================  ===================  ==================================

State arrays are ``<name>.weight`` and ``<name>.bias`` (float32 in memory; float16 on disk is accepted and
widened). Inference does one ``torch.addmm`` per layer with weights transposed once and cached per device,
so a batch of ``B`` blocks costs the four matrix products ``(B,4096)(4096,h)``, ``(B,h)(h,d)``,
``(B,d)(d,h)``, ``(B,h)(h,4096)`` plus the activations.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Mapping

import numpy as np

from sdfcodec.errors import InvalidValueError, ShapeError
from sdfcodec.plugin import lazy_module

if TYPE_CHECKING:
    from ._net import AENet

torch = lazy_module("torch")  # imported on first use: listing codecs and reading headers never need it

__all__ = ["LAYERS", "N_VOXELS", "layer_shapes", "check_state", "build_module", "module_state", "export_state",
           "Inference"]

N_VOXELS = 16 ** 3
LAYERS = ("enc1", "enc2", "dec1", "dec2")
OUTPUTS = ("sigmoid", "tanh")


def layer_shapes(code_size: int, hidden: int) -> dict[str, tuple[int, int]]:
    """``{layer: (out, in)}`` weight shapes of the ``4096 - hidden - code_size - hidden - 4096`` network."""
    return {"enc1": (hidden, N_VOXELS), "enc2": (code_size, hidden),
            "dec1": (hidden, code_size), "dec2": (N_VOXELS, hidden)}


def check_state(state: Mapping[str, np.ndarray], code_size: int, hidden: int, what: str = "ae"
                ) -> dict[str, np.ndarray]:
    """Validate and widen a state dict to contiguous float32 arrays.

    Raises
    ------
    InvalidValueError
        Missing arrays or NaN/Inf values.
    ShapeError
        An array whose shape does not fit ``code_size`` / ``hidden``.
    """
    shapes = layer_shapes(code_size, hidden)
    need = [f"{n}.{p}" for n in LAYERS for p in ("weight", "bias")]
    missing = [k for k in need if k not in state]
    if missing:
        raise InvalidValueError(f"{what} state lacks array(s) {missing}; it needs {need}")
    extra = sorted(set(state) - set(need))
    if extra:
        raise InvalidValueError(f"{what} state has unexpected array(s) {extra}; it holds exactly {need}")
    out = {}
    for name, (o, i) in shapes.items():
        w = np.ascontiguousarray(state[f"{name}.weight"], dtype=np.float32)
        b = np.ascontiguousarray(state[f"{name}.bias"], dtype=np.float32)
        if w.shape != (o, i) or b.shape != (o,):
            raise ShapeError(f"{what} (code_size={code_size}, hidden={hidden}) needs {name}.weight {(o, i)} and "
                             f"{name}.bias ({o},), got {w.shape} and {b.shape}; was the model trained with another "
                             "code_size or hidden width?")
        if not (np.isfinite(w).all() and np.isfinite(b).all()):
            raise InvalidValueError(f"{what} state array {name} holds NaN or infinite values")
        out[f"{name}.weight"], out[f"{name}.bias"] = w, b
    return out


def build_module(code_size: int, hidden: int, output: str, state: Mapping[str, np.ndarray] | None = None
                 ) -> AENet:
    """A trainable :class:`torch.nn.Module` (on CPU, float32), loaded from ``state`` when given."""
    if output not in OUTPUTS:
        raise InvalidValueError(f"ae output must be one of {OUTPUTS}, got {output!r}")
    from ._net import AENet  # defines a torch.nn.Module subclass: importing it imports torch

    net = AENet(code_size, hidden, output)
    if state is not None:
        arrays = check_state(state, code_size, hidden)
        net.load_state_dict({k: torch.from_numpy(v.copy()) for k, v in arrays.items()}, strict=False)
    return net


def module_state(net: torch.nn.Module) -> dict[str, np.ndarray]:
    """The module's parameters and buffers as contiguous float32 numpy arrays (CPU copies): the training
    representation (checkpoints); :func:`export_state` turns it into codec state."""
    # np.array (not ascontiguousarray, which turns 0-d arrays into 1-d ones) keeps the scalar buffer 0-d
    return {k: np.array(v.detach().cpu().numpy(), dtype=np.float32, order="C", copy=True)
            for k, v in net.state_dict().items()}


def export_state(raw: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Fold the input standardisation of a :func:`module_state` into ``enc1`` (in float64):
    ``W ((x - s) c) + b = (c W) x + (b - c W s)``. Returns the 8 codec state arrays, float32."""
    out = {k: np.ascontiguousarray(v, dtype=np.float32) for k, v in raw.items() if k.split(".")[0] in LAYERS}
    shift = np.asarray(raw.get("in_shift", np.zeros(N_VOXELS)), np.float64)
    scale = float(np.asarray(raw.get("in_scale", 1.0)))
    w = out["enc1.weight"].astype(np.float64) * scale
    out["enc1.bias"] = np.ascontiguousarray(out["enc1.bias"].astype(np.float64) - w @ shift, dtype=np.float32)
    out["enc1.weight"] = np.ascontiguousarray(w, dtype=np.float32)
    return out


class Inference:
    """Frozen encode/decode from plain arrays, one ``addmm`` per layer, weights cached per device.

    Parameters
    ----------
    state : mapping of str to np.ndarray
        Arrays validated by :func:`check_state` (float32, contiguous).
    output : {"sigmoid", "tanh"}
        Activation of the output layer.
    """

    def __init__(self, state: Mapping[str, np.ndarray], output: str):
        if output not in OUTPUTS:
            raise InvalidValueError(f"ae output must be one of {OUTPUTS}, got {output!r}")
        # transposed once: x (B, in) @ W^T (in, out) is the layout addmm wants
        self._host = {n: (np.ascontiguousarray(state[f"{n}.weight"].T), state[f"{n}.bias"]) for n in LAYERS}
        self._tanh = output == "tanh"  # a flag, not torch.tanh: loading a model (a map's info) never imports torch
        self._cache: dict[torch.device, dict[str, tuple[torch.Tensor, torch.Tensor]]] = {}

    def _on(self, device: torch.device) -> dict[str, tuple[torch.Tensor, torch.Tensor]]:
        mats = self._cache.get(device)
        if mats is None:
            mats = {n: (torch.from_numpy(w).to(device), torch.from_numpy(b).to(device))
                    for n, (w, b) in self._host.items()}
            self._cache[device] = mats
        return mats

    def encode(self, x: torch.Tensor) -> torch.Tensor:
        """``(B, 4096)`` float32 -> codes ``(B, d)`` float32 in ``(0, 1)``, on ``x.device``."""
        m = self._on(x.device)
        h = torch.sigmoid_(torch.addmm(m["enc1"][1], x, m["enc1"][0]))
        return torch.sigmoid_(torch.addmm(m["enc2"][1], h, m["enc2"][0]))

    def decode(self, z: torch.Tensor) -> torch.Tensor:
        """Codes ``(B, d)`` float32 -> ``(B, 4096)`` float32 on ``z.device``."""
        m = self._on(z.device)
        h = torch.sigmoid_(torch.addmm(m["dec1"][1], z, m["dec1"][0]))
        y = torch.addmm(m["dec2"][1], h, m["dec2"][0])
        return torch.tanh_(y) if self._tanh else torch.sigmoid_(y)
