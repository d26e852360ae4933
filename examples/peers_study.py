"""Rate-distortion of our maps against SZ3, ZFP and SPERR at equal total bytes, surfaces included.

    python examples/peers_study.py --kitchen KITCHEN_DIR --kitchen-map KITCHEN.sdfz
                                                         # the four data sets and the whole kitchen: long
    python examples/peers_study.py --ours-only --kitchen KITCHEN_DIR --kitchen-map KITCHEN.sdfz
                                                         # only our maps again, the committed peers' points kept
    python examples/peers_study.py --quick               # a tiny synthetic corner (the CI test's path)

Writes docs/rd-peers.json, one figure per data set docs/rd-peers-<data set>.png (F@1, Chamfer-L1 and max error
against bytes per coded block) and the section "peers" of docs/rate-distortion.md (other sections of that page
are left as they are; ``make docs`` renders the same text from the JSON): the targets we hold our maps to
(examples/peers_targets.py) per data set at 32:1 .. 256:1 (512 .. 64 B per coded block), decode on read of our
variable-rate maps against a fixed-length pca-64 map, the whole kitchen at equal Chamfer, and every point with
its decode throughput.

Peers: SZ3 (pysz; its absolute bound bisected to land on each byte count), ZFP (zfpy, fixed rate per block) and
SPERR (numcodecs-wasm-sperr, fixed bit rate) on their own bytes, measured at :data:`PEER_BYTES`. Ours: the
entries of :data:`OURS` (``sdfcodec encode LOSSLESS OUT --target-bytes B``), every file of the map counted with
the shipped model referenced (``encode``'s default); a target ``encode`` refuses is recorded with its reason.
``--ours-only`` reruns every ``sdfcodec encode`` of the study (our points, decode on read, the whole kitchen's
maps) and keeps the peers' points of the JSON already in the output folder.

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
(also kept from earlier runs, not in the default set of the page: the shipped eigenshapes at fixed dtypes, the
networks, the registry's sz3 maps, residual bounds, a DCT and a NanoVDB-style quantiser).
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

# As the command line (sdfcodec/cli/__init__.py): OpenBLAS's threads sleep as soon as a product ends, instead of
# spinning ~0.1 s on the other cores. Set before numpy loads; without it, the spin after one map's decode (the
# fixed pca-64 map's threaded product) ran into the next map's timed read (decode on read), and the study's
# encodes ran beside spinning threads.
os.environ.setdefault("OPENBLAS_THREAD_TIMEOUT", "4")

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _page import replace_section  # noqa: E402
import peers_targets as pt  # noqa: E402
from rate_distortion import (BLOCK, TRUNC, VS, SurfaceReference, fused_like, kitchen_blocks,  # noqa: E402
                             nonempty_mask, normalised, synthetic_blocks)

ROOT = Path(__file__).resolve().parents[1]
R = TRUNC[1] - TRUNC[0]
F32 = BLOCK ** 3 * 4
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
        self.maps: dict[str, Path] = {}  # our maps by setting (m_ours), for decode_on_read

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
    # the plain map first: the target we hold --sign-exact to is <= 1.5x its bytes
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


def _sz3_at(vol: np.ndarray, nbytes: float, tries: int = 24) -> tuple[bytes, float]:
    """SZ3's stream of ``vol`` nearest ``nbytes`` in all, and its absolute bound (normalised): SZ3 has no rate
    mode, so its bound is bisected (in log) until the stream is within 0.5 % of ``nbytes``."""
    from sdfcodec.map.field import sz3_compress

    lo, hi, best = np.log(1e-5), 0.0, None  # bound 1e-5 .. 1 (the whole truncation range, 14 cm)
    for _ in range(tries):
        e = float(np.exp((lo + hi) / 2))
        s = sz3_compress(vol, e)
        if best is None or abs(np.log(len(s) / nbytes)) < abs(np.log(len(best[0]) / nbytes)):
            best = (s, e)
        if abs(len(s) / nbytes - 1) < 0.005:
            break
        lo, hi = (lo, np.log(e)) if len(s) < nbytes else (np.log(e), hi)  # too small: a tighter bound
    return best


def m_sz3_peer(d: Data, quick: bool) -> None:
    """SZ3 (pysz) on the whole dense field (no mask: the plain field, as SZ3 users code it) at each byte count of
    :data:`PEER_BYTES`, its absolute bound bisected to land within 0.5 % of it."""
    from sdfcodec.map.field import sz3_decompress

    vol, blocks = _dense(d)
    for b in (PEER_BYTES[3::4] if quick else PEER_BYTES):
        s, e = _sz3_at(vol, b * d.n)
        d.point("sz3 (peer, whole field)", f"{b:g} B/block asked", "sz3-peer", len(s),
                blocks(sz3_decompress(s, vol.shape)), lambda: sz3_decompress(s, vol.shape), bound_cm=e * R * 100)


def m_zfp(d: Data, quick: bool) -> None:
    """ZFP (zfpy 1.0.1) fixed rate per block at each byte count of :data:`PEER_BYTES` (rate = 8 B / 4096 bits a
    value; headerless payload counted: rate x 512 B exactly, zfpy's 16-byte header per block left out). From
    96 B up: at 8 bits per 4^3 block (64 B) and below zfpy 1.0.1 returns a wrong stream or crashes the process."""
    import zfpy

    for b in (PEER_BYTES[3::4] if quick else [b for b in PEER_BYTES if b >= 96]):
        r = 8 * b / BLOCK ** 3
        streams = [zfpy.compress_numpy(x, rate=r) for x in d.x]
        y = np.stack([zfpy.decompress_numpy(s) for s in streams])
        d.point("zfp fixed-rate (block)", f"rate {r:g}", "zfp", sum(len(s) - 16 for s in streams), y,
                lambda: [zfpy.decompress_numpy(s) for s in streams], header_bytes_per_block=16)


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
    for b in (PEER_BYTES[3::4] if quick else PEER_BYTES):
        codec = Sperr(mode="bpp", bpp=8.0 * b * d.n / vol.size)
        s = np.frombuffer(bytes(codec.encode(vol)), np.uint8)  # its stream, header included
        d.point("sperr (peer, whole field)", f"{b:g} B/block asked", "sperr", s.nbytes,
                blocks(np.asarray(codec.decode(s)).reshape(vol.shape)),
                lambda: codec.decode(s), bpp=8.0 * b * d.n / vol.size)


def encode(src: Path, out: Path, opts: dict) -> str | None:
    """Run ``sdfcodec encode SRC OUT --OPTION VALUE ...`` (the real command, in this process); None when it wrote
    the map, else its one-line refusal (also printed)."""
    import contextlib
    import io
    import shutil

    from sdfcodec.cli import app
    from typer.main import get_command

    if out.exists():
        shutil.rmtree(out)
    argv = ["encode", str(src), str(out), "--overwrite"] + [a for k, v in opts.items() for a in (f"--{k}", str(v))]
    err = io.StringIO()
    with contextlib.redirect_stderr(err):  # the command's one-line error goes to stderr: kept for the page
        code = get_command(app).main(argv, standalone_mode=False)
    text = err.getvalue().strip()
    if text:
        print(text, file=sys.stderr, flush=True)
    if out.exists() and not code:
        return None
    return " ".join(text.splitlines()[-1:]).removeprefix("error: ") or f"exit status {code}"


def lossless_map(d: Data) -> Path:
    """The data set's lossless (``raw``) map with its observation: what every ``encode`` of ours reads."""
    import sdfcodec

    src = d.work / f"{d.name}-lossless.sdfz".replace(" ", "_")
    with sdfcodec.create_map(src, codec=sdfcodec.get_codec("raw"), voxel_size=VS, truncation=TRUNC,
                             overwrite=True, tool="examples/peers_study.py") as m:
        m.write_blocks(d.coords, d.tsdf, observed=d.obs)
    return src


def m_ours(d: Data, quick: bool) -> None:
    """Our maps as ``sdfcodec encode LOSSLESS OUT --target-bytes B`` writes them (one point per entry of
    :data:`OURS`, options as typed), every file of the map counted (a shipped model is referenced by default);
    a refused target is recorded with its one-line reason (the floor or ceiling it names)."""
    import sdfcodec

    src = lossless_map(d)
    index = {tuple(c): i for i, c in enumerate(d.coords)}
    for opts in (OURS_QUICK if quick else OURS):
        label = " ".join(f"{k} {v}" for k, v in opts.items())
        path = d.work / f"{d.name}-ours-{label}.sdfz".replace(" ", "_")
        refusal = encode(src, path, opts)
        if refusal is not None:  # the run goes on, the page says so
            REFUSED.append({"dataset": d.name, "options": opts, "message": refusal})
            continue
        total = sum(f.stat().st_size for f in path.rglob("*") if f.is_file())
        m = sdfcodec.open_map(path)
        y = np.ones_like(d.x)

        def decode():
            for c, blocks in m.iter_decoded():
                y[[index[tuple(cc)] for cc in c]] = normalised(blocks)

        decode()
        d.point("ours: sdfcodec encode", label, "ours", total, y, decode, options=opts)
        d.maps[label] = path


def decode_on_read(d: Data, quick: bool, repeat: int = 15) -> dict | None:
    """Decode on read (open the map, decode every block, close) of each variable-rate map :func:`m_ours` wrote
    against the fixed-length pca-64 map (``encode --codec pca --code-size 64``) of the same blocks, the maps timed
    in turn within each of ``repeat`` rounds, each round starting one map further on; best time of each. None
    without maps of ours.

    Why the rotation: a read right after another map's is slower than one right after the same map's (what the
    process keeps of the map read last, and the caches, serve the next read of it); in a fixed order the first
    variable-rate map always came right after the fixed map (kitchen half, 64 B: best 37-45 ms in the study's
    fixed order, 28 ms in a balanced order, load 0.8). Why 15 rounds: the best of 9 moved by up to a fifth from run
    to run on an idle 2-core machine (kitchen half, fixed map 12.3-17.7 ms best)."""
    import sdfcodec

    if not d.maps:
        return None
    ref = d.work / f"{d.name}-fixed-pca-64.sdfz".replace(" ", "_")
    if encode(lossless_map(d), ref, {"codec": "pca", "code-size": 64}) is not None:
        return None
    paths = {"fixed pca-64": ref, **d.maps}
    times: dict[str, list[float]] = {k: [] for k in paths}
    order = list(paths.items())
    for r in range(2 if quick else repeat):
        for name, path in order[r % len(order):] + order[:r % len(order)]:
            t = time.perf_counter()
            with sdfcodec.open_map(path) as m:
                for _c, _b in m.iter_decoded():
                    pass
            times[name].append(time.perf_counter() - t)
    nbytes = {k: sum(f.stat().st_size for f in p.rglob("*") if f.is_file()) / d.n for k, p in paths.items()}
    return {"repeat": 2 if quick else repeat, "load": os.getloadavg()[0], "times_s": times, "bytes": nbytes,
            "reference_blocks_per_s": d.n / min(times["fixed pca-64"]),
            "ratios": pt.decode_on_read(times, "fixed pca-64")}


def kitchen_full(path: Path, work: Path, quick: bool) -> dict:
    """The whole fused kitchen map (``path``, lossless): SZ3 maps through our own ``encode --codec sz3
    --max-error E`` and ours through ``encode --target-bytes B``, every file of each counted, surfaces by
    ``sdfcodec compare`` against ``path``; then our bytes at each SZ3 map's Chamfer (peers_targets.equal_chamfer)."""
    import sdfcodec
    from sdfcodec.evaluation.compare import compare_command

    with sdfcodec.open_map(path) as m:
        n = m.count_states()["coded"]
    sides: dict[str, list[dict]] = {"sz3": [], "ours": []}
    runs = [("sz3", {"codec": "sz3", "max-error": e}) for e in ((0.01,) if quick else (0.005, 0.01, 0.02, 0.03))]
    runs += [("ours", {"target-bytes": b}) for b in ((128,) if quick else (96, 128, 160, 192, 256))]
    refused = []
    for side, opts in runs:
        out = work / ("kitchen-full-" + "-".join(f"{k}-{v}" for k, v in opts.items()) + ".sdfz")
        why = encode(path, out, opts)
        if why is not None:
            refused.append({"options": opts, "message": why})
            continue
        s = compare_command(str(path), str(out), quiet=True)
        total = sum(f.stat().st_size for f in out.rglob("*") if f.is_file())
        sides[side].append({"setting": " ".join(f"--{k} {v}" for k, v in opts.items()), "bytes": total,
                            "bytes_per_block": total / n, "chamfer_mm": 1000 * s["chamfer_l1"], "f1": s["f_score_1"],
                            "max_error_cm": None})
        print(f"  kitchen full {sides[side][-1]['setting']}: {total / n:.1f} B/block, Chamfer "
              f"{1000 * s['chamfer_l1']:.2f} mm, F@1 {s['f_score_1']:.3f}", flush=True)
    return {"coded_blocks": n, **sides, "refused": refused, "equal_chamfer": pt.equal_chamfer(sides["ours"], sides["sz3"]),
            "reverse": pt.equal_chamfer(sides["sz3"], sides["ours"]),
            "load": os.getloadavg()[0]}


#: Our points: ``sdfcodec encode`` options per point (a dict, as typed without the dashes): ``--target-bytes B``
#: alone (it picks codec, lengths and steps) at the four ratios and between them. A new configuration is one more
#: entry.
OURS: list[dict] = [{"target-bytes": b} for b in (64, 96, 128, 192, 256, 384, 512)]
OURS_QUICK: list[dict] = [{"target-bytes": b} for b in (128, 512)]
#: ``{"dataset", "options", "message"}`` of the :data:`OURS` entries ``sdfcodec encode`` refused
REFUSED: list[dict] = []
#: bytes per coded block the peers are measured at: the four ratios (512 .. 64 B = 32:1 .. 256:1 of dense
#: float32) and between and beside them, so that each is read at our exact bytes between two near points
PEER_BYTES = (48, 64, 96, 128, 192, 256, 384, 512, 768)
X_BYTES = (32, 64, 128, 256, 512, 1024)


#: name -> (function, description). Add an entry to add a method (bounds' residual stages: one entry each).
METHODS: dict[str, Callable[[Data, bool], None]] = {
    "pca": m_pca, "bounds": m_bounds, "networks": m_nn, "sz3-map": m_sz3_map, "sz3-peer": m_sz3_peer, "zfp": m_zfp, "dct": m_dct,
    "nanovdb": m_nanovdb, "sperr": m_sperr, "ours": m_ours,
}
REGISTRY = ("eigenshapes", "ours", "bounds", "networks", "sz3-registry")


# ----------------------------------------------------------------------------------------------- targets
def targets(points: list[dict], ds: str, refused: list[dict]) -> dict:
    """The equal-bytes targets on data set ``ds`` (:func:`peers_targets.equal_bytes_rows`)."""
    P = [p for p in points if p["dataset"] == ds]
    fam = {f: [p for p in P if p["family"] == f] for f in ("ours", "sz3-peer", "sperr", "zfp")}
    peers = {"sz3": fam["sz3-peer"], "sperr": fam["sperr"], "zfp": fam["zfp"]}
    return {"equal_bytes": pt.equal_bytes_rows(fam["ours"], peers, [r for r in refused if r["dataset"] == ds])}


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


def _runs(res: dict) -> str:
    """Where, when and how our points and the peers' were measured (one sentence when one run did both)."""
    o, p = res["ours_run"], res["peers_run"]
    return _measured(o, "Measured") if o == p else _measured(o, "Ours") + " " + _measured(p, "Peers")


def _measured(run: dict, what: str) -> str:
    return (f"{what} measured on {run['cpus']} CPUs at load {run['load_before'][0]:.1f}-{run['load_after'][0]:.1f}, "
            f"{run['date']}, by `{run['command']}`.")


def _chamfer_row(r: dict) -> str:
    s, o = r["ref"], r["smallest_reaching"]
    return (f"| {s['setting']} | {s['bytes_per_block']:.1f} | {s['chamfer_mm']:.2f} / {s['f1']:.3f} | "
            f"{_fmt(r['bytes_at_equal_chamfer'], '{:.1f}')} | "
            + ("none" if o is None else f"{o['setting']}: {o['bytes_per_block']:.1f} B, {o['chamfer_mm']:.2f} mm, "
               f"F@1 {o['f1']:.3f}") + f" | {_fmt(r['bytes_ratio'], '{:.2f}')} | "
            + {True: "**yes**", False: "**no**", None: "not measurable"}[r["met"]] + " |")


def markdown(res: dict) -> str:
    peers_run, ours_run = res["peers_run"], res["ours_run"]
    L = ["## The registry against every peer at equal bytes", "", "Made by:", "", "```",
         peers_run["command"]] + ([ours_run["command"]] if ours_run["command"] != peers_run["command"] else []) + [
         "```", "", "Method: the docstrings of `examples/peers_study.py` and `examples/peers_targets.py`. "
         + res["note"], "", "### Targets (measured, wins and losses alike)", "",
         "Per data set and ratio: our point is `sdfcodec encode LOSSLESS OUT --target-bytes B` (a refused target "
         "with the floor or ceiling it names); each peer's F@1 / Chamfer-L1 / max error are read off its curve at "
         "our exact bytes per coded block (between its two measured points either side, linear in log(bytes), and "
         "in log(value) for Chamfer and max error; the peers are measured at " + ", ".join(map(str, res["peer_bytes"]))
         + " B per coded block; beyond a curve that stops short, as SZ3's does at float precision on the exact "
         "synthetic fields, its largest point, with fewer bytes than ours). The target we hold our maps to: our "
         "Chamfer <= 0.5x SZ3's and "
         "SPERR's at equal bytes.", ""]
    for ds, t in res["targets"].items():
        L += [f"**{ds}**", ""] + pt.markdown_targets(
            {**t, "decode_on_read": res.get("decode_on_read", {}).get(ds)}, _runs(res))
    kf = res.get("kitchen_full")
    if kf:
        L += [f"### The whole kitchen map (frames 0-499, {kf['coded_blocks']} coded blocks): smaller than SZ3's at "
              "equal Chamfer?", "", "Both sides written by `sdfcodec encode` (SZ3: `--codec sz3 --max-error E`, "
              "ours: `--target-bytes B`), every file of each map counted, surfaces by `sdfcodec compare LOSSLESS "
              "MAP`. Our bytes at SZ3's Chamfer: our curve read in log-log between the two maps either side.", "",
              "| SZ3 map | SZ3 B/block | SZ3 Chamfer (mm) / F@1 | our B/block at that Chamfer | our smallest map "
              "reaching it | ours / SZ3 bytes | smaller? |", "|---|---:|---|---:|---|---:|---|"]
        for r in kf["equal_chamfer"]:
            L.append(_chamfer_row(r))
        L += ["", "The reverse reading: SZ3's bytes (its curve, log-log) at each of our maps' Chamfer.", "",
              "| our map | our B/block | our Chamfer (mm) / F@1 | SZ3 B/block at that Chamfer | SZ3's smallest map "
              "reaching it | SZ3 / our bytes | SZ3 smaller? |", "|---|---:|---|---:|---|---:|---|"]
        for r in kf.get("reverse", []):
            L.append(_chamfer_row(r))
        L += ["", "Our maps: " + "; ".join(f"{p['setting']}: {p['bytes_per_block']:.1f} B, {p['chamfer_mm']:.2f} mm, "
                                           f"F@1 {p['f1']:.3f}" for p in kf["ours"])
              + "".join(f"; {r['options']}: refused ({r['message']})" for r in kf["refused"]) + ".", "",
              f"Measured at load {kf['load']:.1f} (after the run).", ""]
    for ds in res["datasets"]:
        P = [p for p in res["points"] if p["dataset"] == ds]
        run = _runs(res)
        L += [f"### {ds} ({P[0]['blocks']} coded blocks)" if P else f"### {ds}", "",
              f"![{ds}](rd-peers-{_slug(ds)}.png)", "", f"**{ds}: at {', '.join(f'{b} B' for b in X_BYTES[1:5])} "
              "per coded block** (each curve read as above; - outside its range)", "",
              "| method | " + " | ".join(f"{b} B: F@1 / Chamfer mm / max cm" for b in X_BYTES[1:5]) + " |",
              "|---|" + "---:|" * 4]
        curves: dict[str, list[dict]] = {}
        for p in P:
            curves.setdefault(_curve(p), []).append(p)
        for name, S in sorted(curves.items()):
            cells = []
            for b in X_BYTES[1:5]:
                v = [pt.at_bytes(S, b, k) for k in ("f1", "chamfer_mm", "max_error_cm")]
                cells.append("-" if v[0] is None else f"{v[0]:.3f} / {_fmt(v[1], '{:.2f}')} / {_fmt(v[2], '{:.2f}')}")
            L.append(f"| {name} | " + " | ".join(cells) + " |")
        L += [f"- `sdfcodec encode` refused {' '.join(f'--{k} {v}' for k, v in r['options'].items())}: {r['message']}"
              for r in res.get("refused", []) if r["dataset"] == ds]
        L += ["", f"**{ds}: every point, with decode throughput** (blocks/s of the method's decoder over all blocks, "
              "best of 3, and as a ratio to a memory copy of the decoded float32 blocks timed interleaved with it)", "",
              "| method | setting | B/block | ratio | MSE | max (cm) | Chamfer (mm) | F@1 | decode blocks/s | "
              "decode, x memcpy |", "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
        for p in sorted(P, key=lambda p: (p["family"], p["method"], p["bytes_per_block"])):
            L.append(f"| {p['method']} | {p['setting']} | {p['bytes_per_block']:.1f} | {p['ratio']:.0f} | "
                     f"{p['mse']:.3g} | {p['max_error_cm']:.2f} | {_fmt(p['chamfer_mm'], '{:.2f}')} | {p['f1']:.3f} | "
                     f"{_fmt(p.get('decode_blocks_per_s'), '{:,.0f}')} | {_fmt(p.get('decode_vs_memcpy'), '{:.3f}')} |")
        L += ["", run, ""]
    m = res["machine"]
    L += [f"Run: {m['cpus']} CPUs, Python {m['python']}, pysz {m['pysz']}, zfpy {m['zfpy']}, numcodecs-wasm-sperr "
          f"{m['numcodecs-wasm-sperr']}; peers' run {peers_run['wall_s']:.0f} s, ours {ours_run['wall_s']:.0f} s."
          + (" Decode figures were taken under load (more than one job per core): compare the ratios taken "
             "interleaved, not the blocks/s." if max(peers_run["load_before"][0], peers_run["load_after"][0],
                                                     ours_run["load_before"][0], ours_run["load_after"][0])
             > m["cpus"] else ""), ""]
    return "\n".join(L)


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--kitchen", type=Path, default=Path(os.environ.get("SDFCODEC_KITCHEN", "7scenes-redkitchen")),
                    help="a 7-Scenes redkitchen sequence folder (colour and depth frames, poses, gravity); default: $SDFCODEC_KITCHEN, else ./7scenes-redkitchen")
    ap.add_argument("--kitchen-map", type=Path, default=None,
                    help="the whole fused kitchen as a lossless map (sdfcodec fuse KITCHEN OUT): the target 'smaller "
                         "than SZ3's at equal Chamfer' (skipped without it)")
    ap.add_argument("--quick", action="store_true", help="a tiny synthetic corner, few settings (the CI test)")
    ap.add_argument("--methods", default=None, help="comma-separated entries of METHODS (--list; default: "
                                                    "ours,sz3-peer,zfp,sperr)")
    ap.add_argument("--ours-only", action="store_true",
                    help="rerun only our maps (every `sdfcodec encode`: our points, decode on read, the whole-kitchen "
                         "maps) and re-render, keeping the peers' points of the committed OUT/rd-peers.json")
    ap.add_argument("--render", action="store_true", help="only recompute the targets from OUT/rd-peers.json's "
                                                           "points and rewrite it, the figures and the page section")
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
    if a.render:
        return rerender(a.out or ROOT / "docs")
    a.methods = "ours" if a.ours_only else a.methods or "ours,sz3-peer,zfp,sperr"
    unknown = [m for m in a.methods.split(",") if m not in METHODS]
    if unknown:
        ap.error(f"unknown method(s) {unknown}; known: {', '.join(METHODS)}")
    import torch

    with torch.no_grad():  # a context, not set_grad_enabled: main() is also called in-process by the tests
        return _study(a, argv)


def _datasets(a, work: Path) -> list[tuple[str, Callable]]:
    """(name, thunk) of each data set asked: each is built when its turn comes, so a long run writes as it goes."""
    if a.quick:
        return [("synthetic (quick)", lambda: (lambda c, t: (c, *fused_like(t)))(*synthetic_blocks(True)))]
    want, sets = a.datasets.split(","), []
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
    return sets


def _study(a, argv) -> dict:
    work = a.workdir or (Path(tempfile.mkdtemp(prefix="rd-peers-")) if a.quick else ROOT / "build" / "rd-peers")
    work.mkdir(parents=True, exist_ok=True)
    out = a.out or (work if a.quick else ROOT / "docs")
    out.mkdir(parents=True, exist_ok=True)
    run = {"command": _command(argv), "cpus": os.cpu_count(), "load_before": os.getloadavg(), "t0": time.perf_counter()}
    old = json.loads((out / "rd-peers.json").read_text()) if a.ours_only else None
    sets = _datasets(a, work)
    if old is not None:  # the committed run's data sets and its peers' points
        sets = [(n, b) for n, b in sets if n in old["datasets"]]
    points, names, res, dor = [], [], {}, {}
    kf = None if old is None else old.get("kitchen_full")
    for name, build in sets:
        d = Data(name, *build(), work)
        print(f"{name}: {d.n} coded blocks", flush=True)
        for m in a.methods.split(","):
            METHODS[m](d, a.quick)
        dor[name] = decode_on_read(d, a.quick)
        for p in d.points:
            p["blocks"] = d.n
        kept = [] if old is None else [p for p in old["points"] if p["dataset"] == name and p["family"] != "ours"]
        points += kept + d.points
        names.append(name)
        res = _write(out, points, names, run, old, dor, kf)  # after each data set: a long run keeps its part
    if a.kitchen_map is not None:
        kf = kitchen_full(a.kitchen_map, work, a.quick)
        res = _write(out, points, names, run, old, dor, kf)
    return res


def _command(argv) -> str:
    args = list(sys.argv[1:] if argv is None else argv)
    for i, a in enumerate(args[:-1]):  # this machine's folders say nothing to a reader: their role instead
        if a in ("--kitchen", "--kitchen-map", "--workdir", "--out"):
            args[i + 1] = a[2:].upper().replace("-", "_") + ("" if a == "--kitchen-map" else "_DIR")
    return "python examples/peers_study.py" + (" " + shlex.join(args) if args else "")


def _write(out: Path, points: list[dict], names: list[str], run: dict, old: dict | None, dor: dict,
           kf: dict | None) -> dict:
    from importlib.metadata import version

    now = {**{k: v for k, v in run.items() if k != "t0"}, "load_after": os.getloadavg(),
           "wall_s": time.perf_counter() - run["t0"], "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())}
    refused = [r for r in REFUSED if r["dataset"] in names]
    res = {"datasets": names, "points": points, "refused": refused, "peer_bytes": list(PEER_BYTES),
           "targets": {ds: targets(points, ds, refused) for ds in names}, "decode_on_read": dor,
           "kitchen_full": kf, "peers_run": now if old is None else old["peers_run"], "ours_run": now,
           "note": ("Data sets: kitchen = the held-out half (x > middle) of the 7-Scenes redkitchen fused at 2 cm; "
                    "synthetic = room_scene(seed=0, geometry='rich', ceiling=True) at 2 cm on a lattice moved by "
                    "0.3 voxel, fused-like; rooms = synthetic_room(seed 1 and 2, behind='solid') side by side, fused-like; "
                    "building = building_scene(seed=0, rooms_per_side=1) like synthetic. Our maps are surface-true "
                    "(observation mask, counted in their bytes); 'ours' rows count every file of the map, the "
                    "shipped model referenced (the default of `sdfcodec encode`); the peers (SZ3, ZFP, SPERR) code "
                    "the plain field (unobserved voxels as free space), with no mask to count, bytes as their own "
                    "libraries return them."),
           "machine": {"cpus": os.cpu_count(), "python": sys.version.split()[0], "pysz": version("pysz"),
                       "zfpy": version("zfpy"), "numcodecs-wasm-sperr": version("numcodecs-wasm-sperr")}}
    _save(out, res)
    print(f"  after {now['wall_s']:.0f} s", flush=True)
    return res


def _save(out: Path, res: dict) -> None:
    (out / "rd-peers.json").write_text(json.dumps(res, indent=1) + "\n")
    for ds in res["datasets"]:
        plot(res["points"], ds, out / f"rd-peers-{_slug(ds)}.png")
    replace_section(out / "rate-distortion.md", "peers", markdown(res), title="# Rate-distortion")
    print(f"wrote {out / 'rd-peers.json'}, rd-peers-*.png and the 'peers' section of rate-distortion.md", flush=True)


def rerender(out: Path) -> dict:
    """Recompute the targets from the points of ``out``/rd-peers.json (nothing measured) and rewrite it, the
    figures and the page's section: after a change to examples/peers_targets.py."""
    res = json.loads((out / "rd-peers.json").read_text())
    res["targets"] = {ds: targets(res["points"], ds, res["refused"]) for ds in res["datasets"]}
    kf = res.get("kitchen_full")
    if kf:
        kf.update(equal_chamfer=pt.equal_chamfer(kf["ours"], kf["sz3"]), reverse=pt.equal_chamfer(kf["sz3"], kf["ours"]))
    _save(out, res)
    return res


if __name__ == "__main__":
    main()
