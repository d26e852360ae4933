"""Pictures without a display: meshes rendered by CPU ray casting (open3d's RaycastingScene) and shaded.

Used for the docs and reports; nothing here needs OpenGL, EGL or a window.

The default view is a level, orthographic "doll's house" view: the camera's up is the world's up (the image's
horizon is level), it looks down from above and to one side, faces seen from behind (the outside of a wall
fused from inside the room) are see-through, and the side is chosen so that most of the floor shows. Being
orthographic, the image has one scale across it: :func:`mesh_picture` draws a scale bar in metres.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

__all__ = ["render_mesh", "render_view", "RenderedView", "mesh_picture", "draw_scale_bar", "save_png"]

#: Azimuths (degrees about the up axis, 0 = looking along +u of the floor plane) tried for the default view:
#: the diagonals, so that a room shows two of its walls meeting in a corner (it reads as 3-D).
AZIMUTHS = (45, 135, 225, 315)
#: Rays that hit a back face continue behind it at most this many times (doll's house walls, then the floor).
BACK_FACE_PASSES = 6


@dataclass
class RenderedView:
    """A rendered mesh and the view it was rendered from.

    Attributes:
        image: ``(H, W, 3)`` uint8.
        metres_per_pixel: horizontal image scale of an orthographic view (None for a perspective one).
        azimuth_deg, elevation_deg: the view direction about and above the horizontal plane (orthographic).
        floor_fraction: share of the image showing upward-facing surfaces (how much floor is in view).
    """

    image: np.ndarray
    metres_per_pixel: float | None
    azimuth_deg: float | None
    elevation_deg: float | None
    floor_fraction: float


def _unit(v) -> np.ndarray:
    v = np.asarray(v, np.float64)
    return v / np.linalg.norm(v)


def _plane_basis(up: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors spanning the plane perpendicular to ``up`` (``x``, ``y`` when ``up`` is ``z``)."""
    ref = np.array([1.0, 0.0, 0.0]) if abs(up[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = _unit(ref - (ref @ up) * up)
    return u, np.cross(up, u)


def _ortho_rays(lo, hi, up, azimuth_deg, elevation_deg, width, height, margin=1.04):
    """Parallel rays looking down at ``elevation_deg`` from the side ``azimuth_deg``, framing the box
    ``lo``-``hi``; returns the rays ``(H, W, 6)`` and the metres per pixel."""
    u, v = _plane_basis(up)
    a, e = np.radians(azimuth_deg), np.radians(elevation_deg)
    horiz = np.cos(a) * u + np.sin(a) * v  # the viewing direction's horizontal part
    fwd = _unit(np.cos(e) * horiz - np.sin(e) * up)
    right = np.cross(fwd, up)
    right /= np.linalg.norm(right)
    cam_up = np.cross(right, fwd)  # level: in the plane of fwd and the world's up, so the horizon stays level
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    centre = (lo + hi) / 2
    pr, pu = (corners - centre) @ right, (corners - centre) @ cam_up
    span_r, span_u = 2 * np.abs(pr).max() * margin, 2 * np.abs(pu).max() * margin
    mpp = max(span_r / width, span_u / height, 1e-9)
    xs = (np.arange(width) - (width - 1) / 2) * mpp
    ys = ((height - 1) / 2 - np.arange(height)) * mpp  # row 0 is the top of the picture
    start = centre - fwd * (np.linalg.norm(hi - lo) + 1.0)
    origins = start + xs[None, :, None] * right + ys[:, None, None] * cam_up
    dirs = np.broadcast_to(fwd, origins.shape)
    return np.concatenate([origins, dirs], -1).astype(np.float32), mpp


def _cast(scene, rays: np.ndarray, cull_back: bool):
    """First hit of each ray; with ``cull_back``, faces whose normal points away from the ray (the back of a
    surface: marching-cubes triangles face free space) are passed through, up to BACK_FACE_PASSES times."""
    import open3d as o3d

    shape = rays.shape[:-1]
    flat = rays.reshape(-1, 6).copy()
    t_total = np.full(len(flat), np.inf, np.float32)
    normals = np.zeros((len(flat), 3), np.float32)
    todo = np.arange(len(flat))
    travelled = np.zeros(len(flat), np.float32)
    for _ in range(BACK_FACE_PASSES if cull_back else 1):
        if not len(todo):
            break
        hit = scene.cast_rays(o3d.core.Tensor(flat[todo]))
        t = hit["t_hit"].numpy()
        n = hit["primitive_normals"].numpy()
        ok = np.isfinite(t)
        back = ok & (np.sum(n * flat[todo, 3:], -1) > 0) if cull_back else np.zeros_like(ok)
        front = ok & ~back
        t_total[todo[front]] = travelled[todo[front]] + t[front]
        normals[todo[front]] = n[front]
        # continue the rays that met a back face from just behind it
        step = t[back] + 1e-4
        flat[todo[back], :3] += flat[todo[back], 3:] * step[:, None]
        travelled[todo[back]] += step
        todo = todo[back]
    return t_total.reshape(shape), normals.reshape(*shape, 3)


def _shade(rays, t, normals, up, heights_range, light):
    valid = np.isfinite(t)
    dirs = rays[..., 3:]
    # any face still turned away (no culling, or an open edge) is shaded as seen from the camera
    flip = np.sum(normals * dirs, axis=-1, keepdims=True) > 0
    normals = np.where(flip, -normals, normals)
    # a headlight (from the camera) plus a light from above: every visible face is lit, tops brighter
    ldir = up if light is None else _unit(light)
    shade = 0.2 + 0.5 * np.clip(-np.sum(normals * dirs, axis=-1), 0, 1) + 0.3 * np.clip(normals @ ldir, 0, 1)
    pts = rays[..., :3] + dirs * np.where(valid, t, 0)[..., None]
    h0, h1 = heights_range
    zn = np.clip((pts @ up - h0) / max(h1 - h0, 1e-6), 0, 1)
    base = np.stack([0.55 + 0.35 * zn, 0.62 + 0.1 * zn, 0.85 - 0.45 * zn], -1)
    img = np.where(valid[..., None], base * shade[..., None], 1.0)
    floor = valid & (normals @ up > 0.8)
    return (np.clip(img, 0, 1) * 255).astype(np.uint8), float(floor.mean())


def render_view(mesh, *, width: int = 960, height: int = 720, eye=None, target=None, up=(0.0, 0.0, 1.0),
                fov_deg: float = 60.0, light=None, azimuth_deg: float | None = None, elevation_deg: float = 40.0,
                cull_back: bool = True, height_range: tuple[float, float] | None = None) -> RenderedView:
    """Render an open3d ``TriangleMesh`` (legacy) by ray casting; see :func:`render_mesh` for the parameters.

    Without ``eye`` the view is orthographic, level, from ``elevation_deg`` above the horizontal and the
    azimuth (of the four diagonals, tried on a small image) that shows the most surface among those showing
    most of the upward-facing surface (the floor), unless
    ``azimuth_deg`` is given. With ``eye`` it is a perspective view from there towards ``target``.
    """
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
    lo, hi = np.asarray(mesh.get_min_bound(), float), np.asarray(mesh.get_max_bound(), float)
    upv = _unit(up)
    heights = np.asarray(mesh.vertices) @ upv
    # a fixed colour scale of at least 1 m: a flat floor keeps one colour instead of stretching its noise
    h0 = float(heights.min()) if len(heights) else 0.0
    hr = height_range or (h0, h0 + max(float(np.ptp(heights)) if len(heights) else 0.0, 1.0))
    if eye is not None:
        centre = (lo + hi) / 2 if target is None else np.asarray(target, float)
        # open3d's pinhole rays put image row 0 at the bottom and column 0 on the right for the up vector it
        # is given (the picture comes out turned by 180 degrees): giving it the opposite up turns it back
        rays = o3d.t.geometry.RaycastingScene.create_rays_pinhole(
            fov_deg, o3d.core.Tensor(centre, o3d.core.float32), o3d.core.Tensor(np.asarray(eye, float), o3d.core.float32),
            o3d.core.Tensor(-upv, o3d.core.float32), width, height).numpy()
        t, n = _cast(scene, rays, cull_back)
        img, ff = _shade(rays, t, n, upv, hr, light)
        return RenderedView(img, None, None, None, ff)
    if azimuth_deg is None:
        small = max(64, width // 8)
        seen = []  # (floor fraction, surface fraction) per azimuth
        for az in AZIMUTHS:
            rays, _ = _ortho_rays(lo, hi, upv, az, elevation_deg, small, max(48, small * height // width))
            t, n = _cast(scene, rays, cull_back)
            seen.append((float((np.isfinite(t) & (n @ upv > 0.8)).mean()), float(np.isfinite(t).mean())))
        # of the views that show most of the floor, the one showing the most surface: from behind its walls a
        # room is floor only (they are see-through), from the open side its walls face the camera too
        floor_best = max(f for f, _ in seen)
        azimuth_deg = max((s, -i, AZIMUTHS[i]) for i, (f, s) in enumerate(seen) if f >= 0.7 * floor_best)[2]
    rays, mpp = _ortho_rays(lo, hi, upv, azimuth_deg, elevation_deg, width, height)
    t, n = _cast(scene, rays, cull_back)
    img, ff = _shade(rays, t, n, upv, hr, light)
    return RenderedView(img, mpp, float(azimuth_deg), float(elevation_deg), ff)


def render_mesh(mesh, *, width: int = 960, height: int = 720, eye=None, target=None, up=(0.0, 0.0, 1.0),
                fov_deg: float = 60.0, light=None, azimuth_deg: float | None = None, elevation_deg: float = 40.0,
                cull_back: bool = True) -> np.ndarray:
    """Render an open3d ``TriangleMesh`` (legacy) to an ``(H, W, 3)`` uint8 image by ray casting.

    The camera's up is ``up``, the world's up direction (for 7-Scenes, minus the gravity direction), so the
    picture is level. Without ``eye``: an orthographic view from ``elevation_deg`` above the horizontal and
    from the side (``azimuth_deg``, default: a diagonal showing most of the floor and the walls facing it) framing the whole mesh. With
    ``eye``: a perspective view (``fov_deg`` horizontal) from ``eye`` towards ``target`` (default: the
    bounding box's centre). With ``cull_back``, faces seen from behind are see-through. Surfaces are shaded by
    a headlight plus a directional ``light`` (default: from ``up``) and tinted by height (blue low, sand high,
    over at least 1 m) so floors, furniture and walls read apart.
    """
    return render_view(mesh, width=width, height=height, eye=eye, target=target, up=up, fov_deg=fov_deg,
                       light=light, azimuth_deg=azimuth_deg, elevation_deg=elevation_deg,
                       cull_back=cull_back).image


def draw_scale_bar(ax, metres_per_pixel: float, width_px: int, height_px: int) -> float:
    """A horizontal scale bar (a round length near a fifth of the image) in the lower left of an image axis;
    returns its length in metres."""
    target = 0.2 * width_px * metres_per_pixel
    length = max(x for x in (0.01, 0.02, 0.05, 0.1, 0.2, 0.25, 0.5, 1, 2, 5, 10, 20, 50, 100) if x <= max(target, 0.01))
    px = length / metres_per_pixel
    x0, y0 = 0.04 * width_px, 0.94 * height_px
    ax.plot([x0, x0 + px], [y0, y0], "k-", lw=3, solid_capstyle="butt")
    ax.text(x0 + px / 2, y0 - 0.02 * height_px, f"{length:g} m", ha="center", va="bottom", fontsize=9)
    return length


def mesh_picture(mesh, path: str | Path, *, title: str | None = None, up=(0.0, 0.0, 1.0), width: int = 800,
                 height: int = 600, ax=None, **view) -> Path | RenderedView:
    """A mesh rendered by :func:`render_view` with a title, a scale bar in metres (orthographic views; the
    scale holds across the image, along its horizontal) and a note of the view direction.

    With ``ax`` (a matplotlib axis) it draws there and returns the :class:`RenderedView` (``path`` unused);
    otherwise it writes a PNG at ``path`` and returns the path.
    """
    rendered = render_view(mesh, width=width, height=height, up=up, **view)
    own = ax is None
    if own:
        plt = _plt()
        # the image one to one in pixels under a title strip: no layout engine, no resampling (cheap to save)
        fig = plt.figure(figsize=(width / 100, height / 100 + 0.4), dpi=100)
        ax = fig.add_axes((0.0, 0.0, 1.0, height / (height + 40.0)))
    ax.imshow(rendered.image, interpolation="none")
    ax.set_axis_off()
    if rendered.metres_per_pixel is not None:
        draw_scale_bar(ax, rendered.metres_per_pixel, width, height)
        ax.text(width - 4, height - 4, f"view from {rendered.elevation_deg:.0f}\u00b0 above the horizontal, "
                "orthographic; up is the map's up", ha="right", va="bottom", fontsize=8, color="0.35")
    if title:
        ax.set_title(title, fontsize=11)
    if not own:
        return rendered
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)
    return path


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_png(image: np.ndarray, path: str | Path) -> Path:
    """Write an ``(H, W, 3)`` uint8 image as PNG (matplotlib, Agg backend)."""
    _plt()
    import matplotlib.pyplot as plt

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    plt.imsave(path, image)
    return path
