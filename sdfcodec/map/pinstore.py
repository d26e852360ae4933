"""The pinned observation mask in a map (extension ``pinned-observation-mask``, spec/map-format.md section 6g):
one ``M2`` stream (:mod:`sdfcodec.map.pinmask`) per chunk of codes, in the array ``mask_streams``, written by
the variable-rate writer (:class:`PinnedStreams`) and read through :class:`PinnedMaskArray`, which stands in
for the ``observed`` array (packed rows of 512 bytes per block) wherever a reader reads mask rows.

A chunk's stream decodes from the chunk's own codes and the block states: the pinned voxels of its coded
blocks come from their exact decode (a coded block of another chunk may take either sign there), so a region
still reads only its chunks.
"""

from __future__ import annotations

import json
from typing import TYPE_CHECKING, Any, Callable

import numpy as np

from ..codec import numpy_decode_affine
from ..core._validate import BLOCK
from ..core.header import PINNED_MASK_EXTENSION, BlockState
from ..errors import FormatError, InvalidValueError
from . import pinmask as pm
from . import pinread
from .format import check_stream_array, decoded_range
from .grouping import ChunkCache, chunk_box, each_chunk, read_threads, thread_shares
from .metric import decode_affine

if TYPE_CHECKING:
    from ..codec import Codec
    from .reader import MapReader

__all__ = ["PINNED_ARRAY", "PINNED_MASK_EXTENSION", "linear_basis", "map_basis", "chunk_blocks", "PinnedStreams",
           "PinnedMaskArray"]

#: The array of the streams: ``(Cx, Cy, Cz, L)`` uint8, one row per chunk of codes: the stream's length
#: (uint32 LE), the stream, zeros (as ``code_streams``, spec section 4e).
PINNED_ARRAY = "mask_streams"

#: Decoded chunks a reader keeps (512 B per coded block each): a region read block group by block group decodes
#: each chunk's stream once.
CACHED_CHUNKS = 8
_OFFSETS = np.array([(a, b, c) for a in (-1, 0, 1) for b in (-1, 0, 1) for c in (-1, 0, 1)
                     if (a, b, c) != (0, 0, 0)], dtype=np.int64)


def linear_basis(codec: Codec, step: Any, size: int, truncation: tuple[float, float]) -> np.ndarray | None:
    """:func:`~sdfcodec.map.pinmask.fixed_point_basis` of a codec whose decode is ``mean + codes components``
    (pca with a dataset mean), for codes of length ``size`` with steps ``step``; None for any other codec."""
    if getattr(codec, "mean", None) != "dataset":
        return None
    sd = codec.state_dict()
    if "components" not in sd or "mean" not in sd:
        return None
    step = np.broadcast_to(np.asarray(step, np.float64), (size,))
    return pm.fixed_point_basis(np.asarray(sd["components"])[:size], sd["mean"], step, truncation)


def map_basis(reader: MapReader) -> np.ndarray | None:
    """:func:`linear_basis` of the map ``reader`` reads (its codec, variable-rate steps, code size and truncation),
    the same array for every map whose codec state has the same digest (a shipped model referenced by many maps,
    or one map opened again): the last :data:`CACHED_BASES` kept, read-only."""
    h = reader.header
    digest = h.codec.state_sha256
    key = None if digest is None else (h.codec.id, json.dumps(h.codec.config, sort_keys=True, default=str), digest,
                                       np.asarray(h.codes.variable_rate.step, np.float64).tobytes(), h.codes.size,
                                       tuple(float(t) for t in reader.truncation))
    got = _BASES.get(key) if key is not None else None
    if got is None:
        got = linear_basis(reader.codec, h.codes.variable_rate.step, h.codes.size, reader.truncation)
        if got is not None and key is not None:  # a state checked against its digest when the codec was loaded
            got.flags.writeable = False
            _BASES.put(key, got)
    return got


#: Bases :func:`map_basis` keeps (4 MB each for a pca-128 codec).
CACHED_BASES = 2
_BASES = ChunkCache(CACHED_BASES)


