"""Variable-rate codes in a map (extension ``variable-rate-codes``, spec section 4e): the writer's pass that turns
the float codes written so far into one entropy-coded stream per chunk of blocks (:class:`VariableRateWriter`,
with rate control: a step, a byte budget or an error bound). The reader's decode of those streams back into
dequantised float codes is :mod:`sdfcodec.map.varread`.

While a map is written its ``codes`` array holds the writer's full-precision float32 codes and a temporary array
the per-block gains (:func:`sdfcodec.core.varrate.gains`); on commit both are replaced by the array ``code_streams``
``(Cx, Cy, Cz, L)`` uint8, one row per chunk of ``codes`` (a chunk of ``chunk_blocks`` ^ 3 blocks): a little-endian
uint32 word count ``W``, then ``W`` little-endian uint32 words of the chunk's rANS stream, zeros after. The
``codes`` array keeps its metadata and no chunk. The pass holds the map's codes and gains in memory (512 bytes
per coded block at code size 64).

Unless asked for the exact mask, the pass also replaces the coded observation mask by one exact only where it
can change the decoded surface at the step chosen (:mod:`sdfcodec.map.lossymask`, spec section 6f), recomputed
at every step rate control tries: the bytes it saves go to the codes.
"""

from __future__ import annotations

from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable

import numpy as np

from ..core._lazy import lazy_module
from ..core._validate import BLOCK
from ..errors import InvalidValueError
from ..core.header import (APPROX_MASK_EXTENSION, CODED_MASK_EXTENSION, REFINEMENT_EXTENSION, BlockState, Extension,
                           VariableRate)
from ..core.varrate import (CODER, LAGRANGE, SHRINK, SHRINK_BELOW, EntropyModel, choose_lengths, encode_chunk, gains,
                            stream_bytes)
from .implied import drop_implied, inline_states
from .errortarget import (CODE_HALVINGS, LOG2_CODE_STEPS, REFINE_RANGE, REFINE_TRIES, ErrorSample, refine_steps,
                          unreachable)
from .observed import MASK_ARRAY, error_weights, pack_mask, read_block_rows, unpack_mask, write_block_rows
from .varread import STREAM_ARRAY  # the array this writer fills (exported here too: the writer's side names it)

if TYPE_CHECKING:
    from ..codec import Codec

torch = lazy_module("torch")

__all__ = ["stream_chunk_keys", "STREAM_ARRAY", "GAIN_ARRAY", "STREAM_METADATA_BYTES", "stream_document_bytes",
           "stream_compressors", "VariableRateWriter", "check_variable_rate", "SAMPLE_BLOCKS", "TOLERANCE",
           "REFINE_FROM", "codes_share"]

#: Temporary array of the writer (never in a committed map): per coded block the gains of its code elements.
GAIN_ARRAY = "variable_rate_gains"
#: Coded blocks the writer keeps (voxels, mask, codes) to check ``--target-error`` on.
SAMPLE_BLOCKS = 2048
#: ``--target-bytes``: the step search stops at most this fraction below the target, never above it (what it
#: counts is exact but the compressor's frame of each row, estimated at 20 bytes): a byte the side information
#: saves goes to the codes.
TOLERANCE = 0.0005
#: Where the bisection on log2(step) stops when no step lands within TOLERANCE: 2^-10 (14 halvings).
STEP_RESOLUTION = 2.0 ** -10
#: ``--target-bytes`` from which the bytes go to the codes and a surface refinement (spec 6h), per coded block:
#: a pca-128 decode's Chamfer stops falling near 128 B (kitchen half: 3.91 mm at 128 B, 3.86 at 192 B).
REFINE_FROM = 160.0
#: The step search's last rounds with the pinned mask's chooser (low targets): bisection rounds, and how far
#: below the step found they look (log2 of the step).
CHOICE_ROUNDS, CHOICE_SPAN = 4, 0.16
_STREAM_DOC_BASE = 309  # a stream array's compact document but the digits of its width (measured)


def stream_document_bytes(width: int) -> int:
    """Bytes of a stream array's document (``zarr.json``, compact JSON) whose rows are ``width`` bytes: the width
    is written twice (shape and chunk shape), so a byte counted exactly at rate control depends on its digits."""
    return _STREAM_DOC_BASE + 2 * len(str(int(width)))


#: Bytes of the ``code_streams`` array document for rows of 1,000-9,999 bytes (the writer's first count; rate
#: control corrects it by :func:`stream_document_bytes` once it knows the width).
STREAM_METADATA_BYTES = stream_document_bytes(9999)
_ROW_FRAME = 20  # zstd frame and block headers plus the CRC32C of one row, bytes (measured 17-21)


def codes_share(target: float) -> float:
    """Bytes per coded block the codes (and the other files) get of a ``target`` that a refinement shares:
    128 at 256, growing by 8 % of the target beyond it (measured on the kitchen half,
    docs/variable-rate.md)."""
    return float(np.clip(128.0 + 0.08 * (target - 256.0), 110.0, 0.75 * target))


