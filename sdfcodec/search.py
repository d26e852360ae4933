"""Descriptor search and selective expansion of compressed maps (the paper's section V-C, Fig. 7).

Similar blocks get similar codes, so a map's codes double as shape descriptors. A *query model* is a small set
of descriptors made by encoding shapes of interest with the map's own codec: the paper's floor model is the
TSDF of a horizontal plane at 15 offsets across a block. :func:`search` scores every coded block of a map by
its minimum squared distance to the set (one matrix product per streamed batch of chunks), selects by
threshold and/or top-k, and :func:`expand` decodes only the selected blocks (as blocks, a dense sub-volume or
a mesh). Nothing else of the map is decoded.

Conventions
-----------
* Block voxel ``(i, j, k)`` sits at ``(i, j, k)`` voxel units inside its block; shapes are posed about the
  block's centre ``(7.5, 7.5, 7.5)``, and the 15 plane offsets are the midpoints of 15 equal parts of the
  block's extent ``[-0.5, 15.5]`` (its voxels' cells), 1.07 voxels apart, so every plane that crosses a block
  is within 0.53 voxels of one of them.
* ``up`` is the world direction of "up" in the map's grid (default ``+z``). The shapes are defined with
  ``+z`` up and rotated onto ``up``: for a map whose gravity is not the grid's ``-z`` (the 7-Scenes kitchen),
  pass the true up direction.
* ``behind``: how the shapes treat voxels more than ``|d_min|`` behind a surface. ``"unobserved"`` (default)
  stores them as free space ``d_max``, which is what fusion produces (a camera never sees behind a surface,
  see ``sdfcodec/fusion.py``); ``"solid"`` clips them to ``d_min``, as a truncated exact SDF of a solid
  (``write_volume(sample_volume(...))``) does. Use the one that matches how the map was made.
* Scores are squared Euclidean distances between codes (float32). For ``pca`` maps (``mean="dataset"``)
  they equal squared distances between the blocks' projections onto the first ``L`` eigenshapes, in
  normalised units (``v = (d - d_min) / (d_max - d_min)``, summed over the 4096 voxels); for ``raw`` maps
  they are exact squared voxel distances.

Prefix levels
-------------
For prefix-ordered codecs (PCA), a query encoded with the map's codec and cut to its first ``L`` elements is
compared with the first ``L`` elements of the map's codes, reading only the code chunks that hold them (a
level-32 search of a 128-element map reads a quarter of the code bytes). Maps with different code sizes whose
bases share their leading components (pca-32/64/128 prefixes of one basis) give the same level-``L``
scores. Codecs whose codes are not prefix-ordered (``raw``, ``ae``) are searched at their full size only.

Bytes read are counted by wrapping the map's Zarr store (:class:`CountingStore`): what the search actually
fetched, per array (``codes``, ``state``, ``codec``, metadata), for any store (local, zip, HTTP...).

Query models are saved as ``.npz`` files of plain arrays (:func:`save_query`, :func:`load_query`, never
pickles): the descriptors, optionally the normalised shape blocks (so the model can be re-encoded for any
map), and JSON metadata in a uint8 array.

Evaluation helpers at the end (:func:`synthetic_room`, :func:`evaluate_retrieval`, :func:`bench_search`)
produce the precision/recall curves and throughput figures of ``docs/search.md``.
"""

from __future__ import annotations

import json
import math
import os
import time
import warnings
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Callable, Iterable, Mapping, Sequence

import numpy as np
import torch
import zarr
import zarr.abc.store

from ._validate import BLOCK
from .blocks import check_truncation, normalise
from .codec import Codec
from .errors import FormatError, InvalidValueError, SDFCodecWarning, ShapeError
from .header import BlockState
from .mapfile import Map, open_map, state_digest

__all__ = [
    "QUERY_NAMES",
    "BEHIND",
    "ConeRotations",
    "QueryModel",
    "SearchResult",
    "Expansion",
    "CountingStore",
    "axis_rotations",
    "cone_rotations",
    "rotation_to",
    "plane_offsets",
    "query_blocks",
    "build_query",
    "save_query",
    "load_query",
    "auto_threshold",
    "search",
    "expand",
    "LabelledRoom",
    "synthetic_room",
    "TRUTH",
    "pr_curve",
    "operating_points",
    "evaluate_retrieval",
    "bench_search",
]

#: The built-in named queries (see :func:`query_blocks`).
QUERY_NAMES: tuple[str, ...] = ("floor", "ceiling", "wall", "edge", "corner")
#: Ways of treating voxels more than ``|d_min|`` behind a surface (see the module docstring).
BEHIND: tuple[str, ...] = ("unobserved", "solid")

_QUERY_META = "__sdfcodec_query__"
QUERY_FORMAT = "sdfcodec-query"
QUERY_VERSION = 1
_CENTRE = (BLOCK - 1) / 2.0  # 7.5: the block's centre in voxel units (voxel i at position i)


# ------------------------------------------------------------------------------------------------ rotations
def axis_rotations() -> np.ndarray:
    """The 24 proper rotations of the cube (signed permutation matrices with determinant +1).

    Returns
    -------
    np.ndarray
        ``(24, 3, 3)`` float64, the identity first.
    """
    out = []
    for perm in ((0, 1, 2), (0, 2, 1), (1, 0, 2), (1, 2, 0), (2, 0, 1), (2, 1, 0)):
        for signs in np.ndindex(2, 2, 2):
            r = np.zeros((3, 3))
            for row, (col, s) in enumerate(zip(perm, signs)):
                r[row, col] = -1.0 if s else 1.0
            if np.linalg.det(r) > 0:
                out.append(r)
    return np.stack(out)


def rotation_to(direction: Sequence[float]) -> np.ndarray:
    """The smallest rotation taking ``+z`` onto ``direction`` (normalised on use).

    Returns
    -------
    np.ndarray
        ``(3, 3)`` float64; ``R @ (0, 0, 1)`` is the unit ``direction``.
    """
    d = np.asarray(direction, dtype=np.float64).reshape(3)
    n = np.linalg.norm(d)
    if not np.isfinite(n) or n < 1e-12:
        raise InvalidValueError(f"a direction needs a finite, non-zero vector, got {list(d)}")
    d = d / n
    z = np.array([0.0, 0.0, 1.0])
    c = float(z @ d)
    if c < -1 + 1e-12:  # opposite: half a turn about x
        return np.diag([1.0, -1.0, -1.0])
    v = np.cross(z, d)
    vx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + vx + vx @ vx / (1.0 + c)


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
        c, s = math.cos(psi), math.sin(psi)
        out.append(tilt @ np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]))
    return np.stack(out)


def _rotation_set(rotations: Any) -> tuple[np.ndarray, Any]:
    """``rotations`` argument -> ``((R, 3, 3) matrices, JSON description)``."""
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
            return _rotation_set(cone)
        raise InvalidValueError(f"rotations must be None, 'axis', 'cone[:ANGLE[:COUNT]]', a ConeRotations or "
                                f"(R, 3, 3) matrices; got {rotations!r}")
    if isinstance(rotations, ConeRotations):
        return (cone_rotations(rotations.angle_deg, rotations.count, spin=rotations.spin, seed=rotations.seed),
                rotations.to_json())
    if isinstance(rotations, Mapping) and "cone" in rotations:
        return _rotation_set(ConeRotations(rotations["cone"], rotations.get("count", 16), rotations.get("spin", True),
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


def _plane(q: np.ndarray, pos: np.ndarray) -> np.ndarray:
    return q[..., 2] - pos[2]  # solid below, free above (+z)


def _edge(q: np.ndarray, pos: np.ndarray) -> np.ndarray:
    """Concave edge along z: free where x > pos_x and y > pos_y (two walls seen from inside)."""
    x, y = q[..., 0] - pos[0], q[..., 1] - pos[1]
    nearest = np.minimum(x, y)
    return np.where(nearest > 0, nearest, -np.sqrt(np.minimum(x, 0) ** 2 + np.minimum(y, 0) ** 2))


def _corner(q: np.ndarray, pos: np.ndarray) -> np.ndarray:
    """Concave corner: free where x, y, z exceed pos (floor and two walls seen from inside)."""
    x, y, z = (q[..., i] - pos[i] for i in range(3))
    nearest = np.minimum(np.minimum(x, y), z)
    depth = np.sqrt(np.minimum(x, 0) ** 2 + np.minimum(y, 0) ** 2 + np.minimum(z, 0) ** 2)
    return np.where(nearest > 0, nearest, -depth)


def _rx(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0, 0], [0, c, -s], [0, s, c]])


def _ry(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0, s], [0, 1.0, 0], [-s, 0, c]])


