"""Models shipped inside the package (plain-array .npz files; see :mod:`sdfcodec.model`).

``pca-128.npz``: the default eigenshapes, 128 principal components of normalised 16^3 blocks (voxel size
0.02 m, truncation [-0.04, 0.1] m), trained by ``make default-model`` (``examples/train_default_model.py``) on
synthetic blocks plus real sub-volumes fused from 7-Scenes redkitchen. Its prefixes serve pca-32 and pca-64.
"""

from __future__ import annotations

from functools import lru_cache
from importlib import resources

from ..codec import Codec
from ..errors import InvalidValueError
from ..model import load_model

__all__ = ["default_codec", "DEFAULT_PCA"]

DEFAULT_PCA = "pca-128.npz"


@lru_cache(maxsize=1)
def _default_pca() -> Codec:
    with resources.as_file(resources.files(__name__) / DEFAULT_PCA) as path:
        return load_model(path)


def default_codec(codec_id: str = "pca", code_size: int = 64) -> Codec:
    """The shipped trained codec ``codec_id`` at ``code_size`` (pca: 1..128, a prefix of the shipped basis)."""
    if codec_id != "pca":
        raise InvalidValueError(f"no shipped model for codec {codec_id!r}; train one with `sdfcodec train` and "
                                "pass it with --model")
    base = _default_pca()
    if not 1 <= code_size <= base.code_size:
        raise InvalidValueError(f"the shipped PCA model has {base.code_size} components; code_size must be in "
                                f"1..{base.code_size}, got {code_size} (train a larger one with `sdfcodec train`)")
    return base.prefix(code_size)
