"""Rate-distortion of step-quantised (int16) codes against float32, float16 and int8 code storage on a fused map
(docs/rate-distortion.md, "Quantised codes").

    python examples/quantised_codes.py KITCHEN.sdfz [--sizes 32,64,128] [--steps ...] [--allocated]
        [--speed-tiles 16] [--out docs/quantised-codes.json]
    python examples/quantised_codes.py docs/quantised-codes.json --render     # the tables again

KITCHEN.sdfz is a lossless fused map (codec raw, with fusion weights: ``sdfcodec fuse`` of the 7-Scenes
redkitchen frames). Every point is a real map: the lossless map transcoded (``Map.write_map``, which encodes
with the observation and the surface weight) into a pca-K map with the shipped eigenshapes, then measured:

* bytes per coded block: every file of the map but its codec state (``codec/``), divided by the coded blocks
  ("all-in": codes, observation mask, block states, Zarr metadata), and the ``codes/`` files alone;
* surfaces: ``sdfcodec.core.surface.compare_volumes`` of the decoded map against the lossless one over the observed
  voxels (Chamfer-L1 in mm, F-score at 1 voxel);
* MSE: mean squared error in normalised units (1 = the truncation range) over the observed voxels of coded
  blocks; max error: largest absolute error there, in metres;
* speed: encode (the transcode, best of ``--repeat``) and decode (``decode_region``, best of ``--repeat``) in
  coded blocks per second, float32 and int16 maps timed interleaved in the same run.

``--allocated`` adds int16 points whose step per component follows the codec's explained variance (step_j =
s * (var_0 / var_j)^(1/4): coarser steps for weaker components) at the same scales ``s``.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

import sdfcodec
from sdfcodec.map.rate import stored_bytes
from sdfcodec.core.surface import compare_volumes

DEFAULT_STEPS = (0.01, 0.02, 0.04, 0.08, 0.16, 0.32, 0.64)


def observed_volume(raw: sdfcodec.Map) -> np.ndarray:
    """The lossless map's observation as a dense bool volume (unobserved blocks: False)."""
    obs = np.zeros(raw.shape_voxels, bool)
    coords = np.argwhere(raw.block_states() == 2)
    for c, o in zip(coords, raw.read_observed(coords)):
        s = tuple(slice(16 * a, 16 * a + 16) for a in c)
        sh = obs[s].shape
        obs[s] = o[:sh[0], :sh[1], :sh[2]]
    return obs


def coded_voxels(m: sdfcodec.Map) -> np.ndarray:
    mask = np.zeros(m.shape_voxels, bool)
    for c in np.argwhere(m.block_states() == 2):
        mask[tuple(slice(16 * a, 16 * a + 16) for a in c)] = True
    return mask


def write(path: Path, raw: sdfcodec.Map, codec, **kw) -> float:
    t = time.perf_counter()
    with sdfcodec.create_map(path, codec=codec, voxel_size=raw.voxel_size, truncation=raw.truncation,
                             origin=raw.origin, shape_voxels=raw.shape_voxels, overwrite=True, **kw) as m:
        m.write_map(raw)
    return time.perf_counter() - t


def measure(path: Path, orig: np.ndarray, obs: np.ndarray, region: np.ndarray, repeat: int) -> dict:
    m = sdfcodec.open_map(path)
    n = m.count_states()["coded"]
    best = np.inf
    for _ in range(repeat):
        t = time.perf_counter()
        dec = m.decode_region()
        best = min(best, time.perf_counter() - t)
    d_min, d_max = m.truncation
    sel = obs & region
    err = dec[sel] - orig[sel]
    sm = compare_volumes(orig, dec, m.voxel_size, origin=m.origin, observed=obs).to_dict()
    b = stored_bytes(path)
    return {"bytes_all_in": b["total"], "bytes_codes": b["codes"], "bytes_mask": b["mask"],
            "mse": float(np.mean((err / (d_max - d_min)) ** 2)), "max_error_m": float(np.abs(err).max()),
            "chamfer_mm": 1000 * sm["chamfer_l1"], "f1": sm["f_score_1"], "decode_blocks_per_s": n / best,
            "coded_blocks": n}


