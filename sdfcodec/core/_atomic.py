"""Crash-safe replacement of map directories that readers can use while it happens (spec section 9).

The protocol, for a map directory ``NAME`` (all names below are siblings of it):

* A writer builds the new version in ``.NAME.tmp-<hex>`` and holds an exclusive ``flock`` on that directory
  while it lives, so nobody collects it as garbage.
* Commit makes the new version current in one step: ``renameat2(RENAME_EXCHANGE)`` swaps it with ``NAME``
  (Linux, glibc >= 2.28); the previous version then sits at the temporary name and is renamed to
  ``.NAME.old-<hex>``. Where the exchange is not available the fallback is two renames, with a window in
  which ``NAME`` is missing (the previous version is whole at ``.NAME.old-<hex>`` during it).
* Readers open ``NAME`` as a directory file descriptor, take a shared ``flock`` on it, check that it is still
  the directory at ``NAME`` (else retry), and read every file through ``/proc/self/fd/<fd>/...``: a later
  swap cannot mix another version into what they read, because the version they hold is never deleted
  while their lock stands.
* Garbage collection (after every commit, and when the last reader of a replaced version lets go) removes
  every ``.NAME.tmp-*`` and ``.NAME.old-*`` whose exclusive ``flock`` it can take: nobody reads or writes it.
  Locks die with their process, so a killed writer or reader never keeps garbage alive.
* Writers that read, modify and write a map (updates) serialise on ``.NAME.lock`` (removed when released).

Nothing here is specific to Zarr: the store writers use on top of :func:`write_new_file` is
``sdfcodec.map.io.stores.CowLocalStore``.
"""

from __future__ import annotations

import ctypes
import errno
import fcntl
import os
import re
import shutil
import time
import uuid
from pathlib import Path

from ..errors import InvalidValueError, MapBusyError, WriteFailedError

__all__ = ["HAVE_PROC_FD", "hidden_path", "make_temp_dir", "pin_dir", "release_pin", "swap_into_place",
           "collect", "WriterLock", "write_new_file", "link_tree", "same_dir", "dir_id", "remove_tree",
           "check_output_path", "share_lock"]

#: Readers can hold a directory through ``/proc/self/fd`` (Linux). Elsewhere they read by path and must reopen
#: a map after it was replaced (documented in spec section 9).
HAVE_PROC_FD = os.path.isdir("/proc/self/fd")
_HIDDEN_RE = re.compile(r"(tmp|old)-[0-9a-f]{8,32}")
_TEMP_NAME_RE = re.compile(r"\..+\.tmp-[0-9a-f]{8,32}")
_AT_FDCWD = -100
_RENAME_EXCHANGE = 2
_renameat2_fn = None


def hidden_path(final: Path, kind: str) -> Path:
    """A fresh hidden sibling name of ``final``: ``.NAME.<kind>-<hex>`` (kind ``tmp`` or ``old``)."""
    return final.with_name(f".{final.name}.{kind}-{uuid.uuid4().hex[:16]}")


def dir_id(fd: int) -> tuple[int, int]:
    st = os.fstat(fd)
    return st.st_dev, st.st_ino


def same_dir(fd: int, path: Path) -> bool:
    """True when ``path`` names the very directory ``fd`` holds (not a replacement)."""
    try:
        st = os.stat(path)
    except OSError:
        return False
    return (st.st_dev, st.st_ino) == dir_id(fd)


def _try_lock(fd: int, op: int) -> bool | None:
    """``flock`` without blocking: True (got it), False (someone holds a conflicting lock), None (the file
    system has no flock: callers proceed without the protection, never delete on its strength)."""
    try:
        fcntl.flock(fd, op | fcntl.LOCK_NB)
        return True
    except BlockingIOError:
        return False
    except OSError as e:
        if e.errno in (errno.ENOLCK, errno.EOPNOTSUPP, errno.ENOSYS, errno.EINVAL, errno.EBADF):
            return None
        raise


def _wait_lock(fd: int, op: int, deadline: float) -> bool | None:
    delay = 0.001
    while True:
        got = _try_lock(fd, op)
        if got is not False or time.monotonic() >= deadline:
            return got
        time.sleep(delay)
        delay = min(delay * 2, 0.05)


