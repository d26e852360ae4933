"""Synthetic RGB-D sequences of an analytic room: the project's built-in data, nothing downloaded.

A room is a union of exact primitives from :mod:`sdfcodec.core.sdf` (floor, walls and optional ceiling as thick
slabs, furniture as boxes, cylinders and balls), so its signed distance is known everywhere that matters:
the union's distance (the minimum) is exact outside all solids, i.e. in the whole free space a camera sees.
The same primitives are also built as an open3d triangle mesh, which :class:`Renderer` ray casts with
``open3d.t.geometry.RaycastingScene`` (Embree) to make depth images. Boxes are meshed exactly; cylinders
and balls are fine polygonal approximations (sagitta under 0.1 mm for the sizes used here).

World frame: metres, z up, the floor surface is ``z = 0`` and the room's interior spans
``[0, sx] x [0, sy] x [0, sz]``. Cameras follow the sequence readers' conventions
(:mod:`sdfcodec.data.sequences`): x right, y down, z forward, camera-to-world poses, pixel ``(u, v)`` sees
the ray ``((u - cx) / fx, (v - cy) / fy, 1)`` and depth is z-depth.

:func:`render_sequence` writes the TUM RGB-D layout that :func:`~sdfcodec.data.sequences.open_sequence`
reads: ``depth/<timestamp>.png`` (16-bit, 5000 per metre, 0 = no reading), ``depth.txt``,
``groundtruth.txt`` (at exactly the depth timestamps, so association is exact), ``intrinsics.txt``
(``fx fy cx cy width height``) and ``scene.json`` (the primitives and their labels, to rebuild the exact
SDF with :meth:`RoomScene.load`). Everything is deterministic given ``seed``.

Presets (:data:`PRESETS`) pick the motion, the sensor model and the scene:

==================  =======  ===========  ========  ==========
preset              frames   deg / frame  geometry  noise
==================  =======  ===========  ========  ==========
``slow-clean``      180      1.5          normal    none
``slow-noisy``      180      1.5          normal    kinect
``fast-clean``      60       6.0          normal    none
``fast-noisy``      60       6.0          normal    kinect
``poor-geometry``   180      1.5          poor      none
``rich-geometry``   180      1.5          rich      none
``building``        10,000   (walk)       building  none
``building-small``  600      (walk)       building  none
==================  =======  ===========  ========  ==========

"slow" moves about 2 cm and 1.5 degrees per frame at 30 Hz (TUM's fr1/desk is similar), "fast" four times
that. "poor" is an empty room (floor and walls only: hard for geometric tracking); "rich" adds rotated
boxes, lying cylinders and balls. Images are 320x240 with fx = fy = 262.5 (the Kinect's 525 halved).

Labels. Every primitive has a label in :data:`LABELS` (``floor``, ``wall``, ``ceiling``, ``furniture``);
:meth:`RoomScene.surface_labels` labels points near the surface by their nearest primitive, and
:meth:`RoomScene.floor_blocks` says which 16^3 blocks of a map hold mostly floor surface (the ground truth
for floor retrieval); given the map's observation mask it counts only the floor the map observed (a fused map
never holds the slab's underside or floor the camera did not see).
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

from ..errors import InvalidValueError, MapExistsError
from ..core.metrics import Trajectory, write_tum
from ..core.sdf import Box, Cylinder, Sphere
from .scene import LABELS, MIN_OBSERVED_FLOOR, RoomScene, look_at, open3d_module
from .sequences import TUM_DEPTH_SCALE, Intrinsics, write_depth_png

__all__ = [
    "LABELS",
    "MIN_OBSERVED_FLOOR",
    "PRESETS",
    "DepthNoise",
    "KINECT_NOISE",
    "Preset",
    "RoomScene",
    "Renderer",
    "room_scene",
    "camera_path",
    "look_at",
    "render_sequence",
    "DEFAULT_INTRINSICS",
]


DEFAULT_INTRINSICS = Intrinsics(262.5, 262.5, 159.5, 119.5, 320, 240)
_SLAB = 0.2  # thickness (m) of floor, wall and ceiling slabs: thicker than any truncation band


# ------------------------------------------------------------------------------------------ sensor model
@dataclass(frozen=True)
class DepthNoise:
    """A Kinect-v1-like depth sensor model (applied to exact z-depth in metres).

    Attributes
    ----------
    sigma0, sigma2, z0 : float
        Axial Gaussian noise ``sigma(z) = sigma0 + sigma2 * (z - z0)^2`` metres (Nguyen, Izadi and Lovell,
        3DIMPVT 2012: 1.2 mm + 1.9 mm/m^2 from 0.4 m).
    quantise : bool
        Round to the Kinect's disparity steps: 1/8 pixel at a 0.075 m baseline and 580 px focal length, so
        the depth step is ``z^2 / 348`` (11 mm at 2 m), whatever the image size.
    dropout : float
        Fraction of pixels that randomly give no reading.
    edge_jump : float or None
        A pixel whose depth differs from a 4-neighbour's by more than this fraction of its depth gives no
        reading (the Kinect's shadows and flying pixels at depth edges); None keeps them.
    grazing_deg : float or None
        Pixels that see a surface more than this many degrees from its normal give no reading.
    min_range, max_range : float
        Metres; readings outside give none.
    """

    sigma0: float = 0.0012
    sigma2: float = 0.0019
    z0: float = 0.4
    quantise: bool = True
    dropout: float = 0.01
    edge_jump: float | None = 0.05
    grazing_deg: float | None = 80.0
    min_range: float = 0.4
    max_range: float = 4.5

    def apply(self, depth: np.ndarray, normal_cos: np.ndarray | None, rng: np.random.Generator) -> np.ndarray:
        """Noisy copy of exact z-depth ``depth`` (H, W) metres (0 = no reading); ``normal_cos`` (H, W) is
        ``|cos|`` of the angle between each pixel's ray and the surface normal (None skips that test)."""
        z = np.asarray(depth, dtype=np.float64)
        valid = z > 0
        missing = ~valid
        if self.edge_jump is not None:
            zp = np.pad(np.where(valid, z, np.inf), 1, mode="edge")
            jump = np.zeros_like(z)
            for dv, du in ((0, 1), (2, 1), (1, 0), (1, 2)):
                nb = zp[dv:dv + z.shape[0], du:du + z.shape[1]]
                jump = np.maximum(jump, np.where(np.isfinite(nb), np.abs(nb - z), np.inf))
            missing |= valid & (jump > self.edge_jump * z)
        if self.grazing_deg is not None and normal_cos is not None:
            missing |= normal_cos < math.cos(math.radians(self.grazing_deg))
        if self.dropout > 0:
            missing |= rng.random(z.shape) < self.dropout
        noisy = z + rng.standard_normal(z.shape) * (self.sigma0 + self.sigma2 * (z - self.z0) ** 2)
        if self.quantise:
            fb = 580.0 * 0.075  # focal length (px) x baseline (m) of a Kinect v1
            disparity = np.round(fb / np.maximum(noisy, 1e-6) * 8.0) / 8.0
            noisy = np.where(disparity > 0, fb / np.maximum(disparity, 1e-9), 0.0)
        missing |= (noisy < self.min_range) | (noisy > self.max_range)
        return np.where(missing, 0.0, noisy).astype(np.float32)


KINECT_NOISE = DepthNoise()


@dataclass(frozen=True)
class Preset:
    """A synthetic sequence recipe (see the module docstring's table)."""

    frames: int
    degrees_per_frame: float
    geometry: str
    noise: DepthNoise | None


PRESETS: dict[str, Preset] = {
    "slow-clean": Preset(180, 1.5, "normal", None),
    "slow-noisy": Preset(180, 1.5, "normal", KINECT_NOISE),
    "fast-clean": Preset(60, 6.0, "normal", None),
    "fast-noisy": Preset(60, 6.0, "normal", KINECT_NOISE),
    "poor-geometry": Preset(180, 1.5, "poor", None),
    "rich-geometry": Preset(180, 1.5, "rich", None),
    # multi-room buildings (sdfcodec.data.building): the geometry names the plan, the walk sets the speed
    "building": Preset(10_000, 0.0, "building", None),
    "building-small": Preset(600, 0.0, "building-small", None),
}


# ------------------------------------------------------------------------------------------------ scenes
def _rot_z(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _rot_x(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def room_scene(seed: int = 0, geometry: str = "normal", ceiling: bool = False,
               size: tuple[float, float, float] = (4.0, 3.2, 2.5), keep_out: float = 1.15) -> RoomScene:
    """A random furnished room (deterministic by ``seed``).

    Parameters
    ----------
    seed : int
        Random seed for the furniture.
    geometry : {"poor", "normal", "rich"}
        ``poor``: floor and walls only; ``normal``: a table and 4 boxes or upright cylinders along the walls;
        ``rich``: 10 pieces including rotated boxes, lying cylinders and balls.
    ceiling : bool
        Close the room with a ceiling slab at ``z = sz``.
    size : tuple of float
        Interior ``(sx, sy, sz)`` metres.
    keep_out : float
        Metres; no furniture within this horizontal distance of the room's centre, where
        :func:`camera_path` flies.

    Returns
    -------
    RoomScene
        Floor surface at ``z = 0``; walls at ``x = 0, sx`` and ``y = 0, sy``.
    """
    if geometry not in ("poor", "normal", "rich"):
        raise InvalidValueError(f"geometry must be 'poor', 'normal' or 'rich', got {geometry!r}")
    sx, sy, sz = (float(v) for v in size)
    if min(sx, sy) < 2 * keep_out + 0.4 or sz < 1.8:
        raise InvalidValueError(f"room size {size} is too small: needs sx, sy >= {2 * keep_out + 0.4:.2f} m "
                                f"(twice keep_out plus furniture) and sz >= 1.8 m")
    t = _SLAB
    prims: list = [Box((sx / 2, sy / 2, -t / 2), (sx / 2 + t, sy / 2 + t, t / 2))]
    labels = ["floor"]
    wall_h = sz + (t if ceiling else 0.0)
    for center, half in (((-t / 2, sy / 2, wall_h / 2), (t / 2, sy / 2 + t, wall_h / 2)),
                         ((sx + t / 2, sy / 2, wall_h / 2), (t / 2, sy / 2 + t, wall_h / 2)),
                         ((sx / 2, -t / 2, wall_h / 2), (sx / 2 + t, t / 2, wall_h / 2)),
                         ((sx / 2, sy + t / 2, wall_h / 2), (sx / 2 + t, t / 2, wall_h / 2))):
        prims.append(Box(center, half))
        labels.append("wall")
    if ceiling:
        prims.append(Box((sx / 2, sy / 2, sz + t / 2), (sx / 2 + t, sy / 2 + t, t / 2)))
        labels.append("ceiling")
    rng = np.random.default_rng(seed)
    placed: list[tuple[float, float, float]] = []  # footprint discs (x, y, radius) already used
    centre = np.array([sx / 2, sy / 2])

    def spot(radius: float) -> tuple[float, float] | None:
        for _ in range(200):
            xy = rng.uniform([radius + 0.02, radius + 0.02], [sx - radius - 0.02, sy - radius - 0.02])
            if np.linalg.norm(xy - centre) < keep_out + radius:
                continue
            if all(math.hypot(xy[0] - x, xy[1] - y) > r + radius + 0.05 for x, y, r in placed):
                placed.append((float(xy[0]), float(xy[1]), radius))
                return float(xy[0]), float(xy[1])
        return None

    def add(prim) -> None:
        prims.append(prim)
        labels.append("furniture")

    if geometry != "poor":
        # a table: top and four legs
        tw, td = rng.uniform(0.35, 0.5), rng.uniform(0.25, 0.35)
        xy = spot(math.hypot(tw, td))
        if xy is not None:
            angle = rng.uniform(0, np.pi) if geometry == "rich" else 0.0
            rot = _rot_z(angle)
            add(Box((xy[0], xy[1], 0.70), (tw, td, 0.02), rot if angle else None))
            for ex, ey in ((1, 1), (1, -1), (-1, 1), (-1, -1)):
                off = rot @ np.array([ex * (tw - 0.05), ey * (td - 0.05), 0.0])
                add(Box((xy[0] + off[0], xy[1] + off[1], 0.34), (0.025, 0.025, 0.34), rot if angle else None))
        kinds = ["box", "box", "cylinder", "box"] if geometry == "normal" else \
            ["box", "box", "box", "rbox", "rbox", "cylinder", "cylinder", "lying", "ball", "ball"]
        for kind in kinds:
            if kind in ("box", "rbox"):
                half = rng.uniform([0.12, 0.12, 0.15], [0.4, 0.3, 0.55])
                xy = spot(float(np.hypot(half[0], half[1])))
                if xy is None:
                    continue
                rot = _rot_z(rng.uniform(0, np.pi)) if kind == "rbox" else None
                add(Box((xy[0], xy[1], half[2]), tuple(half), rot))
            elif kind == "cylinder":
                r, hh = rng.uniform(0.1, 0.25), rng.uniform(0.2, 0.6)
                xy = spot(r)
                if xy is not None:
                    add(Cylinder((xy[0], xy[1], hh), r, hh))
            elif kind == "lying":
                r, hh = rng.uniform(0.1, 0.2), rng.uniform(0.25, 0.45)
                xy = spot(hh)
                if xy is not None:
                    add(Cylinder((xy[0], xy[1], r), r, hh, _rot_z(rng.uniform(0, np.pi)) @ _rot_x(np.pi / 2)))
            elif kind == "ball":
                r = rng.uniform(0.1, 0.25)
                xy = spot(r)
                if xy is not None:
                    add(Sphere((xy[0], xy[1], r), r))
    return RoomScene(prims, labels, (sx, sy, sz), seed=int(seed), geometry=geometry)


# ------------------------------------------------------------------------------------------ camera path


def camera_path(scene: RoomScene, frames: int, degrees_per_frame: float, start_deg: float = 0.0,
                radius: float = 0.75, height: float = 1.35) -> np.ndarray:
    """Smooth hand-held-like poses ``(frames, 4, 4)`` (camera-to-world) circling the room's centre.

    The camera moves on a circle of ``radius`` metres around the centre at about ``height`` metres (with a
    small vertical bob and roll), looking across the room at the lower part of the opposite walls, where
    the furniture stands; the view direction also sways. Frame ``i`` is at angle
    ``start_deg + i * degrees_per_frame`` along the circle.
    """
    c = scene.center
    sx, sy = scene.size[0], scene.size[1]
    reach = np.array([sx / 2 - 0.35, sy / 2 - 0.35])  # where the gaze meets the far side
    poses = np.empty((frames, 4, 4))
    for i in range(frames):
        th = math.radians(start_deg + i * degrees_per_frame)
        eye = c + np.array([radius * math.cos(th), radius * math.sin(th), height + 0.08 * math.sin(3 * th)])
        gaze = th + math.pi + 0.35 * math.sin(2 * th)
        target = c + np.array([reach[0] * math.cos(gaze), reach[1] * math.sin(gaze), 0.45 + 0.15 * math.sin(th)])
        poses[i] = look_at(eye, target, roll=0.06 * math.sin(1.5 * th))
    return poses


# ---------------------------------------------------------------------------------------------- renderer
class Renderer:
    """Ray casts depth images of a :class:`RoomScene` (or any open3d mesh) with open3d/Embree.

    Parameters
    ----------
    scene : RoomScene or open3d.geometry.TriangleMesh
        What to render.
    """

    def __init__(self, scene):
        o3d = open3d_module()
        mesh = scene.mesh() if isinstance(scene, RoomScene) else scene
        self._scene = o3d.t.geometry.RaycastingScene()
        self._scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
        self._o3d = o3d
        self._dirs_cache: dict = {}

    def _camera_dirs(self, intr: Intrinsics) -> np.ndarray:
        key = (intr.fx, intr.fy, intr.cx, intr.cy, intr.width, intr.height)
        if key not in self._dirs_cache:
            u, v = np.meshgrid(np.arange(intr.width, dtype=np.float64), np.arange(intr.height, dtype=np.float64))
            # z component 1: the ray parameter at the hit is then the z-depth itself
            self._dirs_cache[key] = np.stack([(u - intr.cx) / intr.fx, (v - intr.cy) / intr.fy,
                                              np.ones_like(u)], axis=-1)
        return self._dirs_cache[key]

    def render(self, pose: np.ndarray, intrinsics: Intrinsics = DEFAULT_INTRINSICS, noise: DepthNoise | None = None,
               rng: np.random.Generator | None = None) -> np.ndarray:
        """Depth image ``(H, W)`` float32 z-depth metres (0 where a ray hits nothing) seen from ``pose``
        (4x4 camera-to-world), exact unless ``noise`` is given (then ``rng`` draws it)."""
        pose = np.asarray(pose, dtype=np.float64)
        dirs_cam = self._camera_dirs(intrinsics)
        dirs = dirs_cam @ pose[:3, :3].T
        rays = np.concatenate([np.broadcast_to(pose[:3, 3], dirs.shape), dirs], axis=-1).astype(np.float32)
        hit = self._scene.cast_rays(self._o3d.core.Tensor(rays))
        depth = hit["t_hit"].numpy().astype(np.float64)
        depth[~np.isfinite(depth)] = 0.0
        if noise is None:
            return depth.astype(np.float32)
        normals = hit["primitive_normals"].numpy().astype(np.float64)
        cos = np.abs((normals * dirs).sum(-1)) / np.maximum(np.linalg.norm(dirs, axis=-1), 1e-12)
        return noise.apply(depth, cos, rng if rng is not None else np.random.default_rng(0))


def render_sequence(out_dir: str | Path, preset: str = "slow-clean", seed: int = 0, *, frames: int | None = None,
                    degrees_per_frame: float | None = None, geometry: str | None = None,
                    noise: DepthNoise | None | str = "preset", intrinsics: Intrinsics = DEFAULT_INTRINSICS,
                    ceiling: bool = False, frame_rate: float = 30.0, start_time: float = 1000.0,
                    overwrite: bool = False) -> Path:
    """Render a synthetic depth sequence of a random room and write it in the TUM RGB-D layout.

    Parameters
    ----------
    out_dir : str or Path
        Folder to write (created). It must not already hold a sequence unless ``overwrite``.
    preset : str
        A key of :data:`PRESETS`; the keyword arguments below override its parts.
    seed : int
        Seeds the room's furniture and the sensor noise.
    frames, degrees_per_frame, geometry : optional
        Override the preset's frame count, angular speed and scene richness.
    noise : DepthNoise, None or "preset"
        The sensor model: ``"preset"`` keeps the preset's, None renders exact depth (only quantised to
        0.2 mm by the PNG), a :class:`DepthNoise` replaces it.
    intrinsics : Intrinsics
        Camera (default 320x240, fx = fy = 262.5).
    ceiling : bool
        Close the room (every ray then hits something).
    frame_rate, start_time : float
        Timestamps are ``start_time + i / frame_rate`` seconds.
    overwrite : bool
        Replace an existing sequence in ``out_dir``.

    Returns
    -------
    Path
        ``out_dir``, readable with :func:`sdfcodec.data.sequences.open_sequence`; ``scene.json`` in it
        rebuilds the exact scene with :meth:`RoomScene.load`.
    """
    if isinstance(noise, str) and noise != "preset":
        raise InvalidValueError(f"noise must be a DepthNoise, None or 'preset', got {noise!r}")
    if preset not in PRESETS:
        raise InvalidValueError(f"unknown preset {preset!r}; choose one of {', '.join(PRESETS)}")
    p = PRESETS[preset]
    p = replace(p, frames=p.frames if frames is None else int(frames),
                degrees_per_frame=p.degrees_per_frame if degrees_per_frame is None else float(degrees_per_frame),
                geometry=p.geometry if geometry is None else geometry,
                noise=p.noise if isinstance(noise, str) and noise == "preset" else noise)
    if p.frames < 1:
        raise InvalidValueError(f"frames must be at least 1, got {p.frames}")
    out = Path(out_dir)
    if (out / "depth.txt").exists() and not overwrite:
        raise MapExistsError(f"{out} already holds a sequence (depth.txt); pass overwrite=True to replace it")
    (out / "depth").mkdir(parents=True, exist_ok=True)
    if p.geometry.startswith("building"):
        from .building import building_sequence

        scene, poses = building_sequence(p.geometry, seed, p.frames)
    else:
        scene = room_scene(seed, p.geometry, ceiling=ceiling)
        poses = camera_path(scene, p.frames, p.degrees_per_frame)
    renderer = Renderer(scene)
    rng = np.random.default_rng([seed, 1])  # a stream of its own: the noise does not move the furniture
    stamps = start_time + np.arange(p.frames) / frame_rate
    lines = ["# depth maps", f"# file: 'sdfcodec synthetic preset={preset} seed={seed}'", "# timestamp filename"]
    for t, pose in zip(stamps, poses):
        depth = renderer.render(pose, intrinsics, p.noise, rng)
        name = f"depth/{t:.6f}.png"
        write_depth_png(out / name, depth, TUM_DEPTH_SCALE)
        lines.append(f"{t:.6f} {name}")
    (out / "depth.txt").write_text("\n".join(lines) + "\n")
    # ground truth at the depth timestamps, printed identically, so association is exact
    write_tum(out / "groundtruth.txt", Trajectory.from_poses(poses, np.round(stamps, 6)),
              header=f"ground truth trajectory\nfile: 'sdfcodec synthetic preset={preset} seed={seed}'")
    k = intrinsics
    (out / "intrinsics.txt").write_text(f"# fx fy cx cy width height\n{k.fx!r} {k.fy!r} {k.cx!r} {k.cy!r} "
                                        f"{k.width} {k.height}\n")
    scene_dict = scene.to_dict()
    scene_dict["render"] = {"preset": preset, "frames": p.frames, "degrees_per_frame": p.degrees_per_frame,
                            "noise": None if p.noise is None else asdict(p.noise), "frame_rate": frame_rate}
    (out / "scene.json").write_text(json.dumps(scene_dict, indent=1))
    return out
