"""A synthetic multi-room building and a camera walk through all of it: the built-in large-map sequence.

:func:`building_scene` lays out a one-storey building, deterministically from a seed: a straight corridor
with rooms on both sides, every room joined to the corridor by a door (an opening in a 0.2 m thick wall, with
a lintel above it) and, at random, to its neighbour on the same side; a floor slab and a ceiling slab over
everything; furniture-like boxes and cylinders along the rooms' walls, clear of the doors and of the middle of
each room, where the camera loops. Everything is a :mod:`sdfcodec.core.sdf` primitive (Box, Cylinder), so the scene
is a :class:`~sdfcodec.data.scene.RoomScene` (exact SDF, labels, a mesh for the ray caster, ``scene.json``).

:func:`building_path` walks it: along the corridor's centre line, into each room through its door (south
side, then north side, room by room), once round the room looking across it at the far walls and furniture,
and back out. The route is a polyline sampled at equal arc length into exactly ``frames`` poses, so the
speed is ``length / frames`` (11.5 cm per frame for ``building``, 12 cm for ``building-small``: 3.5 m/s at
30 Hz, a run rather than a walk, which keeps the sequence affordable); view directions are smoothed (a Gaussian
over 0.6 m of the walk, as yaw and pitch) so that the turns at doors are gradual.

Presets (registered in :data:`sdfcodec.data.render.PRESETS`, rendered by
:func:`~sdfcodec.data.render.render_sequence`, exact depth):

==================  =====  ==========  =============================================
preset              rooms  frames      lossless map at 2 cm (measured, docs/scale.md)
==================  =====  ==========  =============================================
``building``        64     10,000      101,500 coded blocks
``building-small``  4      600         6,645 coded blocks (CI renders fewer, smaller)
==================  =====  ==========  =============================================
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..errors import InvalidValueError
from ..core.sdf import Box, Cylinder
from .scene import RoomScene, look_at

__all__ = ["BuildingLayout", "Room", "BUILDINGS", "building_scene", "building_path", "building_sequence"]

WALL = 0.2  # wall, floor and ceiling thickness (m): thicker than the truncation band, as in render.py's rooms
DOOR_WIDTH, DOOR_HEIGHT = 1.0, 2.1
EYE_HEIGHT = 1.4


@dataclass(frozen=True)
class Room:
    """One room: interior ``[x0, x1] x [y0, y1]``, its door to the corridor at ``door_x`` in the wall at
    ``door_y`` (the wall's face on the room's side), ``side`` -1 (south of the corridor) or +1 (north)."""

    x0: float
    x1: float
    y0: float
    y1: float
    door_x: float
    door_y: float
    side: int

    @property
    def centre(self) -> np.ndarray:
        return np.array([(self.x0 + self.x1) / 2, (self.y0 + self.y1) / 2])

    @property
    def loop_radius(self) -> float:
        """Radius (m) of the camera's loop about the centre: clear of the furniture along the walls."""
        return max(0.4, min(self.x1 - self.x0, self.y1 - self.y0) / 2 - 1.5)


@dataclass(frozen=True)
class BuildingLayout:
    """The plan of a building: its rooms, the corridor ``[0, length] x [0, corridor_width]`` and the storey
    height (floor surface at z = 0, ceiling surface at z = height)."""

    rooms: tuple[Room, ...]
    length: float
    corridor_width: float
    height: float


#: Preset name -> (rooms per side of the corridor, frames of the walk).
BUILDINGS: dict[str, tuple[int, int]] = {"building": (32, 10_000), "building-small": (2, 600)}


def _box(lo, hi) -> Box:
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    return Box(tuple((lo + hi) / 2), tuple((hi - lo) / 2))