def _rz(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def _shape_family(name: str, offsets: np.ndarray) -> tuple[Callable, np.ndarray, np.ndarray]:
    """``(sdf(q (..., 3), pos (3,)) in voxels, positions (P, 3), base orientations (B, 3, 3))``; ``offsets``:
    plane offsets (voxels from the block centre) of the plane family."""
    if name in ("floor", "ceiling", "wall"):
        pos = np.zeros((len(offsets), 3))
        pos[:, 2] = offsets
        if name == "floor":
            base = np.eye(3)[None]
        elif name == "ceiling":
            base = _rx(math.pi)[None]  # normal -z: solid above, free below
        else:  # normals +x, +y, -x, -y: +z turned onto each horizontal axis
            base = np.stack([_rz(k * math.pi / 2) @ _ry(math.pi / 2) for k in range(4)])
        return _plane, pos, base
    if name == "edge":
        o = _offsets(5)
        pos = np.array([(a, b, 0.0) for a in o for b in o])
        return _edge, pos, axis_rotations()  # the 12 axis-aligned concave edges of a room (deduplicated later)
    if name == "corner":
        o = _offsets(4)
        pos = np.array([(a, b, c) for a in o for b in o for c in o])
        return _corner, pos, axis_rotations()  # the 8 axis-aligned concave corners
    raise InvalidValueError(f"unknown query {name!r}; built-in queries are {', '.join(QUERY_NAMES)} (or pass "
                            "blocks, a QueryModel or the path of a saved one)")


def _truncate(d: np.ndarray, truncation: tuple[float, float], behind: str) -> np.ndarray:
    """Metres -> truncated metres, with voxels more than ``|d_min|`` behind a surface per ``behind``."""
    d_min, d_max = truncation
    out = np.clip(d, d_min, d_max)
    if behind == "unobserved":
        out = np.where(d < d_min, d_max, out)
    elif behind != "solid":
        raise InvalidValueError(f"behind must be one of {BEHIND}, got {behind!r}")
    return out.astype(np.float32)


def _dedupe(blocks: np.ndarray, *extra: np.ndarray) -> tuple[np.ndarray, ...]:
    """Drop repeated blocks (equal to 1e-4 normalised), keeping first occurrences in order."""
    key = np.round(blocks.reshape(len(blocks), -1), 4)
    _, first = np.unique(key, axis=0, return_index=True)
    keep = np.sort(first)
    return (blocks[keep], *(e[keep] for e in extra))


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
                 behind: str = "unobserved") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The normalised TSDF blocks of a built-in query shape.

    Shapes (defined with ``+z`` up, then rotated onto ``up``):

    ``"floor"``
        A horizontal plane, solid below and free space above, at heights spanning the block
        (:func:`plane_offsets`: the paper's model has 15; the default for fused, unobserved-behind maps has
        17, one per voxel step, because their field jumps where a layer passes ``|d_min|`` behind the floor).
    ``"ceiling"``
        The same plane upside down (solid above).
    ``"wall"``
        Vertical planes facing ``+x``, ``+y``, ``-x``, ``-y`` at ``offsets`` positions (60 descriptors).
    ``"edge"``
        The 12 axis-aligned concave edges of a room (floor-wall, wall-wall, ceiling-wall) at 5 x 5 positions.
    ``"corner"``
        The 8 axis-aligned concave corners of a room at 4 x 4 x 4 positions.

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
        See the module docstring.

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
    """
    check_truncation(*truncation)
    if not (np.isfinite(voxel_size) and voxel_size > 0):
        raise InvalidValueError(f"voxel_size must be a positive number of metres, got {voxel_size!r}")
    if behind not in BEHIND:
        raise InvalidValueError(f"behind must be one of {BEHIND}, got {behind!r}")
    sdf, pos, base = _shape_family(name, plane_offsets(offsets, voxel_size=voxel_size, truncation=truncation,
                                                       behind=behind))
    extra, _ = _rotation_set(rotations)
    r_up = rotation_to(up)
    grid = np.stack(np.meshgrid(*[np.arange(BLOCK, dtype=np.float64) - _CENTRE] * 3, indexing="ij"), -1)
    blocks, rots, poss = [], [], []
    for e in extra:
        for b in base:
            r = r_up @ e @ b
            q = grid @ r  # grid-to-shape coordinates: R^T p for each voxel position p
            for p in pos:
                blocks.append(_truncate(sdf(q, p) * voxel_size, truncation, behind))
                rots.append(r)
                poss.append(p)
    v = normalise(np.stack(blocks), *truncation)
    return _dedupe(v, np.asarray(rots, np.float32), np.asarray(poss, np.float32))


def _rotate_user_blocks(v: np.ndarray, rotations: np.ndarray) -> np.ndarray:
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


def _probe_blocks(voxel_size: float, truncation: tuple[float, float]) -> np.ndarray:
    """Six fixed, generic blocks (tilted planes, a corner, a ball): encoding them tells whether two codecs
    agree, for models that carry descriptors only. ``(6, 16, 16, 16)`` normalised float32."""
    grid = np.stack(np.meshgrid(*[np.arange(BLOCK, dtype=np.float64) - _CENTRE] * 3, indexing="ij"), -1)
    ds = []
    for k, (a, b) in enumerate(((0.3, 0.2), (1.1, -0.4), (2.0, 0.9), (-0.7, 2.5))):
        n = np.array([math.sin(a) * math.cos(b), math.sin(a) * math.sin(b), math.cos(a)])
        ds.append(grid @ n - (k - 1.5) * 2.0)
    ds.append(_corner(grid @ _rz(0.4) @ _rx(0.3), np.array([-2.0, 1.0, -3.0])))
    ds.append(np.linalg.norm(grid - np.array([2.0, -1.0, 1.5]), axis=-1) - 5.0)
    return normalise(np.stack([_truncate(d * voxel_size, truncation, "solid") for d in ds]), *truncation)


# -------------------------------------------------------------------------------------------- query model
@dataclass
class QueryModel:
    """A descriptor set: shapes of interest encoded with a map's codec.

    Attributes
    ----------
    name : str
        Free-text name (``"floor"`` for the built-in floor model).
    descriptors : np.ndarray
        ``(M, D)`` float32 codes of the shapes, from the codec described by ``codec_config``.
    codec_config : dict
        ``get_config()`` of the codec that encoded them (JSON).
    codec_state_sha256 : str or None
        Digest of that codec's learned state (``sdfcodec.mapfile.state_digest``), None without state.
    voxel_size : float
        Metres per voxel the shapes were sampled at.
    truncation : tuple of float
        ``(d_min, d_max)`` metres the shapes were truncated and normalised with.
    blocks : np.ndarray or None
        ``(M, 16, 16, 16)`` float32 normalised shape blocks. With them, :func:`search` re-encodes the model
        with any map's codec; without them, the descriptors are used only on maps whose codec agrees.
    rotations : np.ndarray or None
        ``(M, 3, 3)`` float32 shape-to-grid rotations (built-in shapes).
    positions : np.ndarray or None
        ``(M, 3)`` float32 shape positions in voxels (built-in shapes; see :func:`query_blocks`).
    spec : dict or None
        How a built-in query was made (``{"shape", "up", "rotations", "offsets", "behind"}``): a map with a
        different voxel size or truncation gets the query rebuilt from it.
    probe_codes : np.ndarray or None
        ``(6, D)`` float32 codes of fixed probe blocks under the same codec, used to check that a map's codec
        agrees with the one that made descriptors-only models.
    """

    name: str
    descriptors: np.ndarray
    codec_config: dict
    codec_state_sha256: str | None
    voxel_size: float
    truncation: tuple[float, float]
    blocks: np.ndarray | None = None
    rotations: np.ndarray | None = None
    positions: np.ndarray | None = None
    spec: dict | None = None
    probe_codes: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.descriptors = np.ascontiguousarray(self.descriptors, dtype=np.float32)
        if self.descriptors.ndim != 2 or not len(self.descriptors):
            raise ShapeError(f"descriptors must have shape (M, D) with M >= 1, got {self.descriptors.shape}")
        if not np.isfinite(self.descriptors).all():
            raise InvalidValueError("descriptors hold NaN or infinite values")
        m = len(self.descriptors)
        if self.blocks is not None:
            self.blocks = np.asarray(self.blocks, dtype=np.float32)
            if self.blocks.shape != (m, BLOCK, BLOCK, BLOCK):
                raise ShapeError(f"blocks must have shape ({m}, 16, 16, 16) to match the descriptors, got "
                                 f"{self.blocks.shape}")
        self.truncation = (float(self.truncation[0]), float(self.truncation[1]))

    def __len__(self) -> int:
        return len(self.descriptors)

    @property
    def code_size(self) -> int:
        """``D``, the descriptors' length."""
        return int(self.descriptors.shape[1])

    @property
    def up(self) -> np.ndarray:
        """``(3,)`` float64 unit up direction of a built-in query (``+z`` otherwise)."""
        u = np.asarray((self.spec or {}).get("up", (0.0, 0.0, 1.0)), dtype=np.float64)
        return u / np.linalg.norm(u)

    def matches_codec(self, codec: Codec, state_sha256: str | None = None) -> bool:
        """True when ``codec`` is the one that made the descriptors (same config and state digest)."""
        sha = state_sha256 if state_sha256 is not None else (state_digest(codec.state_dict())
                                                               if codec.state_dict() else None)
        return codec.get_config() == self.codec_config and sha == self.codec_state_sha256

    def without_blocks(self) -> "QueryModel":
        """A copy holding only descriptors (small; usable on maps whose codec agrees, checked by probes)."""
        return replace(self, blocks=None)


def _codec_sha(codec: Codec) -> str | None:
    state = codec.state_dict()
    return state_digest(state) if state else None


