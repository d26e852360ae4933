"""Online fusion into a compressed map with bounded memory: :func:`fuse_to_map`.

:func:`sdfcodec.fusion.tsdf.fuse` keeps every block of a sequence in open3d's VoxelBlockGrid and hands them all
over at the end: memory grows with the map (32 KiB per block: float32 distance and weight). Here the grid is
a bounded *working set*: its hash map is sized once to the budget (``working_set_mb`` / 32 KiB blocks) and
never grows. For every frame:

1. the blocks the frame touches are found (``compute_unique_block_coordinates``, the same allocation rule as
   :func:`~sdfcodec.fusion.tsdf.fuse`);
2. if those not yet in the working set would overflow it, the least recently seen blocks (never the frame's
   own) are **paged out**: read from the grid, encoded into the map through the ordinary writer
   (:meth:`sdfcodec.Map.write_blocks` with their fusion weights, so the observation mask and the
   error-weighted, surface-true encoding are exactly what ``sdfcodec encode`` of a fused map does) and erased
   from the grid, down to ``low_water`` of the budget so that page-outs come in batches;
3. blocks of the frame that the map already holds are **paged in**: their codes are decoded (unobserved
   voxels back to ``d_max``), their weights read, and both put back in the grid;
4. the frame is integrated (the shifted band of :mod:`sdfcodec.fusion.tsdf`, so the result is the same TSDF).

At the end the working set is flushed into the map and the map is committed (crash-safe as every write:
nothing appears at the path until then, spec section 9). The peak working set is bounded by the budget as
long as one frame's blocks fit in it (else :class:`~sdfcodec.errors.InvalidValueError` says how much it
needs).

What is stored, and why: the **fusion weights** (float16 per voxel, exact to 2048 observations; the writer's
``weights`` array, extension "fusion-weights"), not just an observation mask. A block paged back in resumes
Curless-Levoy averaging from its decoded distances with its true weights, so a new frame moves it by
``1 / (w + 1)`` as it would have in an unbounded grid; with only a mask, every paged-in voxel would restart at
weight 1 and the next frame would count as much as all the earlier ones together. The distances are the lossy
part: a block paged out and in is re-fused from its decoded state, so its error is the codec's error of its
last page-out, not a sum (a PCA code of a decoded block is the same code: the projection is idempotent, the
clipping and error weights aside). At commit a map with a lossy codec drops them by default (its observation
mask stays; ``keep_weights=True`` keeps them as uint8 counts, :mod:`sdfcodec.map.weights`): the fusion is over.

The lattice must be known before the first frame, so the origin is worked out from the poses (every camera
centre minus the farthest a ray can allocate, ``depth_max`` along the widest ray plus the band, rounded down
to the block lattice that :func:`~sdfcodec.fusion.tsdf.fuse` uses); the map's grid then holds every block. Pass
``origin`` to choose it (e.g. to compare with a ``fuse(..., origin=...)`` of the same sequence).
"""

from __future__ import annotations

import math
import resource
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any, Iterable

import numpy as np
import torch

from ..core._validate import BLOCK
from ..data.sequences import Frame, Intrinsics, Sequence
from ..errors import InvalidValueError
from .tsdf import FrameFeed, check_fusion_parameters, fusion_input, open3d_module, to_open3d_order
from ..core.header import BlockState
from ..map.observed import read_block_rows

if TYPE_CHECKING:
    from ..codec import Codec

__all__ = ["BLOCK_BYTES", "fuse_to_map", "fusion_codec", "lattice_origin"]

#: Bytes a block takes in the working set: float32 distance and float32 weight per voxel.
BLOCK_BYTES = BLOCK ** 3 * 8
PAGE_SLICE = 512  # blocks read out of the grid and written into the map at a time


