"""Loading a map's codec: the plugin named by the header, built from its configuration, with the learned state
stored under ``codec/`` checked against the header's digest (spec sections 5 and 9a). Nothing here runs code
from the map: the id resolves only to an installed entry point, and the state is plain arrays."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from ..codec import Codec
from ..errors import ChecksumError, FormatError
from ..registry import get_codec_class
from .format import state_digest

if TYPE_CHECKING:
    from .reader import MapReader

__all__ = ["load_codec"]


def load_codec(reader: MapReader) -> Codec:
    """The codec that wrote the map ``reader`` reads, fitted with the map's stored state.

    Raises:
        UnknownCodecError: the plugin is not installed. FormatError: a configuration the plugin rejects, missing
        or oversized state arrays, state that does not fit the codec, or codes the codec cannot have made.
        ChecksumError: the state does not match ``codec.state_sha256``.
    """
    h, where = reader.header, reader.location
    spec = h.codec
    cls = get_codec_class(spec.id, package_hint=spec.package)
    try:
        codec = cls.from_config(spec.config)
    except Exception as e:  # a hostile or stale config: the plugin's own error, whatever its type
        raise FormatError(f"{where}: header field codec.config is not a valid {spec.id!r} configuration "
                          f"({type(e).__name__}: {e})") from e
    state = {}
    if spec.state_arrays:
        total = 0
        for name in spec.state_arrays:
            arr = reader.member(f"codec/{name}")
            if arr is None:
                raise FormatError(f"{where}: codec state array 'codec/{name}' (listed in codec.state_arrays) "
                                  "is missing")
            reader.check_array(arr)
            total += math.prod(arr.shape) * np.dtype(arr.dtype).itemsize
            if total > reader.max_decode_bytes:
                raise FormatError(f"{where}: the codec state is over {reader.max_decode_bytes} bytes, the reader's "
                                  "limit (raise max_decode_bytes in open_map() if the map is genuine)")
            state[name] = reader.read(arr, (slice(None),) * arr.ndim)
    if spec.state_sha256 is not None and state_digest(state) != spec.state_sha256:
        raise ChecksumError(f"{where}: the codec state under codec/ does not match the digest "
                            "in the header; the map's codec arrays were altered or corrupted")
    try:
        if state:
            codec = codec.load_state_dict(state)
        fitted = codec.is_fitted
    except Exception as e:
        raise FormatError(f"{where}: the codec state under codec/ does not fit codec {spec.id!r} "
                          f"({type(e).__name__}: {e})") from e
    if not fitted:
        raise FormatError(f"{where}: codec {spec.id!r} needs learned state, which the map does not store")
    if codec.code_size != h.codes.size:
        raise FormatError(f"{where}: header field codes.size is {h.codes.size}, but the codec makes codes of "
                          f"{codec.code_size} elements")
    if h.codes.prefix_ordered and not codec.prefix_ordered:
        raise FormatError(f"{where}: header field codes.prefix_ordered is true, but codec {spec.id!r} codes "
                          "are not prefix-ordered")
    return codec