def _open_dir(path: Path | str, *, nofollow: bool = False) -> int:
    flags = os.O_RDONLY | getattr(os, "O_DIRECTORY", 0) | getattr(os, "O_CLOEXEC", 0)
    if nofollow:
        flags |= getattr(os, "O_NOFOLLOW", 0)
    return os.open(path, flags)


def make_temp_dir(final: Path) -> tuple[Path, int]:
    """Create ``.NAME.tmp-<hex>`` beside ``final`` and lock it exclusively; returns its path and fd."""
    for _ in range(100):
        tmp = hidden_path(final, "tmp")
        try:
            os.mkdir(tmp)
        except FileExistsError:
            continue
        # another writer's garbage collection may remove it between mkdir and flock (its lock is free until
        # ours is taken): before we open it, or after; either way, retry with a new name
        try:
            fd = _open_dir(tmp)
        except FileNotFoundError:
            continue
        if _try_lock(fd, fcntl.LOCK_EX) is not False and same_dir(fd, tmp):
            return tmp, fd
        os.close(fd)
    raise OSError(f"could not create a temporary directory beside {final}")


def share_lock(fd: int) -> None:
    """Turn a writer's exclusive lock on its directory ``fd`` into a reader's shared one (one ``flock`` call: the
    lock is converted, never released in between), so that the version it wrote is held like any read one."""
    _try_lock(fd, fcntl.LOCK_SH)


def pin_dir(path: Path, timeout: float = 30.0) -> int:
    """Open the directory at ``path`` for reading and hold it (shared lock) against garbage collection.

    Raises:
        FileNotFoundError, NotADirectoryError: nothing (or a file) at ``path``.
        MapBusyError: it kept being replaced, or stayed locked, for ``timeout`` seconds.
    """
    deadline = time.monotonic() + timeout
    while True:
        fd = _open_dir(path)
        try:
            got = _wait_lock(fd, fcntl.LOCK_SH, deadline)
            # a version locked exclusively is being removed, or was current only until a swap we raced with
            if got is not False and same_dir(fd, path):
                return fd
        except BaseException:
            os.close(fd)
            raise
        os.close(fd)
        if time.monotonic() >= deadline:
            raise MapBusyError(f"{path} kept changing or stayed locked for {timeout:.0f} s; try again")


def release_pin(fd: int, final: Path, owner_pid: int) -> None:
    """Let go of a pinned version; when it was replaced meanwhile and this was its last reader, remove it now
    (rather than at the next commit), and with it whatever else nobody holds (:func:`collect`: a writer
    killed after the swap left its own leftovers, which no commit may come to collect). Never raises: it runs
    from finalizers."""
    try:
        # a forked child shares the lock with its parent: only the process that took it may clean up
        if os.getpid() == owner_pid and not same_dir(fd, final) and _try_lock(fd, fcntl.LOCK_EX) is True:
            ident = dir_id(fd)
            for entry in _hidden_entries(final):
                try:
                    st = entry.stat(follow_symlinks=False)
                except OSError:
                    continue
                if (st.st_dev, st.st_ino) == ident:
                    shutil.rmtree(entry.path, ignore_errors=True)
                    break
            collect(final)
    except Exception:  # noqa: BLE001 - best effort; the next commit collects what is left
        pass
    finally:
        try:
            os.close(fd)
        except OSError:
            pass


def _renameat2():
    global _renameat2_fn
    if _renameat2_fn is None:
        try:
            fn = ctypes.CDLL(None, use_errno=True).renameat2
            fn.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
            fn.restype = ctypes.c_int
            _renameat2_fn = fn
        except (AttributeError, OSError):
            _renameat2_fn = False
    return _renameat2_fn or None


def _exchange(a: Path, b: Path) -> bool:
    """Swap the directory entries ``a`` and ``b`` atomically; False when the platform cannot."""
    fn = _renameat2()
    if fn is None:
        return False
    if fn(_AT_FDCWD, os.fsencode(a), _AT_FDCWD, os.fsencode(b), _RENAME_EXCHANGE) == 0:
        return True
    err = ctypes.get_errno()
    if err in (errno.EINVAL, errno.ENOSYS, errno.EOPNOTSUPP):
        return False  # this kernel or file system cannot exchange: fall back
    raise OSError(err, os.strerror(err), str(a), None, str(b))