def storage_speed(kitchen: sdfcodec.Map, k: int, step: float, tiles: int, repeat: int, work: Path) -> dict:
    """Code storage alone, float32 against int16 at ``step``, timed interleaved (best of ``repeat``): writing
    already-encoded codes (``write_codes``: quantise, compress, store) and reading them back (``read_codes``:
    decompress, dequantise), on the kitchen's pca-k codes tiled ``tiles`` times along x (the codec's own encode
    and decode are the same for both storages and left out)."""
    ref = work / "speed-src.sdfz"
    codec = sdfcodec.pretrained_codec("pca", k)
    write(ref, kitchen, codec)
    coords, z = sdfcodec.open_map(ref).read_codes()
    span = coords[:, 0].max() + 1
    cc = np.concatenate([coords + [span * i, 0, 0] for i in range(tiles)])
    zz = np.concatenate([z] * tiles)
    t = {"float32": ([], []), "int16": ([], [])}
    for _ in range(repeat):
        for name, kw in (("float32", {}), ("int16", {"code_dtype": "int16", "code_step": step})):
            p = work / f"speed-{name}.sdfz"
            t0 = time.perf_counter()
            with sdfcodec.create_map(p, codec=codec, voxel_size=kitchen.voxel_size, truncation=kitchen.truncation,
                                     overwrite=True, **kw) as m:
                m.write_codes(cc, zz)
            t[name][0].append(time.perf_counter() - t0)
            m = sdfcodec.open_map(p)
            t0 = time.perf_counter()
            m.read_codes()
            t[name][1].append(time.perf_counter() - t0)
    n = len(cc)
    out = {"codec": f"pca-{k}", "step": step, "blocks": n}
    for name, (w, r) in t.items():
        out[f"{name}_write_blocks_per_s"] = n / min(w)
        out[f"{name}_read_blocks_per_s"] = n / min(r)
    out["write_int16_vs_float32"] = min(t["float32"][0]) / min(t["int16"][0])
    out["read_int16_vs_float32"] = min(t["float32"][1]) / min(t["int16"][1])
    return out


def sz3_rows(orig: np.ndarray, obs: np.ndarray, region: np.ndarray, n_coded: int, voxel_size: float,
             origin, truncation, bounds_m=(0.01, 0.02, 0.04), repeat: int = 3) -> list[dict]:
    """SZ3 (pysz, absolute error bound) on the whole dense lossless volume, for reference: bytes per coded block =
    the compressed stream / coded blocks (no mask: SZ3 codes the field itself); distortion as for the maps."""
    import pysz

    rows = []
    d_min, d_max = truncation
    vol = np.ascontiguousarray(orig, dtype=np.float32)
    for e in bounds_m:
        cfg = pysz.szConfig()
        cfg.errorBoundMode = pysz.szErrorBoundMode.ABS
        cfg.absErrorBound = e
        comp, _ = pysz.sz.compress(vol, cfg)
        best = np.inf
        for _ in range(repeat):
            t = time.perf_counter()
            dec, _ = pysz.sz.decompress(comp, np.float32, vol.shape)
            best = min(best, time.perf_counter() - t)
        dec = np.clip(dec, d_min, d_max)
        sel = obs & region
        err = dec[sel] - orig[sel]
        sm = compare_volumes(orig, dec, voxel_size, origin=origin, observed=obs).to_dict()
        rows.append({"codec": "sz3 (pysz 1.1.0)", "storage": f"abs bound {100 * e:g} cm",
                     "bytes_all_in": comp.nbytes / n_coded, "bytes_codes": comp.nbytes / n_coded, "bytes_mask": 0.0,
                     "mse": float(np.mean((err / (d_max - d_min)) ** 2)), "max_error_m": float(np.abs(err).max()),
                     "chamfer_mm": 1000 * sm["chamfer_l1"], "f1": sm["f_score_1"],
                     "decode_blocks_per_s": n_coded / best, "coded_blocks": n_coded})
    return rows


