"""Rate-distortion of the registry's codecs against every peer, surfaces included (issues 16 and 42).

    python examples/peers_study.py                     # kitchen half, synthetic room, rooms, building: long
    python examples/peers_study.py --quick             # a tiny synthetic corner (the CI test's path)
    python examples/peers_study.py --methods sz3-map,zfp-rate ...   # a subset (names: --list)

Writes docs/rd-peers.json, one figure per data set docs/rd-peers-<data set>.png (F@1, Chamfer-L1 and max error
against bytes per coded block) and the section "peers" of docs/rate-distortion.md (other sections of that page
are left as they are): per data set the methods read at 64, 128, 256 and 512 bytes per coded block (256:1 ..
32:1 of dense float32) and their decode throughput, each table with the machine, load, date and command.

Peers: SZ3 (pysz), ZFP (zfpy), SPERR (numcodecs-wasm-sperr), each on its own bytes. Ours: the entries of
:data:`OURS`, ``sdfcodec encode`` options as dicts (``--target-bytes`` included), every file of the map counted
with the shipped model referenced; a new configuration is one more dict.

Data sets (normalised units v = (d - d_min) / (d_max - d_min), truncation (-0.04, 0.1) m, 2 cm voxels):
``kitchen``: 7-Scenes redkitchen (500 frames) fused by ``sdfcodec.fusion.tsdf.fuse``, the blocks of the second half
along x: the half the shipped eigenshapes never saw in training, and the half no choice of this study was tuned
on (the SZ3 field layout, 8^3-block chunks and free space in unobserved voxels, was chosen on the first half).
``synthetic``: the furnished room of ``sdfcodec.data.render.room_scene(seed=0, geometry="rich")`` sampled
exactly on a lattice moved by 0.3 voxel (so that no wall lies on voxel centres, where the side of a crossing is a
rounding accident: unshifted, even an 8-bit NanoVDB-style copy with 0.3 mm max error measured 3.5 mm Chamfer) and
made fused-like (voxels more than 4 cm behind a surface unobserved, as fusion leaves them). ``rooms``: two
randomly posed furnished rooms of ``sdfcodec.search.rooms.synthetic_room`` side by side; ``building``:
``sdfcodec.data.building.building_scene`` (two rooms off a corridor), both fused-like as ``synthetic``.

Every method codes the same coded (not all-free) blocks. Distortion over the observed voxels of those blocks:
MSE (normalised), max error (cm); surfaces (``sdfcodec.core.surface.compare_volumes`` against the lossless blocks,
over their observation): Chamfer-L1 (mm) and F-score at 1 voxel. Rate: bytes per coded block with everything
but the codec state counted (maps: every file but ``codec/``: codes, observation mask, block states, Zarr
metadata); the codec state is reported apart and amortised over a 1M-block map. Decode speed: blocks per second
of the method's decoder over all blocks (best of 3) as a ratio to a memory copy of the same float32 blocks
timed interleaved with it (``decode_vs_memcpy``: 1 = as fast as copying the decoded bytes).

Methods are entries of :data:`METHODS` (a name and a function giving points), so a new one is one entry to add
(``bounds``: pca-64 with the residual stage of ``--max-error`` 1, 2, 4 cm and ``--sign-exact``).
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import sys
import tempfile
import time
from pathlib import Path
from typing import Callable

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _page import replace_section  # noqa: E402
from rate_distortion import (BLOCK, TRUNC, VS, SurfaceReference, fused_like, kitchen_blocks,  # noqa: E402
                             nonempty_mask, normalised, synthetic_blocks)

ROOT = Path(__file__).resolve().parents[1]
R = TRUNC[1] - TRUNC[0]
F32 = BLOCK ** 3 * 4
BUDGETS = (256, 128, 64)  # 64:1, 128:1, 256:1
STEPS = (0.02, 0.04, 0.08, 0.16, 0.32, 0.64, 1.28)


def rooms_blocks(seeds: tuple[int, ...] = (1, 2)) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``sdfcodec.search.rooms.synthetic_room(seed, behind="solid")`` for each of ``seeds`` (randomly posed
    furnished rooms, exact distances), side by side along x one block apart, fused-like: coords, metres,
    observed."""
    from sdfcodec.core.blocks import split_blocks
    from sdfcodec.search.rooms import synthetic_room

    coords, tsdf, x0 = [], [], 0
    for seed in seeds:
        b = split_blocks(synthetic_room(seed, behind="solid", voxel_size=VS, truncation=TRUNC).volume, fill=TRUNC[1])
        c = np.argwhere(np.ones(b.shape[:3], bool)).astype(np.int64)
        coords.append(c + [x0, 0, 0])
        tsdf.append(b.reshape(-1, BLOCK, BLOCK, BLOCK))
        x0 += b.shape[0] + 1
    return (np.concatenate(coords), *fused_like(np.concatenate(tsdf).astype(np.float32)))


