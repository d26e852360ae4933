"""voxblox TSDF layer files (``.voxblox``, ``.vxblx``, ``.tsdf``): reading and writing the wire format.

What a file holds, as voxblox's public sources define it (``Block.proto``, ``Layer.proto``, the block
serialisation and ``io/layer_io``), written here from that description:

- one or more *layers*, each a varint message count ``M`` followed by ``M`` length-delimited messages (a varint
  byte length, then the message): a ``LayerProto`` header, then ``M - 1`` ``BlockProto`` blocks;
- ``LayerProto``: ``voxel_size`` (field 1, double), ``voxels_per_side`` (2, varint), ``type`` (3: the string
  ``"tsdf"``, ``"esdf"``, ``"occupancy"`` or ``"intensity"``; files of early voxblox versions hold a number
  there instead);
- ``BlockProto``: ``voxels_per_side`` (1), ``voxel_size`` (2, double), ``origin_x/y/z`` (3-5, doubles, metres:
  the block's corner, ``block index x voxels_per_side x voxel_size``), ``has_data`` (6), ``voxel_data`` (7,
  repeated uint32, unpacked as voxblox writes it, or packed);
- a TSDF voxel is 3 words: the float32 bits of the distance (metres), of the weight, and the colour
  ``r << 24 | g << 16 | b << 8 | a``; voxels in order ``x + n (y + n z)`` (x fastest); voxel ``(i, j, k)`` of a
  block samples ``origin + (index + 0.5) x voxel_size``. Weight 0 means the voxel was never observed.

The block payloads are decoded with numpy, a whole ``voxel_data`` field at once (no per-voxel Python), so
a file of a million blocks is read at disk speed rather than protobuf-per-message speed; :func:`scan_voxblox`
reads a file once and keeps only each block's byte range and index (40 bytes a block), and
:func:`read_voxblox_blocks` reads any subset of blocks back by those ranges.
"""

from __future__ import annotations

import array
import os
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO, Iterable

import numpy as np

from ..errors import FormatError, InputNotFoundError

__all__ = ["VoxbloxIndex", "VOXBLOX_SUFFIXES", "looks_like_voxblox", "scan_voxblox", "read_voxblox_blocks",
           "write_voxblox", "encode_block"]

VOXBLOX_SUFFIXES = (".voxblox", ".vxblx", ".tsdf")
#: voxels_per_side above this is absurd (a block of 2^30 voxels); refused before anything is allocated.
MAX_VOXELS_PER_SIDE = 1024
_TAG_VOXEL_DATA = (7 << 3) | 0  # field 7, varint: one word


@dataclass
class VoxbloxIndex:
    """What :func:`scan_voxblox` learned of a file's TSDF layer.

    ``offsets`` / ``lengths`` ``(n,)`` int64: the byte range of each block message; ``block_index`` ``(n, 3)``
    int64: each block's index on voxblox's block lattice; ``d_range``: the least and greatest distance of an
    observed voxel (metres; None when nothing is observed); ``observed``: voxels of weight > 0."""

    path: Path
    voxel_size: float
    voxels_per_side: int
    layer_type: str
    offsets: np.ndarray
    lengths: np.ndarray
    block_index: np.ndarray
    d_range: tuple[float, float] | None
    observed: int
    weight_max: float


def looks_like_voxblox(head: bytes) -> bool:
    """Whether the first bytes of a file read as a voxblox layer: a message count, then a LayerProto whose first
    field is ``voxel_size`` (a double, tag 0x09)."""
    try:
        _, p = _varint(head, 0)
        _, p = _varint(head, p)
    except FormatError:
        return False
    return p < len(head) and head[p] == 0x09


def _varint(buf: bytes | memoryview, pos: int, what: str = "a varint") -> tuple[int, int]:
    """Decode one varint of ``buf`` at ``pos``: ``(value, next position)``."""
    value = shift = 0
    while True:
        if pos >= len(buf):
            raise FormatError(f"truncated stream: ends inside {what}")
        b = buf[pos]
        pos += 1
        value |= (b & 0x7F) << shift
        if b < 0x80:
            return value, pos
        shift += 7
        if shift > 63:
            raise FormatError(f"malformed varint in {what} (more than 10 bytes)")


