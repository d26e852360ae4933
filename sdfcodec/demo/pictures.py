"""The demo report's pictures (``sdfcodec demo``): meshes of maps, a field slice per map, error against bytes,
trajectories against ground truth. The floor-search picture is :func:`sdfcodec.view.search.search_picture`.

Every picture carries what it shows in its title, and spatial axes or a scale bar in metres.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["mesh_figure", "slice_picture", "error_bytes_picture", "trajectory_picture", "STYLES"]


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def mesh_figure(m, path: Path, *, title: str, mesh=None) -> Path:
    """A map's marching-cubes mesh (decoded blocks) in the level doll's-house view of
    :func:`sdfcodec.view.pictures.mesh_picture`: camera up = the map's up (its header's, else +z), from above and to the
    side that shows the floor, a scale bar in metres, ``title`` above. Returns ``path``; ``mesh`` saves the
    meshing when the caller has it."""
    from ..fusion.tsdf import mesh_from_blocks
    from ..view.pictures import mesh_picture

    if mesh is None:
        cs, bs = zip(*m.iter_blocks())
        mesh = mesh_from_blocks(np.concatenate(cs), np.concatenate(bs), origin=m.origin, voxel_size=m.voxel_size,
                                truncation=m.truncation)
    up = m.header.up if m.header.up is not None else (0.0, 0.0, 1.0)
    return mesh_picture(mesh, path, title=title, up=up, width=640, height=480)


def slice_picture(fields: dict[str, np.ndarray], z: int, height_m: float, path: Path, *, origin, voxel_size: float,
                  truncation=(-0.04, 0.1)) -> None:
    """Top row: the distance on the horizontal slice ``z`` per map; bottom row: each decoded slice minus the
    first (fused) one. Axes in metres of the map's world frame (voxel centres at ``origin + i * voxel_size``)."""
    plt = _plt()
    names = list(fields)
    ref = fields[names[0]][:, :, z]
    nx, ny = ref.shape
    # imshow's extent is the outer edges of the pixels: half a voxel beyond the first and last centres
    ext = (origin[0] - voxel_size / 2, origin[0] + (nx - 0.5) * voxel_size,
           origin[1] - voxel_size / 2, origin[1] + (ny - 0.5) * voxel_size)
    fig, axes = plt.subplots(2, len(names), figsize=(3.0 * len(names) + 0.8, 6.2), constrained_layout=True,
                             squeeze=False)
    di = None
    for i, name in enumerate(names):
        sl = fields[name][:, :, z]
        im = axes[0, i].imshow(sl.T, origin="lower", cmap="RdBu", vmin=truncation[0], vmax=truncation[1], extent=ext)
        axes[0, i].set_title(name)
        if i == 0:
            axes[1, i].set_axis_off()
            axes[1, i].text(0.5, 0.5, "each map minus\nthe fused one \u2192", ha="center", va="center",
                            transform=axes[1, i].transAxes)
        else:
            di = axes[1, i].imshow((sl - ref).T, origin="lower", cmap="PuOr", vmin=-0.03, vmax=0.03, extent=ext)
            axes[1, i].set_xlabel("x (m)")
        axes[0, i].set_xlabel("x (m)", fontsize=8)
        if i == 0:
            axes[0, i].set_ylabel("y (m)")
        if i == 1:
            axes[1, i].set_ylabel("y (m)")
        for ax in axes[:, i]:
            ax.tick_params(labelsize=7)
    fig.colorbar(im, ax=axes[0, :], shrink=0.8, label="distance (m)")
    if di is not None:
        fig.colorbar(di, ax=axes[1, :], shrink=0.8, label="error (m)")
    fig.suptitle(f"horizontal slice at z = {height_m:.2f} m (world frame), {voxel_size * 100:.0f} cm voxels")
    fig.savefig(path, dpi=80)
    plt.close(fig)


def error_bytes_picture(rows: list[dict], dense_bytes: int, path: Path) -> None:
    plt = _plt()
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.4), constrained_layout=True)
    raw = rows[0]

    def value(r: dict, key: str) -> float:
        if key == "chamfer_mm":
            c = r["surface"]["chamfer_l1"]
            return float("nan") if c is None else 1000 * c
        return r[key]

    for ax, key in ((axes[0], "mse_vs_fused"), (axes[1], "rmse_near_vs_exact_mm"), (axes[2], "chamfer_mm")):
        for r in rows[1:]:
            colour, y = ("tab:blue" if r["codec"] == "pca" else "tab:orange"), value(r, key)
            ax.plot([r["code_bytes"], r["bytes_on_disk"]], [y] * 2, "-", color=colour, alpha=0.35)
            ax.plot(r["code_bytes"], y, "o", color=colour, mfc="white")
            ax.plot(r["bytes_on_disk"], y, "o", color=colour)
            ax.annotate(r["map"], (r["code_bytes"], y), textcoords="offset points", xytext=(-6, 5), ha="right",
                        fontsize=8)
        ax.plot(raw["bytes_on_disk"], value(raw, key), "s", color="grey")
        ax.annotate("raw (lossless)", (raw["bytes_on_disk"], value(raw, key)), textcoords="offset points",
                    xytext=(-6, 5), ha="right", fontsize=8, color="grey")
        ax.axvline(dense_bytes, color="k", lw=0.8, ls=":")
        ax.annotate("dense\nfloat32", (dense_bytes, 0.02), xycoords=("data", "axes fraction"),
                    textcoords="offset points", xytext=(-4, 0), ha="right", fontsize=8)
        ax.set_xscale("log")
        ax.set_ylim(bottom=0)
        ax.set_xlabel("bytes (log scale)")
        ax.grid(alpha=0.3, which="both")
    axes[0].set_ylabel("per-voxel MSE vs the fused map (normalised)")
    axes[1].set_ylabel("RMSE near surfaces vs the exact room (mm)")
    axes[2].set_ylabel("Chamfer-L1 of the surfaces vs the fused map (mm)")
    fig.suptitle("error against bytes: hollow = codes only, filled = whole map file (with the codec's basis or "
                 "weights); blue pca, orange ae")
    fig.savefig(path, dpi=80)
    plt.close(fig)


STYLES = {"raw": ("tab:green", "-"), "pca-32": ("tab:purple", ":"), "pca-64": ("tab:blue", "--"),
           "pca-128": ("tab:cyan", "-."), "ae-64": ("tab:orange", ":")}


def trajectory_picture(gt: np.ndarray, tracks: dict[str, dict], path: Path) -> None:
    plt = _plt()
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.4), constrained_layout=True)
    ax = axes[0]
    ax.plot(gt[:, 0, 3], gt[:, 1, 3], "k-", lw=2.5, alpha=0.4, label="ground truth")
    for name, t in tracks.items():
        c, ls = STYLES.get(name, ("tab:red", ":"))
        p = t["poses"]
        ax.plot(p[:, 0, 3], p[:, 1, 3], ls, color=c, lw=1.3, label=f"{t['label']} (ATE {1000 * t['ate_rmse']:.1f} mm)")
    ax.plot(gt[0, 0, 3], gt[0, 1, 3], "ko", ms=5)
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title("camera positions from above (dot: start)")
    ax.legend(fontsize=8)
    ax = axes[1]
    for name, t in tracks.items():
        c, ls = STYLES.get(name, ("tab:red", ":"))
        ax.plot(t["frame_index"], 1000 * np.asarray(t["errors"]), ls, color=c, label=t["label"])
    ax.set_xlabel("frame")
    ax.set_ylabel("position error (mm)")
    ax.set_title("absolute trajectory error per frame")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.savefig(path, dpi=80)
    plt.close(fig)


