"""Other systems' TSDF maps into sdfcodec maps and back: :func:`import_map`, :func:`export_map`.

Import, in two passes over the source and a bounded working set:

1. the source is scanned (:func:`~sdfcodec.interop.voxblox.scan_voxblox`, or the arrays of an Open3D grid):
   its blocks' places and the range of its observed distances, nothing else is kept (40 bytes a block; with
   their assignment to map blocks below, about 100 bytes a block at the peak);
2. every source block is assigned to the 16^3 map blocks it overlaps; the assignments are sorted by the map's
   chunk of codes, and the map blocks are assembled and written a group of whole chunks at a time (about
   ``batch_blocks`` map blocks): each chunk of the map is written once, and memory holds one group (its map
   blocks and the source blocks they need), whatever the size of the source.

Positions are exact: a source voxel with global index ``g`` (block index x voxels per side + voxel index)
lies at ``(g + c) x voxel_size`` (``c`` = 0.5 for voxblox, whose voxels sample their centres, 0 for Open3D),
so the map's origin is put at ``(G0 + c) x voxel_size`` with ``G0`` the least ``g`` of the source, and source
voxel ``g`` becomes map voxel ``g - G0``, at its own world position.

Lossless by default: the ``raw`` codec with metric codes (spec section 4f: the codes are the voxels' own float32
metres, not normalised), the map's truncation chosen from the data (its least observed distance, and just above
its greatest, so that no observed voxel is clipped or taken for free space), the weights kept as float32 and
weight 0 as unobserved (the observation mask). Every observed voxel then reads back bit for bit: voxblox's
float32 distance and weight, and for Open3D ``float32(float64(tsdf) x float64(trunc_voxel_multiplier x
voxel_size))`` (Open3D stores distance divided by its truncation) and its weight. ``exact=False`` writes the
normalised raw map older readers open (distances to ``(d_max - d_min) x 2^-24``, weights float16).
What is not kept: voxblox's colour, Open3D attributes other than ``tsdf`` and ``weight``.

Export decodes a map (a region, a prefix level) to either format, a map block at a time; its voxels that were
not observed (or lie outside the region) are written with weight 0.
"""

from __future__ import annotations

import itertools
import os
import tempfile
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Sequence

import numpy as np

from ..core._validate import BLOCK
from ..errors import FormatError, InputNotFoundError, InvalidValueError
from ..core.header import BlockState
from .open3d_grid import (DEFAULT_TRUNC_VOXEL_MULTIPLIER, looks_like_open3d_grid, open3d_tsdf, open_open3d_grid,
                          write_open3d_grid)
from .voxblox import (VOXBLOX_SUFFIXES, encode_block, looks_like_voxblox, read_voxblox_blocks, scan_voxblox,
                      write_voxblox)

if TYPE_CHECKING:
    from ..codec import Codec
    from ..map.facade import Map

__all__ = ["FORMATS", "Source", "open_source", "detect_format", "import_map", "export_map", "export_format",
           "lossless_truncation"]

FORMATS = ("voxblox", "open3d")
#: Smallest positive float16 (the map stores weights as float16): a smaller positive weight is raised to it so
#: that the voxel still reads as observed.
_MIN_WEIGHT16 = float(np.float16(2.0 ** -24))
_SCAN_SLICE = 4096  # Open3D blocks scanned at a time for the range of observed distances
#: The map's block-state grid (one byte a block of its bounding box) may take at most this (1 GiB): more is a
#: source with a block far from the rest, refused before anything is allocated.
MAX_GRID_BLOCKS = 1 << 30


class Source:
    """A source TSDF as the importer sees it: ``n`` blocks of ``resolution ** 3`` voxels of ``voxel_size``
    metres, block ``b``'s voxel (0, 0, 0) at global voxel index ``starts[b]`` ``(n, 3)`` int64, voxel ``g`` at
    ``(g + centre) x voxel_size``; ``read(ids)`` gives distances (metres) and weights ``(k, r, r, r)`` float32,
    voxels indexed ``(x, y, z)``; ``d_range`` the least and greatest observed distance (None: none)."""

    def __init__(self, kind: str, path: Path, voxel_size: float, resolution: int, starts: np.ndarray,
                 centre: float, d_range: tuple[float, float] | None, read: Callable, close: Callable = lambda: None):
        self.kind, self.path, self.voxel_size, self.resolution = kind, path, voxel_size, resolution
        self.starts, self.centre, self.d_range, self.read, self.close = starts, centre, d_range, read, close


