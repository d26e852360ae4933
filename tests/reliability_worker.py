"""Helper process for tests/test_reliability.py: a small fork server that writes and reads maps on command.

It imports sdfcodec once and forks a child per job, so that a test can run (and SIGKILL) dozens of writers
and several concurrent readers without paying Python's and torch's start-up each time. The server itself
never touches zarr or torch before forking: its children start without helper threads.

Protocol: one JSON object per line on stdin, one reply per line on stdout.
  {"job": "write", "op": "update"|"create"|"transcode", "path": ..., "gen": g, "cid": c, "layout": [...],
   "kill_at_step": n|null, "out": file|null}            -> {"pid": pid}
  {"job": "read", "path": ..., "out": file, "stop": file, "deadline": t, "seed": s}   -> {"pid": pid}
  {"job": "updates", "path": ..., "gen": g, "cid": c, "count": k, "out": file}        -> {"pid": pid}
  {"job": "tiny", "path": ..., "gen": g, "out": file|null}  (gen 0 creates)           -> {"pid": pid}
  {"job": "tiny_read", "path": ..., "out": file, "stop": file, "deadline": t, "seed": s} -> {"pid": pid}
  {"job": "wait", "pid": pid}                                                         -> {"pid": pid, "status": s}
  {"job": "quit"}
``status`` is the child's exit code, or minus the signal that killed it (-9 for SIGKILL).

The maps hold constant blocks of the lossless ``raw`` codec; what a map must contain is a function of a
content id ``cid`` (:func:`content`), and each write records ``{"gen": ..., "cid": ...}`` as its provenance
tool, so a reader can tell which version it sees and check every block of it.

The ``tiny`` jobs keep updates as small and fast as they get (issue 21: readers must really see swaps): a map of
16 constant blocks in two chunks, and generation g rewrites one block, ``(g - 1) % 16`` (:func:`tiny_value`).
``tiny_read`` readers never stop at the first problem: they count reads, verifies, errors and mixed versions.

Run as ``reliability_worker.py faults KIND DIR`` it is instead the child of tests/test_writes.py that writes
maps where writes really fail (see :func:`faults_main`).
"""

from __future__ import annotations

import gc
import importlib
import json
import os
import random
import signal
import sys
import threading
import time
import traceback

import numpy as np

import sdfcodec
import sdfcodec.map  # noqa: F401
from sdfcodec.core import _atomic

VS, TRUNC = 0.02, (-0.04, 0.1)
N0, ADD, NMAX = 24, 8, 200
TOL = 2e-4  # metres; float16 codes (transcoded layouts) round constant blocks to ~1e-4 m


