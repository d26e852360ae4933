"""Pictures without a display: meshes rendered by CPU ray casting (open3d's RaycastingScene) and shaded.

Used for the docs and reports; nothing here needs OpenGL, EGL or a window.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["render_mesh", "save_png"]


def render_mesh(mesh, *, width: int = 960, height: int = 720, eye=None, target=None, up=(0.0, 0.0, 1.0),
                fov_deg: float = 60.0, light=None) -> np.ndarray:
    """Render an open3d ``TriangleMesh`` (legacy) to an ``(H, W, 3)`` uint8 image by ray casting.

    The camera looks from ``eye`` at ``target`` (default: from above and to one side of the bounding box,
    towards its centre), with ``up`` the world's up direction (for 7-Scenes, minus the gravity direction). Surfaces are shaded by a headlight plus a directional ``light`` (default: from
    ``up``), and tinted by height so floors, furniture and walls read apart.
    """
    import open3d as o3d

    tmesh = o3d.t.geometry.TriangleMesh.from_legacy(mesh)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(tmesh)
    lo, hi = np.asarray(mesh.get_min_bound()), np.asarray(mesh.get_max_bound())
    centre = (lo + hi) / 2 if target is None else np.asarray(target, float)
    upv = np.asarray(up, float) / np.linalg.norm(up)
    if eye is None:
        # from above and to one side: 50 degrees down from the horizontal, at 2 bounding radii
        radius = 0.5 * np.linalg.norm(hi - lo)
        side = np.array([-0.6, -0.8, 0.0]) - upv * (np.array([-0.6, -0.8, 0.0]) @ upv)
        side = side / np.linalg.norm(side) if np.linalg.norm(side) > 1e-6 else np.cross(upv, [1.0, 0.0, 0.0])
        eye = centre + 2.0 * radius * (np.cos(np.radians(50)) * side + np.sin(np.radians(50)) * upv)
    rays = o3d.t.geometry.RaycastingScene.create_rays_pinhole(fov_deg, o3d.core.Tensor(centre, o3d.core.float32),
                                                              o3d.core.Tensor(np.asarray(eye, float), o3d.core.float32),
                                                              o3d.core.Tensor(np.asarray(up, float), o3d.core.float32),
                                                              width, height)
    hit = scene.cast_rays(rays)
    t = hit["t_hit"].numpy()
    normals = hit["primitive_normals"].numpy()
    valid = np.isfinite(t)
    dirs = rays.numpy()[..., 3:]
    # face normals point either way in marching-cubes meshes of open surfaces: face them to the camera
    flip = np.sum(normals * dirs, axis=-1, keepdims=True) > 0
    normals = np.where(flip, -normals, normals)
    # a headlight (from the camera) plus a light from above: every visible face is lit, tops brighter
    ldir = upv if light is None else np.asarray(light, float) / np.linalg.norm(light)
    shade = 0.2 + 0.5 * np.clip(-np.sum(normals * dirs, axis=-1), 0, 1) + 0.3 * np.clip(normals @ ldir, 0, 1)
    pts = rays.numpy()[..., :3] + dirs * np.where(valid, t, 0)[..., None]
    heights = np.asarray(mesh.vertices) @ upv
    z = pts @ upv
    zn = np.clip((z - heights.min()) / max(np.ptp(heights), 1e-6), 0, 1)
    base = np.stack([0.55 + 0.35 * zn, 0.62 + 0.1 * zn, 0.85 - 0.45 * zn], -1)
    img = np.where(valid[..., None], base * shade[..., None], 1.0)
    return (np.clip(img, 0, 1) * 255).astype(np.uint8)


def save_png(image: np.ndarray, path: str | Path) -> Path:
    """Write an ``(H, W, 3)`` uint8 image as PNG (matplotlib, Agg backend)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    plt.imsave(path, image)
    return path
