"""The trainable autoencoder module: its own module because defining a ``torch.nn.Module`` subclass imports
torch, which listing codecs and reading map headers never need (:func:`sdfcodec_ae.network.build_module`
imports it on first use)."""

from __future__ import annotations

import torch

from .network import N_VOXELS, layer_shapes

__all__ = ["AENet"]


class AENet(torch.nn.Module):
    """The trainable module (float32). ``forward(x (B, 4096)) -> (B, 4096)``.

    While training, the input is standardised, ``(x - in_shift) * in_scale`` (buffers; the identity unless
    set): centred inputs condition the first layer far better than raw blocks, which are mostly 1.0. The
    standardisation is affine, so :func:`export_state` folds it into ``enc1`` exactly and the stored network
    is the plain ``4096 - h - d - h - 4096`` one.
    """

    def __init__(self, code_size: int, hidden: int, output: str):
        super().__init__()
        for name, (o, i) in layer_shapes(code_size, hidden).items():
            setattr(self, name, torch.nn.Linear(i, o))
        self.out_act = torch.tanh if output == "tanh" else torch.sigmoid
        self.register_buffer("in_shift", torch.zeros(N_VOXELS))
        self.register_buffer("in_scale", torch.ones(()))

    def encode(self, x: torch.Tensor) -> torch.Tensor:
        return torch.sigmoid(self.enc2(torch.sigmoid(self.enc1((x - self.in_shift) * self.in_scale))))

    def decode(self, z: torch.Tensor) -> torch.Tensor:
        return self.out_act(self.dec2(torch.sigmoid(self.dec1(z))))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.decode(self.encode(x))