def swap_into_place(tmp: Path, final: Path) -> Path:
    """Make the directory ``tmp`` the one at ``final`` (which exists); returns where the previous one went."""
    old = hidden_path(final, "old")
    if _exchange(tmp, final):
        # the new version is in place. Killed (or failing) before this rename, the previous version waits at
        # the temporary name instead: collected all the same
        try:
            os.rename(tmp, old)
        except OSError:
            return tmp
        return old
    os.rename(final, old)  # killed between these two renames: no map at `final`, the previous one whole at `old`
    try:
        os.rename(tmp, final)
    except BaseException:
        os.rename(old, final)  # put the previous version back; the new one stays at `tmp`
        raise
    return old


def _hidden_entries(final: Path):
    prefix = f".{final.name}."
    try:
        entries = list(os.scandir(final.parent))
    except OSError:
        return []
    return [e for e in entries if e.name.startswith(prefix) and _HIDDEN_RE.fullmatch(e.name[len(prefix):])]


def collect(final: Path) -> int:
    """Remove the replaced versions and dead writers' temporaries of ``final`` that nobody holds; returns how
    many. Entries somebody holds (a reader's shared lock, a live writer's exclusive one) are kept."""
    removed = 0
    for entry in _hidden_entries(final):
        try:
            fd = _open_dir(entry.path, nofollow=True)
        except OSError:
            continue
        try:
            if _try_lock(fd, fcntl.LOCK_EX) is True and same_dir(fd, Path(entry.path)):
                shutil.rmtree(entry.path, ignore_errors=True)
                removed += 1
        finally:
            os.close(fd)
    return removed


class WriterLock:
    """Exclusive lock serialising the writers of one map: ``.NAME.lock`` beside it, removed on release."""

    def __init__(self, final: Path, timeout: float):
        self.final, self.timeout = final, timeout
        self.path = final.with_name(f".{final.name}.lock")
        self.fd: int | None = None

    def acquire(self) -> "WriterLock":
        deadline = time.monotonic() + self.timeout
        while True:
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT | getattr(os, "O_CLOEXEC", 0), 0o666)
            got = _wait_lock(fd, fcntl.LOCK_EX, deadline)
            if got is False:
                os.close(fd)
                raise MapBusyError(f"{self.final} is being written by another process (lock file {self.path}); "
                                   f"waited {self.timeout:g} s: try again when it is done")
            try:
                st = os.stat(self.path)
                same = (st.st_dev, st.st_ino) == dir_id(fd)
            except OSError:
                same = False
            if same:  # else the holder we waited for removed that file: lock the current one
                self.fd = fd
                return self
            os.close(fd)

    def release(self) -> None:
        if self.fd is None:
            return
        try:
            os.unlink(self.path)  # while still holding it, so a waiter sees the file is gone and retries
        except OSError:
            pass
        os.close(self.fd)
        self.fd = None

    def __enter__(self) -> "WriterLock":
        return self.acquire()

    def __exit__(self, *exc) -> None:
        self.release()


def check_output_path(path: Path | str, *, directory: bool = False) -> Path:
    """Refuse an output path before anything is written there; returns it as a Path. Refused: a path naming no
    entry of its own (``.``, ``..``, a trailing ``/``: ``encode v.npy .`` would have replaced the current
    directory), a path inside a Zarr store (a directory above it, links resolved, holds ``zarr.json``: a map or a
    data set; ``track MAP SEQ -o MAP/zarr.json`` once replaced the header of the map it had just read), and, for a
    file output (``directory`` False), an existing directory (its rename would fail after all the work).

    Raises:
        InvalidValueError: saying which and what to do.
    """
    p = Path(path)
    if p.name in ("", ".", "..") or str(path).endswith(os.sep):
        raise InvalidValueError(f"output {str(path)!r} names a directory, not an output of its own: give it a name "
                                f"(e.g. {os.path.join(str(path), 'out.sdfz' if directory else 'out.npy')})")
    parent = Path(os.path.realpath(p.parent))
    stores = [d for d in (parent, *parent.parents) if os.path.isfile(d / "zarr.json")]
    if stores:  # named by its outermost folder: the map, not its array
        raise InvalidValueError(f"output {path} lies inside {stores[-1]}, a Zarr store (a map or a data set): "
                                "writing there would corrupt it; write the output elsewhere")
    if not directory and p.is_dir():
        raise InvalidValueError(f"output {path} is a directory; name a file to write (e.g. {p / 'out'}{p.suffix})")
    return p


