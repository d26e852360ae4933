"""Search with the CLI's defaults on maps nobody tuned on: precision and recall per room kind and query.

    PYTHONPATH=. .venv/bin/python docs/search/evaluate.py [--seeds 7501 7502 7503] [--jobs 3] [--out docs/search/eval-defaults.json]
    PYTHONPATH=. .venv/bin/python docs/search/evaluate.py --kinds fused fused-tilted --jobs 2 --out docs/search/eval-pca64-fused.json
    PYTHONPATH=. .venv/bin/python docs/search/evaluate.py --kinds fused fused-tilted --jobs 2 --target-bytes 128 --out docs/search/eval-vr128.json
    PYTHONPATH=. .venv/bin/python docs/search/evaluate.py --kinds fused fused-tilted --jobs 2 --target-bytes 64 --out docs/search/eval-vr64.json

Every map is searched exactly as ``sdfcodec search MAP --query Q`` does with no flags (``threshold="auto"``:
the calibrated threshold, ``behind`` and ``up`` from the map); precision and recall of the selection are
pooled over the rooms of a kind. Room kinds:

* ``exact``: exact truncated SDFs of furnished rooms (``sdfcodec.search.rooms.synthetic_room(behind="solid")``,
  primitives of ``sdfcodec.core.sdf``), layouts ``poor``, ``normal``, ``rich``, written with ``write_volume`` (what
  ``sdfcodec encode room.npy`` does);
* ``exact-open``: an analytic scene, a floor over solid ground with two boxes, a sphere and a
  cylinder, 160 x 160 x 64 voxels, no walls (only floor truth);
* ``exact-tilted``: exact rooms tilted by up to 10 degrees;
* ``fused`` / ``fused-tilted``: rooms rendered as depth frames along a camera path and fused
  (``sdfcodec.fusion.tsdf.fuse``), encoded with their observation (what ``sdfcodec fuse`` + ``sdfcodec encode``
  do); the tilted ones turned by up to 10 degrees with their camera path;
* ``kitchen``: the real 7-Scenes kitchen, fused, up from its gravity file; labels from plane fits on the
  lossless map (``kitchen_labels``).

Truth per block (``sdfcodec.search.metrics.TRUTH`` on ``LabelledRoom.block_labels``): a *clean* floor / wall /
ceiling block has >= 90 % of its surface voxels on one such primitive, which covers >= 90 % of its section of
the block in its own plane; planes only clipping a corner (section under a quarter face) are left out; every
other block is a negative. *(pure)*: >= 90 % against < 10 %, mixed blocks left out. Edges, corners and poles
(exact rooms): see ``TRUTH``. Each floor, wall and ceiling search runs with the map-level stage (the CLI's
default) and without it (``--shape-only``). Codec: the shipped pca-64, searched at its full level
(``--target-bytes B``: variable-rate maps of B bytes per coded block, pca-128 prefixes with the pinned mask).
"""

from __future__ import annotations

import argparse
import os
import json
import math
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

import sdfcodec
from sdfcodec import pretrained_codec
from sdfcodec.search.engine import expand, search
from sdfcodec.search.rooms import LabelledRoom, synthetic_room
from sdfcodec.search.metrics import TRUTH

HERE = Path(__file__).resolve().parent


def _kitchen_dir() -> Path | None:
    """A 7-Scenes redkitchen sequence folder (frames, poses, gravity): --kitchen DIR or $SDFCODEC_KITCHEN."""
    d = os.environ.get("SDFCODEC_KITCHEN")
    return Path(d) if d else None
QUERIES = ("floor", "wall", "ceiling")
PARTS = ("edge", "corner", "pole")


def _write(path: Path, room: LabelledRoom, codec, **kw) -> sdfcodec.Map:
    with sdfcodec.create_map(path, codec=codec, voxel_size=room.voxel_size, truncation=room.truncation,
                             origin=tuple(room.origin), overwrite=True, **kw) as w:
        w.write_volume(room.volume)
    return sdfcodec.open_map(path)