def building_blocks(seed: int = 0, rooms_per_side: int = 1) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``sdfcodec.data.building.building_scene(seed, rooms_per_side)`` (rooms off a corridor, furnished)
    sampled exactly on a lattice moved by 0.3 voxel with a 16 cm margin, fused-like: coords, metres, observed."""
    from sdfcodec.core.blocks import split_blocks
    from sdfcodec.data.building import building_scene
    from sdfcodec.core.sdf import sample_volume

    scene, margin = building_scene(seed, rooms_per_side)[0], 0.16
    shape = tuple(int(round((s + 2 * margin) / VS)) for s in scene.size)
    vol = sample_volume(scene.sdf, shape, VS, origin=(-margin + 0.3 * VS,) * 3, truncation=TRUNC)
    b = split_blocks(vol, fill=TRUNC[1])
    coords = np.argwhere(np.ones(b.shape[:3], bool)).astype(np.int64)
    return (coords, *fused_like(np.ascontiguousarray(b.reshape(-1, BLOCK, BLOCK, BLOCK), dtype=np.float32)))


class Data:
    """One data set: coded blocks ``x`` (normalised, (N, 16, 16, 16)), their coords, metres and observation, the
    dense reference for surfaces, and a work directory for maps."""

    def __init__(self, name: str, coords, tsdf, observed, work: Path):
        v = normalised(tsdf)
        coded = nonempty_mask(v)
        self.name, self.work = name, work
        self.coords, self.tsdf, self.obs = coords[coded], tsdf[coded], observed[coded]
        self.x = np.ascontiguousarray(v[coded])
        self.ref = SurfaceReference(coords, tsdf, observed, coded)
        self.n = len(self.x)
        self.points: list[dict] = []
        self._mask_bytes = None

    def point(self, method: str, setting: str, family: str, nbytes: float, y: np.ndarray,
              decode: Callable[[], object] | None = None, state_bytes: int = 0, **extra) -> dict:
        """Measure decoded blocks ``y`` (normalised, in the order of ``x``) stored in ``nbytes`` in all."""
        obs = self.obs
        err = (np.asarray(y, np.float64) - self.x)[obs]
        p = {"dataset": self.name, "method": method, "setting": setting, "family": family,
             "bytes_per_block": nbytes / self.n, "ratio": F32 * self.n / nbytes, "mse": float(np.mean(err ** 2)),
             "max_error_cm": float(np.abs(err).max() * R * 100), "codec_state_bytes": int(state_bytes),
             "bytes_per_block_1M": nbytes / self.n + state_bytes / 1e6, **extra}
        s = self.ref.metrics(np.where(obs, y, 1.0))
        p.update(chamfer_mm=None if s["chamfer_l1"] is None else 1000 * s["chamfer_l1"], f1=s["f_score_1"])
        if decode is not None:
            p.update(speed(decode, self.n))
        self.points.append(p)
        print(f"  {method:22s} {setting:24s} {p['bytes_per_block']:8.1f} B  mse {p['mse']:.2e}  max "
              f"{p['max_error_cm']:5.2f} cm  chamfer {p['chamfer_mm'] or float('inf'):6.2f} mm  F@1 {p['f1']:.3f}",
              flush=True)
        return p


def speed(decode: Callable[[], object], n: int, repeat: int = 3) -> dict:
    """Best-of-``repeat`` decode time against a memory copy of ``n`` float32 blocks, interleaved."""
    src = np.ones((n, BLOCK ** 3), np.float32)
    dst = np.empty_like(src)
    td, tc = [], []
    for _ in range(repeat):
        t = time.perf_counter()
        np.copyto(dst, src)
        tc.append(time.perf_counter() - t)
        t = time.perf_counter()
        decode()
        td.append(time.perf_counter() - t)
    return {"decode_blocks_per_s": n / min(td), "decode_vs_memcpy": min(tc) / min(td),
            "load": os.getloadavg()[0]}


# ------------------------------------------------------------------------------------------------ our maps
def _map_points(d: Data, method: str, family: str, codec, settings: list[tuple[str, dict]]) -> None:
    import sdfcodec
    from sdfcodec.map.rate import stored_bytes

    index = {tuple(c): i for i, c in enumerate(d.coords)}
    for setting, kw in settings:
        path = d.work / f"{d.name}-{method}-{setting}.sdfz".replace(" ", "_")
        with sdfcodec.create_map(path, codec=codec, voxel_size=VS, truncation=TRUNC, overwrite=True,
                                 tool="examples/peers_study.py", **kw) as m:
            m.write_blocks(d.coords, d.tsdf, observed=d.obs)
        b = stored_bytes(path)
        state = sum(f.stat().st_size for f in (path / "codec").rglob("*") if f.is_file())
        m = sdfcodec.open_map(path)
        assert m.count_states()["coded"] == d.n, f"{method} {setting}: not every block coded"
        y = np.empty_like(d.x)

        def decode():
            for c, blocks in m.iter_decoded():
                y[[index[tuple(cc)] for cc in c]] = normalised(blocks)

        decode()
        d.point(method, setting, family, b["total"] * d.n, y, decode, state_bytes=state,
                codes_bytes_per_block=b["codes"], mask_bytes_per_block=b["mask"])


def m_pca(d: Data, quick: bool) -> None:
    """The shipped eigenshapes, surface-true maps: float32, float16, int8 and int16 at uniform steps."""
    import sdfcodec

    for k in ((16,) if quick else (16, 32, 64, 128)):
        sets = [(t, {"code_dtype": t}) for t in (("float32", "int8") if quick else ("float32", "float16", "int8"))]
        sets += [(f"int16 step {s:g}", {"code_dtype": "int16", "code_step": s})
                 for s in (STEPS[3::3] if quick else STEPS)]
        _map_points(d, f"pca-{k}", "eigenshapes", sdfcodec.pretrained_codec("pca", k), sets)


def m_nn(d: Data, quick: bool) -> None:
    """The shipped autoencoder and the PCA + AE mixtures (their codes are not uniform-step: no int16)."""
    import sdfcodec

    for name, codec in (("ae-64", sdfcodec.pretrained_codec("ae", 64)),
                        ("parallel 64+64", sdfcodec.pretrained_codec("parallel")),
                        ("sequential 64+64", sdfcodec.pretrained_codec("sequential"))):
        _map_points(d, name, "networks", codec, [(t, {"code_dtype": t}) for t in ("float32", "float16", "int8")])


def m_sz3_map(d: Data, quick: bool) -> None:
    """The registry's sz3 codec: real maps, field-compressed (8^3-block chunks), with the observation mask."""
    import sdfcodec

    for cm in ((1, 4) if quick else (0.5, 1, 2, 4, 6)):  # the codec allows at most half the truncation range (7 cm)
        _map_points(d, "sz3 (registry)", "sz3-registry", sdfcodec.get_codec("sz3", max_error=cm / 100 / R),
                    [(f"bound {cm:g} cm", {})])