def _varints(b: np.ndarray, what: str) -> np.ndarray:
    """All the varints of the bytes ``b`` ``(n,)`` uint8, which must end with a whole one, each of at most 32
    bits: ``(m,)`` uint32. A few gathers over all the values (no loop over values)."""
    ends = np.flatnonzero(b < 0x80)
    if len(b) and (not len(ends) or ends[-1] != len(b) - 1):
        raise FormatError(f"truncated stream: {what} ends inside a varint")
    if not len(ends):
        return np.zeros(0, dtype=np.uint32)
    starts = np.empty_like(ends)
    starts[0] = 0
    starts[1:] = ends[:-1] + 1
    if (ends - starts).max() > 4 or (b[ends[ends - starts == 4]] > 0x0F).any():
        raise FormatError(f"{what} holds a value of more than 32 bits (a voxel word is a uint32)")
    lens = ends - starts  # bytes after the first
    out = (b[starts] & 0x7F).astype(np.uint32)
    last = len(b) - 1
    for k in range(1, int(lens.max()) + 1):  # a gather of every value's k-th byte, at most 4 more
        byte = (b[np.minimum(starts + k, last)] & 0x7F).astype(np.uint32)
        out |= np.where(lens >= k, byte, np.uint32(0)) << np.uint32(7 * k)
    return out


def _fields(msg: bytes, what: str, stop_at: int | None = None) -> tuple[dict[int, list], int]:
    """The fields of a protobuf message (``{field: [values]}``; varints as ints, fixed64 as float, 32-bit as
    bytes, length-delimited as ``(start, end)`` byte ranges) up to the first occurrence of field ``stop_at``,
    whose tag position is returned (``len(msg)`` when it does not occur)."""
    out: dict[int, list] = {}
    pos = 0
    while pos < len(msg):
        start = pos
        key, pos = _varint(msg, pos, what)
        field, wire = key >> 3, key & 7
        if field == stop_at:
            return out, start
        if wire == 0:
            value, pos = _varint(msg, pos, what)
        elif wire == 1:
            if pos + 8 > len(msg):
                raise FormatError(f"truncated stream: {what} ends inside a double")
            value, pos = struct.unpack_from("<d", msg, pos)[0], pos + 8
        elif wire == 2:
            n, pos = _varint(msg, pos, what)
            if pos + n > len(msg):
                raise FormatError(f"truncated stream: {what} ends inside field {field}")
            value, pos = (pos, pos + n), pos + n
        elif wire == 5:
            if pos + 4 > len(msg):
                raise FormatError(f"truncated stream: {what} ends inside a 32-bit field")
            value, pos = msg[pos:pos + 4], pos + 4
        else:
            raise FormatError(f"{what} is not a protobuf message (wire type {wire} of field {field})")
        out.setdefault(field, []).append(value)
    return out, len(msg)


def _layer_type(fields: dict[int, list], msg: bytes) -> str:
    """The layer's voxel type: the string of field 3, or for files of early voxblox versions (a number there),
    ``"legacy-N"``."""
    t = fields.get(3, [None])[-1]
    if t is None:
        return "unknown"
    if isinstance(t, tuple):
        return bytes(msg[t[0]:t[1]]).decode("utf-8", "replace")
    return f"legacy-{t}"


def _parse_block(msg: bytes, n_vox: int, what: str) -> tuple[dict[int, list], np.ndarray]:
    """A BlockProto: its scalar fields and its ``voxel_data`` words ``(w,)`` uint32."""
    fields, at = _fields(msg, what, stop_at=7)
    raw = np.frombuffer(msg, dtype=np.uint8)
    tail = raw[at:]
    if len(tail) and tail[0] == ((7 << 3) | 2):  # packed: one length-delimited run of varints
        n, p = _varint(msg, at + 1, what)
        if p + n > len(msg):
            raise FormatError(f"truncated stream: {what} ends inside its voxel data")
        words = _varints(raw[p:p + n], what)
        rest = msg[p + n:]
    else:
        try:
            vals = _varints(tail, what)  # tag, word, tag, word... as voxblox writes them
        except FormatError:
            vals = np.zeros(1, dtype=np.uint32)  # something else follows the words: the slow path says what
        if len(vals) % 2 or not (vals[0::2] == _TAG_VOXEL_DATA).all():
            # other fields after or between the words (legal protobuf, not what voxblox writes): slow path
            return _parse_block_slow(msg, what)
        words, rest = vals[1::2], b""
    if rest:
        more, _ = _fields(rest, what)
        fields.update(more)
    return fields, words.astype(np.uint32)


