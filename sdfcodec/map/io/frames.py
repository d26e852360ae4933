"""A stored chunk's frame checked before anything decodes it: its CRC32C (Zarr's ``crc32c`` codec: the last four
bytes are the little-endian CRC32C of the bytes before them) and the structure of its Blosc frame
(:func:`blosc_frame_problem`). The guarded stores check every chunk Zarr reads with them
(:mod:`~sdfcodec.map.io.stores`); the reader that goes without Zarr (:mod:`~sdfcodec.map.summary`'s, for
``info``) calls them directly. Nothing here imports Zarr."""

from __future__ import annotations

from typing import Any

import google_crc32c  # what Zarr's crc32c codec computes with
import numpy as np

__all__ = ["crc32c_matches", "blosc_frame_problem"]


def crc32c_matches(data: Any) -> bool:
    """True when ``data`` (any bytes-like object) ends with the CRC32C of the rest, as Zarr writes it."""
    view = np.frombuffer(data, np.uint8)  # slices without a copy; google_crc32c takes arrays, not memoryviews
    return len(view) >= 4 and google_crc32c.value(view[:-4]) == int.from_bytes(view[-4:].tobytes(), "little")


def blosc_frame_problem(frame: bytes | memoryview, max_nbytes: int) -> str | None:
    """What is wrong with the structure of a Blosc (version 1 format) frame, or None. The C decompressor trusts
    the frame's header and block offsets: a frame cut short, or with a tampered header, would make it read or
    write outside its buffers (a crash, not an error) or allocate what the header claims (a bomb). Checked:
    the header's compressed size is the frame's, the uncompressed size fits the chunk, the type size is not 0,
    the block-start table lies inside the frame, and every stream of every block (a block is split into one
    stream per byte of the type size when shuffled, by the decompressor's own rule) has its 4-byte length and
    that many bytes inside the frame."""
    if len(frame) < 16:
        return f"{len(frame)} bytes, shorter than a Blosc header"
    flags, typesize = frame[2], frame[3]
    nbytes, blocksize, cbytes = (int.from_bytes(frame[i:i + 4], "little") for i in (4, 8, 12))
    if nbytes > max_nbytes:
        return f"it claims {nbytes} bytes uncompressed, more than its shape holds ({max_nbytes})"
    if cbytes != len(frame):
        return f"its header gives {cbytes} compressed bytes, the chunk holds {len(frame)}"
    if flags & 0x02:  # stored uncompressed (memcpyed): the data follows the header
        return None if cbytes == nbytes + 16 else f"a stored frame of {nbytes} bytes cannot be {cbytes} long"
    if nbytes == 0:
        return None
    if typesize == 0:  # the decompressor divides the block size by it
        return "its type size is 0"
    if blocksize == 0 or blocksize > max(nbytes, 1 << 31):
        return f"block size {blocksize} for {nbytes} bytes"
    nblocks = -(-nbytes // blocksize)
    table = 16 + 4 * nblocks
    if table > cbytes:
        return f"{nblocks} blocks do not fit their offset table in {cbytes} bytes"
    data = np.frombuffer(frame, dtype=np.uint8)
    starts = data[16:table].view("<i4").astype(np.int64)
    outside = np.flatnonzero((starts < table) | (starts > cbytes - 4))
    if outside.size:
        i = int(outside[0])
        return f"block {i} starts at byte {int(starts[i])}, outside the frame's data [{table}, {cbytes - 4}]"
    # c-blosc's blosc_d: a block is split into `typesize` streams unless the frame says not to (flag 0x10),
    # the type is wider than 16 bytes, a stream would hold under 128 bytes, or it is the short last block
    leftover = nbytes % blocksize
    split = not flags & 0x10 and typesize <= 16 and blocksize // typesize >= 128
    nsplits = np.full(nblocks, typesize if split else 1, dtype=np.int64)
    if leftover:
        nsplits[-1] = 1
    pos = starts.copy()  # walked in step over all blocks at once: at most 16 rounds, each vectorised
    for j in range(int(nsplits.max())):
        live = np.flatnonzero(nsplits > j)
        at = pos[live]
        short = np.flatnonzero(at > cbytes - 4)
        if short.size:
            i = int(live[short[0]])
            return f"block {i}'s stream {j} starts at byte {int(pos[i])}, past the end of the frame ({cbytes})"
        idx = at[:, None] + np.arange(4)
        lengths = data[idx].astype(np.int64) @ np.array([1, 1 << 8, 1 << 16, 1 << 24], dtype=np.int64)
        lengths = np.where(lengths >= 1 << 31, lengths - (1 << 32), lengths)  # a signed int32
        bad = np.flatnonzero((lengths < 0) | (lengths > cbytes - at - 4))
        if bad.size:
            i, n = int(live[bad[0]]), int(lengths[bad[0]])
            return f"block {i}'s stream {j} claims {n} bytes, past the end of the frame"
        pos[live] = at + 4 + lengths
    return None
