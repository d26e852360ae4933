"""The ``sdfcodec`` command line (typer + rich). Errors print one line on stderr and exit non-zero."""

from __future__ import annotations

import errno
import functools
import json
import sys
import time
import warnings
from pathlib import Path
from typing import Any, Callable, Optional

import numpy as np
import typer
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table

from . import __version__
from .errors import InputNotFoundError, InvalidValueError, MapExistsError, SDFCodecError, WriteFailedError

__all__ = ["app", "main"]

app = typer.Typer(help="Compress TSDF robot maps into per-block codes (PCA eigenshapes and friends).",
                  no_args_is_help=True, add_completion=False, pretty_exceptions_enable=False)
out = Console()
err = Console(stderr=True, soft_wrap=True)


def _fail(msg: str, code: int = 1) -> None:
    err.print(f"[bold red]error:[/] {msg}", highlight=False, soft_wrap=True)
    raise typer.Exit(code)


def _cli(fn: Callable) -> Callable:
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
            _fail(f"{e.strerror or e}: {e.filename}" if getattr(e, "filename", None) else str(e))
        except SDFCodecError as e:
            _fail(str(e))
        except OSError as e:  # any other file-system failure (a full disk under an output, a path through a file)
            name = errno.errorcode.get(e.errno or 0, "")
            advice = WriteFailedError.ADVICE.get(name, "check the path and the file system and run again")
            where = f": {e.filename}" if getattr(e, "filename", None) else ""
            _fail(f"{e.strerror or e}{where}; {advice}")
        finally:
            warnings.showwarning = old

    return wrapper


def _write_output(output: Path, tmp: Path, write: Callable[[Path], bool]) -> bool:
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


class _PlainWriter:
    """A file seen only through its ``write`` (numpy then writes with it, chunk by chunk)."""

    def __init__(self, f: Any):
        self.write = f.write


def _progress() -> Progress:
    return Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                    TextColumn("{task.fields[rate]}"), console=err, transient=True)


def _triple(text: str | None, name: str) -> tuple[float, float, float] | None:
    if text is None:
        return None
    try:
        vals = tuple(float(v) for v in text.split(","))
    except ValueError:
        vals = ()
    if len(vals) != 3:
        _fail(f"{name} must be three comma-separated numbers, got {text!r}")
    return vals  # type: ignore[return-value]


def _pair(text: str, name: str) -> tuple[float, float]:
    try:
        a, b = (float(v) for v in text.split(","))
    except ValueError:
        _fail(f"{name} must be two comma-separated numbers like -0.04,0.1, got {text!r}")
    return a, b


def _region(text: str | None) -> tuple | None:
    if text is None:
        return None
    try:
        parts = [tuple(float(v) for v in p.split(":")) for p in text.split(",")]
        assert len(parts) == 3 and all(len(p) == 2 for p in parts)
    except (ValueError, AssertionError):
        _fail(f"--region must look like x0:x1,y0:y1,z0:z1, got {text!r}")
    return tuple(parts)


def _print_json(obj: Any) -> None:
    sys.stdout.write(json.dumps(obj, indent=2, default=str) + "\n")


def _report(summary: Any, as_json: bool, line: Callable[[], str]) -> None:
    """Print ``summary`` as JSON, or the human line ``line()`` (built only when needed)."""
    if as_json:
        _print_json(summary)
    else:
        out.print(line(), markup=False)  # results are plain text: "[m]" in a table header is a unit, not markup


def _refuse_existing(path: Path, overwrite: bool, *, map_output: bool = False) -> None:
    if path.exists() and not overwrite:
        raise MapExistsError(f"{path} exists; pass --overwrite to replace it")
    if map_output:  # before any work: --overwrite replaces a map, never a directory or file that is not one
        from .map.writer import check_replaceable

        check_replaceable(path)


@app.callback()
def _root(version: bool = typer.Option(False, "--version", help="Print the version and exit.")) -> None:
    if version:
        out.print(f"sdfcodec {__version__}")
        raise typer.Exit()


@app.command("codecs")
@_cli
def codecs_cmd(as_json: bool = typer.Option(False, "--json", help="Machine-readable output.")) -> None:
    """List installed codecs: id, code sizes, prefix-ordered, needs fitting, providing package."""
    from .registry import get_codec_class, list_codecs

    rows = []
    for entry in list_codecs():
        row: dict[str, Any] = {"id": entry.id, "package": entry.package, "version": entry.version}
        try:
            cls = get_codec_class(entry.id)
            row.update(code_sizes=list(cls.code_sizes), prefix_ordered=cls.prefix_ordered,
                       requires_fit=cls.requires_fit, status="ok")
        except SDFCodecError as e:  # one broken plugin is reported, the rest still listed
            row.update(code_sizes=None, prefix_ordered=None, requires_fit=None, status=f"failed: {e}")
        rows.append(row)
    if as_json:
        _print_json(rows)
        return
    table = Table(title="installed sdfcodec codecs")
    for col in ("id", "code sizes", "prefix-ordered", "needs fitting", "package", "status"):
        table.add_column(col)
    for r in rows:
        yn = {True: "yes", False: "no", None: "?"}
        table.add_row(r["id"], ", ".join(map(str, r["code_sizes"] or [])) or "?", yn[r["prefix_ordered"]],
                      yn[r["requires_fit"]], f"{r['package'] or '(run time)'} {r['version'] or ''}", r["status"])
    out.print(table)


