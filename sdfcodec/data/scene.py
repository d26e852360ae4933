"""The labelled room scenes the built-in sequences are rendered from: a union of exact primitives from
:mod:`sdfcodec.core.sdf` with a label each (:data:`LABELS`), their exact SDF, their open3d mesh, the surface
labels that make the ground truth of retrieval (:meth:`RoomScene.floor_blocks`), and :func:`look_at` for
camera poses. Below both :mod:`sdfcodec.data.render` (rooms, the renderer, sequences) and
:mod:`sdfcodec.data.building` (the multi-room building), which both build scenes and cameras from it."""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InvalidValueError, MissingDependencyError
from ..core.sdf import Box, Cylinder, Plane, Scene, Sphere

__all__ = ["LABELS", "MIN_OBSERVED_FLOOR", "RoomScene", "look_at", "open3d_module"]

LABELS = ("floor", "wall", "ceiling", "furniture")

#: :meth:`RoomScene.floor_blocks` on a map's observation: the fewest observed floor surface voxels of a floor
#: block, a quarter of a block face (fewer is a corner clipped by the floor or a few observed voxels at the
#: edge of what the camera saw).
MIN_OBSERVED_FLOOR = 64
_FACETS = 96  # segments of cylinder and ball meshes


@dataclass
class RoomScene:
    """An analytic room: primitives (exact SDFs), their labels, and the matching triangle mesh.

    Attributes
    ----------
    primitives : list
        :mod:`sdfcodec.core.sdf` primitives (Box, Cylinder, Sphere); the room is their union.
    labels : list of str
        One of :data:`LABELS` per primitive.
    size : tuple of float
        Interior extent ``(sx, sy, sz)`` metres; the interior spans ``[0, sx] x [0, sy] x [0, sz]``.
    seed : int
        The seed it was generated from (informational).
    geometry : str
        ``"poor"``, ``"normal"`` or ``"rich"``.
    """

    primitives: list
    labels: list[str]
    size: tuple[float, float, float]
    seed: int = 0
    geometry: str = "normal"
    _mesh: Any = field(default=None, init=False, repr=False, compare=False)

    @property
    def sdf(self) -> Scene:
        """The union as a :class:`sdfcodec.core.sdf.Scene` (callable on ``(..., 3)`` points, metres)."""
        return Scene(list(self.primitives))

    def __call__(self, points: np.ndarray) -> np.ndarray:
        """Signed distance ``(...)`` metres at ``points`` ``(..., 3)``: exact in free space."""
        return self.sdf(points)

    @property
    def center(self) -> np.ndarray:
        """The interior's centre at floor level, ``(3,)`` metres."""
        return np.array([self.size[0] / 2, self.size[1] / 2, 0.0])

    def mesh(self):
        """The room as an ``open3d.geometry.TriangleMesh`` (legacy), built once and cached."""
        if self._mesh is None:
            o3d = open3d_module()
            total = o3d.geometry.TriangleMesh()
            for prim in self.primitives:
                total += _primitive_mesh(prim, o3d)
            total.compute_vertex_normals()
            self._mesh = total
        return self._mesh

    def surface_labels(self, points: np.ndarray, band: float) -> np.ndarray:
        """Label index (into :data:`LABELS`) of the nearest primitive for points within ``band`` metres of
        the surface, -1 elsewhere; ``points`` ``(..., 3)`` -> ``(...)`` int8."""
        pts = np.asarray(points, dtype=np.float64)
        best = np.full(pts.shape[:-1], np.inf)
        label = np.full(pts.shape[:-1], -1, dtype=np.int8)
        for prim, name in zip(self.primitives, self.labels):
            d = prim(pts)
            closer = d < best
            best = np.where(closer, d, best)
            label = np.where(closer, np.int8(LABELS.index(name)), label)
        return np.where(np.abs(best) <= band, label, np.int8(-1)).astype(np.int8)

    def block_label_fractions(self, coords: np.ndarray, origin, voxel_size: float, band: float | None = None,
                              batch: int = 128, observed: np.ndarray | None = None) -> np.ndarray:
        """Per block, the fraction of its surface voxels nearest to each label.

        Parameters
        ----------
        coords : np.ndarray
            ``(N, 3)`` int block indices; voxel ``(i, j, k)`` of block ``c`` is at
            ``origin + voxel_size * (16 c + (i, j, k))`` (spec/map-format.md).
        origin : array-like
            ``(3,)`` metres, the world position of voxel (0, 0, 0) of block (0, 0, 0).
        voxel_size : float
            Metres.
        band : float, optional
            A voxel is a surface voxel when the scene's distance there is within ``band`` (default half a
            voxel diagonal, ``0.87 voxel_size``: each surface point has one such voxel nearby).
        observed : np.ndarray, optional
            ``(N, 16, 16, 16)`` bool, what a map observed of each block (``Map.read_observed``): only observed
            surface voxels count. Without it every surface voxel counts, seen or not (the underside of the
            floor slab, the back of a wall).

        Returns
        -------
        np.ndarray
            ``(N, len(LABELS))`` float32; rows sum to 1 for blocks with (observed) surface voxels, 0 otherwise.
        """
        return self._label_counts(coords, origin, voxel_size, band, batch, observed)[1]

    def _label_counts(self, coords, origin, voxel_size, band, batch, observed) -> tuple[np.ndarray, np.ndarray]:
        """``(N, len(LABELS))`` float32 surface-voxel counts and fractions (:meth:`block_label_fractions`)."""
        coords = np.asarray(coords, dtype=np.int64).reshape(-1, 3)
        band = 0.5 * math.sqrt(3.0) * voxel_size if band is None else float(band)
        local = np.stack(np.meshgrid(*[np.arange(16)] * 3, indexing="ij"), -1).reshape(-1, 3)
        out = np.zeros((len(coords), len(LABELS)), dtype=np.float32)
        counted = np.zeros_like(out)
        if observed is not None:
            observed = np.asarray(observed, dtype=bool).reshape(len(coords), 16 ** 3)
        origin = np.asarray(origin, dtype=np.float64)
        for s in range(0, len(coords), batch):
            c = coords[s:s + batch]
            pts = origin + voxel_size * (16 * c[:, None, :] + local[None]).astype(np.float64)
            if observed is None:
                lab = self.surface_labels(pts, band)
            else:  # only the observed voxels count: the scene is evaluated at those alone (a fused map's ~40 %)
                seen = observed[s:s + batch]
                lab = np.full(seen.shape, -1, dtype=np.int8)
                lab[seen] = self.surface_labels(pts[seen], band)
            counts = np.stack([(lab == k).sum(axis=1) for k in range(len(LABELS))], axis=1).astype(np.float32)
            total = counts.sum(axis=1, keepdims=True)
            out[s:s + batch] = np.divide(counts, total, out=np.zeros_like(counts), where=total > 0)
            counted[s:s + batch] = counts
        return counted, out

    def floor_blocks(self, coords: np.ndarray, origin, voxel_size: float, min_fraction: float = 0.5,
                     band: float | None = None, observed: np.ndarray | None = None,
                     min_observed: int = MIN_OBSERVED_FLOOR) -> np.ndarray:
        """``(N,)`` bool: blocks whose surface voxels are at least ``min_fraction`` floor (see
        :meth:`block_label_fractions` for the arguments). This is the ground truth of floor retrieval.

        With ``observed`` (``(N, 16, 16, 16)`` bool, the map's observation of each block) only what the map
        observed counts: a block is floor when its observed surface voxels are at least ``min_fraction`` floor
        and at least ``min_observed`` of them are (less is a sliver no search can tell from noise). Without
        it, the floor's unseen underside and floor the camera never saw count too, which no map can hold."""
        counts, frac = self._label_counts(coords, origin, voxel_size, band, 128, observed)
        fl = LABELS.index("floor")
        got = frac[:, fl] >= min_fraction
        return got if observed is None else got & (counts[:, fl] >= min_observed)

    # ---- serialisation (JSON only, never pickles)
    def to_dict(self) -> dict:
        """A JSON-able description (primitive types and parameters, labels, size, seed, geometry)."""
        prims = []
        for p in self.primitives:
            d = {k: (np.asarray(v).tolist() if v is not None else None) for k, v in asdict(p).items()}
            prims.append({"type": type(p).__name__, **d})
        return {"size": list(self.size), "seed": self.seed, "geometry": self.geometry,
                "primitives": prims, "labels": list(self.labels)}

    @classmethod
    def from_dict(cls, data: dict) -> "RoomScene":
        """Inverse of :meth:`to_dict`."""
        kinds = {"Box": Box, "Cylinder": Cylinder, "Sphere": Sphere, "Plane": Plane}
        prims = []
        for p in data["primitives"]:
            p = dict(p)
            kind = kinds.get(p.pop("type"))
            if kind is None:
                raise InvalidValueError(f"unknown primitive type in scene description: {p}")
            if p.get("rotation") is not None:
                p["rotation"] = np.asarray(p["rotation"], dtype=np.float64)
            prims.append(kind(**p))
        return cls(prims, list(data["labels"]), tuple(data["size"]), int(data.get("seed", 0)),
                   str(data.get("geometry", "normal")))

    def save(self, path: str | Path) -> Path:
        """Write :meth:`to_dict` as JSON."""
        Path(path).write_text(json.dumps(self.to_dict(), indent=1))
        return Path(path)

    @classmethod
    def load(cls, path: str | Path) -> "RoomScene":
        """Read a scene written by :meth:`save` (``scene.json`` of a rendered sequence, or its folder)."""
        p = Path(path)
        if p.is_dir():
            p = p / "scene.json"
        return cls.from_dict(json.loads(p.read_text()))


