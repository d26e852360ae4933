"""What every ``sdfcodec`` command shares: the typer app, the consoles, the one-line error wrapper, argument
parsers, safe output files and the report printer. Commands live in :mod:`sdfcodec.cli.maps` (map files) and
:mod:`sdfcodec.cli.work` (fusion, tracking, evaluation, training, benchmarks, the demo).

Output rules, decided here and nowhere else. On a terminal: rich tables and live progress bars. On a pipe or a
file (stdout not a terminal): nothing wrapped or cut, tables as tab-separated lines (``# `` before a title or
caption line, then a header row, then one row a line) that ``tail``, ``cut -f`` and ``awk -F'\t'`` can use, and
each command's summary as one line. Progress (stderr not a terminal): one line every
``SDFCODEC_PROGRESS_SECONDS`` seconds (default 10; what, how far, rate), none for work that ends sooner.
``--json`` prints only JSON on stdout, whatever it is connected to. Ctrl-C ends a command with status 130 and one
line saying whether its output changed (outputs are written beside and renamed: never half-written)."""

from __future__ import annotations

import contextlib
import errno
import functools
import inspect
import json
import logging
import os
import sys
import threading
import time
import warnings
import weakref
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Iterator, List, Optional, Sequence

import numpy as np
import typer
from typer.core import TyperGroup
from rich.console import Console
from rich.table import Table
from rich.text import Text

from .. import __version__
from ..errors import InputNotFoundError, MapExistsError, SDFCodecError, WriteFailedError

if TYPE_CHECKING:
    from rich.progress import Progress

__all__ = ["app", "out", "err", "fail", "cli", "reads_maps", "write_output", "PlainWriter", "progress_bar",
           "parse_triple", "parse_pair", "parse_truncation", "parse_region", "print_json", "report", "refuse_existing", "human_bytes",
           "load_volume", "overwrite_option", "json_option", "check_device_flag", "finished_cleanly", "end_process"]


def unwrap_paragraphs(text: str | None) -> str | None:
    """``text`` with the line breaks inside each paragraph (blank-line separated) turned into spaces, so that help
    wraps by paragraph at the terminal's width: docstrings are hard-wrapped at 120 columns in the source, and
    typer's rich mode keeps those breaks after the first paragraph. A paragraph that starts with ``\\b`` (click's
    "keep these lines") is left as it is."""
    if not text:
        return text
    import inspect

    paragraphs = inspect.cleandoc(text).split("\n\n")
    return "\n\n".join(p if p.startswith("\b") else " ".join(p.split("\n")) for p in paragraphs)


_tidied: "weakref.WeakSet[Any]" = weakref.WeakSet()  # the commands whose help is tidied (click builds them once)


def _tidy_help(command: Any, ctx: Any) -> None:
    """One command's help as the project shows it: paragraphs unwrapped (:func:`unwrap_paragraphs`), and no type
    name where it says nothing: none on a flag (``<bool>``: a flag takes no value) or on text (``<str>``: every
    value on a command line is text); ``<int>``, ``<float>`` and ``<path>`` stay."""
    if command in _tidied:
        return
    command.help = unwrap_paragraphs(command.help)
    helper = command.get_help_option(ctx)  # made on first use, then kept: --help is a flag too
    for param in [*command.params, *([helper] if helper is not None else [])]:
        says_nothing = getattr(param, "is_bool_flag", False) or (
            hasattr(param, "display_type") and param.display_type(ctx) == "<str>")
        if not says_nothing:
            continue
        if param.param_type_name == "argument":  # an argument's type column ignores its metavar (its name)
            param.display_type_rich = lambda ctx: None
        elif param.metavar is None:
            param.metavar = ""  # an option's type column shows its metavar when one is set
    _tidied.add(command)


class _Commands(TyperGroup):
    """The ``sdfcodec`` group: every command's help tidied (:func:`_tidy_help`) when click first looks it up, so a
    command added anywhere gets the same help without repeating settings on each option."""

    def get_command(self, ctx: Any, cmd_name: str) -> Any:
        command = super().get_command(ctx, cmd_name)
        if command is not None:
            _tidy_help(command, ctx)
        return command

    def format_help(self, ctx: Any, formatter: Any) -> None:
        _tidy_help(self, ctx)
        super().format_help(ctx, formatter)