def _parse_block_slow(msg: bytes, what: str) -> tuple[dict[int, list], np.ndarray]:
    """Field by field, for a block whose words are not one run at its end."""
    fields, _ = _fields(msg, what)
    words: list[int] = []
    for v in fields.pop(7, []):
        if isinstance(v, tuple):
            words.extend(_varints(np.frombuffer(msg[v[0]:v[1]], dtype=np.uint8), what).tolist())
        else:
            words.append(v)
    if any(w >= 2**32 for w in words):
        raise FormatError(f"{what} holds a voxel word of more than 32 bits")
    return fields, np.asarray(words, dtype=np.uint32)


class _Window:
    """Sequential reads of a file through a large buffer (one read call per few MiB, not two per message)."""

    def __init__(self, f: BinaryIO, size: int, span: int = 1 << 22):
        self.f, self.size, self.span = f, size, span
        self.base, self.buf = 0, b""
        f.seek(0)

    def get(self, pos: int, n: int) -> bytes:
        """Bytes ``[pos, pos + n)`` (fewer at the end of the file); ``pos`` never goes back before the window."""
        end = pos + n
        if pos < self.base or end > self.base + len(self.buf):
            keep = self.buf[pos - self.base:] if self.base <= pos < self.base + len(self.buf) else b""
            self.f.seek(pos + len(keep))
            self.buf = keep + self.f.read(max(n - len(keep), self.span))
            self.base = pos
        return self.buf[pos - self.base:end - self.base]


def _messages(f: BinaryIO, size: int, what: str) -> Iterable[tuple[int, int, int, bytes | None]]:
    """Walk the layers of an open file: yield ``(layer number, message number, offset, message)`` for every
    message, checking each length against what is left of the file before anything is read; the message is
    read through a large window."""
    pos, layer = 0, 0
    win = _Window(f, size)
    while pos < size:
        count, p = _varint(win.get(pos, 10), 0, f"{what}: the message count of layer {layer}")
        if count == 0:
            raise FormatError(f"{what}: layer {layer} holds no message (an empty voxblox file?)")
        pos += p
        # every message takes at least two bytes (its length and one field): a larger count is absurd
        if count > (size - pos) // 2:
            raise FormatError(f"{what}: layer {layer} claims {count} messages, more than its {size - pos} bytes "
                              "can hold (a truncated or corrupt file)")
        for i in range(count):
            n, p = _varint(win.get(pos, 10), 0, f"{what}: the length of message {i} of layer {layer}")
            pos += p
            if n == 0 or pos + n > size:
                raise FormatError(f"truncated stream: {what}: message {i} of layer {layer} claims {n} bytes, "
                                  f"{size - pos} are left (a file cut short?)")
            yield layer, i, pos, win.get(pos, n)
            pos += n
        layer += 1


def _parse_blocks(msgs: list[bytes], n_vox: int, whats: list[str]) -> tuple[list[dict[int, list]], Any]:
    """Many BlockProtos at once: their scalar fields and voxel words ``(k, 3 n_vox)`` uint32 (a list of ``k``
    arrays, of any length, when a message is not laid out as voxblox writes them). Where every message
    ends with its words unpacked, as voxblox writes them, the words of all messages are decoded in one numpy
    pass; otherwise block by block (:func:`_parse_block`, which also names what is wrong)."""
    heads, tails = [], []
    for msg, what in zip(msgs, whats):
        fields, at = _fields(msg, what, stop_at=7)
        heads.append(fields)
        tails.append(at)
    k, per = len(msgs), 6 * n_vox  # a tag and a word per voxel word
    sizes = np.asarray([len(m) - a for m, a in zip(msgs, tails)], dtype=np.int64)
    if k and (sizes > 0).all():
        buf = np.frombuffer(b"".join(m[a:] for m, a in zip(msgs, tails)), dtype=np.uint8)
        starts = np.concatenate([[0], np.cumsum(sizes)[:-1]])
        term = buf < 0x80
        if (buf[starts] == _TAG_VOXEL_DATA).all() and term[starts + sizes - 1].all() and (
                np.add.reduceat(term, starts) == per).all():
            vals = _varints(buf, whats[0]).reshape(k, per)
            if (vals[:, 0::2] == _TAG_VOXEL_DATA).all():
                return heads, vals[:, 1::2].astype(np.uint32)
    words = []
    for j, (msg, what) in enumerate(zip(msgs, whats)):
        heads[j], w = _parse_block(msg, n_vox, what)
        words.append(w)  # of any length: the caller's check names a mismatch
    return heads, words


