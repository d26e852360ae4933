"""The read side of variable-rate codes (extension ``variable-rate-codes``, spec section 4e): the array
``code_streams`` that holds them, the decode of a chunk's stream back into integer codes and dequantised float
codes, zero beyond each block's prefix (:class:`VariableRateReader`), and the decode of a group of blocks in runs
of like prefix lengths (:func:`decode_runs`). The writer's pass, rate control and streams' layout are in
:mod:`sdfcodec.map.varrate`.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from ..core import ans
from ..core._lazy import lazy_module
from ..core._validate import BLOCK, empty
from ..core.header import BlockState, VariableRate
from ..core.varrate import EntropyModel, decode_chunk
from ..errors import FormatError, InvalidValueError
from .format import check_stream_array
from .grouping import ChunkCache, chunk_box, each_chunk

if TYPE_CHECKING:
    from .placement import BlockPlacer
    from .reader import MapReader

torch = lazy_module("torch")

__all__ = ["STREAM_ARRAY", "VariableRateReader", "CACHED_CODE_CHUNKS", "RUN_WIDTH", "RUN_MERGE", "prefix_lengths",
           "decode_runs"]

#: The array of a variable-rate map's code streams: one row per chunk of ``codes`` (spec section 4e).
STREAM_ARRAY = "code_streams"


class VariableRateReader:
    """Reads the dequantised codes of coded blocks of a variable-rate map (``reader``: a MapReader)."""

    def __init__(self, reader: MapReader, spec: VariableRate):
        self.reader, self.spec = reader, spec
        self.model = EntropyModel.unpack(spec.model, reader.header.codes.size)
        self.step = np.broadcast_to(np.asarray(spec.step, np.float64), (reader.header.codes.size,))
        arr = reader.member(STREAM_ARRAY)
        h = reader.header
        cb = h.codes.chunk_blocks
        cgrid = tuple(-(-n // cb) for n in h.grid_blocks)
        check_stream_array(reader, arr, STREAM_ARRAY, "4e", f"map has variable-rate codes but lacks array "
                           f"'{STREAM_ARRAY}'")
        self.arr, self.cb, self.cgrid = arr, cb, cgrid
        self._states = None
        self._cache = ChunkCache(CACHED_CODE_CHUNKS)  # ((chunk, level) -> (local coords, integer codes))

    def states(self) -> np.ndarray:
        if self._states is None:
            self._states = self.reader.block_states()
        return self._states

    def codes_for(self, coords: np.ndarray, level: int) -> np.ndarray:
        """``(n, level)`` float32 dequantised codes of coded blocks ``coords`` ``(n, 3)``: each chunk they lie in
        is read and decoded once."""
        out = np.zeros((len(coords), level), np.float32)
        if not len(coords):
            return out
        cb = self.cb
        keys, inverse = np.unique(coords // cb, axis=0, return_inverse=True)
        inverse = inverse.reshape(-1)
        states = self.states()
        for i, (key, (local, q)) in enumerate(zip(keys, self.chunk_codes(keys, level))):
            index = np.full(tuple(min(cb, g - int(c) * cb) for c, g in zip(key, states.shape)), -1, np.int64)
            index[tuple(local.T)] = np.arange(len(local))
            sel = np.flatnonzero(inverse == i)
            r = index[tuple((coords[sel] - key * cb).T)]
            if (r < 0).any():
                raise InvalidValueError("codes_for was asked for a block that is not coded")
            out[sel] = q[r] * self.step[:level]
        return out

    def chunk_codes(self, keys: np.ndarray, level: int) -> list[tuple[np.ndarray, np.ndarray]]:
        """Per chunk of ``keys`` ``(m, 3)``: (its coded blocks' coordinates relative to the chunk ``(n, 3)``, C
        order, the integer codes ``(n, level)`` int32 of its stream). The last :data:`CACHED_CODE_CHUNKS` chunks
        decoded are kept: a pinned mask read right after the field's (or before it) decodes each stream once.
        The streams not kept are decoded on the read threads (:func:`~sdfcodec.map.grouping.each_chunk`)."""
        names = [(tuple(int(c) for c in k), level) for k in keys]
        # the cached chunks held from the start: decoding more than CACHED_CODE_CHUNKS others evicts them
        out = {i: self._cache[name] for i, name in enumerate(names) if name in self._cache}
        todo = [i for i in range(len(keys)) if i not in out]
        rows = self.reader.read_rows(self.arr, [keys[i] for i in todo])
        if len(todo) > 1:  # what every thread's decode reads, made once before they start
            self.states()
            if ans.available():
                self.model.cdfs()
        for i, got in zip(todo, each_chunk(lambda job: self._decode(keys[job[0]], job[1], level), zip(todo, rows))):
            out[i] = got
            self._cache.put(names[i], got)
        return [out[i] for i in range(len(keys))]

    def _decode(self, key: np.ndarray, row: np.ndarray, level: int) -> tuple[np.ndarray, np.ndarray]:
        """(coded blocks ``(n, 3)`` relative to chunk ``key``, integer codes ``(n, level)``) from its stored ``row``."""
        cb, states = self.cb, self.states()
        box = chunk_box(key, cb, states.shape)
        local = np.argwhere(states[box] == BlockState.CODED)
        row = np.ascontiguousarray(row.reshape(-1))
        nw = int(row[:4].view("<u4")[0])
        if nw == 0 or 4 + 4 * nw > len(row):
            raise FormatError(f"{self.reader.location}: chunk {tuple(int(c) for c in key)} of array "
                              f"'{STREAM_ARRAY}' holds no stream (or a truncated one) but {len(local)} coded "
                              "block(s) lie in it; the map is incomplete there: restore it from a copy or "
                              "re-encode")
        try:
            q = decode_chunk(row[4:4 + 4 * nw].view("<u4"), len(local), self.model, level)
        except Exception as e:  # a checksum-valid but inconsistent stream
            raise FormatError(f"{self.reader.location}: the stream of chunk {tuple(int(c) for c in key)} of "
                              f"array '{STREAM_ARRAY}' does not decode ({e}); the map is corrupted there") from e
        return local, q


#: Chunks of integer codes a reader keeps decoded (4 B per element): see :meth:`VariableRateReader.chunk_codes`.
CACHED_CODE_CHUNKS = 8


#: Prefix lengths decoded together are rounded up to a multiple of this: runs of blocks of like lengths decode
#: their own prefix, not the longest of the group (a pca-128 map's blocks keep 60-120 elements).
RUN_WIDTH = 16
#: A run joins the next (wider) one when decoding its blocks at that width costs fewer extra code elements than
#: this (about 0.3 ms of matrix product on 2 cores): each run is a call of its own (a product, the mask's restore,
#: the bound check), and on a small map (the kitchen half's 196 blocks made 8 runs) those calls, not the
#: arithmetic, were the decode; a large group's runs of hundreds of blocks stay apart.
RUN_MERGE = 2048


def prefix_lengths(codes: Any) -> np.ndarray:
    """``(n,)`` int64: each row's prefix length (last non-zero element + 1) of codes ``(n, L)`` (numpy or a tensor)."""
    nz = np.asarray(codes.cpu() if hasattr(codes, "cpu") else codes) != 0
    return np.where(nz.any(axis=1), nz.shape[1] - np.argmax(nz[:, ::-1], axis=1), 0)