app = typer.Typer(help="Compress TSDF robot maps into per-block codes (PCA eigenshapes and friends).",
                  no_args_is_help=True, add_completion=False, pretty_exceptions_enable=False, cls=_Commands)


def overwrite_option(what: str = "OUTPUT") -> Any:
    """The ``--overwrite`` flag every command that writes a file or map shares (the same words everywhere)."""
    return typer.Option(False, "--overwrite", help=f"Replace {what} if already there.")


def json_option(text: str = "Print the summary as JSON (only JSON on stdout).") -> Any:
    """The ``--json`` flag every command shares; ``text`` says what the JSON holds where it differs."""
    return typer.Option(False, "--json", help=text)


out = Console()
err = Console(stderr=True, soft_wrap=True)


def fail(msg: str, code: int = 1) -> None:
    # the message as plain text, never markup: "pip install 'sdfcodec[fusion]'" must keep its "[fusion]"
    err.print(Text.assemble(("error:", "bold red"), " ", str(msg)), highlight=False, soft_wrap=True)
    raise typer.Exit(code)


_finished: list[bool] = []  # finished_cleanly() was called by the command running (one command per process)


def finished_cleanly() -> None:
    """Say that the running command has printed its answer, closed every file it wrote and left no thread of its
    own working (a read-only command: search): :func:`end_process` may then skip Python's teardown."""
    _finished.append(True)


def end_process(code: Any) -> None:
    """End the process with status ``code`` right away when the command :func:`finished_cleanly`: the streams
    flushed and the ``atexit`` handlers run (readers' pins, remote sessions, logging), as at a normal exit, but
    not the teardown of the ~700 modules a command imports (0.2-0.4 s after the answer on two cores at load 4-6).
    Returns (the caller exits as usual) otherwise, or when a stream cannot be flushed."""
    if not _finished or not (code is None or (isinstance(code, int) and not isinstance(code, bool))):
        return
    import atexit

    try:
        sys.stdout.flush()
        sys.stderr.flush()
    except (OSError, ValueError):  # a closed pipe: Python's own exit reports it
        return
    run_exitfuncs = getattr(atexit, "_run_exitfuncs", None)  # CPython's; without it, Python's own exit
    if run_exitfuncs is None:
        return
    run_exitfuncs()  # what Py_Finalize runs first; os._exit then skips the rest
    os._exit(code or 0)


def cli(fn: Callable) -> Callable:
    """Turn the project's errors (and missing files) into one line on stderr and exit status 1."""

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        def show(message, category, filename, lineno, file=None, line=None):
            err.print(Text.assemble(("warning:", "yellow"), " ", str(message)), highlight=False, soft_wrap=True)

        old = warnings.showwarning
        warnings.showwarning = show
        _targets.clear()  # one command per process, but CliRunner runs many in one
        _finished.clear()
        try:
            return fn(*args, **kwargs)
        except KeyboardInterrupt:  # Ctrl-C: the shell's 128 + SIGINT, and what became of the output
            # Zarr's event loop still holds the interrupted write's tasks; when the process exits, asyncio would log
            # "Task was destroyed but it is pending!" for each of them after our line. The output is already dealt
            # with (rolled back or named), so they say nothing the user can act on.
            logging.getLogger("asyncio").setLevel(logging.CRITICAL)
            fail(_interrupted(), 130)
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


def reads_maps(fn: Callable) -> Callable:
    """Give a command that reads maps the options ``--trusted-key PATH`` (repeatable: the map must be signed by
    one of these Ed25519 public keys) and ``--no-verify-chunks`` (skip checking each chunk against the map's
    manifest: benchmarks only), applied as the process's read defaults while it runs (spec sections 9b, 9c).
    Put it below :func:`cli`, so that an unusable key file is one line too."""
    trusted = inspect.Parameter(
        "trusted_key", inspect.Parameter.KEYWORD_ONLY, annotation=Optional[List[Path]],
        default=typer.Option(None, "--trusted-key", metavar="PATH", help="Refuse maps not signed by this Ed25519 "
                             "public key (PEM or raw 32 bytes; repeat for several). See docs/integrity.md."))
    unchecked = inspect.Parameter(
        "no_verify_chunks", inspect.Parameter.KEYWORD_ONLY, annotation=bool,
        default=typer.Option(False, "--no-verify-chunks", help="Do not check chunks against the map's manifest "
                             "(for benchmarks only: a moved or altered chunk then decodes silently)."))

    @functools.wraps(fn)
    def wrapper(*args: Any, trusted_key: Optional[List[Path]] = None, no_verify_chunks: bool = False,
                **kwargs: Any) -> Any:
        if not trusted_key and not no_verify_chunks:
            return fn(*args, **kwargs)  # the defaults: a light command imports nothing for them
        from ..map.manifest import set_check_default
        from ..map.signing import set_trust_defaults

        try:
            set_trust_defaults(trusted_key)
            set_check_default(not no_verify_chunks)
            return fn(*args, **kwargs)
        finally:  # one command per process, but CliRunner runs many in one
            set_trust_defaults(None)
            set_check_default(True)

    sig = inspect.signature(fn)
    wrapper.__signature__ = sig.replace(parameters=[*sig.parameters.values(), trusted, unchecked])
    wrapper.__annotations__ = {**fn.__annotations__, "trusted_key": Optional[List[Path]], "no_verify_chunks": bool}
    return wrapper


