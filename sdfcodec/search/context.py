"""What a query must know about the map it searches, read from the map itself (:func:`map_context`):

* ``behind``: how the map stores the space more than ``|d_min|`` behind a surface. A map that records its
  observation (fusion weights or an observation mask, spec sections 6a/6b), or was written by ``sdfcodec
  fuse``, is a fused map: ``"unobserved"``. A map that records nothing is looked at: the most plane-like
  quarter of a sample of its coded blocks vote, by score, between axis-aligned plane models stored both ways
  (a fused-style field is a thin band behind each surface, then a step back to ``d_max``; an exact SDF is solid
  behind). The two families are far apart in code space, so the vote is clear on any map with planes.
* ``up``: the header's ``up`` field (spec section 3, written by ``sdfcodec fuse`` for sequences that record
  their gravity), else estimated from the map's level surfaces (:func:`estimate_up`; ``+z`` when they say the
  map is level within a degree, or when too few blocks look level).
* ``weighted``: whether the map's blocks were encoded surface-true (weighted least squares,
  :func:`sdfcodec.map.observed.error_weights`); a query for it is encoded the same way, with the mask of what a
  camera would observe of each shape, so that its codes compare like with like.

Each value says where it came from (``*_source``), for the search's JSON and text output. Explicit values
(``--behind``, ``--up``) win.
"""

from __future__ import annotations

import math
import weakref
from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np

from ..errors import InvalidValueError
from ..map import Map
from ..map.observed import MASK_EXTENSION
from .arrays import encode_array
from .models import shape_model
from .shapes import BEHIND

__all__ = ["MapContext", "map_context", "check_up", "VOTE_SAMPLE", "UP_CONE_DEG", "LEVEL_DEG", "MIN_UP_VOTES", "UP_CALIBRATION_SAMPLES", "BLOCK_MIDDLE", "estimate_up"]

#: Coded blocks scored to tell a fused-style field from an exact SDF when the map records neither.
VOTE_SAMPLE = 8192
#: :func:`estimate_up`: the cone (degrees about the grid's +z) searched for level surfaces.
UP_CONE_DEG = 15.0
#: :func:`estimate_up`: estimates closer than this (degrees) to +z keep +z: a plane this far from level rises
#: half a voxel across a block, within the half voxel the models' offset lattice tolerates (1.79 degrees).
LEVEL_DEG = math.degrees(math.atan(0.5 / 16))
#: :func:`estimate_up`: simulated instances per calibrated threshold (a direction needs fewer than a search).
UP_CALIBRATION_SAMPLES = 96
#: :func:`estimate_up`: blocks vote when their nearest plane passes within this many voxels of their centre.
BLOCK_MIDDLE = 6.0
#: :func:`estimate_up`: fewer votes than this keep +z.
MIN_UP_VOTES = 8


@dataclass(frozen=True)
class MapContext:
    """How to build queries for one map (see the module docstring)."""

    behind: str
    behind_source: str
    up: tuple[float, float, float]
    up_source: str
    weighted: bool

    def to_json(self) -> dict:
        return {"behind": self.behind, "behind_source": self.behind_source, "up": [round(u, 6) for u in self.up],
                "up_source": self.up_source, "weighted_encoding": self.weighted}


def check_up(up: Any) -> tuple[float, float, float]:
    """``up`` -> a unit 3-tuple; :class:`InvalidValueError` for anything but three finite numbers of non-zero
    length (a string ``"x,y,z"`` is accepted, as the CLI passes it)."""
    if isinstance(up, str):
        try:
            up = [float(p) for p in up.split(",")]
        except ValueError as e:
            raise InvalidValueError(f"--up must be three numbers x,y,z, got {up!r}") from e
    u = np.asarray(up, dtype=np.float64).reshape(-1)
    if u.shape != (3,) or not np.all(np.isfinite(u)):
        raise InvalidValueError(f"up must be three finite numbers x,y,z, got {up!r}")
    n = float(np.linalg.norm(u))
    if n < 1e-9:
        raise InvalidValueError(f"up {u.tolist()} has zero length: give the direction opposite gravity in the map's "
                                "grid axes, e.g. 0,0,1")
    return tuple(float(x) for x in u / n)