@app.command("info")
@_cli
def info_cmd(map_path: str = typer.Argument(..., metavar="MAP", help="Map path or URL."),
             as_json: bool = typer.Option(False, "--json", help="Machine-readable output.")) -> None:
    """Show a map's header, blocks by state, bytes on disk and ratio to a dense float32 volume."""
    from .map import open_map

    info = open_map(map_path).info()
    if as_json:
        _print_json(info)
        return
    table = Table(show_header=False, title=f"map {map_path}")
    b = info["blocks"]
    rows = [
        ("format version", str(info["format_version"])),
        ("codec", json.dumps(info["codec"])),
        ("code", f"{info['code_size']} x {info['code_dtype']} (levels {info['levels']})"),
        ("voxel size", f"{info['voxel_size']} m"),
        ("truncation", f"[{info['truncation'][0]}, {info['truncation'][1]}] m"),
        ("origin", f"{info['origin']} m"),
        ("extent", f"{info['shape_voxels']} voxels, {info['grid_blocks']} blocks"),
        ("blocks", f"{b['coded']} coded, {b['empty']} empty, {b['unobserved']} unobserved"),
        ("dense float32", _bytes(info["dense_float32_bytes"])),
        ("codes (uncompressed)", _bytes(info["code_bytes_raw"])),
    ]
    if info["bytes_on_disk"] is not None:
        rows += [("on disk", f"{_bytes(info['bytes_on_disk'])} (codec state {_bytes(info['codec_state_bytes'])})"),
                 ("ratio dense : disk", f"{info['ratio_dense_to_disk']:.1f} : 1"),
                 ("ratio dense : disk without codec state", f"{info['ratio_dense_to_codes']:.1f} : 1")]
    for k, v in rows:
        table.add_row(k, v)
    out.print(table)


def _bytes(n: float | None) -> str:
    if n is None:
        return "?"
    for unit in ("B", "KiB", "MiB", "GiB", "TiB"):
        if abs(n) < 1024 or unit == "TiB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.2f} {unit}"
        n /= 1024
    return str(n)


def _load_volume(path: Path, key: str | None) -> tuple[np.ndarray, dict[str, Any]]:
    """A dense TSDF from .npy or .npz (``tsdf`` or the only array; optional voxel_size/origin/truncation)."""
    meta: dict[str, Any] = {}
    if path.suffix == ".npy":
        vol = np.load(path, allow_pickle=False, mmap_mode="r")
    elif path.suffix == ".npz":
        with np.load(path, allow_pickle=False) as z:
            names = [n for n in z.files if n not in ("voxel_size", "origin", "truncation")]
            pick = key or ("tsdf" if "tsdf" in z.files else (names[0] if len(names) == 1 else None))
            if pick is None or pick not in z.files:
                _fail(f"{path} holds arrays {z.files}; choose one with --key")
            vol = z[pick]
            for m in ("voxel_size", "origin", "truncation"):
                if m in z.files:
                    meta[m] = z[m].tolist()
    else:
        _fail(f"{path}: input must be a .npy or .npz volume, or a map directory")
    return np.asarray(vol), meta


