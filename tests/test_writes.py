"""Writes that fail in the file system (issue 21 item 1): disk full, no permission, file too large, I/O
errors while creating, replacing, transcoding or updating a map, and in the CLI's file outputs.

Each must end in a :class:`sdfcodec.errors.WriteFailedError` (an ``SDFCodecError`` and an ``OSError``) that
names the path and what to do, with the previous map byte- and decode-identical and no hidden temporary left.

Real failures where this machine allows them without privileges we lack:
* ENOSPC: a 1 MiB tmpfs mounted in a private user and mount namespace (``unshare -rm``);
* EACCES: a directory of mode 0555. The tests run as root, whom chmod does not stop, so the child runs as
  uid 1000 in a user namespace without capabilities (``unshare --user --map-user=1000``);
* EFBIG: ``RLIMIT_FSIZE`` set in a child process.
Those children are tests/reliability_worker.py ``faults ...``. Fault injection covers the rest: every data
write of a small map (the lowest-level file write, in ``sdfcodec.core._atomic``) and every file-system step
(mkdir, link, rename, replace, the exchange) failing in turn with ENOSPC, EACCES and EIO.
"""

from __future__ import annotations

import errno
import json
import os
import resource
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import pytest

import sdfcodec
from sdfcodec.core import _atomic
from sdfcodec import errors
from sdfcodec.map import writer as writer_mod
from sdfcodec.testing import analytic_blocks
from sdfcodec.map.verify import verify_map

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(HERE))
import reliability_worker as rw  # noqa: E402

VS, TRUNC = 0.02, (-0.04, 0.1)
CASES = ("update_map", "transcode", "create_map", "cli_encode", "cli_decode", "cli_mesh")


def _env() -> dict:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), str(ROOT / "plugins"), env.get("PYTHONPATH", "")])
    return env


def _results(proc: subprocess.CompletedProcess) -> dict:
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("RESULTS ")]
    assert proc.returncode == 0 and lines, proc.stdout[-2000:] + proc.stderr[-3000:]
    return json.loads(lines[-1][len("RESULTS "):])


def _check_cases(res: dict, d: Path, err: int, text: str) -> None:
    """Every case failed cleanly: a WriteFailedError (or, in the CLI, one error line and exit status 1) that
    names the path and says what to do; the old map is untouched; nothing hidden and no output left."""
    assert sorted(res) == sorted(CASES)
    for name, r in res.items():
        assert r["map_unchanged"] and r["decodes_identically"], (name, r)
        assert r["hidden_left"] == [], (name, r)
        if name.startswith("cli_"):
            lines = [ln for ln in r["stderr"].splitlines() if ln.strip()]
            assert r["exit_code"] == 1 and len(lines) == 1 and "Traceback" not in r["stderr"], (name, r)
            assert lines[0].startswith("error: could not finish") and str(d) in lines[0], (name, r)
            assert not r["output_exists"], (name, r)
            if name != "cli_mesh":  # open3d says only that it failed: the message asks whether the disk is full
                assert text in lines[0], (name, r)
        else:
            assert r["type"] == "WriteFailedError" and r["sdfcodec_error"] and r["errno"] == err, (name, r)
            assert str(d) in r["message"] and "What to do" in r["message"] and text in r["message"], (name, r)
    assert res["create_map"]["new_map_exists"] is False


def _world_readable_tmp() -> Path:
    d = Path(tempfile.mkdtemp(prefix="sdfcodec-writes-"))
    d.chmod(0o755)
    return d


def test_disk_full_for_real():
    """ENOSPC from a real, full file system: a 1 MiB tmpfs holding a ~600 KiB map."""
    if shutil.which("unshare") is None:
        pytest.skip("no unshare(1) here to mount a small tmpfs")
    d = _world_readable_tmp()
    try:
        probe = subprocess.run(["unshare", "-rm", "sh", "-c", f"mount -t tmpfs -o size=1m tmpfs {d}"],
                               capture_output=True, text=True)
        if probe.returncode != 0:
            pytest.skip(f"cannot mount a tmpfs in a user namespace here: {probe.stderr.strip()}")
        proc = subprocess.run(["unshare", "-rm", "sh", "-c", 'mount -t tmpfs -o size=1m tmpfs "$0" && exec "$1" '
                               '"$2" faults enospc "$0"', str(d), sys.executable, str(HERE / "reliability_worker.py")],
                              capture_output=True, text=True, env=_env(), timeout=300)
        _check_cases(_results(proc), d, errno.ENOSPC, "No space left on device")
    finally:
        shutil.rmtree(d, ignore_errors=True)