def write_file(path: Path | str, write, doing: str = "writing") -> Path:
    """Write the file ``path`` (a trajectory, a model, a picture, a mesh: any output that is not a map)
    through ``write(tmp)``, into a hidden sibling ``.NAME.<hex>.partial.EXT`` (the extension kept, so that
    writers that pick a format by it still do), then rename it over ``path``: nobody ever sees a half-written
    file, and a failed write leaves the previous file (if any) as it was and no temporary. ``write`` returning
    False means it failed without saying why (open3d): a file system without a free block is then called
    full (ENOSPC), anything else an I/O error.

    Raises:
        WriteFailedError: any OSError while writing or renaming (disk full, no permission, a file too large,
            an I/O error), naming ``path`` and saying what to do.
    """
    path = check_output_path(path)  # never inside a map, never onto a directory
    outcome = ("the file there is unchanged" if os.path.lexists(path) else "nothing was written there") + \
        " and no temporary file is left"
    tmp = path.with_name(f".{path.name}.{uuid.uuid4().hex[:12]}.partial{path.suffix}")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        if write(tmp) is False:
            code = errno.ENOSPC if os.statvfs(path.parent).f_bavail == 0 else errno.EIO
            raise WriteFailedError.from_os_error(OSError(code, os.strerror(code), str(path)), path, doing, outcome)
        os.replace(tmp, path)
    except BaseException as e:
        try:
            tmp.unlink(missing_ok=True)
        except OSError:
            pass
        if isinstance(e, OSError) and not isinstance(e, WriteFailedError):
            raise WriteFailedError.from_os_error(e, path, doing, outcome) from e
        raise
    return path


def write_new_file(path: Path, data, exclusive: bool = False) -> int:
    """Write ``data`` (bytes-like) as the file ``path`` without ever writing into an existing file: into a new
    file renamed over ``path`` (``exclusive``: linked to it, FileExistsError when it exists). Returns the
    bytes written. Hard links an update shares with the previous version thus stay intact.

    Inside a writer's temporary directory ``.NAME.tmp-<hex>`` the missing folders are made below it, never
    the temporary directory itself: Zarr writes several keys at once, and when one write fails the others run
    on after the writer was aborted; they must fail (FileNotFoundError) rather than bring back the directory
    the abort removed."""
    _make_parents(path.parent)
    tmp = path.with_name(f"{path.name}.{uuid.uuid4().hex}.partial")
    try:
        with open(tmp, "xb") as f:
            n = f.write(data)
        if exclusive:
            os.link(tmp, path)  # FileExistsError when the key exists
            os.unlink(tmp)
        else:
            os.replace(tmp, path)
        return n
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def _make_parents(d: Path) -> None:
    top = next((a for a in (d, *d.parents) if _TEMP_NAME_RE.fullmatch(a.name)), None)
    if top is None:
        d.mkdir(parents=True, exist_ok=True)
        return
    for sub in [top / rel for rel in reversed(d.relative_to(top).parents)][1:] + ([d] if d != top else []):
        try:
            os.mkdir(sub)
        except FileExistsError:
            pass


def remove_tree(path: Path, settle: float = 2.0) -> None:
    """Remove the directory (or file) ``path`` for good: again after short waits, for up to ``settle`` s, while
    something still re-creates entries inside it (an aborted writer's Zarr writes still running)."""
    deadline = time.monotonic() + settle
    while True:
        if os.path.isdir(path) and not os.path.islink(path):
            shutil.rmtree(path, ignore_errors=True)
        elif os.path.lexists(path):
            try:
                os.unlink(path)
            except OSError:
                pass
        if not os.path.lexists(path) or time.monotonic() >= deadline:
            return
        time.sleep(0.01)


def link_tree(src: Path | str, dst: Path) -> None:
    """Fill the existing directory ``dst`` with hard links to every file under ``src`` (copies where the file
    system refuses links). Safe because writers replace files (:func:`write_new_file`), never rewrite them."""
    src = str(src)
    for dirpath, dirnames, filenames in os.walk(src):
        rel = os.path.relpath(dirpath, src)
        target = dst if rel == "." else dst / rel
        target.mkdir(exist_ok=True)
        for name in filenames:
            s, d = os.path.join(dirpath, name), target / name
            try:
                os.link(s, d)
            except OSError:
                shutil.copy2(s, d)