def write_output(output: Path, write: Callable[[Path], Any], doing: str = "writing") -> Path:
    """Write a file output through ``write(tmp)`` into a hidden sibling renamed over ``output``
    (:func:`sdfcodec.core._atomic.write_file`): never a half-written file at ``output``, no temporary left on any
    failure (an interrupt, an error of ``write``, a refused rename onto a directory), never inside a map. A refused
    write (disk full, permission, I/O error; ``write`` returning False) is a WriteFailedError naming ``output``."""
    from ..core._atomic import write_file

    if not output.parent.is_dir():  # a typo in the folder is not created silently (write_file would make it)
        raise InputNotFoundError(f"no such directory for the output {output}: {output.parent} (create it first)")
    return write_file(output, write, doing)


class PlainWriter:
    """A file seen only through its ``write`` (numpy then writes with it, chunk by chunk)."""

    def __init__(self, f: Any):
        self.write = f.write


@functools.cache
def _rate_column() -> type:
    """rich's progress column of the task's ``rate`` field when a caller sets one, else its measured speed in
    ``unit``/s; made on first use: importing ``rich.progress`` took 20-25 ms of the half second ``sdfcodec info``
    takes on a 2-core machine."""
    from rich.progress import ProgressColumn

    class RateColumn(ProgressColumn):
        def __init__(self, unit: str):
            super().__init__()
            self.unit = unit

        def render(self, task: Any) -> Text:
            rate = task.fields.get("rate")
            if isinstance(rate, str) and rate:
                return Text(rate)
            speed = task.finished_speed or task.speed
            return Text(f"{speed:,.1f} {self.unit}/s" if speed else "")

    return RateColumn


def progress_seconds() -> float:
    """Seconds between progress lines on a pipe: ``SDFCODEC_PROGRESS_SECONDS`` (default 10; tests shorten it)."""
    try:
        return max(float(os.environ.get("SDFCODEC_PROGRESS_SECONDS", "10")), 0.05)
    except ValueError:
        return 10.0


class LineProgress:
    """Progress without a terminal: every :func:`progress_seconds` one line on stderr per unfinished task
    (``encoding: 1,024 of 4,096 blocks (25%), 310.2 blocks/s, 10 s, about 10 s left``); nothing when the work
    ends sooner. The part of rich's :class:`~rich.progress.Progress` the commands use (``add_task``,
    ``advance``, ``update``, a context manager); fields such as ``rate`` are accepted and ignored."""

    def __init__(self, unit: str = "blocks", every: float | None = None):
        self.unit, self.every = unit, every or progress_seconds()
        self.tasks: dict[int, dict[str, Any]] = {}
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def __enter__(self) -> "LineProgress":
        # a thread, not the callers' advance calls: work with no callback (one long decode) is reported too
        self._thread = threading.Thread(target=self._run, name="sdfcodec-progress", daemon=True)
        self._thread.start()
        return self

    def __exit__(self, *exc: Any) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join()

    def add_task(self, description: str, total: float | None = None, **fields: Any) -> int:
        task = len(self.tasks)
        self.tasks[task] = {"description": description, "total": total, "completed": 0.0,
                            "start": time.monotonic()}
        return task

    def advance(self, task: int, advance: float = 1) -> None:
        self.tasks[task]["completed"] += advance

    def update(self, task: int, *, advance: float | None = None, completed: float | None = None,
               total: float | None = None, description: str | None = None, **fields: Any) -> None:
        t = self.tasks[task]
        if completed is not None:
            t["completed"] = completed
        if advance is not None:
            t["completed"] += advance
        if total is not None:
            t["total"] = total
        if description is not None:
            t["description"] = description

    def line(self, task: int) -> str | None:
        """The progress line of ``task`` now (None once it is complete)."""
        t = self.tasks[task]
        done, total, secs = t["completed"], t["total"], time.monotonic() - t["start"]
        if total is not None and done >= total:
            return None
        if not done:
            return f"{t['description']}: {secs:.0f} s so far"
        rate = done / max(secs, 1e-9)
        text = f"{t['description']}: {done:,.0f}"
        if total:
            text += f" of {total:,.0f} {self.unit} ({100 * done / total:.0f}%)"
        else:
            text += f" {self.unit}"
        text += f", {rate:,.1f} {self.unit}/s, {secs:.0f} s"
        if total:
            text += f", about {(total - done) / rate:.0f} s left"
        return text

    def _run(self) -> None:
        while not self._stop.wait(self.every):
            for task in list(self.tasks):
                text = self.line(task)
                if text is not None:
                    sys.stderr.write(text + "\n")
                    sys.stderr.flush()


