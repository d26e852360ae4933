"""The commands that bring other systems' maps and trajectories in and out: import, export, trajectory."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from ..errors import InvalidValueError
from .common import (app, check_code_size, cli, heartbeat, parse_region, parse_truncation, refuse_existing, report,
                     write_output)

__all__: list[str] = []  # commands register on the app; nothing to import from here


@app.command("import")
@cli
def import_cmd(
    source: Path = typer.Argument(..., metavar="SRC", help="voxblox TSDF layer (.voxblox, .vxblx, .tsdf) or Open3D VoxelBlockGrid (.npz of VoxelBlockGrid.save)."),
    output: Path = typer.Argument(..., metavar="OUT.sdfz", help="Map to write."),
    format: Optional[str] = typer.Option(None, "--format", help="voxblox or open3d (default: detected from the content)."),
    codec_id: str = typer.Option("raw", "--codec", help="Codec of the map: raw (lossless, the default), pca (the shipped eigenshapes), or another fitted one."),
    code_size: Optional[int] = typer.Option(None, "--code-size", help="Code length of --codec pca (default 64)."),
    model: Optional[Path] = typer.Option(None, "--model", help="Trained codec (.npz from `sdfcodec train`) instead of --codec."),
    code_dtype: str = typer.Option("float32", "--code-dtype", help="float32, float16 or int8 code storage."),
    truncation: Optional[str] = typer.Option(None, "--truncation", help="d_min,d_max metres of the map (default: from the data, so that nothing is clipped)."),
    trunc_voxel_multiplier: float = typer.Option(8.0, "--trunc-voxel-multiplier", help="Open3D only: its truncation in voxels (integrate's default 8); its tsdf is distance / (this x voxel size)."),
    max_error: Optional[float] = typer.Option(None, "--max-error", help="Block codecs (pca, ae...): a residual stage, every observed voxel within E metres at full level (as encode)."),
    sign_exact: bool = typer.Option(False, "--sign-exact", help="Block codecs: every voxel at a surface crossing keeps its sign (as encode)."),
    chunk_blocks: Optional[int] = typer.Option(None, "--chunk-blocks", help="Blocks per axis of a chunk of codes (as encode)."),
    shard_blocks: Optional[int] = typer.Option(None, "--shard-blocks", help="Zarr shards of N blocks per axis (as encode)."),
    keep_weights: bool = typer.Option(False, "--keep-weights", help="With a lossy --codec: keep the fusion weights "
                                      "(uint8 counts; a lossy map drops them by default, its observation mask kept)."),
    exact: Optional[bool] = typer.Option(None, "--exact/--no-exact", help="Store the voxels' own float32 metres and float32 weights, read back bit for bit (the default with the raw codec); --no-exact writes the normalised raw map readers before the extension metric-codes open (distances to (d_max - d_min) x 2^-24 m, weights float16)."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace OUT.sdfz if it exists."),
    as_json: bool = typer.Option(False, "--json", help="Print a JSON summary."),
) -> None:
    """Import a voxblox TSDF layer or an Open3D VoxelBlockGrid into a map, streamed (bounded memory).

    Lossless by default: raw codec, every observed voxel's distance and weight bit for bit (voxblox's float32
    metres; Open3D's float32(tsdf x trunc_voxel_multiplier x voxel size)), the data's own truncation, weight 0 =
    unobserved; every voxel lands on the map's grid at its own world position. For a codec that must be fitted,
    or a rate target, transcode the lossless map afterwards with `sdfcodec encode MAP OUT --codec ...` (every
    encode option).
    docs/how-to/import-voxblox.md, import-open3d.md."""
    trunc = parse_truncation(truncation) if truncation else None
    if code_size is not None and model is None:
        code_size = check_code_size(codec_id, code_size)
    refuse_existing(output, overwrite, map_output=True)
    from ..interop.importer import import_map
    from ..model import load_model
    from ..fusion.online import fusion_codec

    codec = load_model(model) if model is not None else fusion_codec(codec_id, code_size)
    with heartbeat(f"importing {source}", as_json):
        summary = import_map(source, output, format=format, codec=codec, truncation=trunc,
                             trunc_voxel_multiplier=trunc_voxel_multiplier, code_dtype=code_dtype,
                             overwrite=overwrite, max_error=max_error, sign_exact=sign_exact,
                             chunk_blocks=chunk_blocks, shard_blocks=shard_blocks,
                             keep_weights=True if keep_weights else None, exact=exact)
    report(summary, as_json, lambda: (
        f"wrote {output}: {summary['format']} {summary['source_blocks']} blocks of {summary['voxels_per_side']}^3 "
        f"voxels ({summary['observed_voxels']} observed) into {summary['blocks']['coded']} coded blocks, voxel "
        f"{summary['voxel_size']:.6g} m, truncation [{summary['truncation'][0]:.6g}, {summary['truncation'][1]:.6g}] m"
        f", codec {summary['codec']['id']}{' (exact metres)' if summary['exact'] else ''} ({summary['seconds']:.1f} s)"))


@app.command("export")
@cli
def export_cmd(
    map_path: str = typer.Argument(..., metavar="MAP", help="Map path or URL."),
    output: Path = typer.Argument(..., metavar="OUT", help="File to write (.voxblox for voxblox, .npz for open3d)."),
    format: Optional[str] = typer.Option(None, "--format", help="voxblox (a TSDF layer voxblox's load_map reads) or open3d (VoxelBlockGrid.load); default: told by OUT's name (.voxblox, .vxblx, .tsdf or .npz)."),
    region: Optional[str] = typer.Option(None, "--region", help="x0:x1,y0:y1,z0:z1 (half-open voxels, or metres with --units m)."),
    units: str = typer.Option("voxels", "--units", help="Units of --region: voxels or m."),
    level: Optional[int] = typer.Option(None, "--level", help="Decode only the first K code elements."),
    voxels_per_side: int = typer.Option(16, "--voxels-per-side", help="Block size of the output (voxblox voxels_per_side, Open3D block_resolution): 1, 2, 4, 8 or 16."),
    trunc_voxel_multiplier: float = typer.Option(8.0, "--trunc-voxel-multiplier", help="open3d only: tsdf = distance / (this x voxel size)."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace OUT if it exists."),
    as_json: bool = typer.Option(False, "--json", help="Print a JSON summary."),
) -> None:
    """Decode a map (or a region) to a voxblox TSDF layer or an Open3D VoxelBlockGrid .npz.

    Voxels not observed, or outside --region, are written with weight 0 (voxblox and Open3D: unobserved)."""
    box = parse_region(region)
    refuse_existing(output, overwrite)
    from ..interop.importer import export_format, export_map

    format = export_format(output) if format is None else format  # told by OUT's name, not the temporary's

    def write(tmp: Path) -> bool:
        summary.update(export_map(map_path, tmp, format=format, region=box, units=units, level=level,
                                  voxels_per_side=voxels_per_side, trunc_voxel_multiplier=trunc_voxel_multiplier,
                                  overwrite=True))
        return True

    summary: dict = {}
    with heartbeat(f"exporting {map_path}", as_json):
        write_output(output, write, "exporting the map")
    summary["output"] = str(output)
    moved = any(abs(s) > 0 for s in summary["shift"])
    report(summary, as_json, lambda: (
        f"wrote {output}: {format} layer of {summary['blocks']} blocks of {summary['voxels_per_side']}^3 voxels "
        f"({summary['observed_voxels']} observed)"
        + (f"; voxels moved by {tuple(round(s, 9) for s in summary['shift'])} m onto {format}'s lattice" if moved
           else "")))


@app.command("trajectory")
@cli
def trajectory_cmd(
    sequence: Path = typer.Argument(..., metavar="SEQUENCE", help="TUM RGB-D or 7-Scenes directory."),
    output: Path = typer.Option(..., "-o", "--output", help="TUM trajectory file to write (e.g. gt.txt)."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace OUTPUT if it exists."),
    as_json: bool = typer.Option(False, "--json", help="Print a JSON summary."),
) -> None:
    """Write a sequence's ground-truth poses as a TUM trajectory file (7-Scenes: its per-frame pose files, frame i
    at i/30 s, the times `track` gives its frames), for `view --groundtruth` and `evo`."""
    refuse_existing(output, overwrite)
    from ..data.sequences import open_sequence
    from ..core.trajectory import write_tum

    seq = open_sequence(sequence)
    if seq.trajectory is None or not len(seq.trajectory):
        raise InvalidValueError(f"{sequence} has no ground-truth poses to write")
    traj = seq.trajectory

    def write(tmp: Path) -> bool:
        write_tum(tmp, traj, header=f"ground truth of {sequence} ({seq.layout})")
        return True

    write_output(output, write, "writing the trajectory")
    summary = {"output": str(output), "poses": len(traj), "layout": seq.layout}
    report(summary, as_json, lambda: f"wrote {output}: {len(traj)} poses of {sequence} ({seq.layout})")
