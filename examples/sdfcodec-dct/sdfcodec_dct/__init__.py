"""``dct``: keep the lowest-frequency 3-D DCT coefficients of a block (an example third-party plugin).

The orthonormal 3-D DCT-II of a 16^3 block has 4096 coefficients. The codec keeps the ``code_size`` with the
lowest total frequency ``i + j + k`` (ties in C order), so codes are prefix-ordered: a prefix keeps fewer,
coarser frequencies. Those coefficients are an orthonormal basis of 4096-vectors, so encode and decode are
one matrix product each, on the input's device. It needs no training.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from sdfcodec import Codec
from sdfcodec.errors import InvalidValueError

__all__ = ["DCTCodec", "dct_basis"]


def dct_basis(n: int = 16) -> np.ndarray:
    """The orthonormal DCT-II matrix ``(n, n)``: row ``f`` is frequency ``f`` sampled at the ``n`` voxels."""
    x = np.arange(n)
    c = np.cos(np.pi * (x[None, :] + 0.5) * x[:, None] / n) * math.sqrt(2.0 / n)
    c[0] /= math.sqrt(2.0)
    return c


class DCTCodec(Codec):
    """3-D DCT truncation codec. Args: code_size: number of coefficients kept (1..4096)."""

    codec_id = "dct"
    prefix_ordered = True
    requires_fit = False
    code_sizes = (32, 64, 128)
    # the optional fast paths this codec provides (spec/codec-plugins.md, section 4a): its decode is one matrix
    # product, which can write the caller's buffer itself
    capabilities = frozenset({"decode_into"})

    def __init__(self, code_size: int = 64):
        self.code_size = code_size

    def _basis(self, device: torch.device) -> torch.Tensor:
        cache = self.__dict__.setdefault("_cache", {})
        if device not in cache:
            if not isinstance(self.code_size, int) or not 1 <= self.code_size <= 4096:
                raise InvalidValueError(f"dct code_size must be an int in 1..4096, got {self.code_size!r}")
            c = dct_basis(16)
            f = np.stack(np.meshgrid(*[np.arange(16)] * 3, indexing="ij"), -1).reshape(-1, 3)
            order = np.lexsort((np.arange(4096), f.sum(axis=1)))[: self.code_size]  # low total frequency first
            i, j, k = f[order].T
            basis = np.einsum("ax,ay,az->axyz", c[i], c[j], c[k]).reshape(self.code_size, 4096)
            cache[device] = torch.from_numpy(basis.astype(np.float32)).to(device)
        return cache[device]

    def _encode(self, blocks: torch.Tensor) -> torch.Tensor:
        return blocks.reshape(len(blocks), 4096) @ self._basis(blocks.device).T

    def _decode(self, codes: torch.Tensor) -> torch.Tensor:
        b = self._basis(codes.device)[: codes.shape[1]]
        return (codes @ b).reshape(len(codes), 16, 16, 16)

    def decode_into(self, codes: torch.Tensor, out: torch.Tensor, scale: float, offset: float) -> None:
        # scale * (codes @ basis) + offset as one product written straight into the caller's buffer
        b = self._basis(codes.device)[: codes.shape[1]]
        base = torch.tensor(offset, dtype=out.dtype, device=out.device)
        torch.addmm(base, codes, b, beta=1.0, alpha=scale, out=out.view(len(codes), 4096))