def test_read_only_directory_for_real():
    """EACCES from a real directory of mode 0555 holding the map (as uid 1000, without capabilities)."""
    d = _world_readable_tmp()
    cmd = [sys.executable, str(HERE / "reliability_worker.py"), "faults", "existing", str(d)]
    if os.geteuid() == 0:
        if shutil.which("unshare") is None:
            pytest.skip("running as root without unshare(1): chmod cannot refuse root a write")
        cmd = ["unshare", "--user", "--map-user=1000", "--map-group=1000"] + cmd
    try:
        rw.noise_map(d / "a.sdfz", 6)
        d.chmod(0o555)
        proc = subprocess.run(cmd, capture_output=True, text=True, env=_env(), timeout=300)
        if os.geteuid() == 0 and "RESULTS" not in proc.stdout and "unshare" in proc.stderr:
            pytest.skip(f"no user namespaces here: {proc.stderr.strip()[:200]}")
        _check_cases(_results(proc), d, errno.EACCES, "Permission denied")
    finally:
        d.chmod(0o755)
        shutil.rmtree(d, ignore_errors=True)


def test_file_size_limit_for_real(tmp_path):
    """EFBIG from RLIMIT_FSIZE (20 kB) in the child: every chunk of two or more noise blocks passes it."""
    rw.noise_map(tmp_path / "a.sdfz", 6)  # written before the limit (its chunks of 4 blocks pass it)

    def limit() -> None:
        resource.setrlimit(resource.RLIMIT_FSIZE, (20_000, resource.getrlimit(resource.RLIMIT_FSIZE)[1]))

    proc = subprocess.run([sys.executable, str(HERE / "reliability_worker.py"), "faults", "existing", str(tmp_path)],
                          capture_output=True, text=True, env=_env(), timeout=300, preexec_fn=limit)
    _check_cases(_results(proc), tmp_path, errno.EFBIG, "File too large")
    assert "ulimit -f" in _results(proc)["update_map"]["message"]


# -- fault injection: each write and each file-system step of a small map, failing in turn ------------------