def live_progress() -> bool:
    """Whether stderr is a terminal (live bars), not a pipe or a file (:class:`LineProgress`)."""
    return err.is_terminal


def progress_bar(unit: str = "blocks") -> Progress | LineProgress:
    """A live bar on a terminal (stderr); :class:`LineProgress` (a line every ~10 s) when stderr is not one."""
    if not live_progress():
        return LineProgress(unit)
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    return Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                    _rate_column()(unit), console=err, transient=True)


@contextlib.contextmanager
def working(description: str) -> Iterator[None]:
    """Work with no measure of how far it is (one call into the library): a pulsing bar on a terminal, a line
    every ~10 s (``fusing: 20 s so far``) without one."""
    with progress_bar() as prog:
        prog.add_task(description, total=None, rate="")
        yield


def heartbeat(description: str, as_json: bool) -> contextlib.AbstractContextManager:
    """Around library work that draws its own bars on a terminal (fusion, eval, the demo): :func:`working`'s
    lines where those bars cannot show (stderr not a terminal), nothing on a terminal or with ``--json``."""
    return contextlib.nullcontext() if live_progress() or as_json else working(description)


def say(text: str) -> None:
    """A command's summary sentence on stdout: through rich on a terminal (wrapped to the window), else as one
    plain line (never wrapped at 80 columns)."""
    if out.is_terminal:
        out.print(text, markup=False, highlight=False)
    else:
        sys.stdout.write(text + "\n")
        sys.stdout.flush()


def print_table(columns: Sequence[str] | None, rows: Sequence[Sequence[Any]], *, title: str | None = None,
                caption: str | None = None, justify: str = "left", min_width: int | None = None) -> None:
    """A table on stdout: rich on a terminal (cells fold, never cut to "..."); on a pipe tab-separated lines,
    ``# title`` and ``# caption`` lines first, then the header (``columns``; None: a key-value table without
    one), then one line per row, so that ``| tail -1`` is the last row."""
    cells = [["" if c is None else str(c) for c in row] for row in rows]
    if not out.is_terminal:
        lines = [f"# {t}" for t in (title, *(caption or "").splitlines()) if t]
        if columns is not None:
            lines.append("\t".join(columns))
        lines += ["\t".join(c.replace("\t", " ").replace("\n", " ") for c in row) for row in cells]
        sys.stdout.write("".join(line + "\n" for line in lines))
        sys.stdout.flush()
        return
    table = Table(title=title, show_header=columns is not None, caption=caption, caption_justify="left")
    ncols = len(columns) if columns is not None else max((len(r) for r in cells), default=0)
    for i in range(ncols):
        name = columns[i] if columns is not None else ""
        # as wide as the widest word: a figure or an id folds onto a second line at worst, never loses its end
        widest = max([len(w) for w in name.split()] + [len(r[i]) for r in cells if i < len(r)] or [0])
        table.add_column(name, justify=justify, overflow="fold",  # type: ignore[arg-type]
                         min_width=min(widest, 40))
    for row in cells:
        table.add_row(*row)
    out.print(table, width=max(out.width, min_width) if min_width else None, crop=False)


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