def fusion_codec(codec_id: str = "raw", code_size: int | None = None) -> Codec:
    """The codec a fused map is written with (``sdfcodec fuse --codec --code-size``): ``raw`` (lossless), ``pca``
    (the shipped eigenshapes cut to ``code_size``, default 64, as ``sdfcodec encode`` picks them), or any other
    registered codec that is fitted as constructed (fusion has nothing to fit it on before it writes)."""
    from ..registry import get_codec, pretrained_codec

    if codec_id == "raw":
        if code_size not in (None, 4096):
            raise InvalidValueError(f"--code-size {code_size} does not apply to the raw codec (4096 values a block)")
        return get_codec("raw")
    if codec_id == "pca":
        return pretrained_codec("pca", code_size or 64)
    codec = get_codec(codec_id, **({"code_size": code_size} if code_size else {}))
    if not getattr(codec, "is_fitted", True):
        raise InvalidValueError(f"codec {codec_id!r} must be fitted before fusion writes with it: use --codec pca "
                                "(shipped eigenshapes) or raw, and transcode with `sdfcodec encode --model` afterwards")
    return codec


def lattice_origin(poses: np.ndarray, intrinsics: Intrinsics, voxel_size: float, depth_max: float,
                   truncation: tuple[float, float]) -> np.ndarray:
    """A map origin ``(3,)`` metres on the world block lattice (multiples of ``16 voxel_size``, as
    :func:`~sdfcodec.fusion.tsdf.fuse` aligns it) below every block that fusing depth up to ``depth_max`` from camera
    poses ``(N, 4, 4)`` can allocate: each camera centre minus the longest ray (the image corner's, at z-depth
    ``depth_max + |d_min|``) and one block of slack."""
    k = intrinsics
    corner = max(math.hypot((u - k.cx) / k.fx, (v - k.cy) / k.fy) for u in (0, k.width - 1) for v in (0, k.height - 1))
    reach = (depth_max - truncation[0]) * math.sqrt(1.0 + corner ** 2)
    block_m = BLOCK * float(voxel_size)
    lo = np.asarray(poses, dtype=np.float64)[:, :3, 3].min(axis=0) - reach - block_m
    return np.floor(lo / block_m) * block_m


class _Stored:
    """Which blocks the map holds: a boolean grid over block indices, grown on demand."""

    def __init__(self, shape=(1, 1, 1)):
        self.grid = np.zeros(tuple(max(1, int(s)) for s in shape), dtype=bool)

    def _fit(self, coords: np.ndarray) -> None:
        need = coords.max(axis=0) + 1
        if np.any(need > self.grid.shape):
            pad = [(0, max(0, int(n) - s)) for n, s in zip(need, self.grid.shape)]
            self.grid = np.pad(self.grid, pad)

    def add(self, coords: np.ndarray) -> None:
        if len(coords):
            self._fit(coords)
            self.grid[tuple(coords.T)] = True

    def holds(self, coords: np.ndarray) -> np.ndarray:
        inside = np.all(coords < np.asarray(self.grid.shape), axis=1)
        out = np.zeros(len(coords), dtype=bool)
        out[inside] = self.grid[tuple(coords[inside].T)]
        return out