def m_bounds(d: Data, quick: bool) -> None:
    """The shipped eigenshapes with the residual stage (spec 6d): --max-error E, --sign-exact."""
    import sdfcodec

    k = 16 if quick else 64
    # the plain map first: the issue's target for --sign-exact is <= 1.5x its bytes
    sets = [("plain", {})] + [(f"max-error {cm:g} cm", {"max_error": cm / 100}) for cm in ((2,) if quick else (1, 2, 4))]
    sets.append(("sign-exact", {"sign_exact": True}))
    _map_points(d, f"pca-{k} + residual", "bounds", sdfcodec.pretrained_codec("pca", k), sets)


# ------------------------------------------------------------------------------------------------- peers
def _dense(d: Data) -> tuple[np.ndarray, Callable[[np.ndarray], np.ndarray]]:
    """The data set's blocks as one dense normalised field (other blocks free space) and its inverse."""
    vol = (d.ref.original - TRUNC[0]) / R
    c = d.ref.coords

    def blocks(field: np.ndarray) -> np.ndarray:
        g = field.reshape(field.shape[0] // BLOCK, BLOCK, field.shape[1] // BLOCK, BLOCK, field.shape[2] // BLOCK,
                          BLOCK)
        return np.ascontiguousarray(g[c[:, 0], :, c[:, 1], :, c[:, 2], :])

    return vol.astype(np.float32), blocks


def m_sz3_peer(d: Data, quick: bool) -> None:
    """SZ3 (pysz) on the whole dense field with an absolute bound, no mask (what the issue measured)."""
    from sdfcodec.map.field import sz3_compress, sz3_decompress

    vol, blocks = _dense(d)
    for cm in ((1, 4) if quick else (0.5, 1, 2, 4, 6, 8, 10, 14)):
        s = sz3_compress(vol, cm / 100 / R)
        d.point("sz3 (peer, whole field)", f"bound {cm:g} cm", "sz3-peer", len(s),
                blocks(sz3_decompress(s, vol.shape)), lambda: sz3_decompress(s, vol.shape))


def m_zfp(d: Data, quick: bool) -> None:
    """ZFP (zfpy 1.0.1): fixed rate per block (headerless payload counted: rate x 512 B exactly), fixed accuracy
    per block and on the whole field."""
    import zfpy

    for r in ((0.25, 0.5) if quick else (0.1875, 0.25, 0.375, 0.5, 1.0)):
        streams = [zfpy.compress_numpy(b, rate=r) for b in d.x]
        y = np.stack([zfpy.decompress_numpy(s) for s in streams])
        d.point("zfp fixed-rate (block)", f"rate {r:g}", "zfp", sum(len(s) - 16 for s in streams), y,
                lambda: [zfpy.decompress_numpy(s) for s in streams], header_bytes_per_block=16)
    vol, blocks = _dense(d)
    for cm in ((4,) if quick else (2, 4, 8, 16, 32)):
        t = cm / 100 / R
        streams = [zfpy.compress_numpy(b, tolerance=t) for b in d.x]
        y = np.stack([zfpy.decompress_numpy(s) for s in streams])
        d.point("zfp fixed-accuracy (block)", f"tolerance {cm:g} cm", "zfp", sum(len(s) for s in streams), y,
                lambda: [zfpy.decompress_numpy(s) for s in streams])
        s = zfpy.compress_numpy(vol, tolerance=t)
        d.point("zfp fixed-accuracy (field)", f"tolerance {cm:g} cm", "zfp", len(s),
                blocks(zfpy.decompress_numpy(s)), lambda: zfpy.decompress_numpy(s))


def _zstd(a: np.ndarray) -> bytes:
    from numcodecs import Zstd

    return Zstd(level=19).encode(np.ascontiguousarray(a).tobytes())


def _unzstd(b: bytes, dtype, shape) -> np.ndarray:
    from numcodecs import Zstd

    return np.frombuffer(Zstd().decode(b), dtype).reshape(shape)