def chunk_blocks(states: np.ndarray, key: np.ndarray, cb: int) -> tuple[np.ndarray, np.ndarray]:
    """``(coords (n, 3), outside (m, 3))``: the coded blocks of chunk ``key`` in C order (the order of its
    stream), and the coded blocks of other chunks that touch them."""
    lo = np.asarray(key, np.int64) * cb
    box = tuple(slice(int(a), int(a) + cb) for a in lo)
    coords = np.argwhere(states[box] == BlockState.CODED) + lo
    # the blocks around them, marked in the chunk's box grown by one (argwhere: C order, as a sort would give)
    hull = np.zeros(tuple(s.stop - s.start + 2 for s in box), bool)
    hull[tuple((coords[:, None, :] - lo + 1 + _OFFSETS[None]).reshape(-1, 3).T)] = True
    hull[tuple(slice(1, s.stop - s.start + 1) for s in box)] = False  # the chunk's own blocks
    near = np.argwhere(hull) + lo - 1
    near = near[((near >= 0) & (near < np.asarray(states.shape))).all(axis=1)]
    return coords, near[states[tuple(near.T)] == BlockState.CODED]


def _kernels():
    """:mod:`sdfcodec.core.pinkernels` where numba is installed, else None."""
    from ..core import ans

    if not ans.available():
        return None
    from ..core import pinkernels

    return pinkernels


def _zstd(row: np.ndarray) -> bytes:
    """``row`` as zarr's ``zstd`` codec at level 1 stores it (numcodecs' Zstd, no checksum)."""
    from numcodecs.zstd import Zstd

    return bytes(Zstd(level=1).encode(row))