def _wall_with_doors(axis: int, at: float, lo: float, hi: float, doors: list[float], height: float) -> list[Box]:
    """A wall slab centred on coordinate ``at`` of ``axis`` (0: x = at, 1: y = at), spanning ``[lo, hi]`` along
    the other horizontal axis and the storey's height, with door openings centred at ``doors`` (a lintel
    above each)."""
    t, h_top = WALL, height
    start = lo
    spans = []
    for d in sorted(doors):
        spans.append((start, d - DOOR_WIDTH / 2))
        start = d + DOOR_WIDTH / 2
    spans.append((start, hi))
    out = []

    def slab(a0, a1, z0, z1):
        if a1 - a0 <= 1e-6:
            return
        if axis == 1:
            out.append(_box((a0, at - t / 2, z0), (a1, at + t / 2, z1)))
        else:
            out.append(_box((at - t / 2, a0, z0), (at + t / 2, a1, z1)))

    for a0, a1 in spans:
        slab(a0, a1, 0.0, h_top)
    for d in doors:
        slab(d - DOOR_WIDTH / 2, d + DOOR_WIDTH / 2, DOOR_HEIGHT, h_top)
    return out


def building_scene(seed: int = 0, rooms_per_side: int = 2):
    """A building with ``rooms_per_side`` rooms on each side of a corridor (deterministic by ``seed``).

    Returns
    -------
    scene : sdfcodec.data.scene.RoomScene
        Its primitives (labels floor, wall, ceiling, furniture), ``size`` the overall extent, geometry
        ``"building"``.
    layout : BuildingLayout
        The plan (rooms, doors, corridor) the camera path follows.
    """
    if int(rooms_per_side) != rooms_per_side or rooms_per_side < 1:
        raise InvalidValueError(f"rooms_per_side must be a positive integer, got {rooms_per_side!r}")
    n = int(rooms_per_side)
    rng = np.random.default_rng([seed, 18])
    t = WALL
    height = float(rng.uniform(2.7, 3.0))
    wc = float(rng.uniform(2.2, 2.6))  # corridor width
    depth = {-1: float(rng.uniform(5.0, 6.5)), 1: float(rng.uniform(5.0, 6.5))}  # room depth per side
    widths = rng.uniform(5.0, 7.5, n)
    xs = np.concatenate([[0.0], np.cumsum(widths + t)])  # room i spans [xs[i], xs[i] + widths[i]]
    length = float(xs[-1] - t)
    y_lo, y_hi = -t - depth[-1], wc + t + depth[1]
    prims: list = []
    labels: list[str] = []

    def add(items, label):
        items = items if isinstance(items, list) else [items]
        prims.extend(items)
        labels.extend([label] * len(items))

    # floor and ceiling slabs over the whole plan, exterior walls included
    add(_box((-t, y_lo - t, -t), (length + t, y_hi + t, 0.0)), "floor")
    add(_box((-t, y_lo - t, height), (length + t, y_hi + t, height + t)), "ceiling")
    # exterior walls: ends of the building, south and north faces
    add(_box((-t, y_lo - t, 0.0), (0.0, y_hi + t, height)), "wall")
    add(_box((length, y_lo - t, 0.0), (length + t, y_hi + t, height)), "wall")
    add(_box((-t, y_lo - t, 0.0), (length + t, y_lo, height)), "wall")
    add(_box((-t, y_hi, 0.0), (length + t, y_hi + t, height)), "wall")
    rooms: list[Room] = []
    doors = {-1: [], 1: []}
    for side in (-1, 1):
        for i in range(n):
            x0, x1 = float(xs[i]), float(xs[i] + widths[i])
            door_x = float(rng.uniform(x0 + 0.9, x1 - 0.9))
            doors[side].append(door_x)
            if side < 0:
                y0, y1, door_y = y_lo, -t, -t
            else:
                y0, y1, door_y = wc + t, y_hi, wc + t
            rooms.append(Room(x0, x1, y0, y1, door_x, door_y, side))
    # corridor walls (their centre lines at y = -t/2 and y = wc + t/2), one door per room
    add(_wall_with_doors(1, -t / 2, 0.0, length, doors[-1], height), "wall")
    add(_wall_with_doors(1, wc + t / 2, 0.0, length, doors[1], height), "wall")
    # partitions between neighbouring rooms, some with a connecting door
    for side in (-1, 1):
        y0, y1 = (y_lo, -t) if side < 0 else (wc + t, y_hi)
        for i in range(n - 1):
            xw = float(xs[i + 1] - t / 2)
            conn = [float(rng.uniform(y0 + 1.0, y1 - 1.0))] if rng.random() < 0.5 else []
            add(_wall_with_doors(0, xw, y0, y1, conn, height), "wall")
    for room in rooms:
        add(_furnish(room, rng), "furniture")
    scene = RoomScene(prims, labels, (length, y_hi - y_lo, height), seed=int(seed), geometry="building")
    return scene, BuildingLayout(tuple(rooms), length, wc, height)


