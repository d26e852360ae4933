"""What every ``sdfcodec`` command shares: the typer app, the consoles, the one-line error wrapper, argument
parsers, safe output files and the report printer. Commands live in :mod:`sdfcodec.cli.maps` (map files) and
:mod:`sdfcodec.cli.work` (fusion, tracking, evaluation, training, benchmarks, the demo)."""

from __future__ import annotations

import errno
import functools
import json
import sys
import warnings
from pathlib import Path
from typing import Any, Callable

import numpy as np
import typer
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

from .. import __version__
from ..errors import MapExistsError, SDFCodecError, WriteFailedError

__all__ = ["app", "out", "err", "fail", "cli", "write_output", "PlainWriter", "progress_bar", "parse_triple",
           "parse_pair", "parse_region", "print_json", "report", "refuse_existing", "human_bytes", "load_volume"]

app = typer.Typer(help="Compress TSDF robot maps into per-block codes (PCA eigenshapes and friends).",
                  no_args_is_help=True, add_completion=False, pretty_exceptions_enable=False)
out = Console()
err = Console(stderr=True, soft_wrap=True)


def fail(msg: str, code: int = 1) -> None:
    err.print(f"[bold red]error:[/] {msg}", highlight=False, soft_wrap=True)
    raise typer.Exit(code)


def cli(fn: Callable) -> Callable:
    """Turn the project's errors (and missing files) into one line on stderr and exit status 1."""

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        def show(message, category, filename, lineno, file=None, line=None):
            err.print(f"[yellow]warning:[/] {message}", highlight=False, soft_wrap=True)

        old = warnings.showwarning
        warnings.showwarning = show
        try:
            return fn(*args, **kwargs)
        # file errors first: one that names its file (InputNotFoundError too) prints "reason: path", not "[Errno 2]"
        except (FileNotFoundError, IsADirectoryError, PermissionError) as e:
            fail(f"{e.strerror or e}: {e.filename}" if getattr(e, "filename", None) else str(e))
        except SDFCodecError as e:
            fail(str(e))
        except OSError as e:  # any other file-system failure (a full disk under an output, a path through a file)
            name = errno.errorcode.get(e.errno or 0, "")
            advice = WriteFailedError.ADVICE.get(name, "check the path and the file system and run again")
            where = f": {e.filename}" if getattr(e, "filename", None) else ""
            fail(f"{e.strerror or e}{where}; {advice}")
        finally:
            warnings.showwarning = old

    return wrapper


def write_output(output: Path, tmp: Path, write: Callable[[Path], bool]) -> bool:
    """Write a file output through ``write(tmp)`` (False: the writer refused, e.g. an unknown mesh format), then
    rename it over ``output``: never a half-written file at ``output``, and no ``tmp`` left on any failure. A
    refused write (disk full, permission, I/O error) is a WriteFailedError naming ``output``."""
    outcome = "the file there is unchanged" if output.exists() else "nothing was written there"
    ok = False
    try:
        ok = write(tmp)
        if ok:
            tmp.replace(output)
        return ok
    except OSError as e:
        raise WriteFailedError.from_os_error(e, output, "writing", f"{outcome} and no temporary file is left") from e
    finally:
        if not ok:
            try:
                tmp.unlink(missing_ok=True)
            except OSError:
                pass


class PlainWriter:
    """A file seen only through its ``write`` (numpy then writes with it, chunk by chunk)."""

    def __init__(self, f: Any):
        self.write = f.write


def progress_bar() -> Progress:
    return Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                    TextColumn("{task.fields[rate]}"), console=err, transient=True)


def parse_triple(text: str | None, name: str) -> tuple[float, float, float] | None:
    if text is None:
        return None
    try:
        vals = tuple(float(v) for v in text.split(","))
    except ValueError:
        vals = ()
    if len(vals) != 3:
        fail(f"{name} must be three comma-separated numbers, got {text!r}")
    return vals  # type: ignore[return-value]