def check_variable_rate(codec: Codec) -> None:
    """Refuse a codec whose codes a prefix does not decode (variable-rate codes drop each block's tail)."""
    from ..core.quantize import check_quantisable

    if not getattr(codec, "prefix_ordered", False):  # first: what a variable-rate map needs most
        raise InvalidValueError(f"codec {codec.codec_id!r} codes are not prefix-ordered: variable-rate codes keep a "
                                "prefix of each block's code, so they need a codec such as pca")
    check_quantisable(codec)


def _basis(codec: Codec) -> np.ndarray:
    """``(D, 4096)`` float64: what each code element adds to the normalised decode (the codec is linear)."""
    d = codec.code_size
    eye = torch.from_numpy(np.vstack([np.zeros((1, d)), np.eye(d)]).astype(np.float32))
    dec = codec.decode(eye).reshape(d + 1, -1).double().numpy()
    return dec[1:] - dec[:1]


def stream_chunk_keys(state: np.ndarray, chunk_blocks: int) -> list[str]:
    """The store keys of the ``code_streams`` chunks a map with block states ``state`` (Bx, By, Bz) writes: one per
    chunk of ``chunk_blocks``^3 blocks holding a coded block (Zarr v3's default chunk key encoding)."""
    chunks = np.unique(np.argwhere(state == BlockState.CODED) // chunk_blocks, axis=0)
    return [f"{STREAM_ARRAY}/c/{i}/{j}/{k}/0" for i, j, k in chunks.tolist()]


class VariableRateWriter:
    """The variable-rate pass of a :class:`~sdfcodec.map.writer.MapWriter`: ``observe`` the blocks as they are
    encoded (gains, a sample), ``finish`` on commit. Exactly one of ``step`` (metres-free: normalised code
    units, one number or one per element), ``target_bytes`` (per coded block, every file of the map counted) and
    ``target_error`` (metres, :func:`~sdfcodec.map.errortarget.surface_error` on the sample, with a refinement
    where it makes the map smaller) chooses the step; ``lagrange`` scales the
    Lagrange multiplier (:data:`sdfcodec.core.varrate.LAGRANGE`); ``exact_mask`` keeps the observation mask exact
    (by default it is exact only where it decides the surface, :mod:`sdfcodec.map.lossymask`), and stored only at
    the voxels where it can (``pinned_mask``, for codecs that decode linearly: :mod:`sdfcodec.map.pinstore`)."""

    def __init__(self, codec: Codec, *, step: Any = None, target_bytes: float | None = None,
                 target_error: float | None = None, lagrange: float = LAGRANGE, exact_mask: bool = False,
                 pinned_mask: bool = True, refine: bool = True, refine_step: float | None = None):
        check_variable_rate(codec)
        if sum(x is not None for x in (step, target_bytes, target_error)) != 1:
            raise InvalidValueError("variable-rate codes take exactly one of a step, a target of bytes per coded "
                                    "block and a target error")
        for name, val in (("target bytes", target_bytes), ("target error", target_error)):
            if val is not None and not (np.isfinite(val) and val > 0):
                raise InvalidValueError(f"the {name} must be a finite number > 0, got {val!r}")
        self.codec, self.d = codec, codec.code_size
        if step is not None:
            from ..core.quantize import check_step
            step = check_step(step, self.d)
        self.step, self.target_bytes, self.target_error = step, target_bytes, target_error
        self.lagrange = float(lagrange)
        #: the ridge towards the zero code the blocks were encoded with again on commit (:meth:`_shrunk`), or 0;
        #: below SHRINK_BELOW bytes the blocks are kept for that second encode and the choice between the two
        self.shrink, self._may_shrink = 0.0, target_bytes is not None and target_bytes < SHRINK_BELOW
        self._surface_weight = 1.0
        self.exact_mask, self.pinned_mask = bool(exact_mask), bool(pinned_mask)
        self._mask: _LossyMask | None = None
        if refine_step is not None and not (np.isfinite(refine_step) and 2.0 ** -24 <= refine_step < 1.0):
            raise InvalidValueError(f"the refinement step must be a number of metres in [2^-24, 1), got {refine_step!r}")
        if refine_step is not None and target_bytes is not None:
            raise InvalidValueError("a refinement step and a target of bytes both choose the refinement's bytes: "
                                    "give one (a byte target picks the step itself)")
        # the surface refinement (spec 6h): with a byte target from REFINE_FROM, an error target, or a step asked for
        self.refine_step = refine_step
        self.refine = bool(refine) and (refine_step is not None or target_error is not None
                                        or (target_bytes is not None and target_bytes >= REFINE_FROM))
        self._truth = None  # a TrueValues (map/refine.py) once a block is seen: on disk, not in memory
        self._q: np.ndarray | None = None
        self.voxel_size = 1.0
        basis = _basis(codec)
        self.basis_sq = (basis * basis).astype(np.float32)
        self._sample = None if target_error is None else ErrorSample(codec, SAMPLE_BLOCKS)
        self.report: dict[str, Any] = {}

    def observe(self, gain_arr: Any, coords: np.ndarray, v: np.ndarray, observed: np.ndarray | None,
                codes: np.ndarray, truncation: tuple[float, float], voxel_size: float, surface_weight: float
                ) -> None:
        """Blocks ``coords`` ``(n, 3)`` just encoded to ``codes`` ``(n, D)`` from normalised ``v`` with ``observed``:
        store their gains in ``gain_arr`` and keep a random sample for the error target."""
        w = error_weights(v, observed, truncation, voxel_size, surface_weight)
        w = np.ones((len(v), BLOCK ** 3), np.float32) if w is None else w.reshape(len(v), -1)
        g = gains(w, self.basis_sq)
        write_block_rows(gain_arr, coords, g)
        self.voxel_size, self._surface_weight = float(voxel_size), float(surface_weight)
        if self.refine or self._may_shrink:  # the true values (refinement, second encode): float32 metres, bits
            from .refine import TrueValues

            d_min, d_max = truncation
            x = (np.asarray(v, np.float32).reshape(len(v), -1) * np.float32(d_max - d_min) + np.float32(d_min))
            if self._truth is None:
                self._truth = TrueValues()
            self._truth.add(coords, x, observed)
        if self._sample is not None:
            self._sample.add(coords, v, observed, codes, g, self._truth)

    # -- the pass on commit ---------------------------------------------------------------------------
    def _lam(self, step: np.ndarray, g: np.ndarray) -> float:
        return self.lagrange * float(np.mean(step) ** 2) * max(float(g.mean()), 1e-12)

    def _encode_all(self, z: np.ndarray, g: np.ndarray, chunk_ids: np.ndarray, step: np.ndarray
                    ) -> tuple[list[np.ndarray], EntropyModel, np.ndarray]:
        q, k, model = choose_lengths(z, g, step, self._lam(step, g))
        self._q = q
        bounds = np.flatnonzero(np.diff(chunk_ids)) + 1
        streams = [encode_chunk(q[a:b], k[a:b], model) for a, b in zip(np.r_[0, bounds], np.r_[bounds, len(z)])]
        if self._mask is not None:  # the mask that goes with these codes, and its bytes
            self._mask.at(q, step)
        return streams, model, k

    def _rows_bytes(self, streams: list[np.ndarray]) -> int:
        return sum(stream_bytes(s) + _ROW_FRAME for s in streams)

    def finish(self, group: Any, state: np.ndarray, chunk_blocks: int, other_bytes: Callable[[dict], int],
               truncation: tuple[float, float], extensions: list | None = None) -> VariableRate:
        """Replace the float codes of ``group`` by the chunk streams (module docstring); ``other_bytes(fields)``:
        the bytes of every other file of the map once its header holds ``fields`` (rate control; counting the
        mask as written so far). With a coded mask and not ``exact_mask``, its lossy version is written and
        ``extensions`` (the header's list, which ``other_bytes`` counts) gets ``approximate-observation-mask``.
        Returns the header field."""
        try:
            return self._commit(group, state, chunk_blocks, other_bytes, truncation, extensions)
        finally:  # the refinement's true values (a temporary file) are no longer needed, however the pass ends
            if self._truth is not None:
                self._truth.close()

    def _commit(self, group: Any, state: np.ndarray, chunk_blocks: int, other_bytes: Callable[[dict], int],
                truncation: tuple[float, float], extensions: list | None) -> VariableRate:
        coded = np.argwhere(state == BlockState.CODED)
        cb = chunk_blocks
        ch, loc = coded // cb, coded % cb
        order = np.lexsort((loc[:, 2], loc[:, 1], loc[:, 0], ch[:, 2], ch[:, 1], ch[:, 0]))
        coded, ch = coded[order], ch[order]
        cgrid = tuple(-(-n // cb) for n in state.shape)
        chunk_ids = np.ravel_multi_index(tuple(ch.T), cgrid) if len(ch) else np.zeros(0, np.int64)
        z = _rows(group["codes"], coded).astype(np.float64)
        g = _rows(group[GAIN_ARRAY], coded).astype(np.float64)
        if len(z) and not np.isfinite(z).all():
            raise InvalidValueError("codes hold NaN/Inf values; they cannot be quantised")
        # small states travel in the header and neither codes' nor state's files are stored (spec 4e; the
        # writer counts neither); otherwise the codes document is slimmed, done below once the codes are read
        inline = inline_states(state)
        slim = 0 if inline else _slim_codes_document(group.store.root, write=False)
        if not self.exact_mask and MASK_ARRAY in group and len(coded) and extensions is not None:
            self._mask = _LossyMask(self.codec, group[MASK_ARRAY], coded, truncation,
                                    *self._pinned(group, coded, state, cb, truncation, extensions))
            if APPROX_MASK_EXTENSION not in {e.name for e in extensions}:  # a transcode's may be there already
                extensions.append(Extension(name=APPROX_MASK_EXTENSION, required=False))
        mask = self._mask
        ref = self._refinement(coded, state, cb, truncation) if len(coded) else None

        def other(f: dict) -> int:
            return other_bytes({**f, "states": inline}) - slim + (0 if mask is None else mask.saved)

        share = None if ref is None or self.target_bytes is None else codes_share(self.target_bytes)
        planned = None  # an error target's refinement
        if self.target_error is not None and len(z):
            step, planned = self._error_plan(ref, z, g, chunk_ids, other, len(coded), truncation)
        else:
            step = self._choose_step(z, g, chunk_ids, other, len(coded), truncation, share)
        shrink = SHRINK if self._may_shrink and len(z) else 0.0
        if shrink > 0 and self._truth is not None and self._truth.rows_of(coded) is not None:
            z = self._shrunk(coded, truncation, shrink, z, g, step)  # per block the cheaper of two codes, step again
            step = self._choose_step(z, g, chunk_ids, other, len(coded), truncation, share, float(np.mean(step)))
        refinement = planned
        if ref is not None and self.target_error is None:
            refinement, spare = self._choose_refinement(ref, z, g, chunk_ids, step, other, len(coded))
            if refinement is None and share is not None:  # nothing fits beside the codes: codes alone
                step = self._choose_step(z, g, chunk_ids, other, len(coded), truncation)
            for _ in range(2):  # the finest refinement left bytes: finer codes take them, then the refinement again
                if refinement is None or share is None or spare <= TOLERANCE * share:
                    break
                share += spare
                step = self._choose_step(z, g, chunk_ids, other, len(coded), truncation, share)
                refinement, spare = self._choose_refinement(ref, z, g, chunk_ids, step, other, len(coded))
            if refinement is not None and share is not None and spare > 0.05 * self.target_bytes:
                got = self.target_bytes - spare
                raise InvalidValueError(
                    f"a target of {self.target_bytes:g} bytes per coded block is above what variable-rate codes and a "
                    f"surface refinement take on this map: at most {got:.1f} (both at their finest steps); ask for "
                    f"at most {got:.0f}, or store the map lossless (--codec raw) or error-bounded (--codec sz3 "
                    "--max-error E)")
        if len(z):
            streams, model, k = self._encode_all(z, g, chunk_ids, step)
            if refinement is not None:  # the mask's pins follow the refined field (spec 6h)
                ref.at(self._q, step, refinement[0], refinement[1])
                if mask is not None:
                    mask.at(self._q, step)
                ref.write(group, stream_compressors())
                extensions.append(Extension(name=REFINEMENT_EXTENSION, required=True))
            if mask is not None:
                mask.write(group)
        else:
            streams, model, k = [], EntropyModel([0] * self.d, [0.5] * self.d, [0] * self.d, [1] + [0] * self.d), []
        uniform = bool((step == step[0]).all())
        spec = VariableRate(step=[float(step[0])] if uniform else [float(s) for s in step], coder=CODER,
                            model=model.pack(), states=inline, refinement=None if refinement is None else ref.spec)
        width = max([stream_bytes(s) for s in streams], default=4)
        arr = group.create_array(STREAM_ARRAY, shape=(*cgrid, width), dtype="uint8", fill_value=0,
                                 chunks=(1, 1, 1, width), compressors=stream_compressors(),
                                 dimension_names=["cx", "cy", "cz", "byte"])
        arr = arr.with_config({"write_empty_chunks": True})
        for s, cid in zip(streams, chunk_ids[np.r_[0, np.flatnonzero(np.diff(chunk_ids)) + 1]] if len(z) else []):
            row = np.zeros(width, np.uint8)
            row[:4] = np.frombuffer(np.uint32(len(s)).astype("<u4").tobytes(), np.uint8)
            row[4:4 + 4 * len(s)] = np.frombuffer(s.astype("<u4").tobytes(), np.uint8)
            arr[(*np.unravel_index(cid, cgrid), slice(None))] = row
        if inline:
            drop_implied(group.store.root)
        else:
            _drop_chunks(group, "codes")
            _slim_codes_document(group.store.root, write=True)
        del group[GAIN_ARRAY]
        n = max(len(coded), 1)
        self.report.update(step=float(np.mean(step)), mean_length=float(np.mean(k)) if len(k) else 0.0,
                           stream_bytes_per_coded_block=self._rows_bytes(streams) / n)
        if mask is not None:
            self.report.update(mask_bytes_per_coded_block=mask.bytes / n,
                               exact_mask_bytes_per_coded_block=mask.exact / n)
        return spec

    def _shrunk(self, coded: np.ndarray, truncation: tuple[float, float], shrink: float, z: np.ndarray,
                g: np.ndarray, step: np.ndarray) -> np.ndarray:
        """Codes ``(n, D)`` float64 of the blocks ``coded``: per block, the first encode's ``z`` or the encode again
        from the true values with a ridge towards the zero code (``shrink``, :data:`sdfcodec.core.varrate.SHRINK`),
        whichever costs less ``D + lam R`` once quantised at ``step`` (the step found for ``z``): ``D`` the
        reader's weighted error of the truncated decode against the true values (not the gains' second-order
        estimate: the flat valley is what it misses), ``R`` the bits under each candidate's own model. Where the
        step is coarse the smaller codes win; elsewhere most blocks keep the first encode. Sets ``self.shrink`` and
        the report's ``shrunk_blocks``."""
        from .observed import encode_blocks

        rows = self._truth.rows_of(coded)
        d_min, d_max = truncation
        lam = self._lam(step, g)

        def truth(i: int) -> tuple[np.ndarray, np.ndarray | None]:
            """Blocks ``i:i + SAMPLE_BLOCKS``' normalised true values and observation, read from the memory map
            of the true values (a batch at a time: the map's blocks are never all in memory)."""
            r = rows[i:i + SAMPLE_BLOCKS]
            v = (np.asarray(self._truth.values[r]) - np.float32(d_min)) / np.float32(d_max - d_min)
            obs = self._truth.observed
            return (v.astype(np.float32).reshape(-1, BLOCK, BLOCK, BLOCK),
                    None if obs is None else unpack_mask(np.asarray(obs[r])))

        starts = range(0, len(coded), SAMPLE_BLOCKS)
        shrunk = np.empty_like(z)
        for i in starts:
            v, obs = truth(i)
            shrunk[i:i + len(v)] = encode_blocks(self.codec, v, obs, truncation, self.voxel_size, self._surface_weight,
                                                 "cpu", shrink=shrink)
        cols = np.arange(self.d)
        quantised, bits = [], []
        for c in (z, shrunk):
            q, k, model = choose_lengths(c, g, step, lam)
            quantised.append(q)
            bits.append(np.where(cols < k[:, None], model.bits(q), 0.0).sum(axis=1) + model.length_bits()[k])
        err = np.empty((2, len(z)))
        for i in starts:
            v, obs = truth(i)
            w = error_weights(v, obs, truncation, self.voxel_size, self._surface_weight)
            x = v.reshape(len(v), -1)
            for e_c, q in zip(err, quantised):
                dec = self.codec.decode(torch.from_numpy((q[i:i + len(v)] * step).astype(np.float32))).numpy()
                e = (np.clip(dec.reshape(len(v), -1), 0, 1) - x) ** 2
                e_c[i:i + len(v)] = (e if w is None else e * w.reshape(len(v), -1)).sum(axis=1)
        cost = err + lam * np.stack(bits)
        pick = cost[1] < cost[0]
        self.shrink = shrink
        self.report["shrunk_blocks"] = int(pick.sum())
        return np.where(pick[:, None], shrunk, z)

    def _pinned(self, group: Any, coded: np.ndarray, state: np.ndarray, cb: int, truncation: tuple[float, float],
                extensions: list) -> tuple[Any, int]:
        """``(PinnedStreams or None, metadata bytes it adds)``: the pinned mask (spec 6g) where ``pinned_mask`` and
        the codec decodes linearly; then ``extensions`` lists ``pinned-observation-mask`` in place of the
        ``observed`` array's two."""
        from .pinstore import PINNED_ARRAY, PINNED_MASK_EXTENSION, PinnedStreams, linear_basis

        basis = linear_basis(self.codec, 1.0, self.d, truncation) if self.pinned_mask else None
        if basis is None:
            return None, 0
        truth = unpack_mask(_rows(group[MASK_ARRAY], coded))
        streams = PinnedStreams(coded, truth, state, cb, lambda step: linear_basis(self.codec, step, self.d, truncation),
                                truncation)
        gone = {e.name for e in extensions} & {"observation-mask", CODED_MASK_EXTENSION}
        extensions[:] = [e for e in extensions if e.name not in gone] + [
            Extension(name=PINNED_MASK_EXTENSION, required=True)]
        from .manifest import manifest_bytes_estimate

        root = Path(group.store.root)
        meta = root / MASK_ARRAY / "zarr.json"
        # its document against the observed array's, and (if the map has a manifest) their records in it
        old = [f.relative_to(root).as_posix() for f in (root / MASK_ARRAY).rglob("*") if f.is_file()]
        new = [f"{PINNED_ARRAY}/zarr.json"] + [f"{PINNED_ARRAY}/c/{'/'.join(str(int(c)) for c in k)}/0"
                                                for k in streams.keys]
        keys = manifest_bytes_estimate(new) - manifest_bytes_estimate(old)
        return streams, STREAM_METADATA_BYTES - (meta.stat().st_size if meta.exists() else 0) + max(keys, 0)

    def _choose_step(self, z, g, chunk_ids, other_bytes, n, truncation, share=None, below=None) -> np.ndarray:
        if self.step is not None:
            return self.step
        if not len(z):
            raise InvalidValueError("the map has no coded blocks (all free space): there are no codes to rate-control")
        return self._step_for_bytes(z, g, chunk_ids, other_bytes, n, share, below)

    def _refinement(self, coded: np.ndarray, state: np.ndarray, cb: int, truncation: tuple[float, float]):
        """A :class:`~sdfcodec.map.refine.RefinementStreams` of the coded blocks when the refinement can apply
        here: asked for, the codec linear, every coded block's true values seen, and a mask exact or pinned (the
        approximate mask of section 6f is decided on the unrefined decode); else None."""
        from .pinstore import linear_basis
        from .refine import RefinementStreams

        if not self.refine:
            return None
        if self._truth is None or linear_basis(self.codec, 1.0, self.d, truncation) is None:
            return None
        if self._mask is not None and self._mask.pinned is None:
            return None
        rows = self._truth.rows_of(coded)
        if rows is None:
            return None
        return RefinementStreams(coded, self._truth, rows, cb, state.shape,
                                 lambda step: linear_basis(self.codec, step, self.d, truncation), truncation)

    def _choose_refinement(self, ref, z, g, chunk_ids, step, other_bytes, n
                           ) -> tuple[tuple[float, float] | None, float]:
        """``((step, tau) metres of the refinement, spare bytes per coded block)``: the asked step, or (a byte
        target) the finest whose map fits the target, bisection on log(step) from 0.2 mm to 5 cm, None when even
        the coarsest does not fit; spare: what the finest refinement leaves of the target (0 otherwise)."""
        from .refine import tau_for_step

        total = self._refined_bytes(ref, z, g, chunk_ids, step, other_bytes, n)
        if self.refine_step is not None:
            asked = (self.refine_step, tau_for_step(self.refine_step, self.voxel_size))
            ref.at(self._q, step, *asked)
            return asked, 0.0
        t = self.target_bytes
        lo, hi = np.log2(REFINE_RANGE)
        if total(2 ** hi) > t:
            if self._mask is not None:
                self._mask.pinned.refined = None
            return None, 0.0
        finest = total(2 ** lo)
        if finest <= t:  # bytes left over: the caller gives them to the codes
            return (2 ** lo, tau_for_step(2 ** lo, self.voxel_size)), t - finest
        for _ in range(14):
            mid = (lo + hi) / 2
            got = total(2 ** mid)
            if t * (1 - 0.01) <= got <= t:
                hi = mid
                break
            lo, hi = (mid, hi) if got > t else (lo, mid)
        self.report.update(refine_step=2 ** hi)
        return (2 ** hi, tau_for_step(2 ** hi, self.voxel_size)), 0.0

    def _refined_bytes(self, ref, z, g, chunk_ids, step, other_bytes, n) -> Callable[[float], float]:
        """The map's bytes per coded block with codes at ``step`` beside a refinement of step ``r`` metres, as a
        function of ``r``: the codes encoded once, here; from here the pins follow the refined field (spec 6h)."""
        from .manifest import manifest_bytes_estimate
        from .refine import REFINE_ARRAY, tau_for_step

        streams, model, _ = self._encode_all(z, g, chunk_ids, step)
        if self._mask is not None:
            self._mask.pinned.refined = ref.refined
        width = max([stream_bytes(x) for x in streams], default=4)
        codes = self._rows_bytes(streams) + stream_document_bytes(width) - STREAM_METADATA_BYTES
        keys = [f"{REFINE_ARRAY}/zarr.json"] + [f"{REFINE_ARRAY}/c/{'/'.join(map(str, k))}/0" for k in ref.keys]
        listed = manifest_bytes_estimate(keys) - manifest_bytes_estimate([])

        def total(r: float) -> float:
            ref.at(self._q, step, r, tau_for_step(r, self.voxel_size))
            if self._mask is not None:
                self._mask.at(self._q, step)
            rw = max([stream_bytes(x) for x in ref.streams], default=4)
            fields = dict(step=[float(step[0])], coder=CODER, model=model.pack(), refinement=ref.spec)
            return (codes + other_bytes(fields) + ref.bytes + stream_document_bytes(rw) + listed) / n
        return total

    def _codes_bytes(self, z, g, chunk_ids, s: float, other_bytes, n) -> tuple[float, float]:
        """``(the map's bytes per coded block with codes alone at step s, of them not the code streams')``."""
        streams, model, _ = self._encode_all(z, g, chunk_ids, np.full(self.d, s))
        width = max([stream_bytes(x) for x in streams], default=4)  # the document's digits (finish's width)
        other = other_bytes(dict(step=[s], coder=CODER, model=model.pack())) + stream_document_bytes(
            width) - STREAM_METADATA_BYTES
        return (self._rows_bytes(streams) + other) / n, other / n

    def _step_for_bytes(self, z, g, chunk_ids, other_bytes, n, share=None, below=None) -> np.ndarray:
        """Bisection on log(step): the codes' exact stream bytes plus everything else against the target (or
        ``share`` of it: the codes' part beside a refinement). ``below``: a step known to fit codes larger than
        ``z`` (the first encode's, before the shrink): the search starts between it and 8 times finer, without
        the costly ends (the finest step codes every element at full length), unless ``z`` does not fit there."""
        t = self.target_bytes if share is None else share
        total = partial(self._codes_bytes, z, g, chunk_ids, other_bytes=other_bytes, n=n)  # of a step s
        lo, hi = LOG2_CODE_STEPS
        if below is not None and total(below)[0] <= t:
            lo, hi = np.log2(below) - 3.0, float(np.log2(below))
        else:
            below = None
        t_hi, other_hi = (0.0, 0.0) if below is not None else total(2 ** hi)
        if t_hi > t * (1 + TOLERANCE):
            raise InvalidValueError(f"a target of {t:g} bytes per coded block is below what this map can take: at "
                                    f"least {t_hi:.1f} (of it {other_hi:.1f} of observation mask, weights, block "
                                    "states, header and metadata; codes all but empty)")
        t_lo, _ = (np.inf, 0.0) if below is not None else total(2 ** lo)
        if t_lo < t and share is not None:  # beside a refinement: the finest codes, the refinement takes the rest
            return np.full(self.d, 2 ** lo)
        if t_lo < t:
            raise InvalidValueError(f"a target of {t:g} B per coded block is above what variable-rate codes take on "
                                    f"this map: at most {t_lo:.1f} (at step {2 ** lo:g}); ask for at most {int(t_lo)},"
                                    " or take longer codes (--code-size), a refinement (no --no-refine), --fixed-rate")
        # rate-distortion rounding and the mask's free bits make the bytes step by more than TOLERANCE between
        # neighbouring steps on some maps: stop at a 0.07 % step resolution with ``hi``, the finest step known to fit
        while hi - lo > STEP_RESOLUTION:
            mid = (lo + hi) / 2
            got, _ = total(2 ** mid)
            if t * (1 - TOLERANCE) <= got <= t:
                hi = mid
                break
            lo, hi = (mid, hi) if got > t else (lo, mid)
        mask = self._mask
        if self.shrink > 0 and mask is not None and mask.pinned is not None:
            # low targets: the mask's free bits chosen (pinstore.PinnedStreams.choose) in a few last rounds only
            # (the chooser costs three masks), below the step found, keeping the finest that fits
            mask.pinned.choose = True
            lo = hi - CHOICE_SPAN
            for _ in range(CHOICE_ROUNDS):
                mid = (lo + hi) / 2
                got, _ = total(2 ** mid)
                lo, hi = (mid, hi) if got > t else (lo, mid)
        return np.full(self.d, 2 ** hi)

    def _error_plan(self, ref, z, g, chunk_ids, other_bytes, n, truncation
                    ) -> tuple[np.ndarray, tuple[float, float] | None]:
        """``(codes step, refinement (step, band) metres or None)``: of the codes alone and beside a refinement at
        ``refine_steps`` of the target (or the step asked), the steps whose sample's surface error meets it
        (:mod:`sdfcodec.map.errortarget`), then the fewest bytes the map measures; refused when none meets it."""
        from .refine import tau_for_step

        e, mask = self.target_error, self._mask  # called with coded blocks, so a sample of them

        def quantised(zs: np.ndarray, gs: np.ndarray, s: float) -> np.ndarray:
            st = np.full(self.d, s)
            return choose_lengths(zs, gs, st, self._lam(st, gs))[0] * st

        steps = [] if ref is None else [self.refine_step] if self.refine_step else refine_steps(e)
        options, reached = [], []
        if ref is None or self.refine_step is None:
            s, got = self._sample.coarsest_step(e, truncation, quantised)
            reached.append(got)
            if s is not None:
                if mask is not None and mask.pinned is not None:
                    mask.pinned.refined = None  # the pins of the unrefined field
                options.append((self._codes_bytes(z, g, chunk_ids, s, other_bytes, n)[0], s, None, got))

        def beside(s: float, r: float, band: float, got: float) -> tuple:  # the option of codes s and refinement r
            return self._refined_bytes(ref, z, g, chunk_ids, np.full(self.d, s), other_bytes, n)(r), s, (r, band), got

        refined = []
        for r in steps:  # coarsest first: the first REFINE_TRIES that meet the target on the sample are measured
            band = tau_for_step(r, self.voxel_size)
            s, got = self._sample.coarsest_step(e, truncation, quantised, (r, band))
            reached.append(got)
            refined += [] if s is None else [beside(s, r, band, got)]
            if len(refined) == REFINE_TRIES:
                break
        if refined:  # beside the best refinement, finer codes may make a smaller map (less left to correct)
            _, s, (r, band), got = best = min(refined, key=lambda o: o[0])
            options += [best] + [beside(s * 2.0 ** -j, r, band, got) for j in range(1, CODE_HALVINGS + 1)]
        if not options:
            raise unreachable(e, min(reached), bool(steps))
        _, s, refinement, got = min(options, key=lambda o: o[0])
        if mask is not None and mask.pinned is not None:  # the pins follow the field chosen (spec 6h)
            mask.pinned.refined = None if refinement is None else ref.refined
        self.report.update(sample_surface_error=got, refine_step=refinement and refinement[0])
        return np.full(self.d, s), refinement


class _LossyMask:
    """The lossy mask of the coded blocks ``coords`` for the codes last given to :meth:`at`: ``bytes`` its chunks'
    bytes, ``saved`` what they take beyond the exact mask's (negative: saved), :meth:`write` stores it. With
    ``pinned`` (a :class:`~sdfcodec.map.pinstore.PinnedStreams` of the same blocks), the pinned mask (spec 6g)
    instead: ``saved`` counts the ``observed`` array it replaces, ``meta_delta`` its metadata's bytes less."""

    def __init__(self, codec: Codec, arr: Any, coords: np.ndarray, truncation: tuple[float, float],
                 pinned: Any = None, meta_delta: int = 0):
        from .lossymask import MaskChunks

        self.codec, self.coords, self.truncation = codec, coords, truncation
        self.chunks = MaskChunks(arr, coords)
        # the pinned streams' truth is this one: one copy (4 KB per coded block) for both
        self.truth = unpack_mask(_rows(arr, coords)) if pinned is None else pinned.truth
        self.exact = self.bytes = self.chunks.bytes(pack_mask(self.truth))
        self.rows: np.ndarray | None = None
        self.pinned, self.meta_delta = pinned, meta_delta

    @property
    def saved(self) -> int:
        return self.bytes - self.exact + (self.meta_delta if self.pinned is not None else 0)

    def at(self, q: np.ndarray, step: np.ndarray) -> None:
        """``q`` ``(n, D)`` integer codes of the coded blocks, in ``coords``' order, and their steps ``(D,)``."""
        from .lossymask import pinned_in_batches, relax_mask

        if self.pinned is not None:
            self.pinned.at(q, step)
            self.bytes = self.pinned.bytes
            return
        d_min, d_max = self.truncation
        codes = np.asarray(q * step, np.float32)

        def decode(idx: np.ndarray) -> np.ndarray:
            dec = self.codec.decode(torch.from_numpy(codes[idx])).numpy()
            return np.clip(dec * (d_max - d_min) + d_min, d_min, d_max)

        self.rows = pack_mask(relax_mask(self.truth, pinned_in_batches(self.coords, decode, self.truncation)))
        self.bytes = self.chunks.bytes(self.rows)

    def write(self, group: Any) -> None:
        if self.pinned is None:
            self.chunks.write(self.rows)
            return
        self.pinned.write(group, stream_compressors())
        del group[MASK_ARRAY]  # the pinned streams replace it (spec 6g)


def _slim_codes_document(root: str | Path, write: bool) -> int:
    """The bytes that giving the ``codes`` array of the variable-rate map being written in ``root`` the chain
    ``bytes, crc32c`` and no dimension names saves, and (``write``) do it: it never holds a chunk once the streams
    replace them (such a map is not updated), so the Blosc entry a chunk would need is 90 bytes of JSON no reader
    uses."""
    import json
    import os

    path = Path(root) / "codes" / "zarr.json"
    raw = path.read_bytes()
    doc = json.loads(raw)
    doc["codecs"] = [c for c in doc["codecs"] if c.get("name") in ("bytes", "crc32c")]
    doc.pop("dimension_names", None)  # OPTIONAL in Zarr v3, and nothing to label: 37 bytes
    data = json.dumps(doc, separators=(",", ":")).encode()
    if write:
        part = path.with_name("zarr.json.part")
        part.write_bytes(data)
        os.replace(part, path)
    return len(raw) - len(data)


def stream_compressors() -> list:
    """The chain of ``code_streams``: zstd level 1 (the zero padding of each row takes a few bytes; the stream
    itself is incompressible) and a CRC32C checksum."""
    from zarr.codecs import Crc32cCodec, ZstdCodec

    return [ZstdCodec(level=1), Crc32cCodec()]


class _PlainReads:
    """What :func:`~sdfcodec.map.observed.read_block_rows` needs of a reader, for the writer's own arrays."""

    @staticmethod
    def read_many(arr: Any, sels: list) -> list[np.ndarray]:
        return [np.asarray(arr[sel]) for sel in sels]


def _rows(arr: Any, coords: np.ndarray) -> np.ndarray:
    """Rows ``arr[bx, by, bz, :]`` of blocks ``coords`` ``(n, 3)``, one read per chunk (the writer's own arrays)."""
    return read_block_rows(_PlainReads, arr, coords)


def _drop_chunks(group: Any, name: str) -> None:
    """Delete every chunk file of array ``name`` of a local group (its metadata stays)."""
    import shutil

    root = Path(group.store.root) / name / "c"
    if root.exists():
        shutil.rmtree(root)