def _furnish(room: Room, rng: np.random.Generator) -> list:
    """Boxes (cabinets, desks) and upright cylinders along a room's walls, clear of its door and of the disc
    the camera loops in."""
    placed: list[tuple[np.ndarray, np.ndarray]] = []  # footprints (lo, hi) already used
    keep_r = room.loop_radius + 0.7
    door_zone = (np.array([room.door_x - 0.9, min(room.door_y, room.door_y + 1.6 * room.side) - 0.1]),
                 np.array([room.door_x + 0.9, max(room.door_y, room.door_y + 1.6 * room.side) + 0.1]))
    out: list = []
    for _ in range(int(rng.integers(5, 9))):
        for _try in range(40):
            cyl = rng.random() < 0.25
            if cyl:
                r = float(rng.uniform(0.12, 0.3))
                half = np.array([r, r, rng.uniform(0.25, 0.6)])
            else:
                half = np.array([rng.uniform(0.15, 0.6), rng.uniform(0.15, 0.45), rng.uniform(0.2, 0.9)])
                if rng.random() < 0.5:
                    half[:2] = half[1::-1]
            wall = int(rng.integers(4))  # against which wall: 0 x0, 1 x1, 2 y0, 3 y1
            gap = float(rng.uniform(0.02, 0.3))
            c = np.array([rng.uniform(room.x0 + half[0] + 0.05, room.x1 - half[0] - 0.05),
                          rng.uniform(room.y0 + half[1] + 0.05, room.y1 - half[1] - 0.05)])
            if wall == 0:
                c[0] = room.x0 + gap + half[0]
            elif wall == 1:
                c[0] = room.x1 - gap - half[0]
            elif wall == 2:
                c[1] = room.y0 + gap + half[1]
            else:
                c[1] = room.y1 - gap - half[1]
            lo, hi = c - half[:2], c + half[:2]
            if np.linalg.norm(np.clip(room.centre, lo, hi) - room.centre) < keep_r:
                continue
            if np.all(hi > door_zone[0]) and np.all(lo < door_zone[1]):
                continue
            if any(np.all(hi + 0.05 > a) and np.all(lo - 0.05 < b) for a, b in placed):
                continue
            placed.append((lo, hi))
            if cyl:
                out.append(Cylinder((c[0], c[1], half[2]), half[0], half[2]))
            else:
                out.append(Box((c[0], c[1], half[2]), tuple(half)))
            break
    return out