class PinnedStreams:
    """The ``M2`` streams of a map's coded blocks ``coords`` ``(n, 3)`` (grouped by chunk, C order inside each:
    the writer's order) with true mask ``truth`` ``(n, 16, 16, 16)``, for integer codes given to :meth:`at`
    (``basis_for(step)``: :func:`linear_basis` at those steps):
    ``bytes`` what their chunks take, :meth:`write` stores them."""

    def __init__(self, coords: np.ndarray, truth: np.ndarray, states: np.ndarray, cb: int,
                 basis_for: Callable[[np.ndarray], np.ndarray], truncation: tuple[float, float]):
        self.coords, self.truth, self.states, self.cb = np.asarray(coords, np.int64), truth, states, cb
        self.basis_for, self.truncation = basis_for, truncation
        self.keys, self.inverse = np.unique(self.coords // cb, axis=0, return_inverse=True)
        self.inverse = self.inverse.reshape(-1)
        self.plans = [chunk_blocks(states, k, cb) for k in self.keys]
        self.streams: list[bytes] = []
        self.bytes = 0
        #: ``(rows, v, bound) -> (v, bound)``: the refined exact field of those rows (spec 6h), or None
        self.refined: Callable | None = None
        #: whether :meth:`at` chooses the unobserved free bits too (:func:`~sdfcodec.map.pinmask.chosen_bits`:
        #: about 1 B per coded block less on the kitchen half, at three times the mask's cost; the variable-rate
        #: writer turns it on for the last rounds of its step search at low byte targets)
        self.choose = False

    def at(self, q: np.ndarray, step: np.ndarray) -> None:
        """``q`` ``(n, k)`` integer codes of the blocks, in ``coords``' order, with steps ``step``."""
        q, basis = np.asarray(q), self.basis_for(step)
        index = {tuple(c): i for i, c in enumerate(self.coords)}
        self.streams = []
        for i, (own, outside) in enumerate(self.plans):
            sel = np.flatnonzero(self.inverse == i)
            if not np.array_equal(self.coords[sel], own):
                raise InvalidValueError("PinnedStreams needs the coded blocks grouped by chunk, in C order inside each")
            near = np.array([index[tuple(c)] for c in outside], np.int64)
            both = np.r_[sel, near]
            v, bound = pm.exact_decode(q[both], basis)  # E of the codes' length D (spec 6g)
            if self.refined is not None:  # a surface refinement's field decides the pins (spec 6h)
                v, bound = self.refined(both, v, bound)
            neg, pos = pm.sign_bounds(v, bound)  # the neighbours' true decode: exact bits at the chunk's faces
            bits = pm.canonical_bits(self.coords[both], self.truth[both], neg, pos, self.truncation)[:len(sel)]
            pins = pm.pinned_voxels_of(own, neg[:len(sel)], pos[:len(sel)], outside, self.truncation)
            # the truly observed voxels the canonical bits leave 0 are free: the coder's likelier value; with
            # ``choose``, every pinned voxel they leave 0 where a 1 meshes nothing new, by the stream's length
            bits = pm.cheapest_bits(own, bits, self.truth[sel] & ~bits, pins)
            if self.choose:
                _, negp, posp = pm.exact_pins(self.coords[both], neg, pos, np.zeros((0, 3), np.int64),
                                              self.truncation)
                bits = pm.chosen_bits(own, bits, pins, negp[:len(sel)], posp[:len(sel)], outside, self.truncation,
                                      start=bits)
            self.streams.append(pm.encode_pinned(own, bits, pins))
        self.bytes = sum(len(_zstd(r)) + 4 for r in self._rows())  # each row as stored: zstd level 1, CRC32C

    def _rows(self) -> list[np.ndarray]:
        """Per chunk with coded blocks its row: the stream's length (uint32 LE), the stream, zeros."""
        width = 4 + max((len(s) for s in self.streams), default=0)
        rows = []
        for s in self.streams:
            row = np.zeros(width, np.uint8)
            row[:4] = np.frombuffer(np.uint32(len(s)).astype("<u4").tobytes(), np.uint8)
            row[4:4 + len(s)] = np.frombuffer(s, np.uint8)
            rows.append(row)
        return rows

    def write(self, group: Any, compressors: list) -> None:
        """Create ``mask_streams`` in ``group`` (chain ``compressors``) with the streams of the last :meth:`at`."""
        cgrid = tuple(-(-n // self.cb) for n in self.states.shape)
        rows = self._rows()
        width = len(rows[0]) if rows else 4
        arr = group.create_array(PINNED_ARRAY, shape=(*cgrid, width), dtype="uint8", fill_value=0,
                                 chunks=(1, 1, 1, width), compressors=compressors)
        arr = arr.with_config({"write_empty_chunks": True})
        for key, row in zip(self.keys, rows):
            arr[(*(int(k) for k in key), slice(None))] = row


class PinnedMaskArray:
    """Stands in for the ``observed`` array of a map with a pinned mask (``reader``: a MapReader whose header
    lists ``pinned-observation-mask``): ``shape``, ``chunks`` and ``dtype`` of the packed mask, and
    :meth:`block_rows`."""

    def __init__(self, reader: MapReader):
        h = reader.header
        cb = h.codes.chunk_blocks
        arr = reader.member(PINNED_ARRAY)
        check_stream_array(reader, None if h.codes.variable_rate is None else arr, PINNED_ARRAY, "6g",
                           f"map lists {PINNED_MASK_EXTENSION} but lacks array '{PINNED_ARRAY}' or variable-rate codes")
        self.reader, self.streams, self.cb = reader, arr, cb
        self.shape = (*h.grid_blocks, BLOCK ** 3 // 8)
        self.chunks = (cb, cb, cb, BLOCK ** 3 // 8)
        self.dtype = np.dtype(np.uint8)
        self.path = PINNED_ARRAY
        self._basis: np.ndarray | None = None
        self._cache = ChunkCache(CACHED_CHUNKS)  # decoded chunks: (row index, packed rows, packed pinned voxels)

    def basis(self) -> np.ndarray:
        if self._basis is None:
            h, r = self.reader.header, self.reader
            self._basis = map_basis(r)
            if self._basis is None:
                raise FormatError(f"{r.location}: {PINNED_MASK_EXTENSION} needs a codec whose decode is linear "
                                  f"(pca with a dataset mean); this map's is {h.codec.id!r}")
        return self._basis

    def _decode(self, key: np.ndarray, row: np.ndarray, states: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(row index (cb, cb, cb) int64 of each block of the chunk, -1 where not coded; packed rows (n, 512);
        the pinned voxels' packed rows (n, 512))`` of chunk ``key`` from its stored ``row``."""
        own, outside = chunk_blocks(states, key, self.cb)
        index = np.full((self.cb,) * 3, -1, np.int64)
        if not len(own):
            return index, *(np.zeros((0, BLOCK ** 3 // 8), np.uint8),) * 2
        # the integer codes themselves, decoded once for the field read and the mask (the reader keeps them)
        q = self._codes(key)
        # what the signs are told from (pinread): one float32 product, refined in place for a refined map
        v = self._float_decode(q, own)
        zeros, pins = self._zeros(key, row, own, outside, q, v, np.arange(len(own)))
        mask = np.ones(len(own) * BLOCK ** 3, bool)
        mask[zeros] = False
        index[tuple((own - np.asarray(key, np.int64) * self.cb).T)] = np.arange(len(own))
        return index, np.packbits(mask).reshape(len(own), -1), _packed(pins)  # flat: a block's 4096 bits a row

    def _codes(self, key: np.ndarray) -> np.ndarray:
        """The integer codes ``(n, L)`` of chunk ``key``'s coded blocks (C order), as the field's read keeps them."""
        (_, q), = self.reader.vr.chunk_codes(np.asarray(key, np.int64)[None], self.reader.header.codes.size)
        return q

    def _float_decode(self, q: np.ndarray, coords: np.ndarray) -> np.ndarray | None:
        """``(n, 4096)`` float32 metres: the codec's decode of integer codes ``q`` ``(n, L)`` on the CPU (its
        prefix only), as the field's read decodes them; None without the compiled kernels (pinread: the exact
        decode then)."""
        if _kernels() is None:
            return None
        r = self.reader
        used = max(int(np.flatnonzero(q.any(axis=0)).max(initial=-1)) + 1, 1)
        codes = (q[:, :used] * r.vr.step[:used]).astype(np.float32)  # as codes_for
        fast = numpy_decode_affine(r.codec)
        if fast is not None:  # torch-free (a search of the mask alone need not import it): the same rows, folded
            (d_min, d_max), (scale, offset) = r.truncation, decode_affine(r.header.codes, r.truncation, True)
            v = fast(codes, scale, offset)
            lo, hi = decoded_range(d_max - d_min, d_min)  # in metres, as the read below judges them
            if not v.size or lo <= v.min() and v.max() <= hi:  # else the read below refuses it, naming a block
                return np.clip(v, d_min, d_max, out=v)  # truncated, as decode_codes' metres
        import torch

        v = r.decode_codes(torch.from_numpy(codes), metres=True, coords=coords, residual=False, refine=False,
                           unmasked=True)
        return v.numpy().reshape(len(q), -1)

    def _zeros(self, key: np.ndarray, row: np.ndarray, own: np.ndarray, outside: np.ndarray, q: np.ndarray,
               v: np.ndarray | None, rows: np.ndarray, threads: int = 1) -> tuple[np.ndarray, np.ndarray]:
        """``(the unobserved voxels (b * 4096 + voxel, pinmask.unobserved_voxels), the pinned voxels (rows (n, 16,
        16) uint16 or (n, 16, 16, 16) bool))`` of chunk ``key``'s coded blocks ``own`` from its stored ``row``, its
        integer codes ``q`` and the float decode ``v[rows[b]]`` of block ``b`` (``-1``: not decoded;
        :func:`~sdfcodec.map.pinread.decode_pins`, its blocks split among ``threads``)."""
        r = self.reader
        row = np.ascontiguousarray(np.asarray(row).reshape(-1))
        n = int(row[:4].view("<u4")[0])
        where = f"{r.location}: chunk {tuple(int(c) for c in key)} of array '{PINNED_ARRAY}'"
        if n == 0 or 4 + n > len(row):
            raise FormatError(f"{where} holds no stream (or a truncated one) but {len(own)} coded block(s) lie "
                              "in it; the map is incomplete there: restore it from a copy or re-encode")
        if r.refinement is not None and v is not None and _kernels() is not None:  # spec 6h: pinread, refined
            ref = r.refinement
            pins = pinread.decode_refined_pins(v, rows, q, self.basis(), own, outside, r.truncation, ref.spec.tau,
                                               ref.spec.step, lambda sel: ref.corrections(key, sel), threads)
            return pm.unobserved_voxels(row[4:4 + n].tobytes(), own, pins, where, threads=threads), pins
        if r.refinement is not None:  # without the compiled kernels: every voxel's refined exact field
            v, bound = r.refinement.refined(own, *pm.exact_decode(q, self.basis()))
            neg, pos = pm.sign_bounds(v, bound)
            pins = pm.pinned_voxels_of(own, neg, pos, outside, r.truncation)
            return pm.unobserved_voxels(row[4:4 + n].tobytes(), own, pins, where), pins
        pins = pinread.decode_pins(v, rows, q, self.basis(), own, outside, r.truncation, threads)
        return pm.unobserved_voxels(row[4:4 + n].tobytes(), own, pins, where, threads=threads), pins

    def _zeros_beside(self, key: np.ndarray, row: np.ndarray, own: np.ndarray, outside: np.ndarray, q: np.ndarray,
                      flat: np.ndarray, rows: np.ndarray, unread: np.ndarray, threads: int) -> np.ndarray:
        """:meth:`_zeros` of a chunk whose coded blocks ``unread`` (indices into ``own``) the caller did not decode
        (a region read): those get the float product too, beside the caller's rows copied, so that their signs are
        told from it as the others' are (else every voxel of theirs is decided by its exact decode, ~0.1 ms a
        block: 19 of a 37 ms read of eight blocks of a chunk of 196). The pins are the same either way; of a
        refined map the read blocks' refined decode is copied back into ``flat``."""
        read = np.flatnonzero(rows >= 0)
        v = np.empty((len(own), BLOCK ** 3), np.float32)
        v[read] = flat[rows[read]]
        v[unread] = self._float_decode(q[unread], own[unread])
        zeros, _ = self._zeros(key, row, own, outside, q, v, np.arange(len(own)), threads=threads)
        if self.reader.refinement is not None:
            flat[rows[read]] = v[read]
        return zeros

    def unmask(self, coords: np.ndarray, v: np.ndarray, free: float) -> None:
        """Set the unobserved voxels of ``v`` ``(n, 16, 16, 16)`` float32, the reader's full-level decode in metres
        of coded blocks ``coords`` ``(n, 3)`` (before any residual; truncated or not; of a refined map: truncated,
        without the corrections, which are added here), to ``free``, in place: the pins of each chunk told from
        ``v`` itself (:mod:`sdfcodec.map.pinread`; a chunk's blocks not among ``coords`` by their exact decode)."""
        if not len(coords):
            return
        r, cb = self.reader, self.cb
        states = r.vr.states()
        coords = np.asarray(coords, np.int64)
        keys, inverse = np.unique(coords // cb, axis=0, return_inverse=True)
        inverse = inverse.reshape(-1)
        streams = r.read_rows(self.streams, keys)
        flat = v.reshape(len(v), -1)
        pinkernels = _kernels()
        if r.refinement is not None and pinkernels is None:  # numpy: the corrections added here, pins told exactly
            flat += r.refinement.rows(coords)
            np.clip(flat, *r.truncation, out=flat)
        # compiled: the chunks on every core (the kernels release the GIL; each chunk writes only its blocks' rows
        # of v), each chunk's pins split among its share of them (thread_shares: a chunk of most of the coded blocks
        # gets most of the cores), the largest first; what every thread reads made before they start
        threads = read_threads() if pinkernels is not None else 1
        if threads > 1:
            self.basis()
            if r.refinement is not None:
                r.refinement.model.cdf()
        sizes = [int(np.count_nonzero(states[chunk_box(k, cb, states.shape)] == BlockState.CODED)) for k in keys]
        inner = thread_shares(sizes, threads)

        def chunk(i: int) -> None:
            key = keys[i]
            own, outside = chunk_blocks(states, key, cb)
            sel = np.flatnonzero(inverse == i)
            index = np.full((cb,) * 3, -1, np.int64)
            index[tuple((coords[sel] - key * cb).T)] = sel
            rows = index[tuple((own - key * cb).T)]  # each coded block's row of v, -1 where not read
            q = self._codes(key)
            unread = np.flatnonzero(rows < 0)
            if len(unread) and pinkernels is not None:
                zeros = self._zeros_beside(key, streams[i], own, outside, q, flat, rows, unread, inner[i])
            else:
                zeros, _ = self._zeros(key, streams[i], own, outside, q, flat, rows, threads=inner[i])
            if pinkernels is not None:  # distinct voxels: the zeros' slices on the chunk's threads
                edges = np.linspace(0, len(zeros), inner[i] + 1).astype(np.int64)
                each_chunk(lambda j: pinkernels.set_voxels(flat, rows, zeros[edges[j]:edges[j + 1]],
                                                           np.float32(free)), range(inner[i]), inner[i])
                return
            at = rows[zeros >> 12]
            hit = at >= 0
            flat[at[hit], zeros[hit] & (BLOCK ** 3 - 1)] = free

        each_chunk(chunk, sorted(range(len(keys)), key=lambda i: -sizes[i]), threads)

    def block_rows(self, coords: np.ndarray) -> np.ndarray:
        """``(n, 512)`` uint8 packed mask rows of blocks ``coords`` ``(n, 3)`` (255 where not coded): each chunk
        they lie in is read and decoded once."""
        return self.rows_with_pins(coords)[0]

    def rows_with_pins(self, coords: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(mask rows, pinned rows)``, both ``(n, 512)`` uint8 packed for blocks ``coords`` ``(n, 3)`` (255 where not
        coded): :meth:`block_rows` and the pinned voxels, where the mask is stored (every other voxel reads observed
        whatever the cameras saw), from one decode of each chunk they lie in."""
        out = np.full((2, len(coords), BLOCK ** 3 // 8), 255, np.uint8)
        if not len(coords):
            return out[0], out[1]
        r, cb = self.reader, self.cb
        states = r.vr.states()
        keys, inverse = np.unique(np.asarray(coords, np.int64) // cb, axis=0, return_inverse=True)
        inverse = inverse.reshape(-1)
        names = [tuple(int(c) for c in k) for k in keys]
        got = {k: self._cache[k] for k in names if k in self._cache}
        todo = [i for i, k in enumerate(names) if k not in got]
        rows = r.read_rows(self.streams, [names[i] for i in todo])
        for i, row in zip(todo, rows):
            got[names[i]] = self._decode(keys[i], row, states)
            self._cache.put(names[i], got[names[i]])
        for i, name in enumerate(names):
            index, packed, pins = got[name]
            sel = np.flatnonzero(inverse == i)
            k = index[tuple((np.asarray(coords, np.int64)[sel] - keys[i] * cb).T)]
            out[0, sel[k >= 0]], out[1, sel[k >= 0]] = packed[k[k >= 0]], pins[k[k >= 0]]
        return out[0], out[1]


def _packed(pins: np.ndarray) -> np.ndarray:
    """``(n, 512)`` uint8: pinned voxels as rows ``(n, 16, 16)`` uint16 (bit ``z``: voxel ``z``) or ``(n, 16, 16,
    16)`` bool, packed as the mask's rows are (C order, most significant bit first)."""
    n = len(pins)
    if pins.dtype != bool:  # each uint16 row's two bytes, low first: bits 0-7 are z 0-7, bits 8-15 z 8-15
        pins = np.unpackbits(np.ascontiguousarray(pins, "<u2").view(np.uint8), axis=-1, bitorder="little")
    return np.packbits(pins.reshape(n, -1), axis=1)