def m_dct(d: Data, quick: bool) -> None:
    """Per-block orthonormal 16^3 DCT-II, a uniform quantiser with a deadzone (|c| < 0.75 step -> 0, else
    round), the int16 integers zstd-19 compressed, coefficient-major (all blocks' first coefficient, then the
    second...: runs of zeros)."""
    from scipy.fft import dctn, idctn

    c = dctn(d.x.astype(np.float64), axes=(1, 2, 3), norm="ortho").reshape(d.n, -1)
    for step in ((0.4, 1.6) if quick else (0.1, 0.2, 0.4, 0.8, 1.6, 3.2)):
        q = np.where(np.abs(c) < 0.75 * step, 0, np.rint(c / step)).astype(np.int16)
        blob = _zstd(q.T)

        def decode(blob=blob, step=step):
            qq = _unzstd(blob, np.int16, (BLOCK ** 3, d.n)).T
            return idctn((qq * step).reshape(d.x.shape), axes=(1, 2, 3), norm="ortho")

        d.point("dct + deadzone + zstd", f"step {step:g}", "dct", len(blob) + 4, decode().astype(np.float32),
                decode)


def m_nanovdb(d: Data, quick: bool) -> None:
    """NanoVDB-style: each 8^3 leaf stores a float32 offset and scale and 8- or 4-bit values (its quantised
    grid's layout), the whole zstd-19 compressed."""
    leaves = d.x.reshape(d.n, 2, 8, 2, 8, 2, 8).transpose(0, 1, 3, 5, 2, 4, 6).reshape(-1, 512)
    lo, hi = leaves.min(axis=1), leaves.max(axis=1)
    for bits in (8, 4):
        levels = (1 << bits) - 1
        scale = np.where(hi > lo, (hi - lo) / levels, 1.0).astype(np.float32)
        q = np.rint((leaves - lo[:, None]) / scale[:, None]).astype(np.uint8)
        packed = q if bits == 8 else (q[:, 0::2] << 4 | q[:, 1::2])
        blob = _zstd(np.concatenate([lo.astype(np.float32).view(np.uint8), scale.view(np.uint8), packed.ravel()]))

        def decode(blob=blob, bits=bits):
            raw = _unzstd(blob, np.uint8, (-1,))
            n = len(lo)
            o, s = raw[:4 * n].view(np.float32), raw[4 * n:8 * n].view(np.float32)
            p = raw[8 * n:].reshape(n, -1)
            qq = p if bits == 8 else np.stack([p >> 4, p & 15], axis=2).reshape(n, 512)
            vals = o[:, None] + s[:, None] * qq
            return vals.reshape(d.n, 2, 2, 2, 8, 8, 8).transpose(0, 1, 4, 2, 5, 3, 6).reshape(d.x.shape)

        d.point("nanovdb-style", f"{bits}-bit", "nanovdb", len(blob), decode().astype(np.float32), decode)


def m_sperr(d: Data, quick: bool) -> None:
    """SPERR (numcodecs-wasm-sperr 0.2.3: SPERR compiled to WebAssembly) on the whole dense field at a fixed
    bit rate, chosen so that the stream takes B bytes per coded block (the bytes counted are its own output)."""
    from numcodecs_wasm_sperr import Sperr

    vol, blocks = _dense(d)
    for b in ((128, 512) if quick else X_BYTES):
        codec = Sperr(mode="bpp", bpp=8.0 * b * d.n / vol.size)
        s = np.frombuffer(bytes(codec.encode(vol)), np.uint8)  # its stream, header included
        d.point("sperr (peer, whole field)", f"{b:g} B/block asked", "sperr", s.nbytes,
                blocks(np.asarray(codec.decode(s)).reshape(vol.shape)),
                lambda: codec.decode(s), bpp=8.0 * b * d.n / vol.size)


def m_ours(d: Data, quick: bool) -> None:
    """Our maps as ``sdfcodec encode`` writes them, one curve point per entry of :data:`OURS` (its options as
    they would be typed; ``--codec-state reference`` added for the shipped models), every file of the map
    counted: transcoded from a lossless (``raw``) map of the data set with its observation."""
    import sdfcodec
    from sdfcodec.cli import app
    from typer.main import get_command

    src = d.work / f"{d.name}-lossless.sdfz".replace(" ", "_")
    with sdfcodec.create_map(src, codec=sdfcodec.get_codec("raw"), voxel_size=VS, truncation=TRUNC,
                             overwrite=True, tool="examples/peers_study.py") as m:
        m.write_blocks(d.coords, d.tsdf, observed=d.obs)
    index = {tuple(c): i for i, c in enumerate(d.coords)}
    for opts in (OURS[:2] if quick else OURS):
        label = " ".join(f"{k} {v}" for k, v in opts.items() if k != "codec")
        path = d.work / f"{d.name}-ours-{label}.sdfz".replace(" ", "_")
        argv = ["encode", str(src), str(path), "--overwrite", "--codec-state", "reference"]
        argv += [a for k, v in opts.items() for a in (f"--{k}", str(v))]
        if path.exists():
            import shutil

            shutil.rmtree(path)
        get_command(app).main(argv, standalone_mode=False)
        if not path.exists():  # refused (its one-line reason is printed): the run goes on, the page says so
            REFUSED.append({"dataset": d.name, "options": opts})
            continue
        total = sum(f.stat().st_size for f in path.rglob("*") if f.is_file())
        m = sdfcodec.open_map(path)
        y = np.ones_like(d.x)

        def decode():
            for c, blocks in m.iter_decoded():
                y[[index[tuple(cc)] for cc in c]] = normalised(blocks)

        decode()
        d.point(f"ours: {opts['codec']}", label, "ours", total, y, decode, options=opts)