def open_room(seed: int) -> LabelledRoom:
    """An analytic scene: a floor over solid ground, two boxes, a sphere, a cylinder (160 x 160 x 64)."""
    from sdfcodec.data.render import RoomScene
    from sdfcodec.search.rooms import LabelledRoom
    from sdfcodec.core.sdf import Box, Cylinder, Sphere, sample_volume, Scene

    rng = np.random.default_rng([seed, 3])
    vs, shape = 0.02, (160, 160, 64)
    h = rng.uniform(0.2, 0.5)  # floor height in the grid
    prims = [Box((1.6, 1.6, h - 1.0), (3.0, 3.0, 1.0))]
    labels = ["floor"]
    for _ in range(2):
        c = rng.uniform(0.6, 2.6, 2)
        half = rng.uniform(0.15, 0.35, 3)
        prims.append(Box((c[0], c[1], h + half[2]), tuple(half)))
        labels.append("furniture")
    c = rng.uniform(0.6, 2.6, 2)
    r = rng.uniform(0.15, 0.3)
    prims.append(Sphere((c[0], c[1], h + r), r))
    c = rng.uniform(0.6, 2.6, 2)
    prims.append(Cylinder((c[0], c[1], h + 0.3), rng.uniform(0.1, 0.25), 0.3))
    labels += ["furniture", "furniture"]
    vol = sample_volume(Scene(prims), shape, vs, (0.0, 0.0, 0.0))
    scene = RoomScene(prims, labels, (3.2, 3.2, 1.28), seed, "open")
    return LabelledRoom(volume=vol, origin=np.zeros(3), voxel_size=vs, truncation=(-0.04, 0.1), scene=scene,
                        rotation=np.eye(3), size=(3.2, 3.2, 1.28), up=np.array([0.0, 0.0, 1.0]), behind="solid")


def fused_room(seed: int, tilt_deg: float, path: Path, codec, frames: int = 120, **kw
               ) -> tuple[sdfcodec.Map, LabelledRoom]:
    """Render a furnished room with a ceiling along a camera path, fuse it, encode it with its observation
    (``kw``: more arguments of ``create_map``)."""
    from sdfcodec.data.render import DEFAULT_INTRINSICS, Renderer, RoomScene, camera_path, room_scene
    from sdfcodec.search.rooms import LabelledRoom
    from sdfcodec.data.sequences import Frame
    from sdfcodec.fusion.tsdf import fuse
    from sdfcodec.core.geometry import rot_x, rot_z
    from sdfcodec.core.sdf import grid_points

    rng = np.random.default_rng([seed, 11])
    scene = room_scene(seed, geometry=("normal", "rich")[seed % 2], ceiling=True)
    rot = np.eye(3)
    if tilt_deg:
        a = rng.uniform(0, 2 * math.pi)
        rot = rot_z(a) @ rot_x(math.radians(rng.uniform(0.5 * tilt_deg, tilt_deg))) @ rot_z(-a)
    from sdfcodec.search.rooms import _pose  # noqa: the evaluation poses primitives as synthetic_room does
    posed = RoomScene([_pose(p, rot) for p in scene.primitives], list(scene.labels), scene.size, seed, scene.geometry)
    poses = camera_path(scene, frames, 3.0)
    lift = np.eye(4)
    lift[:3, :3] = rot
    poses = lift @ poses
    renderer = Renderer(posed)
    fr = [Frame(index=i, timestamp=i / 30, depth=renderer.render(p), pose=p, path=Path(f"f{i}")) for i, p in
          enumerate(poses)]
    fused = fuse(fr, voxel_size=0.02, truncation=(-0.04, 0.1), intrinsics=DEFAULT_INTRINSICS, quiet=True)
    with sdfcodec.create_map(path, codec=codec, voxel_size=0.02, origin=tuple(fused.origin), overwrite=True,
                             tool="sdfcodec fuse (evaluation)", **kw) as w:
        w.write_blocks(fused.coords, fused.tsdf, weights=fused.weights)
    m = sdfcodec.open_map(path)
    # exact distances on the fused grid, for the labels
    shape = tuple(int(n) for n in m.shape_voxels)
    from sdfcodec.search.rooms import _sample_union  # noqa: the same sampler as synthetic_room
    raw = _sample_union(posed.primitives, shape, 0.02, np.asarray(m.origin), reach=0.12)
    vol = np.clip(raw, -0.04, 0.1).astype(np.float32)
    lab = LabelledRoom(volume=vol, origin=np.asarray(m.origin), voxel_size=0.02, truncation=(-0.04, 0.1),
                       scene=posed, rotation=rot, size=scene.size, up=rot[:, 2].copy(), behind="unobserved")
    del grid_points
    return m, lab


