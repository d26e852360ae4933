"""The search benchmark: the scoring kernel on in-memory codes beside a numpy product of its shape, and whole
searches of a map on disk (:func:`bench_search`)."""

from __future__ import annotations

from typing import Any, Callable, Iterable

import numpy as np

from ..core._lazy import lazy_module
from .codecs import timed_record
from .harness import interleave, load, time_call

torch = lazy_module("torch")

__all__ = ["bench_search"]


def bench_search(code_sizes: Iterable[int] = (64,), *, descriptors: int = 15, batches: Iterable[int] = (65536,),
                 device: str = "cpu", min_time: float = 0.2, map_blocks: int = 0,
                 map_levels: dict[int, Iterable[int]] | None = None, workdir: Any = None,
                 progress: Callable[[str], None] | None = None, repeats: int = 5) -> list[dict]:
    """Search throughput: the scoring kernel on in-memory codes beside a plain numpy matrix product of the same
    shape, and (``map_blocks > 0``) whole searches of a map on disk with the bytes they read.

    Codes are random with the shipped eigenshapes' per-component spread (``sqrt(explained_variance)``), so
    their magnitudes (and compressibility) resemble real ones; descriptors are the floor model.

    Parameters
    ----------
    code_sizes : iterable of int
        Code lengths ``k`` (1..128: prefixes of the shipped pca-128 basis).
    descriptors : int
        Model size ``M`` (15: the paper's floor model; other values: planes at that many offsets).
    batches : iterable of int
        Blocks per kernel call.
    device : str
        Where the kernel runs (the baseline is always numpy on the CPU).
    min_time : float
        Seconds per timing round (``repeats`` rounds interleaved with the baseline).
    map_blocks : int
        Coded blocks of the benchmark map (0: skip the map records). The map is dense in a cube of blocks.
    map_levels : mapping of int to sequence of int, optional
        Code size -> levels to search its map at (default: the full size; e.g. ``{128: [32, 128]}``).
    workdir : str or os.PathLike, optional
        Where the map is written (default: a temporary directory).

    Returns
    -------
    list of dict
        Records like :func:`bench_codec`'s: ``codec``, ``code_size``, ``operation``
        (``"search"`` for the kernel, ``"search-map"`` for a whole search), ``batch``, ``device``,
        ``blocks_per_s``, ``baseline`` (``"numpy matmul"``, into a preallocated output),
        ``baseline_blocks_per_s``, ``ratio_to_baseline`` (medians; the kernel's bests too, as
        :func:`~sdfcodec.bench.codecs.timed_record`), ``us_per_block``, ``load_before`` and ``load_after``
        (``os.getloadavg()`` around the timing: this is a shared machine); map records add ``level``,
        ``code_bytes_read``, ``code_bytes_full``, ``seconds``.
    """
    # imported here: this module is imported by the CLI and plugins that never search, and search imports the
    # map reader
    import math
    import tempfile
    from pathlib import Path

    from ..map import create_map, open_map
    from ..registry import pretrained_codec
    from ..search.query import build_query
    from ..search.engine import search
    from ..search.scoring import Scorer

    records = []
    dev = torch.device(device)
    sync = torch.cuda.synchronize if dev.type == "cuda" else (lambda: None)
    rng = np.random.default_rng(0)
    for k in code_sizes:
        codec = pretrained_codec("pca", k)
        spread = np.sqrt(codec.explained_variance_).astype(np.float32)
        q = build_query("floor", codec=codec, offsets=descriptors).descriptors
        scorer = Scorer(q, dev)
        qt = np.ascontiguousarray(q.T)
        for b in batches:
            codes = rng.standard_normal((b, k), dtype=np.float32) * spread
            x = torch.from_numpy(codes).to(dev) if dev.type != "cpu" else codes
            if progress:
                progress(f"search kernel pca-{k} batch {b}")
            load0 = load()
            if dev.type == "cpu":
                out = np.ones((b, len(q)), np.float32)
                base, what = (lambda: np.matmul(codes, qt, out=out)), "numpy matmul"
            else:  # on a device the roofline is the device's own product of the same shape
                tq, tout = torch.from_numpy(qt).to(dev), torch.ones((b, len(q)), device=dev)
                base, what = (lambda: (torch.matmul(x, tq, out=tout), sync())), f"torch matmul on {dev}"
            tm = interleave({"candidate": lambda: (scorer(x), sync()), "baseline": base}, repeats=repeats,
                            min_time=min_time)
            records.append(dict(timed_record(tm["candidate"], tm["baseline"], b, codec="pca", code_size=k,
                                             operation="search", batch=b, device=str(dev), descriptors=len(q),
                                             baseline=what),
                                load_before=load0, load_after=load()))
        if map_blocks > 0:
            tmp = tempfile.TemporaryDirectory(prefix="sdfcodec-bench-") if workdir is None else None
            try:
                path = Path(tmp.name if tmp else workdir) / f"bench-pca-{k}.sdfz"
                side = math.ceil(map_blocks ** (1 / 3))
                coords = np.stack(np.meshgrid(*[np.arange(side)] * 3, indexing="ij"), -1).reshape(-1, 3)[:map_blocks]
                if progress:
                    progress(f"writing a {len(coords)}-block pca-{k} map")
                with create_map(path, codec=codec, voxel_size=0.02, overwrite=True, tool="sdfcodec.search.bench") as w:
                    for i in range(0, len(coords), 1 << 16):
                        c = coords[i:i + (1 << 16)]
                        w.write_codes(c, rng.standard_normal((len(c), k), dtype=np.float32) * spread)
                m = open_map(path)
                m.codec  # load the codec state once, outside the timed searches
                for lv in (map_levels or {}).get(k, [k]):
                    if progress:
                        progress(f"searching the pca-{k} map at level {lv}")
                    load0 = load()
                    res = search(m, build_query("floor", codec=codec, offsets=descriptors), level=lv, top=100,
                                 device=dev)
                    base_codes = rng.standard_normal((len(coords), lv), dtype=np.float32)
                    base_q = np.ascontiguousarray(q[:, :lv].T)
                    base_out = np.ones((len(coords), len(q)), np.float32)
                    tb = time_call(lambda: np.matmul(base_codes, base_q, out=base_out), min_time, repeats)
                    t = res.stats["seconds"]
                    records.append({"codec": "pca", "code_size": k, "operation": "search-map", "level": lv,
                                    "batch": len(coords), "device": str(dev), "descriptors": len(q),
                                    "blocks_per_s": len(coords) / t, "baseline": "numpy matmul",
                                    "baseline_blocks_per_s": len(coords) / tb, "ratio_to_baseline": tb / t,
                                    "us_per_block": 1e6 * t / len(coords), "seconds": t,
                                    "code_bytes_read": res.stats["code_bytes_read"],
                                    "code_bytes_full": res.stats["code_bytes_full"],
                                    "load_before": load0, "load_after": load()})
            finally:
                if tmp is not None:
                    tmp.cleanup()
    return records