def coord(i: int) -> tuple[int, int, int]:
    return (i % 8, (i // 8) % 8, i // 64)


def n_coded(cid: int) -> int:
    return min(N0 + ADD * cid, NMAX)


def value(i: int, cid: int) -> float:
    """Distance (metres) filling block i in content cid: block 0 changes with every cid, the others never."""
    return -0.03 + 0.002 * (cid % 50) if i == 0 else -0.035 + 0.0005 * (i % 200)


def content(cid: int) -> tuple[dict[tuple[int, int, int], float], tuple[int, int, int]]:
    """Coded blocks -> value, and the one block marked empty (the next one to be coded)."""
    return {coord(i): value(i, cid) for i in range(n_coded(cid))}, coord(n_coded(cid))


def blocks_of(coords: list, cid: int) -> np.ndarray:
    index = {coord(i): i for i in range(NMAX + 1)}
    return np.stack([np.full((16, 16, 16), value(index[tuple(c)], cid), np.float32) for c in coords])


def tag(gen: int, cid: int) -> str:
    return json.dumps({"gen": gen, "cid": cid})


def check_content(m: sdfcodec.Map, cid: int) -> None:
    """Raise AssertionError unless the open map holds exactly content ``cid`` (states and every code)."""
    coded, empty = content(cid)
    states = m.block_states()
    got_coded = {tuple(int(v) for v in c) for c in np.argwhere(states == 2)}
    got_empty = {tuple(int(v) for v in c) for c in np.argwhere(states == 1)}
    assert got_coded == set(coded), f"cid {cid}: coded blocks differ: {sorted(got_coded ^ set(coded))[:5]}"
    assert got_empty == {empty}, f"cid {cid}: empty blocks {sorted(got_empty)[:5]} != {[empty]}"
    coords, codes = m.read_codes()
    d_min, d_max = TRUNC
    metres = codes * (d_max - d_min) + d_min  # raw codes are the normalised voxels
    for c, row in zip(coords, metres):
        want = coded[tuple(int(v) for v in c)]
        assert np.abs(row - want).max() <= TOL, f"cid {cid}: block {tuple(c)} holds {row[0]}, expected {want}"


def _install_step_kill(n: int | None, counter: list) -> None:
    """Count the file-system steps a write takes (renames, links, unlinks, mkdirs, the exchange) and SIGKILL
    this process just before step ``n``: a deterministic kill point at every step of a commit."""
    lock = threading.Lock()

    def step() -> None:
        with lock:
            counter[0] += 1
            if n is not None and counter[0] >= n:
                os.kill(os.getpid(), signal.SIGKILL)

    for name in ("rename", "replace", "link", "unlink", "mkdir", "rmdir"):
        orig = getattr(os, name)

        def wrapper(*a, __orig=orig, **k):
            step()
            return __orig(*a, **k)

        setattr(os, name, wrapper)
    orig_exchange = _atomic._exchange

    def exchange(*a, **k):
        step()
        return orig_exchange(*a, **k)

    _atomic._exchange = exchange


def write(op: str, path: str, gen: int, cid: int, layout: list) -> None:
    """Move the map at ``path`` to generation ``gen`` holding content ``cid`` in ``layout`` (dtype, chunk_blocks).

    update: cid - 1 -> cid by writing only what changed. create: cid from scratch (overwrite).
    transcode: read the map and write it again in another layout (same cid)."""
    raw = sdfcodec.get_codec("raw")
    coded, empty = content(cid)
    dtype, cb = layout
    if op == "update":
        before, _ = content(cid - 1)
        changed = [c for c in coded if c not in before] + [coord(0)]
        with sdfcodec.update_map(path, tool=tag(gen, cid)) as m:
            m.write_blocks(changed, blocks_of(changed, cid))
            m.mark_empty([empty])
    elif op == "create":
        cs = list(coded)
        with sdfcodec.create_map(path, codec=raw, voxel_size=VS, truncation=TRUNC, code_dtype=dtype, chunk_blocks=cb,
                                 overwrite=True, tool=tag(gen, cid)) as m:
            m.write_blocks(cs, blocks_of(cs, cid))
            m.mark_empty([empty])
    elif op == "transcode":
        src = sdfcodec.open_map(path)
        with sdfcodec.create_map(path, codec=src.codec, voxel_size=src.voxel_size, truncation=src.truncation,
                                 origin=src.origin, shape_voxels=src.shape_voxels, code_dtype=dtype, chunk_blocks=cb,
                                 overwrite=True, tool=tag(gen, cid)) as m:
            m.mark_empty(np.argwhere(src.block_states() == 1))
            for coords, blocks in src.iter_blocks():
                m.write_blocks(coords, np.clip(blocks, *TRUNC))
        src.close()
    else:
        raise ValueError(op)


def read_loop(path: str, stop: str, deadline: float, seed: int) -> dict:
    """Open, read and check the map over and over while a writer updates it; also hold maps across swaps."""
    rng = random.Random(seed)
    ops = held = 0
    gens = set()
    while time.time() < deadline and not os.path.exists(stop):
        with sdfcodec.open_map(path) as m:
            info = json.loads(m.header.provenance.tool)
            gens.add(info["gen"])
            # every version carries its integrity manifest, and this reader checks what it reads against it
            assert m.header.manifest is not None and m.reader.group.store.manifest is not None, "no manifest"
            pinned = m.reader.pinned_fd
            if rng.random() < 0.5:
                time.sleep(rng.uniform(0, 0.05))  # let a writer swap in a new version under this open map
            check_content(m, info["cid"])  # states, codes: all of the version opened
            dec = m.decode_region(((0, 16), (0, 16), (0, 16)))  # block (0, 0, 0): changes with every version
            assert abs(float(dec.mean()) - value(0, info["cid"])) <= 2e-4, "decoded block 0 is of another version"
            if not _atomic.same_dir(pinned, __import__("pathlib").Path(path)):
                held += 1  # the map was replaced while this one was open, and it still read its own version
            ops += 1
    return {"ops": ops, "gens": sorted(gens), "held_across_swap": held}


TINY_N, TINY_CB = 16, 2


def tiny_coord(i: int) -> tuple[int, int, int]:
    return (i % 4, (i // 4) % 2, i // 8)


def tiny_value(i: int, gen: int) -> float:
    """Metres filling block i of tiny generation ``gen``: set by the last update k <= gen that wrote it."""
    last = 0 if gen < i + 1 else gen - (gen - 1 - i) % TINY_N
    return -0.03 + 0.0011 * (last % 60)


def tiny_write(path: str, gen: int) -> None:
    """Generation 0: create the tiny map. gen > 0: update gen - 1 -> gen, one block."""
    raw = sdfcodec.get_codec("raw")
    if gen == 0:
        cs = [tiny_coord(i) for i in range(TINY_N)]
        blocks = np.stack([np.full((16, 16, 16), tiny_value(i, 0), np.float32) for i in range(TINY_N)])
        with sdfcodec.create_map(path, codec=raw, voxel_size=VS, truncation=TRUNC, chunk_blocks=TINY_CB,
                                 overwrite=True, tool=tag(0, 0)) as m:
            m.write_blocks(cs, blocks)
        return
    i = (gen - 1) % TINY_N
    with sdfcodec.update_map(path, tool=tag(gen, gen)) as m:
        m.write_blocks([tiny_coord(i)], np.full((1, 16, 16, 16), tiny_value(i, gen), np.float32))


def tiny_check(m: sdfcodec.Map, gen: int) -> list[str]:
    """What in the open map is not tiny generation ``gen`` (states, codes, and the decoded blocks)."""
    bad = [] if m.header.manifest is not None and m.reader.group.store.manifest is not None else [
        f"gen {gen}: no integrity manifest, or reads not checked against it"]
    states = m.block_states()
    want = {tiny_coord(i) for i in range(TINY_N)}
    got = {tuple(int(v) for v in c) for c in np.argwhere(states == 2)}
    if got != want or (states == 1).any():
        bad.append(f"gen {gen}: coded blocks {sorted(got ^ want)[:4]} differ")
    coords, codes = m.read_codes()
    metres = codes * (TRUNC[1] - TRUNC[0]) + TRUNC[0]
    index = {tiny_coord(i): i for i in range(TINY_N)}
    for c, row in zip(coords, metres):
        i = index.get(tuple(int(v) for v in c))
        if i is None or np.abs(row - tiny_value(i, gen)).max() > TOL:
            bad.append(f"gen {gen}: block {tuple(int(v) for v in c)} code holds {row[0]:.4f}")
    dec = m.decode_region(((0, 64), (0, 32), (0, 32)))
    for i in range(TINY_N):
        x, y, z = (16 * v for v in tiny_coord(i))
        blk = dec[x:x + 16, y:y + 16, z:z + 16]
        if np.abs(blk - tiny_value(i, gen)).max() > TOL:
            bad.append(f"gen {gen}: decoded block {tiny_coord(i)} holds {float(blk.mean()):.4f}")
    return bad


def tiny_read_loop(path: str, stop: str, deadline: float, seed: int) -> dict:
    """Open, check (codes, states, decode) and now and then verify the tiny map, over and over, holding each
    open map a random while so that updates swap under it. Counts instead of stopping at a problem."""
    from pathlib import Path

    from sdfcodec.map.verify import verify_map

    rng = random.Random(seed)
    reads = verifies = 0
    errors, mixed, held = [], [], set()
    while time.time() < deadline and not os.path.exists(stop):
        try:
            with sdfcodec.open_map(path) as m:
                gen = json.loads(m.header.provenance.tool)["gen"]
                pinned = m.reader.pinned_fd
                time.sleep(rng.uniform(0, 0.06))  # let a writer swap in a new version under this open map
                mixed += tiny_check(m, gen)  # everything read is of the version opened, after a swap too
                if not _atomic.same_dir(pinned, Path(path)):
                    held.add(gen)  # the update gen -> gen + 1 completed while this reader held gen
            reads += 1
            if rng.random() < 0.25:
                rep = verify_map(path, decode_blocks=TINY_N)
                verifies += 1
                if not rep.ok:
                    errors.append("verify: " + "; ".join(str(p) for p in rep.problems)[:300])
        except Exception as e:  # noqa: BLE001 - counted: the test requires none
            errors.append(f"{type(e).__name__}: {e}"[:300])
    return {"reads": reads, "verifies": verifies, "errors": errors[:20], "n_errors": len(errors),
            "mixed": mixed[:20], "n_mixed": len(mixed), "held_gens": sorted(held)}


def updates(path: str, gen: int, cid: int, count: int) -> dict:
    for k in range(1, count + 1):
        write("update", path, gen + k, cid + k, ["float32", 4])
        time.sleep(0.02)
    return {"updates": count}


def _child(cmd: dict) -> int:
    out = cmd.get("out")
    try:
        if cmd["job"] == "write":
            counter = [0]
            _install_step_kill(cmd.get("kill_at_step"), counter)
            write(cmd["op"], cmd["path"], cmd["gen"], cmd["cid"], cmd["layout"])
            result = {"steps": counter[0]}
        elif cmd["job"] == "read":
            result = read_loop(cmd["path"], cmd["stop"], cmd["deadline"], cmd["seed"])
        elif cmd["job"] == "updates":
            result = updates(cmd["path"], cmd["gen"], cmd["cid"], cmd["count"])
        elif cmd["job"] == "tiny":
            counter = [0]
            _install_step_kill(cmd.get("kill_at_step"), counter)
            t0 = time.perf_counter()
            tiny_write(cmd["path"], cmd["gen"])
            result = {"steps": counter[0], "seconds": time.perf_counter() - t0}
        elif cmd["job"] == "sign":  # sign the map with the Ed25519 key of seed ``seed`` (hex), killable
            from sdfcodec.map.sign import sign_map

            counter = [0]
            _install_step_kill(cmd.get("kill_at_step"), counter)
            sign_map(cmd["path"], bytes.fromhex(cmd["seed"]))
            result = {"steps": counter[0]}
        elif cmd["job"] == "tiny_read":
            result = tiny_read_loop(cmd["path"], cmd["stop"], cmd["deadline"], cmd["seed"])
        else:
            raise ValueError(cmd["job"])
        code = 0
    except BaseException:  # noqa: BLE001 - reported to the test through `out`
        result = {"error": traceback.format_exc()}
        code = 1
    if out:
        with open(out, "w") as f:
            json.dump(result, f)
    return code


# -- writes that really fail: the child of tests/test_writes.py ---------------------------------------------

def noise_blocks(n: int, seed: int) -> np.ndarray:
    """``(n, 16, 16, 16)`` float32 metres of uniform noise: incompressible, 16 KiB per block as raw codes."""
    return np.random.default_rng(seed).uniform(*TRUNC, size=(n, 16, 16, 16)).astype(np.float32)


def noise_map(path, n: int, seed: int = 0) -> None:
    """A raw map of ``n`` noise blocks in a row along x (chunks of 4 blocks)."""
    coords = [(i, 0, 0) for i in range(n)]
    with sdfcodec.create_map(path, codec=sdfcodec.get_codec("raw"), voxel_size=VS, truncation=TRUNC,
                             chunk_blocks=4) as m:
        m.write_blocks(coords, noise_blocks(n, seed))


def files_of(path) -> dict[str, bytes]:
    """Every file's bytes of the map at ``path``, by path inside it."""
    from pathlib import Path

    p = Path(path)
    return {str(f.relative_to(p)): f.read_bytes() for f in sorted(p.rglob("*")) if f.is_file()}


def snapshot(path) -> tuple[dict, np.ndarray]:
    """Every file's bytes, and the decoded volume, of the map at ``path``."""
    files = files_of(path)
    with sdfcodec.open_map(path) as m:
        return files, np.asarray(m.decode_region())


def hidden_left(directory) -> list[str]:
    return sorted(n for n in os.listdir(directory) if n.startswith("."))


def write_cases(d: str, grow_blocks: int) -> dict:
    """Try every kind of write that must fail where ``d`` has no room (or no permission) for it; ``d/a.sdfz``
    is an existing map. Returns, per case, how it ended: the error's type, errno and message, whether the
    previous map is byte- and decode-identical, and what hidden files were left in ``d``."""
    from pathlib import Path

    from typer.testing import CliRunner

    from sdfcodec.cli import app

    a = Path(d) / "a.sdfz"
    runner = CliRunner()
    before = snapshot(a)
    results = {}

    def outcome(name: str, exc: BaseException | None, extra: dict | None = None) -> None:
        files, vol = snapshot(a)
        results[name] = {"type": type(exc).__name__ if exc else None, "errno": getattr(exc, "errno", None),
                         "sdfcodec_error": isinstance(exc, sdfcodec.errors.SDFCodecError),
                         "message": str(exc) if exc else None, "map_unchanged": files == before[0],
                         "decodes_identically": bool(np.array_equal(vol, before[1])),
                         "hidden_left": hidden_left(d), **(extra or {})}

    def attempt(name: str, fn) -> None:
        try:
            fn()
            outcome(name, None)
        except Exception as e:  # noqa: BLE001 - reported
            outcome(name, e)

    def update() -> None:
        with sdfcodec.update_map(a, wait=2) as m:
            m.write_blocks([(i, 1, 0) for i in range(grow_blocks)], noise_blocks(grow_blocks, 7))

    def transcode_in_place() -> None:
        src = sdfcodec.open_map(a)
        try:
            with sdfcodec.create_map(a, codec=src.codec, voxel_size=src.voxel_size, truncation=src.truncation,
                                     code_dtype="float32", chunk_blocks=2, overwrite=True) as m:
                for coords, blocks in src.iter_blocks():
                    m.write_blocks(coords, np.clip(blocks, *TRUNC))
        finally:
            src.close()

    def create_new() -> None:
        with sdfcodec.create_map(Path(d) / "new.sdfz", codec=sdfcodec.get_codec("raw"), voxel_size=VS) as m:
            m.write_blocks([(i, 0, 0) for i in range(grow_blocks)], noise_blocks(grow_blocks, 8))

    attempt("update_map", update)
    attempt("transcode", transcode_in_place)
    attempt("create_map", create_new)
    results["create_map"]["new_map_exists"] = os.path.lexists(Path(d) / "new.sdfz")
    for name, args, out in (("cli_encode", ["encode", str(a), str(a), "--overwrite", "--codec", "raw"], None),
                            ("cli_decode", ["decode", str(a), str(Path(d) / "a.npy")], Path(d) / "a.npy"),
                            ("cli_mesh", ["mesh", str(a), str(Path(d) / "a.ply")], Path(d) / "a.ply")):
        r = runner.invoke(app, args)
        exc = r.exception if not isinstance(r.exception, SystemExit) else None
        outcome(name, exc, {"exit_code": r.exit_code, "stderr": r.stderr,
                            "output_exists": bool(out and os.path.lexists(out))})
    return results


def faults_main(kind: str, d: str) -> None:
    """``enospc``: ``d`` is an empty, small file system (a 1 MiB tmpfs): fill most of it with a map, then try
    the writes that need more room. ``existing``: ``d`` holds ``a.sdfz`` and writes fail for another reason
    (the directory is not writable by this process, a file size limit). Prints the results of
    :func:`write_cases` as JSON."""
    if kind == "enospc":
        noise_map(os.path.join(d, "a.sdfz"), 36)  # ~600 KiB of incompressible codes
        res = write_cases(d, grow_blocks=64)
    elif kind == "existing":
        res = write_cases(d, grow_blocks=8)
    else:
        raise ValueError(kind)
    print("RESULTS " + json.dumps(res))


def _preload() -> None:
    """Load, before the first fork, what every job would otherwise load again after it (~2 s a job): torch,
    zarr and the map package (`import sdfcodec` is lazy), the scipy and sklearn modules the map modules take on
    first use, and the registry's scan of the installed codecs (another 0.06 s of a job's 0.3 s). Nothing of it
    starts a thread. (The ``faults`` child of test_writes.py runs once and loads only what it uses.)"""
    import scipy.linalg  # noqa: F401
    import scipy.spatial  # noqa: F401
    import sklearn.decomposition  # noqa: F401
    import torch  # noqa: F401

    for module in ("facade", "reader", "writer", "manifest", "verify", "sign"):
        importlib.import_module(f"sdfcodec.map.{module}")
    sdfcodec.get_codec("raw")
    assert threading.active_count() == 1, "the fork server must not start threads before it forks"
    # what was loaded lives as long as every job: out of the cyclic collector's reach, so that a job's
    # collections scan only what the job made and leave the loaded modules' pages shared with the server
    # (as tests/conftest.py does for the test processes)
    gc.freeze()


def main() -> None:
    if sys.argv[1:2] == ["faults"]:
        faults_main(sys.argv[2], sys.argv[3])
        return
    _preload()
    for line in sys.stdin:
        cmd = json.loads(line)
        if cmd["job"] == "quit":
            break
        if cmd["job"] == "wait":
            pid, status = os.waitpid(cmd["pid"], 0)
            code = -os.WTERMSIG(status) if os.WIFSIGNALED(status) else os.WEXITSTATUS(status)
            reply = {"pid": pid, "status": code}
        else:
            pid = os.fork()
            if pid == 0:
                code = 1
                try:
                    code = _child(cmd)
                finally:
                    os._exit(code)
            reply = {"pid": pid}
        sys.stdout.write(json.dumps(reply) + "\n")
        sys.stdout.flush()


if __name__ == "__main__":
    main()