@app.command("encode")
@_cli
def encode_cmd(
    input: str = typer.Argument(..., metavar="INPUT", help=".npy/.npz dense TSDF in metres, or a map to transcode."),
    output: Path = typer.Argument(..., metavar="OUTPUT", help="Map to write (a directory, e.g. room.sdfz)."),
    codec_id: Optional[str] = typer.Option(None, "--codec", help="Codec id (see `sdfcodec codecs`); default pca."),
    code_size: Optional[int] = typer.Option(None, "--code-size", help="Code length (e.g. 32, 64, 128)."),
    model: Optional[Path] = typer.Option(None, "--model", help="Trained codec (.npz from `sdfcodec train`)."),
    voxel_size: Optional[float] = typer.Option(None, "--voxel-size", help="Voxel edge in metres (volumes)."),
    truncation: Optional[str] = typer.Option(None, "--truncation", help="d_min,d_max in metres [-0.04,0.1]."),
    origin: Optional[str] = typer.Option(None, "--origin", help="x,y,z metres of voxel (0,0,0) [0,0,0]."),
    key: Optional[str] = typer.Option(None, "--key", help="Array name inside an .npz input."),
    code_dtype: str = typer.Option("float32", "--code-dtype", help="float32, float16 or int8 code storage (int8: per-block offset and scale, a quarter of float32)."),
    fit: bool = typer.Option(False, "--fit", help="Fit the codec on the input instead of the shipped model."),
    fit_max_blocks: int = typer.Option(100_000, "--fit-max-blocks", help="Blocks sampled to fit a codec."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace OUTPUT if it exists."),
    device: str = typer.Option("cpu", "--device", help="Torch device to encode on (cpu, cuda)."),
    as_json: bool = typer.Option(False, "--json", help="Print a JSON summary."),
) -> None:
    """Encode a dense TSDF volume (or transcode a map) into a compressed map.

    The codec comes from --model, else (pca) the shipped default eigenshapes cut to --code-size (default 64),
    else it is fitted on the input's non-empty blocks (also with --fit); the map stores it either way.
    """
    from .blocks import normalise, split_blocks
    from .map import create_map, open_map
    from .map.format import check_volume
    from .model import load_model
    from .registry import get_codec

    _refuse_existing(output, overwrite, map_output=True)
    src_map = None
    in_path = Path(input)
    if "://" in input or in_path.is_dir():
        src_map = open_map(input)
        vs, trunc, org = src_map.voxel_size, src_map.truncation, src_map.origin
    else:
        if not in_path.exists():
            raise InputNotFoundError(errno.ENOENT, "no such input file", str(in_path))
        vol, meta = _load_volume(in_path, key)
        vs = voxel_size if voxel_size is not None else meta.get("voxel_size")
        if vs is None:
            _fail(f"{in_path} does not record its voxel size: pass --voxel-size (metres)")
        trunc = _pair(truncation, "--truncation") if truncation else tuple(meta.get("truncation", (-0.04, 0.1)))
        org = _triple(origin, "--origin") or tuple(meta.get("origin", (0.0, 0.0, 0.0)))
        vol = check_volume(vol, trunc)

    if model is not None:
        codec = load_model(model)
        if codec_id and codec_id != codec.codec_id:
            raise InvalidValueError(f"--codec {codec_id} contradicts the model {model} (codec {codec.codec_id})")
        if code_size and code_size != codec.code_size:
            raise InvalidValueError(f"--code-size {code_size} contradicts the model {model} "
                                    f"(code size {codec.code_size})")
    elif (codec_id or "pca") == "pca" and not fit:
        from .registry import pretrained_codec

        codec = pretrained_codec("pca", code_size or 64)
    else:
        params = {"code_size": code_size} if code_size else {}
        codec = get_codec(codec_id or "pca", **params)

    fitted_on = None
    if not codec.is_fitted:
        # asked to (--fit), or no shipped model: learn from the input's blocks as the map will encode them
        from .map.observed import fit_codec
        sample, observed = np.zeros((0, 16, 16, 16), np.float32), None
        if src_map is None:
            sample = split_blocks(vol, fill=trunc[1]).reshape(-1, 16, 16, 16)
        elif pairs := list(src_map.iter_blocks()):
            sample, coords = np.concatenate([b for _, b in pairs]), np.concatenate([c for c, _ in pairs])
            observed = src_map.read_observed(coords) if src_map.records_observation else None
        fitted_on = fit_codec(codec, normalise(sample, *trunc), observed, trunc, vs, max_blocks=fit_max_blocks, log=lambda n:
                              err.print(f"fitting {codec!r} on {n} non-empty blocks of the input (pass --model to use a trained one)"))

    shape = src_map.shape_voxels if src_map is not None else (0, 0, 0)
    with _progress() as prog, create_map(output, codec=codec, voxel_size=vs, truncation=trunc, origin=org,
                                         shape_voxels=shape, code_dtype=code_dtype, overwrite=overwrite,
                                         device=device, tool="sdfcodec encode", source=str(input)) as m:
        if src_map is not None:
            total = src_map.count_states()["coded"]
            task = prog.add_task("transcoding", total=total, rate="")
            m.write_map(src_map, progress=lambda n: prog.advance(task, n))
        else:
            nblocks = int(np.prod([-(-n // 16) for n in vol.shape]))
            task = prog.add_task("encoding", total=nblocks, rate="")
            m.write_volume(vol, progress=lambda n: prog.advance(task, n))
    info = m.info()
    summary = {"output": str(output), "codec": codec.get_config(), "fitted_on_blocks": fitted_on,
               "blocks": info["blocks"], "bytes_on_disk": info["bytes_on_disk"],
               "ratio_dense_to_disk": info["ratio_dense_to_disk"]}
    _report(summary, as_json, lambda: (
        f"wrote {output}: {info['blocks']['coded']} coded blocks, {_bytes(info['bytes_on_disk'])} on disk, "
        f"{info['ratio_dense_to_disk']:.1f}:1 against dense float32"))


@app.command("decode")
@_cli
def decode_cmd(
    map_path: str = typer.Argument(..., metavar="MAP", help="Map path or URL."),
    output: Path = typer.Argument(..., metavar="OUTPUT.npy", help="Dense TSDF (metres) to write."),
    level: Optional[int] = typer.Option(None, "--level", help="Decode only the first K code elements."),
    region: Optional[str] = typer.Option(None, "--region", help="x0:x1,y0:y1,z0:z1 (half-open voxels, or metres)."),
    units: str = typer.Option("voxels", "--units", help="Units of --region: voxels or m."),
    device: str = typer.Option("cpu", "--device", help="Torch device to decode on."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace OUTPUT if it exists."),
    as_json: bool = typer.Option(False, "--json", help="Print a JSON summary."),
) -> None:
    """Decode a map (or a region of it) to a dense .npy volume in metres, free space where nothing is coded."""
    from .map import open_map

    if output.suffix != ".npy":
        _fail(f"OUTPUT must end in .npy, got {output}")
    _refuse_existing(output, overwrite)
    m = open_map(map_path)
    with _progress() as prog:
        prog.add_task("decoding", total=None, rate="")
        vol = m.decode_region(_region(region), units=units, level=level, device=None if device == "cpu" else device)
    if not isinstance(vol, np.ndarray):
        vol = vol.cpu().numpy()
    def save(tmp: Path) -> bool:
        with open(tmp, "wb") as f:
            # through Python's write, not numpy's C-level tofile: a short write then raises OSError with its
            # errno (ENOSPC, EFBIG...) instead of numpy's errno-less "requested and written"
            np.save(_PlainWriter(f), vol)
        return True

    _write_output(output, output.with_name(f".{output.name}.tmp"), save)
    summary = {"output": str(output), "shape": list(vol.shape), "level": level or m.code_size,
               "voxel_size": m.voxel_size, "origin": list(m.origin)}
    _report(summary, as_json, lambda: f"wrote {output}: {vol.shape} float32 metres (level {summary['level']})")


@app.command("fuse")
@_cli
def fuse_cmd(
    sequence: str = typer.Argument(..., metavar="SEQUENCE", help="TUM RGB-D or 7-Scenes directory."),
    output: Path = typer.Argument(..., metavar="OUTPUT", help="Map to write (e.g. kitchen.sdfz)."),
    voxel_size: float = typer.Option(0.02, "--voxel-size", help="Voxel edge in metres."),
    truncation: str = typer.Option("-0.04,0.1", "--truncation", help="d_min,d_max in metres."),
    depth_max: float = typer.Option(4.0, "--depth-max", help="Ignore depth beyond this (metres)."),
    code_dtype: str = typer.Option("float32", "--code-dtype", help="float32, float16 or int8 storage of the field (int8: per-block offset and scale)."),
    weights: bool = typer.Option(True, "--weights/--no-weights", help="Store the per-voxel fusion weights (which voxels were observed: transcoding keeps them as a mask)."),
    overwrite: bool = typer.Option(False, "--overwrite"),
    as_json: bool = typer.Option(False, "--json"),
) -> None:
    """Fuse a posed depth sequence (Curless-Levoy, open3d VoxelBlockGrid) into a lossless `raw` map.

    Transcode it afterwards with `sdfcodec encode OUTPUT SMALLER.sdfz --codec pca`.
    """
    from .fusion import fuse
    from .map import create_map
    from .registry import get_codec

    _refuse_existing(output, overwrite, map_output=True)
    trunc = _pair(truncation, "--truncation")
    fused = fuse(sequence, voxel_size=voxel_size, truncation=trunc, depth_max=depth_max, quiet=as_json)
    with create_map(output, codec=get_codec("raw"), voxel_size=voxel_size, truncation=trunc,
                    origin=tuple(fused.origin), code_dtype=code_dtype, overwrite=overwrite, tool="sdfcodec fuse", up=fused.up,
                    source=str(sequence)) as m:
        m.write_blocks(fused.coords, fused.tsdf, **({"weights": fused.weights} if weights else {"observed": fused.weights > 0}))
    info = m.info()
    summary = {"output": str(output), "frames_integrated": fused.frames_integrated,
               "frames_skipped": fused.frames_skipped, "allocated_blocks": len(fused), "blocks": info["blocks"],
               "fusion_seconds": fused.seconds, "frames_per_s": fused.frames_integrated / max(fused.seconds, 1e-9),
               "bytes_on_disk": info["bytes_on_disk"]}
    _report(summary, as_json, lambda: (
        f"wrote {output}: {fused.frames_integrated} frames ({summary['frames_per_s']:.0f} frames/s), "
        f"{len(fused)} allocated blocks ({info['blocks']['coded']} coded, {info['blocks']['empty']} empty)"))


@app.command("mesh")
@_cli
def mesh_cmd(
    map_path: str = typer.Argument(..., metavar="MAP", help="Map path or URL."),
    output: Path = typer.Argument(..., metavar="OUT.ply", help="Triangle mesh to write (.ply, .obj, .stl...)."),
    level: Optional[int] = typer.Option(None, "--level", help="Decode only the first K code elements."),
    overwrite: bool = typer.Option(False, "--overwrite"),
    as_json: bool = typer.Option(False, "--json"),
) -> None:
    """Extract the zero level set of a map as a triangle mesh (marching cubes on the decoded blocks)."""
    import open3d as o3d

    from .fusion import mesh_from_blocks
    from .map import open_map

    _refuse_existing(output, overwrite)
    m = open_map(map_path)
    coords, blocks = [], []
    for c, b in m.iter_blocks(level=level):
        coords.append(c)
        blocks.append(b)
    if not coords:
        _fail(f"{map_path} has no coded blocks: nothing to mesh")
    mesh = mesh_from_blocks(np.concatenate(coords), np.concatenate(blocks), origin=m.origin,
                            voxel_size=m.voxel_size, truncation=m.truncation)
    def write_mesh(tmp: Path) -> bool:
        if not o3d.io.write_triangle_mesh(str(tmp), mesh):
            return False
        # open3d reports success even when the disk filled up under it (a truncated file): read it back
        back = o3d.io.read_triangle_mesh(str(tmp))
        return len(back.vertices) == len(mesh.vertices) and len(back.triangles) == len(mesh.triangles)

    existed = output.exists()
    if not _write_output(output, output.with_name(f".tmp-{output.name}"), write_mesh):
        if output.suffix.lower() not in (".ply", ".obj", ".stl", ".off", ".gltf", ".glb"):
            _fail(f"could not write {output}: unsupported extension; use .ply, .obj or .stl")
        # open3d reports only failure, not why: with a known format it is the file system
        raise WriteFailedError(f"could not finish writing {output}: open3d could not write the file (is the disk "
                               f"full or the directory not writable?); "
                               f"{'the file there is unchanged' if existed else 'nothing was written there'} and "
                               "no temporary file is left. What to do: free space or fix the directory's "
                               "permissions, or write elsewhere", None, None, str(output))
    summary = {"output": str(output), "vertices": len(mesh.vertices), "triangles": len(mesh.triangles)}
    _report(summary, as_json, lambda: (
        f"wrote {output}: {summary['vertices']} vertices, {summary['triangles']} triangles"))


@app.command("search")
@_cli
def search_cmd(
    map_path: str = typer.Argument(..., metavar="MAP", help="Map path or URL."),
    query: str = typer.Option("floor", "--query", help="floor, ceiling, wall, edge, corner, pole, like:X,Y,Z[;X,Y,Z] (blocks like these), or a saved query (.npz)."),
    level: Optional[int] = typer.Option(None, "--level", help="Match only the first K code elements."),
    threshold: Optional[float] = typer.Option(None, "--threshold", help="Select blocks scoring at most this."),
    top: Optional[int] = typer.Option(None, "--top", help="Select the K best-scoring blocks."),
    behind: Optional[str] = typer.Option(None, "--behind", help="solid (exact SDF) or unobserved (fused); default: what the map records."),
    up: Optional[str] = typer.Option(None, "--up", help="Up direction x,y,z in the map's grid; default: the map's header, else 0,0,1."),
    tilt: Optional[float] = typer.Option(None, "--tilt", help="Also match surfaces tilted up to DEG degrees from level."),
    out_dir: Optional[Path] = typer.Option(None, "--out", help="Write the picture (and mesh of the selection) here."),
    device: Optional[str] = typer.Option(None, "--device", help="Torch device for scoring (default: cuda if present)."),
    no_mesh: bool = typer.Option(False, "--no-mesh", help="Do not write the mesh of the expanded blocks."),
    overwrite: bool = typer.Option(False, "--overwrite"),
    as_json: bool = typer.Option(False, "--json", help="Print every selected block's coordinates and score."),
) -> None:
    """Search a compressed map in code space and decompress only the blocks that match (the paper's Fig. 7)."""
    from .search_cli import format_summary, search_command

    summary = search_command(map_path, query, level, threshold, top, out_dir, as_json, device, mesh=not no_mesh,
                             overwrite=overwrite, behind=behind, up=up, tilt=tilt)
    _report(summary, as_json, lambda: format_summary(summary))


@app.command("verify")
@_cli
def verify_cmd(
    map_path: str = typer.Argument(..., metavar="MAP", help="Map path or URL."),
    as_json: bool = typer.Option(False, "--json", help="Machine-readable report."),
) -> None:
    """Check a map: header, every chunk's checksum, codec state digest, states against codes, and a decode."""
    from .verify import verify_command

    raise typer.Exit(verify_command(map_path, as_json))


@app.command("track")
@_cli
def track_cmd(
    map_path: str = typer.Argument(..., metavar="MAP", help="Map path or URL."),
    sequence: str = typer.Argument(..., metavar="SEQUENCE", help="TUM RGB-D or 7-Scenes directory."),
    output: Path = typer.Option(..., "-o", "--output", help="TUM-format trajectory to write."),
    level: Optional[int] = typer.Option(None, "--level", help="Decode only the first K code elements."),
    device: Optional[str] = typer.Option(None, "--device", help="Torch device."),
    cache_mb: float = typer.Option(256.0, "--cache-mb", help="Decoded-block cache bound (MiB)."),
    dense: bool = typer.Option(False, "--dense", help="Decode the whole map first instead of on demand."),
    start: str = typer.Option("groundtruth", "--start", help="Start pose: groundtruth (the paper) or identity."),
    frames: Optional[int] = typer.Option(None, "--frames", help="Track only the first N frames."),
    stride: int = typer.Option(1, "--stride", help="Use every K-th frame."),
    as_json: bool = typer.Option(False, "--json"),
) -> None:
    """Track a depth sequence against a (compressed) map from the ground-truth start pose; write TUM poses."""
    from .evaluation import track_command

    summary = track_command(map_path, sequence, output, level=level, device=device, cache_mb=cache_mb, dense=dense,
                            start=start, frames=frames, stride=stride, progress=not as_json)
    _report(summary, as_json, lambda: f"wrote {output}: " + ", ".join(
        f"{k} {v:.4g}" if isinstance(v, float) else f"{k} {v}" for k, v in summary.items()
        if not isinstance(v, (dict, list))))


@app.command("eval")
@_cli
def eval_cmd(
    sequences: list[str] = typer.Argument(..., metavar="SEQUENCE...",
                                          help="synthetic:PRESET (e.g. synthetic:fast-noisy) or a sequence folder."),
    out_dir: Path = typer.Option(Path("eval-out"), "-o", "--out", help="Results JSON, table and pictures go here."),
    methods: Optional[str] = typer.Option(None, "--methods", help="Comma-separated (default: all of Table 1)."),
    frames: int = typer.Option(60, "--frames", help="Frames per sequence (0: all)."),
    stride: int = typer.Option(1, "--stride", help="Use every K-th frame."),
    size: str = typer.Option("320x240", "--size", help="Image size of rendered synthetic sequences, WxH."),
    voxel_size: float = typer.Option(0.02, "--voxel-size"),
    docs_dir: Optional[Path] = typer.Option(None, "--docs", help="Also write eval.md/eval.json/eval/ here."),
    model: list[str] = typer.Option([], "--model", metavar="KEY=FILE",
                                    help="Model file for a row, e.g. ae-32=ae-32.npz (repeatable)."),
    as_json: bool = typer.Option(False, "--json"),
) -> None:
    """Reproduce the paper's Table 1: reconstruction error and tracking ATE per compression method."""
    from .evaluation import eval_command, markdown_table

    if any("=" not in m for m in model):
        _fail(f"--model must look like ae-32=ae-32.npz, got {[m for m in model if '=' not in m]}")
    models = dict(m.split("=", 1) for m in model)

    try:
        wh = tuple(int(v) for v in size.lower().split("x"))
        assert len(wh) == 2
    except (ValueError, AssertionError):
        _fail(f"--size must look like 320x240, got {size!r}")
    results = eval_command(sequences, out_dir, methods=methods.split(",") if methods else None,
                           frames=frames or None, stride=stride, size=wh, voxel_size=voxel_size, docs_dir=docs_dir,
                           progress=not as_json, log=None if as_json else (lambda s_: err.print(s_, highlight=False)),
                           models=models)
    _report(results, as_json, lambda: markdown_table(results))


@app.command("dataset")
@_cli
def dataset_cmd(
    output: Path = typer.Argument(..., metavar="OUTPUT", help="Data set to write (a Zarr directory)."),
    synthetic: int = typer.Option(0, "--synthetic", help="Number of synthetic primitive blocks."),
    sequence: list[str] = typer.Option([], "--sequence", help="RGB-D sequence (TUM or 7-Scenes) to fuse and sample."),
    map_paths: list[str] = typer.Option([], "--map", help="Map to decode and sample."),
    volume: list[Path] = typer.Option([], "--volume", help="Dense .npy TSDF (metres) to sample."),
    voxel_size: float = typer.Option(0.02, "--voxel-size", help="Voxel edge (synthetic blocks, fusion)."),
    truncation: str = typer.Option("-0.04,0.1", "--truncation", help="d_min,d_max in metres."),
    stride: int = typer.Option(8, "--stride", help="Sub-volume stride in voxels (the paper: 8)."),
    max_mean: float = typer.Option(0.85, "--max-mean", help="Drop windows whose normalised mean is above this."),
    empty_fraction: float = typer.Option(0.02, "--empty-fraction", help="Share of dropped windows kept anyway."),
    batch_size: int = typer.Option(500, "--batch-size", help="Blocks per batch (the paper: 500)."),
    seed: int = typer.Option(0, "--seed"),
    overwrite: bool = typer.Option(False, "--overwrite"),
    as_json: bool = typer.Option(False, "--json"),
) -> None:
    """Build a training data set: synthetic blocks plus sub-volumes of real maps, split 300:50:50 by batches."""
    from .data.sampler import iter_windows
    from .data.synthetic import synthetic_blocks
    from .dataset import build_dataset
    from .map import open_map

    trunc = _pair(truncation, "--truncation")
    window_kw = dict(stride=stride, truncation=trunc, max_mean=max_mean, empty_fraction=empty_fraction, seed=seed)

    def synth(n: int):
        for i in range(0, n, 10_000):  # chunks of 10k keep memory flat and the bar moving
            yield synthetic_blocks(min(10_000, n - i), seed=seed + i, voxel_size=voxel_size, truncation=trunc)

    def fused(path: str):
        from .fusion import fuse

        yield from iter_windows(fuse(path, voxel_size=voxel_size, truncation=trunc, quiet=True).to_dense(),
                                **window_kw)

    sources = ([("synthetic", synth(synthetic))] if synthetic else []) \
        + [(f"sequence:{p}", fused(p)) for p in sequence] \
        + [(f"map:{p}", iter_windows(open_map(p).decode_region(), **window_kw)) for p in map_paths] \
        + [(f"volume:{p}", iter_windows(np.load(p, mmap_mode="r", allow_pickle=False), **window_kw)) for p in volume]
    if not sources:
        _fail("give at least one source: --synthetic N, --sequence PATH, --map MAP or --volume X.npy")
    with _progress() as prog:
        task = prog.add_task("collecting blocks", total=None, rate="")
        ds = build_dataset(output, sources, batch_size=batch_size, seed=seed, voxel_size=voxel_size,
                           truncation=trunc, overwrite=overwrite, progress=lambda n: prog.advance(task, n))
    if as_json:
        _print_json(ds.meta)
    else:
        out.print(f"wrote {output}: {ds.meta['splits']} blocks from {ds.meta['sources']}")


@app.command("train")
@_cli
def train_cmd(
    dataset: Path = typer.Argument(..., metavar="DATASET", help="Data set from `sdfcodec dataset`."),
    output: Path = typer.Option(..., "-o", "--output", help="Model file to write (.npz)."),
    codec_id: str = typer.Option("pca", "--codec", help="Codec id."),
    code_size: Optional[int] = typer.Option(None, "--code-size", help="Code length."),
    max_memory_gb: float = typer.Option(4.0, "--max-memory-gb",
                                        help="Train in memory below this; stream the data set above it."),
    overwrite: bool = typer.Option(False, "--overwrite"),
    as_json: bool = typer.Option(False, "--json"),
) -> None:
    """Train a codec on a data set and save it as a model (.npz of plain arrays); report validation/test error."""
    from .dataset import open_dataset
    from .model import save_model
    from .registry import get_codec

    _refuse_existing(output, overwrite)
    ds = open_dataset(dataset)
    codec = get_codec(codec_id, **({"code_size": code_size} if code_size else {}))
    n = ds.split("train").shape[0]
    t0 = time.perf_counter()
    with _progress() as prog:
        if n * 4096 * 4 <= max_memory_gb * 2**30:
            prog.add_task(f"fitting {codec!r} on {n} blocks (in memory)", total=None, rate="")
            codec.fit(ds.load("train"))
        else:
            task = prog.add_task(f"fitting {codec!r} on {n} blocks (streamed)", total=n, rate="")

            def batches():
                for b in ds.iter_batches("train"):
                    prog.advance(task, len(b))
                    yield b

            codec.fit_stream(batches())
    seconds = time.perf_counter() - t0
    save_model(codec, output)
    report: dict[str, Any] = {"model": str(output), "codec": codec.get_config(), "train_blocks": n,
                              "fit_seconds": seconds}
    for split in ("validation", "test"):
        sq, count = 0.0, 0
        for b in ds.iter_batches(split):
            err2 = (codec.decode(codec.encode(b)) - b) ** 2
            sq += float(err2.sum(dtype=np.float64))
            count += len(b)
        report[split] = {"blocks": count, "mse_voxel": sq / (count * 4096), "sse_block": sq / count}
    _report(report, as_json, lambda: (
        f"wrote {output} ({codec!r}, {n} blocks, {seconds:.1f} s): validation MSE/voxel "
        f"{report['validation']['mse_voxel']:.3e}, test {report['test']['mse_voxel']:.3e}"))


@app.command("bench")
@_cli
def bench_cmd(
    codec_id: str = typer.Option("pca", "--codec", help="Codec to measure."),
    sizes: str = typer.Option("32,64,128", "--sizes", help="Code sizes."),
    batches: Optional[str] = typer.Option(None, "--batches", help="Batch sizes (default 1..65536 by x4)."),
    device: str = typer.Option("cpu", "--device", help="Torch device."),
    quick: bool = typer.Option(False, "--quick", help="Fewer, shorter measurements (under 30 s)."),
    read: Optional[int] = typer.Option(None, "--read", help="Blocks in the map timed for decode-on-read "
                                       "(default 65536, --quick 8192; 0: skip)."),
    http: bool = typer.Option(True, "--http/--no-http", help="Also time decode-on-read over HTTP (loopback)."),
    search: bool = typer.Option(True, "--search/--no-search", help="Also time the descriptor search kernel "
                                "(pca only: search scores pca codes)."),
    as_json: bool = typer.Option(False, "--json", help="Print records as JSON."),
) -> None:
    """Encode/decode throughput (blocks/s) beside numpy matrix products of the codec's shapes, same run.

    Decode-on-read times a whole map read and decoded to float32 metres by Map.iter_decoded, from local disk
    and over HTTP from a server on loopback, beside the same roofline, the memory-copy bandwidth of this
    machine (as blocks/s of 16 KiB) and the codec's decode of the same codes in memory (JSON:
    memcpy_blocks_per_s, in_memory_decode_blocks_per_s). For pca, the search kernel (15 floor descriptors)
    is timed beside a numpy product of its shape. Tracking is benchmarked by `sdfcodec eval` instead (it needs
    a sequence and a map of it). Every record has speedup_vs_paper (405 and 645 us/block over ours).

    The baseline is the codec's "roofline": one (B,4096)x(4096,k) product for a linear codec (pca), or the
    layer shapes a codec declares (ae, parallel, sequential; see sdfcodec.bench). Those are timed with the
    shipped weights where they exist (ae-64, parallel/sequential 64+64), else untrained ones; for the
    mixtures --sizes is the size of each part (64: code 64+64+1).
    """
    from .bench import PAPER_US_PER_BLOCK, bench_codec, vs_paper
    from .codec import uses_weights
    from .registry import get_codec_class

    ks = [int(s) for s in sizes.split(",")]
    bs = [int(b) for b in batches.split(",")] if batches else ([1, 64, 4096] if quick else
                                                               [1, 16, 256, 1024, 4096, 16384, 65536])
    n_read = (8192 if quick else 65536) if read is None else read
    if n_read < 0:
        _fail(f"--read must be >= 0, got {n_read}")
    do_search = search and codec_id == "pca"
    n_search = 8192 if quick else 65536
    with _progress() as prog:
        task = prog.add_task("bench", total=len(ks) * (len(bs) * (2 + uses_weights(get_codec_class(codec_id))) + (n_read > 0) + do_search), rate="")
        step = lambda s: prog.update(task, advance=1, description=s)  # noqa: E731
        records = bench_codec(codec_id, ks, bs, device=device, min_time=0.05 if quick else 0.2, progress=step,
                              read_blocks=n_read, http=http)
        if do_search:
            from .bench import bench_search

            found = bench_search([k for k in ks if 1 <= k <= 128], batches=[n_search], device=device,
                                 min_time=0.05 if quick else 0.2, progress=step)
            records += [dict(r, **vs_paper(r["us_per_block"])) for r in found]  # the same paper comparison
    if as_json:
        _print_json(records)
        return
    layered = any("roofline_shapes" in r for r in records)  # codecs with benchmark hooks (sdfcodec.bench)
    if layered:
        lines: dict[tuple, str] = {}
        for r in records:
            if "roofline_shapes" not in r:
                continue
            lines.setdefault((r["code_size"], r["operation"]), f"code {r['code_size']} {r['operation']}: " + " + ".join(
                f"(B,{m})x({m},{n})" for m, n in r["roofline_shapes"]))
            if "weights" in r:  # registered codecs: where the timed weights come from
                lines.setdefault((r["code_size"], "weights"), f"code {r['code_size']} weights: {r['weights']}")
        table = Table(title=f"{codec_id} throughput on {device} (baseline: numpy matmuls of the codec's layer "
                            "shapes, same run)", caption="\n".join(lines.values()), caption_justify="left")
    else:
        table = Table(title=f"{codec_id} throughput on {device} (baseline: numpy matmul of the same shape, same run)")
    reads = [f"{r['operation']} code {r['code_size']}: memory-copy roofline {r['memcpy_blocks_per_s']:,.0f} "
             f"blocks/s (ratio {r['ratio_to_memcpy']:.2f}), in-memory decode {r['in_memory_decode_blocks_per_s']:,.0f} "
             f"blocks/s (ratio {r['ratio_to_in_memory_decode']:.2f})" for r in records if "memcpy_blocks_per_s" in r]
    if reads:
        table.caption = "\n".join(([table.caption] if table.caption else []) + reads)
        table.caption_justify = "left"
    rows = [(str(r["code_size"]), r["operation"], str(r["batch"]), f"{r['blocks_per_s']:,.0f}",
             f"{r['baseline_blocks_per_s']:,.0f}", f"{r['ratio_to_baseline']:.2f}", f"{r['us_per_block']:.2f}",
             f"{PAPER_US_PER_BLOCK[0] / r['us_per_block']:,.0f}x") for r in records]
    for i, col in enumerate(("code", "op", "batch", "blocks/s", "baseline blocks/s", "ratio", "us/block", "vs paper")):
        # as wide as the widest figure: a figure is never cut, whatever the terminal
        table.add_column(col, justify="right", min_width=max(*(len(w) for w in col.split()), *(len(r[i]) for r in rows)))
    for row in rows:
        table.add_row(*row)
    out.print(table, width=max(out.width, 120), crop=False)  # ~120 columns wide: never truncate figures


@app.command("demo")
@_cli
def demo_cmd(
    out_dir: Path = typer.Option(Path("demo-out"), "--out", help="Directory for the maps, pictures and report.md."),
    voxel_size: float = typer.Option(0.02, "--voxel-size", help="Voxel edge in metres."),
    frames: int = typer.Option(120, "--frames", min=2, help="Frames to render and fuse."),
    track_frames: int = typer.Option(60, "--track-frames", min=2, help="Frames to track (every --track-stride-th)."),
    track_stride: int = typer.Option(2, "--track-stride", min=1, help="Track every N-th rendered frame."),
    ae: bool = typer.Option(True, "--ae/--no-ae", help="Also encode with the shipped AE-64 when installed."),
    as_json: bool = typer.Option(False, "--json", help="Print the results (results.json) as JSON."),
) -> None:
    """Render, fuse, compress, search and track a synthetic room; write OUT/report.md with tables and pictures.

    Built-in data only, nothing downloaded. Encodes with the shipped eigenshapes at 32/64/128 (and the shipped
    AE-64 when its plugin is installed), measures every map's surfaces against the original, searches the
    pca-64 map for floors and expands only them, and tracks the sequence against every map (pca-64 on demand).
    """
    from .demo import run_demo

    t0 = time.perf_counter()
    summary = run_demo(out_dir, voxel_size=voxel_size, frames=frames, track_frames=track_frames,
                       track_stride=track_stride, ae=ae, console=err)
    if as_json:
        _print_json(summary)
        return
    out.print(f"report: {out_dir / 'report.md'} ({time.perf_counter() - t0:.0f} s)")


@app.command("compare")
@_cli
def compare_cmd(original: str = typer.Argument(..., metavar="ORIGINAL", help="The original (lossless) map."),
                decoded: str = typer.Argument(..., metavar="DECODED", help="The map to judge, on the same grid."),
                level: Optional[int] = typer.Option(None, "--level", help="Decode DECODED at this prefix level."),
                as_json: bool = typer.Option(False, "--json", help="Machine-readable output (metres).")) -> None:
    """Surface fidelity of DECODED against ORIGINAL: Chamfer-L1, F-score, near-surface error (docs/surface.md)."""
    from .surface import compare_command, metrics_table

    summary = compare_command(original, decoded, level=level, quiet=as_json)
    _report(summary, as_json, lambda: metrics_table(summary))


def main() -> None:
    app()


if __name__ == "__main__":
    main()