def decode_runs(reader: MapReader, codes: Any, coords: np.ndarray, rows: np.ndarray | None, out: Any,
                placer: BlockPlacer, metres: bool, refine: bool = True, refine_rows: np.ndarray | None = None,
                unmasked: bool = False) -> Any:
    """:meth:`MapReader.decode_codes` of a group whose blocks are sorted by prefix length: each run of blocks whose
    lengths round up to the same multiple of :data:`RUN_WIDTH` decodes only that prefix (into its slice of
    ``out``, or placed by ``placer``); the decodes in the group's order, or None with a placer. ``unmasked``:
    as decode_codes."""
    k = prefix_lengths(codes)
    width = np.maximum(-(-k // RUN_WIDTH) * RUN_WIDTH, RUN_WIDTH).clip(max=codes.shape[1])
    bounds = np.r_[0, np.flatnonzero(np.diff(width)) + 1, len(k)]
    runs: list[list[int]] = []  # [start, stop, width], widths increasing
    for a, b in zip(bounds[:-1], bounds[1:]):
        if a == b:
            continue
        w = int(width[a])
        if runs and (runs[-1][1] - runs[-1][0]) * (w - runs[-1][2]) < RUN_MERGE:
            runs[-1][1:] = [int(b), w]
        else:
            runs.append([int(a), int(b), w])
    if out is None and placer is None and len(runs) > 1:  # one buffer, each run decoded into its slice
        out = empty((len(k), BLOCK, BLOCK, BLOCK), codes.device)
    parts = []
    cpu = codes.device.type == "cpu"
    for a, b, w in runs:
        # numpy's copy on the CPU: torch's threaded one waits for the BLAS threads still spinning (16 ms a group)
        run = torch.from_numpy(np.ascontiguousarray(codes.numpy()[a:b, :w])) if cpu else codes[a:b, :w].contiguous()
        part = reader.decode_codes(run, metres=metres, coords=coords[a:b],
                                   mask_rows=None if rows is None else rows[a:b],
                                   out=None if out is None else out[a:b], placer=placer, refine=refine,
                                   refine_rows=None if refine_rows is None else refine_rows[a:b],
                                   unmasked=unmasked)
        parts.append(part)
    if placer is not None:
        return None
    return out if out is not None else parts[0]