def detect_format(path: str | os.PathLike) -> str:
    """``"voxblox"`` or ``"open3d"`` from the file's content (not its name)."""
    p = Path(path)
    if not p.is_file():
        raise InputNotFoundError(f"no map file at {p}")
    with open(p, "rb") as f:
        head = f.read(32)
    if head[:4] == b"PK\x03\x04":
        if looks_like_open3d_grid(p):
            return "open3d"
        raise FormatError(f"{p} is a zip/npz archive but not an Open3D VoxelBlockGrid (no key, block_resolution, "
                          "voxel_size arrays); give --format or a grid saved with VoxelBlockGrid.save")
    if looks_like_voxblox(head):
        return "voxblox"
    raise FormatError(f"cannot tell the format of {p} from its content (neither a voxblox layer nor an Open3D "
                      "VoxelBlockGrid .npz); pass --format voxblox or --format open3d")


def open_source(path: str | os.PathLike, format: str | None = None, *,
                trunc_voxel_multiplier: float = DEFAULT_TRUNC_VOXEL_MULTIPLIER) -> Source:
    """Scan ``path`` (format detected from its content when None) into a :class:`Source`."""
    fmt = format or detect_format(path)
    if fmt == "voxblox":
        ix = scan_voxblox(path)
        f = open(ix.path, "rb")
        return Source("voxblox", ix.path, ix.voxel_size, ix.voxels_per_side, ix.block_index * ix.voxels_per_side,
                      0.5, ix.d_range, lambda ids: read_voxblox_blocks(ix, ids, f), f.close)
    if fmt == "open3d":
        if not (np.isfinite(trunc_voxel_multiplier) and trunc_voxel_multiplier > 0):
            raise InvalidValueError(f"--trunc-voxel-multiplier must be a positive number, got {trunc_voxel_multiplier}")
        g = open_open3d_grid(path)
        unit = float(trunc_voxel_multiplier) * g.voxel_size
        lo, hi = np.inf, -np.inf
        for i in range(0, len(g.keys), _SCAN_SLICE):  # a slice at a time: memory-mapped arrays stay on disk
            d, w = g.read_blocks(np.arange(i, min(i + _SCAN_SLICE, len(g.keys))), unit)
            seen = w > 0
            if not np.isfinite(w).all() or (w < 0).any():
                raise FormatError(f"{g.path}: a weight is negative or NaN/Inf")
            if seen.any():
                if not np.isfinite(d[seen]).all():
                    raise FormatError(f"{g.path}: an observed voxel's tsdf is NaN/Inf")
                lo, hi = min(lo, float(d[seen].min())), max(hi, float(d[seen].max()))
        return Source("open3d", g.path, g.voxel_size, g.resolution, g.keys * g.resolution, 0.0,
                      None if lo > hi else (lo, hi), lambda ids: g.read_blocks(np.asarray(ids), unit))
    raise InvalidValueError(f"--format must be one of {', '.join(FORMATS)}, got {format!r}")


def lossless_truncation(d_range: tuple[float, float], voxel_size: float) -> tuple[float, float]:
    """A map truncation ``(d_min, d_max)`` holding every observed distance of ``d_range`` unclipped: ``d_min`` the
    least (or ``-voxel_size`` when none is negative), ``d_max`` a thousandth of the range above the greatest, so
    that no observed voxel normalises to within the writer's free-space tolerance of 1.0."""
    lo, hi = d_range
    d_min = min(float(lo), -float(voxel_size))
    top = max(float(hi), float(voxel_size))
    return d_min, top + 1e-3 * (top - d_min)


