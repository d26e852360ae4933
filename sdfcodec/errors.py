"""Errors and warnings raised by sdfcodec.

Every error the project raises on purpose derives from :class:`SDFCodecError`, so a caller can catch one
type; each also derives from the closest built-in exception (``ValueError``, ``KeyError``...) so code that
already catches those keeps working. Messages name what was wrong and what to do about it.
"""

from __future__ import annotations

__all__ = [
    "SDFCodecError",
    "SDFCodecWarning",
    "UnknownCodecError",
    "PluginLoadError",
    "ShapeError",
    "DTypeError",
    "InvalidValueError",
    "NotFittedError",
    "FormatError",
    "VersionError",
    "ChecksumError",
    "MapExistsError",
    "MapNotFoundError",
    "ReadOnlyError",
    "InputNotFoundError",
    "OutOfRangeError",
    "MissingDependencyError",
    "SamplingError",
    "MapBusyError",
]


class SDFCodecError(Exception):
    """Base class of every error sdfcodec raises on purpose."""


class SDFCodecWarning(UserWarning):
    """Base class of sdfcodec's warnings (e.g. values clipped to the truncation range)."""


class UnknownCodecError(SDFCodecError, LookupError):
    """No installed codec has the requested id (the message names the id and, when known, its package)."""


class PluginLoadError(SDFCodecError, ImportError):
    """A codec plugin is installed but failed to import; other codecs keep working."""


class ShapeError(SDFCodecError, ValueError):
    """An array has the wrong rank or shape."""


class DTypeError(SDFCodecError, TypeError):
    """An array has a dtype that cannot be used (integers, booleans, complex...)."""


class InvalidValueError(SDFCodecError, ValueError):
    """An array holds NaN or infinite values, or a parameter is out of range."""


class NotFittedError(SDFCodecError, RuntimeError):
    """A codec that needs fitting was used before ``fit`` or ``load_state_dict``."""


class FormatError(SDFCodecError, ValueError):
    """A map on disk does not follow the map format (bad header, missing array, unreadable chunk)."""


class VersionError(FormatError):
    """A map was written by a newer format version, or needs an extension this reader does not know."""


class ChecksumError(FormatError):
    """A stored chunk failed its checksum or could not be decompressed (the message names the chunk)."""


class MapExistsError(SDFCodecError, FileExistsError):
    """The output path exists and overwriting was not asked for."""


class MapNotFoundError(SDFCodecError, FileNotFoundError):
    """No map (or no file) at the given path or URL."""


class ReadOnlyError(SDFCodecError, PermissionError):
    """A write was attempted on a map opened read-only."""


class InputNotFoundError(SDFCodecError, FileNotFoundError):
    """An input file the caller named (a volume to encode, a depth image...) does not exist.

    Raised like the built-in, ``InputNotFoundError(errno.ENOENT, "no such input file", path)``, so ``filename``
    and ``strerror`` are set as for any missing file.
    """


class OutOfRangeError(SDFCodecError, IndexError):
    """An index (a frame number...) is outside the collection; an IndexError, so ``for`` loops and ``except
    IndexError`` keep working."""


class MissingDependencyError(SDFCodecError, ImportError):
    """An optional dependency (e.g. open3d for fusion and rendering) is not installed; the message names the
    extra to install (``pip install 'sdfcodec[fusion]'``)."""


class SamplingError(SDFCodecError, RuntimeError):
    """A random generator could not draw what was asked for within its retry budget (the message says what)."""


class MapBusyError(SDFCodecError, TimeoutError):
    """Another process kept a map locked (an update in progress) for longer than the caller would wait."""


# -- codec registry and model files (issue 14) ------------------------------------------------------------
__all__ += ["RegistrationError", "CodecTypeError", "ModelNotFoundError"]


class RegistrationError(SDFCodecError, ValueError):
    """A codec (or its benchmark) could not be registered: a malformed ``codec_id`` or a clash with another
    class registered under the same id."""


class CodecTypeError(SDFCodecError, TypeError):
    """Something that must be a codec (a ``Codec`` subclass, an id or a config dict) is of another type."""


class ModelNotFoundError(SDFCodecError, FileNotFoundError):
    """No model file (trained codec, state ``.npz``) at the given path, or no shipped model for a codec or
    size: the message says how to train or where to pass one."""


__all__ += ["RemoteReadError"]


class RemoteReadError(SDFCodecError, OSError):
    """An object of a remote map (HTTP(S), S3) could not be read: a transient failure that outlasted every
    try (5xx, reset, timeout), or a response refused unread (too large, a redirect loop, a client error).
    The message names the object's URL, the status and the number of tries; it says nothing about whether
    the map itself is intact."""