def building_path(layout: BuildingLayout, frames: int) -> np.ndarray:
    """Camera-to-world poses ``(frames, 4, 4)`` walking through every room of ``layout`` (module docstring):
    along the corridor, in through each door, once round the room, out again."""
    from scipy.ndimage import gaussian_filter1d

    if int(frames) != frames or frames < 2:
        raise InvalidValueError(f"a building walk needs at least 2 frames, got {frames!r}")
    mid = layout.corridor_width / 2
    pts: list[np.ndarray] = []  # (x, y) waypoints
    gaze: list[np.ndarray | None] = []  # per waypoint: a target (x, y, z) to look at, None = along the walk

    def walk(p, target=None):
        pts.append(np.asarray(p, np.float64))
        gaze.append(None if target is None else np.asarray(target, np.float64))

    walk((0.8, mid))
    by_x = sorted(layout.rooms, key=lambda r: (r.x0, r.side))
    for room in by_x:
        walk((room.door_x, mid))
        inside = np.array([room.door_x, room.door_y + room.side * 1.0])
        walk((room.door_x, room.door_y - room.side * 0.3))
        walk(inside)
        c, r = room.centre, room.loop_radius
        start = math.atan2(inside[1] - c[1], inside[0] - c[0])
        steps = 72
        reach = np.array([(room.x1 - room.x0) / 2 - 0.3, (room.y1 - room.y0) / 2 - 0.3])
        for k in range(steps + 1):
            th = start + 2 * math.pi * k / steps
            eye = c + r * np.array([math.cos(th), math.sin(th)])
            g = th + math.pi + 0.35 * math.sin(2 * th)  # across the room, swaying
            walk(eye, (c[0] + reach[0] * math.cos(g), c[1] + reach[1] * math.sin(g), 0.6))
        walk(inside)
        walk((room.door_x, room.door_y - room.side * 0.3))
        walk((room.door_x, mid))
    walk((layout.length - 0.8, mid))
    P = np.array(pts)
    seg = np.linalg.norm(np.diff(P, axis=0), axis=1)
    keep = np.r_[True, seg > 1e-9]
    P, gz = P[keep], [g for g, k in zip(gaze, keep) if k]
    s = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(P, axis=0), axis=1))]
    u = np.linspace(0.0, s[-1], int(frames))
    xy = np.stack([np.interp(u, s, P[:, 0]), np.interp(u, s, P[:, 1])], -1)
    # where to look: along the walk (2 m ahead) outside the loops, across the room inside them
    ahead = np.stack([np.interp(np.minimum(u + 2.0, s[-1]), s, P[:, 0]),
                      np.interp(np.minimum(u + 2.0, s[-1]), s, P[:, 1])], -1)
    nearest = np.clip(np.searchsorted(s, u), 0, len(s) - 1)
    fwd = np.concatenate([ahead - xy, np.full((len(u), 1), -0.25)], axis=1)
    for i, j in enumerate(nearest):
        g = gz[j]
        if g is not None:
            fwd[i] = g - np.r_[xy[i], EYE_HEIGHT]
    fwd[np.linalg.norm(fwd[:, :2], axis=1) < 1e-6, :2] = (1.0, 0.0)  # the last frames: keep looking east
    # smoothed as yaw (unwrapped) and pitch, not as vectors: a reversal at a door then becomes a gradual
    # half turn instead of vectors cancelling out
    yaw = np.unwrap(np.arctan2(fwd[:, 1], fwd[:, 0]))
    pitch = np.arctan2(fwd[:, 2], np.linalg.norm(fwd[:, :2], axis=1))
    step = s[-1] / max(len(u) - 1, 1)
    sigma = max(1.0, 0.6 / max(step, 1e-6))  # frames in 0.6 m of walking
    yaw = gaussian_filter1d(yaw, sigma, mode="nearest")
    pitch = np.clip(gaussian_filter1d(pitch, sigma, mode="nearest"), -0.6, 0.3)  # never straight up or down
    fwd = np.stack([np.cos(yaw) * np.cos(pitch), np.sin(yaw) * np.cos(pitch), np.sin(pitch)], -1)
    t = np.arange(len(u))
    z = EYE_HEIGHT + 0.05 * np.sin(2 * math.pi * u / 1.4)  # the bob of walking, one step every 0.7 m
    poses = np.empty((len(u), 4, 4))
    for i in t:
        eye = np.r_[xy[i], z[i]]
        poses[i] = look_at(eye, eye + fwd[i], roll=0.03 * math.sin(u[i] / 1.3))
    return poses


def building_sequence(preset: str, seed: int = 0, frames: int | None = None):
    """The scene and camera poses of a building preset (a key of :data:`BUILDINGS`): ``(RoomScene, poses
    (frames, 4, 4))``. ``frames`` None takes the preset's walk; fewer take its first ``frames`` poses (the same
    speed, as a room preset's first frames are: ``eval --frames 60`` sees the start of the building), more walk
    the same route slower."""
    if preset not in BUILDINGS:
        raise InvalidValueError(f"unknown building preset {preset!r}; one of {sorted(BUILDINGS)}")
    per_side, n = BUILDINGS[preset]
    scene, layout = building_scene(seed, per_side)
    if frames is not None and int(frames) < 1:
        raise InvalidValueError(f"frames must be at least 1, got {frames!r}")
    want = n if frames is None else int(frames)
    return scene, building_path(layout, max(n, want))[:want]