def build_query(shape: str | np.ndarray = "floor", *, map: Map | None = None, codec: Codec | None = None,
                voxel_size: float | None = None, truncation: tuple[float, float] | None = None,
                up: Sequence[float] = (0.0, 0.0, 1.0), rotations: Any = None, offsets: int | str = "auto",
                behind: str = "unobserved", keep_blocks: bool = True, name: str | None = None) -> QueryModel:
    """Build a query model by encoding shapes with a codec (the map's own, for searching that map).

    Parameters
    ----------
    shape : str or np.ndarray
        A built-in name (:data:`QUERY_NAMES`, see :func:`query_blocks`), or user blocks ``(N, 16, 16, 16)`` in
        metres (e.g. blocks cut from a map with ``Map.iter_blocks``), truncated to the map's range.
    map : Map, optional
        The map the query is for: its codec, voxel size and truncation are used.
    codec, voxel_size, truncation :
        Instead of ``map``: a fitted codec, metres per voxel (default 0.02) and ``(d_min, d_max)`` metres
        (default ``(-0.04, 0.1)``).
    up, rotations, offsets, behind :
        See :func:`query_blocks`. For user blocks, ``rotations`` resamples them (exactly for the 24 axis
        rotations, trilinearly otherwise) and ``up``, ``offsets``, ``behind`` are unused.
    keep_blocks : bool
        Store the normalised shape blocks in the model (re-encodable for other maps; 16 KiB each).
    name : str, optional
        Model name (default: the shape name, or ``"blocks"``).

    Returns
    -------
    QueryModel
        ``descriptors`` ``(M, D)`` float32 on the CPU.
    """
    if map is not None:
        codec = map.codec
        voxel_size, truncation = map.voxel_size, map.truncation
    if codec is None:
        raise InvalidValueError("build_query needs the map (map=...) or a fitted codec (codec=...) to encode with")
    voxel_size = 0.02 if voxel_size is None else float(voxel_size)
    truncation = (-0.04, 0.1) if truncation is None else tuple(float(t) for t in truncation)
    check_truncation(*truncation)
    rot = pos = spec = None
    if isinstance(shape, str):
        v, rot, pos = query_blocks(shape, voxel_size=voxel_size, truncation=truncation, up=up, rotations=rotations,
                                   offsets=offsets, behind=behind)
        _, rot_json = _rotation_set(rotations)
        spec = {"shape": shape, "up": [float(u) for u in np.asarray(up, dtype=np.float64) / np.linalg.norm(up)],
                "rotations": rot_json, "offsets": offsets if isinstance(offsets, str) else int(offsets),
                "behind": behind}
        name = name or shape
    else:
        b = np.asarray(shape)
        if b.dtype.kind != "f":
            raise InvalidValueError(f"query blocks must be floating-point metres, got dtype {b.dtype}")
        if b.ndim == 3:
            b = b[None]
        if b.ndim != 4 or b.shape[1:] != (BLOCK, BLOCK, BLOCK) or not len(b):
            raise ShapeError(f"query blocks must have shape (N, 16, 16, 16) (metres), got {b.shape}")
        if not np.isfinite(b).all():
            raise InvalidValueError("query blocks hold NaN or infinite values")
        v = normalise(np.clip(b, *truncation), *truncation)
        mats, _ = _rotation_set(rotations)
        if len(mats) > 1 or not np.allclose(mats[0], np.eye(3)):
            v = _dedupe(_rotate_user_blocks(v, mats))[0]
        name = name or "blocks"
    codes = np.asarray(codec.encode(v), dtype=np.float32)
    probes = np.asarray(codec.encode(_probe_blocks(voxel_size, truncation)), dtype=np.float32)
    return QueryModel(name=name, descriptors=codes, codec_config=codec.get_config(),
                      codec_state_sha256=_codec_sha(codec), voxel_size=voxel_size, truncation=truncation,
                      blocks=v if keep_blocks else None, rotations=rot, positions=pos, spec=spec, probe_codes=probes)


def save_query(model: QueryModel, path: str | os.PathLike) -> Path:
    """Write a query model as ``.npz`` (plain arrays, compressed, atomic); returns the path.

    Layout: ``descriptors`` and, when present, ``blocks``, ``rotations``, ``positions``, ``probe_codes``, plus
    ``__sdfcodec_query__``, a uint8 array of UTF-8 JSON ``{"format": "sdfcodec-query", "version": 1, "name",
    "codec_config", "codec_state_sha256", "voxel_size", "truncation", "spec"}``.
    """
    from .model import save_state_file

    meta = {"format": QUERY_FORMAT, "version": QUERY_VERSION, "name": model.name, "codec_config": model.codec_config,
            "codec_state_sha256": model.codec_state_sha256, "voxel_size": model.voxel_size,
            "truncation": list(model.truncation), "spec": model.spec}
    arrays = {"descriptors": model.descriptors,
              _QUERY_META: np.frombuffer(json.dumps(meta).encode(), dtype=np.uint8)}
    for key in ("blocks", "rotations", "positions", "probe_codes"):
        if getattr(model, key) is not None:
            arrays[key] = getattr(model, key)
    save_state_file(path, arrays)
    return Path(path)


def load_query(path: str | os.PathLike) -> QueryModel:
    """Read a query model written by :func:`save_query` (never unpickles).

    Raises
    ------
    FormatError
        Not a query model, or its metadata is broken. ``VersionError`` for a newer format version.
    """
    from .model import load_meta_file

    if not Path(path).is_file():
        raise InvalidValueError(f"no query model at {path}: give a built-in query ({', '.join(QUERY_NAMES)}) or the "
                                "path of a model written by sdfcodec.search.save_query")
    meta, arrays = load_meta_file(path, _QUERY_META, QUERY_FORMAT, QUERY_VERSION, "query model",
                                  "sdfcodec.search.save_query")
    if "descriptors" not in arrays:
        raise FormatError(f"{path}: query model lacks its descriptors array")
    try:
        return QueryModel(name=str(meta["name"]), descriptors=arrays["descriptors"], codec_config=meta["codec_config"],
                          codec_state_sha256=meta["codec_state_sha256"], voxel_size=float(meta["voxel_size"]),
                          truncation=tuple(meta["truncation"]), blocks=arrays.get("blocks"),
                          rotations=arrays.get("rotations"), positions=arrays.get("positions"),
                          spec=meta.get("spec"), probe_codes=arrays.get("probe_codes"))
    except KeyError as e:
        raise FormatError(f"{path}: query metadata lacks {e}") from e


# ----------------------------------------------------------------------------------------- store counting
class CountingStore(zarr.storage.WrapperStore):
    """A read-through Zarr store wrapper that counts the bytes it returns, per top-level array name
    (``codes``, ``state``, ``codec``, ``weights``) and ``meta`` for ``zarr.json`` metadata documents."""

    def __init__(self, store: zarr.abc.store.Store):
        super().__init__(store)
        self.bytes: dict[str, int] = {}
        self.keys: list[str] = []

    def _count(self, key: str, buf) -> None:
        if buf is None:
            return
        kind = "meta" if key.endswith("zarr.json") else key.split("/", 1)[0]
        self.bytes[kind] = self.bytes.get(kind, 0) + len(buf)
        self.keys.append(key)

    async def get(self, key, prototype, byte_range=None):
        buf = await self._store.get(key, prototype, byte_range)
        self._count(key, buf)
        return buf

    async def get_partial_values(self, prototype, key_ranges):
        out = await self._store.get_partial_values(prototype, key_ranges)
        for (key, _), buf in zip(key_ranges, out):
            self._count(key, buf)
        return out


def _counting_view(m: Map) -> tuple[Map, CountingStore]:
    """The same map read through a :class:`CountingStore` (shares the header and any loaded codec)."""
    if m.writable:
        raise InvalidValueError(f"{m.location} is still being written; leave the create_map block (commit) and "
                                "search the map with sdfcodec.open_map")
    group = m._group  # the map's Zarr group: re-opened over a counting wrapper of its store
    store = CountingStore(group.store)
    view = Map(zarr.open_group(store, mode="r", path=group.path or None, zarr_format=3), m.header, m.location,
               max_decode_bytes=m.max_decode_bytes)
    view._codec = m._codec
    return view, store


def _code_chunk_bytes(m: Map, level: int | None = None) -> int | None:
    """Bytes on disk of the map's code chunks holding elements ``[0, level)`` (all when None); local
    directory maps only (None otherwise)."""
    root = Path(m.location) / "codes" / "c"
    if "://" in m.location or not root.is_dir():
        return None
    cc = m.header.codes.chunk_code
    last = -(-(level or m.code_size) // cc)
    total = 0
    for f in root.rglob("*"):
        if f.is_file() and f.name.isdigit() and int(f.name) < last:
            total += f.stat().st_size
    return total


# ---------------------------------------------------------------------------------------------- searching
@dataclass
class SearchResult:
    """What :func:`search` found.

    Attributes
    ----------
    coords : np.ndarray
        ``(N, 3)`` int64 block indices of the selected blocks, best (lowest score) first.
    scores : np.ndarray
        ``(N,)`` float32 minimum squared code distance of each to the query's descriptors (see the module
        docstring for units).
    nearest : np.ndarray
        ``(N,)`` int64 index of the nearest descriptor (into ``query.descriptors``; for the floor model, which
        plane offset).
    level : int
        Code elements compared (``L``).
    query : QueryModel
        The model as used (encoded with the map's codec).
    threshold, top :
        The selection asked for (None: not used).
    stats : dict
        ``blocks_scored`` (every coded block), ``selected``, ``descriptors``, ``level``, ``code_size``,
        ``bytes_read`` (dict per array: ``codes``, ``state``, ``codec``, ``meta``), ``code_bytes_read``,
        ``code_bytes_full`` (all code chunks of the map on disk; local maps, else None),
        ``code_bytes_level`` (the chunks holding the first ``L`` elements), ``seconds``, ``blocks_per_s``,
        ``device``.
    all_coords, all_scores : np.ndarray or None
        Every coded block and its score (``keep_scores=True`` only): ``(B, 3)`` int64 and ``(B,)`` float32.
    """

    coords: np.ndarray
    scores: np.ndarray
    nearest: np.ndarray
    level: int
    query: QueryModel
    threshold: float | None
    top: int | None
    stats: dict = field(default_factory=dict)
    all_coords: np.ndarray | None = None
    all_scores: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.coords)

    def to_json(self, blocks: bool = True) -> dict:
        """JSON-able summary; with ``blocks``, every selected block as ``{"coords": [x, y, z], "score": s}``."""
        out = {"query": self.query.name, "level": self.level, "threshold": self.threshold, "top": self.top,
               **{k: v for k, v in self.stats.items()}}
        if blocks:
            out["blocks"] = [{"coords": [int(c) for c in xyz], "score": float(s)}
                             for xyz, s in zip(self.coords, self.scores)]
        return out


def _default_device(device: str | torch.device | None) -> torch.device:
    if device is None:
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(device)