def mask_bytes(kitchen: sdfcodec.Map, rooms: list[str], work: Path) -> list[dict]:
    """Bytes per coded block of the observation mask (``observed/`` files) through the writer's mask chain
    (``mask_compressors``: Blosc zstd 5 without shuffle when the committed run was made) and through the general
    chain ``compressors()`` (zstd 3, byte shuffle), on the kitchen and on fused synthetic rooms (``.npz`` with
    ``coords``, ``tsdf`` metres, ``observed`` and ``origin``), pca-32 maps (the mask does not depend on the
    codec). Row keys ``mask_before`` (general chain) and ``mask_now`` (mask chain) are those of the JSON."""
    import sdfcodec.map.writer as writer_module
    from sdfcodec.map.format import compressors, mask_compressors

    out = []
    codec = sdfcodec.pretrained_codec("pca", 32)
    inputs = [("kitchen", None)] + [(Path(r).stem, r) for r in rooms]
    for name, src in inputs:
        row = {"input": name}
        for label, chain in (("before", compressors), ("now", mask_compressors)):
            p = work / f"mask-{label}.sdfz"
            saved = writer_module.mask_compressors
            writer_module.mask_compressors = chain
            try:
                if src is None:
                    write(p, kitchen, codec)
                else:
                    d = np.load(src)
                    with sdfcodec.create_map(p, codec=codec, voxel_size=0.02, truncation=(-0.04, 0.1),
                                             origin=tuple(d["origin"]), overwrite=True) as m:
                        m.write_blocks(d["coords"], d["tsdf"], observed=d["observed"])
            finally:
                writer_module.mask_compressors = saved
            b = stored_bytes(p)
            row[f"mask_{label}"], row["coded_blocks"] = b["mask"], sdfcodec.open_map(p).count_states()["coded"]
        out.append(row)
        print(json.dumps(row), flush=True)
    return out


