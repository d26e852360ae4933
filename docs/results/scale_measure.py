"""Measurements for docs/scale.md (run: .venv/bin/python docs/results/scale_measure.py [WORKDIR]): decode-on-read
throughput from a local store, bytes fetched over HTTP for a region, and the dask paths. Prints JSON."""
import http.server, json, os, threading, time, sys
from functools import partial
from pathlib import Path
import numpy as np, torch, sdfcodec
from sdfcodec.testing import analytic_blocks
from sdfcodec.core.sdf import Box, Cylinder, Plane, Scene, Sphere, sample_volume

out = Path(sys.argv[1] if len(sys.argv) > 1 else "/tmp/scalebench")
out.mkdir(exist_ok=True)
res = {"loadavg_start": os.getloadavg(), "cpus": os.cpu_count(), "torch_threads": torch.get_num_threads()}
rng = np.random.default_rng(0)
pca = sdfcodec.get_codec("pca", code_size=64).fit(analytic_blocks(500, seed=1))

# 1. decode on read, pca-64 float32 codes, 48^3-block grid, 75% of blocks coded, the same codes in two maps:
#    16^3 blocks per chunk (the default) and 8^3 (the earlier default; smaller remote region reads)
coords = np.argwhere(rng.random((48, 48, 48)) < 0.75)
base = pca.encode(analytic_blocks(512, seed=2))
z = base[rng.integers(0, 512, len(coords))] + rng.normal(0, 0.01, (len(coords), 64)).astype(np.float32)
maps = {}
for cb in (16, 8):
    path = maps[cb] = out / f"bench-c{cb}.sdfz"
    with sdfcodec.create_map(path, codec=pca, voxel_size=0.02, chunk_blocks=cb, overwrite=True) as w:
        w.write_codes(coords, z)
m = sdfcodec.open_map(maps[16])
_, allcodes = m.read_codes()
n = len(allcodes)
res["coded_blocks"] = n

def best(fn, reps=5):
    ts = []
    for _ in range(reps):
        t = time.perf_counter(); fn(); ts.append(time.perf_counter() - t)
    return n / min(ts), n / float(np.median(ts))

def decode_only():
    for i in range(0, n, 8192):
        pca.decode(torch.from_numpy(allcodes[i:i + 8192]))

res["decode_only_in_memory"] = best(decode_only)
for cb, path in maps.items():
    m = sdfcodec.open_map(path)
    res[f"c{cb}_iter_codes"] = best(lambda: sum(len(c) for c, _ in m.iter_codes(chunks_per_batch=16)))
    for pf in (0, 2):
        res[f"c{cb}_iter_decoded_prefetch{pf}"] = best(lambda: sum(len(c) for c, _ in m.iter_decoded(prefetch=pf)))
    res[f"c{cb}_iter_decoded_level32"] = best(lambda: sum(len(c) for c, _ in m.iter_decoded(level=32)))

# 2. the same maps over HTTP on loopback: a 32^3-voxel region and the whole map
sent = []
class H(http.server.SimpleHTTPRequestHandler):
    disable_nagle_algorithm = True  # as real servers: no 40 ms delayed-ACK stall per response
    protocol_version = "HTTP/1.1"
    def log_message(self, *a): pass
    def copyfile(self, src, dst):
        d = src.read(); dst.write(d); sent.append(len(d))
srv = http.server.ThreadingHTTPServer(("127.0.0.1", 0), partial(H, directory=str(out)))
threading.Thread(target=srv.serve_forever, daemon=True).start()
for cb, path in maps.items():
    url = f"http://127.0.0.1:{srv.server_address[1]}/{path.name}"
    total = sum(p.stat().st_size for p in path.rglob("*") if p.is_file())
    sent.clear()
    r = sdfcodec.open_map(url)
    r.decode_region(((128, 160), (128, 160), (128, 160)))
    res[f"c{cb}_http_region_bytes"], res[f"c{cb}_map_bytes"] = sum(sent), total
    res[f"c{cb}_http_iter_decoded"] = best(lambda: sum(len(c) for c, _ in r.iter_decoded()))
srv.shutdown()

# 3. dask: a 256 x 256 x 128 scene (8.4 M voxels), encode single-process vs dask, decode_region vs to_dask
vol = sample_volume(Scene([Plane((0, 0, 1), 0.3), Plane((1, 0, 0), 0.2), Sphere((2.6, 2.6, 1.2), 0.8),
                           Box((4.0, 1.5, 1.0), (0.5, 0.4, 0.7)), Cylinder((1.5, 4.0, 1.2), 0.5, 1.0)]),
                    (256, 256, 128), 0.02, truncation=(-0.04, 0.1))
np.save(out / "vol.npy", vol)
t = time.perf_counter()
with sdfcodec.create_map(out / "single.sdfz", codec=pca, voxel_size=0.02, overwrite=True) as w:
    w.write_volume(vol)
res["write_volume_single_s"] = time.perf_counter() - t
from distributed import Client, LocalCluster
from sdfcodec.map.scale import encode_volume_dask
with LocalCluster(n_workers=2, threads_per_worker=1, processes=False, dashboard_address=None) as c, Client(c):
    t = time.perf_counter()
    encode_volume_dask(out / "vol.npy", out / "dask.sdfz", pca, voxel_size=0.02, overwrite=True)
    res["encode_volume_dask_s"] = time.perf_counter() - t
    md = sdfcodec.open_map(out / "dask.sdfz")
    t = time.perf_counter(); a = md.to_dask().compute(); res["to_dask_compute_s"] = time.perf_counter() - t
t = time.perf_counter(); b = md.decode_region(); res["decode_region_s"] = time.perf_counter() - t
res["to_dask_vs_decode_region_maxdiff"] = float(np.abs(a - b).max())
res["coded_blocks_scene"] = md.count_states()["coded"]
res["loadavg_end"] = os.getloadavg()
print(json.dumps(res, indent=1))
