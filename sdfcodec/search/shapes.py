"""Query shapes: the normalised TSDF blocks of the built-in queries (floor, ceiling, wall, edge, corner) and
the rotation sets a query model can be made invariant to.

Shapes are posed about the block's centre ``(7.5, 7.5, 7.5)`` (voxel ``i`` at position ``i``), defined with
``+z`` up and rotated onto the map's ``up``; ``behind`` says how voxels more than ``|d_min|`` behind a surface
are stored (see :mod:`sdfcodec.search`). Rotations themselves come from :mod:`sdfcodec.core.geometry`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from ..core._validate import BLOCK
from ..core.blocks import check_truncation, normalise
from ..errors import InvalidValueError, ShapeError
from ..core.geometry import axis_rotations, rot_x, rot_y, rot_z, rotation_to

__all__ = [
    "WALL_YAWS",
    "EDGE_YAWS",
    "PART_REACH",
    "MIN_SHAPE_SURFACE",
    "NEAR_MISSES",
    "POLE_RADII",
    "FUSED_STRETCH",
    "sample_shapes",
    "QUERY_NAMES",
    "BEHIND",
    "ConeRotations",
    "cone_rotations",
    "rotation_set",
    "plane_offsets",
    "query_blocks",
    "check_query_name",
    "truncate",
    "dedupe_blocks",
    "rotate_blocks",
    "probe_blocks",
]

#: The built-in named queries (see :func:`query_blocks`).
QUERY_NAMES: tuple[str, ...] = ("floor", "ceiling", "wall", "edge", "corner", "pole")
#: Radii (voxels) of the pole model's vertical cylinders.
POLE_RADII: tuple[float, ...] = (2.0, 3.5, 6.0, 10.0)
#: Ways of treating voxels more than ``|d_min|`` behind a surface (see the :mod:`sdfcodec.search` docstring).
BEHIND: tuple[str, ...] = ("unobserved", "solid")

#: Field stretches of a fused map's surfaces: fusion stores projective distances (along the camera's axis), so a
#: surface seen at angle theta from its normal has its field stretched by 1 / cos(theta) along the normal; these
#: cover views up to 66 degrees (stretch 2.5). Query shapes for fused maps are sampled at each.
FUSED_STRETCH: tuple[float, ...] = (1.0, 1.25, 1.5, 1.75, 2.0, 2.5)
#: Shapes a query must not match, for the queries whose clean instances vary more than their model samples (a
#: threshold keeping 99 % of simulated edges would keep planes too): the calibrated threshold also keeps at most
#: 1 % of simulated instances of these (:func:`sdfcodec.search.calibrate.calibrate_threshold`).
NEAR_MISSES: dict[str, tuple[str, ...]] = {"edge": ("floor", "wall", "ceiling"),
                                           "corner": ("edge", "floor", "wall"),
                                           "pole": ("wall", "floor", "edge")}
#: Wall normals sampled about up: any horizontal normal is within 7.5 degrees of one.
WALL_YAWS = 24
_CENTRE = (BLOCK - 1) / 2.0  # 7.5: the block's centre in voxel units (voxel i at position i)
#: Edges and corners are modelled (and calibrated) with their line or apex within this many voxels of the block's
#: centre along each axis: every face then fills at least a fifth of the block's surface (an edge near a face
#: is nearly a plane, which the edge model must not match).
PART_REACH = 4.0
#: Yaws about up of the edge and corner models (30 degrees apart, and a right-angled edge repeats every 90: any
#: edge is within 15 degrees of one).
EDGE_YAWS = 12
# the shape-frame families, each turned about up by the yaws: an edge along z (two walls), the same edge lying
# along y with its second face up (floor and wall) or down (ceiling and wall); a corner of floor and two walls,
# and of ceiling and two walls
_EDGE_FAMILIES = (np.eye(3), rot_x(math.pi / 2), rot_x(-math.pi / 2))
_CORNER_FAMILIES = (np.eye(3), rot_x(math.pi))


def _yawed(families: Sequence[np.ndarray], yaws: int) -> np.ndarray:
    """``(yaws * F, 3, 3)``: each family rotation turned about +z by ``yaws`` equal steps."""
    return np.stack([rot_z(2 * math.pi * k / yaws) @ f for f in families for k in range(yaws)])


# ------------------------------------------------------------------------------------------------ rotations
@dataclass(frozen=True)
class ConeRotations:
    """Random rotations within a cone: the shape's ``+z`` tilted to a direction uniform on the spherical cap
    of half-angle ``angle_deg`` about ``+z`` (then mapped onto ``up``), after a spin about ``+z`` uniform in
    ``[0, 360)`` degrees when ``spin`` (which makes walls and edges invariant to yaw). The identity is always
    the first of the ``count`` rotations. Deterministic given ``seed``."""

    angle_deg: float = 10.0
    count: int = 16
    spin: bool = True
    seed: int = 0

    def to_json(self) -> dict:
        return {"cone": float(self.angle_deg), "count": int(self.count), "spin": bool(self.spin),
                "seed": int(self.seed)}


def cone_rotations(angle_deg: float = 10.0, count: int = 16, *, spin: bool = True, seed: int = 0) -> np.ndarray:
    """Rotations within a cone (see :class:`ConeRotations`).

    Returns
    -------
    np.ndarray
        ``(count, 3, 3)`` float64, the identity first.
    """
    if not (0.0 <= angle_deg <= 180.0) or int(count) < 1:
        raise InvalidValueError(f"a cone needs 0 <= angle_deg <= 180 and count >= 1, got {angle_deg}, {count}")
    rng = np.random.default_rng(seed)
    out = [np.eye(3)]
    cos_a = math.cos(math.radians(angle_deg))
    for _ in range(int(count) - 1):
        cz = rng.uniform(cos_a, 1.0)  # uniform on the cap: cos(theta) uniform
        phi = rng.uniform(0.0, 2 * math.pi)
        sz = math.sqrt(max(0.0, 1.0 - cz * cz))
        tilt = rotation_to((sz * math.cos(phi), sz * math.sin(phi), cz))
        psi = rng.uniform(0.0, 2 * math.pi) if spin else 0.0
        out.append(tilt @ rot_z(psi))
    return np.stack(out)


def rotation_set(rotations: Any) -> tuple[np.ndarray, Any]:
    """A ``rotations`` argument (see :func:`query_blocks`) -> ``((R, 3, 3) float64 matrices, JSON description)``
    (the description is what a saved query model's ``spec`` records)."""
    if rotations is None or rotations == "none":
        return np.eye(3)[None], "none"
    if isinstance(rotations, str):
        if rotations == "axis":
            return axis_rotations(), "axis"
        if rotations.startswith("cone"):
            # "cone", "cone:ANGLE" or "cone:ANGLE:COUNT" (CLI-friendly)
            parts = rotations.split(":")[1:]
            try:
                if len(parts) > 2:
                    raise ValueError("too many fields")
                cone = ConeRotations(angle_deg=float(parts[0]) if parts else 10.0,
                                     count=int(parts[1]) if len(parts) > 1 else 16)
            except ValueError as e:
                raise InvalidValueError(f"bad cone rotations {rotations!r}; write cone:ANGLE_DEG[:COUNT]") from e
            return rotation_set(cone)
        raise InvalidValueError(f"rotations must be None, 'axis', 'cone[:ANGLE[:COUNT]]', a ConeRotations or "
                                f"(R, 3, 3) matrices; got {rotations!r}")
    if isinstance(rotations, ConeRotations):
        return (cone_rotations(rotations.angle_deg, rotations.count, spin=rotations.spin, seed=rotations.seed),
                rotations.to_json())
    if isinstance(rotations, Mapping) and "cone" in rotations:
        return rotation_set(ConeRotations(rotations["cone"], rotations.get("count", 16), rotations.get("spin", True),
                                           rotations.get("seed", 0)))
    if isinstance(rotations, Mapping) and "matrices" in rotations:  # as stored in a saved model's spec
        rotations = rotations["matrices"]
    r = np.asarray(rotations, dtype=np.float64)
    if r.ndim == 2:
        r = r[None]
    if r.ndim != 3 or r.shape[1:] != (3, 3):
        raise ShapeError(f"rotation matrices must have shape (R, 3, 3), got {r.shape}")
    if not np.allclose(r @ r.transpose(0, 2, 1), np.eye(3), atol=1e-6) or np.any(np.linalg.det(r) < 0):
        raise InvalidValueError("rotation matrices must be orthonormal with determinant +1")
    return r, {"matrices": r.tolist()}



# ------------------------------------------------------------------------------------------- query shapes
def _offsets(n: int) -> np.ndarray:
    """``n`` offsets (voxels, relative to the block centre): midpoints of ``n`` equal parts of ``[-8, 8]``."""
    return -BLOCK / 2 + (np.arange(n) + 0.5) * BLOCK / n


def _lattice_offsets(voxel_size: float, truncation: tuple[float, float]) -> np.ndarray:
    """One plane offset per voxel step, midway between the heights where a voxel layer crosses ``d_min``
    (relative to the block centre, voxels): 17 offsets covering surfaces from half a voxel outside the block's
    voxel layers on either side. With ``behind="unobserved"`` a layer's value jumps from ``d_min`` to ``d_max``
    where it crosses ``|d_min|`` behind the surface, so a plane is only close to model planes on the same side
    of every jump: this puts exactly one in each interval, at most half a voxel from any plane in it."""
    frac = (-truncation[0] / voxel_size) % 1.0
    t = np.arange(-2, BLOCK + 1) + frac + 0.5  # voxel coordinates (voxel i at i)
    t = t[(t >= -1.0) & (t < BLOCK)]
    return t - _CENTRE


#: Plane shapes (model descriptors and calibration instances) hold at least this many voxels within one voxel of
#: their plane: a plane only clipping a block's corner is left out (64: a quarter of a face's voxels).
MIN_SHAPE_SURFACE = 64


def _surface_voxels(q: np.ndarray, p: np.ndarray) -> int:
    """Voxels of a block (``q``: its voxel positions in the shape's frame) within one voxel of the plane at ``p``."""
    return int((np.abs(q[..., 2] - p[2]) <= 1.0).sum())


def _extent(r: np.ndarray) -> float:
    """How far (voxels) a plane with normal ``r[:, 2]`` may pass from the block's centre and still hold surface
    voxels of the block: its voxels' half-extent along the normal, plus one voxel (a plane up to a voxel beyond
    the outer voxels is the surface of the block on each side of it). 8.5 for axis-aligned planes, up to 13.99
    for one along a diagonal."""
    return float(_CENTRE * np.abs(r[:, 2]).sum() + 1.0)


def _reach(pos: np.ndarray, r: np.ndarray) -> np.ndarray:
    """Plane positions ``(P, 3)`` (offsets along z, evenly spaced) continued at their spacing to :func:`_extent` of
    rotation ``r``: a plane oblique to the grid crosses the block farther from its centre than an axis-aligned one."""
    off = np.sort(pos[:, 2])
    if len(off) < 2:
        return pos
    step = float(off[1] - off[0])
    ext = _extent(r)
    lo = off[0] - step * np.arange(1, int(max(0.0, (off[0] + ext) // step)) + 1)
    hi = off[-1] + step * np.arange(1, int(max(0.0, (ext - off[-1]) // step)) + 1)
    z = np.concatenate([lo[::-1], off, hi])
    return np.stack([np.zeros_like(z), np.zeros_like(z), z], axis=1)


# The shapes' signed distances (voxels) at positions ``q`` ``(..., 3)`` for shape positions ``pos`` ``(3,)``, or
# ``(P, 1, 1, 1, 3)`` against ``q`` ``(16, 16, 16, 3)``: every position at once (:func:`query_blocks`).
def _plane(q: np.ndarray, pos: np.ndarray) -> np.ndarray:
    return q[..., 2] - pos[..., 2]  # solid below, free above (+z)


def _edge(q: np.ndarray, pos: np.ndarray) -> np.ndarray:
    """Concave edge along z: free where x > pos_x and y > pos_y (two walls seen from inside)."""
    x, y = q[..., 0] - pos[..., 0], q[..., 1] - pos[..., 1]
    nearest = np.minimum(x, y)
    return np.where(nearest > 0, nearest, -np.sqrt(np.minimum(x, 0) ** 2 + np.minimum(y, 0) ** 2))


def _corner(q: np.ndarray, pos: np.ndarray) -> np.ndarray:
    """Concave corner: free where x, y, z exceed pos (floor and two walls seen from inside)."""
    x, y, z = (q[..., i] - pos[..., i] for i in range(3))
    nearest = np.minimum(np.minimum(x, y), z)
    depth = np.sqrt(np.minimum(x, 0) ** 2 + np.minimum(y, 0) ** 2 + np.minimum(z, 0) ** 2)
    return np.where(nearest > 0, nearest, -depth)


def _pole(q: np.ndarray, pos: np.ndarray) -> np.ndarray:
    """Solid vertical cylinder (along z) of radius ``pos[2]`` about the axis ``x = pos[0], y = pos[1]``."""
    return np.hypot(q[..., 0] - pos[..., 0], q[..., 1] - pos[..., 1]) - pos[..., 2]


def _shape_family(name: str, offsets: np.ndarray) -> tuple[Callable, np.ndarray, np.ndarray]:
    """``(sdf(q (..., 3), pos (3,)) in voxels, positions (P, 3), base orientations (B, 3, 3))``; ``offsets``:
    plane offsets (voxels from the block centre) of the plane family."""
    if name in ("floor", "ceiling", "wall"):
        pos = np.zeros((len(offsets), 3))
        pos[:, 2] = offsets
        if name == "floor":
            base = np.eye(3)[None]
        elif name == "ceiling":
            base = rot_x(math.pi)[None]  # normal -z: solid above, free below
        else:  # any horizontal normal: +z turned onto WALL_YAWS directions about up, 15 degrees apart
            base = np.stack([rot_z(2 * math.pi * k / WALL_YAWS) @ rot_y(math.pi / 2) for k in range(WALL_YAWS)])
        return _plane, pos, base
    if name == "edge":
        o = _offsets(5) * (PART_REACH / 6.4)  # within PART_REACH of the centre: both faces fill a share of the block
        pos = np.array([(a, b, 0.0) for a in o for b in o])
        # a room's concave edges at any yaw about up: wall-wall (vertical), floor-wall, ceiling-wall
        return _edge, pos, _yawed(_EDGE_FAMILIES, EDGE_YAWS)
    if name == "corner":
        o = _offsets(4) * (PART_REACH / 6.0)
        pos = np.array([(a, b, c) for a in o for b in o for c in o])
        return _corner, pos, _yawed(_CORNER_FAMILIES, EDGE_YAWS)  # floor and ceiling corners at any yaw
    if name == "pole":
        o = _offsets(5)
        pos = np.array([(a, b, r) for a in o for b in o for r in POLE_RADII])
        return _pole, pos, np.eye(3)[None]  # vertical cylinders along up, axis at (a, b), radius r
    check_query_name(name)
    raise AssertionError(name)  # check_query_name raised: every built-in name is handled above


def truncate(d: np.ndarray, truncation: tuple[float, float], behind: str) -> np.ndarray:
    """Signed distances (any shape, metres) -> truncated float32 metres, with voxels more than ``|d_min|``
    behind a surface per ``behind`` (see the package docstring)."""
    d_min, d_max = truncation
    if behind not in BEHIND:
        raise InvalidValueError(f"behind must be one of {BEHIND}, got {behind!r}")
    # clipped in the input's precision, then float32; the unobserved voxels set in place (a np.where with a
    # Python float made a float64 copy of the whole array: the plane check's largest cost)
    out = np.asarray(np.clip(d, d_min, d_max), dtype=np.float32)
    if behind == "unobserved":
        np.copyto(out, np.float32(d_max), where=d < d_min)
    return out


#: :func:`dedupe_blocks` keys rows by every this many voxels first (a prime: no stride along a grid axis).
_DEDUPE_STRIDE = 61


def dedupe_blocks(blocks: np.ndarray, *extra: np.ndarray) -> tuple[np.ndarray, ...]:
    """Drop repeated blocks ``(N, 16, 16, 16)`` (equal to 1e-4 normalised), keeping first occurrences in order;
    the ``extra`` arrays (first axis ``N``) are cut to the same rows. Returns ``(blocks, *extra)``."""
    flat = blocks.reshape(len(blocks), -1)

    def rounded(a: np.ndarray) -> np.ndarray:
        key = np.round(a, 4)
        key += 0.0  # -0.0 equals 0.0
        return key

    # a hash table of the rows' bytes, not a sort of 16 KiB rows (the wall's 2,856 blocks: a third of building its
    # model); keyed first by a sample of each row's voxels, and only rows whose samples agree compared in full
    groups: dict[bytes, list[int]] = {}
    for i, row in enumerate(rounded(flat[:, ::_DEDUPE_STRIDE])):
        groups.setdefault(row.tobytes(), []).append(i)
    keep = []
    for rows in groups.values():
        if len(rows) == 1:
            keep.extend(rows)
            continue
        first: dict[bytes, int] = {}
        keep.extend(i for i, row in zip(rows, rounded(flat[rows])) if first.setdefault(row.tobytes(), i) == i)
    if len(keep) == len(blocks):
        return (blocks, *extra)
    idx = np.sort(np.asarray(keep, np.int64))
    return (blocks[idx], *(e[idx] for e in extra))


def plane_offsets(offsets: int | str = "auto", *, voxel_size: float = 0.02,
                  truncation: tuple[float, float] = (-0.04, 0.1), behind: str = "unobserved") -> np.ndarray:
    """The plane offsets of the floor, ceiling and wall models, voxels from the block centre ``(7.5, 7.5, 7.5)``.

    ``offsets``: an int ``n`` (the midpoints of ``n`` equal parts of the block's extent ``[-0.5, 15.5]``; the
    paper's model is 15); ``"lattice"`` (one per voxel step, midway between the jumps of an unobserved-behind
    field: 17); ``"auto"``: ``"lattice"`` for ``behind="unobserved"``, 15 for ``"solid"`` (whose field
    changes continuously with the offset, so evenly spaced planes suffice).

    Returns
    -------
    np.ndarray
        ``(n,)`` float64, ascending.
    """
    if offsets == "auto":
        offsets = "lattice" if behind == "unobserved" else 15
    if offsets == "lattice":
        return _lattice_offsets(voxel_size, truncation)
    if isinstance(offsets, bool) or not isinstance(offsets, (int, np.integer)) or offsets < 1:
        raise InvalidValueError(f"offsets must be a positive int, 'lattice' or 'auto', got {offsets!r}")
    return _offsets(int(offsets))


def query_blocks(name: str, *, voxel_size: float = 0.02, truncation: tuple[float, float] = (-0.04, 0.1),
                 up: Sequence[float] = (0.0, 0.0, 1.0), rotations: Any = None, offsets: int | str = "auto",
                 behind: str = "unobserved", return_observed: bool = False,
                 stretch: Sequence[float] = (1.0,)) -> tuple[np.ndarray, ...]:
    """The normalised TSDF blocks of a built-in query shape.

    Shapes (defined with ``+z`` up, then rotated onto ``up``):

    ``"floor"``
        A horizontal plane, solid below and free space above, at heights spanning the block
        (:func:`plane_offsets`: the paper's model has 15; the default for fused, unobserved-behind maps has
        17, one per voxel step, because their field jumps where a layer passes ``|d_min|`` behind the floor).
    ``"ceiling"``
        The same plane upside down (solid above).
    ``"wall"``
        Vertical planes with :data:`WALL_YAWS` (24) horizontal normals 15 degrees apart (any wall is within 7.5
        degrees of one) at ``offsets`` positions.
    ``"edge"``
        A room's right-angled concave edges (wall-wall, floor-wall, ceiling-wall) at :data:`EDGE_YAWS` (12)
        yaws about up and 5 x 5 positions.
    ``"corner"``
        A room's concave corners (floor or ceiling with two walls) at 12 yaws and 4 x 4 x 4 positions.
    ``"pole"``
        Solid vertical cylinders along ``up`` (poles, table legs, pipes) with :data:`POLE_RADII` radii at
        5 x 5 axis positions.

    Parameters
    ----------
    name : str
        One of :data:`QUERY_NAMES`.
    voxel_size : float
        Metres per voxel of the map the query is for.
    truncation : tuple of float
        ``(d_min, d_max)`` metres of that map.
    up : sequence of 3 floats
        Up direction in the map's grid (normalised on use).
    rotations : None, "axis", "cone[:ANGLE[:COUNT]]", ConeRotations or (R, 3, 3) array
        Extra rotations (about ``up``'s frame) the model should be invariant to; each shape is sampled at
        every one. ``"axis"``: the 24 rotations of the cube (a floor model then also holds ceilings and
        walls); a cone: tilts within an angle plus a spin about ``up``.
    offsets : int, "lattice" or "auto"
        Plane offsets across the block (:func:`plane_offsets`; 15 in the paper).
    behind : {"unobserved", "solid"}
        See the :mod:`sdfcodec.search` docstring.
    return_observed : bool
        Also return which voxels a fused map would have observed (see ``observed`` below).
    stretch : sequence of float
        Field stretches to sample each shape at (1: an exact distance field; :data:`FUSED_STRETCH` for fused
        maps).

    Returns
    -------
    blocks : np.ndarray
        ``(M, 16, 16, 16)`` float32 normalised values in ``[0, 1]``, duplicates removed.
    rotations : np.ndarray
        ``(M, 3, 3)`` float32, each block's shape-to-grid rotation.
    positions : np.ndarray
        ``(M, 3)`` float32 voxels, the shape's position parameters in its own frame relative to the block
        centre ``(7.5, 7.5, 7.5)`` (for planes: ``(0, 0, offset)``, the plane passing ``offset`` voxels from the
        centre along its normal).
    observed : np.ndarray
        With ``return_observed`` only: ``(M, 16, 16, 16)`` bool, the voxels a camera in front of the surface
        observes (for ``behind="unobserved"`` all but those more than ``|d_min|`` behind it; all for
        ``"solid"``). A map with an observation mask encodes its blocks weighted by theirs
        (:func:`sdfcodec.map.observed.error_weights`); a query for it is encoded the same way.
    """
    check_truncation(*truncation)
    if not (np.isfinite(voxel_size) and voxel_size > 0):
        raise InvalidValueError(f"voxel_size must be a positive number of metres, got {voxel_size!r}")
    if behind not in BEHIND:
        raise InvalidValueError(f"behind must be one of {BEHIND}, got {behind!r}")
    sdf, pos, base = _shape_family(name, plane_offsets(offsets, voxel_size=voxel_size, truncation=truncation,
                                                       behind=behind))
    extra, _ = rotation_set(rotations)
    r_up = rotation_to(up)
    grid = np.stack(np.meshgrid(*[np.arange(BLOCK, dtype=np.float64) - _CENTRE] * 3, indexing="ij"), -1)
    plane = name in ("floor", "ceiling", "wall")
    # metres per voxel of each stretch, each product as a scalar multiply makes it
    scales = np.array([voxel_size * float(st) for st in stretch], np.float64)[None, :, None, None, None]
    blocks, rots, poss, seen = [], [], [], []
    # every position and stretch of one orientation at once: (P, S, 16, 16, 16), in the order a loop over
    # positions, then stretches, would make them (the same values, to the bit)
    for e in extra:
        for b in base:
            r = r_up @ e @ b
            q = grid @ r  # grid-to-shape coordinates: R^T p for each voxel position p
            ps = _reach(pos, r) if plane else pos
            if plane:  # a plane clipping a corner: nearly a block of solid or free space, no plane to match
                ps = ps[[_surface_voxels(q, p) >= MIN_SHAPE_SURFACE for p in ps]]
            if not len(ps):
                continue
            d = sdf(q, ps[:, None, None, None, :])[:, None] * scales
            blocks.append(normalise(truncate(d, truncation, behind), *truncation).reshape(-1, BLOCK, BLOCK, BLOCK))
            # what a camera in front of the surface observes: everything but the space more than |d_min| behind it
            # (fusion updates voxels down to d_min); an exact SDF is observed everywhere
            seen.append((d >= truncation[0] if behind == "unobserved" else np.ones(d.shape, bool))
                        .reshape(-1, BLOCK, BLOCK, BLOCK))
            rots.append(np.broadcast_to(r, (d.shape[0] * d.shape[1], 3, 3)))
            poss.append(np.repeat(ps, d.shape[1], axis=0))
    v = np.concatenate(blocks)
    out = dedupe_blocks(v, np.concatenate(rots).astype(np.float32), np.concatenate(poss).astype(np.float32),
                        np.concatenate(seen))
    return out if return_observed else out[:3]


def rotate_blocks(v: np.ndarray, rotations: np.ndarray) -> np.ndarray:
    """Resample normalised blocks ``(N, 16, 16, 16)`` under each rotation about the block centre (trilinear,
    nearest value beyond the block) -> ``(R * N, 16, 16, 16)``."""
    from scipy.ndimage import map_coordinates

    grid = np.stack(np.meshgrid(*[np.arange(BLOCK, dtype=np.float64) - _CENTRE] * 3, indexing="ij"), -1)
    out = []
    for r in rotations:
        src = (grid @ r + _CENTRE).reshape(-1, 3).T  # the rotated block at p shows the original at R^T p
        exact = np.allclose(src, np.round(src), atol=1e-9)
        for b in v:
            out.append(map_coordinates(b, np.round(src) if exact else src, order=0 if exact else 1,
                                       mode="nearest").reshape(BLOCK, BLOCK, BLOCK))
    return np.stack(out).astype(np.float32)


def probe_blocks(voxel_size: float, truncation: tuple[float, float]) -> np.ndarray:
    """Six fixed, generic blocks (tilted planes, a corner, a ball): encoding them tells whether two codecs
    agree, for models that carry descriptors only. ``(6, 16, 16, 16)`` normalised float32."""
    grid = np.stack(np.meshgrid(*[np.arange(BLOCK, dtype=np.float64) - _CENTRE] * 3, indexing="ij"), -1)
    ds = []
    for k, (a, b) in enumerate(((0.3, 0.2), (1.1, -0.4), (2.0, 0.9), (-0.7, 2.5))):
        n = np.array([math.sin(a) * math.cos(b), math.sin(a) * math.sin(b), math.cos(a)])
        ds.append(grid @ n - (k - 1.5) * 2.0)
    ds.append(_corner(grid @ rot_z(0.4) @ rot_x(0.3), np.array([-2.0, 1.0, -3.0])))
    ds.append(np.linalg.norm(grid - np.array([2.0, -1.0, 1.5]), axis=-1) - 5.0)
    return normalise(np.stack([truncate(d * voxel_size, truncation, "solid") for d in ds]), *truncation)


def check_query_name(name: str) -> None:
    """Raise :class:`InvalidValueError` naming the built-in queries unless ``name`` is one of them."""
    if name not in QUERY_NAMES:
        raise InvalidValueError(f"unknown query {name!r}; built-in queries are {', '.join(QUERY_NAMES)} (or pass "
                                "blocks, a QueryModel or the path of a saved one)")


def sample_shapes(name: str, count: int, *, voxel_size: float = 0.02, truncation: tuple[float, float] = (-0.04, 0.1),
                  up: Sequence[float] = (0.0, 0.0, 1.0), tilt_deg: float = 0.0, behind: str = "unobserved",
                  stretch: tuple[float, float] = (1.0, 1.0), seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """``count`` random instances of a built-in shape, with continuous parameters where a model samples a
    lattice: plane offsets uniform across the block's extent along their normal (:func:`_extent`; corner slivers
    redrawn), any wall, edge and corner yaw, edge and corner positions uniform within :data:`PART_REACH` voxels of
    the centre, each tilted uniformly within ``tilt_deg`` of ``up`` (random axis) and spun
    about it, the field stretched by a factor uniform in ``stretch`` (see :data:`FUSED_STRETCH`). What a map's
    clean instances of the shape look like, to calibrate a threshold on.

    Returns
    -------
    blocks, observed : np.ndarray
        ``(count, 16, 16, 16)`` float32 normalised values and bool observed voxels (see :func:`query_blocks`).
    """
    check_query_name(name)
    rng = np.random.default_rng([int(seed), 17])
    sdf, _, base = _shape_family(name, np.zeros(1))
    r_up = rotation_to(up)
    grid = np.stack(np.meshgrid(*[np.arange(BLOCK, dtype=np.float64) - _CENTRE] * 3, indexing="ij"), -1)
    cos_t = math.cos(math.radians(tilt_deg))
    ds = []
    for _ in range(int(count)):
        cz = rng.uniform(cos_t, 1.0)
        phi = rng.uniform(0.0, 2 * math.pi)
        sz = math.sqrt(max(0.0, 1.0 - cz * cz))
        tilt = rotation_to((sz * math.cos(phi), sz * math.sin(phi), cz))
        b = base[rng.integers(len(base))]
        if name == "wall":
            b = rot_z(rng.uniform(0.0, 2 * math.pi)) @ rot_y(math.pi / 2)
        elif name in ("edge", "corner"):  # any yaw, not only the model's
            fam = _EDGE_FAMILIES if name == "edge" else _CORNER_FAMILIES
            b = rot_z(rng.uniform(0.0, 2 * math.pi)) @ fam[rng.integers(len(fam))]
        spin = rot_z(rng.uniform(0.0, 2 * math.pi)) if name in ("floor", "ceiling") else np.eye(3)
        r = r_up @ tilt @ spin @ b
        q = grid @ r
        if name == "pole":
            p = np.array([rng.uniform(-6.0, 6.0), rng.uniform(-6.0, 6.0), rng.uniform(min(POLE_RADII),
                                                                                      max(POLE_RADII))])
        elif name in ("floor", "ceiling", "wall"):
            # a plane up to one voxel beyond the block's outer voxel layers is still its surface: the block on
            # each side of a surface between them holds it (its mesh needs both)
            ext = _extent(r)
            for _ in range(32):  # a clean instance is more than a corner sliver (the strict truth's rule)
                p = np.array([0.0, 0.0, rng.uniform(-ext, ext)])
                if _surface_voxels(q, p) >= MIN_SHAPE_SURFACE:
                    break
        else:  # edges and corners: where the model places them
            p = rng.uniform(-PART_REACH, PART_REACH, 3)
        ds.append(sdf(q, p) * voxel_size * rng.uniform(*stretch))
    d = np.stack(ds)  # truncated and masked at once: the same values as block by block
    seen = d >= truncation[0] if behind == "unobserved" else np.ones(d.shape, bool)
    return normalise(truncate(d, truncation, behind), *truncation), seen