def parse_pair(text: str, name: str) -> tuple[float, float]:
    try:
        a, b = (float(v) for v in text.split(","))
    except ValueError:
        fail(f"{name} must be two comma-separated numbers like -0.04,0.1, got {text!r}")
    return a, b


def parse_region(text: str | None) -> tuple | None:
    if text is None:
        return None
    try:
        parts = [tuple(float(v) for v in p.split(":")) for p in text.split(",")]
        assert len(parts) == 3 and all(len(p) == 2 for p in parts)
    except (ValueError, AssertionError):
        fail(f"--region must look like x0:x1,y0:y1,z0:z1, got {text!r}")
    return tuple(parts)


def print_json(obj: Any) -> None:
    sys.stdout.write(json.dumps(obj, indent=2, default=str) + "\n")


def report(summary: Any, as_json: bool, line: Callable[[], str]) -> None:
    """Print ``summary`` as JSON, or the human line ``line()`` (built only when needed)."""
    if as_json:
        print_json(summary)
    else:
        out.print(line(), markup=False)  # results are plain text: "[m]" in a table header is a unit, not markup


def refuse_existing(path: Path, overwrite: bool, *, map_output: bool = False) -> None:
    if path.exists() and not overwrite:
        raise MapExistsError(f"{path} exists; pass --overwrite to replace it")
    if map_output:  # before any work: --overwrite replaces a map, never a directory or file that is not one
        from ..map.writer import check_replaceable

        check_replaceable(path)


@app.callback()
def _root(version: bool = typer.Option(False, "--version", help="Print the version and exit."),
          follow_symlinks: bool = typer.Option(
              False, "--follow-symlinks", help="Follow symbolic links inside local maps (refused by default)."),
          remote_timeout: float = typer.Option(
              None, "--remote-timeout", metavar="SECONDS",
              help="Total time for one try of one object of a remote map (default 60)."),
          remote_tries: int = typer.Option(
              None, "--remote-tries", metavar="N", help="Tries per object of a remote map (default 4).")) -> None:
    if version:
        out.print(f"sdfcodec {__version__}")
        raise typer.Exit()
    # a process default, not arguments: every command (and the library functions that open maps for it:
    # verify, search, compare, track, eval, the tracker's map field) reads through sdfcodec.map.stores
    from ..map.stores import set_read_defaults

    limits = {k: v for k, v in (("total_timeout", remote_timeout), ("tries", remote_tries)) if v is not None}
    try:
        set_read_defaults(follow_symlinks=follow_symlinks, remote_limits=limits)
    except SDFCodecError as e:
        fail(str(e).replace("remote_limits.total_timeout", "--remote-timeout")
             .replace("remote_limits.tries", "--remote-tries").replace("remote_limits timeouts", "--remote-timeout"))


def human_bytes(n: float | None) -> str:
    if n is None:
        return "?"
    for unit in ("B", "KiB", "MiB", "GiB", "TiB"):
        if abs(n) < 1024 or unit == "TiB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.2f} {unit}"
        n /= 1024
    return str(n)


def load_volume(path: Path, key: str | None) -> tuple[np.ndarray, dict[str, Any]]:
    """A dense TSDF from ..npy or .npz (``tsdf`` or the only array; optional voxel_size/origin/truncation)."""
    meta: dict[str, Any] = {}
    if path.suffix == ".npy":
        vol = np.load(path, allow_pickle=False, mmap_mode="r")
    elif path.suffix == ".npz":
        with np.load(path, allow_pickle=False) as z:
            names = [n for n in z.files if n not in ("voxel_size", "origin", "truncation")]
            pick = key or ("tsdf" if "tsdf" in z.files else (names[0] if len(names) == 1 else None))
            if pick is None or pick not in z.files:
                fail(f"{path} holds arrays {z.files}; choose one with --key")
            vol = z[pick]
            for m in ("voxel_size", "origin", "truncation"):
                if m in z.files:
                    meta[m] = z[m].tolist()
    else:
        fail(f"{path}: input must be a .npy or .npz volume, or a map directory")
    return np.asarray(vol), meta
