"""The surface refinement of a variable-rate map (required extension ``surface-refinement``, spec/map-format.md
section 6h): integer corrections at the voxels whose exact decode lies near zero (:mod:`sdfcodec.core.refine`),
one entropy-coded stream per chunk of codes in the array ``refine_streams``, written by
:class:`RefinementStreams` (from the variable-rate pass, :mod:`sdfcodec.map.varrate`) and read by
:class:`RefinementReader`, which adds them to every full-level decode and gives the pinned mask (spec 6g) the
refined exact field its pins are decided on.

Why: a pca-128 decode of real maps stops improving at ~3.9 mm Chamfer on the kitchen half whatever the step
(the same 3.86 mm at 192 B and at a step of 0.0015, 261 B, with the exact mask): the basis cannot follow the
surface closer; the values of the voxels next to it can (2-voxel band set to the truth: 0.50 mm).
"""

from __future__ import annotations

from concurrent.futures import Future, ThreadPoolExecutor
from typing import TYPE_CHECKING, Any, Callable

import numpy as np

from ..core import ans
from ..core import refine as cr
from ..core._validate import BLOCK
from ..core.header import REFINEMENT_EXTENSION, BlockState, Refinement
from ..core.varrate import stream_bytes
from ..errors import FormatError
from . import pinmask as pm
from .format import check_stream_array
from .grouping import ChunkCache, chunk_box, read_threads

if TYPE_CHECKING:
    from .reader import MapReader

__all__ = ["REFINE_ARRAY", "REFINEMENT_EXTENSION", "UNIT", "TrueValues", "RefinementStreams", "RefinementReader",
           "tau_for_step"]

REFINE_ARRAY = "refine_streams"
#: Metres per unit of the exact decode, the correction step and tau.
UNIT = 2.0 ** -pm.FRACTION_BITS
_SCALE = 2.0 ** pm.FRACTION_BITS
_ROW_FRAME = 20  # zstd frame and CRC32C of one stored row (as code_streams')
#: Cached decoded chunks of a reader (4 B per voxel of their blocks).
CACHED_CHUNKS = 8
#: Coded blocks the writer's pass decodes at once (about 140 KB each while in work: a peak of ~70 MB, measured).
BATCH_BLOCKS = 512


def tau_for_step(step_m: float, voxel_size: float) -> float:
    """The band (metres) refined at a correction step ``step_m``: one voxel at 8 mm steps, growing to three
    voxels at 1 mm (kitchen half: a fine step pays in the band it can afford; measured table in
    docs/variable-rate.md)."""
    t = np.clip(np.log2(0.008 / step_m) / 3.0, 0.0, 1.0)
    return float(voxel_size * (1.0 + 2.0 * t))


