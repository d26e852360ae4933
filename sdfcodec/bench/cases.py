"""The device check (``sdfcodec bench --full [--device cuda]``): one table of cases, one JSON document.

Every case is a function ``case(setup) -> list of records`` in :data:`CASES`; most build :class:`Figure` s (a
candidate and its baselines, timed interleaved by :func:`run_figure`). The same code runs on every device
(the device is a parameter, never a branch of its own), so a CPU run (``--device cpu``, the CI smoke test
with ``--quick``) exercises the code paths a GPU run takes, and both write the same keys.

Cases (sizes in :data:`SIZES`, quick and full):

``pca-decode``
    pca-32/64/128 decode of codes already on the device: ``codec.decode`` in float32, and in bfloat16 and
    float16 as one ``addmm`` on the codec's public state (the codec has no low-precision path: this is what one
    would give), with the error it adds in metres (``max_abs_error_m``, against the float32 decode, over the
    default 0.14 m truncation range). Baselines: torch's GEMM of the decode's shape into a preallocated output
    (``baseline``, the roofline) and a device-to-device copy of the decoded output (``copy_blocks_per_s``:
    bytes copied per second over the bytes of one decoded block at that dtype).
``decode-on-read``
    :meth:`sdfcodec.Map.iter_decoded` of a local pca-64 map into the device's memory
    (:func:`~sdfcodec.bench.codecs.bench_decode_on_read`, with its numpy roofline, memory copy and in-memory
    decode).
``search``
    the search scoring kernel on the device (:func:`~sdfcodec.bench.search.bench_search`).
``tracking``
    one SDF Tracker frame (``frames_per_s``) on the device against a dense field of the analytic scene, the
    depth image ray cast from the exact scene; baseline: one pass of the field's value and gradient at every
    pixel's point (``baseline``), the least a frame must sample. ``translation_error_m`` checks it tracked.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Callable, Iterable

import numpy as np

from ..core._lazy import lazy_module
from .codecs import bench_decode_on_read
from .harness import interleave, load, ratio, run_document
from .search import bench_search

if TYPE_CHECKING:
    from ..codec import Codec

torch = lazy_module("torch")

__all__ = ["Figure", "Setup", "CASES", "SIZES", "run_figure", "run_cases"]

TRUNCATION = (-0.04, 0.1)
#: sizes per mode: blocks per decode batch, blocks of the decode-on-read map, codes per search batch, tracking
#: image (width, height)
SIZES = {"quick": {"decode_batch": 128, "read_blocks": 1024, "search_batch": 4096, "image": (160, 120)},
         "full": {"decode_batch": 65536, "read_blocks": 65536, "search_batch": 1 << 20, "image": (640, 480)}}
DTYPES = ("float32", "bfloat16", "float16")


@dataclass(frozen=True)
class Setup:
    """What every case gets: the device, the mode's sizes, timing settings and a progress callback."""

    device: str
    sizes: dict[str, Any]
    repeats: int = 5
    min_time: float = 0.2
    progress: Callable[[str], None] = lambda s: None

    @property
    def dev(self) -> Any:
        return torch.device(self.device)

    def sync(self) -> None:
        """Wait for the device's queued work (a no-op on the CPU): timed callables end with it."""
        if self.dev.type == "cuda":
            torch.cuda.synchronize(self.dev)


@dataclass
class Figure:
    """One figure: ``candidate`` and its ``baselines`` (name -> callable; the first is the record's
    ``baseline``), ``work`` units (blocks, frames) per call, and the record's ``fields`` (what was measured,
    and figures measured once, such as an error)."""

    fields: dict[str, Any]
    candidate: Callable[[], object]
    baselines: dict[str, Callable[[], object]]
    work: int
    unit: str = "blocks"
    baseline_work: dict[str, int] = field(default_factory=dict)  # per baseline when not ``work`` (a copy's blocks)


def run_figure(setup: Setup, fig: Figure) -> dict[str, Any]:
    """Time ``fig`` interleaved with its baselines; the record: ``fields``, ``{unit}_per_s`` (median) and
    ``_best``, for the first baseline ``baseline_{unit}_per_s`` and ``ratio_to_baseline`` (ratio of medians),
    ``ratio_of_bests``, ``ratio_paired``, ``ratio_cpu``; for the others ``{name}_{unit}_per_s`` and
    ``ratio_to_{name}``; ``load_before/after``."""
    load0 = load()
    tm = interleave({"candidate": fig.candidate, **fig.baselines}, repeats=setup.repeats, min_time=setup.min_time)
    c, u = tm["candidate"], fig.unit
    rec = {**fig.fields, "device": setup.device, f"{u}_per_s": fig.work / c.median,
           f"{u}_per_s_best": fig.work / c.best, "repeats": setup.repeats}
    for i, name in enumerate(fig.baselines):
        b, w = tm[name], fig.baseline_work.get(name, fig.work)
        key = "baseline" if i == 0 else name
        rec[f"{key}_{u}_per_s"] = w / b.median
        rec["ratio_to_baseline" if i == 0 else f"ratio_to_{name}"] = (fig.work / c.median) / (w / b.median)
        if i == 0:  # the same ratio other ways (harness.ratio), scaled by the work per call of each side
            rec.update({k: v * fig.work / w for k, v in ratio(c, b).items() if k != "ratio_of_medians"})
    rec.update(load_before=load0, load_after=load())
    return rec


