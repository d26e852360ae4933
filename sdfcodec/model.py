"""Model files: a trained codec (its config and learned state) as one ``.npz`` of plain arrays.

Layout: every state array under its own name, plus ``__sdfcodec_model__``, a uint8 array holding UTF-8 JSON
``{"format": "sdfcodec-model", "version": 1, "config": {...}}``. Files are read with
``allow_pickle=False``: object arrays are refused, never unpickled. Plugin authors reach these functions
through :mod:`sdfcodec.plugin`; a missing file raises :class:`~sdfcodec.errors.ModelNotFoundError`.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Mapping

import numpy as np

from .codec import Codec
from .errors import FormatError, ModelNotFoundError, NotFittedError, SDFCodecError, VersionError

__all__ = ["save_model", "load_model", "save_state_file", "load_state_file", "load_meta_file"]

_META = "__sdfcodec_model__"
MODEL_FORMAT = "sdfcodec-model"
MODEL_VERSION = 1


def save_state_file(path: str | Path, arrays: Mapping[str, np.ndarray], doing: str = "writing") -> None:
    """Write plain arrays to ``path`` (.npz, compressed), atomically (temp file, then rename).

    Raises:
        WriteFailedError: the file system refused the write (disk full, permission...); nothing is left at
            ``path`` but what was there before.
    """
    from .core._atomic import write_file

    def write(tmp: Path) -> None:
        with open(tmp, "xb") as f:  # an ordinary file (mode 0666 less the umask), shareable like any model
            np.savez_compressed(f, **{k: np.asarray(v) for k, v in arrays.items()})

    write_file(path, write, doing)


def load_state_file(path: str | Path) -> dict[str, np.ndarray]:
    """Read the arrays of a ``.npz`` without ever unpickling.

    Raises:
        ModelNotFoundError: no file at ``path`` (a ``FileNotFoundError`` too).
        FormatError: not a readable ``.npz``, or object arrays (which would need unpickling).
    """
    try:
        with np.load(Path(path), allow_pickle=False) as z:
            return {k: z[k] for k in z.files}
    except FileNotFoundError as e:
        raise ModelNotFoundError(f"no such file: {path}") from e
    except ValueError as e:  # object arrays need pickle: refused
        raise FormatError(f"{path}: holds object arrays, which sdfcodec never unpickles ({e})") from e
    except Exception as e:
        raise FormatError(f"{path}: not a readable .npz file ({type(e).__name__}: {e})") from e


def load_meta_file(path: str | Path, key: str, fmt: str, version: int, what: str, writer: str
                   ) -> tuple[dict, dict[str, np.ndarray]]:
    """Read a ``.npz`` of plain arrays whose entry ``key`` is UTF-8 JSON metadata with ``format == fmt`` and
    ``version <= version``; returns ``(metadata, the other arrays)``. ``what``/``writer`` name the kind of file
    and what writes it, in errors (FormatError; VersionError for a newer version)."""
    arrays = load_state_file(path)
    if key not in arrays:
        raise FormatError(f"{path}: not an sdfcodec {what} (no {key} entry); {what}s are written by {writer}")
    try:
        meta = json.loads(arrays.pop(key).tobytes().decode())
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise FormatError(f"{path}: {what} metadata is not valid JSON ({e})") from e
    if not isinstance(meta, dict) or meta.get("format") != fmt:
        got = meta.get("format") if isinstance(meta, dict) else meta
        raise FormatError(f"{path}: {what} format is {got!r}, expected {fmt!r}")
    if not isinstance(meta.get("version"), int) or meta["version"] > version:
        raise VersionError(f"{path}: {what} format version {meta.get('version')} is newer than this sdfcodec "
                           f"reads ({version}); upgrade sdfcodec")
    return meta, arrays


def save_model(codec: Codec, path: str | Path) -> Path:
    """Save a fitted codec to ``path`` (``.npz``); returns the path."""
    if not codec.is_fitted:
        raise NotFittedError(f"{codec!r} is not fitted: there is no learned state to save (call fit first)")
    meta = json.dumps({"format": MODEL_FORMAT, "version": MODEL_VERSION, "config": codec.get_config()})
    arrays = dict(codec.state_dict())
    arrays[_META] = np.frombuffer(meta.encode(), dtype=np.uint8)
    save_state_file(path, arrays, "saving the model")
    return Path(path)


def load_model(path: str | Path) -> Codec:
    """Load a codec saved by :func:`save_model` (its plugin must be installed)."""
    from .registry import get_codec

    meta, arrays = load_meta_file(path, _META, MODEL_FORMAT, MODEL_VERSION, "model",
                                  "`sdfcodec train` or sdfcodec.model.save_model")
    codec = get_codec(meta["config"]).load_state_dict(arrays)
    try:
        codec.validate_state()
    except SDFCodecError as e:
        raise FormatError(f"{path}: {e}") from e
    return codec