def _limit(step: int) -> int:
    # |c| step below 2^24 units: the reader's float32 correction is exact (spec 6h)
    return int(min(cr.MAX_CORRECTION, ((1 << 24) - 1) // step))


class TrueValues:
    """The true values of the blocks a writer encodes, kept for the refinement in an unlinked temporary file
    (``dir``, default the system's temporary directory: 16.5 KB per block on disk, none in memory; the file is
    gone when :meth:`close` runs or the process ends, however it ends). :meth:`add` blocks as they come,
    :meth:`rows_of` finds coded blocks' rows, ``values`` ``(m, 4096)`` float32 metres and ``observed``
    ``(m, 512)`` uint8 (packed bits, or None) read them (memory maps of the file)."""

    def __init__(self, dir: str | None = None):
        self.dir, self._file, self._coords, self.n = dir, None, [], 0
        self.packed: bool | None = None
        self._view: np.ndarray | None = None

    def add(self, coords: np.ndarray, values: np.ndarray, observed: np.ndarray | None) -> None:
        """Blocks ``coords`` ``(n, 3)`` with true values ``values`` ``(n, 4096)`` float32 metres and mask
        ``observed`` ``(n, ...)`` bool or None (one kind for all blocks); a block added again replaces itself."""
        import tempfile

        if self._file is None:
            self._file = tempfile.TemporaryFile(prefix="sdfcodec-refine-", dir=self.dir)
            self.packed = observed is not None
        rec = np.zeros(len(coords), self._dtype())
        rec["v"] = np.asarray(values, np.float32).reshape(len(coords), -1)
        if self.packed:
            rec["o"] = np.packbits(np.asarray(observed, bool).reshape(len(coords), -1), axis=1)
        self._file.seek(0, 2)
        self._file.write(rec.tobytes())
        self._coords.append(np.asarray(coords, np.int64).reshape(-1, 3))
        self.n += len(coords)
        self._view = None

    def _dtype(self) -> np.dtype:
        return np.dtype([("v", "<f4", BLOCK ** 3)] + ([("o", "u1", BLOCK ** 3 // 8)] if self.packed else []))

    def rows_of(self, coords: np.ndarray, partial: bool = False) -> np.ndarray | None:
        """``(n,)`` int64: the row of each block ``coords`` ``(n, 3)`` (its last :meth:`add`), or None when a block
        was never added (``partial``: -1 for each such block instead; so for indices below 0)."""
        coords = np.asarray(coords, np.int64).reshape(-1, 3)
        if not self.n:
            return np.full(len(coords), -1, np.int64) if partial or not len(coords) else None
        seen = np.concatenate(self._coords)
        dims = np.maximum(seen.max(axis=0), coords.max(axis=0, initial=0)) + 1
        key = np.ravel_multi_index(tuple(seen.T), dims)[::-1]
        uniq, first = np.unique(key, return_index=True)  # first of the reversed: the last added
        known = (coords >= 0).all(axis=1)
        want = np.ravel_multi_index(tuple(np.maximum(coords, 0).T), dims)
        at = np.minimum(np.searchsorted(uniq, want), len(uniq) - 1)
        found = known & (uniq[at] == want)
        if not partial and not found.all():
            return None
        return np.where(found, self.n - 1 - first[at], -1).astype(np.int64)

    def _rec(self) -> np.ndarray:
        if self._view is None:
            self._file.flush()
            self._view = np.memmap(self._file, dtype=self._dtype(), mode="r", shape=(self.n,))
        return self._view

    @property
    def values(self) -> np.ndarray:
        return self._rec()["v"]

    @property
    def observed(self) -> np.ndarray | None:
        return self._rec()["o"] if self.packed else None

    def close(self) -> None:
        """Drop the file (its space comes back at once: it has no name)."""
        self._view = None
        if self._file is not None:
            self._file.close()
            self._file = None


class RefinementStreams:
    """The streams of a map's coded blocks ``coords`` ``(n, 3)`` (grouped by chunk, C order inside each: the
    writer's order) with true values at rows ``rows`` ``(n,)`` of ``store`` (a :class:`TrueValues`), for integer
    codes and steps given to :meth:`at` (``basis_for(step)``: :func:`~sdfcodec.map.pinstore.linear_basis`).
    Works through about :data:`BATCH_BLOCKS` blocks at a time (whole chunks), so its memory does not grow with
    the map's: the corrections go to an unlinked temporary file until the law that codes them is known. After
    :meth:`at`: ``bytes`` (rows as stored), ``spec`` (the header's :class:`Refinement`), :meth:`refined` (the
    pinned mask's hook), :meth:`write`."""

    def __init__(self, coords: np.ndarray, store: TrueValues, rows: np.ndarray, cb: int, grid: tuple,
                 basis_for: Callable[[np.ndarray], np.ndarray], truncation: tuple[float, float]):
        self.coords, self.cb, self.grid = np.asarray(coords, np.int64), cb, grid
        self.store, self.rows = store, np.asarray(rows, np.int64)
        self.basis_for, self.truncation = basis_for, truncation
        chunk = self.coords // cb
        self.bounds = np.r_[0, np.flatnonzero(np.any(np.diff(chunk, axis=0) != 0, axis=1)) + 1, len(self.coords)]
        self.keys = chunk[self.bounds[:-1]] if len(self.coords) else np.zeros((0, 3), np.int64)
        self.bytes, self.spec, self.streams = 0, None, []
        self._rt: tuple[int, int] | None = None
        self._v: tuple | None = None  # (codes' key, exact decode) of a map of one batch
        self._refined: np.ndarray | None = None

    def _corrections(self, idx: np.ndarray, v: np.ndarray, r: int, tau: int
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(clipped v, sel, c)`` of coded blocks ``idx`` (rows of ``coords``) with exact decode ``v``."""
        v = cr.clip_units(v, self.truncation, _SCALE)
        sel = cr.select(v, tau)
        rows = self.rows[idx]
        obs = self.store.observed
        obs = None if obs is None else np.unpackbits(obs[rows], axis=1).astype(bool)
        return v, sel, cr.corrections(self.store.values[rows], obs, v, sel, r, _limit(r), scale=_SCALE)

    def at(self, q: np.ndarray, step: np.ndarray, r_m: float, tau_m: float) -> None:
        """Corrections of step ``r_m`` metres at the voxels within ``tau_m`` metres, for integer codes ``q``
        ``(n, k)`` at steps ``step``."""
        import tempfile

        r = max(int(round(r_m * _SCALE)), 1)
        tau = max(int(round(tau_m * _SCALE)), 1)
        basis, q = self.basis_for(step), np.asarray(q)
        counts = np.zeros(2 * cr.MAX_CORRECTION + 1, np.int64)
        lengths = []
        with tempfile.TemporaryFile(prefix="sdfcodec-refine-", dir=self.store.dir) as spill:
            for a, b, ends in self._batches():
                v = self._decode(q, a, b, basis, step)
                vc, sel, c = self._corrections(np.arange(a, b), v, r, tau)
                # a map of one batch keeps its refined field for the pinned mask's hook (asked for every chunk
                # and its neighbours at each step rate control tries); a larger one computes it there
                self._refined = cr.refine(vc, sel, c, r, self.truncation, _SCALE) if b - a == len(q) else None
                counts += np.bincount(c + cr.MAX_CORRECTION, minlength=len(counts))
                lengths += np.diff(np.r_[0, np.cumsum(sel.sum(axis=1))[ends - a - 1]]).tolist()
                spill.write(c.astype("<i2").tobytes())  # |c| <= MAX_CORRECTION
            nz = np.flatnonzero(counts)
            m = max(int(np.abs(nz - cr.MAX_CORRECTION).max(initial=0)), 1)
            model = cr.CorrectionModel(counts[cr.MAX_CORRECTION - m:cr.MAX_CORRECTION + m + 1])
            spill.seek(0)
            self.streams = [cr.encode_corrections(np.frombuffer(spill.read(2 * n), "<i2"), model) for n in lengths]
        self.spec = Refinement(step=r, tau=tau, model=model.pack())
        self._rt = (r, tau)
        self.bytes = sum(stream_bytes(s) + _ROW_FRAME for s in self.streams)

    def _decode(self, q: np.ndarray, a: int, b: int, basis: np.ndarray, step: np.ndarray) -> np.ndarray:
        """The exact decode of rows ``a:b`` of ``q``; a map of one batch keeps it for the next :meth:`at` (rate
        control tries several refinement steps on the same codes)."""
        whole = a == 0 and b == len(q)
        key = (q.shape, hash(q.tobytes()), tuple(np.broadcast_to(step, q.shape[1:]).tolist())) if whole else None
        if key is not None and self._v is not None and self._v[0] == key:
            return self._v[1]
        v, _ = pm.exact_decode(q[a:b], basis)
        self._v = None if key is None else (key, v)
        return v

    def _batches(self):
        """``(a, b, ends)``: rows ``a:b`` of ``coords``, whole chunks of about :data:`BATCH_BLOCKS` blocks (a
        chunk's at least), ending at rows ``ends``."""
        i, nb = 0, len(self.bounds) - 1
        while i < nb:
            j = i + 1
            while j < nb and self.bounds[j + 1] - self.bounds[i] <= BATCH_BLOCKS:
                j += 1
            yield int(self.bounds[i]), int(self.bounds[j]), self.bounds[i + 1:j + 1]
            i = j

    def refined(self, idx: np.ndarray, v: np.ndarray, bound: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The pinned mask's hook: the refined exact field of blocks ``idx`` (rows of ``coords``) with exact decode
        ``v`` ``(len(idx), 4096)`` (unclipped, as :func:`~sdfcodec.map.pinmask.exact_decode` gives it) at the
        last :meth:`at`, and their bound (one unit more: the reader's float32 sum rounds once, spec 6h)."""
        if self._refined is not None:
            return self._refined[idx], bound + 1.0
        r, tau = self._rt
        v, sel, c = self._corrections(np.asarray(idx, np.int64), v, r, tau)
        return cr.refine(v, sel, c, r, self.truncation, _SCALE), bound + 1.0

    def write(self, group: Any, compressors: list) -> None:
        """Create ``refine_streams`` in ``group`` with the streams of the last :meth:`at`."""
        cgrid = tuple(-(-n // self.cb) for n in self.grid)
        width = max([stream_bytes(s) for s in self.streams], default=4)
        arr = group.create_array(REFINE_ARRAY, shape=(*cgrid, width), dtype="uint8", fill_value=0,
                                 chunks=(1, 1, 1, width), compressors=compressors)
        arr = arr.with_config({"write_empty_chunks": True})
        for key, s in zip(self.keys, self.streams):
            row = np.zeros(width, np.uint8)
            row[:4] = np.frombuffer(np.uint32(len(s)).astype("<u4").tobytes(), np.uint8)
            row[4:4 + 4 * len(s)] = np.frombuffer(s.astype("<u4").tobytes(), np.uint8)
            arr[(*(int(k) for k in key), slice(None))] = row


class RefinementReader:
    """The corrections of a map listing ``surface-refinement`` (``reader``: a MapReader with variable-rate codes
    and a linear codec): :meth:`rows` for the decode, :meth:`refined` for the pinned mask."""

    def __init__(self, reader: MapReader, spec: Refinement):
        h = reader.header
        cb = h.codes.chunk_blocks
        arr = reader.member(REFINE_ARRAY)
        check_stream_array(reader, arr, REFINE_ARRAY, "6h", f"map lists {REFINEMENT_EXTENSION} but lacks array "
                           f"'{REFINE_ARRAY}'")
        self.reader, self.arr, self.cb, self.spec = reader, arr, cb, spec
        self.model = cr.CorrectionModel.unpack(spec.model)
        self._basis: np.ndarray | None = None
        self._cache = ChunkCache(CACHED_CHUNKS)  # chunk -> (index, local coords, sel, corrections): _chunk
        self._ahead: dict[tuple[int, ...], Future] = {}  # chunk -> its (row, symbols decoded ahead): start

    def start(self, coords: np.ndarray) -> None:
        """Decode ahead, on threads of their own, the streams of the chunks holding blocks ``coords`` ``(n, 3)``
        (those not kept), before the selection that tells how many corrections each holds is known (compiled
        only; :func:`sdfcodec.core.refine.corrections_ahead`): a read calls this before its float decode, whose
        selection then finds its corrections decoded."""
        if not ans.available():
            return
        keys = [tuple(int(k) for k in key) for key in np.unique(np.asarray(coords, np.int64) // self.cb, axis=0)]
        keys = [k for k in keys if k not in self._cache and k not in self._ahead]
        if not keys:
            return
        r, cb = self.reader, self.cb
        rows = r.read_rows(self.arr, keys)
        states = r.vr.states()
        self.model.cdf()  # made once, before the threads read it

        def job(key: tuple[int, ...], row: np.ndarray) -> tuple[np.ndarray, Any]:
            row = np.ascontiguousarray(row.reshape(-1))
            nw = int(row[:4].view("<u4")[0])
            if 4 + 4 * nw > len(row):  # _chunk says so
                return row, None
            box = chunk_box(key, cb, states.shape)
            cap = int(np.count_nonzero(states[box] == BlockState.CODED)) * BLOCK ** 3  # the most it can hold
            return row, cr.corrections_ahead(row[4:4 + 4 * nw].view("<u4"), cap, self.model)

        pool = ThreadPoolExecutor(max_workers=min(read_threads(), len(keys)), thread_name_prefix="sdfcodec-refine")
        for key, row in zip(keys, rows):
            self._ahead[key] = pool.submit(job, key, row)
        pool.shutdown(wait=False)  # the jobs run on; the pool's threads end with them

    def basis(self) -> np.ndarray:
        if self._basis is None:
            from .pinstore import map_basis

            r, h = self.reader, self.reader.header
            self._basis = map_basis(r)
            if self._basis is None:
                raise FormatError(f"{r.location}: {REFINEMENT_EXTENSION} needs a codec whose decode is linear "
                                  f"(pca with a dataset mean); this map's is {h.codec.id!r}")
        return self._basis

    def _chunk(self, key: tuple[int, ...], v: np.ndarray | None = None, sel: np.ndarray | None = None
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``(index (cb,)*3 int64 -1 where not coded, local coords (n, 3), sel (n, 4096) bool, c (m,) int32)``;
        ``v``: the exact decode of the chunk's coded blocks (C order) when the caller has it, or ``sel``: their
        selected voxels (the pinned mask's read, :func:`~sdfcodec.map.pinread.decode_refined_pins`)."""
        if key in self._cache:
            return self._cache[key]
        r, cb = self.reader, self.cb
        (local, q), = r.vr.chunk_codes(np.asarray(key, np.int64)[None], r.header.codes.size)
        index = np.full((cb,) * 3, -1, np.int64)
        index[tuple(local.T)] = np.arange(len(local))
        if sel is None or len(sel) != len(local):
            if v is None or len(v) != len(local):
                v, _ = pm.exact_decode(q, self.basis())
            sel = cr.select_unclipped(v, self.spec.tau, r.truncation, _SCALE)
        started = self._ahead.pop(key, None)
        if started is not None:
            row, ahead = started.result()
        else:
            (row,), ahead = r.read_rows(self.arr, [key]), None
        row = np.ascontiguousarray(row.reshape(-1))
        nw = int(row[:4].view("<u4")[0])
        where = f"{r.location}: chunk {key} of array '{REFINE_ARRAY}'"
        if 4 + 4 * nw > len(row) or (nw == 0 and sel.any()):  # a chunk with nothing selected holds no word
            raise FormatError(f"{where} holds no stream (or a truncated one) but {len(local)} coded block(s) lie in "
                              "it; the map is incomplete there: restore it from a copy or re-encode")
        try:
            c = cr.decode_corrections(row[4:4 + 4 * nw].view("<u4"), int(sel.sum()), self.model, ahead)
        except FormatError as e:
            raise FormatError(f"{where}: {e}; the map is corrupted there") from e
        if len(c) and np.abs(c).max() > _limit(self.spec.step):
            raise FormatError(f"{where}: a correction exceeds the limit of spec 6h; the map is corrupted there")
        self._cache.put(key, out := (index, local, sel, c))
        return out

    def _blocks(self, coords: np.ndarray):
        """Per chunk of ``coords`` ``(n, 3)``: (rows of coords in it, their rows in the chunk, the chunk)."""
        coords = np.asarray(coords, np.int64)
        keys, inverse = np.unique(coords // self.cb, axis=0, return_inverse=True)
        inverse = inverse.reshape(-1)
        for i, key in enumerate(keys):
            ch = self._chunk(tuple(int(k) for k in key))
            at = np.flatnonzero(inverse == i)
            k = ch[0][tuple((coords[at] - key * self.cb).T)]
            if (k < 0).any():
                raise FormatError(f"{self.reader.location}: a block asked for is not coded")
            yield at, k, ch

    def corrections(self, key: tuple[int, ...], sel: np.ndarray) -> np.ndarray:
        """``(m,)`` int32: the corrections of chunk ``key``'s selected voxels ``sel`` ``(n, 4096)`` bool (its coded
        blocks in C order, as the caller found them), kept for :meth:`rows`.

        Raises:
            FormatError: as :meth:`check`.
        """
        return self._chunk(tuple(int(k) for k in key), sel=sel)[3]

    def check(self, coords: np.ndarray) -> None:
        """Decode the stream of every chunk holding blocks ``coords`` ``(n, 3)`` (``verify``).

        Raises:
            FormatError: a stream is missing, truncated or does not decode to its voxels' corrections.
        """
        for key in np.unique(np.asarray(coords, np.int64) // self.cb, axis=0):
            self._chunk(tuple(int(k) for k in key))

    def rows(self, coords: np.ndarray) -> np.ndarray:
        """``(n, 4096)`` float32: the corrections in metres of coded blocks ``coords`` ``(n, 3)``, 0 where none."""
        out = np.zeros((len(coords), BLOCK ** 3), np.float32)
        step = np.float32(self.spec.step * UNIT)  # exact: an integer below 2^24 times a power of two
        for at, k, (_, _, sel, c) in self._blocks(coords):
            full = np.zeros(sel.shape, np.float32)
            full[sel] = c.astype(np.float32) * step  # exact in float32: |c| step < 2^24 units
            out[at] = full[k]
        return out

    def refined(self, coords: np.ndarray, v: np.ndarray, bound: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The refined exact field of coded blocks ``coords`` ``(n, 3)`` (exact decode ``v`` ``(n, 4096)``, bound
        ``(n,)``): what the pinned mask decides its pins on (:meth:`RefinementStreams.refined`)."""
        keys = np.unique(np.asarray(coords, np.int64) // self.cb, axis=0)
        if len(keys) == 1:  # a chunk's blocks, as the pinned mask asks: its exact decode is this one
            self._chunk(tuple(int(k) for k in keys[0]), v)
        out = cr.clip_units(v, self.reader.truncation, _SCALE)
        for at, k, (_, _, sel, c) in self._blocks(coords):
            corr = np.zeros(sel.shape, np.float64)
            corr[sel] = c.astype(np.float64) * self.spec.step
            out[at] = cr.clip_units(out[at] + corr[k], self.reader.truncation, _SCALE)
        return out, bound + 1.0
