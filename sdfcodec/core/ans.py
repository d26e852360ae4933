"""The compiled path of the rANS streams (observation masks, variable-rate codes): the same words as constriction
0.5.0's ``AnsCoder`` with ``Bernoulli(perfect=False)`` / ``Categorical(perfect=False)`` models, decoded and
encoded by :mod:`sdfcodec.core.anskernels` (numba, the optional extra ``fast``). Callers check
:func:`available` and keep constriction's path without numba; both read and write the same streams.

The kernels compile on first use and are cached on disk (a few seconds once per machine)."""

from __future__ import annotations

import importlib.util
from collections.abc import Callable
from typing import Any

import numpy as np

from ..errors import FormatError, InvalidValueError  # FormatError is a ValueError, as constriction raises

__all__ = ["symbols_ahead", "available", "Decoder", "decode_mask", "pack_mask", "encode_mask", "encode_bits",
           "wave_order", "wave_order_planes", "decode_planes", "table_cdfs", "decode_chunk", "categorical_cdf",
           "encode", "bernoulli_intervals", "categorical_intervals"]

_TOTAL = 1 << 24  # constriction's default precision: probabilities are multiples of 2^-24
_FOUND: list[bool] = []


def available() -> bool:
    """Whether the compiled path can run here (numba is installed); checked without importing numba."""
    if not _FOUND:
        _FOUND.append(importlib.util.find_spec("numba") is not None)
    return _FOUND[0]


def _k():
    from . import anskernels

    return anskernels


def symbols_ahead(ahead: np.ndarray, n: int) -> tuple[np.ndarray, bool]:
    """The first ``n`` symbols ``(n,)`` int32 of a :meth:`Decoder.categorical_ahead` decode, and whether the coder
    is empty after them: exactly what :meth:`Decoder.categorical` of ``n`` symbols and ``is_empty`` give (past the
    last symbol decoded, when the coder was empty for good, each symbol is the table's first)."""
    flag = _k().AHEAD_EMPTY
    if n <= len(ahead):
        return ahead[:n] & ~flag, bool(n == 0 or ahead[n - 1] & flag)
    done = len(ahead) == 0 or bool(ahead[-1] & flag)  # shorter than n: it stopped empty (n <= its cap)
    return np.concatenate([ahead & ~flag, np.zeros(n - len(ahead), np.int32)]), done