def _assignments(src: Source, g0: np.ndarray, chunk: int) -> tuple[np.ndarray, np.ndarray]:
    """``(source block id, map block (3,))`` pairs of every map block each source block overlaps, sorted by the
    map's chunk of codes, then by map block."""
    r = src.resolution
    local = src.starts - g0
    first, last = local // BLOCK, (local + r - 1) // BLOCK
    span = last - first + 1
    ids, blocks = [], []
    for d in itertools.product(*(range(int(s)) for s in span.max(axis=0))) if len(span) else ():
        sel = np.flatnonzero((span > np.asarray(d)).all(axis=1))
        ids.append(sel)
        blocks.append(first[sel] + np.asarray(d))
    ids = np.concatenate(ids) if ids else np.zeros(0, np.int64)
    blocks = np.concatenate(blocks) if blocks else np.zeros((0, 3), np.int64)
    ch = blocks // chunk
    order = np.lexsort((blocks[:, 2], blocks[:, 1], blocks[:, 0], ch[:, 2], ch[:, 1], ch[:, 0]))
    return ids[order], blocks[order]


def _groups(blocks: np.ndarray, chunk: int, batch_blocks: int) -> list[tuple[int, int]]:
    """Ranges ``[lo, hi)`` of the sorted assignments, each whole chunks of the map holding about
    ``batch_blocks`` map blocks."""
    if not len(blocks):
        return []
    new_block = np.r_[True, (np.diff(blocks, axis=0) != 0).any(axis=1)]
    ch = blocks // chunk
    new_chunk = np.r_[True, (np.diff(ch, axis=0) != 0).any(axis=1)]
    n_blocks = np.cumsum(new_block)
    out, lo, start_count = [], 0, 0
    for i in np.flatnonzero(new_chunk)[1:]:
        if n_blocks[i - 1] - start_count >= batch_blocks:
            out.append((lo, int(i)))
            lo, start_count = int(i), int(n_blocks[i - 1])
    out.append((lo, len(blocks)))
    return out


