"""The walk-through of docs/how-to/kitchen.md, run for real: every command of the page on the 7-Scenes kitchen
(frames 0-499), its output recorded into docs/how-to/kitchen.json, from which the page quotes
(tests/test_docs_kitchen.py checks every quoted line against that record).

Run: ``.venv/bin/python docs/how-to/kitchen_measure.py --kitchen DIR --work WORKDIR [--out docs/how-to/kitchen.json]``
(DIR: a 7-Scenes redkitchen sequence folder, default ``$SDFCODEC_KITCHEN``; WORKDIR: an empty scratch folder).
The commands run as a new user runs them, ``sdfcodec COMMAND`` one process each, in WORKDIR, with the kitchen
linked there as ``7scenes-redkitchen`` and an empty query cache (``SDFCODEC_CACHE_DIR``), so the first search is
cold; the HTTP steps read the maps through ``python -m http.server 8000`` run in WORKDIR. Each record keeps the
command, its stdout and stderr, exit status, wall and CPU seconds and the load average before it.
"""
from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import resource
import shlex
import subprocess
import sys
import time
from pathlib import Path

URL = "http://127.0.0.1:8000"

#: the page's commands, in its order (``sdfcodec`` is the command line, run as ``python -m sdfcodec``)
STEPS = [
    "sdfcodec fuse 7scenes-redkitchen kitchen.sdfz",
    "sdfcodec info kitchen.sdfz",
    "sdfcodec encode kitchen.sdfz kitchen-pca.sdfz",
    "sdfcodec encode kitchen.sdfz kitchen-pca32.sdfz --code-size 32",
    "sdfcodec encode kitchen.sdfz kitchen-128.sdfz --target-bytes 128",
    "sdfcodec encode kitchen.sdfz kitchen-sz3.sdfz --codec sz3",
    "sdfcodec encode kitchen.sdfz kitchen-sz3-1cm.sdfz --codec sz3 --max-error 0.01",
    "sdfcodec info kitchen-pca.sdfz",
    "sdfcodec info kitchen-128.sdfz",
    "sdfcodec info kitchen-sz3-1cm.sdfz",
    "sdfcodec compare kitchen.sdfz kitchen-pca.sdfz",
    "sdfcodec compare kitchen.sdfz kitchen-pca.sdfz --level 32",
    "sdfcodec compare kitchen.sdfz kitchen-128.sdfz",
    "sdfcodec compare kitchen.sdfz kitchen-sz3-1cm.sdfz",
    "sdfcodec decode kitchen-pca.sdfz kitchen.npz",
    "sdfcodec decode kitchen-pca.sdfz kitchen-32.npy --level 32",
    "sdfcodec decode kitchen-pca.sdfz corner.npy --region 0:1,0:1,1:2 --units m",
    "sdfcodec mesh kitchen-pca.sdfz kitchen.ply",
    "sdfcodec search kitchen-pca.sdfz --query floor",
    "sdfcodec search kitchen-pca.sdfz --query floor",
    "sdfcodec search kitchen-pca.sdfz --query wall",
    "sdfcodec search kitchen-pca.sdfz --query wall",
    f"sdfcodec info {URL}/kitchen-pca.sdfz",
    f"sdfcodec decode {URL}/kitchen-pca.sdfz corner-http.npy --region 0:1,0:1,1:2 --units m",
    f"sdfcodec search {URL}/kitchen-pca.sdfz --query floor",
    "sdfcodec track kitchen-pca.sdfz 7scenes-redkitchen -o track.txt",
    "sdfcodec view kitchen-pca.sdfz --query floor --trajectory track.txt --groundtruth 7scenes-redkitchen -o kitchen.rrd",
]


def run(cmd: str, work: Path, env: dict) -> dict:
    args = shlex.split(cmd)
    load = os.getloadavg()[0]
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    p = subprocess.run([sys.executable, "-m", "sdfcodec", *args[1:]], cwd=work, env=env, capture_output=True,
                       text=True)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    print(f"{cmd}  ({wall:.1f} s wall, load {load:.1f})\n{p.stdout}{p.stderr}", flush=True)
    return {"command": cmd, "returncode": p.returncode, "stdout": p.stdout, "stderr": p.stderr,
            "wall_s": round(wall, 2), "cpu_s": round(cpu, 2), "load_before": round(load, 2)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--kitchen", default=os.environ.get("SDFCODEC_KITCHEN"), help="7-Scenes redkitchen folder")
    ap.add_argument("--work", required=True, type=Path, help="empty scratch folder")
    ap.add_argument("--out", type=Path, default=Path(__file__).parent / "kitchen.json")
    a = ap.parse_args()
    if not a.kitchen or not Path(a.kitchen).is_dir():
        sys.exit("error: --kitchen DIR (a 7-Scenes redkitchen sequence folder) is needed")
    a.work.mkdir(parents=True, exist_ok=True)
    if any(a.work.iterdir()):
        sys.exit(f"error: {a.work} is not empty")
    (a.work / "7scenes-redkitchen").symlink_to(Path(a.kitchen).resolve())
    # as a user's shell runs them: Python writes its bytecode (this project's machines set PYTHONDONTWRITEBYTECODE,
    # and in a clone that never wrote it every command compiled each module it imported: 0.3-0.7 s a command)
    env = {**{k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"},
           "SDFCODEC_CACHE_DIR": str(a.work / "cache"), "COLUMNS": "120"}
    server = subprocess.Popen([sys.executable, "-m", "http.server", "8000", "--bind", "127.0.0.1"], cwd=a.work,
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        time.sleep(1.0)
        records = [run(cmd, a.work, env) for cmd in STEPS]
    finally:
        server.terminate()
        server.wait()
    doc = {"what": "docs/how-to/kitchen.md, run by docs/how-to/kitchen_measure.py",
           "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
           "machine": f"{platform.machine()}, {os.cpu_count()} cores, {platform.system()} {platform.release()}",
           "python": platform.python_version(), "records": records}
    a.out.write_text(json.dumps(doc, indent=1) + "\n", encoding="utf-8")
    bad = [r["command"] for r in records if r["returncode"] != 0]
    if bad:
        sys.exit(f"error: these failed: {bad}")


if __name__ == "__main__":
    main()