#: Blocks decoded together (one numpy pass over their words).
_PARSE_BATCH = 256


def scan_voxblox(path: str | os.PathLike, *, keep_layer: str = "tsdf") -> VoxbloxIndex:
    """Read a voxblox file once: find its TSDF layer (the first; other layers of the file are skipped), check
    every block, and return where each block is and the range of its observed distances.

    Raises:
        InputNotFoundError: no such file.
        FormatError: not a voxblox layer file, no TSDF layer (naming the layers there are), a truncated
            stream, a block whose voxel count, size or origin does not match the layer, duplicate blocks.
    """
    p = Path(path)
    if not p.is_file():
        raise InputNotFoundError(f"no voxblox file at {p}")
    size = p.stat().st_size
    what = str(p)
    found: list[str] = []
    # flat machine integers, not Python lists of ints and tuples (about 150 bytes a block at 10^6 blocks)
    offsets, lengths, index = array.array("q"), array.array("q"), array.array("q")
    stats = {"lo": np.inf, "hi": -np.inf, "observed": 0, "wmax": 0.0}
    pending: list[tuple[int, int, bytes]] = []
    current = None

    def flush() -> None:
        _, vs, vps, kind = current
        names = [f"{what}: block {i - 1}" for i, _, _ in pending]
        heads, words = _parse_blocks([m for _, _, m in pending], vps ** 3, names)
        for (i, off, msg), fields, w, name in zip(pending, heads, words, names):
            dist, weight = _check_block(fields, w, vs, vps, kind, name)
            index.extend(_block_index(fields, vs, vps, name))
            offsets.append(off)
            lengths.append(len(msg))
            seen = weight > 0
            if seen.any():
                d = dist[seen]
                if not np.isfinite(d).all():
                    raise FormatError(f"{name} has an observed voxel whose distance is NaN/Inf")
                stats["lo"], stats["hi"] = min(stats["lo"], float(d.min())), max(stats["hi"], float(d.max()))
                stats["observed"] += int(seen.sum())
                stats["wmax"] = max(stats["wmax"], float(weight.max()))
        pending.clear()

    with open(p, "rb") as f:
        for layer, i, off, msg in _messages(f, size, what):
            if i == 0:
                if current is not None:
                    break  # the TSDF layer is complete; later layers are not ours
                fields, _ = _fields(msg, f"{what}: layer header {layer}")
                vs, vps = fields.get(1, [None])[-1], fields.get(2, [None])[-1]
                kind = _layer_type(fields, msg)
                if not isinstance(vs, float) or not np.isfinite(vs) or vs <= 0 or not isinstance(vps, int):
                    raise FormatError(f"{what}: layer {layer} has no valid voxel_size / voxels_per_side (not a "
                                      "voxblox layer file?)")
                if not 0 < vps <= MAX_VOXELS_PER_SIDE:
                    raise FormatError(f"{what}: layer {layer} claims {vps} voxels per side (absurd; at most "
                                      f"{MAX_VOXELS_PER_SIDE})")
                found.append(kind)
                if kind == keep_layer or kind.startswith("legacy-"):
                    current = (layer, float(vs), int(vps), kind)
                continue
            if current is None or layer != current[0]:
                continue  # a block of a layer we skip
            pending.append((i, off, msg))
            if len(pending) >= _PARSE_BATCH:
                flush()
        if pending:
            flush()
    if current is None:
        raise FormatError(f"{what} holds no TSDF layer (its layers: {', '.join(found) or 'none'}); only TSDF "
                          "layers can be imported (an ESDF, occupancy or intensity layer is not a TSDF)")
    bi = np.frombuffer(index, dtype=np.int64).reshape(-1, 3).copy()
    if len(bi) and len(np.unique(bi, axis=0)) != len(bi):
        raise FormatError(f"{what}: the TSDF layer holds the same block twice (a corrupt file)")
    observed = stats["observed"]
    return VoxbloxIndex(path=p, voxel_size=current[1], voxels_per_side=current[2], layer_type=current[3],
                        offsets=np.frombuffer(offsets, dtype=np.int64).copy(),
                        lengths=np.frombuffer(lengths, dtype=np.int64).copy(),
                        block_index=bi, d_range=None if observed == 0 else (stats["lo"], stats["hi"]),
                        observed=observed, weight_max=stats["wmax"])