def _assemble(src: Source, g0: np.ndarray, ids: np.ndarray, blocks: np.ndarray, d_max: float, exact: bool
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The map blocks ``(m, 3)`` of one group of assignments with their distances (``d_max`` where nothing was
    observed) and weights ``(m, 16, 16, 16)`` float32 (raised to float16's least where that map stores them)."""
    ub, inv = np.unique(blocks, axis=0, return_inverse=True)
    inv = inv.reshape(-1)
    need, where = np.unique(ids, return_inverse=True)
    where = where.reshape(-1)
    sd, sw = src.read(need)
    dist = np.full((len(ub), BLOCK, BLOCK, BLOCK), np.float32(d_max), dtype=np.float32)
    weight = np.zeros_like(dist)
    r = src.resolution
    local = src.starts[ids] - g0
    for k in range(len(ids)):
        s0, m0 = local[k], ub[inv[k]] * BLOCK
        lo, hi = np.maximum(s0, m0), np.minimum(s0 + r, m0 + BLOCK)
        a = tuple(slice(int(x), int(y)) for x, y in zip(lo - s0, hi - s0))
        b = tuple(slice(int(x), int(y)) for x, y in zip(lo - m0, hi - m0))
        dist[(inv[k],) + b] = sd[(where[k],) + a]
        weight[(inv[k],) + b] = sw[(where[k],) + a]
    unseen = weight <= 0
    dist[unseen] = np.float32(d_max)
    if not exact:  # float16 weights: the least positive one, so that the voxel still reads as observed
        weight[(weight > 0) & (weight < _MIN_WEIGHT16)] = _MIN_WEIGHT16
    return ub, dist, weight


def import_map(src: str | os.PathLike, out: str | os.PathLike, *, format: str | None = None, codec: Codec | None = None,
               truncation: Sequence[float] | None = None, trunc_voxel_multiplier: float = DEFAULT_TRUNC_VOXEL_MULTIPLIER,
               code_dtype: str = "float32", overwrite: bool = False, batch_blocks: int = 1024,
               progress: Callable[[int], None] | None = None, exact: bool | None = None,
               **create_kw: Any) -> dict[str, Any]:
    """Import a voxblox TSDF layer or an Open3D VoxelBlockGrid file into a new map at ``out`` (module docstring).

    Parameters
    ----------
    src : path
        ``.voxblox``/``.vxblx``/``.tsdf`` layer file, or ``.npz`` of ``VoxelBlockGrid.save``.
    out : path
        The map to write (a local directory, written atomically: nothing appears there unless it completes).
    format : {"voxblox", "open3d"}, optional
        Default: detected from the content.
    codec : Codec, optional
        Default ``get_codec("raw")`` (lossless). Any fitted codec.
    truncation : (d_min, d_max), optional
        Metres; default :func:`lossless_truncation` of the data. One that would clip an observed voxel is
        refused.
    trunc_voxel_multiplier : float
        Open3D grids only: Open3D's truncation in voxels (its ``integrate`` default, 8); its ``tsdf`` values are
        distances in units of ``trunc_voxel_multiplier x voxel_size``.
    code_dtype, overwrite, **create_kw
        As for :func:`sdfcodec.create_map`.
    batch_blocks : int
        About how many map blocks are assembled and written at once (the working set).
    exact : bool, optional
        Metric codes and float32 weights (spec section 4f; every observed voxel and weight bit for bit). Default:
        True for the raw codec with float32 codes and no residual stage, else False (lossy codecs normalise).
    progress : callable, optional
        Called with the number of map blocks written after each group.

    Returns
    -------
    dict
        ``output``, ``format``, ``source_blocks``, ``voxels_per_side``, ``voxel_size``, ``origin``,
        ``truncation``, ``observed_voxels``, ``map_blocks`` (written), ``blocks`` (the map's coded / empty
        counts), ``seconds``, ``codec``.

    Raises
    ------
    FormatError
        The source is malformed (one line naming what: a truncated stream, a voxel count mismatch, a layer that
        is not a TSDF, absurd counts...). InvalidValueError: bad parameters, a truncation that clips the data.
    """
    from ..map import create_map
    from ..registry import get_codec

    t0 = time.perf_counter()
    if not (isinstance(batch_blocks, int) and batch_blocks > 0):
        raise InvalidValueError(f"batch_blocks must be a positive integer, got {batch_blocks!r}")
    source = open_source(src, format, trunc_voxel_multiplier=trunc_voxel_multiplier)
    try:
        vs = float(source.voxel_size)
        if source.d_range is None:
            raise FormatError(f"{source.path} holds no observed voxel (every weight is 0): nothing to import")
        if truncation is None:
            trunc = lossless_truncation(source.d_range, vs)
        else:
            trunc = (float(truncation[0]), float(truncation[1]))
            lo, hi = source.d_range
            if lo < trunc[0] or hi > trunc[1]:
                raise InvalidValueError(f"truncation [{trunc[0]}, {trunc[1]}] m would clip observed distances of "
                                        f"{source.path} (they span [{lo}, {hi}] m); widen it or leave it out")
        codec = get_codec("raw") if codec is None else codec
        if exact is None:
            exact = (codec.codec_id == "raw" and code_dtype == "float32" and create_kw.get("max_error") is None
                     and not create_kw.get("sign_exact") and create_kw.get("variable_rate") is None)
        g0 = source.starts.min(axis=0) if len(source.starts) else np.zeros(3, np.int64)
        origin = tuple(float((g + source.centre) * vs) for g in g0)
        extent = (source.starts - g0 + source.resolution).max(axis=0)
        shape = tuple(int(-(-int(e) // BLOCK) * BLOCK) for e in extent)
        grid = [n // BLOCK for n in shape]
        if int(np.prod(grid, dtype=object)) > MAX_GRID_BLOCKS:
            raise FormatError(f"{source.path}: its blocks span {grid} map blocks, whose block-state grid alone "
                              f"would take more than {MAX_GRID_BLOCKS >> 20} MiB; a block far from the rest (a corrupt "
                              "file?) or a map too large for one sdfcodec map: split it")
        m = create_map(out, codec=codec, voxel_size=vs, truncation=trunc, origin=origin, shape_voxels=shape,
                       code_dtype=code_dtype, overwrite=overwrite, tool="sdfcodec import", source=str(source.path),
                       exact=bool(exact), **create_kw)
        written = observed = 0
        with m:
            chunk = m.writer.codes_spec.chunk_blocks
            ids, blocks = _assignments(source, g0, chunk)
            for lo, hi in _groups(blocks, chunk, batch_blocks):
                coords, dist, weight = _assemble(source, g0, ids[lo:hi], blocks[lo:hi], trunc[1], bool(exact))
                seen = (weight > 0).reshape(len(coords), -1)
                keep = seen.any(axis=1)
                if keep.any():
                    m.write_blocks(coords[keep], dist[keep], weights=weight[keep])
                written += int(keep.sum())
                observed += int(seen.sum())
                if progress is not None:
                    progress(int(keep.sum()))
            del ids, blocks
        info = m.info()
    finally:
        source.close()
    return {"output": str(out), "format": source.kind, "source": str(source.path),
            "source_blocks": int(len(source.starts)), "voxels_per_side": int(source.resolution), "voxel_size": vs,
            "origin": list(origin), "truncation": list(trunc), "observed_voxels": observed, "map_blocks": written,
            "blocks": info["blocks"], "codec": codec.get_config(), "exact": bool(exact),
            "seconds": time.perf_counter() - t0}


def _lattice(m: Map, centre: float, per_side: int, fmt: str) -> tuple[np.ndarray, list[float]]:
    """The global voxel index of map voxel (0, 0, 0) on the target format's lattice (voxel ``g`` at
    ``(g + centre) x voxel_size``), and the shift (metres) that putting the map there costs (0 for a map whose
    origin is on that lattice, as every imported map's is)."""
    q = np.asarray(m.origin, dtype=np.float64) / m.voxel_size - centre
    g0 = np.round(q).astype(np.int64)
    shift = [float(v) for v in (g0 - q) * m.voxel_size]
    if (g0 % per_side).any():
        raise InvalidValueError(f"the map's origin {tuple(m.origin)} is voxel {tuple(int(v) for v in g0)} of the {fmt} "
                                f"lattice, not a multiple of the {per_side} voxels of its blocks: choose a block size "
                                f"dividing {tuple(int(v) for v in g0)}")
    return g0, shift


def _export_blocks(m: Map, region: Any, units: str, level: int | None) -> Any:
    """Yield ``(coords (n, 3), distances (n, 16, 16, 16) metres, weights (n, 16, 16, 16))`` of the map's coded
    and observed-empty blocks touching ``region``; weight 0 on voxels not observed or outside the region."""
    from ..map.format import region_voxels

    box = region_voxels(region, units, m.shape_voxels, m.origin, m.voxel_size)
    lo = np.asarray([a for a, _ in box])
    hi = np.asarray([b for _, b in box])

    def weights_of(coords: np.ndarray) -> np.ndarray:
        w = m.read_weights(coords) if m.has_weights else m.read_observed(coords).astype(np.float32)
        obs = m.read_observed(coords)
        # an observed voxel keeps its weight (exact in a map with float32 weights), or the least float16 one
        w = np.where(obs, np.where(w > 0, w, _MIN_WEIGHT16), 0).astype(np.float32)
        inside = np.ones_like(obs)
        for c, b in enumerate(coords):
            v0 = b * BLOCK
            if (v0 < lo).any() or (v0 + BLOCK > hi).any():
                a, z = np.clip(lo - v0, 0, BLOCK), np.clip(hi - v0, 0, BLOCK)
                cut = np.zeros((BLOCK,) * 3, dtype=bool)
                cut[a[0]:z[0], a[1]:z[1], a[2]:z[2]] = True
                inside[c] = cut
        return np.where(inside, w, np.float32(0))

    for coords, blocks in m.iter_decoded(box, level=level):
        yield coords, np.asarray(blocks, dtype=np.float32), weights_of(coords)
    states = m.block_states()
    b0, b1 = lo // BLOCK, -(-hi // BLOCK)
    sub = states[b0[0]:b1[0], b0[1]:b1[1], b0[2]:b1[2]]
    empty = np.argwhere(sub == BlockState.EMPTY) + b0
    for i in range(0, len(empty), 4096):
        c = empty[i:i + 4096]
        yield c, np.full((len(c), BLOCK, BLOCK, BLOCK), np.float32(m.truncation[1])), weights_of(c)


def export_format(out: str | os.PathLike) -> str:
    """The format :func:`export_map` writes to a file named ``out`` by default: ``voxblox`` for a voxblox suffix
    (:data:`~sdfcodec.interop.voxblox.VOXBLOX_SUFFIXES`), ``open3d`` for ``.npz``.

    Raises:
        InvalidValueError: any other name (names the suffixes, and ``--format``)."""
    suffix = Path(out).suffix.lower()
    if suffix in VOXBLOX_SUFFIXES:
        return "voxblox"
    if suffix == ".npz":
        return "open3d"
    raise InvalidValueError(f"cannot tell the format to export from the name {Path(out).name!r}: name it "
                            f"{' or '.join(VOXBLOX_SUFFIXES)} (voxblox) or .npz (open3d), or pass --format")


def export_map(map_path: str | os.PathLike, out: str | os.PathLike, *, format: str | None = None,
               region: Any = None, units: str = "voxels", level: int | None = None,
               voxels_per_side: int | None = None, trunc_voxel_multiplier: float = DEFAULT_TRUNC_VOXEL_MULTIPLIER,
               overwrite: bool = False) -> dict[str, Any]:
    """Decode a map (or a ``region`` of it, at a prefix ``level``) to a voxblox TSDF layer file or an Open3D
    VoxelBlockGrid ``.npz`` at ``out`` (written to a temporary file beside it, then renamed into place).

    ``voxels_per_side``: the target's block size (voxblox ``voxels_per_side``, Open3D ``block_resolution``), a
    divisor of 16 (default 16; a map imported from voxblox exports back at its own 8 when given 8). Voxels
    not observed, or outside the region, get weight 0; colour is 0. Returns a summary (``blocks`` written,
    ``observed_voxels``, ``shift``: metres the voxels moved onto the target's lattice, 0 for maps imported
    from it). ``format``: ``voxblox`` or ``open3d``; by default told by the name of ``out`` (a voxblox suffix,
    :data:`~sdfcodec.interop.voxblox.VOXBLOX_SUFFIXES`, or ``.npz``).
    """
    from ..map import open_map

    format = export_format(out) if format is None else format
    if format not in FORMATS:
        raise InvalidValueError(f"--format must be one of {', '.join(FORMATS)}, got {format!r}")
    n = BLOCK if voxels_per_side is None else int(voxels_per_side)
    if n <= 0 or BLOCK % n:
        raise InvalidValueError(f"voxels per side must divide {BLOCK} (1, 2, 4, 8 or 16), got {voxels_per_side}")
    out = Path(out)
    if out.exists() and not overwrite:
        raise InvalidValueError(f"{out} exists; pass --overwrite to replace it")
    if out.exists() and not out.is_file():
        raise InvalidValueError(f"{out} exists and is not a file; nothing was changed")
    m = open_map(map_path)
    centre = 0.5 if format == "voxblox" else 0.0
    g0, shift = _lattice(m, centre, n, format)
    vs = m.voxel_size
    k = BLOCK // n
    sub = np.stack(np.meshgrid(*[np.arange(k)] * 3, indexing="ij"), -1).reshape(-1, 3)
    count = observed = 0
    keys, tsdfs, weights = [], [], []
    unit = float(trunc_voxel_multiplier) * vs
    tmp = out.with_name(f".{out.name}.tmp-{os.getpid()}")
    try:
        with tempfile.TemporaryFile(dir=out.parent) as body:
            for coords, dist, wt in _export_blocks(m, region, "voxels" if units is None else units, level):
                for c, d, w in zip(coords, dist, wt):
                    for s in sub:
                        sl = tuple(slice(int(a) * n, int(a) * n + n) for a in s)
                        ws = w[sl]
                        if not (ws > 0).any():
                            continue
                        ds = np.where(ws > 0, d[sl], np.float32(0))
                        idx = (g0 + c * BLOCK + s * n) // n
                        if format == "voxblox":
                            body.write(encode_block(idx, ds, ws, vs))
                        else:
                            keys.append(idx)
                            tsdfs.append(open3d_tsdf(ds, unit))
                            weights.append(ws)
                        count += 1
                        observed += int((ws > 0).sum())
            with open(tmp, "wb") as f:
                if format == "voxblox":
                    write_voxblox(f, vs, n, count, body)
                else:
                    shape = (0, n, n, n)
                    write_open3d_grid(f, np.asarray(keys, dtype=np.int64).reshape(-1, 3),
                                      np.stack(tsdfs) if tsdfs else np.zeros(shape, np.float32),
                                      np.stack(weights) if weights else np.zeros(shape, np.float32), vs)
        os.replace(tmp, out)
    finally:
        if tmp.exists():
            tmp.unlink()
    return {"output": str(out), "format": format, "blocks": count, "voxels_per_side": n, "observed_voxels": observed,
            "voxel_size": vs, "shift": shift, "level": level or m.code_size}