#: Kitchen walls (``kitchen_labels``): a vertical planar block is a wall of the room when at most this share of the
#: map's observed zero crossings lie more than BOUND_BEHIND metres behind its plane.
BOUND_SHARE = 0.02
BOUND_BEHIND = 0.1


def kitchen_labels(raw: sdfcodec.Map, coords: np.ndarray, gravity_up: np.ndarray) -> dict:
    """Labels of the kitchen's blocks from plane fits on the lossless map.

    Each block's observed zero crossings (between observed neighbours differing by < 0.1 m) are fitted with a
    plane (SVD); a block is *planar* with >= 64 crossings at an rms distance < 0.5 voxel, its normal pointing
    along the field's mean gradient. The floor plane is fitted to the crossings of the planar blocks facing
    within 20 degrees of the gravity file's up whose centroids are in the lowest quarter of those blocks along
    it, then refitted five times to the crossings of planar blocks whose normals are within 10 degrees of the
    plane's and whose centroids lie within 0.04 m of it (the kitchen's floor is 6 degrees off the recorded
    gravity, so a height band along gravity would cut it into strips). *Floor*: those blocks. *Up-facing*:
    planar blocks facing within 10 degrees of the floor's normal (floor, table and counter tops). *Vertical*:
    blocks whose crossings lie >= 90 % within 2 voxels of their own plane, whose normal is within 10 degrees of
    perpendicular to it (walls, cabinet fronts, appliance sides). *Wall*: a vertical block that bounds the room,
    with at most ``BOUND_SHARE`` of the map's crossings more than ``BOUND_BEHIND`` behind its plane; vertical
    blocks that do not (cabinet fronts, appliance sides: the counter, the floor or the wall above them lie
    behind) are left out of the wall truth, neither positive nor negative (the ``vertical`` truth, every vertical
    block, is reported beside it). *Floor* (strict): >= 64 crossings, >= 90 % of them within 2 voxels of the
    floor plane, or of the block's own plane where that plane is within 10 degrees of the floor's and within 2
    voxels of it at the crossings' centroid (a fused real floor bends by a voxel or two across the room). Blocks
    with fewer than 64 observed crossings (a surface passing near a face, or seen in part) cannot be labelled and
    are left out of every truth. *Ceiling*: none is in view."""
    vs = raw.voxel_size
    blocks = expand(raw, coords, device="cpu").blocks
    obs = raw.read_observed(coords)
    normal, rms, centroid, npts, pts_of = [], [], [], [], []
    for c, b, o in zip(coords, blocks, obs):
        pts = []
        for ax in range(3):
            a, bb = np.take(b, range(15), axis=ax), np.take(b, range(1, 16), axis=ax)
            ok = np.take(o, range(15), axis=ax) & np.take(o, range(1, 16), axis=ax)
            cross = (np.sign(a) != np.sign(bb)) & ok & (np.abs(a - bb) < 0.1)
            idx = np.argwhere(cross).astype(np.float64)
            idx[:, ax] += a[cross] / (a[cross] - bb[cross])
            pts.append(idx)
        p = np.asarray(raw.origin) + vs * (16 * c + np.concatenate(pts))
        npts.append(len(p))
        pts_of.append(p)
        if len(p) < 3:
            normal.append(np.zeros(3)), rms.append(9.0), centroid.append(np.zeros(3))
            continue
        mu = p.mean(axis=0)
        _, sv, vt = np.linalg.svd(p - mu, full_matrices=False)
        n = vt[2]
        grad = np.stack(np.gradient(b), -1)[(np.abs(b) < 0.02) & o].mean(axis=0)
        normal.append(n if n @ grad >= 0 else -n)
        rms.append(float(sv[2] / math.sqrt(len(p)) / vs))
        centroid.append(mu)
    normal, rms, centroid, npts = map(np.asarray, (normal, rms, centroid, npts))
    planar = (npts >= 64) & (rms < 0.5)
    cos10 = math.cos(math.radians(10))
    cand = np.flatnonzero(planar & (normal @ gravity_up >= math.cos(math.radians(20))))
    h = centroid[cand] @ gravity_up
    on = cand[h <= np.quantile(h, 0.25)] if len(cand) else cand
    fn, fd = gravity_up, 0.0
    for _ in range(6):
        q = np.concatenate([pts_of[i] for i in on]) if len(on) else np.zeros((0, 3))
        if len(q) < 3:
            break
        mu = q.mean(axis=0)
        fn = np.linalg.svd(q - mu, full_matrices=False)[2][2]
        fn = fn if fn @ gravity_up >= 0 else -fn
        fd = float(fn @ mu)
        on = np.flatnonzero(planar & (normal @ fn >= cos10) & (np.abs(centroid @ fn - fd) <= 0.04))
    # a block's crossings on the floor plane, and on its own plane (within 2 voxels)
    on_floor = np.array([np.mean(np.abs(p @ fn - fd) <= 2 * vs) if len(p) else 0.0 for p in pts_of])
    on_own = np.array([np.mean(np.abs((p - m) @ n) <= 2 * vs) if len(p) >= 3 else 0.0
                       for p, n, m in zip(pts_of, normal, centroid)])
    enough = npts >= 64
    # a fused real floor is not one exact plane (pose drift bends it by a voxel or two across the room): a block
    # whose crossings lie on its own plane, parallel to the floor's (10 degrees) and within 2 voxels of it at its
    # centroid, is floor too (before: only blocks within 2 voxels of the one fitted plane, which called a block
    # lying 95 % on its own floor plane a voxel off that plane a negative)
    floor_own = (on_own >= 0.9) & (normal @ fn >= cos10) & (np.abs(centroid @ fn - fd) <= 2 * vs)
    floor = enough & ((on_floor >= 0.9) | floor_own)
    vertical = (on_own >= 0.9) & (np.abs(normal @ fn) <= math.sin(math.radians(10)))
    upward = planar & (normal @ fn >= cos10)
    # a wall of the room bounds it: at most BOUND_SHARE of the map's observed crossings lie more than BOUND_BEHIND
    # behind its block's plane (a cabinet front or an appliance side has the counter, the wall above it or the
    # floor behind it)
    every = np.concatenate([p for p in pts_of if len(p)])
    every = every[:: max(1, len(every) // 200000)]
    behind = np.array([np.mean((every - m) @ n < -BOUND_BEHIND) if v else 1.0
                       for n, m, v in zip(normal, centroid, vertical & enough)])
    bounding = vertical & enough & (behind <= BOUND_SHARE)
    # blocks with fewer crossings than a plane fit needs are left out of every truth: a surface near a face, or
    # seen in part (fused maps observe a thin band), cannot be labelled from the lossless map
    return {"floor": floor, "floor_sliver": ~enough, "wall": bounding, "wall_sliver": ~enough | (vertical & ~bounding),
            "vertical": vertical & enough, "vertical_sliver": ~enough,
            "ceiling": np.zeros(len(coords), bool), "ceiling_sliver": ~enough,
            "upward": upward, "floor_normal": fn, "floor_d": fd,
            "floor_tilt_deg": float(np.degrees(np.arccos(min(1.0, fn @ gravity_up))))}


def _observed_surface(m: sdfcodec.Map, room: LabelledRoom, coords: np.ndarray) -> np.ndarray:
    """Per block, how many voxels within one voxel of the exact surface the fused map observed."""
    pad = [(0, (-n) % 16) for n in room.volume.shape]
    vol = np.pad(room.volume, pad, constant_values=room.truncation[1])
    out = np.zeros(len(coords), np.int64)
    obs = m.read_observed(coords)
    for i, c in enumerate(coords):
        b = vol[tuple(slice(16 * a, 16 * a + 16) for a in c)]
        out[i] = int(((np.abs(b) <= room.voxel_size) & obs[i]).sum())
    return out


def _pr(selected: np.ndarray, pos: np.ndarray) -> tuple[int, int, int]:
    return int((selected & pos).sum()), int(selected.sum()), int(pos.sum())


def _new_row() -> dict:
    return {"tp": 0, "selected": 0, "positives": 0, "blocks": 0, "maps": 0, "thresholds": [], "behind": set()}


def _count(tally: dict, key: tuple, res, selected: np.ndarray, pos: np.ndarray) -> None:
    """Add one map's precision/recall counts (its blocks ``selected`` against the truth ``pos``, both over the
    blocks counted) and the search's threshold and context to the row ``key`` of ``tally``."""
    tp, ns, npos = _pr(selected, pos)
    t = tally.setdefault(key, _new_row())
    for k, v in (("tp", tp), ("selected", ns), ("positives", npos), ("blocks", len(pos)), ("maps", 1)):
        t[k] += v
    t["thresholds"].append(round(float(res.threshold), 2))
    t["behind"].add(res.stats["context"]["behind"])


def _search(m: sdfcodec.Map, q: str, scene: bool = True):
    # the CLI's defaults (scene=False: --shape-only, the code-space score alone)
    res = search(m, q, threshold="auto", keep_scores=True, device="cpu", scene=scene)
    sel = np.zeros(len(res.all_coords), bool)
    key = {tuple(c): i for i, c in enumerate(res.all_coords.tolist())}
    for c in res.coords.tolist():
        sel[key[tuple(c)]] = True
    return res, sel


def _tally(kinds: list, seeds: list, target_bytes: float | None = None) -> dict:
    """Pooled counts per (room kind, query row) over the maps of ``kinds`` made from ``seeds``: pca-64, or with
    ``target_bytes`` variable-rate maps of that many bytes per coded block (pca-128 prefixes, pinned mask)."""
    codec, kw = pretrained_codec("pca", 64), {}
    if target_bytes is not None:
        codec = pretrained_codec("pca", 128)
        kw = {"codec_state": "reference", "variable_rate": {"target_bytes": float(target_bytes)}}
    tally: dict = {}
    labels_of: dict = {}
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        for kind in kinds:
            items = []
            if kind == "kitchen":
                kdir = _kitchen_dir()
                if kdir is None or not kdir.is_dir():
                    print("no kitchen data (--kitchen DIR or $SDFCODEC_KITCHEN); skipped", file=sys.stderr)
                    continue
                from sdfcodec.fusion.tsdf import fuse
                fused = fuse(kdir, voxel_size=0.02, truncation=(-0.04, 0.1), quiet=True)
                rawp = tmp / "kitchen-raw.sdfz"
                with sdfcodec.create_map(rawp, codec=sdfcodec.get_codec("raw"), voxel_size=0.02,
                                         origin=tuple(fused.origin), up=fused.up, tool="sdfcodec fuse") as w:
                    w.write_blocks(fused.coords, fused.tsdf, weights=fused.weights)
                raw = sdfcodec.open_map(rawp)
                p64 = tmp / "kitchen-pca64.sdfz"
                with sdfcodec.create_map(p64, codec=codec, voxel_size=0.02, origin=raw.origin,
                                         tool="sdfcodec encode", **kw) as w:
                    w.write_map(raw)
                items.append((sdfcodec.open_map(p64), None, raw))
            for seed in seeds:
                path = tmp / f"{kind}-{seed}.sdfz"
                if kind == "exact":
                    for g in ("poor", "normal", "rich"):
                        room = synthetic_room(seed, geometry=g, behind="solid")
                        items.append((_write(tmp / f"{kind}-{seed}-{g}.sdfz", room, codec, **kw), room, None))
                elif kind == "exact-open":
                    room = open_room(seed)
                    items.append((_write(path, room, codec, **kw), room, None))
                elif kind == "exact-tilted":
                    room = synthetic_room(seed, geometry=("normal", "rich")[seed % 2], behind="solid", tilt_deg=10)
                    items.append((_write(path, room, codec, **kw), room, None))
                elif kind in ("fused-style", "fused-style-tilted"):
                    # exact distances in a band, unobserved (d_max) beyond it, written as a plain volume: the map
                    # records neither weights nor up, so what is behind surfaces and up are found from its blocks
                    tilt = 10.0 if kind.endswith("tilted") else 0.0
                    for g in (("poor", "normal", "rich") if not tilt else (("normal", "rich")[seed % 2],)):
                        room = synthetic_room(seed, geometry=g, behind="unobserved", tilt_deg=tilt)
                        items.append((_write(tmp / f"{kind}-{seed}-{g}.sdfz", room, codec, **kw), room, None))
                elif kind in ("fused", "fused-tilted"):
                    m, room = fused_room(seed, 10.0 if kind == "fused-tilted" else 0.0, path, codec, **kw)
                    items.append((m, room, None))
            runs = [(it, q, sc) for it in items for q in QUERIES for sc in (True, False)]
            if kind in ("exact", "exact-tilted", "fused-style"):  # truths from the primitives' structure (no scene stage)
                runs += [(it, q, True) for it in items for q in PARTS]
            for (m, room, raw), q, scene in runs:
                    if kind == "exact-open" and q != "floor":
                        continue
                    res, sel = _search(m, q, scene)
                    qn = q
                    q = q if scene else f"{q} [shape only]"
                    if room is not None:
                        if id(room) not in labels_of:  # the same coords for every query of a map
                            labels_of[id(room)] = room.block_labels(res.all_coords)
                        lab = labels_of[id(room)]
                        pos, neg = TRUTH[qn](lab)
                        counted = pos | neg
                        # the pure truth: mixed blocks left out of both counts
                        if f"{qn}-pure" in TRUTH:
                            p_pos, p_neg = TRUTH[f"{qn}-pure"](lab)
                            keep = p_pos | p_neg
                            _count(tally, (kind, f"{q} (pure)"), res, sel[keep], p_pos[keep])
                        if kind.startswith("fused"):
                            # fused maps: clean blocks of which fusion observed too little surface to judge
                            # (fewer than 64 observed surface voxels, e.g. the block under a floor that passes
                            # at its top face) are left out
                            seen = _observed_surface(m, room, res.all_coords) >= 64
                            keep = (seen | ~pos) & counted
                            _count(tally, (kind, f"{q} (observed)"), res, sel[keep], pos[keep])
                    else:
                        if id(raw) not in labels_of:
                            labels_of[id(raw)] = kitchen_labels(raw, res.all_coords, np.asarray(m.header.up))
                        lab = labels_of[id(raw)]
                        pos = lab[qn]
                        counted = ~lab.get(f"{qn}_sliver", np.zeros(len(pos), bool))
                        if qn == "floor":  # also: every up-facing plane (floor and furniture tops alike)
                            _count(tally, ("kitchen (floor + tops)", q), res, sel, lab["upward"])
                        if qn == "wall":  # also: the previous truth, every vertical planar block (cabinet fronts too)
                            vc = ~lab["vertical_sliver"]
                            _count(tally, ("kitchen (vertical planes)", q), res, sel[vc], lab["vertical"][vc])
                    _count(tally, (kind, q), res, sel[counted], pos[counted])
            print(f"{kind} {seeds} done ({time.perf_counter() - t0:.0f} s)", file=sys.stderr, flush=True)
    return tally


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", type=int, nargs="+", default=[7501, 7502, 7503])
    ap.add_argument("--kinds", nargs="+", default=["exact", "exact-open", "exact-tilted", "fused-style",
                                                     "fused-style-tilted", "fused", "fused-tilted", "kitchen"])
    ap.add_argument("--kitchen", type=Path, default=None,
                    help="a 7-Scenes redkitchen sequence folder (default: $SDFCODEC_KITCHEN); without one the kitchen "
                         "rows are skipped")
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--jobs", type=int, default=1, help="processes (one task per kind and seed)")
    ap.add_argument("--target-bytes", type=float, default=None,
                    help="search variable-rate maps of B bytes per coded block (pinned mask) instead of pca-64")
    args = ap.parse_args(argv)
    if args.kitchen is not None:  # the worker processes read it from the environment
        os.environ["SDFCODEC_KITCHEN"] = str(args.kitchen)
    t0, load_before = time.perf_counter(), os.getloadavg()
    # one task per kind and seed (the kitchen once), run in --jobs processes; counts are pooled afterwards
    tasks = [([k], [sd], args.target_bytes) for k in args.kinds if k != "kitchen" for sd in args.seeds]
    tasks += [(["kitchen"], [], args.target_bytes)] if "kitchen" in args.kinds else []
    if args.jobs > 1:
        import multiprocessing as mp

        with mp.get_context("spawn").Pool(args.jobs) as pool:
            parts = pool.starmap(_tally, tasks)
    else:
        parts = [_tally(*t) for t in tasks]
    tally: dict = {}
    for kind in args.kinds:  # rows in the order of the kinds
        for part in parts:
            for (k, q), t in part.items():
                if k.split(" (")[0] != kind:
                    continue
                acc = tally.setdefault((k, q), _new_row())
                for f in ("tp", "selected", "positives", "blocks", "maps"):
                    acc[f] += t[f]
                acc["thresholds"] += t["thresholds"]
                acc["behind"] |= t["behind"]
    rows = []
    print("| rooms | query | maps | blocks | positives | selected | precision | recall | behind | thresholds |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for (kind, q), t in tally.items():
        p = t["tp"] / t["selected"] if t["selected"] else float("nan")
        r = t["tp"] / t["positives"] if t["positives"] else float("nan")
        rows.append({"kind": kind, "query": q, **{k: v for k, v in t.items() if k != "behind"},
                     "behind": sorted(t["behind"]), "precision": p, "recall": r})
        print(f"| {kind} | {q} | {t['maps']} | {t['blocks']} | {t['positives']} | {t['selected']} | {p:.3f} | {r:.3f} | "
              f"{', '.join(sorted(t['behind']))} | {min(t['thresholds']):.1f}-{max(t['thresholds']):.1f} |")
    if args.out:
        from datetime import datetime, timezone

        from sdfcodec.bench.harness import machine

        # the command as run, without --out, the kitchen's folder named DIR (a path on the measuring machine)
        words, skip = [], False
        for a in argv if argv is not None else sys.argv[1:]:
            if skip or a.startswith("--out"):
                skip = a == "--out"
                continue
            words.append("DIR" if args.kitchen is not None and a == str(args.kitchen) else a)
        doc = {"seeds": args.seeds, "kinds": args.kinds, "target_bytes": args.target_bytes,
               "command": " ".join(["python docs/search/evaluate.py", *words]), "machine": machine(),
               "date": datetime.now(timezone.utc).strftime("%Y-%m-%d"), "load_before": load_before,
               "load_after": os.getloadavg(), "rows": rows, "seconds": time.perf_counter() - t0}
        args.out.write_text(json.dumps(doc, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