def markdown(doc: dict) -> str:
    """The tables of docs/rate-distortion.md, "Quantised codes", from the JSON this script writes."""
    def ratio(r: dict, key: str) -> str:
        return "1 (ref.)" if r["storage"] == "float32" else (f"{r[key]:.2f}" if key in r else "-")

    lines = ["| codec | codes | B/block all-in | B/block codes | MSE | max error (cm) | Chamfer-L1 (mm) | F@1 | "
             "decode (blocks/s) | encode, x float32 | decode, x float32 |", "|" + "---|" * 11]
    for r in doc["rows"]:
        lines.append(f"| {r['codec']} | {r['storage']} | {r['bytes_all_in']:.1f} | {r['bytes_codes']:.1f} | "
                     f"{r['mse']:.5f} | {100 * r['max_error_m']:.1f} | {r['chamfer_mm']:.2f} | {r['f1']:.3f} | "
                     f"{r['decode_blocks_per_s']:.0f} | {ratio(r, 'encode_vs_float32_same_run')} | "
                     f"{ratio(r, 'decode_vs_float32')} |")
    if doc.get("mask"):
        lines += ["", "The observation mask's bytes per coded block through two Blosc settings (pca-32 maps; the mask "
                  "does not depend on the codec). What the writer stores today, context-coded or at zstd level 9: "
                  "[side-information.md](side-information.md).", "",
                  "| input | coded blocks | mask, zstd 3, byte shuffle | mask, zstd 5, no shuffle |",
                  "|---|---|---|---|"]
        lines += [f"| {r['input']} | {r['coded_blocks']} | {r['mask_before']:.1f} | {r['mask_now']:.1f} |"
                  for r in doc["mask"]]
    if doc.get("storage_speed"):
        lines += ["", "| codec | step | blocks | write float32 / int16 (blocks/s) | int16 / float32 | "
                  "read float32 / int16 (blocks/s) | int16 / float32 |", "|" + "---|" * 7]
        for r in doc["storage_speed"]:
            lines.append(f"| {r['codec']} | {r['step']:g} | {r['blocks']} | {r['float32_write_blocks_per_s']:.0f} / "
                         f"{r['int16_write_blocks_per_s']:.0f} | {r['write_int16_vs_float32']:.2f} | "
                         f"{r['float32_read_blocks_per_s']:.0f} / {r['int16_read_blocks_per_s']:.0f} | "
                         f"{r['read_int16_vs_float32']:.2f} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> list[dict]:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("kitchen")
    ap.add_argument("--sizes", default="32,64,128")
    ap.add_argument("--steps", default=",".join(map(str, DEFAULT_STEPS)))
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--allocated", action="store_true")
    ap.add_argument("--out", default=None)
    ap.add_argument("--speed-tiles", type=int, default=0, help="also time code storage alone (storage_speed)")
    ap.add_argument("--mask-rooms", default=None, help="comma-separated fused rooms (.npz) for the mask bytes")
    ap.add_argument("--sz3", action="store_true", help="add SZ3 rows at 1, 2 and 4 cm (needs pysz: pip install pysz==1.1.0)")
    ap.add_argument("--render", action="store_true", help="print the tables of KITCHEN (here: the JSON) and stop")
    a = ap.parse_args(argv)
    if a.render:
        print(markdown(json.loads(Path(a.kitchen).read_text())))
        return []
    raw = sdfcodec.open_map(a.kitchen)
    orig = raw.decode_region()
    obs = observed_volume(raw)
    work = Path(tempfile.mkdtemp(prefix="quantised-codes-"))
    rows: list[dict] = []
    t_all = time.perf_counter()
    speed, masks = [], []
    if a.mask_rooms is not None:
        masks = mask_bytes(raw, [r for r in a.mask_rooms.split(",") if r], work)
    if a.sz3:
        region = coded_voxels(raw)
        rows += sz3_rows(orig, obs, region, raw.count_states()["coded"], raw.voxel_size, raw.origin, raw.truncation)
        for r in rows:
            print(json.dumps(r), flush=True)
    try:
        for k in (int(s) for s in a.sizes.split(",")) if a.speed_tiles else ():
            for st in (0.04, 0.32):
                speed.append(storage_speed(raw, k, st, a.speed_tiles, max(a.repeat, 3), work))
                print(json.dumps(speed[-1]), flush=True)
        for k in (int(s) for s in a.sizes.split(",")):
            codec = sdfcodec.pretrained_codec("pca", k)
            var = np.asarray(codec.state_dict()["explained_variance"][:k], np.float64)
            region = None
            variants = [("float32", {}), ("float16", {"code_dtype": "float16"}), ("int8", {"code_dtype": "int8"})]
            variants += [(f"int16 step {s:g}", {"code_dtype": "int16", "code_step": s})
                         for s in map(float, a.steps.split(","))]
            if a.allocated:
                variants += [(f"int16 allocated {s:g}", {"code_dtype": "int16",
                                                          "code_step": s * (var[0] / var) ** 0.25})
                             for s in map(float, a.steps.split(","))]
            for name, kw in variants:
                path = work / f"pca{k}-{len(rows)}.sdfz"
                # encode timed interleaved with float32: a float32 write right before each other variant
                times, ref = [], []
                for _ in range(a.repeat if name == "float32" or name.startswith("int16 step") else 1):
                    if name != "float32":
                        ref.append(write(work / "ref.sdfz", raw, codec))
                    times.append(write(path, raw, codec, **kw))
                if region is None:
                    region = coded_voxels(sdfcodec.open_map(path))
                row = {"codec": f"pca-{k}", "storage": name, **measure(path, orig, obs, region, a.repeat)}
                n = row["coded_blocks"]
                row["encode_blocks_per_s"] = n / min(times)
                if name == "float32":
                    dec_f32 = row["decode_blocks_per_s"]
                else:
                    row["encode_vs_float32_same_run"] = min(ref) / min(times)
                    row["decode_vs_float32"] = row["decode_blocks_per_s"] / dec_f32
                rows.append(row)
                print(json.dumps({k2: (round(v, 5) if isinstance(v, float) else v) for k2, v in row.items()}),
                      flush=True)
                shutil.rmtree(path, ignore_errors=True)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    meta = {"input": os.path.abspath(a.kitchen), "wall_s": time.perf_counter() - t_all,
            "load_avg": os.getloadavg(), "cpus": os.cpu_count()}
    if a.out:
        Path(a.out).write_text(json.dumps({"meta": meta, "rows": rows, "storage_speed": speed, "mask": masks}, indent=1) + "\n")
    print(json.dumps(meta))
    print(markdown({"rows": rows, "storage_speed": speed}))
    return rows


if __name__ == "__main__":
    main()