def parse_truncation(text: str) -> tuple[float, float]:
    """``--truncation d_min,d_max``, checked (finite, ``d_min < d_max``): commands parse it before they load
    torch and Zarr (2-3 s), so that a reversed or mistyped range is refused at once."""
    from ..core.blocks import check_truncation

    trunc = parse_pair(text, "--truncation")
    check_truncation(*trunc)
    return trunc


def parse_region(text: str | None) -> tuple | None:
    if text is None:
        return None
    try:
        parts = [tuple(float(v) for v in p.split(":")) for p in text.split(",")]
        assert len(parts) == 3 and all(len(p) == 2 for p in parts)
    except (ValueError, AssertionError):
        fail(f"--region must look like x0:x1,y0:y1,z0:z1, got {text!r}")
    return tuple(parts)


def check_device_flag(device: str | None) -> None:
    """``--device``, checked before the work starts (a name torch knows, a device this machine and torch build
    have): the command's error names the flag (:func:`sdfcodec.core._validate.check_device`)."""
    if device is not None and device != "cpu":  # the CPU is always there: no torch import to say so
        from ..core._validate import check_device

        check_device(device, "--device")


def check_code_size(codec_id: str, code_size: int) -> int | None:
    """``--code-size`` for ``codec_id``: a positive whole number (0 or -1 is refused, never read as "default"),
    one of the sizes of a codec whose code length is fixed (raw: 4096); returns what to pass on (None for a fixed
    size, which the codec takes no parameter for)."""
    import inspect

    from ..errors import InvalidValueError

    if code_size < 1:  # before the registry (and torch) is imported: a typo costs no start-up
        raise InvalidValueError(f"--code-size must be a positive number of code elements (e.g. 32, 64, 128), "
                                f"got {code_size}")
    from ..registry import get_codec_class

    cls = get_codec_class(codec_id)
    if "code_size" in inspect.signature(cls.__init__).parameters:
        return code_size
    sizes = ", ".join(map(str, cls.code_sizes)) or "a size of its own"
    if code_size not in cls.code_sizes:
        raise InvalidValueError(f"codec {codec_id!r} makes codes of {sizes} elements only, not {code_size}; "
                                "drop --code-size")
    return None


def print_json(obj: Any) -> None:
    sys.stdout.write(json.dumps(obj, indent=2, default=str) + "\n")


def report(summary: Any, as_json: bool, line: Callable[[], str]) -> None:
    """Print ``summary`` as JSON, or the human line ``line()`` (built only when needed)."""
    if as_json:
        print_json(summary)
    else:
        say(line())  # results are plain text: "[m]" in a table header is a unit, not markup


_targets: list[tuple[Path, tuple | None]] = []  # the outputs of the running command, as they were at its start


def _stat(path: Path) -> tuple | None:
    try:
        st = path.stat()
    except OSError:
        return None
    return st.st_ino, st.st_mtime_ns, st.st_size


def note_target(path: Path) -> None:
    """Remember ``path`` as an output of the running command, so that Ctrl-C can say what became of it."""
    _targets.append((Path(path), _stat(Path(path))))


def _interrupted() -> str:
    """What Ctrl-C left: each output unchanged, not created, or (the rename came first) written in full."""
    said = []
    for path, before in _targets:
        now = _stat(path)
        if now == before:
            said.append(f"{path} {'was not created' if before is None else 'is unchanged'}")
        else:
            said.append(f"{path} was {'written' if before is None else 'replaced'} in full before the interrupt")
    return "interrupted" + (": " + "; ".join(said) if said else "")


def refuse_existing(path: Path, overwrite: bool, *, map_output: bool = False, directory: bool = False,
                    files: Sequence[str] = ()) -> None:
    """Check an output before any work, the one check every writing command makes: the path is not inside a map
    (or any Zarr store) and names an output of its own (:func:`sdfcodec.core._atomic.check_output_path`); without
    ``overwrite`` nothing there is replaced (a file or map at ``path``; for a directory output, ``files``: the
    names the command writes into it); ``map_output``: only a map (or an empty directory) is ever replaced;
    ``directory``: the output is a directory the command's library call replaces itself (a data set).
    Remembers ``path`` for Ctrl-C's report."""
    from ..core._atomic import check_output_path

    note_target(path)
    check_output_path(path, directory=map_output or directory or bool(files))
    clash = [path / f for f in files if os.path.lexists(path / f)] if files else ([path] if path.exists() else [])
    if clash and not overwrite:
        raise MapExistsError(f"{clash[0]} exists; pass --overwrite to replace it (or choose another output)")
    if map_output:  # before any work: --overwrite replaces a map, never a directory or file that is not one
        from ..map.writer import check_replaceable

        check_replaceable(path)