class _Scorer:
    """Minimum squared distance of codes to descriptors: ``min_m |c|^2 - 2 c.q_m + |q_m|^2``, one matrix
    product per batch. numpy's BLAS on the CPU, torch on other devices."""

    def __init__(self, descriptors: np.ndarray, device: torch.device):
        q = np.ascontiguousarray(descriptors, dtype=np.float32)
        self.device = device
        self.qq = np.einsum("ij,ij->i", q, q)
        self.qt = np.ascontiguousarray(-2.0 * q.T)  # (L, M): the -2 folded into the product
        if device.type != "cpu":
            self.tqt = torch.from_numpy(self.qt).to(device)
            self.tqq = torch.from_numpy(self.qq).to(device)

    def __call__(self, codes: np.ndarray | torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
        """``(n, L)`` float32 codes -> scores ``(n,)`` float32 and nearest index ``(n,)`` int64 (numpy)."""
        if self.device.type == "cpu":
            c = np.asarray(codes, dtype=np.float32)
            g = c @ self.qt
            g += self.qq
            idx = g.argmin(axis=1)
            s = np.take_along_axis(g, idx[:, None], axis=1)[:, 0]
            s += np.einsum("ij,ij->i", c, c)
            np.maximum(s, 0.0, out=s)  # rounding can take an exact match a hair below zero
            return s, idx
        c = (codes if isinstance(codes, torch.Tensor) else torch.from_numpy(np.asarray(codes))).to(self.device)
        g = torch.addmm(self.tqq, c, self.tqt)
        s, idx = g.min(dim=1)
        s = (s + (c * c).sum(dim=1)).clamp_(min=0.0)
        return s.cpu().numpy(), idx.cpu().numpy()


def _resolve_query(query: Any, m: Map, codec: Codec) -> QueryModel:
    """Any accepted query -> a model whose descriptors come from ``codec`` (the map's) or agree with it."""
    if isinstance(query, (str, os.PathLike)) and not (isinstance(query, str) and query in QUERY_NAMES):
        p = Path(query)
        if p.suffix == ".npz" or p.is_file():
            query = load_query(p)
        elif isinstance(query, str):
            _shape_family(query, _offsets(1))  # raises the "unknown query" error naming the built-ins
    if isinstance(query, str):
        return build_query(query, map=m)
    if isinstance(query, np.ndarray):
        return build_query(query, map=m)
    if not isinstance(query, QueryModel):
        raise InvalidValueError(f"query must be a built-in name {QUERY_NAMES}, the path of a saved query model, "
                                f"a QueryModel or blocks (N, 16, 16, 16); got {type(query).__name__}")
    same_geometry = (math.isclose(query.voxel_size, m.voxel_size, rel_tol=1e-6)
                     and np.allclose(query.truncation, m.truncation, rtol=1e-6, atol=1e-9))
    if not same_geometry and query.spec is not None:
        s = query.spec
        return build_query(s["shape"], map=m, up=s["up"], rotations=s["rotations"], offsets=s["offsets"],
                           behind=s["behind"], keep_blocks=query.blocks is not None, name=query.name)
    if not same_geometry:
        warnings.warn(f"query model {query.name!r} was made for voxel size {query.voxel_size} m and truncation "
                      f"{query.truncation}, but the map has {m.voxel_size} m and {m.truncation}; its blocks are "
                      "used as they are (rebuild the model for this map to compare like with like)",
                      SDFCodecWarning, stacklevel=3)
    if query.matches_codec(codec, m.header.codec.state_sha256):
        return query
    if query.blocks is not None:
        return replace(query, descriptors=np.asarray(codec.encode(query.blocks), dtype=np.float32),
                       codec_config=codec.get_config(), codec_state_sha256=_codec_sha(codec),
                       probe_codes=np.asarray(codec.encode(_probe_blocks(query.voxel_size, query.truncation)),
                                              dtype=np.float32))
    # descriptors only: usable where the map's codec encodes the probe blocks to the same leading elements
    if query.probe_codes is None:
        raise InvalidValueError(f"query model {query.name!r} holds neither shape blocks nor probe codes, and its "
                                f"codec ({query.codec_config}) is not the map's; rebuild it with "
                                "build_query(..., map=the_map)")
    k = min(query.code_size, m.code_size)
    if not m.header.codes.prefix_ordered and query.code_size != m.code_size:
        raise InvalidValueError(f"query model {query.name!r} has {query.code_size}-element descriptors but the map's "
                                f"{m.header.codec.id!r} codes ({m.code_size}) are not prefix-ordered; rebuild the "
                                "model with build_query(..., map=the_map)")
    mine = np.asarray(codec.encode(_probe_blocks(query.voxel_size, query.truncation)), dtype=np.float32)[:, :k]
    theirs = query.probe_codes[:, :k]
    if not np.allclose(mine, theirs, rtol=1e-3, atol=1e-3 * max(1.0, float(np.abs(theirs).max()))):
        raise InvalidValueError(f"query model {query.name!r} was encoded by a different codec or basis than the map "
                                f"{m.location} (their first {k} code elements disagree), so its descriptors cannot "
                                "be compared with the map's codes; rebuild it with build_query(..., map=the_map), or "
                                "keep its blocks (keep_blocks=True) so it can be re-encoded")
    return query


def _search_level(m: Map, query: QueryModel, level: int | None) -> int:
    size, prefix = m.code_size, m.header.codes.prefix_ordered
    if level is None:
        level = min(size, query.code_size)
    if isinstance(level, bool) or not isinstance(level, (int, np.integer)) or not 1 <= level <= size:
        raise InvalidValueError(f"level must be an int in 1..{size} (the map's code size), got {level!r}")
    if level < size and not prefix:
        raise InvalidValueError(f"the map's {m.header.codec.id!r} codes are not prefix-ordered, so their first "
                                f"{level} of {size} elements are not a coarser descriptor and a prefix search is "
                                f"meaningless; search at the full size (omit level / --level), or encode the map "
                                "with a prefix-ordered codec such as pca")
    if level > query.code_size:
        raise InvalidValueError(f"level {level} exceeds the query's {query.code_size}-element descriptors; use a "
                                f"level <= {query.code_size}")
    return int(level)


#: :func:`auto_threshold`'s fraction of the model's median nearest-neighbour squared distance.
AUTO_FRACTION = 0.15


def auto_threshold(model: QueryModel, level: int | None = None, codec: Codec | None = None) -> float:
    """A default threshold from the model's own resolution: ``AUTO_FRACTION`` (0.15) times the median squared
    distance between each descriptor and its nearest other descriptor, over the first ``level`` elements.
    For a built-in model sampled over extra rotations, the spacing is that of its unrotated shapes (rebuilt
    with ``codec``, the one that made the descriptors), so rotation sampling does not tighten the threshold.

    For the default floor model (17 planes a voxel apart) this gives 7.2 / 12.8 / 16.8 at levels 32 / 64 / 128
    with the shipped eigenshapes, close to the thresholds that maximise F1 on synthetic rooms (6.9 / 13.0 /
    23.7, docs/search.md). It is a heuristic: pick a threshold from a PR curve, or use ``top``, when it
    matters.

    Raises
    ------
    InvalidValueError
        The model has a single descriptor (no spacing to scale from): give a threshold or ``top``.
    """
    spec = model.spec
    if spec is not None and spec.get("rotations", "none") != "none" and codec is not None:
        model = build_query(spec["shape"], codec=codec, voxel_size=model.voxel_size, truncation=model.truncation,
                            up=spec["up"], offsets=spec["offsets"], behind=spec["behind"], keep_blocks=False)
    q = model.descriptors[:, :level] if level else model.descriptors
    if len(q) < 2:
        raise InvalidValueError(f"query model {model.name!r} has one descriptor, so no automatic threshold can be "
                                "derived; pass threshold= (--threshold) or top= (--top)")
    d = np.einsum("ij,ij->i", q, q)[:, None] - 2 * q @ q.T + np.einsum("ij,ij->i", q, q)[None]
    np.fill_diagonal(d, np.inf)
    return float(AUTO_FRACTION * np.median(np.maximum(d.min(axis=1), 0.0)))


def search(map: Map | str | os.PathLike, query: Any = "floor", *, level: int | None = None,
           threshold: float | str | None = None, top: int | None = None, device: str | torch.device | None = None,
           keep_scores: bool = False, chunks_per_batch: int = 8) -> SearchResult:
    """Score every coded block of a map against a query model and select the closest.

    Streams the map's codes a few chunks at a time (``Map.iter_codes``), reading only the code chunks that
    hold the first ``level`` elements; memory is bounded by the batch plus the selection (and, with
    ``keep_scores``, 28 bytes per coded block).

    Parameters
    ----------
    map : Map or path
        A committed map (open_map), or its path/URL.
    query : str, path, QueryModel or np.ndarray
        A built-in name (:data:`QUERY_NAMES`; built for this map with :func:`build_query` defaults), the path
        of a saved model (``.npz``), a :class:`QueryModel` (re-encoded with the map's codec when it has
        blocks; descriptors-only models must agree with the map's codec), or user blocks ``(N, 16, 16, 16)``
        in metres.
    level : int, optional
        Compare the first ``level`` code elements (prefix-ordered codecs; default: all the map and query
        have in common).
    threshold : float or "auto", optional
        Select blocks whose score is ``<= threshold``; ``"auto"``: :func:`auto_threshold` of the model.
    top : int, optional
        Select at most ``top`` best blocks (with ``threshold``: the best ``top`` under it). With neither,
        every coded block is returned.
    device : str or torch.device, optional
        Where the distances are computed; default CUDA when available, else the CPU.
    keep_scores : bool
        Also return every coded block's coordinates and score (for pictures and PR curves).
    chunks_per_batch : int
        Code chunks read per step (memory vs. call overhead).

    Returns
    -------
    SearchResult

    Raises
    ------
    InvalidValueError
        A prefix level on a map whose codes are not prefix-ordered, a bad level/threshold/top, or a
        descriptors-only model made by another codec.
    """
    t0 = time.perf_counter()
    m = map if isinstance(map, Map) else open_map(map)
    if threshold is not None and threshold != "auto" and (isinstance(threshold, (str, bool)) or not (
            np.isfinite(threshold) and threshold >= 0)):
        raise InvalidValueError(f"threshold must be a finite squared distance >= 0 or 'auto', got {threshold!r}")
    if top is not None and (isinstance(top, bool) or not isinstance(top, (int, np.integer)) or top < 1):
        raise InvalidValueError(f"top must be a positive int, got {top!r}")
    view, store = _counting_view(m)
    codec = view.codec  # loads (and counts) the codec state unless the map already holds it
    if m._codec is None:
        m._codec = codec
    model = _resolve_query(query, m, codec)
    lv = _search_level(m, model, level)
    if threshold == "auto":
        threshold = auto_threshold(model, lv, codec)
    dev = _default_device(device)
    scorer = _Scorer(model.descriptors[:, :lv], dev)

    sel_c, sel_s, sel_i = np.zeros((0, 3), np.int64), np.zeros(0, np.float32), np.zeros(0, np.int64)
    all_c, all_s = [], []
    n_scored = 0
    for coords, codes in view.iter_codes(level=lv, chunks_per_batch=chunks_per_batch):
        s, idx = scorer(codes)
        n_scored += len(s)
        if keep_scores:
            all_c.append(coords)
            all_s.append(s)
        keep = np.ones(len(s), bool) if threshold is None else s <= threshold
        if not keep.any():
            continue
        sel_c = np.concatenate([sel_c, coords[keep]])
        sel_s = np.concatenate([sel_s, s[keep]])
        sel_i = np.concatenate([sel_i, idx[keep]])
        if top is not None and len(sel_s) > top:
            # running top-k: memory stays O(top + batch)
            part = np.argpartition(sel_s, top - 1)[:top]
            sel_c, sel_s, sel_i = sel_c[part], sel_s[part], sel_i[part]
    order = np.lexsort((sel_c[:, 2], sel_c[:, 1], sel_c[:, 0], sel_s))
    sel_c, sel_s, sel_i = sel_c[order], sel_s[order], sel_i[order]
    if top is not None:  # ties at the cut: the lexsort above makes the kept set deterministic only here
        sel_c, sel_s, sel_i = sel_c[:top], sel_s[:top], sel_i[:top]
    seconds = time.perf_counter() - t0
    stats = {
        "map": m.location, "codec": m.header.codec.id, "code_size": m.code_size, "level": lv,
        "descriptors": len(model), "blocks_scored": n_scored, "selected": int(len(sel_c)),
        "bytes_read": dict(store.bytes), "code_bytes_read": int(store.bytes.get("codes", 0)),
        "code_bytes_level": _code_chunk_bytes(m, lv), "code_bytes_full": _code_chunk_bytes(m),
        "seconds": seconds, "blocks_per_s": n_scored / seconds if seconds > 0 else None, "device": str(dev),
    }
    return SearchResult(
        coords=sel_c, scores=sel_s.astype(np.float32), nearest=sel_i, level=lv, query=model, threshold=threshold,
        top=top, stats=stats,
        all_coords=np.concatenate(all_c) if all_c else (np.zeros((0, 3), np.int64) if keep_scores else None),
        all_scores=np.concatenate(all_s) if all_s else (np.zeros(0, np.float32) if keep_scores else None))


# ---------------------------------------------------------------------------------------------- expanding
@dataclass
class Expansion:
    """Selected blocks decoded from a map (:func:`expand`).

    Attributes
    ----------
    coords : np.ndarray
        ``(N, 3)`` int64 block indices.
    blocks : np.ndarray
        ``(N, 16, 16, 16)`` float32 metres (voxels ``(x, y, z)``), decoded at ``level``.
    origin : np.ndarray
        ``(3,)`` float64 metres, world position of the map's voxel ``(0, 0, 0)``.
    voxel_size : float
    truncation : tuple of float
    level : int
    dense : np.ndarray or None
        ``as_="dense"``: ``(16 nx, 16 ny, 16 nz)`` float32 metres over the selected blocks' bounding box,
        ``d_max`` wherever no selected block is (nothing else is decoded).
    dense_offset : np.ndarray or None
        ``(3,)`` int64 map voxel index of ``dense[0, 0, 0]`` (world position ``origin + voxel_size * offset``).
    mesh : open3d.geometry.TriangleMesh or None
        ``as_="mesh"``: marching-cubes mesh of the selected blocks (world metres).
    stats : dict
        ``blocks_decoded``, ``coded_blocks`` (in the whole map), ``code_bytes_read`` (chunks fetched to get
        the selected codes), ``code_bytes_full`` (all code chunks on disk; local maps), ``bytes_read`` (per
        array), ``seconds``.
    """

    coords: np.ndarray
    blocks: np.ndarray
    origin: np.ndarray
    voxel_size: float
    truncation: tuple[float, float]
    level: int
    dense: np.ndarray | None = None
    dense_offset: np.ndarray | None = None
    mesh: Any = None
    stats: dict = field(default_factory=dict)


def expand(map: Map | str | os.PathLike, selection: SearchResult | np.ndarray, as_: str = "blocks", *,
           level: int | None = None, device: str | torch.device | None = None) -> Expansion:
    """Decode only the selected blocks of a map.

    Parameters
    ----------
    map : Map or path
        The map that was searched.
    selection : SearchResult or np.ndarray
        A search result, or block indices ``(N, 3)`` of coded blocks.
    as_ : {"blocks", "dense", "mesh"}
        ``"blocks"``: the decoded blocks; ``"dense"``: also a dense sub-volume over their bounding box;
        ``"mesh"``: also a marching-cubes mesh (``sdfcodec.fusion.mesh_from_blocks``, open3d).
    level : int, optional
        Decode from the first ``level`` code elements (default: the full code, the best reconstruction,
        whatever level the search compared).
    device : str or torch.device, optional
        Where to decode (default CUDA when available, else the CPU); results are numpy.

    Returns
    -------
    Expansion
    """
    t0 = time.perf_counter()
    if as_ not in ("blocks", "dense", "mesh"):
        raise InvalidValueError(f"as_ must be 'blocks', 'dense' or 'mesh', got {as_!r}")
    m = map if isinstance(map, Map) else open_map(map)
    coords = selection.coords if isinstance(selection, SearchResult) else np.asarray(selection)
    if coords.ndim != 2 or coords.shape[1] != 3 or coords.dtype.kind not in "iu":
        raise ShapeError(f"selected block coords must be an integer (N, 3) array, got {coords.shape} {coords.dtype}")
    coords = coords.astype(np.int64)
    view, store = _counting_view(m)
    lv = view._level(level)
    dev = _default_device(device)
    states = view.block_states()
    grid = np.asarray(m.grid_blocks)
    if len(coords) and (coords.min() < 0 or np.any(coords >= grid)):
        raise InvalidValueError(f"selected blocks lie outside the map's block grid {tuple(grid)}")
    if len(coords) and np.any(states[tuple(coords.T)] != BlockState.CODED):
        raise InvalidValueError("some selected blocks are not coded in this map (empty or unobserved): select from "
                                "a search of this map")
    codec = view.codec
    if m._codec is None:
        m._codec = codec
    d_min, d_max = m.truncation
    blocks = np.empty((len(coords), BLOCK, BLOCK, BLOCK), np.float32)
    if codec.halo:
        # codecs that need neighbour context: decode each block's region (the map reader adds the context)
        for i, c in enumerate(coords):
            region = tuple((int(a) * BLOCK, min(int(a + 1) * BLOCK, n)) for a, n in zip(c, m.shape_voxels))
            out = view.decode_region(region, level=lv, device=dev).cpu().numpy()
            blocks[i] = d_max
            blocks[i][tuple(slice(0, s) for s in out.shape)] = out
    elif len(coords):
        # group the selected blocks by code chunk: each chunk holding one is read once, at level lv
        cb = m.header.codes.chunk_blocks
        arr = view._group["codes"]
        chunk_of = coords // cb
        order = np.lexsort(chunk_of.T[::-1])
        bounds = np.flatnonzero(np.any(np.diff(chunk_of[order], axis=0) != 0, axis=1)) + 1
        codes = np.empty((len(coords), lv), np.float32)
        for lo, hi in zip(np.r_[0, bounds], np.r_[bounds, len(order)]):
            idx = order[lo:hi]
            ch = chunk_of[idx[0]]
            box = tuple(slice(int(c) * cb, min(int(c) * cb + cb, g)) for c, g in zip(ch, grid))
            chunk = view._read(arr, (*box, slice(0, lv)))
            codes[idx] = chunk[tuple((coords[idx] - ch * cb).T)]
        for i in range(0, len(coords), 65536):
            v = codec.decode(torch.from_numpy(codes[i:i + 65536]).to(dev))
            blocks[i:i + 65536] = (v * (d_max - d_min) + d_min).cpu().numpy()
    out = Expansion(coords=coords, blocks=blocks, origin=np.asarray(m.origin, np.float64), voxel_size=m.voxel_size,
                    truncation=m.truncation, level=lv)
    if as_ == "dense" and len(coords):
        lo, hi = coords.min(axis=0), coords.max(axis=0) + 1
        nbytes = int(np.prod(hi - lo)) * BLOCK ** 3 * 4
        if nbytes > m.max_decode_bytes:
            raise InvalidValueError(f"the selected blocks' bounding box needs {nbytes / 2**30:.1f} GiB as a dense "
                                    f"volume, above the limit of {m.max_decode_bytes / 2**30:.1f} GiB; use "
                                    "as_='blocks' or raise max_decode_bytes in open_map()")
        dense = np.full(tuple(int(n) * BLOCK for n in hi - lo), d_max, np.float32)
        for c, b in zip(coords - lo, blocks):
            dense[c[0] * BLOCK:(c[0] + 1) * BLOCK, c[1] * BLOCK:(c[1] + 1) * BLOCK, c[2] * BLOCK:(c[2] + 1) * BLOCK] = b
        out.dense, out.dense_offset = dense, lo * BLOCK
    elif as_ == "dense":
        out.dense, out.dense_offset = np.full((0, 0, 0), d_max, np.float32), np.zeros(3, np.int64)
    if as_ == "mesh":
        from .fusion import mesh_from_blocks

        out.mesh = mesh_from_blocks(coords, blocks, origin=m.origin, voxel_size=m.voxel_size, truncation=m.truncation)
    out.stats = {"blocks_decoded": int(len(coords)), "coded_blocks": int((states == BlockState.CODED).sum()),
                 "level": lv, "code_bytes_read": int(store.bytes.get("codes", 0)),
                 "code_bytes_full": _code_chunk_bytes(m), "bytes_read": dict(store.bytes),
                 "seconds": time.perf_counter() - t0}
    return out


# ------------------------------------------------------------------------------- evaluation: labelled rooms
@dataclass
class LabelledRoom:
    """A synthetic room TSDF with analytic ground truth (from :func:`synthetic_room`).

    Attributes
    ----------
    volume : np.ndarray
        ``(X, Y, Z)`` float32 metres, truncated; voxel ``(i, j, k)`` at ``origin + voxel_size * (i, j, k)``.
    origin : np.ndarray
        ``(3,)`` float64 metres (use it as the map's origin).
    voxel_size : float
    truncation : tuple of float
    scene : sdfcodec.data.render.RoomScene
        The room's exact primitives, posed in the same world frame, with labels (floor, wall, ceiling,
        furniture).
    rotation : np.ndarray
        ``(3, 3)`` room-to-world rotation (yaw, then tilt); the room's interior is
        ``rotation @ [0, size]`` per axis.
    size : tuple of float
        Interior extent metres (room frame).
    up : np.ndarray
        ``(3,)`` the room's up direction in the world (``rotation @ z``).
    behind : str
        How voxels behind surfaces were stored (see the module docstring).
    """

    volume: np.ndarray
    origin: np.ndarray
    voxel_size: float
    truncation: tuple[float, float]
    scene: Any
    rotation: np.ndarray
    size: tuple[float, float, float]
    up: np.ndarray
    behind: str

    _OBSERVED_MARGIN = 0.15  # metres beyond the interior still observed (inside the 0.2 m slabs)

    def observed(self, points: np.ndarray) -> np.ndarray:
        """``(...)`` bool: points inside the room's observed region (interior plus 0.15 m, within the slabs)."""
        local = np.asarray(points, dtype=np.float64) @ self.rotation  # world -> room frame (R^T p)
        mg = self._OBSERVED_MARGIN
        return np.all((local >= -mg) & (local <= np.asarray(self.size) + mg), axis=-1)

    def block_labels(self, coords: np.ndarray, up_tolerance_deg: float = 20.0) -> dict:
        """Per block, what its surface is: fractions of its *surface voxels* (voxels within one voxel of the
        exact surface, so that both blocks on either side of a surface that passes between them count it: a
        mesh of that surface needs both) that are

        ``"floor"``
            nearest to the floor primitive (``RoomScene.floor_blocks``'s definition);
        ``"up"``
            on an upward-facing surface (the exact SDF's gradient within ``up_tolerance_deg`` of ``up``):
            the floor and the tops of furniture (tables, cabinets, cylinders) alike.

        Also ``"floor_cover"`` and ``"up_cover"``: the fraction of the block's 256 columns (along the grid
        axis nearest ``up``) holding such a surface voxel, and ``"surface_voxels"``: the count. Blocks without
        surface voxels get fractions 0.

        Parameters
        ----------
        coords : np.ndarray
            ``(N, 3)`` int block indices.

        Returns
        -------
        dict of str to np.ndarray
            ``(N,)`` float32 fractions (``"floor"``, ``"up"``, ``"floor_cover"``, ``"up_cover"``) and int64
            counts (``"surface_voxels"``).
        """
        from .data.render import LABELS

        coords = np.asarray(coords, dtype=np.int64).reshape(-1, 3)
        vs = self.voxel_size
        band = vs
        n = len(coords)
        # the volume holds the exact distance wherever it is within the truncation, so surface voxels come
        # from it; only they are evaluated primitive by primitive (nearest label, gradient)
        pad = [(0, (-s) % BLOCK) for s in self.volume.shape]
        vol = np.pad(self.volume, pad, constant_values=self.truncation[1])
        g = [s // BLOCK for s in vol.shape]
        view = vol.reshape(g[0], BLOCK, g[1], BLOCK, g[2], BLOCK).transpose(0, 2, 4, 1, 3, 5)
        blk = view[tuple(coords.T)].reshape(n, -1)  # (n, 4096)
        surf = np.abs(blk) <= band
        which, vox = np.nonzero(surf)
        local = np.stack(np.unravel_index(vox, (BLOCK,) * 3), -1)
        pts = self.origin + vs * (BLOCK * coords[which] + local).astype(np.float64)  # (S, 3)
        prim_label = np.array([LABELS.index(lab) for lab in self.scene.labels])
        h = 0.25 * vs
        reach = band + 2 * h  # surface points and their gradient stencils are this close to their surface
        _, nearest = _union_at(self.scene.primitives, pts, reach)
        is_floor = prim_label[nearest] == LABELS.index("floor")
        grad = np.zeros_like(pts)
        for ax in range(3):  # the exact SDF's gradient, central differences a quarter voxel apart
            e = np.zeros(3)
            e[ax] = h
            grad[:, ax] = (_union_at(self.scene.primitives, pts + e, reach)[0]
                           - _union_at(self.scene.primitives, pts - e, reach)[0]) / (2 * h)
        upward = grad @ self.up >= math.cos(math.radians(up_tolerance_deg)) * np.maximum(np.linalg.norm(grad, axis=1),
                                                                                           1e-12)
        n_surf = np.bincount(which, minlength=n)
        denom = np.maximum(n_surf, 1)
        axis = int(np.argmax(np.abs(self.up)))
        col = np.delete(local, axis, axis=1) @ np.array([BLOCK, 1])  # column index 0..255 across the up axis

        def cover(mask: np.ndarray) -> np.ndarray:
            cells = np.unique(which[mask] * BLOCK * BLOCK + col[mask])
            return (np.bincount(cells // (BLOCK * BLOCK), minlength=n) / (BLOCK * BLOCK)).astype(np.float32)

        return {"floor": (np.bincount(which, weights=is_floor, minlength=n) / denom).astype(np.float32),
                "up": (np.bincount(which, weights=upward, minlength=n) / denom).astype(np.float32),
                "floor_cover": cover(is_floor), "up_cover": cover(upward), "surface_voxels": n_surf.astype(np.int64)}


def _aabb(prim) -> tuple[np.ndarray, np.ndarray] | None:
    """World bounding box ``(lo, hi)`` of a Box/Cylinder/Sphere primitive (None for others)."""
    from .sdf import Box, Cylinder, Sphere

    c = np.asarray(prim.center, np.float64)
    if isinstance(prim, Sphere):
        return c - prim.radius, c + prim.radius
    if isinstance(prim, Box):
        half = np.asarray(prim.half, np.float64)
    elif isinstance(prim, Cylinder):
        half = np.array([prim.radius, prim.radius, prim.half_height])
    else:
        return None
    ext = half if prim.rotation is None else np.abs(np.asarray(prim.rotation, np.float64)) @ half
    return c - ext, c + ext


def _union_at(primitives: Sequence, points: np.ndarray, reach: float) -> tuple[np.ndarray, np.ndarray]:
    """Union distance ``(S,)`` and index of the nearest primitive ``(S,)`` at points ``(S, 3)``, evaluating each
    primitive only at points within ``reach`` of its bounding box (exact wherever the union is below
    ``reach``; ``+inf`` and index 0 where no primitive is that close)."""
    d = np.full(len(points), np.inf)
    idx = np.zeros(len(points), np.int64)
    for k, prim in enumerate(primitives):
        box = _aabb(prim)
        sel = (np.flatnonzero(np.all((points >= box[0] - reach) & (points <= box[1] + reach), axis=1))
               if box is not None else np.arange(len(points)))
        if not len(sel):
            continue
        dk = prim(points[sel])
        closer = dk < d[sel]
        d[sel[closer]] = dk[closer]
        idx[sel[closer]] = k
    return d, idx


def _sample_union(primitives: Sequence, shape: tuple[int, int, int], voxel_size: float, origin: np.ndarray,
                  reach: float) -> np.ndarray:
    """Union (minimum) distance of primitives on a lattice, metres float32, evaluating each primitive only
    within ``reach`` metres of its bounding box: elsewhere it cannot bring the union below ``reach`` (the
    distances are 1-Lipschitz), and the result there is ``+inf``."""
    from .sdf import grid_points

    d = np.full(shape, np.inf, np.float32)
    for prim in primitives:
        box = _aabb(prim)
        if box is None:
            lo_i, hi_i = np.zeros(3, int), np.asarray(shape)
        else:
            lo_i = np.clip(np.floor((box[0] - reach - origin) / voxel_size).astype(int), 0, shape)
            hi_i = np.clip(np.ceil((box[1] + reach - origin) / voxel_size).astype(int) + 1, 0, shape)
        if np.any(hi_i <= lo_i):
            continue
        for x0 in range(lo_i[0], hi_i[0], BLOCK):  # slabs of x: bounded memory
            x1 = min(x0 + BLOCK, hi_i[0])
            sub = (slice(x0, x1), slice(lo_i[1], hi_i[1]), slice(lo_i[2], hi_i[2]))
            pts = grid_points((x1 - x0, hi_i[1] - lo_i[1], hi_i[2] - lo_i[2]), voxel_size,
                              origin + voxel_size * np.array([x0, lo_i[1], lo_i[2]]))
            np.minimum(d[sub], prim(pts).astype(np.float32), out=d[sub])
    return d


def _pose(prim, rot: np.ndarray):
    """A primitive of :mod:`sdfcodec.sdf` rotated about the world origin by ``rot``."""
    from .sdf import Box, Cylinder, Sphere

    if isinstance(prim, (Box, Cylinder)):
        r = rot if prim.rotation is None else rot @ np.asarray(prim.rotation, np.float64)
        return replace(prim, center=tuple(rot @ np.asarray(prim.center, np.float64)), rotation=r)
    if isinstance(prim, Sphere):
        return replace(prim, center=tuple(rot @ np.asarray(prim.center, np.float64)))
    raise InvalidValueError(f"cannot pose a {type(prim).__name__}")


def synthetic_room(seed: int = 0, *, geometry: str = "normal", size: Sequence[float] | None = None,
                   voxel_size: float = 0.02, truncation: tuple[float, float] = (-0.04, 0.1), tilt_deg: float = 0.0,
                   yaw: bool = True, behind: str = "unobserved") -> LabelledRoom:
    """A furnished room (``sdfcodec.data.render.room_scene`` with a ceiling) sampled as a TSDF with exact
    distances, randomly posed, for retrieval experiments with known labels.

    The floor lands at a random height inside its blocks (the grid's origin is shifted by a random fraction
    of a block), the room is turned by a random yaw about ``z`` (when ``yaw``) and tilted by an angle uniform
    in ``[0, tilt_deg]`` about a random horizontal axis. Voxels behind surfaces follow ``behind``; so do those
    outside the room's observed region (more than 0.15 m beyond its interior): free space ``d_max`` for
    ``"unobserved"`` (the unobserved space around a fused room), solid ``d_min`` for ``"solid"`` (the room is
    a cavity in solid ground).

    Parameters
    ----------
    seed : int
        Deterministic seed (furniture, size, pose).
    geometry : {"poor", "normal", "rich"}
        Furniture (see ``room_scene``): a table and 4 boxes/cylinders for "normal"; 10 pieces including
        rotated boxes, lying cylinders and balls for "rich".
    size : sequence of 3 floats, optional
        Interior metres; default uniform in ``[3, 5] x [3, 4.2] x [2.3, 2.8]``.
    voxel_size, truncation :
        Metres.
    tilt_deg : float
        Largest tilt of the room's up direction from the grid's ``+z``, degrees.
    yaw : bool
        Random rotation about ``z``.
    behind : {"unobserved", "solid"}

    Returns
    -------
    LabelledRoom
    """
    from .data.render import RoomScene, room_scene
    from .sdf import grid_points

    if behind not in BEHIND:
        raise InvalidValueError(f"behind must be one of {BEHIND}, got {behind!r}")
    rng = np.random.default_rng([seed, 7])
    if size is None:
        size = (rng.uniform(3.0, 5.0), rng.uniform(3.0, 4.2), rng.uniform(2.3, 2.8))
    size = tuple(float(s) for s in size)
    keep_out = max(0.0, min(1.15, (min(size[:2]) - 0.4) / 2 - 0.01))
    room = room_scene(seed, geometry=geometry, ceiling=True, size=size, keep_out=keep_out)
    rot = _rz(rng.uniform(0, 2 * math.pi)) if yaw else np.eye(3)
    if tilt_deg > 0:
        axis_angle = rng.uniform(0, 2 * math.pi)
        tilt = rng.uniform(0.0, tilt_deg)
        rot = _rz(axis_angle) @ _rx(math.radians(tilt)) @ _rz(-axis_angle) @ rot
    posed = RoomScene([_pose(p, rot) for p in room.primitives], list(room.labels), room.size, room.seed, room.geometry)
    mg = LabelledRoom._OBSERVED_MARGIN
    corners = np.array([[x, y, z] for x in (-mg, size[0] + mg) for y in (-mg, size[1] + mg)
                        for z in (-mg, size[2] + mg)]) @ rot.T
    lo, hi = corners.min(axis=0), corners.max(axis=0)
    origin = lo - rng.uniform(0, BLOCK * voxel_size, 3)  # the floor at a random height within its block
    shape = tuple(int(n) for n in np.ceil((hi - origin) / voxel_size) + 1)
    lab = LabelledRoom(volume=np.empty(shape, np.float32), origin=origin, voxel_size=float(voxel_size),
                       truncation=tuple(truncation), scene=posed, rotation=rot, size=size, up=rot[:, 2].copy(),
                       behind=behind)
    raw = _sample_union(posed.primitives, shape, voxel_size, origin, reach=truncation[1] + voxel_size)
    for x0 in range(0, shape[0], BLOCK):  # slabs of x: bounded memory
        n = min(BLOCK, shape[0] - x0)
        pts = grid_points((n, shape[1], shape[2]), voxel_size, origin + np.array([x0 * voxel_size, 0.0, 0.0]))
        d = _truncate(raw[x0:x0 + n], truncation, behind)  # +inf (far from every surface) becomes d_max
        # beyond the room's slabs: never observed (free, like a fused map) or, for solid scenes, the room is
        # a cavity in solid ground (the slabs' far sides would otherwise be more surfaces)
        d[~lab.observed(pts)] = truncation[1] if behind == "unobserved" else truncation[0]
        lab.volume[x0:x0 + n] = d
    return lab


def _clean(lab: dict, kind: str = "floor") -> np.ndarray:
    return (lab[kind] >= 0.9) & (lab[f"{kind}_cover"] >= 0.9)


#: Ground-truth definitions for :func:`evaluate_retrieval`: ``name -> f(block_labels) -> (positive, negative)``
#: boolean masks (blocks in neither are left out of precision and recall). A *clean floor block*: >= 90 % of
#: its surface voxels are nearest the floor and the floor covers >= 90 % of its cross-section; a *partial* one
#: holds some floor but is not clean (floor slivers and blocks shared with walls or furniture).
#:
#: ``"floor"``: clean floor blocks against all others (partial ones count as false positives when retrieved);
#: ``"floor-vs-none"``: clean floor blocks against blocks holding no floor at all (partial ones left out);
#: ``"floor-majority"``: blocks whose surface is at least half floor (``RoomScene.floor_blocks``) against all
#: others; ``"up"``: clean upward-facing blocks (floor and furniture tops alike) against all others.
TRUTH: dict[str, Callable[[dict], tuple[np.ndarray, np.ndarray]]] = {
    "floor": lambda lab: (_clean(lab), ~_clean(lab)),
    "floor-vs-none": lambda lab: (_clean(lab), lab["floor"] == 0),
    "floor-majority": lambda lab: (lab["floor"] >= 0.5, lab["floor"] < 0.5),
    "up": lambda lab: (_clean(lab, "up"), ~_clean(lab, "up")),
}


# ------------------------------------------------------------------------------------- evaluation: metrics
def pr_curve(scores: np.ndarray, labels: np.ndarray) -> dict:
    """Precision and recall of "score <= t" for every distinct threshold ``t``.

    Parameters
    ----------
    scores : np.ndarray
        ``(N,)`` lower is more similar.
    labels : np.ndarray
        ``(N,)`` bool ground truth.

    Returns
    -------
    dict
        ``thresholds``, ``precision``, ``recall`` ``(T,)`` float64 arrays (ascending thresholds), and
        ``positives`` (count).
    """
    s = np.asarray(scores, dtype=np.float64)
    y = np.asarray(labels, dtype=bool)
    order = np.argsort(s, kind="stable")
    s, y = s[order], y[order]
    tp = np.cumsum(y)
    k = np.arange(1, len(s) + 1)
    last = np.r_[np.flatnonzero(np.diff(s) > 0), len(s) - 1]  # the last index of each distinct score
    pos = max(int(y.sum()), 1)
    return {"thresholds": s[last], "precision": tp[last] / k[last], "recall": tp[last] / pos,
            "positives": int(y.sum())}


def operating_points(curve: dict, target: float = 0.9) -> dict:
    """Summaries of a :func:`pr_curve`: average precision (``ap``: precision summed over recall steps), the
    best F1 and its threshold, the highest precision at recall ``>= target`` and the highest recall at
    precision ``>= target`` with their thresholds (None when unreachable)."""
    p, r, t = curve["precision"], curve["recall"], curve["thresholds"]
    ap = float(np.sum(np.diff(np.r_[0.0, r]) * p))
    f1 = np.where(p + r > 0, 2 * p * r / np.maximum(p + r, 1e-12), 0.0)
    i = int(np.argmax(f1))
    out = {"ap": ap, "best_f1": float(f1[i]), "best_f1_threshold": float(t[i]),
           "best_f1_precision": float(p[i]), "best_f1_recall": float(r[i])}
    # the best of one measure where the other reaches the target (None when it never does)
    for name, ok, best in (("precision_at_recall", r >= target, p), ("recall_at_precision", p >= target, r)):
        j = np.flatnonzero(ok)[np.argmax(best[ok])] if ok.any() else None
        out[name] = None if j is None else float(best[j])
        out[f"{name}_threshold"] = None if j is None else float(t[j])
    return out


def evaluate_retrieval(rooms: Sequence[LabelledRoom], codecs: Mapping[str, Codec], *,
                       queries: Mapping[str, Mapping[str, Any]] | None = None,
                       levels: Mapping[str, Sequence[int]] | None = None, truths: Sequence[str] = ("floor",),
                       workdir: str | os.PathLike | None = None, keep_curves: bool = True,
                       progress: Callable[[str], None] | None = None) -> list[dict]:
    """Precision/recall of retrieving labelled blocks from maps of synthetic rooms.

    Each room is written as a map per codec (``create_map`` + ``write_volume``: the real pipeline), each map
    searched with each query at each level (every coded block scored), and the scores of all rooms pooled
    (one threshold for all rooms). Ground truth: :data:`TRUTH` definitions of
    :meth:`LabelledRoom.block_labels`.

    Parameters
    ----------
    rooms : sequence of LabelledRoom
    codecs : mapping of str to Codec
        Name (e.g. ``"pca-64"``) -> fitted codec.
    queries : mapping of str to dict, optional
        Name -> :func:`build_query` keyword arguments (``shape`` and options; ``map`` is added). Default:
        ``{"floor": {"shape": "floor"}}``. ``"up": "room"`` uses each room's true up direction.
    levels : mapping of str to sequence of int, optional
        Codec name -> levels to search at (default: the full size).
    truths : sequence of str
        Keys of :data:`TRUTH`.
    workdir : path, optional
        Where maps are written (default: a temporary directory, removed afterwards).
    keep_curves : bool
        Include the PR curve arrays in the records.

    Returns
    -------
    list of dict
        One record per (codec, query, level, truth): ``codec``, ``code_size``, ``query``, ``level``,
        ``descriptors``, ``truth``, ``rooms``, ``blocks`` (counted in precision/recall), ``positives``,
        ``partial`` (blocks holding some floor but not clean floor), the :func:`operating_points` fields,
        ``partial_selected`` (partial blocks under the best-F1 threshold) and, with ``keep_curves``, ``curve``
        (``thresholds``, ``precision``, ``recall`` lists).
    """
    import tempfile

    from .mapfile import create_map

    queries = queries or {"floor": {"shape": "floor"}}
    for t in truths:
        if t not in TRUTH:
            raise InvalidValueError(f"unknown truth {t!r}; choose from {sorted(TRUTH)}")
    tmp = tempfile.TemporaryDirectory(prefix="sdfcodec-eval-") if workdir is None else None
    root = Path(tmp.name if tmp else workdir)
    pooled: dict[tuple, list] = {}
    try:
        for r_i, room in enumerate(rooms):
            labels = None
            for cname, codec in codecs.items():
                path = root / f"room{r_i}-{cname}.sdfz"
                with create_map(path, codec=codec, voxel_size=room.voxel_size, truncation=room.truncation,
                                origin=tuple(room.origin), overwrite=True, tool="sdfcodec.search.evaluate") as w:
                    w.write_volume(room.volume)
                m = open_map(path)
                for qname, kw in queries.items():
                    kw = dict(kw)
                    if isinstance(kw.get("up"), str) and kw["up"] == "room":
                        kw["up"] = room.up
                    model = build_query(kw.pop("shape", "floor"), map=m, **kw)
                    for lv in (levels or {}).get(cname, [m.code_size]):
                        res = search(m, model, level=lv, keep_scores=True, device="cpu")
                        if labels is None or not np.array_equal(labels["coords"], res.all_coords):
                            labels = {"coords": res.all_coords, **room.block_labels(res.all_coords)}
                        partial = (labels["floor"] > 0) & ~_clean(labels)
                        for t in truths:
                            pos, neg = TRUTH[t](labels)
                            keep = pos | neg
                            pooled.setdefault((cname, m.code_size, qname, lv, len(model), t), []).append(
                                (res.all_scores[keep], pos[keep], partial[keep], res.all_scores[partial]))
                if progress:
                    progress(f"room {r_i + 1}/{len(rooms)} {cname}")
    finally:
        if tmp is not None:
            tmp.cleanup()
    records = []
    for (cname, size, qname, lv, n_desc, t), parts in pooled.items():
        s = np.concatenate([p[0] for p in parts])
        y = np.concatenate([p[1] for p in parts])
        partial_scores = np.concatenate([p[3] for p in parts])
        curve = pr_curve(s, y)
        ops = operating_points(curve)
        rec = {"codec": cname, "code_size": size, "query": qname, "level": lv, "descriptors": n_desc, "truth": t,
               "rooms": len(parts), "blocks": int(len(s)), "positives": int(y.sum()), "partial": len(partial_scores),
               **ops, "partial_selected": int((partial_scores <= ops["best_f1_threshold"]).sum())}
        if keep_curves:
            rec["curve"] = {k: np.asarray(curve[k]).tolist() for k in ("thresholds", "precision", "recall")}
        records.append(rec)
    return records


# ------------------------------------------------------------------------------------------------ benchmark
def bench_search(code_sizes: Iterable[int] = (64,), *, descriptors: int = 15, batches: Iterable[int] = (65536,),
                 device: str = "cpu", min_time: float = 0.2, map_blocks: int = 0,
                 map_levels: Mapping[int, Sequence[int]] | None = None, workdir: str | os.PathLike | None = None,
                 progress: Callable[[str], None] | None = None) -> list[dict]:
    """Search throughput: the scoring kernel on in-memory codes beside a plain numpy matrix product of the same
    shape, and (``map_blocks > 0``) whole searches of a map on disk with the bytes they read.

    Codes are random with the shipped eigenshapes' per-component spread (``sqrt(explained_variance)``), so
    their magnitudes (and compressibility) resemble real ones; descriptors are the floor model.

    Parameters
    ----------
    code_sizes : iterable of int
        Code lengths ``k`` (1..128: prefixes of the shipped pca-128 basis).
    descriptors : int
        Model size ``M`` (15: the paper's floor model; other values: planes at that many offsets).
    batches : iterable of int
        Blocks per kernel call.
    device : str
        Where the kernel runs (the baseline is always numpy on the CPU).
    min_time : float
        Seconds per timing round (best of 3, :func:`sdfcodec.bench.time_call`).
    map_blocks : int
        Coded blocks of the benchmark map (0: skip the map records). The map is dense in a cube of blocks.
    map_levels : mapping of int to sequence of int, optional
        Code size -> levels to search its map at (default: the full size; e.g. ``{128: [32, 128]}``).
    workdir : path, optional
        Where the map is written (default: a temporary directory).

    Returns
    -------
    list of dict
        Records like :func:`sdfcodec.bench.bench_codec`'s: ``codec``, ``code_size``, ``operation``
        (``"search"`` for the kernel, ``"search-map"`` for a whole search), ``batch``, ``device``,
        ``blocks_per_s``, ``baseline`` (``"numpy matmul"``), ``baseline_blocks_per_s``, ``ratio_to_baseline``,
        ``us_per_block``, ``load_before`` and ``load_after`` (``os.getloadavg()`` around the timing: this is a
        shared machine); map records add ``level``, ``code_bytes_read``, ``code_bytes_full``, ``seconds``.
    """
    import tempfile

    from .bench import time_call
    from .mapfile import create_map
    from .models import default_codec

    records = []
    dev = torch.device(device)
    sync = torch.cuda.synchronize if dev.type == "cuda" else (lambda: None)
    rng = np.random.default_rng(0)
    for k in code_sizes:
        codec = default_codec("pca", k)
        spread = np.sqrt(codec.explained_variance_).astype(np.float32)
        q = build_query("floor", codec=codec, offsets=descriptors).descriptors
        scorer = _Scorer(q, dev)
        qt = np.ascontiguousarray(q.T)
        for b in batches:
            codes = rng.standard_normal((b, k), dtype=np.float32) * spread
            x = torch.from_numpy(codes).to(dev) if dev.type != "cpu" else codes
            if progress:
                progress(f"search kernel pca-{k} batch {b}")
            load0 = os.getloadavg()
            t = time_call(lambda: (scorer(x), sync()), min_time)
            tb = time_call(lambda: codes @ qt, min_time)
            records.append({"codec": "pca", "code_size": k, "operation": "search", "batch": b, "device": str(dev),
                            "descriptors": len(q), "blocks_per_s": b / t, "baseline": "numpy matmul",
                            "baseline_blocks_per_s": b / tb, "ratio_to_baseline": tb / t, "us_per_block": 1e6 * t / b,
                            "load_before": list(load0), "load_after": list(os.getloadavg())})
        if map_blocks > 0:
            tmp = tempfile.TemporaryDirectory(prefix="sdfcodec-bench-") if workdir is None else None
            try:
                path = Path(tmp.name if tmp else workdir) / f"bench-pca-{k}.sdfz"
                side = math.ceil(map_blocks ** (1 / 3))
                coords = np.stack(np.meshgrid(*[np.arange(side)] * 3, indexing="ij"), -1).reshape(-1, 3)[:map_blocks]
                if progress:
                    progress(f"writing a {len(coords)}-block pca-{k} map")
                with create_map(path, codec=codec, voxel_size=0.02, overwrite=True, tool="sdfcodec.search.bench") as w:
                    for i in range(0, len(coords), 1 << 16):
                        c = coords[i:i + (1 << 16)]
                        w.write_codes(c, rng.standard_normal((len(c), k), dtype=np.float32) * spread)
                m = open_map(path)
                m.codec  # load the codec state once, outside the timed searches
                for lv in (map_levels or {}).get(k, [k]):
                    if progress:
                        progress(f"searching the pca-{k} map at level {lv}")
                    load0 = os.getloadavg()
                    res = search(m, build_query("floor", codec=codec, offsets=descriptors), level=lv, top=100,
                                 device=dev)
                    base_codes = rng.standard_normal((len(coords), lv), dtype=np.float32)
                    base_q = np.ascontiguousarray(q[:, :lv].T)
                    tb = time_call(lambda: base_codes @ base_q, min_time)
                    t = res.stats["seconds"]
                    records.append({"codec": "pca", "code_size": k, "operation": "search-map", "level": lv,
                                    "batch": len(coords), "device": str(dev), "descriptors": len(q),
                                    "blocks_per_s": len(coords) / t, "baseline": "numpy matmul",
                                    "baseline_blocks_per_s": len(coords) / tb, "ratio_to_baseline": tb / t,
                                    "us_per_block": 1e6 * t / len(coords), "seconds": t,
                                    "code_bytes_read": res.stats["code_bytes_read"],
                                    "code_bytes_full": res.stats["code_bytes_full"],
                                    "load_before": list(load0), "load_after": list(os.getloadavg())})
            finally:
                if tmp is not None:
                    tmp.cleanup()
    return records
