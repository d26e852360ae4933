"""What a map's metadata documents (``zarr.json``) may cost to parse (spec section 9a).

A size bound alone does not bound what parsing allocates: 16 MiB of ``[[],[],...]`` is 5.6 million Python
lists (about 360 MB, and a reader parses a document more than once); seven such documents took ``decode`` to
2.33 GB of peak memory and ``verify`` to 2.95 GB. So each document is measured before it is parsed, from its
bytes alone and without building anything per value: its nodes (values, keys and containers: the JSON
separators and openers outside strings) and its nesting depth, each bounded; and a map's documents together are
bounded in bytes and nodes (:class:`MetadataBudget`), since a hostile map can hold many of them. A map's real
metadata is a few kB of a few hundred nodes nested 5 deep.

Zarr-free (``info``'s reader of a local map uses it without importing Zarr).
"""

from __future__ import annotations

import re
import threading

from ...errors import FormatError

__all__ = ["MAX_METADATA_NODES", "MAX_METADATA_DEPTH", "MAX_MAP_METADATA_BYTES", "MAX_MAP_METADATA_NODES",
           "metadata_size", "check_metadata_size", "MetadataBudget"]

#: Most nodes (values, object keys and containers) of one metadata document: about 10 MB when parsed.
MAX_METADATA_NODES = 100_000
#: Deepest nesting of arrays and objects in one metadata document (a map's nests about 5 deep).
MAX_METADATA_DEPTH = 64
#: Most bytes of all the metadata documents one opened map reads, together (each also at most 16 MiB).
MAX_MAP_METADATA_BYTES = 32 << 20
#: Most nodes of all the metadata documents one opened map reads, together.
MAX_MAP_METADATA_NODES = 400_000

# a JSON string once its escaped backslashes and quotes are gone (a regular expression that steps over the
# escapes itself took 3.7 s on 15 MiB of them)
_STRING = re.compile(rb'"[^"]*"')
_NOT_BRACKETS = bytes(b for b in range(256) if b not in b"[]{}")


def metadata_size(data: bytes) -> tuple[int, int]:
    """``(nodes, depth)`` of JSON document ``data`` (an upper bound of its values, keys and containers, and its
    deepest nesting), from its bytes: strings are blanked, then separators and brackets are counted. Allocates
    a few copies of ``data`` at most (the blanked text), whatever it holds; a document that is not JSON gets a
    count too (the parser refuses it after)."""
    # backslashes pair from the left inside a string: drop the pairs, then the escaped quotes, then the strings
    bare = _STRING.sub(b'""', data.replace(b"\\\\", b"").replace(b'\\"', b""))
    openers = bare.count(b"[") + bare.count(b"{")
    nodes = bare.count(b",") + bare.count(b":") + openers + 1
    if nodes > MAX_METADATA_NODES:
        return nodes, 0  # the depth is not needed, and not worth a pass over that many brackets
    depth = level = 0
    for b in bare.translate(None, _NOT_BRACKETS):  # at most 2 x nodes bytes of brackets
        level += 1 if b in (0x5B, 0x7B) else -1
        depth = max(depth, level)
    return nodes, depth


def check_metadata_size(key: str, data: bytes) -> int:
    """Refuse metadata document ``key`` (bytes ``data``) with more than :data:`MAX_METADATA_NODES` nodes or
    nested deeper than :data:`MAX_METADATA_DEPTH`, before anything parses it; returns its node count.

    Raises:
        FormatError: naming ``key`` and the limit.
    """
    nodes, depth = metadata_size(data)
    if nodes > MAX_METADATA_NODES:
        raise FormatError(f"{key} holds about {nodes} JSON values, more than any map metadata "
                          f"({MAX_METADATA_NODES}); refused unparsed")
    if depth > MAX_METADATA_DEPTH:
        raise FormatError(f"{key} is nested {depth} deep, deeper than any map metadata ({MAX_METADATA_DEPTH}); "
                          "refused unparsed")
    return nodes


class MetadataBudget:
    """The metadata documents one opened map has read, bounded together: each distinct key counts once (a
    document read again costs nothing more), at most :data:`MAX_MAP_METADATA_BYTES` and
    :data:`MAX_MAP_METADATA_NODES` in all. Thread-safe (Zarr reads from its own threads)."""

    def __init__(self):
        self._seen: dict[str, tuple[int, int]] = {}
        self._lock = threading.Lock()

    def charge(self, key: str, nbytes: int, nodes: int) -> None:
        """Count document ``key`` of ``nbytes`` bytes and ``nodes`` nodes.

        Raises:
            FormatError: the map's documents together exceed a limit (naming ``key``, the one that did).
        """
        with self._lock:
            old = self._seen.get(key, (0, 0))
            total_b = sum(b for b, _ in self._seen.values()) - old[0] + nbytes
            total_n = sum(n for _, n in self._seen.values()) - old[1] + nodes
            if total_b > MAX_MAP_METADATA_BYTES or total_n > MAX_MAP_METADATA_NODES:
                raise FormatError(f"{key}: the map's metadata documents together hold {total_b} bytes and about "
                                  f"{total_n} JSON values with this one, more than any map's "
                                  f"({MAX_MAP_METADATA_BYTES} bytes, {MAX_MAP_METADATA_NODES} values); refused")
            self._seen[key] = (nbytes, nodes)
