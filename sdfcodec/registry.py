"""Codec registry: codecs are found through the ``sdfcodec.codecs`` entry point group.

Listing is eager (entry point names only, nothing imported); loading is lazy (a plugin's module is imported
the first time its codec is asked for). A plugin that fails to import raises :class:`PluginLoadError` naming
it, and never breaks the listing or loading of other codecs. :func:`register_codec` adds a class at run time
(e.g. in tests or notebooks) and takes precedence over an entry point of the same id. :func:`pretrained_codec`
gives a codec's shipped weights (from its plugin's own package). Every error raised here on purpose is an
:class:`sdfcodec.errors.SDFCodecError`.
"""

from __future__ import annotations

import os
import re
import sys
from dataclasses import dataclass
from importlib import metadata
from typing import Any, Mapping

from .codec import Codec, capabilities
from .errors import (CodecTypeError, InvalidValueError, ModelNotFoundError, PluginLoadError, RegistrationError,
                     UnknownCodecError)

__all__ = ["list_codecs", "get_codec", "get_codec_class", "register_codec", "codec_package", "pretrained_codec",
           "choose_codec", "describe_shipped", "CodecEntry"]

ENTRY_POINT_GROUP = "sdfcodec.codecs"
_ID_RE = re.compile(r"^[a-z0-9][a-z0-9_.-]*$")
_runtime: dict[str, type[Codec]] = {}
_loaded: dict[str, type[Codec]] = {}


@dataclass(frozen=True)
class CodecEntry:
    """One installed codec as listed (without importing it)."""

    id: str
    package: str | None  # the distribution that provides it (None for run-time registrations)
    version: str | None
    target: str  # "module:attribute"


# (sys.path stamp, entry points, their listing) of the last scan
_scanned: tuple[tuple, dict[str, metadata.EntryPoint], dict[str, CodecEntry]] | None = None


def _path_stamp() -> tuple:
    """``sys.path`` with each entry's modification time. Installing, upgrading or removing a distribution adds or
    removes its metadata directory in one of these entries, which changes that entry's time."""
    stamp = []
    for p in sys.path:
        try:
            stamp.append((p, os.stat(p or os.curdir).st_mtime_ns))
        except OSError:
            stamp.append((p, None))
    return tuple(stamp)


def _entry_points() -> dict[str, metadata.EntryPoint]:
    # Scanning reads the metadata of every installed distribution (tens of ms in an environment of a few hundred
    # packages) and every map written asks for its codec's package: the scan is kept while sys.path and its
    # entries' times are unchanged, so a plugin installed while a process runs is still found.
    return dict(_scan()[1])


def _scan() -> tuple[tuple, dict[str, metadata.EntryPoint], dict[str, CodecEntry]]:
    global _scanned
    stamp = _path_stamp()
    if _scanned is None or _scanned[0] != stamp:
        eps = {ep.name: ep for ep in metadata.entry_points(group=ENTRY_POINT_GROUP)}
        # each distribution's name and version are read from its metadata file: once per scan
        _scanned = (stamp, eps, {name: _listing(name, ep) for name, ep in eps.items()})
    return _scanned


def _listing(name: str, ep: metadata.EntryPoint) -> CodecEntry:
    dist = getattr(ep, "dist", None)
    return CodecEntry(name, dist.name if dist else None, dist.version if dist else None, ep.value)


def _entries() -> dict[str, CodecEntry]:
    listed = _scan()[2]
    out: dict[str, CodecEntry] = {}
    for name, ep in _entry_points().items():  # through the module's name, which tests may replace
        known = listed.get(name)
        out[name] = known if known is not None and known.target == ep.value else _listing(name, ep)
    for name, cls in _runtime.items():
        out[name] = CodecEntry(name, None, None, f"{cls.__module__}:{cls.__qualname__}")
    return out


def list_codecs() -> list[CodecEntry]:
    """All installed codecs, sorted by id, without importing any plugin."""
    return [e for _, e in sorted(_entries().items())]


def codec_package(codec_id: str) -> str | None:
    """The distribution that provides ``codec_id``, or None when unknown or registered at run time."""
    entry = _entries().get(codec_id)
    return entry.package if entry else None


# PEP 508 distribution names: the only package names worth printing after "pip install"
_DIST_NAME = re.compile(r"[A-Za-z0-9](?:[A-Za-z0-9._-]{0,98}[A-Za-z0-9])?")


def _install_hint(package: str | None) -> str:
    """The install advice for a missing codec whose package a map's header names. The header is untrusted: a
    name that is not a valid distribution name (spaces, options, URLs, control characters) is not printed,
    and a valid one is said to come from the header, not from sdfcodec."""
    if not isinstance(package, str) or not _DIST_NAME.fullmatch(package):
        return ""
    return f" (the map's header names package {package!r} as its provider: pip install {package})"


