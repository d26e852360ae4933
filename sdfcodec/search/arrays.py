"""A codec's encode and decode on numpy arrays for searches: through the codec's torch-free
:meth:`~sdfcodec.Codec.numpy_path` when it has one (pca), else through :meth:`~sdfcodec.Codec.encode` /
:meth:`~sdfcodec.Codec.decode` (which import torch). A search holds numpy arrays only, so on a pca map it
never imports torch: that import alone is 1.7 s of a 3 s first search on two cores."""

from __future__ import annotations

import numpy as np

from ..codec import Codec, numpy_path_of
from ..errors import PluginError

__all__ = ["encode_array", "decode_array"]


def encode_array(codec: Codec, blocks: np.ndarray) -> np.ndarray:
    """Codes ``(N, code_size)`` float32 of finite normalised blocks ``(N, 16, 16, 16)`` (made by the search, not
    read from a map)."""
    path = numpy_path_of(codec)
    if path is None:
        return np.asarray(codec.encode(np.ascontiguousarray(blocks, dtype=np.float32)), dtype=np.float32)
    x = np.ascontiguousarray(blocks, dtype=np.float32).reshape(len(blocks), -1)
    return np.asarray(path.encode(x), dtype=np.float32)


def decode_array(codec: Codec, codes: np.ndarray) -> np.ndarray:
    """Normalised blocks ``(N, 4096)`` float32 of codes ``(N, k)`` (``k < code_size`` only for prefix-ordered
    codecs).

    Raises
    ------
    PluginError
        The decode holds NaN or infinite values (a corrupted state, as :meth:`~sdfcodec.Codec.decode` says)."""
    c = np.ascontiguousarray(codes, dtype=np.float32)
    path = numpy_path_of(codec)
    if path is None:
        import torch  # the codec has no numpy path: its own decode, without autograd

        with torch.no_grad():
            return np.asarray(codec.decode(c), dtype=np.float32).reshape(len(c), -1)
    out = np.asarray(path.decode(c), dtype=np.float32)
    if len(out) and not np.isfinite(out).all():  # what Codec.decode refuses on every path
        raise PluginError(f"{codec.codec_id} decoded NaN/Inf values for some of {len(c)} codes: the codes or the "
                          "codec's learned state are corrupted")
    return out