def _primitive_mesh(prim, o3d):
    if isinstance(prim, Box):
        half = np.asarray(prim.half, dtype=np.float64)
        m = o3d.geometry.TriangleMesh.create_box(*(2 * half))
        m.translate(-half)
    elif isinstance(prim, Cylinder):
        # vertices on a slightly larger circle so the facets straddle the true surface (mean error ~0)
        r = prim.radius * 2.0 / (1.0 + math.cos(math.pi / _FACETS))
        m = o3d.geometry.TriangleMesh.create_cylinder(r, 2 * prim.half_height, _FACETS, 1)
    elif isinstance(prim, Sphere):
        r = prim.radius * 2.0 / (1.0 + math.cos(math.pi / _FACETS))
        m = o3d.geometry.TriangleMesh.create_sphere(r, _FACETS // 2)
    else:
        raise InvalidValueError(f"cannot mesh a {type(prim).__name__}; rooms use Box, Cylinder and Sphere")
    rot = getattr(prim, "rotation", None)
    if rot is not None:
        m.rotate(np.asarray(rot, dtype=np.float64), center=np.zeros(3))
    m.translate(np.asarray(prim.center, dtype=np.float64))
    return m


def look_at(eye: np.ndarray, target: np.ndarray, up=(0.0, 0.0, 1.0), roll: float = 0.0) -> np.ndarray:
    """Camera-to-world pose ``(4, 4)`` of a camera at ``eye`` looking at ``target`` (x right, y down,
    z forward), with world ``up`` appearing up in the image, then rolled by ``roll`` radians."""
    eye = np.asarray(eye, dtype=np.float64)
    z = np.asarray(target, dtype=np.float64) - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, np.asarray(up, dtype=np.float64))
    if np.linalg.norm(x) < 1e-9:
        raise InvalidValueError("look_at: the viewing direction is parallel to 'up'")
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    c, s = math.cos(roll), math.sin(roll)
    x, y = c * x + s * y, -s * x + c * y
    pose = np.eye(4)
    pose[:3, :3] = np.stack([x, y, z], axis=1)
    pose[:3, 3] = eye
    return pose


def open3d_module():
    """The ``open3d`` module, or a one-line error naming the extra that installs it."""
    try:
        import open3d as o3d
    except ImportError as exc:
        raise MissingDependencyError("rendering synthetic sequences needs open3d: pip install 'sdfcodec[fusion]'") \
            from exc
    return o3d
