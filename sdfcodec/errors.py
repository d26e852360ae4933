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


# -- codec registry and model files -----------------------------------------------------------------------
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


# -- writes that fail in the file system ------------------------------------------------------------------
__all__ += ["WriteFailedError"]


class WriteFailedError(SDFCodecError, OSError):
    """Writing a map or an output file failed in the file system: the disk or quota is full (``ENOSPC``,
    ``EDQUOT``), a file would pass the size limit (``EFBIG``), no permission or a read-only file system
    (``EACCES``, ``EPERM``, ``EROFS``), an I/O error (``EIO``)...

    The message names the path and what to do. ``errno``, ``strerror`` and ``filename`` are those of the
    underlying ``OSError`` (also chained as ``__cause__``). sdfcodec raises it only once the previous map (or
    file) at the path is known to be unchanged and its own temporary files are removed.
    """

    #: what to do, by errno name; anything else gets the generic advice
    ADVICE = {
        "ENOSPC": "the file system is full: free space there (or write elsewhere) and run again",
        "EDQUOT": "your disk quota is used up: free space (or write elsewhere) and run again",
        "EFBIG": "a file would pass the file size limit of this process or file system (`ulimit -f`): raise the "
                 "limit or write elsewhere",
        "EACCES": "no permission to write there: fix the directory's permissions or write elsewhere",
        "EPERM": "the operation is not permitted there: fix the directory's permissions or write elsewhere",
        "EROFS": "the file system is read-only: write elsewhere",
        "EIO": "the storage device reported an I/O error: check the disk (e.g. `dmesg`) and write elsewhere",
    }

    def __init__(self, message: str, errno: int | None = None, strerror: str | None = None,
                 filename: str | None = None):
        super().__init__(message)
        self.errno, self.strerror, self.filename = errno, strerror, filename

    def __str__(self) -> str:
        return str(self.args[0]) if self.args else ""

    def __reduce__(self):  # keep errno and filename when the error crosses processes (dask workers)
        return type(self), (str(self), self.errno, self.strerror, self.filename)

    @classmethod
    def from_os_error(cls, err: OSError, path, doing: str, outcome: str) -> "WriteFailedError":
        """The error for ``err`` raised while ``doing`` (e.g. "writing the map") at ``path``; ``outcome`` says
        what the caller left behind (e.g. "the previous map is unchanged")."""
        import errno as _errno
        import re

        name = _errno.errorcode.get(err.errno or 0, "")
        reason = err.strerror or str(err) or type(err).__name__
        where = ""
        if err.filename and str(err.filename) != str(path):
            # a file inside the writer's hidden temporary copy (removed by now): name it relative to the map
            inner = re.search(r"/\.[^/]+\.(?:tmp|old)-[0-9a-f]+(?:/(.+))?$", str(err.filename))
            if inner is None:
                where = f" ({err.filename})"
            else:
                key = re.sub(r"\.[0-9a-f]{32}\.partial$", "", inner.group(1) or "")  # the file being written
                where = f" (writing {key})" if key else " (making its hidden temporary copy)"
        advice = cls.ADVICE.get(name, "check the file system and run again")
        return cls(f"could not finish {doing} {path}: {reason}{where}; {outcome}. What to do: {advice}",
                   err.errno, err.strerror, str(err.filename) if err.filename else str(path))


__all__ += ["StateReferenceError"]


class StateReferenceError(FormatError):
    """A map stores its codec state by reference to a shipped model (spec/map-format.md, section 6c) that the
    installed plugin does not ship, or ships with another state: the message names the model and its digest and
    says what to do (install the plugin version that ships it, or re-store the map with the state embedded)."""


__all__ += ["IntegrityError", "SignatureError"]


class IntegrityError(ChecksumError):
    """An object of a map is not the one its integrity manifest lists at that key (spec/map-format.md, section
    9b): changed, moved, missing, unlisted, or from another map. The message names the map, the array and the
    key."""


class SignatureError(IntegrityError):
    """Keys were given to trust and the map is unsigned, signed by another key, or changed after signing (spec
    section 9c); or a key file is unusable."""


__all__ += ["PluginError"]


class PluginError(SDFCodecError, RuntimeError):
    """A codec plugin's own code failed or broke the codec contract while it ran (an exception of its own, or
    a decode of the wrong shape, a non-float type or NaN/Inf values): the message names the codec and the
    module that provides it, so the user knows whom to report it to (spec/codec-plugins.md, section 4)."""