def _behind_vote(m: Map, sample: int = VOTE_SAMPLE) -> tuple[float, int]:
    """Of up to ``sample`` coded blocks (the first the map streams), those that tell the two apart (one family at
    least twice as close as the other), the more plane-like half of them, vote: the share closer to planes
    stored fused-style (unobserved behind) than to planes of an exact SDF (solid behind), both in the 6 axis
    orientations; and how many blocks voted (0.5 and 0 when no block tells them apart)."""
    from .scoring import Scorer

    codec = m.codec
    # the same fine offsets for both (half a voxel apart): where a block does not reach |d_min| behind its
    # surface the two families agree and the block abstains
    models = {b: shape_model("floor", codec, float(m.voxel_size), _truncation(m), (0.0, 0.0, 1.0), "axis", 2 * 16 + 1,
                             b, False, (1.0,), False) for b in BEHIND}
    # the map's first level only (prefix-ordered codecs): the bytes a search at that level reads anyway
    lv = m.header.codes.levels[0] if m.header.codes.prefix_ordered else m.code_size
    scorers = {b: Scorer(q.descriptors[:, :lv], "cpu") for b, q in models.items()}
    got: dict[str, list] = {b: [] for b in BEHIND}
    n = 0
    for _, codes in m.iter_codes(level=lv):
        for b in BEHIND:
            got[b].append(scorers[b](codes)[0])
        n += len(codes)
        if n >= sample:
            break
    if not n:
        return 0.0, 0
    su, ss = (np.concatenate(got[b])[:sample] for b in ("unobserved", "solid"))
    best = np.minimum(su, ss)
    tells = np.maximum(su, ss) > 2.0 * best
    if not tells.any():
        return 0.5, 0
    voters = tells & (best <= np.median(best[tells]))
    return float((su[voters] < ss[voters]).mean()), int(voters.sum())


def estimate_up(m: Map, behind: str, sample: int = VOTE_SAMPLE) -> tuple[tuple[float, float, float], str]:
    """The up direction of a map that records none, from its level surfaces: up to ``sample`` coded blocks are
    scored against a floor model sampled over a cone of :data:`UP_CONE_DEG` about ``+z`` (the grid's up), the
    blocks under its calibrated threshold each vote for their nearest descriptor's normal, and the mean of the
    votes is refined twice, with cones of 4 and 2 degrees about it. An estimate within :data:`LEVEL_DEG` of ``+z``, or
    fewer than :data:`MIN_UP_VOTES` votes, keeps ``+z``. Returns ``(up, where it came from)``."""
    from .calibrate import SURFACE_SHARE, calibrate_threshold
    from .scoring import ObservedScorer, Scorer, score_codes, scored_voxels

    codec = m.codec
    lv = m.header.codes.levels[0] if m.header.codes.prefix_ordered else m.code_size
    masked = any(a is not None for a in m.reader.observation_arrays())
    batches = []
    n = 0
    for coords, codes in m.iter_codes(level=lv):
        batches.append((codes, scored_voxels(m, coords) if masked else None))
        n += len(codes)
        if n >= sample:
            break
    up = np.array([0.0, 0.0, 1.0])
    votes = 0
    const = Scorer(encode_array(codec, np.stack([np.zeros((16,) * 3, np.float32), np.ones((16,) * 3, np.float32)]))[:, :lv],
                   "cpu")
    for cone in (f"cone:{UP_CONE_DEG:g}:48", "cone:4:16", "cone:2:16"):
        # unstretched shapes: a direction does not need fusion's stretches (6 times fewer descriptors)
        model = shape_model("floor", codec, float(m.voxel_size), _truncation(m), check_up(up), cone, "auto", behind,
                            _weighted(m), (1.0,), False)
        scorer = Scorer(model.descriptors[:, :lv], "cpu")
        obs = ObservedScorer(model.descriptors[:, :lv], codec, m.truncation, m.voxel_size) if masked else None
        t, _ = calibrate_threshold(model, codec, lv, scorer, obs, samples=UP_CALIBRATION_SAMPLES)
        normals = []
        for codes, seen in batches:
            sc, idx = score_codes(scorer, obs, codes, seen)
            # blocks of solid or free space (the solid around an exact room) hold no surface to vote with
            real = const(codes)[0] > SURFACE_SHARE * t
            # only planes crossing the middle half of a block vote: a plane near a face shows too little of its tilt
            # (a tilted floor clipping many blocks' top layers looks level there)
            mid = np.abs(model.positions[idx][:, 2]) <= BLOCK_MIDDLE
            normals.append(model.rotations[idx[(sc <= t) & real & mid]][:, :, 2])
        nv = np.concatenate(normals) if normals else np.zeros((0, 3))
        votes = len(nv)
        if votes < MIN_UP_VOTES:
            return (0.0, 0.0, 1.0), (f"default: the grid's +z (the map records no up direction and only {votes} "
                                     "blocks look level enough to estimate one; pass --up x,y,z)")
        est = nv.mean(axis=0)
        up = est / np.linalg.norm(est)
    tilt = math.degrees(math.acos(min(1.0, float(up[2]))))
    if tilt < LEVEL_DEG:
        return (0.0, 0.0, 1.0), (f"the grid's +z: the map records no up direction, and its {votes} level-looking "
                                 f"blocks put up {tilt:.1f} degrees from +z (under {LEVEL_DEG:.2f}: level)")
    return tuple(float(u) for u in up), (f"estimated from the map's {votes} level-looking blocks ({tilt:.1f} degrees "
                                         "from the grid's +z; the map records no up direction: pass --up to override)")


