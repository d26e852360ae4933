"""Loading a map's codec: the plugin named by the header, built from its configuration, with the learned state
stored under ``codec/`` checked against the header's digest (spec sections 5 and 9a), or, for a state stored by
reference (section 6c), the state of a model the installed plugin ships, found by name and checked by the same
digest. Nothing here runs code from the map: the id resolves only to an installed entry point, a model name only
to a model that plugin lists, and the state is plain arrays."""

from __future__ import annotations

import hashlib
import json
import math
from typing import TYPE_CHECKING

import numpy as np

from ..codec import Codec
from ..errors import (ChecksumError, FormatError, InvalidValueError, ModelNotFoundError, SDFCodecError,
                      StateReferenceError)
from ..core.header import StateReference
from ..core.tiling import one_blas_thread
from ..registry import describe_shipped, get_codec_class, list_codecs

if TYPE_CHECKING:
    from .reader import MapReader

__all__ = ["load_codec", "shipped_reference", "shipped_model_of", "resolve_reference", "state_digest"]

#: (codec class, model, code size) -> (digest, state): a shipped model's state is cut and hashed once per process
#: (ae-64: 0.16 s to load, 0.03 s to hash on 2 cores), however many maps name it.
_RESOLVED: dict[tuple[type, str, int], tuple[str, dict[str, np.ndarray]]] = {}
#: (codec class, code size, digest) of shipped states a codec has validated in this process: the installed
#: plugin's own arrays, matched by digest, need the check once, not at every open (pca-128's C C^T was a quarter
#: of a small map's read: 46-83 ms at load 6-8).
_VALIDATED: set[tuple[type, int, str]] = set()


def state_digest(state: dict[str, np.ndarray]) -> str:
    """SHA-256 of a codec state: for each array by sorted name, ``name NUL dtype NUL shape-json NUL`` then
    its little-endian C-order bytes (spec/map-format.md, "Codec state")."""
    h = hashlib.sha256()
    for name in sorted(state):
        a = np.ascontiguousarray(state[name])
        a = a.astype(a.dtype.newbyteorder("<"), copy=False)
        h.update(f"{name}\0{a.dtype.str}\0{json.dumps(list(a.shape))}\0".encode())
        h.update(a.tobytes())
    return h.hexdigest()


def _shipped(cls: type[Codec], model: str, code_size: int) -> tuple[str, dict[str, np.ndarray]]:
    key = (cls, model, code_size)
    if key not in _RESOLVED:
        state = cls.shipped_state(model, code_size)
        _RESOLVED[key] = (state_digest(state), state)
    return _RESOLVED[key]


def _find_shipped(cls: type[Codec], code_size: int, digest: str) -> str | None:
    for name, sizes in sorted((cls.shipped_models() or {}).items()):
        if code_size in sizes:
            try:
                if _shipped(cls, name, code_size)[0] == digest:
                    return name
            except ModelNotFoundError:
                continue
    return None


def shipped_model_of(codec_id: str, code_size: int, digest: str | None) -> str | None:
    """The name of the model the installed plugin of ``codec_id`` ships whose state at ``code_size`` has
    ``digest``; None when there is none, or the plugin is not installed or cannot be loaded."""
    if digest is None:
        return None
    try:
        return _find_shipped(get_codec_class(codec_id), code_size, digest)
    except SDFCodecError:
        return None


def shipped_reference(codec: Codec) -> StateReference:
    """The reference to the shipped model whose state ``codec`` holds (what a map stores instead of the state).

    Raises:
        InvalidValueError: no model the codec's plugin ships gives exactly this state at this code size (a
            fitted or trained codec: store its state in the map).
    """
    cls, size = type(codec), codec.code_size
    digest = state_digest(codec.state_dict())
    name = _find_shipped(cls, size, digest)
    if name is not None:
        return StateReference(model=name, sha256=digest)
    raise InvalidValueError(f"codec {codec.codec_id!r} (code size {size}) does not hold the state of a model its "
                            f"plugin ships (shipped: {describe_shipped(cls)}), so its state cannot be stored by "
                            "reference: store it in the map (codec_state='embedded', CLI --codec-state embedded)")