#: Our curves: ``sdfcodec encode`` options per point (a dict, as typed without the dashes). A new configuration
#: (another codec, a variable-rate mode) is one more entry.
OURS: list[dict] = (
    [{"codec": "pca", "code-size": 16, "step": s} for s in (0.64, 0.16)]
    + [{"codec": "pca", "code-size": k, "code-dtype": t} for k in (16, 64) for t in ("int8", "float16")]
    + [{"codec": "pca", "code-size": 64, "step": s} for s in (0.08, 0.02)]
    # variable-rate codes (the default of --target-bytes alone; spec 4e): a curve, not only the four ratios
    + [{"codec": "pca", "target-bytes": b} for b in (64, 96, 128, 160, 192, 256, 320, 512)]
)
#: ``{"dataset", "options"}`` of the :data:`OURS` entries ``sdfcodec encode`` refused (e.g. a target below reach)
REFUSED: list[dict] = []
#: bytes per coded block of interest: 256:1 .. 32:1 of dense float32, and beside them
X_BYTES = (32, 64, 128, 256, 512, 1024)


#: name -> (function, description). Add an entry to add a method (bounds' residual stages: one entry each).
METHODS: dict[str, Callable[[Data, bool], None]] = {
    "pca": m_pca, "bounds": m_bounds, "networks": m_nn, "sz3-map": m_sz3_map, "sz3-peer": m_sz3_peer, "zfp": m_zfp, "dct": m_dct,
    "nanovdb": m_nanovdb, "sperr": m_sperr, "ours": m_ours,
}
REGISTRY = ("eigenshapes", "ours", "bounds", "networks", "sz3-registry")


# ----------------------------------------------------------------------------------------------- targets
def _interp(points: list[dict], at: float, key: str) -> float | None:
    """``key`` of a method's curve at ``at`` bytes per block, linear in log(bytes) between measured points
    (None outside their range: nothing is extrapolated)."""
    P = sorted((p for p in points if p[key] is not None), key=lambda p: p["bytes_per_block"])
    xs = np.log([p["bytes_per_block"] for p in P])
    if len(P) < 2 or not xs[0] <= np.log(at) <= xs[-1]:
        return None
    return float(np.interp(np.log(at), xs, [p[key] for p in P]))


def targets(points: list[dict], ds: str) -> dict:
    P = [p for p in points if p["dataset"] == ds]
    eig = [p for p in P if p["family"] in ("eigenshapes", "ours")]
    reg = [p for p in P if p["family"] in REGISTRY]
    sz3 = [p for p in P if p["family"] == "sz3-peer"]
    out: dict = {}
    zfp128 = next((p for p in P if p["method"] == "zfp fixed-rate (block)" and p["setting"] == "rate 0.25"), None)
    fit = [p for p in eig if p["bytes_per_block"] <= 128]
    if fit and zfp128:
        best = min(fit, key=lambda p: p["mse"])
        bestf = max(fit, key=lambda p: p["f1"])
        out["128B"] = {"eigenshapes_best_mse": _brief(best), "zfp_at_128B": _brief(zfp128),
                       "mse_ratio": best["mse"] / zfp128["mse"], "mse_target_met": best["mse"] <= 0.4 * zfp128["mse"],
                       "eigenshapes_best_f1": _brief(bestf), "f1_target_met": bestf["f1"] >= 0.9}
    for budget in BUDGETS:
        row = {}
        for label, fam in (("eigenshapes", eig), ("registry", reg)):
            within = [p for p in fam if p["bytes_per_block"] <= budget]
            if not within:
                row[label] = None
                continue
            best = {"chamfer_mm": min(within, key=lambda p: p["chamfer_mm"] or np.inf),
                    "f1": max(within, key=lambda p: p["f1"]), "mse": min(within, key=lambda p: p["mse"]),
                    "max_error_cm": min(within, key=lambda p: p["max_error_cm"])}
            r = {}
            for key, b in best.items():
                sz = _interp(sz3, b["bytes_per_block"], key)
                better = None if sz is None or b[key] is None else (b[key] >= sz if key == "f1" else b[key] <= sz)
                r[key] = {"ours": b[key], "by": _brief(b), "sz3_at_equal_bytes": sz, "at_least_as_good": better}
            row[label] = r
        out[f"{budget}B"] = row if budget != 128 else {**out.get("128B", {}), **row}
    fit64 = [p for p in reg if p["bytes_per_block"] <= 64]
    out["moonshot_64B"] = None if not fit64 else {"best": _brief(max(fit64, key=lambda p: p["f1"])),
                                                   "met": max(p["f1"] for p in fit64) >= 0.95}
    return out


def _brief(p: dict) -> dict:
    return {k: p[k] for k in ("method", "setting", "bytes_per_block", "mse", "max_error_cm", "chamfer_mm", "f1")}