def _analytic_codes(codec: Codec, n: int, dev: Any) -> Any:
    from ..testing import analytic_blocks

    x = torch.from_numpy(np.concatenate([analytic_blocks(512, seed=3)] * -(-n // 512))[:n]).to(dev)
    return codec.encode(x)


def pca_decode(setup: Setup) -> list[dict]:
    from ..registry import pretrained_codec

    n, dev, sync = setup.sizes["decode_batch"], setup.dev, setup.sync
    records = []
    for k in (32, 64, 128):
        codec = pretrained_codec("pca", k)
        codes = _analytic_codes(codec, n, dev)
        state = codec.state_dict()
        comps, mean = (torch.from_numpy(state[a]).to(dev) for a in ("components", "mean"))
        exact = codec.decode(codes[:1024]).reshape(-1, 4096)
        for name in DTYPES:
            dt = getattr(torch, name)
            z, w, b = codes.to(dt), comps.to(dt), mean.to(dt)
            out = torch.ones((n, 4096), dtype=dt, device=dev)
            src = torch.ones((n, 4096), dtype=dt, device=dev)
            if name == "float32":
                cand, how = (lambda: (codec.decode(codes), sync())), "codec.decode"
                err = 0.0
            else:
                cand = (lambda z=z, w=w, b=b: (torch.addmm(b, z, w), sync()))
                how = f"one addmm in {name} on the codec's state"
                err = float((torch.addmm(b, z[:1024], w).float() - exact).abs().max()) * (TRUNCATION[1] - TRUNCATION[0])
            setup.progress(f"pca-{k} decode {name} batch {n}")
            fig = Figure({"operation": "pca-decode", "codec": "pca", "code_size": k, "dtype": name, "batch": n,
                          "decode": how, "max_abs_error_m": err, "baseline": f"torch GEMM ({n},{k})x({k},4096) {name}, "
                          "preallocated output", "copy": f"device copy of ({n},4096) {name}"},
                         cand, {"gemm": lambda z=z, w=w, out=out: (torch.matmul(z, w, out=out), sync()),
                                "copy": lambda out=out, src=src: (out.copy_(src), sync())}, n)
            rec = run_figure(setup, fig)
            rec["copy_bytes_per_s"] = rec["copy_blocks_per_s"] * 4096 * dt.itemsize
            records.append(rec)
    return records


def decode_on_read(setup: Setup) -> list[dict]:
    from ..registry import pretrained_codec

    n = setup.sizes["read_blocks"]
    setup.progress(f"pca-64 decode on read of {n} blocks into {setup.device}")
    return bench_decode_on_read(pretrained_codec("pca", 64), n, device=setup.device, min_time=setup.min_time,
                                name="pca", http=False, repeats=setup.repeats)


def search_scoring(setup: Setup) -> list[dict]:
    setup.progress(f"search scoring of {setup.sizes['search_batch']} pca-64 codes")
    return bench_search([64], batches=[setup.sizes["search_batch"]], device=setup.device,
                        min_time=setup.min_time, repeats=setup.repeats)


def _ray_cast(sdf: Callable[[np.ndarray], np.ndarray], pose: np.ndarray, k: tuple, size: tuple[int, int],
              far: float = 4.0) -> np.ndarray:
    """z-depth ``(H, W)`` float32 of the exact scene ``sdf`` by sphere tracing (0 where no surface within far)."""
    w, h = size
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    d_cam = np.stack([(u - k[2]) / k[0], (v - k[3]) / k[1], np.ones_like(u)], -1).reshape(-1, 3)
    dirs = d_cam @ pose[:3, :3].T
    norm = np.linalg.norm(dirs, axis=1)
    dirs /= norm[:, None]
    t = np.zeros(len(dirs))
    live = np.ones(len(dirs), bool)
    for _ in range(200):
        idx = np.flatnonzero(live)
        if not len(idx):
            break
        d = sdf(pose[:3, 3] + t[idx, None] * dirs[idx])
        t[idx] += d
        live[idx[(d < 1e-5) | (t[idx] > far)]] = False
    depth = np.where(t <= far, t / norm, 0.0)  # distance along the ray -> z-depth
    return depth.reshape(h, w).astype(np.float32)


def tracking(setup: Setup) -> list[dict]:
    from ..data.render import look_at
    from ..tracking.densefield import DenseField
    from ..core.geometry import se3_exp
    from ..core.sdf import sample_volume
    from ..testing import analytic_scene
    from ..tracking.tracker import SDFTracker, backproject

    w, h = setup.sizes["image"]
    scene = analytic_scene()
    vol = sample_volume(scene, (96, 80, 56), 0.02, truncation=TRUNCATION)
    fld = DenseField(vol, 0.02, truncation=TRUNCATION, device=setup.dev)
    f = 525.0 * w / 640
    k = (f, f, (w - 1) / 2, (h - 1) / 2)
    truth = look_at(np.array([1.7, 1.45, 0.95]), np.array([0.7, 0.55, 0.35]))
    depth_np = _ray_cast(scene, truth, k, (w, h))
    depth = torch.from_numpy(depth_np).to(setup.dev)
    start = truth @ se3_exp(np.array([0.01, -0.008, 0.006, 0.004, -0.006, 0.003]))  # ~1.5 cm, ~0.45 degrees off
    tracker = SDFTracker(fld, k)
    res = tracker.track(depth, start)
    # the baseline: value and gradient of the field at every pixel's world point, once
    cam = backproject(depth_np, k).numpy().astype(np.float64)  # the valid pixels' camera-frame points
    pts = torch.from_numpy((cam @ truth[:3, :3].T + truth[:3, 3]).astype(np.float32)).to(setup.dev)
    setup.progress(f"tracking one {w} x {h} frame on {setup.device}")
    fig = Figure({"operation": "tracking", "resolution": [w, h], "success": bool(res.success),
                  "iterations": res.iterations, "translation_error_m": float(np.linalg.norm(
                      np.asarray(res.pose)[:3, 3] - truth[:3, 3])),
                  "baseline": f"field value and gradient at the {len(pts)} pixels' points, once"},
                 lambda: (tracker.track(depth, start), setup.sync()),
                 {"sample": lambda: (fld.sample_with_gradient(pts), setup.sync())}, 1, unit="frames")
    return [run_figure(setup, fig)]


#: name -> case; ``sdfcodec bench --full --cases a,b`` runs a subset, in this order
CASES: dict[str, Callable[[Setup], list[dict]]] = {
    "pca-decode": pca_decode,
    "decode-on-read": decode_on_read,
    "search": search_scoring,
    "tracking": tracking,
}


def run_cases(device: str = "cpu", *, quick: bool = False, repeats: int = 5, min_time: float | None = None,
              cases: Iterable[str] | None = None, progress: Callable[[str], None] | None = None,
              sizes: dict[str, Any] | None = None, checkpoint: Callable[[dict], None] | None = None
              ) -> dict[str, Any]:
    """Run the device check; returns the JSON document: ``schema``, ``command``, ``mode``, ``sizes``,
    ``machine``, ``load_before``, ``load_after``, ``seconds``, ``records`` (every case's records, each with
    ``operation``) and ``errors`` (``{"case", "error"}`` of each case that raised: the other cases still run,
    so one broken path on a device never costs the figures of the rest). ``sizes`` overrides entries of the
    mode's :data:`SIZES` (tests use tiny ones); ``checkpoint(doc)`` is called after each case (to write what
    is measured so far)."""
    from ..errors import InvalidValueError

    names = list(CASES) if cases is None else list(cases)
    unknown = [n for n in names if n not in CASES]
    if unknown:
        raise InvalidValueError(f"unknown bench case(s) {unknown}; the cases are {', '.join(CASES)}")
    mode = "quick" if quick else "full"
    min_time = (0.02 if quick else 0.2) if min_time is None else min_time
    setup = Setup(device, {**SIZES[mode], **(sizes or {})}, repeats, min_time,
                  progress or (lambda s: None))
    setup.dev  # a bad device name fails here, before anything runs
    doc: dict[str, Any] = {**run_document(mode, device), "sizes": setup.sizes}
    t0 = time.perf_counter()
    doc.update(records=[], errors=[])
    for n in names:
        try:
            doc["records"] += CASES[n](setup)
        except Exception as e:  # noqa: BLE001 - reported in the document (and by the CLI's exit status)
            doc["errors"].append({"case": n, "error": f"{type(e).__name__}: {e}"})
        doc.update(load_after=load(), seconds=round(time.perf_counter() - t0, 1))
        if checkpoint is not None:
            checkpoint(doc)
    bad = [r["operation"] for r in doc["records"]
           if not all(math.isfinite(v) for k, v in r.items() if k.endswith("_per_s"))]
    if bad:  # a timing bug, not data
        doc["errors"].append({"case": ",".join(bad), "error": "a figure is not finite"})
    return doc
