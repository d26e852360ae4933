"""The ``sdfcodec view`` command: a Rerun recording of a map, a search of it and a trajectory in it."""

from __future__ import annotations

import errno
from pathlib import Path
from typing import Any, Optional

import typer

from .common import app, cli, err, refuse_existing, report, write_output

__all__: list[str] = []  # the command registers on the app; nothing to import from here


# the docstring is the help, read as rich markup: a backslash before "[view]" keeps the extra's name from
# reading as a style tag
@app.command("view")
@cli
def view_cmd(
    map_path: str = typer.Argument(..., metavar="MAP", help="Map path or URL."),
    output: Path = typer.Option(..., "-o", "--output", help="Recording to write (.rrd); open it with `rerun FILE.rrd`."),
    query: Optional[str] = typer.Option(None, "--query", help="Also search the codes (floor, wall, ..., like:X,Y,Z, or a saved query .npz): every block's score as a colour, the selected blocks as boxes."),
    level: Optional[int] = typer.Option(None, "--level", help="Search and mesh with the first K code elements."),
    threshold: Optional[float] = typer.Option(None, "--threshold", help="Select blocks scoring at most this (default: the automatic threshold)."),
    top: Optional[int] = typer.Option(None, "--top", help="Select the K best-scoring blocks."),
    trajectory: Optional[Path] = typer.Option(None, "--trajectory", help="Camera trajectory (TUM file) in the map's frame."),
    groundtruth: Optional[Path] = typer.Option(None, "--groundtruth", help="Ground-truth trajectory to draw the trajectory against, with its ATE: a TUM file, or a sequence directory (7-Scenes pose files, TUM groundtruth.txt)."),
    device: Optional[str] = typer.Option(None, "--device", help="Torch device for the search (default: cuda if present)."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace OUTPUT if it exists."),
    as_json: bool = typer.Option(False, "--json", help="Print a JSON summary."),
) -> None:
    """Write a Rerun recording (.rrd) of a map: its mesh, with --query the code-space search scores as colours and
    the selected blocks, with --trajectory the camera path (against --groundtruth). Positions in metres, the
    map's up (its header's, else +z) shown up. Needs rerun-sdk: pip install 'sdfcodec\\[view]'."""
    from ..errors import InputNotFoundError, InvalidValueError, MissingDependencyError
    from ..view.recording import require_rerun, write_recording

    try:
        require_rerun()
    except MissingDependencyError as e:
        # printed without rich markup: the shared error printer would read "[view]" in the advice as a style tag
        err.print(f"error: {e}", markup=False, highlight=False, soft_wrap=True)
        raise typer.Exit(1)

    if output.suffix != ".rrd":
        raise InvalidValueError(f"the recording must end in .rrd (the viewer opens it by its suffix), got {output}")
    if groundtruth is not None and trajectory is None:
        raise InvalidValueError("--groundtruth needs --trajectory: the ground truth is drawn against a trajectory")
    for p in (trajectory, groundtruth):
        if p is not None and not p.is_file() and not (p is groundtruth and p.is_dir()):
            raise InputNotFoundError(errno.ENOENT, "no such trajectory file", str(p))
    gt_source: Any = groundtruth
    if groundtruth is not None and groundtruth.is_dir():  # a sequence: its own poses (7-Scenes has no TUM file)
        from ..data.sequences import open_sequence

        gt_source = open_sequence(groundtruth).trajectory
        if gt_source is None:
            raise InvalidValueError(f"{groundtruth} has no ground-truth poses")
    refuse_existing(output, overwrite)
    summary: dict = {}

    def write(tmp: Path) -> bool:
        summary.update(write_recording(map_path, tmp, query=query, level=level,
                                       threshold=threshold if threshold is not None else ("auto" if top is None else None),
                                       top=top, trajectory=trajectory, groundtruth=gt_source, device=device))
        return True

    write_output(output, write, "writing the recording")
    summary["output"] = str(output)
    report(summary, as_json, lambda: _line(summary))


def _line(s: dict) -> str:
    parts = [f"wrote {s['output']}: mesh {s['mesh']['vertices']} vertices"]
    if "search" in s:
        parts.append(f"{s['search']['query']} search {s['search']['selected']} of {s['search']['scored']} blocks selected")
    if "trajectory" in s:
        t = s["trajectory"]
        parts.append(f"trajectory {t['poses']} poses" + (f", ATE RMSE {1000 * t['ate_rmse']:.1f} mm against "
                                                          f"{t['groundtruth_poses']} ground-truth poses"
                                                          if "ate_rmse" in t else ""))
    return "; ".join(parts) + f"; open it with: rerun {s['output']}"
