"""Test helpers for voxblox files, written independently of sdfcodec.interop.voxblox: a plain byte-by-byte protobuf
reader and writer (the tests check the importer and exporter against these, not against themselves), and a
generator of large synthetic layers (``python tests/_voxblox_stream.py N OUT`` writes N blocks)."""

from __future__ import annotations

import struct
import sys

import numpy as np

__all__ = ["parse_layers", "layer_voxels", "layer_bytes", "block_message", "synthetic_layer"]


def _uvarint(buf: bytes, pos: int) -> tuple[int, int]:
    out = shift = 0
    while True:
        b = buf[pos]
        pos += 1
        out |= (b & 0x7F) << shift
        if not b & 0x80:
            return out, pos
        shift += 7


def _message(buf: bytes) -> dict[int, list]:
    """Generic protobuf decode: field -> list of values (varint ints, doubles, bytes); packed runs stay bytes."""
    fields: dict[int, list] = {}
    pos = 0
    while pos < len(buf):
        key, pos = _uvarint(buf, pos)
        field, wire = key >> 3, key & 7
        if wire == 0:
            val, pos = _uvarint(buf, pos)
        elif wire == 1:
            val = struct.unpack("<d", buf[pos:pos + 8])[0]
            pos += 8
        elif wire == 2:
            n, pos = _uvarint(buf, pos)
            val = buf[pos:pos + n]
            pos += n
        else:
            raise ValueError(f"wire type {wire}")
        fields.setdefault(field, []).append(val)
    return fields


def parse_layers(data: bytes) -> list[tuple[dict, list[dict]]]:
    """Every layer of a voxblox file: (header fields, [block fields]), voxel words of packed runs expanded."""
    layers, pos = [], 0
    while pos < len(data):
        count, pos = _uvarint(data, pos)
        msgs = []
        for _ in range(count):
            n, pos = _uvarint(data, pos)
            msgs.append(_message(data[pos:pos + n]))
            pos += n
        for b in msgs[1:]:
            words = []
            for v in b.get(7, []):
                if isinstance(v, bytes):
                    p = 0
                    while p < len(v):
                        w, p = _uvarint(v, p)
                        words.append(w)
                else:
                    words.append(v)
            b[7] = words
        layers.append((msgs[0], msgs[1:]))
    return layers


def layer_voxels(header: dict, blocks: list[dict]) -> dict[tuple[int, int, int], tuple[float, float]]:
    """Observed voxels (weight > 0) of a TSDF layer: global voxel index -> (distance, weight) as float32."""
    vps = header[2][0]
    vs = header[1][0]
    out = {}
    for b in blocks:
        origin = [b[k][0] if k in b else 0.0 for k in (3, 4, 5)]
        base = [int(round(o / (vps * vs))) * vps for o in origin]
        words = b[7]
        for lin in range(vps ** 3):
            x, y, z = lin % vps, (lin // vps) % vps, lin // (vps * vps)
            d = struct.unpack("<f", struct.pack("<I", words[3 * lin]))[0]
            w = struct.unpack("<f", struct.pack("<I", words[3 * lin + 1]))[0]
            if w > 0:
                out[(base[0] + x, base[1] + y, base[2] + z)] = (d, w)
    return out


def _varint(n: int) -> bytes:
    out = bytearray()
    while True:
        b = n & 0x7F
        n >>= 7
        out.append(b | (0x80 if n else 0))
        if not n:
            return bytes(out)


def block_message(index, vps: int, vs: float, dist: np.ndarray, weight: np.ndarray, packed: bool = False,
                  n_words: int | None = None) -> bytes:
    """A BlockProto (without its length prefix); ``dist``/``weight`` ``(vps, vps, vps)`` indexed (x, y, z)."""
    d = np.asarray(dist, np.float32).transpose(2, 1, 0).reshape(-1).view(np.uint32)
    w = np.asarray(weight, np.float32).transpose(2, 1, 0).reshape(-1).view(np.uint32)
    words = np.stack([d, w, np.full_like(d, 0x11223344)], 1).reshape(-1).tolist()
    if n_words is not None:
        words = words[:n_words]
    msg = b"\x08" + _varint(vps) + b"\x11" + struct.pack("<d", vs)
    for k, o in zip((0x19, 0x21, 0x29), index):
        msg += bytes([k]) + struct.pack("<d", o * vps * vs)
    msg += b"\x30\x01"
    if packed:
        run = b"".join(_varint(v) for v in words)
        msg += b"\x3a" + _varint(len(run)) + run
    else:
        msg += b"".join(b"\x38" + _varint(v) for v in words)
    return msg


def layer_bytes(vs: float, vps: int, blocks: list[bytes], layer_type: str | int = "tsdf") -> bytes:
    """A whole layer: message count, LayerProto, the block messages."""
    if isinstance(layer_type, str):
        t = layer_type.encode()
        tf = b"\x1a" + _varint(len(t)) + t
    else:
        tf = b"\x18" + _varint(layer_type)
    header = b"\x09" + struct.pack("<d", vs) + b"\x10" + _varint(vps) + tf
    out = _varint(len(blocks) + 1) + _varint(len(header)) + header
    for m in blocks:
        out += _varint(len(m)) + m
    return out


def synthetic_layer(path: str, n_blocks: int, vps: int = 8, vs: float = 0.05, seed: int = 0) -> None:
    """Write a voxblox TSDF layer of ``n_blocks`` blocks (a cube of blocks, 16 payloads of a tilted plane with
    an unobserved corner, cycled) to ``path``, streamed: memory does not grow with ``n_blocks``."""
    rng = np.random.default_rng(seed)
    side = int(np.ceil(n_blocks ** (1 / 3)))
    g = np.indices((vps,) * 3).astype(np.float32)
    payloads = []
    for k in range(16):
        n = rng.normal(size=3)
        n /= np.linalg.norm(n)
        d = np.clip((np.tensordot(n, g - vps / 2, 1) + rng.normal()) * vs, -4 * vs, 4 * vs).astype(np.float32)
        w = np.where(g[0] + g[1] > vps // 2 + k % 4, rng.uniform(0.5, 50, size=d.shape), 0).astype(np.float32)
        payloads.append(block_message((0, 0, 0), vps, vs, d, w))
    header = b"\x09" + struct.pack("<d", vs) + b"\x10" + _varint(vps) + b"\x1a\x04tsdf"
    with open(path, "wb") as f:
        f.write(_varint(n_blocks + 1) + _varint(len(header)) + header)
        # in shuffled order, as voxblox writes its hash map: the importer must not rely on any order
        for i in rng.permutation(n_blocks).tolist():
            x, y, z = i % side - side // 2, (i // side) % side, i // (side * side)
            p = payloads[i % 16]
            head = b"\x08" + _varint(vps) + b"\x11" + struct.pack("<d", vs)
            for key, o in zip((0x19, 0x21, 0x29), (x, y, z)):
                head += bytes([key]) + struct.pack("<d", o * vps * vs)
            # the payload's own header is replaced by this block's (same length: 4 doubles, 2 varints)
            msg = head + p[len(head):]
            f.write(_varint(len(msg)) + msg)


if __name__ == "__main__":
    synthetic_layer(sys.argv[2], int(sys.argv[1]))