def _check_block(fields: dict[int, list], words: np.ndarray, vs: float, vps: int, kind: str,
                 what: str) -> tuple[np.ndarray, np.ndarray]:
    """The block's distances and weights ``(vps ** 3,)`` float32 (voxblox order), after checking it against its
    layer."""
    n_vox = vps ** 3
    bvps = fields.get(1, [vps])[-1]
    bvs = fields.get(2, [vs])[-1]
    if bvps != vps or not isinstance(bvs, float) or abs(bvs - vs) > 1e-9 * vs:
        raise FormatError(f"{what} has {bvps} voxels per side of {bvs} m, its layer {vps} of {vs} m")
    if len(words) != 3 * n_vox:
        per = len(words) / n_vox
        if kind.startswith("legacy-") and len(words) == 2 * n_vox:
            raise FormatError(f"{what} holds 2 words per voxel: an ESDF, occupancy or intensity layer, not a TSDF "
                              "(only TSDF layers can be imported)")
        raise FormatError(f"{what} holds {len(words)} voxel words, a TSDF block of {vps}^3 voxels has {3 * n_vox} "
                          f"({per:.3g} per voxel instead of 3): voxel count mismatch")
    w = words.reshape(n_vox, 3)
    dist = np.ascontiguousarray(w[:, 0]).view(np.float32)
    weight = np.ascontiguousarray(w[:, 1]).view(np.float32)
    if not np.isfinite(weight).all() or (weight < 0).any():
        raise FormatError(f"{what} has a negative or NaN/Inf weight")
    return dist, weight


def _block_index(fields: dict[int, list], vs: float, vps: int, what: str) -> tuple[int, int, int]:
    """The block's index on the block lattice, from its origin (refused when it is off the lattice)."""
    origin = [fields.get(k, [0.0])[-1] for k in (3, 4, 5)]
    if not all(isinstance(o, float) and np.isfinite(o) for o in origin):
        raise FormatError(f"{what} has no valid origin")
    q = np.asarray(origin) / (vps * vs)
    r = np.round(q)
    if np.abs(q - r).max() > 1e-4 or np.abs(r).max() > 2**40:
        raise FormatError(f"{what} lies at {origin} m, not on its layer's block lattice ({vps * vs} m)")
    return int(r[0]), int(r[1]), int(r[2])


def read_voxblox_blocks(index: VoxbloxIndex, ids: np.ndarray, f: BinaryIO | None = None
                        ) -> tuple[np.ndarray, np.ndarray]:
    """Distances and weights ``(len(ids), n, n, n)`` float32 of blocks ``ids`` of a scanned file, voxels
    indexed ``(x, y, z)`` (voxblox stores x fastest). ``f``: the file, open (else opened here)."""
    n = index.voxels_per_side
    ids = np.asarray(ids, dtype=np.int64)
    dist = np.empty((len(ids), n, n, n), dtype=np.float32)
    weight = np.empty_like(dist)
    own = f is None
    f = open(index.path, "rb") if own else f
    try:
        order = np.argsort(index.offsets[ids], kind="stable")  # through the file front to back
        for lo in range(0, len(ids), _PARSE_BATCH):
            sel = order[lo:lo + _PARSE_BATCH]
            msgs, names = [], []
            for i in ids[sel]:
                f.seek(int(index.offsets[i]))
                msg = f.read(int(index.lengths[i]))
                names.append(f"{index.path}: block {int(i)}")
                if len(msg) != index.lengths[i]:
                    raise FormatError(f"truncated stream: {names[-1]} (the file changed since it was scanned?)")
                msgs.append(msg)
            heads, words = _parse_blocks(msgs, n ** 3, names)
            for k, fields, w, name in zip(sel, heads, words, names):
                d, wt = _check_block(fields, w, index.voxel_size, n, index.layer_type, name)
                # voxblox's order is x + n (y + n z): as a C-order (z, y, x) array, transposed to (x, y, z)
                dist[k] = d.reshape(n, n, n).transpose(2, 1, 0)
                weight[k] = wt.reshape(n, n, n).transpose(2, 1, 0)
    finally:
        if own:
            f.close()
    return dist, weight