def fuse_to_map(sequence: Sequence | str | Path | Iterable[Frame], output: str | Path, *, codec: Codec,
                working_set_mb: float = 512.0, voxel_size: float = 0.02,
                truncation: tuple[float, float] = (-0.04, 0.1), depth_max: float | None = 4.0,
                origin: np.ndarray | None = None, intrinsics: Intrinsics | None = None, code_dtype: str = "float32",
                overwrite: bool = False, low_water: float = 0.8, quiet: bool = False, tool: str = "sdfcodec fuse",
                device: str = "CPU:0", keep_weights: bool | None = None) -> dict[str, Any]:
    """Fuse a posed depth sequence into a compressed map at ``output`` through a working set of at most
    ``working_set_mb`` MiB of dense blocks (module docstring).

    Parameters
    ----------
    sequence : Sequence, path or iterable of Frame
        As for :func:`sdfcodec.fusion.tsdf.fuse` (an iterable needs ``intrinsics`` and ``origin``).
    output : path
        The map to write (a local directory).
    codec : Codec
        A fitted codec (e.g. ``pretrained_codec("pca", 64)``; ``get_codec("raw")`` makes it lossless).
    working_set_mb : float
        Budget of the working set, MiB (32 KiB per block).
    voxel_size, truncation, depth_max, device :
        As for :func:`~sdfcodec.fusion.tsdf.fuse`.
    origin : array-like, optional
        ``(3,)`` metres, the map's origin (voxel (0, 0, 0)); default :func:`lattice_origin` of the poses.
    code_dtype, overwrite, tool :
        As for :func:`sdfcodec.create_map`.
    low_water : float
        A page-out empties the working set down to this fraction of the budget (0 < low_water <= 1).
    quiet : bool
        No progress bar.
    keep_weights : bool, optional
        As for :func:`sdfcodec.create_map`: the weights are written while fusing (a block paged back in resumes
        from them) and, by default, dropped at commit from a map with a lossy codec (its observation mask stays).

    Returns
    -------
    dict
        The report: frames integrated/skipped, ``seconds`` and ``frames_per_s`` of the fusion loop (page-outs
        and page-ins included), ``cpu_seconds`` (the process's, all threads, in that loop), ``total_seconds``
        (with the final flush and commit), ``blocks_paged_out`` / ``blocks_paged_in`` (page-out and page-in events, block
        by block), ``page_outs`` (batches), ``blocks_flushed`` (written at the end), ``peak_working_set_blocks``
        and ``peak_working_set_mib``, ``budget_blocks``, ``peak_rss_mib`` (the process's), ``blocks`` (the map's
        coded / empty counts), ``bytes_on_disk``, ``origin``, ``stores`` ("weights", or "observation mask" when they
        were dropped at commit: ``keep_weights``).

    Raises
    ------
    InvalidValueError
        Bad parameters, a codec that is not fitted, no frame with a pose, or a frame whose blocks alone exceed
        the working set.
    ShapeError
        A depth image that does not match the intrinsics.
    """
    from ..map import create_map

    o3d = open3d_module()
    d_min, d_max = check_fusion_parameters(truncation, voxel_size, depth_max)
    if not (np.isfinite(working_set_mb) and working_set_mb > 0):
        raise InvalidValueError(f"working_set_mb must be a positive number of MiB, got {working_set_mb}")
    if not (0.0 < low_water <= 1.0):
        raise InvalidValueError(f"low_water must be in (0, 1], got {low_water}")
    if not getattr(codec, "is_fitted", True):
        raise InvalidValueError(f"online fusion encodes as it goes, so it needs a fitted codec; {codec!r} is not "
                                "(use the shipped pca, or a model trained with `sdfcodec train`)")
    if code_dtype == "int8":
        raise InvalidValueError("online fusion reads its codes back when the camera returns: use --code-dtype float32 "
                                "or float16 (transcode to int8 afterwards with `sdfcodec encode`)")
    budget = int(working_set_mb * 2**20 // BLOCK_BYTES)
    if budget < 1:
        raise InvalidValueError(f"a working set of {working_set_mb} MiB holds no block ({BLOCK_BYTES // 1024} KiB each)")
    if not isinstance(sequence, (str, Path, Sequence)) and (intrinsics is None or origin is None):
        raise InvalidValueError("fusing an iterable of frames online needs intrinsics=... and origin=...")
    sequence, frames, intrinsics, total, up = fusion_input(sequence, intrinsics)
    poses = [] if sequence is None else [e.pose for e in sequence.entries if e.pose is not None]
    if origin is None:
        if not poses:
            raise InvalidValueError("no frame with a pose to fuse; open the sequence with its ground truth")
        if depth_max is None:
            raise InvalidValueError("online fusion works out the map's origin from depth_max: give one, or origin=")
        anchor = lattice_origin(np.stack(poses), intrinsics, voxel_size, depth_max, (d_min, d_max))
    else:
        anchor = np.asarray(origin, dtype=np.float64).reshape(3)
        if not np.all(np.isfinite(anchor)):
            raise InvalidValueError(f"origin must be 3 finite metres, got {origin}")

    dev = o3d.core.Device(device)
    # capacity fixed at the budget: the hash map never rehashes (which would double its buffers)
    vbg = o3d.t.geometry.VoxelBlockGrid(("tsdf", "weight"), (o3d.core.float32, o3d.core.float32), ((1,), (1,)),
                                        float(voxel_size), BLOCK, budget + 1, dev)
    hm = vbg.hashmap()
    feed = FrameFeed(intrinsics, (d_min, d_max), voxel_size, depth_max, anchor, dev, total, quiet)
    half, shift = feed.half, feed.shift
    last_seen = np.full(budget + 1, -1, dtype=np.int64)  # frame each buffer slot was last seen in
    stored = _Stored()
    stats = {"blocks_paged_out": 0, "blocks_paged_in": 0, "page_outs": 0, "page_ins": 0, "peak": 0,
             "page_out_s": 0.0, "page_in_s": 0.0}

    def grid_blocks(buf: Any) -> tuple[np.ndarray, np.ndarray]:
        """Distances (metres, project conventions) and weights ``(n, 16, 16, 16)`` of buffer slots ``buf``."""
        s = vbg.attribute("tsdf")[buf].cpu().numpy()[..., 0].transpose(0, 3, 2, 1)
        w = np.ascontiguousarray(vbg.attribute("weight")[buf].cpu().numpy()[..., 0].transpose(0, 3, 2, 1))
        tsdf = np.clip(s * np.float32(half) + shift, d_min, d_max).astype(np.float32)
        tsdf[w <= 0] = np.float32(d_max)
        return tsdf, w

    def page_out(m, wanted: int, needed: int, frame_no: int) -> None:
        """Page out the ``wanted`` least recently seen blocks (at least ``needed``), none of frame ``frame_no``."""
        t0 = time.perf_counter()
        act = hm.active_buf_indices().to(o3d.core.int64).cpu().numpy()
        age = last_seen[act]
        order = np.argsort(age, kind="stable")[:wanted]
        order = order[age[order] < frame_no]  # never the frame's own blocks
        if len(order) < needed:
            need_mb = (budget - len(order) + needed) * BLOCK_BYTES / 2**20
            raise InvalidValueError(f"frame {frame_no} alone touches more blocks than a working set of {working_set_mb}"
                                    f" MiB holds; give --working-set-mb of at least {math.ceil(need_mb)}")
        # in slices: the copies of a slice on its way into the map (distances, weights, their normalised and
        # error-weight forms, the encoder's tensors) stay a few tens of MiB beside the working set
        for lo in range(0, len(order), PAGE_SLICE):
            sl = act[order[lo:lo + PAGE_SLICE]]
            buf = o3d.core.Tensor(sl, o3d.core.int64, dev)
            keys = hm.key_tensor()[buf].cpu().numpy().astype(np.int64)
            if keys.min() < 0:
                raise InvalidValueError(f"the fused surface reaches below origin={anchor.tolist()}; pass a lower "
                                        "origin")
            tsdf, w = grid_blocks(buf)
            m.write_blocks(keys, tsdf, weights=w)
            del tsdf, w
            stored.add(keys)
            hm.erase(o3d.core.Tensor(keys.astype(np.int32), o3d.core.int32, dev))
            last_seen[sl] = -1
            stats["blocks_paged_out"] += len(keys)
        stats["page_outs"] += 1
        stats["page_out_s"] += time.perf_counter() - t0

    def bring_in(m, coords: np.ndarray, back: np.ndarray) -> None:
        """Activate the frame's blocks ``coords`` that are not in the working set, with the map's content where
        ``back`` (bool) says it holds them (**page-in**) and zeros elsewhere (a new block, as open3d starts one).
        Set explicitly because open3d's hash map reuses the buffers of erased blocks without clearing them."""
        s = np.zeros((len(coords), BLOCK, BLOCK, BLOCK), dtype=np.float32)
        w = np.zeros_like(s)
        if back.any():
            t0 = time.perf_counter()
            reader, held = m.reader, coords[back]
            state = m.writer.state[tuple(held.T)]
            wb = read_block_rows(reader, reader.observation_arrays()[0], held).astype(np.float32)
            tsdf = np.full((len(held), BLOCK, BLOCK, BLOCK), d_max, dtype=np.float32)
            coded = state == BlockState.CODED
            if coded.any():
                # the writer's own array object: it resizes it as the grid grows (a fresh handle can be stale)
                codes = read_block_rows(reader, m.writer.codes, held[coded]).astype(np.float32)
                dec = reader.decode_codes(torch.from_numpy(codes), metres=True, coords=held[coded])
                tsdf[coded] = np.clip(dec.cpu().numpy(), d_min, d_max)
            s[back] = (tsdf - shift) / np.float32(half)
            w[back] = wb.reshape(len(held), BLOCK, BLOCK, BLOCK)
            stats["blocks_paged_in"] += len(held)
            stats["page_ins"] += 1
            stats["page_in_s"] += time.perf_counter() - t0
        buf, _ = hm.activate(o3d.core.Tensor(coords.astype(np.int32), o3d.core.int32, dev))
        buf = buf.to(o3d.core.int64)
        vbg.attribute("tsdf")[buf] = o3d.core.Tensor(to_open3d_order(s), device=dev)
        vbg.attribute("weight")[buf] = o3d.core.Tensor(to_open3d_order(w), device=dev)

    target = max(1, int(low_water * budget))
    t_start, cpu_start = time.perf_counter(), time.process_time()
    m = create_map(output, codec=codec, voxel_size=voxel_size, truncation=(d_min, d_max), origin=tuple(anchor),
                   code_dtype=code_dtype, overwrite=overwrite, tool=tool, up=up,
                   source=str(getattr(sequence, "path", "")) or None, keep_weights=keep_weights)
    with m:
        for frame, img, extrinsic in feed.inputs(frames):
            keys = feed.touched(vbg, img, extrinsic)
            buf, found = hm.find(keys)
            found_np = found.cpu().numpy().astype(bool)
            last_seen[buf.to(o3d.core.int64).cpu().numpy()[found_np]] = feed.integrated
            missing = keys.cpu().numpy().astype(np.int64)[~found_np]
            if hm.size() + len(missing) > budget:
                page_out(m, hm.size() + len(missing) - target, hm.size() + len(missing) - budget, feed.integrated)
            if len(missing):
                if missing.min() < 0:
                    raise InvalidValueError(f"frame {frame.index} reaches below origin={anchor.tolist()}; pass a "
                                            "lower origin")
                bring_in(m, missing, stored.holds(missing))
            feed.integrate(vbg, keys, img, extrinsic)
            buf, _ = hm.find(keys)
            last_seen[buf.to(o3d.core.int64).cpu().numpy()] = feed.integrated
            stats["peak"] = max(stats["peak"], int(hm.size()))
            feed.integrated += 1
        seconds, cpu_seconds = time.perf_counter() - t_start, time.process_time() - cpu_start
        feed.check()
        integrated, skipped = feed.integrated, feed.skipped
        # the working set that is left goes into the map too
        flushed = int(hm.size())
        act = hm.active_buf_indices().to(o3d.core.int64).cpu().numpy()
        for lo in range(0, len(act), PAGE_SLICE):
            buf = o3d.core.Tensor(act[lo:lo + PAGE_SLICE], o3d.core.int64, dev)
            keys = hm.key_tensor()[buf].cpu().numpy().astype(np.int64)
            tsdf, w = grid_blocks(buf)
            m.write_blocks(keys, tsdf, weights=w)
            stored.add(keys)
    info = m.info()
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # KiB on Linux
    return {"output": str(output), "codec": codec.get_config(), "frames_integrated": integrated,
            "frames_skipped": skipped, "seconds": seconds, "frames_per_s": integrated / max(seconds, 1e-9),
            # CPU seconds of the process (all threads) in the fusion loop: on a shared machine, steadier than wall
            "cpu_seconds": cpu_seconds,
            "total_seconds": time.perf_counter() - t_start,
            "working_set_mb": float(working_set_mb), "budget_blocks": budget,
            "peak_working_set_blocks": stats["peak"], "peak_working_set_mib": stats["peak"] * BLOCK_BYTES / 2**20,
            "blocks_paged_out": stats["blocks_paged_out"], "blocks_paged_in": stats["blocks_paged_in"],
            "page_outs": stats["page_outs"], "page_ins": stats["page_ins"], "page_out_seconds": stats["page_out_s"],
            "page_in_seconds": stats["page_in_s"], "blocks_flushed": flushed,
            "allocated_blocks": int(stored.grid.sum()), "blocks": info["blocks"],
            "bytes_on_disk": info["bytes_on_disk"], "peak_rss_mib": rss, "origin": [float(v) for v in anchor],
            "stores": "weights" if m.has_weights else "observation mask"}
