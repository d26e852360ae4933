"""A cache of built-in query models and their calibrated thresholds, in memory and on disk.

Building the floor model for a map samples and encodes hundreds of shapes, and a map that records neither its
up direction nor its observation builds six of them (:mod:`sdfcodec.search.context`) before the first block
is scored: about a second on two cores, while scoring 65,536 blocks takes a twentieth of that. The models
depend only on what the key names (the shape, the codec's configuration and state digest, the voxel size,
truncation, up direction, rotations, offsets, what lies behind surfaces, the weighting and stretches), never
on the map's blocks, so they are built once and reused: within a process from memory (least recently used
first out), across processes from ``.npz`` files of plain arrays (``save_query``/``load_query``; never
pickles) under the cache directory; and the calibrations that depend on no map (the plane check of fused maps)
come shipped for the shipped codecs (:func:`shipped_thresholds`).

The directory is ``$SDFCODEC_CACHE_DIR`` if set (set it empty, ``0`` or ``off`` to keep nothing on disk), else
``$XDG_CACHE_HOME/sdfcodec`` or ``~/.cache/sdfcodec``. A cache file is untrusted like any input: one that does
not load, or whose model is not the one its key asks for, is rebuilt and replaced; a directory that cannot be
written leaves the cache in memory only. Deleting the directory is always safe.
"""

from __future__ import annotations

import collections
import contextlib
import hashlib
import json
import os
from pathlib import Path
from typing import Any, Callable, Iterator

import numpy as np

from ..errors import SDFCodecError

__all__ = ["CACHE_ENV", "SHIPPED_FILE", "cache_dir", "cache_key", "cached_model", "cached_threshold",
           "clear_memory_cache", "announce_builds", "shipped_thresholds"]

#: Environment variable naming the cache directory (empty, ``0`` or ``off``: no disk cache).
CACHE_ENV = "SDFCODEC_CACHE_DIR"
#: Bumped whenever the shapes, their encoding or the calibration change in a way the key does not name, so
#: that files written by an older sdfcodec are not reused.
#: 3: the pca writer's truncation refits as conjugate-gradient steps; 4: those from the fit without the bound
#: voxels, in kernels whose sums keep their order (codes no longer depend on numba's cache)
BUILD_VERSION = 4
#: Models and thresholds kept in memory per process.
MEMORY_ENTRIES = 64

_models: collections.OrderedDict[str, Any] = collections.OrderedDict()
_listeners: list[Callable[[str], None]] = []  # told what is being built, before a cache miss is built
_thresholds: collections.OrderedDict[str, tuple[float, dict]] = collections.OrderedDict()
#: Calibrations shipped with sdfcodec, under the keys a search computes (:func:`shipped_thresholds`).
SHIPPED_FILE = Path(__file__).with_name("shipped-calibrations.json")
_shipped: dict[str, tuple[float, dict]] | None = None


def cache_dir() -> Path | None:
    """The directory of the disk cache, or None when it is switched off (module docstring)."""
    env = os.environ.get(CACHE_ENV)
    if env is not None:
        return None if env.strip().lower() in ("", "0", "off", "none") else Path(env).expanduser()
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "sdfcodec"


def cache_key(kind: str, **parts: Any) -> str:
    """A SHA-256 hex digest naming one cache entry: ``kind`` and ``parts`` as canonical JSON (floats exactly;
    numpy arrays by their dtype, shape and bytes)."""
    def plain(v: Any) -> Any:
        if isinstance(v, np.ndarray):
            a = np.ascontiguousarray(v)
            return {"dtype": a.dtype.str, "shape": list(a.shape), "sha256": hashlib.sha256(a.tobytes()).hexdigest()}
        if isinstance(v, (tuple, list)):
            return [plain(x) for x in v]
        if isinstance(v, dict):
            return {str(k): plain(x) for k, x in v.items()}
        if isinstance(v, (np.floating, np.integer, np.bool_)):
            return v.item()
        return v

    doc = json.dumps({"kind": kind, "build": BUILD_VERSION, **plain(parts)}, sort_keys=True, allow_nan=False)
    return hashlib.sha256(doc.encode()).hexdigest()


