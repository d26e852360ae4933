"""Measure codec state embedded vs by reference (docs/codecs.md, "Codec state: embedded or by reference").

For a small map (a synthetic furnished room, exact TSDF at 2 cm) encoded with the shipped ae-64 and pca-64,
once with the state embedded and once by reference: bytes on disk, and the time to open the map and decode it
whole, each in a fresh process (cold: what a user's first ``open_map`` pays, the shipped model's loading and
hashing included) and again in the same process (warm: a second map naming the same model).

    PYTHONPATH=.:plugins python docs/state_reference_measure.py OUT_DIR [--repeat 3]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

CHILD = r"""
import json, sys, time
t0 = time.perf_counter()
import numpy as np, sdfcodec
t1 = time.perf_counter()
out = {"import_s": t1 - t0}
for k, p in enumerate(sys.argv[1:]):
    t = time.perf_counter()
    m = sdfcodec.open_map(p)
    codec = m.codec  # loads (embedded) or resolves (reference) the state
    t_open = time.perf_counter() - t
    v = m.decode_region()
    out[f"map{k}"] = {"open_s": t_open, "open_decode_s": time.perf_counter() - t, "sum": float(np.sum(v, dtype=np.float64))}
print(json.dumps(out))
"""


def du(path: Path) -> int:
    return sum(os.path.getsize(os.path.join(d, f)) for d, _, fs in os.walk(path) for f in fs)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("out", type=Path)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    import sdfcodec
    from sdfcodec.search.rooms import synthetic_room

    args.out.mkdir(parents=True, exist_ok=True)
    room = synthetic_room(0)
    vol = room.volume
    rows = []
    for cid in ("ae", "pca"):
        codec = sdfcodec.pretrained_codec(cid, 64)
        paths = {}
        for how in ("embedded", "reference"):
            p = paths[how] = args.out / f"{cid}64-{how}.sdfz"
            with sdfcodec.create_map(p, codec=codec, voxel_size=room.voxel_size, overwrite=True,
                                     codec_state=how) as m:
                m.write_volume(vol)
        a, b = (sdfcodec.open_map(paths[h]).decode_region() for h in ("embedded", "reference"))
        assert np.array_equal(a, b)
        for how, p in paths.items():
            cold, warm = [], []
            for _ in range(args.repeat):
                # the same map twice in one fresh process: cold, then warm (codec cache of the second open)
                r = subprocess.run([sys.executable, "-c", CHILD, str(p), str(p)], capture_output=True, text=True,
                                   check=True, env=os.environ)
                res = json.loads(r.stdout)
                cold.append(res["map0"])
                warm.append(res["map1"])
            info = sdfcodec.open_map(p).info()
            rows.append({"codec": f"{cid}-64", "state": how, "bytes_on_disk": du(p),
                         "codec_state_bytes": info["codec_state_bytes"], "code_bytes": info["code_bytes_on_disk"],
                         "coded_blocks": info["blocks"]["coded"],
                         "cold_open_s": min(c["open_s"] for c in cold),
                         "cold_open_decode_s": min(c["open_decode_s"] for c in cold),
                         "warm_open_decode_s": min(w["open_decode_s"] for w in warm)})
            print(json.dumps(rows[-1]))
    load = os.getloadavg()
    (args.out / "state-reference.json").write_text(json.dumps({"rows": rows, "loadavg": load,
                                                               "shape_voxels": list(vol.shape)}, indent=1))
    print("load average", load, "volume", vol.shape)


if __name__ == "__main__":
    t = time.perf_counter()
    main()
    print(f"{time.perf_counter() - t:.1f} s")