def _words(words: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(words, dtype=np.uint32)


def _refuse(status: int) -> None:  # the chunk decoder's status
    if status == 1:  # constriction's AnsCoder(words) refuses these with this message
        raise FormatError("Invalid compressed data: ANS compressed data never ends in a zero word.")


class Decoder:
    """constriction's ``AnsCoder(words)`` (words uint32, the last read first) for the compiled decoders: pass it
    from one stage of a stream to the next.

    Raises:
        ValueError: the last word is 0 (no coder writes it; constriction refuses such a stream).
    """

    def __init__(self, words: np.ndarray) -> None:
        self.words = np.ascontiguousarray(words, dtype=np.uint32)
        self.st = np.zeros(2, np.uint64)
        if not _k().start(self.words, self.st):
            raise FormatError("Invalid compressed data: ANS compressed data never ends in a zero word.")

    def is_empty(self) -> bool:
        """Whether every word was read and the state is back to 0 (constriction's ``is_empty``)."""
        return int(self.st[0]) == 0

    def categorical(self, n: int, table: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
        """``n`` symbols ``(n,)`` int32 under one ``Categorical(perfect=False)`` law (its tables:
        :func:`categorical_cdf`)."""
        return _k().categorical_decode(self.words, self.st, int(n), table[0], table[1], _SLOT_SHIFT)

    def categorical_ahead(self, cap: int, table: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
        """:meth:`categorical` before the number of symbols is known: up to ``cap`` of them ``(m',)`` int32, flagged
        (:func:`~sdfcodec.core.anskernels.categorical_ahead`); :func:`symbols_ahead` takes the first ``n``."""
        return _k().categorical_ahead(self.words, self.st, int(cap), table[0], table[1], _SLOT_SHIFT)

    def flags(self, n: int, p: float) -> np.ndarray:
        """``n`` bits ``(n,)`` bool under ``Bernoulli(p, perfect=False)``."""
        return _k().decode_flags(self.words, self.st, int(n), float(p)).astype(bool)

    def bits(self, grid: np.ndarray, at: np.ndarray, bounds: np.ndarray, deltas: np.ndarray, weights: np.ndarray,
             n_ctx: int, extra: np.ndarray | None = None) -> None:
        """Decode bits into ``grid`` (flat, C-contiguous, int64 or uint8) at positions ``at`` ``(m,)`` int64,
        wavefront by wavefront (``bounds`` ``(W + 1,)`` delimit them in ``at``; every context reads earlier
        wavefronts only), each under Krichevsky-Trofimov counts of its context ``sum_q grid[at + deltas[q]] *
        weights[q] (+ extra)``, ``extra`` ``(m,)`` int64 scaled by the caller, all below ``n_ctx``: what
        constriction decodes with ``Bernoulli(perfect=False)`` and per wavefront ``p1 = c1 / (c0 + c1)``, ``c =
        counts + 1/2``, counts added after each wavefront.

        Raises:
            ValueError: a context is outside ``[0, n_ctx)``.
        """
        ok = _k().decode_bits(self.words, self.st, grid, np.asarray(at, np.int64), np.asarray(bounds, np.int64),
                              np.asarray(deltas, np.int64), np.asarray(weights, np.int64),
                              np.zeros(0, np.int64) if extra is None else np.asarray(extra, np.int64), int(n_ctx))
        if not ok:
            raise InvalidValueError(f"a context is outside [0, {n_ctx})")


def decode_planes(decoder: Decoder, dims: tuple[int, int, int], order: tuple[np.ndarray, np.ndarray, np.ndarray],
                  nbr: np.ndarray, weights: np.ndarray, n_ctx: int) -> np.ndarray:
    """:meth:`Decoder.bits` of the positions ``order`` of :func:`wave_order_planes` in a grid of ``dims``, with
    context neighbours ``nbr`` ``(q, 3)`` rows ``(dw, di, dj)`` (the offset's wavefront step and first two
    axes), given as the ``b * 4096 + voxel`` of the positions whose bit is 0 ``(z,)`` int64, in that order (no
    grid): a view of ``order[0]``, which this overwrites.

    Raises:
        ValueError: a context reaches ``n_ctx``.
    """
    ok, zeros = _k().decode_planes(decoder.words, decoder.st, np.asarray(dims, np.int64), *order,
                                   np.ascontiguousarray(nbr, np.int64), np.asarray(weights, np.int64), int(n_ctx))
    if not ok:
        raise InvalidValueError(f"a context is outside [0, {n_ctx})")
    return zeros


def wave_order_planes(dims: tuple[int, int, int], corner: np.ndarray, rows: np.ndarray, parts: int = 1,
                      each: Callable[[Callable[[Any], Any], list[Any]], Any] | None = None
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(``(b * 4096 + voxel) << 32 | i << 16 | j`` ``(m,)`` int64 per pinned voxel, voxel ``voxel`` of block
    ``b`` at grid position ``(i, j, w - i - j)``; the wavefronts ``w`` ``(W,)``; their bounds ``(W + 1,)``): the
    order of :func:`wave_order` for pins as rows ``(n, 16, 16)`` uint16 of blocks with first voxels ``corner``.
    The blocks are placed in up to ``parts`` runs of slabs along the first axis, of about equal pins, each
    knowing its slots from the pins of the slabs before it: ``each(job, runs)`` runs ``job`` on each (default in
    turn; on threads, which write apart, the same order)."""
    dims, corner = np.asarray(dims, np.int64), np.ascontiguousarray(corner, np.int64)
    rows = np.ascontiguousarray(rows, np.uint16).reshape(len(corner), 16, 16)
    sizes = _k().wave_sizes(dims, corner, rows)  # (slab, wavefront)
    per_wave = sizes.sum(axis=0)
    first = np.cumsum(per_wave) - per_wave  # each wavefront's first slot
    waves = np.flatnonzero(per_wave)
    bounds = np.concatenate(([0], np.cumsum(per_wave[waves])))
    out = np.empty(int(bounds[-1]), np.int64)
    pins = np.cumsum(sizes.sum(axis=1))
    cuts = np.searchsorted(pins, pins[-1] * np.arange(1, max(int(parts), 1)) / max(int(parts), 1)) + 1
    ends = np.unique(np.concatenate((cuts[cuts < len(sizes)], [len(sizes)])))
    runs = np.stack((np.concatenate(([0], ends[:-1])), ends), axis=1)
    before = np.cumsum(sizes, axis=0) - sizes  # the slots the slabs before each take in every wavefront

    def place(run: np.ndarray) -> None:
        _k().wave_place(dims, corner, rows, first + before[run[0]], run, out)

    if each is None or len(runs) == 1:
        for run in runs:
            place(run)
    else:
        each(place, list(runs))
    return out, waves, bounds


def decode_mask(words: np.ndarray, n_rows: int, p_rows: int, cube_waves: tuple[np.ndarray, np.ndarray, np.ndarray],
                vox_waves: tuple[np.ndarray, np.ndarray, np.ndarray], cube_deltas: np.ndarray, deltas: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Decode the words of a mask stream ``M1`` (:mod:`sdfcodec.map.maskcoder`): ``n_rows`` flags (when ``p_rows
    < n_rows``), the ``(p_rows, 512)`` sub-cube states wavefront by wavefront, then the voxels of mixed sub-cubes
    wavefront by wavefront (contexts: the bits at ``deltas``, ``q = 0`` least significant), each under
    Krichevsky-Trofimov counts of the wavefronts before.

    ``cube_waves``/``vox_waves``: (padded flat indices, unpadded flat indices, bounds) of the cells in wavefront
    order (int64); ``cube_deltas``, ``deltas``: the context neighbours' padded offsets. Returns (partial
    ``(n_rows,)`` bool, states ``(p_rows, 512)`` int64, voxels padded by one on every side ``(p_rows, 18, 18,
    18)`` uint8).

    Raises:
        ValueError: the last word is 0 (no coder writes it).
    """
    k, dec = _k(), Decoder(words)
    partial = dec.flags(n_rows, p_rows / n_rows) if p_rows < n_rows else np.ones(n_rows, bool)
    states = k.decode_cubes(dec.words, dec.st, int(p_rows), *cube_waves, np.asarray(cube_deltas, np.int64))
    vpad, at, bounds = k.mixed_voxels(states, len(vox_waves[2]) - 1)
    dec.bits(vpad.reshape(-1), at, bounds, deltas, 1 << np.arange(len(deltas)), 1 << len(deltas))
    return partial, states.astype(np.int64), vpad.reshape(p_rows, 18, 18, 18)


def pack_mask(vpad: np.ndarray, states: np.ndarray) -> tuple[np.ndarray, bool]:
    """:func:`decode_mask`'s voxels ``(p, 18, 18, 18)`` as packed rows ``(p, 512)`` uint8 (``np.packbits`` of
    the C-order bits), and whether each mixed sub-cube of ``states`` ``(p, 512)`` holds both values (else the
    stream contradicts itself: corrupted)."""
    out, ok = _k().pack_rows(np.ascontiguousarray(vpad, np.uint8).reshape(len(vpad), -1),
                             np.ascontiguousarray(states, np.int64))
    return out, bool(ok)


def encode_mask(partial: np.ndarray | None, p_flag: float, bits: np.ndarray,
                cube_waves: tuple[np.ndarray, np.ndarray, np.ndarray], n_vox_waves: int, cube_deltas: np.ndarray,
                deltas: np.ndarray) -> np.ndarray:
    """The words :func:`decode_mask` reads back: row flags ``partial`` ``(R,)`` (None: not coded) under ``p_flag``,
    then the sub-cube states and the voxels of mixed sub-cubes of ``bits`` ``(P, 4096)`` (0/1, the partial rows);
    the same words as constriction's ``AnsCoder().encode_reverse`` of the same symbols and probabilities."""
    k = _k()
    bits = np.ascontiguousarray(bits, np.uint8).reshape(-1, 4096)
    p_rows = len(bits)
    vpad, states = k.padded_states(bits)
    _, at, bounds = k.mixed_voxels(states, n_vox_waves)
    n_flags = 0 if partial is None else len(partial)
    total = n_flags + p_rows * 512 + len(at)
    left, freq = np.empty(total, np.int64), np.empty(total, np.int64)
    if n_flags:
        left[:n_flags], freq[:n_flags] = bernoulli_intervals(partial, np.full(n_flags, p_flag))
    m = k.cube_intervals(states, *cube_waves, np.asarray(cube_deltas, np.int64), left, freq, n_flags)
    m = k.bit_intervals(vpad, at, bounds, np.asarray(deltas, np.int64), (1 << np.arange(len(deltas))).astype(np.int64),
                        np.zeros(0, np.int64), 1 << len(deltas), left, freq, m)
    assert m == total
    return encode(left, freq)


def encode_bits(grid: np.ndarray, at: np.ndarray, bounds: np.ndarray, deltas: np.ndarray, weights: np.ndarray,
                n_ctx: int, extra: np.ndarray | None = None) -> np.ndarray:
    """The words :meth:`Decoder.bits` reads back into ``grid`` (the same arguments; ``grid`` already holds the bits
    at ``at``): those of constriction's ``AnsCoder().encode_reverse`` of the same bits and probabilities.

    Raises:
        ValueError: a context is outside ``[0, n_ctx)``.
    """
    at = np.asarray(at, np.int64)
    left, freq = np.empty(len(at), np.int64), np.empty(len(at), np.int64)
    m = _k().bit_intervals(grid, at, np.asarray(bounds, np.int64), np.asarray(deltas, np.int64),
                           np.asarray(weights, np.int64), np.zeros(0, np.int64) if extra is None else
                           np.asarray(extra, np.int64), int(n_ctx), left, freq, 0)
    if m < 0:
        raise InvalidValueError(f"a context is outside [0, {n_ctx})")
    return encode(left, freq)


def wave_order(grid: np.ndarray, dims: tuple[int, int, int], corner: np.ndarray, pinned: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray]:
    """The ``at`` and ``bounds`` of :meth:`Decoder.bits` for the voxels ``pinned`` ``(n, 16, 16, 16)`` bool of
    blocks whose first voxels are at ``corner`` ``(n, 3)`` in the grid ``grid`` (flat uint8 of shape ``dims``, 2
    wherever a bit is not coded; left so): wavefront by wavefront (``x + y + z``), C order within one; empty
    wavefronts left out."""
    return _k().wave_order(grid, np.asarray(dims, np.int64), np.ascontiguousarray(corner, np.int64),
                           np.ascontiguousarray(pinned, np.bool_).reshape(len(corner), 4096))


def table_cdfs(lengths: np.ndarray, decay: np.ndarray, extent: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The cumulative tables constriction's ``Categorical(table, perfect=False)`` builds of the variable-rate
    model's tables (:class:`sdfcodec.core.varrate.EntropyModel`: ``lengths`` ``(D + 1,)`` float64, then per
    element the two-sided geometric law of ``decay``, ``extent`` ``(D,)``): (all of them concatenated, uint32;
    where each starts; its symbol count), as :func:`decode_chunk` takes them (uint32 tables)."""
    return _k().table_cdfs(np.ascontiguousarray(lengths, np.float64), np.ascontiguousarray(decay, np.float64),
                           np.ascontiguousarray(extent, np.int64))


#: Quantile bits below a slot of the decoders' lookup tables (:func:`sdfcodec.core.anskernels.slot_table`): 2^12
#: slots (32 KiB, in L1 cache) for one law, 2^8 for each of a code model's up to 257 laws.
_SLOT_SHIFT = 12
_CODE_SHIFT = 16
_SLOTS: list = []  # (the tables, their slots) of the last code model decoded: a map's reads use one model


def categorical_cdf(probs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The cumulative table ``(k + 1,)`` uint32 constriction's ``Categorical(probs, perfect=False)`` builds of
    probabilities ``probs`` ``(k,)`` float64, and its slots' first symbols, as :meth:`Decoder.categorical` takes
    them."""
    empty = np.zeros(0)
    cdf = _k().table_cdfs(np.ascontiguousarray(probs, np.float64), empty, empty.astype(np.int64))[0]
    return cdf, _k().slot_table(cdf, np.zeros(1, np.int64), _SLOT_SHIFT)


def _code_slots(cdfs: tuple[np.ndarray, np.ndarray, np.ndarray]) -> np.ndarray:
    """The slot tables of :func:`table_cdfs`' tables, kept for the last tables asked."""
    kept = _SLOTS[0] if _SLOTS else None  # (a local: another thread may replace the entry meanwhile)
    if kept is None or kept[0] is not cdfs[0]:
        kept = (cdfs[0], _k().slot_table(cdfs[0], cdfs[1], _CODE_SHIFT))
        _SLOTS[:] = [kept]
    return kept[1]


def decode_chunk(words: np.ndarray, n: int, level: int, cdfs: tuple[np.ndarray, np.ndarray, np.ndarray],
                 off: np.ndarray) -> np.ndarray:
    """``(n, level)`` int32 from a variable-rate chunk stream (:func:`sdfcodec.core.varrate.decode_chunk`):
    ``cdfs`` from :func:`table_cdfs` of [lengths table, element 0's table, ...]; ``off`` ``(D,)`` the symbol of
    value 0 per element.

    Raises:
        ValueError: the last word is 0.
    """
    status, out = _k().chunk_decode(_words(words), int(n), int(level), cdfs[0], cdfs[1], _code_slots(cdfs),
                                    _CODE_SHIFT, np.asarray(off, np.int64))
    _refuse(status)
    return out


def bernoulli_intervals(bits: np.ndarray, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(left, frequency) ``(n,)`` int64 of each bit under ``Bernoulli(p, perfect=False)``: float64 arithmetic
    as constriction's, elementwise."""
    p = np.asarray(p, np.float64)
    pm = 1.0 - p
    c1 = (pm * ((_TOTAL - 2) / (pm + p))).astype(np.int64) + 1
    one = np.asarray(bits) != 0
    return np.where(one, c1, 0), np.where(one, _TOTAL - c1, c1)


def categorical_intervals(sym: np.ndarray, probs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(left, frequency) ``(n,)`` int64 of each symbol under ``Categorical(perfect=False)`` with its own row of
    ``probs`` ``(n, k)`` float64."""
    probs = np.asarray(probs, np.float64)
    n, k = probs.shape
    cum = np.zeros((n, k + 1))
    for i in range(k):  # left to right, as constriction sums
        cum[:, i + 1] = cum[:, i] + probs[:, i]
    cdf = (cum * ((_TOTAL - k) / cum[:, k])[:, None]).astype(np.int64) + np.arange(k + 1)
    cdf[:, k] = _TOTAL
    rows, s = np.arange(n), np.asarray(sym, np.int64)
    return cdf[rows, s], cdf[rows, s + 1] - cdf[rows, s]


def encode(left: np.ndarray, freq: np.ndarray) -> np.ndarray:
    """uint32 words of ``AnsCoder()`` after ``encode_reverse`` of the symbols with intervals ``[left, left +
    freq)`` (decode order), as ``get_compressed`` returns them."""
    return _k().encode(np.ascontiguousarray(left, np.int64), np.ascontiguousarray(freq, np.int64))