def shipped_thresholds() -> dict[str, tuple[float, dict]]:
    """The calibrations shipped with sdfcodec (:data:`SHIPPED_FILE`, written by ``examples/ship_calibrations.py``:
    the plane check of surface-true maps for the shipped pca sizes at the default voxel size and truncation), by
    cache key: a first search on a fused map finds them as a warm cache would. A key names the codec's state
    digest and :data:`BUILD_VERSION`, so an entry made for other eigenshapes or an older build is never found;
    an unreadable file ships nothing."""
    global _shipped
    if _shipped is None:
        table: dict[str, tuple[float, dict]] = {}
        try:
            for key, e in json.loads(SHIPPED_FILE.read_text(encoding="utf-8"))["entries"].items():
                t, info = e["threshold"], e["info"]
                if isinstance(t, float) and np.isfinite(t) and t >= 0 and isinstance(info, dict):
                    table[key] = (t, info)
        except (OSError, ValueError, KeyError, TypeError, AttributeError):
            table = {}
        _shipped = table
    return _shipped


def _remember(store: collections.OrderedDict, key: str, value: Any) -> Any:
    store[key] = value
    store.move_to_end(key)
    while len(store) > MEMORY_ENTRIES:
        store.popitem(last=False)
    return value


def clear_memory_cache() -> None:
    """Forget the models and thresholds held in memory (the disk cache stays)."""
    _models.clear()
    _thresholds.clear()


@contextlib.contextmanager
def announce_builds(listener: Callable[[str], None]) -> Iterator[None]:
    """Within the block, ``listener(what)`` is called before each model or threshold that is not cached is built
    (``what``: e.g. "building the wall query for pca-64"): a first search spends most of its time there, and a
    command says so instead of looking hung (``sdfcodec search``)."""
    _listeners.append(listener)
    try:
        yield
    finally:
        _listeners.remove(listener)


def _announce(what: str | None) -> None:
    for listener in list(_listeners) if what else ():
        listener(what)  # type: ignore[arg-type]


def _path(key: str, suffix: str) -> Path | None:
    d = cache_dir()
    return None if d is None else d / "queries" / f"{key}{suffix}"


def cached_model(key: str, build: Callable[[], Any], valid: Callable[[Any], bool], what: str | None = None, *,
                 load: Callable[[Path], Any], save: Callable[[Any, Path], Any]) -> Any:
    """The query model cached under ``key``, else ``build()`` (then cached; ``what`` names it for
    :func:`announce_builds`). A model read from disk is used only when ``valid(model)`` holds (it was made by the
    codec and with the spec the key names). ``load(path)`` / ``save(model, path)`` read and write a model's file
    (:func:`sdfcodec.search.models.load_query` / ``save_query``: passed in, as the models module builds through
    this cache)."""
    if key in _models:
        _models.move_to_end(key)
        return _models[key]
    path = _path(key, ".npz")
    if path is not None and path.is_file():
        try:
            model = load(path)
            if valid(model):
                return _remember(_models, key, model)
        except (SDFCodecError, OSError, ValueError):
            pass  # a damaged or foreign file: rebuilt and replaced below
    _announce(what)
    model = build()
    if path is not None:
        try:
            save(model, path)
        except (SDFCodecError, OSError):
            pass  # a read-only or full cache directory: the cache stays in memory
    return _remember(_models, key, model)


def cached_threshold(key: str, compute: Callable[[], tuple[float, dict]],
                     valid: Callable[[dict], bool] = lambda info: True, what: str | None = None) -> tuple[float, dict]:
    """The calibrated threshold and its report cached under ``key``, else ``compute()`` (then cached; ``what``
    names it for :func:`announce_builds`). A report read from disk is used only when ``valid(report)`` holds (it
    has the fields the caller reads)."""
    if key in _thresholds:
        _thresholds.move_to_end(key)
        return _thresholds[key]
    shipped = shipped_thresholds().get(key)
    if shipped is not None and valid(shipped[1]):
        return _remember(_thresholds, key, (shipped[0], dict(shipped[1])))
    path = _path(key, ".json")
    if path is not None and path.is_file():
        try:
            if path.stat().st_size <= 1 << 16:  # a threshold report is a few hundred bytes
                doc = json.loads(path.read_text(encoding="utf-8"))
                t, info = doc["threshold"], doc["info"]
                if isinstance(t, float) and np.isfinite(t) and t >= 0 and isinstance(info, dict) and valid(info):
                    return _remember(_thresholds, key, (t, info))
        except (OSError, ValueError, KeyError, TypeError):
            pass
    _announce(what)
    t, info = compute()
    if path is not None:
        tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            tmp.write_text(json.dumps({"threshold": float(t), "info": info}), encoding="utf-8")
            os.replace(tmp, path)
        except (OSError, TypeError, ValueError):
            try:  # a full or read-only directory: the cache stays in memory, and no half-written file behind
                tmp.unlink(missing_ok=True)
            except OSError:
                pass
    return _remember(_thresholds, key, (t, info))
