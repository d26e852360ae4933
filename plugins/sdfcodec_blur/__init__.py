"""The ``gaussian-blur`` codec: the paper's baseline, a 3-D Gaussian filter applied to the original field.

It compresses nothing (the code is the block, like ``raw``); what it changes is the decoded field, smoothed by
a ``size^3`` kernel (default 9^3, sigma 4/3, the paper's setting). The filter needs ``size // 2`` voxels of
neighbour context, declared as the codec's ``halo``: map readers decode the neighbouring blocks and filter
the assembled neighbourhood, so there are no block seams. A block decoded alone (``codec.decode``) is
filtered with its own faces repeated as context.
"""

from __future__ import annotations

import math

from sdfcodec import Codec
from sdfcodec.errors import InvalidValueError
from sdfcodec.plugin import affine_into, lazy_module

torch = lazy_module("torch")  # imported on first use: listing codecs and reading headers never need it

__all__ = ["GaussianBlurCodec"]


class GaussianBlurCodec(Codec):
    """Gaussian blur of the original field.

    Args:
        size: kernel edge in voxels (odd, >= 1).
        sigma: standard deviation in voxels.
    """

    codec_id = "gaussian-blur"
    prefix_ordered = False
    requires_fit = False
    code_sizes = (4096,)
    capabilities = frozenset({"decode_into"})  # spec/codec-plugins.md, section 4a
    code_size = 4096

    def __init__(self, size: int = 9, sigma: float = 4.0 / 3.0):
        self.size = size
        self.sigma = sigma

    @property
    def halo(self) -> int:  # type: ignore[override]
        return self._checked_size() // 2

    def _checked_size(self) -> int:
        if not isinstance(self.size, int) or self.size < 1 or self.size % 2 == 0:
            raise InvalidValueError(f"gaussian-blur size must be an odd int >= 1, got {self.size!r}")
        if not (isinstance(self.sigma, (int, float)) and self.sigma > 0 and math.isfinite(self.sigma)):
            raise InvalidValueError(f"gaussian-blur sigma must be a positive number of voxels, got {self.sigma!r}")
        return self.size

    def _kernel(self, device: torch.device) -> torch.Tensor:
        h = self.halo
        x = torch.arange(-h, h + 1, dtype=torch.float64)
        k = torch.exp(-0.5 * (x / self.sigma) ** 2)
        return (k / k.sum()).to(device=device, dtype=torch.float32)

    def _encode(self, blocks: torch.Tensor) -> torch.Tensor:
        return blocks.reshape(len(blocks), 4096).clone()

    def _decode(self, codes: torch.Tensor) -> torch.Tensor:
        return codes.reshape(len(codes), 16, 16, 16).clone()

    def decode_into(self, codes: torch.Tensor, out: torch.Tensor, scale: float, offset: float) -> None:
        # the code is the block's voxels: one fused pass straight into the caller's buffer
        affine_into(codes, out, scale, offset)

    def _decode_context(self, padded: torch.Tensor) -> torch.Tensor:
        # separable filter: three 1-D 'valid' convolutions, one per axis (9 + 9 + 9 taps instead of 729)
        k = self._kernel(padded.device)
        n = len(k)
        v = padded[:, None]
        v = torch.nn.functional.conv3d(v, k.view(1, 1, n, 1, 1))
        v = torch.nn.functional.conv3d(v, k.view(1, 1, 1, n, 1))
        v = torch.nn.functional.conv3d(v, k.view(1, 1, 1, 1, n))
        return v[:, 0]
