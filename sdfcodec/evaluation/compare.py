"""The work of ``sdfcodec compare ORIGINAL DECODED``: open two maps (or a volume file and a map), compare their
surfaces with :mod:`sdfcodec.core.surface`, and the rows, title and sentence the command prints
(docs/surface.md)."""

from __future__ import annotations

from typing import Any

from ..core.surface import compare_maps, compare_volume_map
from ..map import open_map

__all__ = ["compare_command", "metrics_table", "metrics_rows", "metrics_title", "metrics_sentence", "level_text"]


def compare_command(original: str, decoded: str, *, level: int | None = None, quiet: bool = False,
                    volume: tuple[Any, dict[str, Any]] | None = None) -> dict[str, Any]:
    """The work of ``sdfcodec compare ORIGINAL DECODED``: open both maps, compare them (a progress bar on
    stderr unless ``quiet``) and return the JSON summary: the metrics of :meth:`SurfaceMetrics.to_dict`
    (metres) plus ``original``, ``decoded``, ``level``, ``voxel_size``. ``volume``: ``(array, meta)`` when
    ORIGINAL is a dense volume file (loaded by the caller), compared by :func:`compare_volume_map`."""
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    if volume is not None:
        with open_map(decoded) as b:
            metrics = compare_volume_map(volume[0], b, level=level, meta=volume[1])
            return {"original": str(original), "decoded": str(decoded), "level": level or b.code_size,
                    "code_size": b.code_size, "voxel_size": b.voxel_size, **metrics.to_dict()}
    a = open_map(original)
    try:
        b = open_map(decoded)
    except BaseException:
        a.close()
        raise
    try:
        with Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                      console=Console(stderr=True), transient=True, disable=quiet) as prog:
            task = prog.add_task("comparing (x-layers)", total=int(a.shape_voxels[0]))
            metrics = compare_maps(a, b, level=level, progress=lambda n: prog.advance(task, n))
        summary = {"original": str(original), "decoded": str(decoded), "level": level or b.code_size,
                   "code_size": b.code_size, "voxel_size": a.voxel_size}
    finally:
        a.close()
        b.close()
    return {**summary, **metrics.to_dict()}


def metrics_table(summary: dict[str, Any]) -> Any:
    """A rich Table of a :func:`compare_command` summary (distances in mm, F-scores in [0, 1])."""
    from rich.table import Table

    t = Table(title=metrics_title(summary))
    t.add_column("metric")
    t.add_column("value", justify="right")
    for name, value in metrics_rows(summary):
        t.add_row(name, value)
    return t


def level_text(level: int, code_size: int | None) -> str:
    """The words for the level a map was decoded at: ``level 32 of 64`` for a prefix, ``full level`` for all of
    its ``code_size`` elements (a field codec's 4,096 "elements" are its voxels, not a level anyone chose)."""
    return "full level" if code_size is not None and level >= code_size else \
        f"level {level}" + (f" of {code_size}" if code_size is not None else "")


def metrics_title(summary: dict[str, Any]) -> str:
    """What a :func:`compare_command` summary compares: ``DECODED (level K of N) against ORIGINAL``."""
    return (f"{summary['decoded']} ({level_text(summary['level'], summary.get('code_size'))}) against "
            f"{summary['original']}")


def metrics_sentence(summary: dict[str, Any]) -> str:
    """The headline figures of a :func:`compare_command` summary in one sentence (mm)."""
    rows = dict(metrics_rows(summary))
    vs_mm = 1000 * summary["voxel_size"]
    return (f"{metrics_title(summary)}: Chamfer-L1 {rows['Chamfer-L1 (mm)']} mm, F-score "
            f"{rows[f'F-score @ 1 voxel ({vs_mm:g} mm)']} at 1 voxel, near-surface RMSE "
            f"{rows['near-surface RMSE (mm)']} mm")


def metrics_rows(summary: dict[str, Any]) -> list[tuple[str, str]]:
    """``(metric, value)`` rows of a :func:`compare_command` summary (distances in mm, F-scores in [0, 1])."""
    def mm(v: float | None) -> str:  # None: a band statistic of an empty band
        return "n/a" if v is None else f"{1000 * v:.3f}"

    def frac(v: float | None) -> str:
        return "n/a" if v is None else f"{v:.4f}"

    vs_mm = 1000 * summary["voxel_size"]
    chamfer = summary["chamfer_l1"]
    rows = [("Chamfer-L1 (mm)", "inf" if chamfer is None else f"{1000 * chamfer:.3f}"),
            (f"F-score @ 1 voxel ({vs_mm:g} mm)", frac(summary["f_score_1"])),
            (f"F-score @ 2 voxels ({2 * vs_mm:g} mm)", frac(summary["f_score_2"])),
            ("sign agreement (band)", frac(summary["sign_agreement"])),
            ("near-surface RMSE (mm)", mm(summary["near_surface_rmse"])),
            ("near-surface bias (mm)", mm(summary["near_surface_bias"])),
            ("surface points (original)", str(summary["n_original"])),
            ("surface points (decoded)", str(summary["n_decoded"])),
            ("band voxels", str(summary["n_band"]))]
    return rows
