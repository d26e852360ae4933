"""Opening a map for reading: :func:`open_reader` finds the store, parses the header, checks the integrity manifest
and signature before any array's metadata is read, and hands the group to :class:`~sdfcodec.map.reader.MapReader`
(what :func:`sdfcodec.open_map` opens)."""

from __future__ import annotations

import os
from typing import Any, Sequence

import zarr
import zarr.abc.store

from ..core.header import parse_header
from ..errors import FormatError, MapNotFoundError, SDFCodecError
from .format import DEFAULT_MAX_DECODE_BYTES
from .io.stores import PinnedStore, open_store, unguarded
from .reader import CodecCache, MapReader

__all__ = ["open_reader"]


def open_reader(path_or_url: str | os.PathLike | zarr.abc.store.Store, *, storage_options: dict | None = None,
                max_decode_bytes: int = DEFAULT_MAX_DECODE_BYTES, cache: CodecCache | None = None,
                follow_symlinks: bool = False, trusted_keys: Sequence[Any] | None = None,
                verify_chunks: bool | None = None, location: str | None = None) -> MapReader:
    """The reader of the map at ``path_or_url`` (what :func:`sdfcodec.open_map` opens; see there).
    ``trusted_keys`` and ``verify_chunks`` default to the process's (``--trusted-key``, ``--no-verify-chunks``);
    ``location``: what messages call it (default ``str(path_or_url)``; a held version's store names its map
    directory)."""
    from .manifest import check_default
    from .signing import protect, trust_default

    loc = location or str(path_or_url)
    try:
        store = open_store(path_or_url, loc, storage_options, follow_symlinks=follow_symlinks)
        group = zarr.open_group(store, mode="r", zarr_format=3)
        raw = group.attrs.get("sdfcodec")
    except (MapNotFoundError, FormatError):
        raise
    except (FileNotFoundError, NotADirectoryError) as e:
        raise MapNotFoundError(f"no map at {loc}") from e
    except SDFCodecError:
        raise
    except Exception as e:
        raise FormatError(f"{loc}: not a readable Zarr v3 group ({type(e).__name__}: {e})") from e
    header = parse_header(raw, where=loc)
    # the integrity manifest and the signature (spec sections 9b, 9c): before any array's metadata is read
    protect(store, header, raw, loc, trusted_keys=trust_default() if trusted_keys is None else trusted_keys,
            verify_chunks=check_default() if verify_chunks is None else verify_chunks)
    inner = unguarded(store)
    # how another process reopens it: the store object itself, the map directory's path (not the pinned
    # /proc/self/fd one), or the location as given
    source = (location if location else  # a held version (a writer's commit): reopened by its map's path
              path_or_url if isinstance(path_or_url, zarr.abc.store.Store) else
              str(inner.path) if isinstance(inner, PinnedStore) else loc, storage_options)
    return MapReader(group, header, loc, max_decode_bytes=max_decode_bytes, cache=cache, source=source)
