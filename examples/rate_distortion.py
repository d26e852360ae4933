"""Rate-distortion: reconstruction error against bytes per block actually stored, for every learned codec (codes
as float32, float16 and int8 in a real map; int8 with per-component scales simulated), ZFP, a 3-D DCT
truncation baseline and Blosc-compressed float16 raw blocks. Writes docs/rate-distortion.json, docs/rate-distortion.png and its section ("codecs") of docs/rate-distortion.md.

    python examples/rate_distortion.py                 # kitchen + synthetic room (a few minutes)
    python examples/rate_distortion.py --quick         # a small synthetic map only (the test's path)

Data sets (normalised units v = (d - d_min) / (d_max - d_min), d in [-0.04, 0.1] m, so 1 unit = 0.14 m):

``kitchen``
    7-Scenes redkitchen fused at 2 cm (``sdfcodec.fusion.tsdf.fuse``), the allocated blocks of the second half along
    x (``coords[:, 0] > grid_shape[0] // 2``): the split the shipped PCA was *not* trained on, exactly as
    ``examples/eval_codecs.py`` takes it. The fused blocks and their observation (fusion weight > 0) are cached
    in ``--workdir``.
``synthetic``
    ``sdfcodec.data.render.room_scene(seed=0, geometry="rich", ceiling=True)`` sampled at 2 cm with a 16 cm
    margin (``eval_codecs.py``'s "synthetic map"), an exact SDF observed everywhere.
``synthetic (quick)``
    ``--quick``: a small corner of that room made fused-like (:func:`fused_like`: voxels at ``d_min``, more
    than 4 cm behind a surface, unobserved and read ``d_max``, as fusion leaves them), so the test exercises
    the fused-map path below.

Fused-map data sets (those with an observation: the kitchen, the quick corner) are measured as sdfcodec now
stores fused maps, too: each learned codec is also written **surface-true** (``write_blocks(...,
observed=...)``: observation mask, surface-weighted least squares, unobserved voxels decode to ``d_max``;
docs/surface.md), its bytes counting the mask chunks (``observed/``) with the codes; the plain maps (no
observation, every voxel fitted alike) are what every other method is compared with on the MSE. And every
point of a fused-map data set gets the **surface metrics** of ``sdfcodec.core.surface.compare_volumes`` against
the lossless blocks (Chamfer-L1, F-score at 1 and 2 voxels, sign agreement, near-surface RMSE and bias; the
band over observed voxels only), on the dense volume of the data set's blocks (blocks no method codes read
``d_max``): a point's ``surface`` dict, metres.

Every method is measured on the same non-empty blocks (blocks that are not all free space, i.e. what a map
codes); an empty block stores no code in any method, only its state. Errors: per-voxel MSE and per-block SSE
(sum over the block's 4096 voxels, mean over blocks). Bytes per block:

* learned codecs, float32 / float16 / int8 codes: a real map is written with ``sdfcodec.create_map(...,
  code_dtype=...)`` and ``write_blocks``; bytes = (chunk files of ``codes/``, ``code_scale/`` (int8: a float32
  offset and scale per block, spec section 4a), ``state/`` and, surface-true, ``observed/``) / coded blocks,
  read from the file system. The
  codec's learned state (``codec/``) and the Zarr metadata documents (``zarr.json``) are per map, not per
  block, and are reported separately. The error is that of the blocks decoded from the map
  (``Map.iter_decoded``).
* int8 codes with per-component scales: SIMULATED, not a map format. The float32 codes read from the map are
  quantised by ``sdfcodec.core.quantize.quantize_codes(per="component")`` (one float32 offset and scale per code
  element, 8 k bytes per map); bytes = the int8 codes and scales compressed with the map's Blosc/zstd (level 3,
  byte shuffle) through numcodecs in chunks of 512 blocks, plus the float32 map's ``state/`` bytes.
* ZFP (zfpy): each 16^3 block compressed on its own, fixed-rate and fixed-accuracy; bytes = the stream length
  (which includes zfpy's 16-byte header; ``payload_bytes_per_block`` is without it).
* DCT: ``scipy.fft.dctn(v, norm="ortho")``, the K coefficients of lowest frequency kept (order: i + j + k, then
  i^2 + j^2 + k^2, then C order) as float16; bytes = 2 K (positions are implied).
* Blosc float16: v as float16, Blosc/zstd level 3 with shuffle in chunks of 64 blocks.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shlex
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _page import replace_section  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
TRUNC, VS, BLOCK = (-0.04, 0.1), 0.02, 16
NV = BLOCK ** 3
FLOAT32_BLOCK_BYTES = NV * 4  # 16 KiB: the dense float32 block the compression ratios are against
ZFP_HEADER = 16

# zfpy 1.0.1 corrupts the heap (glibc: "malloc(): smallbin double linked list corrupted", later and elsewhere)
# at rate 0.125 on 16^3 float32 blocks, i.e. 8 bits per 4^3 zfp block, below the 1 + 8 bits a float32 block
# needs; 10 bits (0.15625) and up ran clean under MALLOC_CHECK_=3, so rates below that are refused.
ZFP_MIN_RATE = 10 / 64
ZFP_RATES = (0.15625, 0.1875, 0.25, 0.375, 0.5, 1.0, 2.0, 4.0, 8.0)
ZFP_TOLERANCES = (0.2, 0.1, 0.05, 0.02, 0.01, 0.005, 0.002, 0.001, 1e-4)
DCT_KS = (16, 32, 64, 128, 256, 512, 1024, 2048, 4096)


# ----------------------------------------------------------------------------------------------- data sets
def kitchen_blocks(path: Path, workdir: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Held-out (second half along x) allocated blocks of the fused kitchen: coords (shifted to start at 0),
    metres and the observation (fusion weight > 0). Cached in ``workdir``."""
    cache = workdir / "kitchen-heldout-observed.npz"
    if cache.exists():
        z = np.load(cache)
        coords, tsdf, observed = z["coords"], z["tsdf"], np.unpackbits(z["observed"], axis=1).astype(bool)
    else:
        from sdfcodec.fusion.tsdf import fuse

        fused = fuse(path, voxel_size=VS, truncation=TRUNC)
        held = fused.select(fused.coords[:, 0] > fused.grid_shape[0] // 2)  # as eval_codecs.py
        coords, tsdf, observed = held.coords, held.tsdf, (held.weights > 0).reshape(len(held.coords), -1)
        workdir.mkdir(parents=True, exist_ok=True)
        np.savez(cache, coords=coords, tsdf=tsdf, observed=np.packbits(observed, axis=1))
    return (coords - coords.min(axis=0), tsdf.astype(np.float32),
            np.ascontiguousarray(observed.reshape(len(coords), BLOCK, BLOCK, BLOCK)))


def synthetic_blocks(quick: bool, shift: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The furnished room of eval_codecs.py's "synthetic map" cut into blocks: all grid blocks (coords, metres).
    ``quick``: a 64 x 64 x 48-voxel corner (floor, two walls, some furniture), sampled with the lattice moved by
    0.3 voxel so that no wall lies on voxel centres (where the exact distance is 0, the side a crossing falls on
    is a rounding accident, which would dominate its surface metrics). ``shift``: the lattice shift in voxels
    (default: 0.3 when ``quick``, else 0, as this page's sections were measured)."""
    from sdfcodec.core.blocks import split_blocks
    from sdfcodec.data.render import room_scene
    from sdfcodec.core.sdf import sample_volume

    room, margin = room_scene(seed=0, geometry="rich", ceiling=True), 0.16
    shape = (64, 64, 48) if quick else tuple(int(round((s + 2 * margin) / VS)) for s in (4.0, 3.2, 2.5))
    shift = (0.3 if quick else 0.0) * VS if shift is None else float(shift) * VS
    vol = sample_volume(room.sdf, shape, VS, origin=(-margin + shift,) * 3, truncation=TRUNC)
    b = split_blocks(vol, fill=TRUNC[1])
    coords = np.argwhere(np.ones(b.shape[:3], bool)).astype(np.int64)
    return coords, np.ascontiguousarray(b.reshape(-1, BLOCK, BLOCK, BLOCK), dtype=np.float32)


def fused_like(tsdf: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """An exact truncated SDF as fusion would leave it: voxels at ``d_min`` (more than ``|d_min|`` behind a
    surface, where fusion never integrates) unobserved, reading ``d_max``. Returns (metres, observed)."""
    observed = tsdf > TRUNC[0] + 1e-6
    return np.where(observed, tsdf, np.float32(TRUNC[1])).astype(np.float32), observed


def normalised(tsdf: np.ndarray) -> np.ndarray:
    from sdfcodec.core.blocks import normalise

    return normalise(tsdf, *TRUNC)


def nonempty_mask(v: np.ndarray) -> np.ndarray:
    """Blocks a map codes: not every voxel free (the map's own test, ``v >= 1 - 1e-6`` everywhere = empty)."""
    return ~(v >= 1 - 1e-6).reshape(len(v), -1).all(axis=1)


def block_sse(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    return ((np.asarray(y, np.float64) - np.asarray(x, np.float64)) ** 2).reshape(len(x), -1).sum(axis=1)


def point(dataset: str, codec: str, setting: str, bytes_per_block: float, x: np.ndarray, y: np.ndarray,
          ref: "SurfaceReference | None" = None, **extra) -> dict:
    """One measured point; with ``ref`` (a fused-map data set) also its surface metrics."""
    sse = block_sse(x, y)
    out = {"dataset": dataset, "codec": codec, "setting": setting, "bytes_per_block": float(bytes_per_block),
           "ratio": FLOAT32_BLOCK_BYTES / float(bytes_per_block), "mse_voxel": float(sse.mean() / NV),
           "sse_block": float(sse.mean()), "max_abs_error": float(np.abs(np.asarray(y, np.float64) - x).max()),
           "blocks": int(len(x)), **extra}
    if ref is not None:
        out["surface"] = ref.metrics(y)
    return out


# --------------------------------------------------------------------------------------- surface metrics
class SurfaceReference:
    """The lossless blocks of a fused-map data set as one dense volume (metres, blocks no method codes at
    ``d_max``) with its observation, to judge decoded blocks by their surfaces (``compare_volumes``)."""

    def __init__(self, coords: np.ndarray, tsdf: np.ndarray, observed: np.ndarray, coded: np.ndarray):
        self.coords = coords[coded]
        self.shape = tuple(int(n) * BLOCK for n in coords.max(axis=0) + 1)
        self.original = self._dense(tsdf[coded])
        self.observed = np.zeros(self.shape, bool)
        self._scatter(self.observed, observed[coded])

    def _scatter(self, vol: np.ndarray, blocks: np.ndarray) -> None:
        g = vol.reshape(self.shape[0] // BLOCK, BLOCK, self.shape[1] // BLOCK, BLOCK, self.shape[2] // BLOCK, BLOCK)
        g[self.coords[:, 0], :, self.coords[:, 1], :, self.coords[:, 2], :] = blocks

    def _dense(self, metres: np.ndarray) -> np.ndarray:
        vol = np.full(self.shape, TRUNC[1], np.float32)
        self._scatter(vol, metres)
        return vol

    def metrics(self, y: np.ndarray) -> dict:
        """``SurfaceMetrics.to_dict()`` (metres) of the decoded non-empty blocks ``y`` (normalised, in the
        order of the coded blocks)."""
        from sdfcodec.core.surface import compare_volumes

        decoded = self._dense(np.asarray(y, np.float32) * (TRUNC[1] - TRUNC[0]) + TRUNC[0])
        return compare_volumes(self.original, decoded, VS, observed=self.observed).to_dict()


# ------------------------------------------------------------------------------------------ map byte counts
def map_bytes(path: Path) -> dict:
    """Bytes on disk of a committed map directory, by part: chunk files of codes/ (with code_scale/ of int8 maps)
    and state/, the codec's learned
    state (codec/, its metadata included), the Zarr metadata documents of codes/, state/ and the group, other."""
    out = {"codes": 0, "state": 0, "mask": 0, "codec_state": 0, "metadata": 0, "other": 0}
    for dirpath, _, files in os.walk(path):
        rel = Path(dirpath).relative_to(path)
        top = rel.parts[0] if rel.parts else ""
        for f in files:
            n = (Path(dirpath) / f).stat().st_size
            if top == "codec":
                out["codec_state"] += n
            elif f == "zarr.json" or (not rel.parts and f in ("manifest.json", "signature.json")):
                out["metadata"] += n  # the integrity manifest and a signature are the map's metadata too
            elif top in ("codes", "code_scale"):
                out["codes"] += n
            elif top == "state":
                out["state"] += n
            elif top == "observed":
                out["mask"] += n
            else:
                out["other"] += n
    out["total"] = sum(out.values())
    return out


# ----------------------------------------------------------------------------------------- learned codecs
def learned_codecs(quick: bool) -> dict:
    import sdfcodec

    codecs = {f"pca-{k}": sdfcodec.pretrained_codec("pca", k) for k in ((16, 64) if quick else (16, 32, 64, 128))}
    if not quick:
        codecs["ae-64"] = sdfcodec.pretrained_codec("ae", 64)
        codecs["parallel 64+64"] = sdfcodec.pretrained_codec("parallel")
        codecs["sequential 64+64"] = sdfcodec.pretrained_codec("sequential")
    return codecs


def blosc():
    from numcodecs import Blosc

    return Blosc(cname="zstd", clevel=3, shuffle=Blosc.SHUFFLE)


def compressed_size(a: np.ndarray, chunk: int) -> int:
    c = blosc()
    return sum(len(c.encode(np.ascontiguousarray(a[i:i + chunk]))) for i in range(0, len(a), chunk))


def measure_learned(name: str, codec, dataset: str, coords: np.ndarray, tsdf: np.ndarray, x: np.ndarray,
                    coded: np.ndarray, workdir: Path, observed: np.ndarray | None = None,
                    ref: SurfaceReference | None = None) -> list[dict]:
    """float32, float16 and int8 maps (stored bytes, decoded error), plain and, given the blocks'
    ``observed`` voxels, surface-true; and int8 with per-component scales simulated from the plain float32
    codes."""
    import sdfcodec
    from sdfcodec.core.quantize import dequantize_codes, quantize_codes

    pts, codes32, state_bytes = [], None, None
    index = {tuple(c): i for i, c in enumerate(coords[coded])}
    modes = ("plain",) if observed is None else ("plain", "surface-true")
    for mode in modes:
        for dtype in ("float32", "float16", "int8"):
            tag = "" if mode == "plain" else "-surface-true"
            path = workdir / "maps" / f"{dataset}-{name.replace(' ', '_').replace('+', '_')}-{dtype}{tag}.sdfz"
            with sdfcodec.create_map(path, codec=codec, voxel_size=VS, truncation=TRUNC, code_dtype=dtype,
                                     overwrite=True, tool="examples/rate_distortion.py") as m:
                m.write_blocks(coords, tsdf, observed=None if mode == "plain" else observed)
            b = map_bytes(path)
            m = sdfcodec.open_map(path)
            n = m.count_states()["coded"]
            assert n == len(x), f"{name} {dtype} {mode}: map coded {n} blocks, expected {len(x)}"
            y = np.empty_like(x)
            for c, blocks in m.iter_decoded():
                y[[index[tuple(cc)] for cc in c]] = normalised(blocks)
            if dtype == "float32" and mode == "plain":
                cc, codes32 = m.read_codes()
                order = [index[tuple(c)] for c in cc]
                codes32 = codes32[np.argsort(order)]
                state_bytes = b["state"]
            m.close()
            setting = ("int8 per-block" if dtype == "int8" else dtype) + tag.replace("-", " ", 1)
            stored = b["codes"] + b["state"] + b["mask"]
            pts.append(point(dataset, name, setting, stored / n, x, y, ref, code_size=codec.code_size,
                             kind="map", surface_true=mode != "plain", map=str(path.relative_to(workdir)),
                             map_bytes=b, codec_state_bytes=b["codec_state"], metadata_bytes=b["metadata"],
                             bytes_per_block_with_codec_state=(stored + b["codec_state"]) / n))
    q, scales = quantize_codes(codes32, per="component")
    deq = dequantize_codes(q, scales, per="component")
    est = compressed_size(q, 512) + compressed_size(scales, 1 << 20)
    y = np.concatenate([np.asarray(codec.decode(deq[i:i + 4096])) for i in range(0, len(deq), 4096)])
    pts.append(point(dataset, name, "int8 per-component (simulated)", (est + state_bytes) / len(x), x, y, ref,
                     code_size=codec.code_size, kind="simulated",
                     raw_bytes_per_block=(q.nbytes + scales.nbytes) / len(x),
                     compressed_codes_and_scales_bytes=est, state_bytes=state_bytes))
    return pts


# ---------------------------------------------------------------------------------------------- baselines
def zfp_roundtrip(x: np.ndarray, **mode) -> tuple[np.ndarray, np.ndarray]:
    """Each block through zfpy on its own: (decoded blocks, stream lengths in bytes)."""
    import zfpy

    if "rate" in mode and mode["rate"] < ZFP_MIN_RATE:
        raise ValueError(f"zfp rate {mode['rate']} < {ZFP_MIN_RATE}: zfpy 1.0.1 overruns its buffer there")
    y, n = np.empty_like(x), np.empty(len(x), np.int64)
    for i, blk in enumerate(x):
        s = zfpy.compress_numpy(np.ascontiguousarray(blk), **mode)
        n[i] = len(s)
        y[i] = zfpy.decompress_numpy(s)
    return y, n


def zfp_points(dataset: str, x: np.ndarray, quick: bool, ref: SurfaceReference | None = None) -> list[dict]:
    pts = []
    for r in ((0.25, 0.5, 2.0) if quick else ZFP_RATES):
        y, n = zfp_roundtrip(x, rate=r)
        pts.append(point(dataset, "zfp fixed-rate", f"rate {r:g} bit/value", n.mean(), x, y, ref, kind="zfp",
                         rate=r, payload_bytes_per_block=float(n.mean() - ZFP_HEADER)))
    for t in ((0.05, 0.005) if quick else ZFP_TOLERANCES):
        y, n = zfp_roundtrip(x, tolerance=t)
        pts.append(point(dataset, "zfp fixed-accuracy", f"tolerance {t:g}", n.mean(), x, y, ref, kind="zfp",
                         tolerance=t, payload_bytes_per_block=float(n.mean() - ZFP_HEADER)))
    return pts


def dct_order(n: int = BLOCK) -> np.ndarray:
    """Flat C-order indices of an n^3 DCT cube, lowest frequency first (i + j + k, then i^2 + j^2 + k^2)."""
    i, j, k = np.meshgrid(*[np.arange(n)] * 3, indexing="ij")
    s, q = (i + j + k).ravel(), (i * i + j * j + k * k).ravel()
    return np.lexsort((np.arange(n ** 3), q, s))


def dct_truncate(x: np.ndarray, keep: int, dtype=np.float16, return_coefficients: bool = False):
    """Keep the ``keep`` lowest-frequency orthonormal DCT-II coefficients (stored as ``dtype``), invert. With
    ``return_coefficients`` also the stored coefficients (N, keep) in ``dtype``."""
    from scipy.fft import dctn, idctn

    c = dctn(x.astype(np.float64), axes=(1, 2, 3), norm="ortho").reshape(len(x), -1)
    kept = np.zeros_like(c)
    idx = dct_order()[:keep]
    stored = np.ascontiguousarray(c[:, idx].astype(dtype))
    kept[:, idx] = stored.astype(np.float64)
    y = idctn(kept.reshape(x.shape), axes=(1, 2, 3), norm="ortho").astype(np.float32)
    return (y, stored) if return_coefficients else y


def baseline_points(dataset: str, x: np.ndarray, quick: bool, ref: SurfaceReference | None = None) -> list[dict]:
    pts = zfp_points(dataset, x, quick, ref)
    for k in ((64, 256, 4096) if quick else DCT_KS):
        y, coef = dct_truncate(x, k, return_coefficients=True)
        pts.append(point(dataset, "dct float16", f"K={k}", 2 * k, x, y, ref, kind="dct", keep=k))
        packed = dict(pts[-1]["surface"]) if ref is not None else None  # the same decoded blocks
        pts.append(point(dataset, "dct float16 + blosc", f"K={k}", compressed_size(coef, 512) / len(x), x, y,
                         kind="dct", keep=k, **({} if packed is None else {"surface": packed})))
    h = x.astype(np.float16)
    pts.append(point(dataset, "blosc float16 raw", "zstd 3, shuffle, 64-block chunks",
                     compressed_size(h, 64) / len(x), x, h.astype(np.float32), ref, kind="raw"))
    return pts


# -------------------------------------------------------------------------------------------- the goal
def loglog_interp(xs, ys, at: float) -> tuple[float, bool]:
    """log-log linear interpolation of the curve (xs, ys) at ``at``; extrapolates from the two end points
    outside the range, and says whether it did."""
    o = np.argsort(xs)
    lx, ly = np.log(np.asarray(xs, float)[o]), np.log(np.asarray(ys, float)[o])
    t = np.log(at)
    if lx[0] <= t <= lx[-1]:
        return float(np.exp(np.interp(t, lx, ly))), False
    a, b = (0, 1) if t < lx[0] else (-2, -1)
    return float(np.exp(ly[a] + (ly[b] - ly[a]) * (t - lx[a]) / (lx[b] - lx[a]))), True


def envelope(pts: list[dict]) -> list[dict]:
    """The points no other point beats on both bytes and error (the lower-left frontier), by bytes."""
    out = []
    for p in sorted(pts, key=lambda p: (p["bytes_per_block"], p["mse_voxel"])):
        if not out or p["mse_voxel"] < out[-1]["mse_voxel"]:
            out.append(p)
    return out


def goal(points: list[dict], dataset: str) -> dict:
    ds = [p for p in points if p["dataset"] == dataset]
    ours_stored = [p for p in ds if p["kind"] == "map"]
    ours_all = ours_stored + [p for p in ds if p["kind"] == "simulated"]
    zr = [p for p in ds if p["codec"] == "zfp fixed-rate"]
    zall = envelope([p for p in ds if p["kind"] == "zfp"])
    res = {}
    for budget in (256, 128):
        row = {"budget_bytes": budget, "ratio": FLOAT32_BLOCK_BYTES // budget}
        for label, cands in (("stored", ours_stored), ("with_int8_simulated", ours_all)):
            fit = [p for p in cands if p["bytes_per_block"] <= budget]
            if not fit:
                row[label] = None
                continue
            best = min(fit, key=lambda p: p["mse_voxel"])
            r = {"codec": best["codec"], "setting": best["setting"], "bytes_per_block": best["bytes_per_block"],
                 "mse_voxel": best["mse_voxel"]}
            for zlabel, zc, key in (("zfp_fixed_rate", zr, "bytes_per_block"),
                                    ("zfp_fixed_rate_headerless", zr, "payload_bytes_per_block"),
                                    ("zfp_best_of_both_modes", zall, "bytes_per_block")):
                zm, extra = loglog_interp([p[key] for p in zc], [p["mse_voxel"] for p in zc], best["bytes_per_block"])
                r[zlabel] = {"mse_voxel": zm, "error_ratio": best["mse_voxel"] / zm, "extrapolated": extra,
                             "ours_lower": best["mse_voxel"] < zm}
            zb = next((p for p in zr if p["payload_bytes_per_block"] == budget), None)
            if zb is not None:  # rate = 8 budget / 4096: the payload is exactly the budget, nothing interpolated
                r["zfp_fixed_rate_at_budget_headerless"] = {
                    "rate": zb["rate"], "mse_voxel": zb["mse_voxel"], "error_ratio": best["mse_voxel"] / zb["mse_voxel"],
                    "ours_lower": best["mse_voxel"] < zb["mse_voxel"]}
            row[label] = r
        base = [p for p in ds if p["kind"] in ("dct", "raw") and p["bytes_per_block"] <= budget]
        if base:
            b = min(base, key=lambda p: p["mse_voxel"])
            row["best_other_baseline"] = {"codec": b["codec"], "setting": b["setting"],
                                          "bytes_per_block": b["bytes_per_block"], "mse_voxel": b["mse_voxel"]}
        res[str(budget)] = row
    pca64 = next((p for p in ds if p["codec"] == "pca-64" and p["setting"] == "float32"), None)
    z05 = next((p for p in zr if p.get("rate") == 0.5), None)
    if pca64 and z05:
        res["pca64_float32_vs_zfp_rate_0.5"] = {
            "pca64_bytes": pca64["bytes_per_block"], "pca64_mse": pca64["mse_voxel"], "zfp_bytes": z05["bytes_per_block"],
            "zfp_mse": z05["mse_voxel"], "error_ratio": pca64["mse_voxel"] / z05["mse_voxel"]}
    return res


# ------------------------------------------------------------------------------------------------- output
STYLE = {"pca": ("C0", "o"), "ae-64": ("C1", "s"), "parallel 64+64": ("C2", "^"), "sequential 64+64": ("C3", "v"),
         "zfp fixed-rate": ("k", "x"), "zfp fixed-accuracy": ("0.5", "+"), "dct float16": ("C4", "d"),
         "dct float16 + blosc": ("C6", "d"),
         "blosc float16 raw": ("C5", "*")}


def plot(points: list[dict], datasets: list[str], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    surf = [ds for ds in datasets if any("surface" in p for p in points if p["dataset"] == ds)]
    rows = 2 if surf else 1
    fig, axes = plt.subplots(rows, len(datasets), figsize=(7.5 * len(datasets), 8.5 + 6 * (rows - 1)), squeeze=False)
    panels = [(0, d, "mse_voxel") for d in datasets] + [(1, d, "chamfer_mm") for d in surf]
    for r in range(1, rows):
        for ax, ds in zip(axes[r], datasets):
            if ds not in surf:
                ax.set_axis_off()

    def value(p: dict, metric: str) -> float:
        if metric == "mse_voxel":
            return p["mse_voxel"]
        c = p["surface"]["chamfer_l1"]
        return float("nan") if c is None else 1000 * c

    for row, ds, metric in panels:
        ax = axes[row][datasets.index(ds)]
        P = [p for p in points if p["dataset"] == ds]
        series: dict[tuple[str, str], list[dict]] = {}
        for p in P:
            fam = "pca" if p["codec"].startswith("pca-") else p["codec"]
            if p["kind"] in ("map", "simulated"):
                key = (fam, p["setting"].split(" (")[0])
            else:
                key = (fam, "")
            series.setdefault(key, []).append(p)
        ls = {"float32": "-", "float16": "--", "int8 per-block": ":", "int8 per-component": "-.",
              "float32 surface-true": (0, (5, 1, 1, 1)), "float16 surface-true": (0, (3, 1)),
              "int8 per-block surface-true": (0, (1, 2))}
        for (fam, setting), S in sorted(series.items()):
            S = sorted(S, key=lambda p: p["bytes_per_block"])
            color, marker = STYLE.get(fam, ("C9", "."))
            sim = S[0]["kind"] == "simulated"
            label = f"{fam} {setting}".strip() + (" (sim.)" if sim else "")
            true = setting.endswith("surface-true")
            ax.plot([p["bytes_per_block"] for p in S], [value(p, metric) for p in S], linestyle=ls.get(setting, "-"),
                    color=color, marker=marker, label=label, alpha=0.5 if sim else 1,
                    mfc="white" if true else color)
            if fam == "pca":
                for p in S:
                    if setting in ("float32", "float32 surface-true"):
                        ax.annotate(p["codec"][4:], (p["bytes_per_block"], value(p, metric)), fontsize=7,
                                    xytext=(3, 3), textcoords="offset points")
        for b, txt in ((256, "64:1"), (128, "128:1")):
            ax.axvline(b, color="0.8", lw=0.8, zorder=0)
            ax.text(b, 1, txt, fontsize=8, color="0.4", ha="center", va="bottom",
                    transform=ax.get_xaxis_transform())
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("bytes per block stored (dense float32 block = 16384)")
        ax.set_ylabel("per-voxel MSE (normalised units)" if metric == "mse_voxel" else
                      "Chamfer-L1 of the surfaces vs the lossless blocks (mm)")
        n = P[0]["blocks"] if P else 0
        ax.set_title(f"{ds} ({n} non-empty blocks)" + ("" if metric == "mse_voxel" else ": surfaces"))
        ax.grid(True, which="both", alpha=0.25)
    ax0 = max((a for a in axes[0]), key=lambda a: len(a.get_legend_handles_labels()[1]))
    handles, labels = ax0.get_legend_handles_labels()
    spare = [ax for r in range(1, rows) for ax, ds in zip(axes[r], datasets) if ds not in surf]
    if spare:  # an empty panel (a data set without surfaces) holds the legend
        spare[0].legend(handles, labels, loc="center", ncol=2, fontsize=8)
        fig.tight_layout()
    else:
        fig.legend(handles, labels, loc="lower center", ncol=4, fontsize=8)
        fig.tight_layout(rect=(0, 0.2 / rows, 1, 1))
    fig.savefig(path, dpi=110)
    plt.close(fig)


def fmt(v: float) -> str:
    return f"{v:.3g}" if v < 1e3 else f"{v:,.0f}"


def chamfer_mm(p: dict) -> str:
    c = p["surface"]["chamfer_l1"]
    return "inf" if c is None else f"{1000 * c:.2f}"


def surface_md(res: dict) -> list[str]:
    """The surfaces section: per fused-map data set, the best Chamfer-L1 of each method family within 256 and
    128 B/block (measured points only, nothing interpolated), and our float32 codecs plain against
    surface-true."""
    L = []
    for ds in res["datasets"]:
        P = [p for p in res["points"] if p["dataset"] == ds and "surface" in p]
        if not P:
            continue
        if not L:
            L += ["## Surfaces: Chamfer-L1 and F-score on fused maps", "",
                  "Fused-map data sets only (those with an observation). Every point's surfaces against the lossless "
                  "blocks' (`sdfcodec.core.surface.compare_volumes`; docs/surface.md): Chamfer-L1 and F@1 voxel (2 cm). "
                  "*plain*: maps written without the observation (every voxel fitted alike, as ZFP, the DCT and "
                  "Blosc see them); *surface-true*: with it (mask, surface-weighted fit, unobserved voxels decode "
                  "to d_max), its mask chunks counted in the bytes.", ""]
        fams = (("ours, surface-true maps", lambda p: p.get("surface_true", False)),
                ("ours, plain maps", lambda p: p["kind"] == "map" and not p.get("surface_true", False)),
                ("zfp (either mode)", lambda p: p["kind"] == "zfp"),
                ("dct / blosc", lambda p: p["kind"] in ("dct", "raw")))
        L += [f"### {ds}", "", "| within | " + " | ".join(f for f, _ in fams) + " |",
              "|---|" + "---|" * len(fams)]
        for budget in (256, 128):
            cells = []
            for _, keep in fams:
                fit = [p for p in P if keep(p) and p["bytes_per_block"] <= budget
                       and p["surface"]["chamfer_l1"] is not None]
                if not fit:
                    cells.append("none fits")
                    continue
                b = min(fit, key=lambda p: p["surface"]["chamfer_l1"])
                cells.append(f"{chamfer_mm(b)} mm, F@1 {b['surface']['f_score_1']:.3f} ({b['codec']} {b['setting']}, "
                             f"{b['bytes_per_block']:.0f} B)")
            L.append(f"| {FLOAT32_BLOCK_BYTES // budget}:1 ({budget} B/block) | " + " | ".join(cells) + " |")
        L += ["", "| codec | plain: B/block, MSE, Chamfer-L1 (mm), F@1 | surface-true: B/block, MSE, Chamfer-L1 "
              "(mm), F@1 |", "|---|---|---|"]
        for name in dict.fromkeys(p["codec"] for p in P if p["kind"] == "map"):
            cells = []
            for st in (False, True):
                q = next((p for p in P if p["codec"] == name and p["kind"] == "map" and
                          p.get("surface_true", False) == st and p["setting"].startswith("float32")), None)
                cells.append("-" if q is None else f"{q['bytes_per_block']:.1f}, {q['mse_voxel']:.3g}, "
                             f"{chamfer_mm(q)}, {q['surface']['f_score_1']:.3f}")
            L.append(f"| {name} float32 | " + " | ".join(cells) + " |")
        L.append("")
    return L


def markdown(res: dict, png: str = "rate-distortion.png") -> str:
    """This script's section of docs/rate-distortion.md, from the results it writes (docs/generate/ renders the
    page from the committed JSON with this same function)."""
    L = ["## Storage formats of our codecs against ZFP, DCT truncation and Blosc (examples/rate_distortion.py)", "",
         "Made by (machine, load and wall time at the end):", "", "```", res["command"], "```", "",
         "Method: see the docstring of `examples/rate_distortion.py`. In short: error is per-voxel MSE and per-block "
         "SSE in normalised units (1 = 0.14 m), over the non-empty blocks of each data set; bytes per block are what "
         "is stored: for our codecs the `codes/` + `state/` chunk files of a real map written with "
         "`create_map(code_dtype=...)` (the codec's learned state and the Zarr metadata are per map and listed "
         "separately), for ZFP the zfpy stream length of each 16^3 block (16 of those bytes are zfpy's header), "
         "for the DCT 2 bytes per kept coefficient, for raw float16 the Blosc/zstd chunks; int8 per-block maps "
         "count their `code_scale/` chunks (a float32 offset and scale per block) with the codes, surface-true maps "
         "their `observed/` chunks (the observation mask, one bit per voxel before compression). "
         "**int8 with per-component scales is "
         "simulated** (quantised from the stored float32 codes; compressed size estimated with the map's "
         "Blosc/zstd through numcodecs): the map format stores per-block scales only.", "",
         f"Data sets: {'; '.join(f'`{k}`: {v}' for k, v in res['datasets'].items())}.", "",
         f"![rate-distortion]({png})", ""]
    L += ["## The goal: at 64:1 and 128:1, is our best codec's error lower than ZFP's at the same stored bytes?", ""]
    for ds, g in res["goal"].items():
        for budget in ("256", "128"):
            row = g[budget]
            for label, what in (("stored", "stored formats (float32/float16/int8 maps)"),
                                ("with_int8_simulated", "including simulated per-component int8")):
                r = row[label]
                if r is None:
                    L.append(f"- **{ds}, {row['ratio']}:1 ({budget} B/block), {what}**: none of our points fits.")
                    continue
                z, zh, zb = r["zfp_fixed_rate"], r["zfp_fixed_rate_headerless"], r["zfp_best_of_both_modes"]
                ex = lambda q: " (extrapolated)" if q["extrapolated"] else ""  # noqa: E731
                L.append(f"- **{ds}, {row['ratio']}:1 ({budget} B/block), {what}: "
                         f"{'YES' if z['ours_lower'] else 'NO'}** against ZFP fixed-rate. Best: {r['codec']} "
                         f"{r['setting']} at {r['bytes_per_block']:.1f} B/block, MSE {r['mse_voxel']:.3g}; ZFP "
                         f"fixed-rate at the same bytes {z['mse_voxel']:.3g}{ex(z)} (ours/ZFP {z['error_ratio']:.2f}); "
                         f"ZFP without its 16-byte header {zh['mse_voxel']:.3g}{ex(zh)} "
                         f"({zh['error_ratio']:.2f}); best of ZFP's two modes {zb['mse_voxel']:.3g}{ex(zb)} "
                         f"({zb['error_ratio']:.2f}).")
                za = r.get("zfp_fixed_rate_at_budget_headerless")
                if za:
                    L.append(f"  - ZFP measured at exactly {budget} B/block (rate {za['rate']:g}, payload without "
                             f"header, nothing interpolated): MSE {za['mse_voxel']:.3g}; ours/ZFP "
                             f"{za['error_ratio']:.2f} ({'ours lower' if za['ours_lower'] else 'ZFP lower'}).")
            ob, st = row.get("best_other_baseline"), row["stored"]
            if ob:
                cmp = (f"; our best stored / this = {st['mse_voxel'] / ob['mse_voxel']:.2f}"
                       f" ({'ours lower' if st['mse_voxel'] < ob['mse_voxel'] else 'the baseline is lower'})"
                       if st else "")
                L.append(f"  - best non-ZFP baseline within {budget} B/block: {ob['codec']} {ob['setting']} at "
                         f"{ob['bytes_per_block']:.1f} B/block, MSE {ob['mse_voxel']:.3g}{cmp}.")
        c = g.get("pca64_float32_vs_zfp_rate_0.5")
        if c:
            L.append(f"- {ds}: fixed-length pca-64 float32 ({c['pca64_bytes']:.1f} B/block, MSE "
                     f"{c['pca64_mse']:.3g}) against ZFP fixed-rate 0.5 bit/value ({c['zfp_bytes']:.0f} B/block, MSE "
                     f"{c['zfp_mse']:.3g}): error ratio {c['error_ratio']:.2f}.")
    L += ["", "ZFP values at our bytes are interpolated linearly in log(bytes)-log(MSE) between its measured points "
          "(extrapolated from the two nearest points where ours lie outside ZFP's range). Read the 128:1 "
          "interpolations with care: ZFP fixed-rate falls off a cliff below 0.25 bit/value (10-12 bits per 4^3 zfp "
          "block barely hold a float32 block's exponent; see the table), so interpolating between 0.1875 and 0.25 "
          "bit/value, with the 16-byte header pushing 0.25 bit/value to 144 B, makes ZFP look far worse than its "
          "headerless 0.25 bit/value point at exactly 128 B. The 'measured at exactly' lines are the fair "
          "comparison. zfpy 1.0.1 corrupts the heap at 0.125 bit/value (8 bits per zfp block) on these blocks, so "
          "the script refuses rates below 10/64 bit/value.", ""]
    L += surface_md(res)
    L += ["## All points", ""]
    for ds in res["datasets"]:
        P = [p for p in res["points"] if p["dataset"] == ds]
        surf = all("surface" in p for p in P)
        L += [f"### {ds} ({P[0]['blocks']} non-empty blocks)", "",
              "| codec | setting | bytes/block | ratio to float32 | MSE/voxel | SSE/block | max abs error | "
              + ("Chamfer-L1 (mm) | F@1 voxel | " if surf else "") + "codec state (B, per map) |",
              "|---|---|---:|---:|---:|---:|---:|" + ("---:|---:|" if surf else "") + "---:|"]
        for p in sorted(P, key=lambda p: (p["kind"] not in ("map", "simulated"), p["codec"], p["bytes_per_block"])):
            cs = f"{p['codec_state_bytes']:,}" if "codec_state_bytes" in p else ""
            sf = f"{chamfer_mm(p)} | {p['surface']['f_score_1']:.3f} | " if surf else ""
            L.append(f"| {p['codec']} | {p['setting']} | {p['bytes_per_block']:.1f} | {p['ratio']:.1f} | "
                     f"{p['mse_voxel']:.3g} | {p['sse_block']:.3g} | {p['max_abs_error']:.3g} | {sf}{cs} |")
        L.append("")
    m = res["machine"]
    L += ["## Run", "",
          f"Machine: {m['cpus']} CPU(s), {m['processor']}, {m['platform']}; Python {m['python']}, zfpy "
          f"{m['zfpy']}, numcodecs {m['numcodecs']}, zarr {m['zarr']}. Load average (1, 5, 15 min) before "
          f"{' '.join(f'{v:.2f}' for v in res['load_before'])}, after "
          f"{' '.join(f'{v:.2f}' for v in res['load_after'])}. Wall time {res['wall_s']:.1f} s.", ""]
    return "\n".join(L)


def write_md(res: dict, path: Path, png: str) -> None:
    # only this script's section of the page: the others are made by their own scripts (examples/_page.py)
    replace_section(path, "codecs", markdown(res, png), title="# Rate-distortion")


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--kitchen", type=Path, default=Path(os.environ.get("SDFCODEC_KITCHEN", "7scenes-redkitchen")),
                    help="a 7-Scenes redkitchen sequence folder (colour and depth frames, poses, gravity); default: $SDFCODEC_KITCHEN, else ./7scenes-redkitchen")
    ap.add_argument("--quick", action="store_true", help="a small synthetic map only, few settings (tests)")
    ap.add_argument("--out", type=Path, default=None, help="where the json/png/md go (default docs/, "
                                                           "or --workdir with --quick)")
    ap.add_argument("--workdir", type=Path, default=ROOT / "build" / "rate-distortion",
                    help="maps written here (kept) and the fused kitchen cache")
    a = ap.parse_args(argv)
    import torch
    import zfpy  # noqa: F401 - fail at once, with a clear ImportError, when the ZFP reference is missing

    t0, load_before = time.perf_counter(), os.getloadavg()
    a.workdir.mkdir(parents=True, exist_ok=True)
    out = a.out or (a.workdir if a.quick else ROOT / "docs")
    out.mkdir(parents=True, exist_ok=True)
    data, descr = {}, {}
    if a.quick:
        coords, tsdf = synthetic_blocks(True)
        data["synthetic (quick)"] = (coords, *fused_like(tsdf))
        descr["synthetic (quick)"] = ("a 64 x 64 x 48-voxel corner of room_scene(seed=0, geometry='rich', ceiling=True) "
                                      "at 2 cm, fused-like (voxels at d_min unobserved, read d_max)")
    else:
        if a.kitchen.is_dir():
            data["kitchen"] = kitchen_blocks(a.kitchen, a.workdir)
            descr["kitchen"] = ("7-Scenes redkitchen fused at 2 cm, truncation (-0.04, 0.1) m, held-out second half "
                                "along x, with its observation (fusion weight > 0)")
        else:
            print(f"no kitchen data at {a.kitchen}: skipped", file=sys.stderr)
        data["synthetic"] = (*synthetic_blocks(False), None)
        descr["synthetic"] = "room_scene(seed=0, geometry='rich', ceiling=True) sampled at 2 cm with a 16 cm margin"
    with torch.no_grad():  # a context, not set_grad_enabled: main() is also called in-process by the tests
        return _study(a, argv, data, descr, out, t0, load_before)


def _study(a, argv, data, descr, out, t0, load_before) -> dict:
    import numcodecs
    import torch
    import zarr

    codecs = learned_codecs(a.quick)
    points = []
    for ds, (coords, tsdf, observed) in data.items():
        v = normalised(tsdf)
        coded = nonempty_mask(v)
        x = np.ascontiguousarray(v[coded])
        ref = None if observed is None else SurfaceReference(coords, tsdf, observed, coded)
        print(f"{ds}: {len(coords)} blocks, {len(x)} non-empty" + ("" if ref is None else ", with an observation"),
              flush=True)
        for name, codec in codecs.items():
            points += measure_learned(name, codec, ds, coords, tsdf, x, coded, a.workdir, observed, ref)
            print(f"  {name} done ({time.perf_counter() - t0:.0f} s)", flush=True)
        points += baseline_points(ds, x, a.quick, ref)
        print(f"  baselines done ({time.perf_counter() - t0:.0f} s)", flush=True)
    cmd = "python examples/rate_distortion.py" + ("" if argv is None and len(sys.argv) <= 1 else " " + shlex.join(
        sys.argv[1:] if argv is None else argv))
    res = {"command": cmd, "datasets": descr, "points": points,
           "goal": {ds: goal(points, ds) for ds in data},
           "machine": {"cpus": os.cpu_count(), "processor": _cpu_model(), "platform": platform.platform(),
                       "python": platform.python_version(), "zfpy": _version("zfpy"),
                       "numcodecs": numcodecs.__version__, "zarr": zarr.__version__, "torch": torch.__version__,
                       "torch_threads": torch.get_num_threads()},
           "load_before": load_before, "load_after": os.getloadavg(), "wall_s": time.perf_counter() - t0}
    (out / "rate-distortion.json").write_text(json.dumps(res, indent=1) + "\n")
    plot(points, list(data), out / "rate-distortion.png")
    write_md(res, out / "rate-distortion.md", "rate-distortion.png")
    for ds, g in res["goal"].items():
        for b in ("256", "128"):
            r = g[b]["stored"]
            if r:
                z = r["zfp_fixed_rate"]
                print(f"{ds} {g[b]['ratio']}:1: best {r['codec']} {r['setting']} {r['bytes_per_block']:.1f} B "
                      f"MSE {r['mse_voxel']:.3g} vs ZFP fixed-rate {z['mse_voxel']:.3g} -> ratio {z['error_ratio']:.2f}")
    print(f"wrote {out / 'rate-distortion.json'}, .png, .md in {res['wall_s']:.1f} s")
    return res


def _version(dist: str) -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version(dist)
    except PackageNotFoundError:
        return "?"


def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


if __name__ == "__main__":
    main()