def get_codec_class(codec_id: str, *, package_hint: str | None = None) -> type[Codec]:
    """Load the class of ``codec_id``.

    Raises:
        UnknownCodecError: no such codec installed (names the id, ``package_hint`` and what is installed).
        PluginLoadError: the plugin is installed but its import failed.
    """
    if codec_id in _runtime:
        return _runtime[codec_id]
    if codec_id in _loaded:
        return _loaded[codec_id]
    eps = _entry_points()
    ep = eps.get(codec_id)
    if ep is None:
        installed = ", ".join(sorted(set(eps) | set(_runtime))) or "none"
        where = _install_hint(package_hint)
        raise UnknownCodecError(f"codec {codec_id!r} is not installed{where}; installed codecs: {installed}")
    try:
        cls = ep.load()
    except Exception as exc:
        dist = getattr(ep, "dist", None)
        raise PluginLoadError(f"codec plugin {codec_id!r} ({ep.value}, package "
                              f"{dist.name if dist else '?'}) failed to import: {type(exc).__name__}: {exc}") from exc
    if not (isinstance(cls, type) and issubclass(cls, Codec)):
        raise PluginLoadError(f"entry point {codec_id!r} = {ep.value} is not a sdfcodec.Codec subclass")
    if getattr(cls, "codec_id", None) != codec_id:
        raise PluginLoadError(f"entry point {codec_id!r} loads {cls.__qualname__} whose codec_id is "
                              f"{getattr(cls, 'codec_id', None)!r}; they must match")
    try:
        capabilities(cls)  # a declared capability the class does not implement: refused here, by name
    except RegistrationError as exc:
        raise PluginLoadError(f"codec plugin {codec_id!r} ({ep.value}): {exc}") from exc
    _loaded[codec_id] = cls
    return cls


def get_codec(id_or_config: str | Mapping[str, Any], **params: Any) -> Codec:
    """Build a codec from an id plus parameters, or from a config dict (``{"id": ..., ...}``).

    The config dict is not modified; ``params`` override its entries. The codec is returned unfitted.
    """
    if isinstance(id_or_config, str):
        config: dict[str, Any] = {"id": id_or_config}
    elif isinstance(id_or_config, Mapping):
        if "id" not in id_or_config:
            raise UnknownCodecError(f"codec config has no 'id' key: {dict(id_or_config)!r}")
        config = dict(id_or_config)
    else:
        raise CodecTypeError(f"get_codec takes a codec id or a config dict, got {type(id_or_config).__name__}")
    config.update(params)
    return get_codec_class(str(config["id"])).from_config(config)


def pretrained_codec(codec_id: str, code_size: int | None = None, **options: Any) -> Codec:
    """The fitted codec ``codec_id`` with the weights its plugin ships, at ``code_size`` (None: the codec's
    default), through :meth:`sdfcodec.Codec.pretrained` of its class; e.g. ``pretrained_codec("pca", 64)``.

    Raises:
        UnknownCodecError / PluginLoadError: as :func:`get_codec_class`.
        ModelNotFoundError: the codec ships no model (or none at that size).
    """
    return get_codec_class(codec_id).pretrained(code_size, **options)


def describe_shipped(cls: type[Codec]) -> str:
    """The models ``cls``'s plugin ships with their code sizes, for messages: ``"pca-128 (code sizes 1-128)"``;
    ``"none"``, or ``"unknown ..."`` when the plugin does not list them (:meth:`Codec.shipped_models`)."""
    models = cls.shipped_models()
    if models is None:
        return "unknown (the plugin does not list its shipped models)"
    parts = []
    for name, sizes in sorted(models.items()):
        s = sorted(sizes)
        run = len(s) > 2 and s == list(range(s[0], s[-1] + 1))
        parts.append(f"{name} (code size{'s' if len(s) > 1 else ''} "
                     f"{f'{s[0]}-{s[-1]}' if run else ', '.join(map(str, s))})")
    return ", ".join(parts) or "none"


def choose_codec(codec_id: str = "pca", code_size: int | None = None, *, fit: bool = False
                 ) -> tuple[Codec, str | None]:
    """The codec to encode with when no trained model is given (what ``sdfcodec encode`` uses): the model the
    plugin ships at ``code_size`` (None: the codec's default), else a new codec of that size, unfitted if it
    learns (also with ``fit``), to be fitted on the data.

    Returns:
        ``(codec, why)``: ``why`` is None when the codec is ready (shipped, or it learns nothing), else one line
        saying why it must be fitted (naming the sizes the plugin ships, when it lists them).
    Raises:
        UnknownCodecError / PluginLoadError: as :func:`get_codec_class`.
    """
    cls = get_codec_class(codec_id)
    if not fit:
        try:
            return cls.pretrained(code_size), None
        # spec/codec-plugins.md section 7: no model at all, or none at this size (we pass no options)
        except (ModelNotFoundError, InvalidValueError):
            pass
    codec = get_codec(codec_id, **({"code_size": code_size} if code_size is not None else {}))
    if codec.is_fitted:
        return codec, None
    if fit:
        return codec, "asked to fit (--fit) instead of using the shipped model"
    size = "its default code size" if code_size is None else f"code size {code_size}"
    return codec, (f"codec {codec_id!r} ships no model at {size} (shipped: {describe_shipped(cls)}); "
                   "pass --model to use a trained one")


def register_codec(cls: type[Codec], *, replace: bool = False) -> type[Codec]:
    """Register a codec class at run time (usable as a decorator); returns ``cls``."""
    if not (isinstance(cls, type) and issubclass(cls, Codec)):
        raise CodecTypeError(f"register_codec takes a Codec subclass, got {cls!r}")
    cid = getattr(cls, "codec_id", None)
    if not isinstance(cid, str) or not _ID_RE.match(cid):
        raise RegistrationError(f"{cls.__qualname__}.codec_id must match {_ID_RE.pattern}, got {cid!r}")
    if not replace and cid in _runtime and _runtime[cid] is not cls:
        raise RegistrationError(f"codec {cid!r} is already registered ({_runtime[cid].__qualname__}); "
                                "pass replace=True")
    capabilities(cls)  # RegistrationError for a capability declared but not implemented
    _runtime[cid] = cls
    return cls
