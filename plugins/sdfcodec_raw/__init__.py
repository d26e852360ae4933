"""The ``raw`` codec: the code of a block is the block itself (4096 values), lossless up to float32
rounding of the metres <-> [0, 1] normalisation (about 1e-8 m).

Fused maps are stored with it so they can be transcoded later (``sdfcodec encode MAP OUT --codec pca``);
with float16 code storage it halves the bytes at about 1e-3 normalised error (float16's resolution near 1).
"""

from __future__ import annotations

from sdfcodec import Codec
from sdfcodec.plugin import affine_into, lazy_module

torch = lazy_module("torch")  # imported on first use: listing codecs and reading headers never need it

__all__ = ["RawCodec"]


class RawCodec(Codec):
    """Identity codec: ``encode`` flattens ``(N, 16, 16, 16)`` to ``(N, 4096)``; ``decode`` reshapes back."""

    codec_id = "raw"
    prefix_ordered = False
    requires_fit = False
    code_sizes = (4096,)
    code_size = 4096
    # spec/codec-plugins.md, section 4a. encode_weighted without overriding it: lossless, every weighting has the
    # same best code (the block itself), so map writers store the voxels as they are rather than filling
    # unobserved space as they do for a lossy codec that ignores weights
    capabilities = frozenset({"decode_into", "encode_weighted"})

    def _encode(self, blocks: torch.Tensor) -> torch.Tensor:
        return blocks.reshape(len(blocks), 4096).clone()

    def _decode(self, codes: torch.Tensor) -> torch.Tensor:
        return codes.reshape(len(codes), 16, 16, 16).clone()

    def decode_into(self, codes: torch.Tensor, out: torch.Tensor, scale: float, offset: float) -> None:
        # the code is the block: one fused pass (scale * codes + offset) straight into the caller's buffer
        affine_into(codes, out, scale, offset)