def _print_version(value: bool) -> None:
    if value:
        say(f"sdfcodec {__version__}")
        raise typer.Exit()


@app.callback()
def _root(version: bool = typer.Option(False, "--version", is_eager=True, callback=_print_version,
                                       help="Print the version and exit."),
          follow_symlinks: bool = typer.Option(
              False, "--follow-symlinks", help="Follow symbolic links inside local maps (refused by default)."),
          remote_timeout: float = typer.Option(
              None, "--remote-timeout", metavar="SECONDS",
              help="Most time one object of a remote map may take, every try together; a stall is not retried "
                   "(default 60)."),
          remote_tries: int = typer.Option(
              None, "--remote-tries", metavar="N", help="Tries per object of a remote map (default 4).")) -> None:
    # --version is eager: handled while the options are parsed, before click asks for a command
    # the read options are a process default, not arguments: every command (and the library functions that open
    # maps for it: verify, search, compare, track, eval, the tracker's map field) reads through sdfcodec.map.io.stores
    limits = {k: v for k, v in (("total_timeout", remote_timeout), ("tries", remote_tries)) if v is not None}
    if not follow_symlinks and not limits and "sdfcodec.map.io.stores" not in sys.modules:
        return  # the built-in defaults, untouched in this process: a light command need not import Zarr for them
    from ..map.io.stores import set_read_defaults

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


_META_SIZES = {"voxel_size": 1, "origin": 3, "truncation": 2}  # the metadata arrays a volume file may carry


def load_volume(path: Path, key: str | None) -> tuple[np.ndarray, dict[str, Any]]:
    """A dense TSDF from .npy or .npz (``tsdf`` or the only array; optional voxel_size/origin/truncation),
    checked as untrusted input: a file numpy cannot read (truncated, a header that lies about its size, a
    pickle: never unpickled), an array of objects, strings or records, or metadata that is not the numbers it
    names is an :class:`InvalidValueError` naming the file and what is wrong, never numpy's exception."""
    import zipfile

    from ..errors import InvalidValueError

    meta: dict[str, Any] = {}
    what = f"{path}: not a readable dense volume"
    try:
        if path.suffix == ".npy":
            vol = np.load(path, allow_pickle=False, mmap_mode="r")
        elif path.suffix == ".npz":
            with np.load(path, allow_pickle=False) as z:
                names = [n for n in z.files if n not in _META_SIZES]
                pick = key or ("tsdf" if "tsdf" in z.files else (names[0] if len(names) == 1 else None))
                if pick is None or pick not in z.files:
                    fail(f"{path} holds arrays {z.files}; choose one with --key")
                vol = z[pick]
                for m, size in _META_SIZES.items():
                    if m in z.files:
                        v = z[m]
                        if v.dtype.kind not in "iuf" or v.size != size or not np.isfinite(v).all():
                            raise InvalidValueError(f"{path}: array {m!r} must hold {size} finite number(s), got "
                                                    f"{v.size} value(s) of type {v.dtype}: fix or drop it")
                        meta[m] = v.item() if size == 1 else v.reshape(-1).tolist()
        else:
            fail(f"{path}: input must be a .npy or .npz volume, or a map directory")
    except SDFCodecError:
        raise
    except (ValueError, EOFError, zipfile.BadZipFile, KeyError) as e:  # numpy's reasons, one line
        reason = " ".join(str(e).split())
        if "pickle" in reason or "Object arrays" in reason or "Python objects" in reason:
            reason = "it holds Python objects (a pickle), which sdfcodec never loads"
        elif "mmap length" in reason or "EOF" in reason or "truncated" in reason.lower():
            reason = f"it is shorter than its header says (truncated or a lying header: {reason})"
        raise InvalidValueError(f"{what} ({reason}); save it with numpy.save (float32 metres)") from None
    if vol.dtype.kind not in "iuf" or vol.dtype.itemsize > 8:
        raise InvalidValueError(f"{what}: it holds {vol.dtype} values, not numbers; a TSDF is float32 metres")
    if vol.ndim != 3:
        raise InvalidValueError(f"{what}: shape {vol.shape}, expected a 3-D (X, Y, Z) volume")
    return np.asarray(vol), meta