# ------------------------------------------------------------------------------------------------ output
def _slug(ds: str) -> str:
    return "".join(ch if ch.isalnum() else "-" for ch in ds).strip("-")


def _curve(p: dict) -> str:
    """The curve a point belongs to: its method, with the options that do not vary along a curve."""
    label = p["method"] + ("" if p["family"] != "eigenshapes" else " " + p["setting"].split(" step")[0])
    if p["family"] == "ours":  # one curve per option set but the varying one (--step, --target-bytes)
        label += "".join(f" {k} {v}" for k, v in p["options"].items() if k not in ("codec", "step", "target-bytes"))
        label += " target-bytes" if "target-bytes" in p["options"] else " step" if "step" in p["options"] else ""
    return label


def plot(points: list[dict], ds: str, path: Path) -> None:
    """One figure for data set ``ds``: F@1, Chamfer-L1 and max error against bytes per coded block."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    keys = (("f1", "F-score @ 1 voxel", False), ("chamfer_mm", "Chamfer-L1 (mm)", True),
            ("max_error_cm", "max error (cm)", True))
    fig, axes = plt.subplots(1, 3, figsize=(18, 5.5), squeeze=False)
    series: dict[str, list[dict]] = {}
    for p in (p for p in points if p["dataset"] == ds):
        series.setdefault(_curve(p), []).append(p)
    for col, (key, name, log) in enumerate(keys):
        ax = axes[0][col]
        for label, S in sorted(series.items()):
            S = sorted(S, key=lambda p: p["bytes_per_block"])
            ys = [np.nan if p[key] is None else p[key] for p in S]
            ax.plot([p["bytes_per_block"] for p in S], ys, marker=".", label=label,
                    lw=2 if S[0]["family"] == "ours" else 1)
        for b in X_BYTES[1:5]:  # 256:1 .. 32:1 of dense float32
            ax.axvline(b, color="0.8", lw=0.8, zorder=0)
        ax.set_xscale("log")
        if log:
            ax.set_yscale("log")
        ax.set_xlim(16, 2048)
        ax.set_xlabel("bytes per coded block (every stored byte)")
        ax.set_ylabel(name)
        ax.set_title(f"{ds}: {name}")
        ax.grid(True, which="both", alpha=0.25)
    axes[0][0].legend(fontsize=6, ncol=2, loc="lower right")
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


def _fmt(v, f="{:.3g}") -> str:
    return "-" if v is None else f.format(v)


def markdown(res: dict) -> str:
    L = ["## The registry against every peer (issues 16 and 42)", "", "Made by:", "", "```", res["command"], "```",
         "", "Method: the docstring of `examples/peers_study.py`. " + res["note"], "",
         "", "### Targets (measured, wins and losses alike)", ""]
    for ds, t in res["targets"].items():
        L.append(f"**{ds}**")
        L.append("")
        a = t.get("128B", {})
        if "mse_ratio" in a:
            e, z = a["eigenshapes_best_mse"], a["zfp_at_128B"]
            L.append(f"- 128 B/block, eigenshapes' MSE <= 0.4x ZFP's at exactly 128 B: "
                     f"**{'met' if a['mse_target_met'] else 'missed'}**: {e['method']} {e['setting']} "
                     f"({e['bytes_per_block']:.1f} B) MSE {e['mse']:.3g} against ZFP rate 0.25 (128 B payload) "
                     f"{z['mse']:.3g}: {a['mse_ratio']:.2f}x.")
            f = a["eigenshapes_best_f1"]
            L.append(f"- 128 B/block, eigenshapes' F@1 >= 0.9: **{'met' if a['f1_target_met'] else 'missed'}**: "
                     f"{f['method']} {f['setting']} ({f['bytes_per_block']:.1f} B) F@1 {f['f1']:.3f}.")
        for budget in BUDGETS:
            row = t[f"{budget}B"]
            for label in ("eigenshapes", "registry"):
                r = row.get(label)
                if r is None:
                    L.append(f"- {F32 // budget}:1 ({budget} B/block), {label}: nothing fits.")
                    continue
                keys = ("chamfer_mm", "f1") if label == "eigenshapes" else ("chamfer_mm", "f1", "mse", "max_error_cm")
                cells, ok = [], []
                for k in keys:
                    c = r[k]
                    ok.append(c["at_least_as_good"])
                    cells.append(f"{k} {_fmt(c['ours'])} ({c['by']['method']} {c['by']['setting']}, "
                                 f"{c['by']['bytes_per_block']:.0f} B) vs SZ3 {_fmt(c['sz3_at_equal_bytes'])}")
                verdict = ("met" if all(o is True for o in ok) else "not measurable (SZ3 has no point there)"
                           if any(o is None for o in ok) else "missed")
                L.append(f"- {F32 // budget}:1 ({budget} B/block), {label} at least as good as SZ3 at equal bytes on "
                         f"{', '.join(keys)}: **{verdict}**: " + "; ".join(cells) + ".")
        m = t.get("moonshot_64B")
        if not m:
            L.append("- moonshot, F@1 >= 0.95 at 64 B/block: **missed**: no registry point at or below 64 B/block.")
        else:
            b = m["best"]
            L.append(f"- moonshot, F@1 >= 0.95 at 64 B/block: **{'met' if m['met'] else 'missed'}**: best "
                     f"{b['method']} {b['setting']} ({b['bytes_per_block']:.1f} B) F@1 {b['f1']:.3f}.")
        L.append("")
    L += ["SZ3 values at equal bytes are interpolated in log(bytes) between SZ3's measured points (peer, whole "
          "field, no mask); outside its range nothing is extrapolated.", ""]
    for ds in res["datasets"]:
        P = [p for p in res["points"] if p["dataset"] == ds]
        L += [f"### {ds}: every point ({P[0]['blocks']} coded blocks)" if P else f"### {ds}", "",
              "| method | setting | B/block | ratio | MSE | max (cm) | Chamfer (mm) | F@1 | codec state (B) | "
              "B/block at 1M blocks | decode, x memcpy |", "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
        for p in sorted(P, key=lambda p: (p["family"], p["method"], p["bytes_per_block"])):
            L.append(f"| {p['method']} | {p['setting']} | {p['bytes_per_block']:.1f} | {p['ratio']:.0f} | "
                     f"{p['mse']:.3g} | {p['max_error_cm']:.2f} | {_fmt(p['chamfer_mm'], '{:.2f}')} | {p['f1']:.3f} | "
                     f"{p['codec_state_bytes']:,} | {p['bytes_per_block_1M']:.1f} | "
                     f"{_fmt(p.get('decode_vs_memcpy'), '{:.3f}')} |")
        L.append("")
        measured = (f"Measured on {res['machine']['cpus']} CPUs at load {res['load_before'][0]:.1f}-"
                    f"{res['load_after'][0]:.1f}, {res['date']}, by `{res['command']}`.")
        L += [f"![{ds}](rd-peers-{_slug(ds)}.png)", "", f"**{ds}: at {', '.join(f'{b} B' for b in X_BYTES[1:5])} "
              "per coded block** (each method's curve read in log(bytes) between its measured points; - outside "
              "its range)", "", "| method | " + " | ".join(f"{b} B: F@1 / Chamfer mm / max cm" for b in X_BYTES[1:5])
              + " |", "|---|" + "---:|" * 4]
        curves: dict[str, list[dict]] = {}
        for p in P:
            curves.setdefault(_curve(p), []).append(p)
        for name, S in sorted(curves.items()):
            cells = []
            for b in X_BYTES[1:5]:
                v = [_interp(S, b, k) for k in ("f1", "chamfer_mm", "max_error_cm")]
                cells.append("-" if v[0] is None else f"{v[0]:.3f} / {_fmt(v[1], '{:.2f}')} / {_fmt(v[2], '{:.2f}')}")
            L.append(f"| {name} | " + " | ".join(cells) + " |")
        ours = [p for p in P if p["family"] == "ours"]
        if ours:  # our configurations are short curves: the best point (F@1) that fits each budget
            cells = []
            for b in X_BYTES[1:5]:
                fit = [p for p in ours if p["bytes_per_block"] <= b]
                q = max(fit, key=lambda p: p["f1"]) if fit else None
                cells.append("-" if q is None else f"{q['f1']:.3f} / {_fmt(q['chamfer_mm'], '{:.2f}')} / "
                             f"{q['max_error_cm']:.2f} ({q['setting']}, {q['bytes_per_block']:.0f} B)")
            L.append("| ours: best point that fits | " + " | ".join(cells) + " |")
        L += [f"- `sdfcodec encode` refused {' '.join(f'--{k} {v}' for k, v in r['options'].items())} (out of "
              "its range on this map)" for r in res.get("refused", []) if r["dataset"] == ds]
        L += ["", measured, "", f"**{ds}: decode throughput** (blocks/s, best of 3, and as a ratio to a memory "
              "copy of the decoded float32 blocks timed beside it)", "",
              "| method | setting | B/block | decode blocks/s | x memcpy |", "|---|---|---:|---:|---:|"]
        for p in sorted(P, key=lambda p: (p["method"], p["bytes_per_block"])):
            L.append(f"| {p['method']} | {p['setting']} | {p['bytes_per_block']:.1f} | "
                     f"{_fmt(p.get('decode_blocks_per_s'), '{:,.0f}')} | {_fmt(p.get('decode_vs_memcpy'), '{:.3f}')} |")
        L += ["", measured, ""]
    m = res["machine"]
    L += [f"Run: {m['cpus']} CPUs, Python {m['python']}, pysz {m['pysz']}, zfpy {m['zfpy']}; load average "
          f"{res['load_before'][0]:.1f} before, {res['load_after'][0]:.1f} after; wall time {res['wall_s']:.0f} s."
          + (" Decode ratios were taken under load (more than one job per core): re-measure idle."
             if max(res["load_before"][0], res["load_after"][0]) > m["cpus"] else ""), ""]
    return "\n".join(L)


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--kitchen", type=Path, default=Path(os.environ.get("SDFCODEC_KITCHEN", "7scenes-redkitchen")),
                    help="a 7-Scenes redkitchen sequence folder (colour and depth frames, poses, gravity); default: $SDFCODEC_KITCHEN, else ./7scenes-redkitchen")
    ap.add_argument("--quick", action="store_true", help="a tiny synthetic corner, few settings (the CI test)")
    ap.add_argument("--methods", default=None, help="comma-separated entries of METHODS (default: all; "
                                                    "--quick: all but the networks)")
    ap.add_argument("--list", action="store_true", help="list the methods and exit")
    ap.add_argument("--datasets", default="kitchen,synthetic,rooms,building",
                    help="comma-separated: kitchen, synthetic, rooms, building")
    ap.add_argument("--out", type=Path, default=None, help="docs/ (default), or the work directory with --quick")
    ap.add_argument("--workdir", type=Path, default=None, help="maps and the fused-kitchen cache")
    a = ap.parse_args(argv)
    if a.list:
        for k, f in METHODS.items():
            print(f"{k}: {f.__doc__.splitlines()[0]}")
        return {}
    a.methods = a.methods or ",".join(m for m in METHODS if not (a.quick and m == "networks"))
    unknown = [m for m in a.methods.split(",") if m not in METHODS]
    if unknown:
        ap.error(f"unknown method(s) {unknown}; known: {', '.join(METHODS)}")
    import torch

    with torch.no_grad():  # a context, not set_grad_enabled: main() is also called in-process by the tests
        return _study(a, argv)


def _study(a, argv) -> dict:
    work = a.workdir or (Path(tempfile.mkdtemp(prefix="rd-peers-")) if a.quick else ROOT / "build" / "rd-peers")
    work.mkdir(parents=True, exist_ok=True)
    out = a.out or (work if a.quick else ROOT / "docs")
    out.mkdir(parents=True, exist_ok=True)
    t0, load_before = time.perf_counter(), os.getloadavg()
    sets = []  # (name, thunk): each data set is built when its turn comes, so a long run writes as it goes
    if a.quick:
        sets.append(("synthetic (quick)", lambda: (lambda c, t: (c, *fused_like(t)))(*synthetic_blocks(True))))
    else:
        want = a.datasets.split(",")
        if "kitchen" in want and a.kitchen.is_dir():
            sets.append(("kitchen", lambda: kitchen_blocks(a.kitchen, work)))
        elif "kitchen" in want:
            print(f"no kitchen data at {a.kitchen}: skipped", file=sys.stderr)
        if "synthetic" in want:  # the lattice moved by 0.3 voxel: no wall on voxel centres (see its docstring)
            sets.append(("synthetic", lambda: (lambda c, t: (c, *fused_like(t)))(*synthetic_blocks(False, shift=0.3))))
        if "rooms" in want:
            sets.append(("rooms", rooms_blocks))
        if "building" in want:
            sets.append(("building", building_blocks))
    points, names, res = [], [], {}
    for name, build in sets:
        d = Data(name, *build(), work)
        print(f"{name}: {d.n} coded blocks", flush=True)
        for m in a.methods.split(","):
            METHODS[m](d, a.quick)
        for p in d.points:
            p["blocks"] = d.n
        points += d.points
        names.append(name)
        res = _write(a, argv, out, points, names, t0, load_before)  # after each data set: a long run keeps its part
    return res


def _write(a, argv, out: Path, points: list[dict], names: list[str], t0: float, load_before) -> dict:
    from importlib.metadata import version

    args = list(sys.argv[1:] if argv is None else argv)
    for i, a in enumerate(args[:-1]):  # this machine's folders say nothing to a reader: their role instead
        if a in ("--kitchen", "--workdir", "--out"):
            args[i + 1] = a[2:].upper() + "_DIR"
    cmd = "python examples/peers_study.py" + (" " + shlex.join(args) if args else "")
    res = {"command": cmd, "datasets": names, "points": points, "refused": REFUSED,
           "targets": {ds: targets(points, ds) for ds in names},
           "note": ("Data sets: kitchen = the held-out half (x > middle) of the 7-Scenes redkitchen fused at 2 cm; "
                    "synthetic = room_scene(seed=0, geometry='rich', ceiling=True) at 2 cm on a lattice moved by "
                    "0.3 voxel, fused-like; rooms = synthetic_room(seed 1 and 2, behind='solid') side by side, fused-like; "
                    "building = building_scene(seed=0, rooms_per_side=1) like synthetic. Our maps are surface-true "
                    "(observation mask, counted in their bytes); 'ours' rows count every file of the map, the "
                    "shipped model referenced (--codec-state reference); the peers (SZ3, ZFP, SPERR) code the plain "
                    "field (unobserved voxels as free space), with no mask to count, bytes as their own libraries "
                    "return them."),
           "machine": {"cpus": os.cpu_count(), "python": sys.version.split()[0], "pysz": version("pysz"),
                       "zfpy": version("zfpy"), "numcodecs-wasm-sperr": version("numcodecs-wasm-sperr")},
           "load_before": load_before, "load_after": os.getloadavg(), "wall_s": time.perf_counter() - t0,
           "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())}
    (out / "rd-peers.json").write_text(json.dumps(res, indent=1) + "\n")
    for ds in names:
        plot(points, ds, out / f"rd-peers-{_slug(ds)}.png")
    replace_section(out / "rate-distortion.md", "peers", markdown(res), title="# Rate-distortion")
    print(f"wrote {out / 'rd-peers.json'}, rd-peers-*.png and the 'peers' section of rate-distortion.md after "
          f"{res['wall_s']:.0f} s", flush=True)
    return res


if __name__ == "__main__":
    main()