def resolve_reference(cls: type[Codec], ref: StateReference, code_size: int, where: str,
                      wrote: str | None = None) -> dict[str, np.ndarray]:
    """The state a map's ``ref`` names: the model ``ref.model`` that ``cls``'s installed plugin ships, cut to
    ``code_size``, whose digest MUST equal ``ref.sha256``; failing that, any model of that plugin with that digest
    (content-addressed: a model renamed by a later plugin version still resolves). Never a path from the header.
    ``wrote``: the distribution and version that wrote the map (``"sdfcodec==0.1.0"``, from the header), named as
    what to install.

    Raises:
        StateReferenceError: no shipped model gives that state (names the model, the digest and what to do).
    """
    found = failed = None
    try:
        models = cls.shipped_models() or {}
    except Exception as e:  # noqa: BLE001 - a broken plugin listing is reported, not raised as its own type
        models, failed = {}, f"{type(e).__name__}: {e}"
    for name in [ref.model] + sorted(n for n in models if n != ref.model):
        if code_size not in models.get(name, ()):
            continue
        try:
            digest, state = _shipped(cls, name, code_size)
        except ModelNotFoundError:
            continue
        except Exception as e:  # noqa: BLE001
            failed = f"{type(e).__name__}: {e}"
            continue
        if name == ref.model:
            found = digest
        if digest == ref.sha256:
            return state
    entry = next((e for e in list_codecs() if e.id == cls.codec_id), None)
    plugin = f"{entry.package} {entry.version}" if entry is not None and entry.package else cls.__module__
    if found is not None:
        why = f"the installed plugin ({plugin}) ships it with another state (sha256 {found})"
    else:
        why = (f"the installed plugin ({plugin}) does not ship it at code size {code_size} (it ships: "
               f"{describe_shipped(cls)}{f'; listing its models failed: {failed}' if failed else ''})")
    raise StateReferenceError(
        f"{where}: the codec state is stored by reference to model {ref.model!r} of codec {cls.codec_id!r} with "
        f"sha256 {ref.sha256}, and {why}. What to do: install "
        f"{f'{wrote} (the plugin version that wrote the map)' if wrote else 'the version of the plugin that ships that model'}, "
        f"or, on a machine that has it, re-store the map with its state embedded, codes copied unchanged "
        f"(sdfcodec encode {where} OUT --codec {cls.codec_id} --code-size {code_size} --codec-state embedded)")


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
    if spec.state_reference is not None:
        wrote = f"{spec.package}=={spec.package_version}" if spec.package and spec.package_version else None
        state = resolve_reference(cls, spec.state_reference, h.codes.size, where, wrote)
    elif spec.state_arrays:
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
    # a referenced state was matched against the digest when resolved (state_sha256 equals it)
    if spec.state_reference is None and spec.state_sha256 is not None and state_digest(state) != spec.state_sha256:
        raise ChecksumError(f"{where}: the codec state under codec/ does not match the digest "
                            "in the header; the map's codec arrays were altered or corrupted")
    try:
        # numpy's BLAS held at one thread: a state's small products (pca: the mean through the basis) woke
        # OpenBLAS's threads, which then spun through the read that follows on the cores it decodes on (a
        # variable-rate read of 849 blocks took 1.8x the CPU time); one thread gives the same products
        with one_blas_thread():
            if state:
                codec = codec.load_state_dict(state)
                ref = spec.state_reference
                key = None if ref is None else (cls, h.codes.size, ref.sha256)
                if key is None or key not in _VALIDATED:
                    codec.validate_state()  # the codec's own judgement of what the digest cannot vouch for
                    if key is not None:
                        _VALIDATED.add(key)
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
