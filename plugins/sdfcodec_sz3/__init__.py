"""The ``sz3`` codec: SZ3 (through pysz), an error-bounded field compressor, inside the registry.

Its codes are the block's voxels, each within ``max_error`` (absolute, normalised units: 1 = d_max - d_min) of
the input. On its own (``encode``) it compresses each block as a separate SZ3 stream and returns what SZ3
decodes from it, so a block's code never depends on the batch. In a map it does better: the map stores the
exact voxels and compresses its ``codes`` array with SZ3 at the same bound, a chunk's 8^3 blocks as one
128^3-voxel field, so the predictor sees neighbours across block faces (the hook ``field_compression``; map
extension ``field-compression``, spec/map-format.md section 4c). Readers decode such a map like a lossless
one: ``decode`` is a reshape. Needs ``pip install 'sdfcodec[sz3]'`` (pysz==1.1.0).

    sdfcodec encode kitchen.sdfz kitchen-sz3.sdfz --codec sz3 --max-error 0.01   # metres
"""

from __future__ import annotations

import numpy as np

from sdfcodec import Codec
from sdfcodec.plugin import affine_into, lazy_module, sz3_compress, sz3_decompress

torch = lazy_module("torch")  # imported on first use: listing codecs and reading headers never need it

__all__ = ["SZ3Codec"]


class SZ3Codec(Codec):
    """SZ3 with an absolute error bound: ``encode`` ``(N, 16, 16, 16)`` -> ``(N, 4096)`` voxels within
    ``max_error`` of the input (float32, on the input's device; computed on the CPU); ``decode`` reshapes.

    Args:
        max_error: absolute error bound in normalised units (0.05 = 7 mm at the paper's truncation of
            (-0.04, 0.1) m), at least 1e-6.
    """

    codec_id = "sz3"
    prefix_ordered = False
    requires_fit = False
    code_sizes = (4096,)
    capabilities = frozenset({"decode_into"})  # spec/codec-plugins.md, section 4a
    code_size = 4096

    def __init__(self, max_error: float = 0.05):
        self.max_error = max_error

    def field_compression(self) -> dict:
        return {"name": "sz3", "max_error": float(self.max_error)}

    def _encode(self, blocks: torch.Tensor) -> torch.Tensor:
        n = len(blocks)
        if blocks.device.type == "meta":
            return torch.empty((n, 4096), device="meta")
        x = blocks.detach().to("cpu", torch.float32).numpy().reshape(n, 16, 16, 16)
        out = np.empty((n, 4096), np.float32)
        for i in range(n):  # one stream per block: codes independent of the batch (spec/codec-plugins.md 2)
            out[i] = sz3_decompress(sz3_compress(x[i], float(self.max_error)), (16, 16, 16)).ravel()
        return torch.from_numpy(out).to(blocks.device)

    def _decode(self, codes: torch.Tensor) -> torch.Tensor:
        return codes.reshape(len(codes), 16, 16, 16).clone()

    def decode_into(self, codes: torch.Tensor, out: torch.Tensor, scale: float, offset: float) -> None:
        # the code is the block's voxels: one fused pass straight into the caller's buffer
        affine_into(codes, out, scale, offset)

    def decode_bound(self, codes: torch.Tensor) -> float | None:
        return float(codes.abs().max()) if codes.numel() and codes.device.type != "meta" else 0.0