#: Contexts already worked out, per open map version (a reader pins one version, so its blocks cannot change
#: under it) and per override: a search builds several models for one map, and each asks.
_CONTEXTS: "weakref.WeakKeyDictionary[Any, dict]" = weakref.WeakKeyDictionary()


def _weighted(m: Map) -> bool:
    """Whether ``m``'s blocks were encoded surface-true: it records its observation (module docstring)."""
    arrays = m.reader.observation_arrays()
    return arrays[0] is not None or arrays[1] is not None or MASK_EXTENSION in {e.name for e in m.header.extensions}


def _truncation(m: Map) -> tuple[float, float]:
    d_min, d_max = m.truncation
    return float(d_min), float(d_max)


def map_context(m: Map, *, behind: str | None = None, up: Sequence[float] | str | None = None) -> MapContext:
    """The query context of map ``m`` (module docstring); ``behind`` / ``up`` given override the map's."""
    key = (behind, up if up is None or isinstance(up, str) else tuple(float(u) for u in np.ravel(up)))
    known = _CONTEXTS.setdefault(m.reader, {})
    if key not in known:
        known[key] = _work_out_context(m, behind, up)
    return known[key]


def _work_out_context(m: Map, behind: str | None, up: Sequence[float] | str | None) -> MapContext:
    h = m.header
    names = {e.name for e in h.extensions}
    behind = None if behind == "auto" else behind
    weighted = _weighted(m)
    if behind is not None:
        if behind not in BEHIND:
            raise InvalidValueError(f"behind must be one of {', '.join(BEHIND)}, got {behind!r}")
        b, b_src = behind, "given"
    elif weighted or "fusion-weights" in names:
        b, b_src = "unobserved", "the map records which voxels were observed (a fused map)"
    elif (h.provenance.tool or "").startswith("sdfcodec fuse"):
        b, b_src = "unobserved", "the map was written by sdfcodec fuse"
    else:
        share, n = _behind_vote(m)
        b = "unobserved" if share >= 0.5 else "solid"
        b_src = (f"the map records no observation; {share:.0%} of {n} sampled plane-like blocks that tell the two "
                 f"apart are closer to planes with unobserved space behind than to solid ones "
                 f"({'a fused-style field' if share >= 0.5 else 'an exact SDF'})" if n else
                 "the map records no observation and no block tells solid from unobserved behind surfaces: the "
                 "fused-style default")
    if up is not None:
        u, u_src = check_up(up), "given"
    elif h.up is not None:
        u, u_src = check_up(h.up), "the map's header (recorded when it was made, e.g. from the sequence's gravity)"
    else:
        u, u_src = estimate_up(m, b)
    return MapContext(behind=b, behind_source=b_src, up=u, up_source=u_src, weighted=weighted)
