"""Deprecated: shipped models now live in their plugins' own packages (``sdfcodec_pca/models/pca-128.npz``,
``sdfcodec_ae/models/ae-64.npz``, ``sdfcodec_mixed/models/sequential-64-64.npz``) and are served by each
codec's :meth:`sdfcodec.Codec.pretrained`. Use ``sdfcodec.pretrained_codec(codec_id, code_size)`` instead of
:func:`default_codec`; this module keeps the old names working, with a ``DeprecationWarning``.
"""

from __future__ import annotations

import warnings

from ..codec import Codec
from ..registry import pretrained_codec

__all__ = ["default_codec", "DEFAULT_PCA"]

DEFAULT_PCA = "pca-128.npz"  # the file name, now in the pca plugin's models/


def default_codec(codec_id: str = "pca", code_size: int = 64) -> Codec:
    """Deprecated: ``sdfcodec.pretrained_codec(codec_id, code_size)`` (the shipped trained ``codec_id`` at
    ``code_size``; pca: 1..128, a prefix of the shipped basis)."""
    warnings.warn("sdfcodec.models.default_codec is deprecated: use sdfcodec.pretrained_codec(codec_id, code_size)",
                  DeprecationWarning, stacklevel=2)
    return pretrained_codec(codec_id, code_size)