class _Failing:
    """A file whose ``write`` writes half of the data, then fails (disk full half-way through a chunk)."""

    def __init__(self, f, err: int):
        self.f, self.err = f, err

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.f.close()

    def write(self, data) -> int:
        mv = memoryview(data).cast("B")
        self.f.write(mv[: len(mv) // 2])
        self.f.flush()
        raise OSError(self.err, os.strerror(self.err), self.f.name)


class Faults:
    """Counts the data writes (``open`` in sdfcodec.core._atomic) or the file-system steps (``os`` functions in
    sdfcodec.core._atomic and the map writer, and the exchange) and makes the ``n``-th fail with ``err``."""

    STEPS = ("mkdir", "link", "rename", "replace")

    def __init__(self, monkeypatch, kind: str, n: int | None = None, err: int = errno.ENOSPC):
        self.kind, self.n, self.err, self.count = kind, n, err, 0
        self.names: list[str] = []  # the steps, in order
        if kind == "write":
            monkeypatch.setattr(_atomic, "open", self._open, raising=False)
        else:
            proxy = _OsProxy(self)
            monkeypatch.setattr(_atomic, "os", proxy)
            monkeypatch.setattr(writer_mod, "os", proxy)
            orig = _atomic._exchange
            monkeypatch.setattr(_atomic, "_exchange", lambda *a: self._step(orig, *a, name="exchange"))

    def _hit(self) -> bool:
        self.count += 1
        return self.n is not None and self.count == self.n

    def _open(self, path, mode="r", *a, **k):
        f = open(path, mode, *a, **k)
        if "w" in mode or "x" in mode:
            if self._hit():
                return _Failing(f, self.err)
        return f

    def _step(self, fn, *a, name: str = "", **k):
        self.names.append(name or fn.__name__)
        if self._hit():
            raise OSError(self.err, os.strerror(self.err), str(a[0]) if a else None)
        return fn(*a, **k)


class _OsProxy:
    def __init__(self, faults: Faults):
        self._faults = faults

    def __getattr__(self, name):
        fn = getattr(os, name)
        if name in Faults.STEPS:
            return lambda *a, **k: self._faults._step(fn, *a, **k)
        return fn


@pytest.fixture(scope="module")
def pca8():
    return sdfcodec.get_codec("pca", code_size=8).fit(analytic_blocks(100, seed=5))


def _blocks(n: int, seed: int) -> np.ndarray:
    return (analytic_blocks(n, seed=seed) * (TRUNC[1] - TRUNC[0]) + TRUNC[0]).astype(np.float32)


def _make(path: Path, codec, seed: int) -> None:
    with sdfcodec.create_map(path, codec=codec, voxel_size=VS, truncation=TRUNC, chunk_blocks=2) as m:
        m.write_blocks([[0, 0, 0], [1, 0, 0], [2, 1, 0], [0, 2, 1]], _blocks(4, seed))
        m.mark_empty([[1, 1, 1]])


def _op(name: str, d: Path, codec) -> Path:
    """Run one kind of write in ``d`` (maps a.sdfz, b.sdfz exist); returns the path it writes."""
    a, b = d / "a.sdfz", d / "b.sdfz"
    if name == "create":
        target = d / "new.sdfz"
        with sdfcodec.create_map(target, codec=codec, voxel_size=VS, truncation=TRUNC, chunk_blocks=2) as m:
            m.write_blocks([[0, 0, 0], [3, 0, 0]], _blocks(2, 7))
        return target
    if name == "overwrite":
        with sdfcodec.create_map(a, codec=codec, voxel_size=VS, truncation=TRUNC, overwrite=True,
                                 code_dtype="int8") as m:
            m.write_blocks([[0, 0, 0]], _blocks(1, 8))
        return a
    if name == "update":
        with sdfcodec.update_map(a, wait=1) as m:
            m.write_blocks([[0, 0, 0], [4, 0, 0]], _blocks(2, 9))
            m.mark_empty([[2, 2, 2]])
        return a
    if name == "transcode":  # b in another layout from a (the CLI's encode MAP OUT --overwrite)
        with sdfcodec.open_map(a) as src, sdfcodec.create_map(
                b, codec=src.codec, voxel_size=src.voxel_size, truncation=src.truncation, overwrite=True,
                code_dtype="float16", chunk_blocks=4) as m:
            m.mark_empty(np.argwhere(src.block_states() == 1))
            for coords, blocks in src.iter_blocks():
                m.write_blocks(coords, np.clip(blocks, *TRUNC))
        return b
    raise ValueError(name)


def _snap(p: Path) -> tuple[dict, np.ndarray]:
    return rw.snapshot(p)


ALL_OPS = ("create", "overwrite", "update", "transcode")


def _inject(monkeypatch, tmp_path, codec, kind: str, all_errnos: bool, ops: tuple = ALL_OPS) -> dict:
    """For each op and each n up to its count of writes (or steps): fail the n-th and check the outcome. It
    must be a WriteFailedError with both maps untouched, or (where the code has a way around the failure: a
    copy where a hard link fails, a replaced version left for the garbage collection when renaming it away
    fails after the swap) the complete new version; in both cases nothing hidden is left."""
    d = tmp_path / "maps"
    d.mkdir()
    _make(d / "a.sdfz", codec, 1)
    _make(d / "b.sdfz", codec, 2)
    before = {p: _snap(d / p) for p in ("a.sdfz", "b.sdfz")}
    pristine = tmp_path / "pristine"
    shutil.copytree(d, pristine)
    errnos = (errno.ENOSPC, errno.EACCES, errno.EIO)
    stats = {"cases": 0, "failed_cleanly": 0, "worked_around": 0}
    for op in ops:
        scratch = tmp_path / f"count-{op}"
        shutil.copytree(d, scratch)
        with monkeypatch.context() as mp:
            counter = Faults(mp, kind)
            expected = _snap(_op(op, scratch, codec))[1]  # the new version, written without faults
        total = counter.count
        assert total >= 3, (op, kind, total)
        stats[op] = total
        target = d / {"create": "new.sdfz", "transcode": "b.sdfz"}.get(op, "a.sdfz")
        for n in range(1, total + 1):
            for err in (errnos if all_errnos else (errnos[n % 3],)):
                stats["cases"] += 1
                try:
                    with monkeypatch.context() as mp:
                        Faults(mp, kind, n, err)
                        _op(op, d, codec)
                except errors.WriteFailedError as e:
                    assert isinstance(e, errors.SDFCodecError) and isinstance(e, OSError) and e.errno == err
                    assert str(target) in str(e) and "What to do" in str(e) and os.strerror(err) in str(e), str(e)
                    assert ("nothing was written there" if op == "create" else "previous map there is unchanged"
                            ) in str(e), str(e)
                    assert sorted(os.listdir(d)) == ["a.sdfz", "b.sdfz"], (op, n, err, os.listdir(d))
                    # byte for byte the map it was (so it decodes as it did: `before` holds that decode, once)
                    for p, (files, _vol) in before.items():
                        assert rw.files_of(d / p) == files, (op, n, err, p)
                    stats["failed_cleanly"] += 1
                    continue
                assert np.array_equal(_snap(target)[1], expected), (op, n, err, counter.names[n - 1])
                assert verify_map(target).ok
                assert not [x for x in os.listdir(d) if x.startswith(".")], (op, n, os.listdir(d))
                stats["worked_around"] += 1
                shutil.rmtree(d)
                shutil.copytree(pristine, d)
    # and with nothing failing, every op still works here (no lock or temporary was left to trip it)
    for op in ("update", "transcode", "overwrite", "create"):
        _op(op, d, codec)
    assert sdfcodec.open_map(d / "a.sdfz").count_states()["coded"] == 1
    assert not [n for n in os.listdir(d) if n.startswith(".")]
    return stats


@pytest.mark.parametrize("kind", ["write", "step"])
def test_every_write_failing_in_turn(monkeypatch, tmp_path, pca8, kind):
    # the step variant on the two commit paths (create: a rename into place; update: the exchange and the
    # hard-linked copy) here; all four kinds of write, with every errno at every step, in the slow variant
    ops = ALL_OPS if kind == "write" else ("create", "update")
    stats = _inject(monkeypatch, tmp_path, pca8, kind, all_errnos=False, ops=ops)
    print(f"fault injection ({kind}):", stats)
    assert stats["cases"] >= 50 and stats["failed_cleanly"] >= 30


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["write", "step"])
def test_every_write_failing_in_turn_every_errno(monkeypatch, tmp_path, pca8, kind):
    stats = _inject(monkeypatch, tmp_path, pca8, kind, all_errnos=True)
    print(f"fault injection, every errno ({kind}):", stats)


def test_failed_writer_takes_no_more_writes(tmp_path, pca8, monkeypatch):
    """After a refused write the writer has aborted itself: a further write or commit is a clear error, and
    leaving the with block (abort) is harmless."""
    _make(tmp_path / "a.sdfz", pca8, 1)
    before = _snap(tmp_path / "a.sdfz")
    m = sdfcodec.update_map(tmp_path / "a.sdfz")
    with monkeypatch.context() as mp:
        Faults(mp, "write", 1, errno.EIO)
        with pytest.raises(errors.WriteFailedError, match="Input/output error.*check the disk"):
            m.write_blocks([[0, 0, 0]], _blocks(1, 3))
    with pytest.raises(errors.InvalidValueError, match="aborted after a failed write"):
        m.write_blocks([[0, 0, 0]], _blocks(1, 3))
    with pytest.raises(errors.InvalidValueError, match="aborted"):
        m.commit()
    m.abort()
    assert _snap(tmp_path / "a.sdfz")[0] == before[0]
    with sdfcodec.update_map(tmp_path / "a.sdfz", wait=0.5) as m2:  # the update lock was released
        m2.mark_empty([[3, 3, 3]])
    assert [n for n in os.listdir(tmp_path) if n.startswith(".")] == []


def test_temporary_directory_stays_locked_while_written(tmp_path, pca8):
    """The writer's temporary directory is the one it locked from start to commit: another writer's garbage
    collection meanwhile must not take it (Zarr's mode "w" used to remove and re-make it, dropping the lock)."""
    path = tmp_path / "m.sdfz"
    m = sdfcodec.create_map(path, codec=pca8, voxel_size=VS, truncation=TRUNC)
    assert _atomic.same_dir(m.writer.tmp_fd, m.writer.tmp)
    assert _atomic.collect(path) == 0 and m.writer.tmp.is_dir()  # a second lock in this process: refused
    m.write_blocks([[0, 0, 0]], _blocks(1, 4))
    assert _atomic.collect(path) == 0
    m.commit()
    assert sdfcodec.open_map(path).count_states()["coded"] == 1
    assert [n for n in os.listdir(tmp_path) if n.startswith(".")] == []


# -- outputs that are not maps: trajectories, models, data sets, search pictures and meshes -----------------

_OTHER_OUTPUTS = r'''
import errno, json, os, sys
from pathlib import Path
import numpy as np
import sdfcodec
from sdfcodec.errors import WriteFailedError

# the fitted model and the data set's blocks come from the parent (outside the full file system): fitting here
# imported scikit-learn and torch (~6 s of the child's ~13 s) for outputs whose content the check does not need
d, map_path, fitted, blocks = Path(sys.argv[1]), sys.argv[2], sys.argv[3], sys.argv[4]
old = d / "old.txt"
from sdfcodec.core.trajectory import Trajectory, write_tum
rng = np.random.default_rng(0)
traj = Trajectory(np.arange(20000) * 0.1, rng.normal(size=(20000, 3)), np.tile([0.0, 0, 0, 1], (20000, 1)))
small = Trajectory(np.arange(3) * 0.1, np.zeros((3, 3)), np.tile([0.0, 0, 0, 1], (3, 1)))
write_tum(old, small)
before = old.read_bytes()
with open(d / "filler", "wb", buffering=0) as f:  # fill the file system to the last byte
    for piece in (bytes(1 << 16), bytes(4096), b"x"):
        try:
            while f.write(piece):
                pass
        except OSError:
            pass

def model():
    from sdfcodec.model import load_model, save_model
    save_model(load_model(fitted), d / "model.npz")

def dataset():
    from sdfcodec.core.dataset import build_dataset
    build_dataset(d / "ds", [("a", [np.load(blocks, allow_pickle=False)])], batch_size=20)

def search(mesh=True):
    from sdfcodec.view.search import search_command
    search_command(map_path, "floor", out_dir=d / "search", top=8, mesh=mesh)

cases = {"trajectory": (lambda: write_tum(d / "traj.txt", traj), d / "traj.txt"),
         "trajectory_replacing": (lambda: write_tum(old, traj), old),
         "model": (model, d / "model.npz"), "dataset": (dataset, d / "ds"),
         "search": (search, d / "search" / "expanded.ply"),
         "search_picture": (lambda: search(mesh=False), d / "search" / "search.png")}
out = {}
for name, (fn, path) in cases.items():
    try:
        fn()
        out[name] = {"type": None}
    except BaseException as e:
        out[name] = {"type": type(e).__name__, "errno": getattr(e, "errno", None), "message": str(e),
                     "sdfcodec_error": isinstance(e, sdfcodec.errors.SDFCodecError), "path": str(path)}
    out[name]["left"] = sorted(p.name for p in d.rglob("*") if p.name not in ("filler", "old.txt", "search"))
    out[name]["old_unchanged"] = old.read_bytes() == before
print("RESULTS " + json.dumps(out))
'''


def test_other_outputs_on_a_full_disk(tmp_path):
    """Library functions writing outputs other than maps, on a real full file system (a tmpfs in a private
    mount namespace, filled to the last byte): a trajectory (new, and replacing one), a model, a data set, a
    search's mesh and picture. Each is one WriteFailedError (ENOSPC) naming its file; nothing half-written or hidden is
    left, and a trajectory file it was replacing is byte-identical (before: a raw OSError, a truncated file)."""
    if shutil.which("unshare") is None:
        pytest.skip("no unshare(1) here to mount a small tmpfs")
    from sdfcodec.core.sdf import sample_volume

    map_path = tmp_path / "room.sdfz"
    vol = sample_volume(sdfcodec.testing.analytic_scene(), (48, 40, 36), VS, truncation=TRUNC)
    codec = sdfcodec.get_codec("pca", code_size=16).fit(analytic_blocks(100, seed=3))
    with sdfcodec.create_map(map_path, codec=codec, voxel_size=VS, truncation=TRUNC) as m:
        m.write_volume(vol)
    from sdfcodec.model import save_model

    fitted, blocks = save_model(codec, tmp_path / "model.npz"), tmp_path / "blocks.npy"
    np.save(blocks, analytic_blocks(60, seed=2))
    d = _world_readable_tmp()
    try:
        proc = subprocess.run(["unshare", "-rm", "sh", "-c", 'mount -t tmpfs -o size=1m tmpfs "$0" && exec "$1" -c '
                               '"$2" "$0" "$3" "$4" "$5"', str(d), sys.executable, _OTHER_OUTPUTS, str(map_path),
                               str(fitted), str(blocks)],
                              capture_output=True, text=True, env=_env(), timeout=300)
        if proc.returncode != 0 and "mount" in proc.stderr and "RESULTS" not in proc.stdout:
            pytest.skip(f"cannot mount a tmpfs in a user namespace here: {proc.stderr.strip()[:200]}")
        res = _results(proc)
    finally:
        shutil.rmtree(d, ignore_errors=True)
    assert sorted(res) == ["dataset", "model", "search", "search_picture", "trajectory", "trajectory_replacing"]
    for name, r in res.items():
        assert r["type"] == "WriteFailedError" and r["sdfcodec_error"] and r["errno"] == errno.ENOSPC, (name, r)
        assert r["path"] in r["message"] and "No space left on device" in r["message"], (name, r)
        assert "What to do" in r["message"] and "\n" not in r["message"], (name, r)
        assert r["left"] == [], (name, r)  # no output, no temporary (the data set's hidden directory neither)
        assert r["old_unchanged"], (name, r)
    assert "the file there is unchanged" in res["trajectory_replacing"]["message"]


def test_dataset_overwrite_replaces_only_a_data_set(tmp_path):
    """``build_dataset(..., overwrite=True)`` replaces a data set, never a directory of other files or a
    plain file (it used to delete whatever directory was there)."""
    from sdfcodec.core.dataset import build_dataset, open_dataset

    src = [("a", [analytic_blocks(60, seed=2)])]
    other = tmp_path / "photos"
    other.mkdir()
    (other / "keep.jpg").write_bytes(b"precious")
    plain = tmp_path / "notes.txt"
    plain.write_text("keep")
    for target in (other, plain):
        with pytest.raises(errors.MapExistsError, match="refusing to replace it"):
            build_dataset(target, src, batch_size=20, overwrite=True)
    assert (other / "keep.jpg").read_bytes() == b"precious" and plain.read_text() == "keep"
    ds = tmp_path / "ds"
    build_dataset(ds, src, batch_size=20)
    build_dataset(ds, [("b", [analytic_blocks(80, seed=4)])], batch_size=20, overwrite=True)
    assert open_dataset(ds).meta["sources"] == {"b": 80}


def test_a_write_into_an_abandoned_directory_is_dropped_quietly(tmp_path):
    """Chunk writes still in flight when an interrupt removed the map being written are moot and raise nothing
    (from Zarr's orphaned tasks they printed a traceback after the CLI's "interrupted" line); a write that fails
    while the directory is still there raises as before."""
    from zarr.core.buffer import default_buffer_prototype

    from sdfcodec.map.io.stores import CowLocalStore

    root = _atomic.hidden_path(tmp_path / "map.sdfz", "tmp")  # where a writer writes a map before its commit
    root.mkdir()
    store = CowLocalStore(root)
    value = default_buffer_prototype().buffer.from_bytes(b"chunk")
    store.set_sync("codes/c/0/0/0/0", value)
    assert (root / "codes/c/0/0/0/0").read_bytes() == b"chunk"
    (root / "codes").chmod(0o500)  # the directory is there, the write fails: an error
    try:
        if os.geteuid() != 0:  # root ignores the mode
            with pytest.raises(OSError):
                store.set_sync("codes/c/1/0/0/0", value)
    finally:
        (root / "codes").chmod(0o700)
    shutil.rmtree(root)
    store.set_sync("codes/c/2/0/0/0", value)  # abandoned: nothing raised, nothing re-created
    assert not root.exists()