def _encode_varints(vals: np.ndarray) -> np.ndarray:
    """Varint bytes ``(m,)`` uint8 of values ``(n,)`` (uint64, each below 2^32), back to back."""
    v = vals.astype(np.uint64)
    lens = np.ones(len(v), dtype=np.int64)
    for k in (7, 14, 21, 28):
        lens += v >= np.uint64(1 << k)
    ends = np.cumsum(lens)
    starts = ends - lens
    out = np.empty(int(ends[-1]) if len(v) else 0, dtype=np.uint8)
    for k in range(5):
        sel = np.flatnonzero(lens > k)
        if not len(sel):
            break
        byte = (v[sel] >> np.uint64(7 * k)) & np.uint64(0x7F)
        cont = (lens[sel] > k + 1).astype(np.uint64) << np.uint64(7)
        out[starts[sel] + k] = (byte | cont).astype(np.uint8)
    return out


def _varint_bytes(n: int) -> bytes:
    return _encode_varints(np.asarray([n], dtype=np.uint64)).tobytes()


def _layer_message(voxel_size: float, vps: int) -> bytes:
    t = b"tsdf"
    return (b"\x09" + struct.pack("<d", voxel_size) + b"\x10" + _varint_bytes(vps)
            + b"\x1a" + _varint_bytes(len(t)) + t)


def encode_block(block_index: np.ndarray, dist: np.ndarray, weight: np.ndarray, voxel_size: float) -> bytes:
    """One length-prefixed TSDF ``BlockProto`` (as voxblox writes it: unpacked voxel words, colour 0) of the block
    at index ``block_index`` ``(3,)`` with distances and weights ``(n, n, n)`` float32 indexed ``(x, y, z)``."""
    n = dist.shape[0]
    words = np.zeros((n ** 3, 3), dtype=np.uint32)
    words[:, 0] = np.ascontiguousarray(dist.transpose(2, 1, 0), dtype=np.float32).reshape(-1).view(np.uint32)
    words[:, 1] = np.ascontiguousarray(weight.transpose(2, 1, 0), dtype=np.float32).reshape(-1).view(np.uint32)
    vals = np.empty(2 * words.size, dtype=np.uint64)
    vals[0::2] = _TAG_VOXEL_DATA
    vals[1::2] = words.reshape(-1)
    origin = np.asarray(block_index, dtype=np.float64) * (n * voxel_size)
    head = (b"\x08" + _varint_bytes(n) + b"\x11" + struct.pack("<d", voxel_size)
            + b"\x19" + struct.pack("<d", origin[0]) + b"\x21" + struct.pack("<d", origin[1])
            + b"\x29" + struct.pack("<d", origin[2]) + b"\x30\x01")
    msg = head + _encode_varints(vals).tobytes()
    return _varint_bytes(len(msg)) + msg


def write_voxblox(out: BinaryIO, voxel_size: float, voxels_per_side: int, n_blocks: int,
                  body: BinaryIO) -> None:
    """Write a TSDF layer to ``out``: its message count (``n_blocks + 1``), its header, then the ``n_blocks``
    block messages already written (by :func:`encode_block`) to the file ``body``, copied in pieces."""
    out.write(_varint_bytes(n_blocks + 1))
    layer = _layer_message(float(voxel_size), int(voxels_per_side))
    out.write(_varint_bytes(len(layer)) + layer)
    body.seek(0)
    while True:
        piece = body.read(1 << 22)
        if not piece:
            break
        out.write(piece)
