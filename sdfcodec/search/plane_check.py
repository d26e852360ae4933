"""The last stage of a floor, ceiling or wall search: every block the chosen plane crosses, checked against that
plane itself.

The map-level stage (:mod:`sdfcodec.search.scene`) finds *which* plane the query means (the floor's level, the
walls) from blocks scored against a model that samples planes on a lattice of offsets and directions. Once the
plane is known, a block of it no longer needs to be near a lattice plane: it must look like *this* plane. For
every coded block the plane crosses (by more than a corner sliver), :func:`plane_residuals` compares the
block's decoded field with the field of the plane stored the map's way (``behind``), over the observed voxels
near the plane (:data:`BAND_VOXELS`), letting the plane move by up to
:data:`~sdfcodec.search.scene.PLANE_TOL_VOXELS` along its normal (the level's fit at that block) and, for fused
maps, stretch as fusion stretches it; and it measures how much of the block's decoded surface lies on the plane
(:data:`PURITY`).

A block is kept when its residual is under a threshold calibrated the way the search's threshold is
(:func:`verify_threshold`): clean instances of the plane crossing a block anywhere (the level's own normal,
fitted off by up to the plane tolerance), stored, encoded and decoded with the map's codec the map's way, and
checked exactly as the map's blocks are; the threshold keeps :data:`~sdfcodec.search.calibrate.CALIBRATION_QUANTILE`
of them. A real map is noisier than those instances (a sensor's noise, a floor that is not flat): the blocks
the code-space stage already put on the plane measure by how much, and the median excess of their residuals
over the simulated ones is added (:func:`verify_planes` reports both).

Maps that record their observation are only pruned by the check (:func:`check_planes`). What this removes:
blocks holding the plane *and* something else (the foot of a table on the floor, a wall's
edge), which lie close enough to some lattice plane to pass the code-space score but not to the plane the
map holds; where the other surface is a sliver a codec smeared into the plane's field (a cabinet's side a voxel
or two tall between a floor and the block's top face), the neighbour beyond that face shows it (:func:`_feet`).
What it adds (maps without an observation record): blocks of the plane that scored poorly against the lattice
(a tilted plane between its directions, a plane near a block's face) but agree with the plane.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from ..core._validate import BLOCK
from ..core.blocks import normalise
from ..core.tiling import run_tiles
from .arrays import decode_array
from .scene import PLANE_TOL_VOXELS
from .models import codec_state_sha256
from .shapes import MIN_SHAPE_SURFACE, truncate
from .scoring import scored_voxels

if TYPE_CHECKING:
    from ..codec import Codec
    from .models import QueryModel

__all__ = ["VERIFY_STEP", "BAND_VOXELS", "JUMP_VOXELS", "PURITY", "MIN_VERDICT_SURFACE", "plane_residuals",
           "verify_threshold", "clean_residuals", "plane_check_key", "verify_planes", "check_planes"]

#: Offsets (voxels) along the plane's normal tried at each block, within the plane tolerance.
VERIFY_STEP = 0.5
#: Blocks with fewer observed voxels within a voxel of the plane than this get no verdict (the map-level stage's
#: decision stands): too little of the plane was seen to compare. The models' own corner-sliver rule
#: (:data:`~sdfcodec.search.shapes.MIN_SHAPE_SURFACE`) divided by four: a quarter of a sliver.
MIN_VERDICT_SURFACE = MIN_SHAPE_SURFACE // 4
#: Voxels compared: those within this distance of the plane (voxels). There the field is the plane's unless another
#: surface is about as near, i.e. the block's surface there is not the plane's (what the truth of a clean block
#: counts); farther out, furniture or a wall a few voxels beyond the block bends a clean block's field too.
BAND_VOXELS = 1.5
#: Voxels this close (voxels) to where an unobserved-behind field jumps from ``d_min`` to ``d_max`` are not
#: compared: a sub-voxel move of the plane flips them, and a codec smears the jump over about as many voxels.
JUMP_VOXELS = 1.0
#: A block is of the plane when at least this share of its surface voxels lie on it (the share a clean block of
#: the evaluation's truth holds; a floor block with a table leg or a wall's foot in it is a block of both).
PURITY = 0.9
#: Decoded voxels within this distance of zero (voxels), and nearer zero than the plane by as much, are another
#: surface's (:func:`plane_residuals`' ``share``): a codec smears a surface just past the block's face to here.
SECOND_SURFACE_VOXELS = 1.5
#: A block observed on the plane (:data:`~sdfcodec.search.shapes.MIN_SHAPE_SURFACE` voxels within a voxel of it)
#: where under this share of those voxels decode near zero, and under :data:`MIN_VERDICT_SURFACE` lie on it, does
#: not hold the plane (most of what was seen there says the surface is elsewhere).
ABSENT_COVER = 0.5
#: A field that holds a plane rises along its normal: a block of a map that records its observation whose decoded
#: field, between observed neighbours near the plane, rises by under this share of what the plane's own field
#: rises (the median over the pairs, :func:`_rise`) does not hold it. Measured: the 2-voxel band behind a wall's
#: face, observed above a floor that continues under the wall, passed for floor (its voxels lie near zero and the
#: floor plane, moved a voxel, fits them), 12-15 blocks along each wall of rooms of docs/search/independent.py;
#: its field rises along the wall's normal, not the floor's.
RISE_SHARE = 0.5
#: A refitted plane whose normal turns more than this (degrees) from the chosen one keeps the chosen normal.
PLANE_REFIT_DEG = 5.0
_CENTRE = (BLOCK - 1) / 2.0
_GRID = np.stack(np.meshgrid(*[np.arange(BLOCK, dtype=np.float64) - _CENTRE] * 3, indexing="ij"), -1)


def _decode(codec: Codec, codes: np.ndarray) -> np.ndarray:
    """Normalised blocks ``(n, 4096)`` float32 decoded from codes (a prefix of a prefix-ordered codec's codes is
    decoded with the rest zero: the search's level)."""
    if codes.shape[1] < codec.code_size:
        codes = np.pad(codes, ((0, 0), (0, codec.code_size - codes.shape[1])))
    return decode_array(codec, codes)


def _voxels(x: np.ndarray, *, voxel_size: float, truncation: tuple[float, float]) -> np.ndarray:
    """Normalised decodes ``x`` -> decoded distances in voxels, positive on the free side (same shape)."""
    d_min, d_max = truncation
    return (x * (d_max - d_min) + d_min) / voxel_size


def _band_residuals(xs: np.ndarray, obs: np.ndarray, dist: np.ndarray, deltas: np.ndarray, stretches: np.ndarray,
                    voxel_size: float, truncation: tuple[float, float], behind: str) -> np.ndarray:
    """``(n, len(deltas) * len(stretches))`` float32 residuals ``sum (x - plane)^2`` of blocks ``xs`` ``(n, C)``
    (normalised decodes of the voxels that lie ``dist`` ``(n, C)`` voxels from the plane, positive on its free side;
    ``obs`` which of them were observed) against the plane's field moved by each delta and stretched by each
    factor, stored per ``behind``; inf for a move with nothing to compare or that leaves the plane only a corner
    sliver of the block (under :data:`~sdfcodec.search.shapes.MIN_SHAPE_SURFACE` voxels within a voxel of it).

    Compared: the observed voxels within :data:`BAND_VOXELS` of the moved plane but, for an unobserved-behind field,
    not within :data:`JUMP_VOXELS` of where it jumps from ``d_min`` to ``d_max`` (a sub-voxel move of the plane flips
    them, so they say nothing about whether the block holds it). Only those are computed, gathered once for every
    move (about 3 of the 7 voxel layers a move of up to 2 voxels reaches), and summed per move in float64: 2.5x
    faster than every move's candidate field over all of them, the same residuals to float32 rounding."""
    n, moves, k = len(xs), len(deltas), len(stretches)
    d_min, d_max, span, vs = (np.float32(v) for v in (*truncation, truncation[1] - truncation[0], voxel_size))
    err, used, inside = np.empty((n, moves, k)), np.empty((n, moves, k), bool), np.empty((n, moves), bool)
    for m, delta in enumerate(deltas):
        # one move at a time: its (n, C) distances in float64, the compared voxels gathered row by row (each row's
        # sums run over its voxels in order, as one gather of every move did), each field made in place
        moved = dist - delta
        near = np.abs(moved)
        inside[:, m] = (near <= 1.0).sum(axis=-1) >= MIN_SHAPE_SURFACE
        rows, cols = np.nonzero((near <= BAND_VOXELS) & obs)
        t, xv = moved[rows, cols], xs[rows, cols]
        d, v = np.empty(len(t), np.float32), np.empty(len(t), np.float32)
        for j, st in enumerate(stretches):
            np.multiply(t, st, out=d, casting="same_kind")  # the product in float64, rounded once into float32
            d *= vs
            # truncate() then normalise() (sdfcodec.search.shapes, core.blocks), in place: the same float32 steps
            np.clip(d, d_min, d_max, out=v)
            use = np.abs(d - d_min) > JUMP_VOXELS * voxel_size if behind == "unobserved" else None
            if use is not None:
                np.copyto(v, d_max, where=d < d_min)
            v -= d_min
            v /= span
            v -= xv
            v *= v
            if use is not None:
                v *= use
            used[:, m, j] = np.bincount(rows if use is None else rows[use], minlength=n) > 0
            err[:, m, j] = np.bincount(rows, weights=v, minlength=n)
    out = err.astype(np.float32)
    out[~inside[:, :, None] | ~used] = np.inf
    return out.reshape(n, moves * k)


def plane_residuals(x: np.ndarray, observed: np.ndarray, dist: np.ndarray, *, voxel_size: float,
                    truncation: tuple[float, float], behind: str, stretches: np.ndarray,
                    tol: float, crossings: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Residual of blocks against a plane.

    Parameters
    ----------
    x : np.ndarray
        ``(n, 4096)`` float32 normalised decoded blocks.
    observed : np.ndarray
        ``(n, 4096)`` bool voxels the map observed.
    dist : np.ndarray
        ``(n, 4096)`` voxels from each voxel to the plane (positive on its free side).
    stretches : np.ndarray
        Field stretches tried (1 for an exact field).
    tol : float
        The plane may move up to this many voxels along its normal at each block.
    crossings : bool
        Another surface's voxels must also lie beside a zero crossing of the decoded field (a sign change to an
        observed neighbour; :func:`_beside_crossing`): for fused maps (see :func:`verify_planes`).

    Returns
    -------
    residual : np.ndarray
        ``(n,)`` float32: ``min sum (x - plane)^2`` over the moves and stretches (a move that leaves the plane
        only a corner sliver of the block is no candidate), the sum over the compared voxels (:func:`_band_residuals`:
        within :data:`BAND_VOXELS` of the plane, observed, away from an unobserved-behind field's jump). A sum,
        not a mean: a plane crossing few of a block's voxels is little evidence either way.
    seen : np.ndarray
        ``(n,)`` int64 observed voxels within one voxel of the plane.
    moved : np.ndarray
        ``(n,)`` float64 the best move (voxels along the normal).
    constant : np.ndarray
        ``(n,)`` float32 the same residual against a block of solid or of free space (the nearer): a block
        no closer to the plane than to those holds no plane (a plane moved to a block's corner is nearly one).
    share : np.ndarray
        ``(n,)`` float64 of the block's surface voxels (decoded within a voxel of zero) on the plane or on its
        free side beyond the compared band, the share on the plane; both measured from the block's own plane
        where it agrees with this one (:func:`_local_plane`), and 0 where the block's surface is a plane turned
        from this one.
    on : np.ndarray
        ``(n,)`` int64 the block's surface voxels on the plane (within a voxel of it, moved).
    off : np.ndarray
        ``(n,)`` int64 the block's surface voxels of another surface (beyond the band on the free side).
    """
    n = len(x)
    outs = tuple(np.empty(n, t) for t in (np.float32, np.int64, np.float64, np.float32, np.float64, np.int64, np.int64))

    def work(a: int, b: int) -> None:  # row tiles on every core (the numpy work releases the GIL), same numbers
        for o, r in zip(outs, _plane_rows(x[a:b], observed[a:b], dist[a:b], voxel_size, truncation, behind,
                                          stretches, tol, crossings)):
            o[a:b] = r

    run_tiles(n, work, rows=CHECK_ROWS)
    return outs


#: Blocks per tile of :func:`plane_residuals` (a wall of the kitchen crosses 34-126 coded blocks).
CHECK_ROWS = 32


def _plane_rows(x: np.ndarray, observed: np.ndarray, dist: np.ndarray, voxel_size: float, truncation: tuple,
                behind: str, stretches: np.ndarray, tol: float, crossings: bool) -> tuple[np.ndarray, ...]:
    """:func:`plane_residuals` of some rows (the same arguments and results)."""
    deltas = np.arange(-tol, tol + 1e-9, VERIFY_STEP)
    out = np.empty(len(x), np.float32)
    moved = np.empty(len(x), np.float64)
    # No move compares a voxel farther than tol + BAND_VOXELS from the plane (nor counts it towards `inside`):
    # each block's candidates are built over its voxels within that reach only, the nearest layers of the block
    # (about half its voxels at tol 2, a third at tol 0.8), packed first in each row, the rest cut off where the
    # row with the most ends. Same residuals but for float32 summation order; 2-2.5x less work (docs/search.md)
    reach = np.abs(dist) <= tol + BAND_VOXELS + 1e-9
    for i in range(0, len(x), CHECK_ROWS):  # (rows, moves x stretches, <= 4096) float32 at a time
        sl = slice(i, i + CHECK_ROWS)
        near = reach[sl]
        cols = np.argsort(~near, axis=1, kind="stable")[:, :max(int(near.sum(axis=1).max()), 1)]
        xs, obs = np.take_along_axis(x[sl], cols, axis=1), np.take_along_axis(observed[sl], cols, axis=1)
        err = _band_residuals(xs, obs, np.take_along_axis(dist[sl], cols, axis=1), deltas, stretches, voxel_size,
                              truncation, behind)
        best = err.argmin(axis=1)
        out[sl] = err[np.arange(len(best)), best]
        moved[sl] = deltas[best // len(stretches)]
    o = observed.astype(np.float32)
    scale = x.shape[1] / np.maximum(o.sum(axis=1), 1.0)
    constant = np.minimum((x * x * o).sum(axis=1), ((1.0 - x) ** 2 * o).sum(axis=1)) * scale
    seen = ((np.abs(dist) <= 1.0) & observed).sum(axis=1)
    # the block's own surface voxels (decoded within a voxel of zero): on the plane, or on its free side beyond
    # the compared band (another surface in the block: furniture, a wall)
    dec = _voxels(x, voxel_size=voxel_size, truncation=truncation)
    surf = (np.abs(dec) <= 1.0) & observed
    near2 = (np.abs(dec) <= SECOND_SURFACE_VOXELS) & observed
    if crossings:  # another surface is where the field crosses zero, not where it lies near zero...
        beside = _beside_crossing(dec, observed)
        # ... but a voxel 1-1.5 voxels from zero may be a surface's just past the block's face (below), whose
        # crossing lies outside the block
        surf_other, near2 = surf & beside, near2 & (beside | ~surf)
    else:
        surf_other = surf
    rel0 = dist - moved[:, None]
    local, turned = _local_plane(rel0, dec, surf)
    on, off, share = None, None, None
    for rel in (rel0, local):  # against the checked plane (moved) and the block's own: the better
        # another surface: decoded within a voxel of zero beyond the band, or, where the codec smeared it (a wall a
        # voxel past the block's face decodes to 1-1.5 voxels), within SECOND_SURFACE_VOXELS and nearer zero than
        # the plane by SECOND_SURFACE_VOXELS (the plane's own field only grows away from it, stretched or not).
        # Tried: counting a surface voxel only where the surface it places (rel - dec) lies beyond the band, so
        # that a real surface's roughness is not a second surface; it let wall feet through on fused-style rooms
        # (development seed 801, rich: floor precision 0.982 -> 0.889)
        on_r = (surf & (np.abs(rel) <= 1.0)).sum(axis=1)
        # a voxel just past the band (within half a voxel of it) whose decoded distance puts its surface within a
        # voxel of the plane is the plane smeared by the codec, not another surface (a fused-style floor 4.5 voxels
        # under a block's top face: pca-64 decodes the voxel 1.55 voxels above it as 0.79, and every block of the
        # floor failed PURITY); farther out the rule stands (a wall's foot holds surface voxels at every height)
        smeared = (rel <= BAND_VOXELS + 0.5) & (rel - dec <= 1.0)
        off_r = ((surf_other | (near2 & (rel - dec >= SECOND_SURFACE_VOXELS))) & (rel > BAND_VOXELS)
                 & ~smeared).sum(axis=1)
        share_r = np.where(on_r + off_r > 0, on_r / np.maximum(on_r + off_r, 1), 1.0)  # no surface: no other either
        better = np.ones(len(x), bool) if share is None else share_r > share
        on = on_r if on is None else np.where(better, on_r, on)
        off = off_r if off is None else np.where(better, off_r, off)
        share = share_r if share is None else np.where(better, share_r, share)
    share = np.where(turned, 0.0, share)  # a surface crossing the plane at an angle is not of it
    return out, seen, moved, constant.astype(np.float32), share, on, off


def _beside_crossing(dec: np.ndarray, observed: np.ndarray) -> np.ndarray:
    """``(n, 4096)`` bool: voxels whose decoded distance ``dec`` ``(n, 4096)`` changes sign to a face neighbour's
    in the block, both observed: the voxels on either side of a zero crossing, i.e. of a surface.

    Why (fused maps only): fusion averages what several views saw, and where a surface was seen a voxel or two
    apart (pose drift, noise) or at a grazing angle it leaves voxels near zero that never cross it. Measured on
    the kitchen, the labelled wall and floor blocks the check called impure at shares 0.85-0.90 held 44-95 such
    voxels 1.5-4 voxels off the plane; counting only voxels beside a crossing as another surface: kitchen floors
    0.929 / 0.867 -> 0.931 / 0.900, walls 0.905 / 0.826 -> 0.846 / 0.957. Not for maps without an observation record: there a
    field near zero that never crosses it is where two solids meet (a cabinet standing on the floor: the
    union's crease), and counting it as another surface is what keeps those blocks out (measured, fused-style
    rooms tilted 10 degrees, seeds 7901-7903: floors 0.902 / 0.991 without, 0.878 / 0.996 with)."""
    v = dec.reshape(len(dec), BLOCK, BLOCK, BLOCK)
    o = observed.reshape(v.shape)
    pos = v >= 0
    out = np.zeros(v.shape, bool)
    for axis in range(3):
        lo, hi = _neighbours(axis)
        flip = (pos[lo] != pos[hi]) & o[lo] & o[hi]
        out[lo] |= flip
        out[hi] |= flip
    return out.reshape(len(dec), -1)


def _feet(x_next: np.ndarray, rel: np.ndarray, normal: np.ndarray, *, voxel_size: float,
          truncation: tuple[float, float]) -> np.ndarray:
    """``(n,)`` surface voxels of another surface that each block holds between its face on the plane's free side
    and the plane, estimated from the neighbour across that face (``x_next``: its normalised decode ``(n, 4096)``;
    rows of blocks without a coded neighbour all 1.0, free space). For maps without an observation record. A surface
    standing on the plane (a wall, a cabinet's side on a floor) that crosses that face runs on down to the plane:
    in the block, only the layers between the face and the plane hold it, and where the plane lies a voxel or two
    under the face a codec smears that sliver into the plane's field (pca-64 decoded none of it in 13 of 16
    false floor blocks of fused-style tilted rooms, seed 8201: a box or a wall's foot 2-3 voxels tall, 10-33 % of
    their surface voxels). Each surface voxel of the neighbour's face layer off the plane (decoded within a voxel
    of zero, beyond the compared band, not the plane smeared) stands for the block's voxels under it, in its
    column along the grid axis nearest the normal, on the plane's free side (``rel``: voxels from the plane,
    moved): the surface runs down to the plane, and the truth of a clean block counts its voxels there too."""
    a = int(np.argmax(np.abs(normal)))
    up = normal[a] > 0
    dec = _voxels(x_next, voxel_size=voxel_size, truncation=truncation).reshape(-1, BLOCK, BLOCK, BLOCK)
    r = rel.reshape(-1, BLOCK, BLOCK, BLOCK)
    face = [slice(None)] * 4
    face[1 + a] = 0 if up else BLOCK - 1  # the neighbour's layer against the block
    # the neighbour's face layer lies one voxel beyond the block's own last layer on the free side: its distances
    # to the plane are those of that layer plus one step towards the free side, |n_a| (either way along the axis)
    r_next = r[tuple(face[:1 + a] + [BLOCK - 1 if up else 0] + face[2 + a:])] + abs(normal[a])
    d_face = dec[tuple(face)]
    other = ((np.abs(d_face) <= 1.0) & (r_next > BAND_VOXELS)
             & ~((r_next <= BAND_VOXELS + 0.5) & (r_next - d_face <= 1.0)))
    column = (r > 0).sum(axis=1 + a)  # the block's voxels on the plane's free side, per column along the axis
    return (other * column).sum(axis=(1, 2))


def _next_blocks(codec: Codec, c: np.ndarray, normal: np.ndarray, is_coded: np.ndarray, codes_of: Any) -> np.ndarray:
    """For blocks ``c`` ``(n, 3)``: the normalised decodes ``(n, 4096)`` of their neighbours one block along the
    grid axis nearest ``normal``, towards its free side; free space (1.0) where that neighbour is not coded
    (``is_coded``: the grid's blocks, bool) or outside the grid."""
    x = np.ones((len(c), BLOCK ** 3), np.float32)
    a = int(np.argmax(np.abs(normal)))
    nb = c.copy()
    nb[:, a] += 1 if normal[a] > 0 else -1
    inside = np.all((nb >= 0) & (nb < is_coded.shape), axis=1)
    has = inside & is_coded[tuple(np.where(inside[:, None], nb, 0).T)]
    if has.any():
        x[has] = _decode(codec, codes_of(nb[has]))
    return x


def _neighbours(axis: int) -> tuple[tuple[slice, ...], tuple[slice, ...]]:
    """Indices of ``(n, 16, 16, 16)`` blocks: every voxel with a neighbour one step along grid ``axis`` (0-2), and
    that neighbour (the pairs of face neighbours along the axis)."""
    keep = (slice(None),) * (1 + axis)
    return keep + (slice(0, BLOCK - 1),), keep + (slice(1, BLOCK),)


#: A block's own plane (:func:`_local_plane`) replaces the checked plane for :data:`PURITY` when its normal is
#: within this angle (degrees) of it: the map-level stage's tolerance for blocks of one plane.
LOCAL_PLANE_DEG = 15.0
#: Surface voxels within this distance (voxels) of the checked plane place a block's own plane: twice the compared
#: band, so that a block turned by up to LOCAL_PLANE_DEG is seen across most of its width.
LOCAL_BAND_VOXELS = 2 * BAND_VOXELS
_GRID_SQ = float((_GRID[..., 0] ** 2).sum())  # sum of one axis' squared centred coordinates over a block
_GRID_OUTER = (_GRID.reshape(-1, 3, 1) * _GRID.reshape(-1, 1, 3)).reshape(-1, 9)  # (4096, 9): g g^T per voxel


def _local_plane(rel: np.ndarray, dec: np.ndarray, surf: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Voxels' distances ``(n, 4096)`` (voxels, + free side) to each block's own plane: the plane through the
    surface points (each voxel moved back along the normal by its decoded distance ``dec``) of its surface voxels
    ``surf`` within :data:`LOCAL_BAND_VOXELS` of the checked plane (``rel``: distances to it), where at least
    :data:`MIN_VERDICT_SURFACE` such points lie on a plane (rms under a voxel, spread over the block) whose
    normal is within :data:`LOCAL_PLANE_DEG` of the checked plane's and which passes within
    :data:`~sdfcodec.search.scene.PLANE_TOL_VOXELS` of it at its points' centre; else ``rel``. And ``(n,)``
    bool: the block's own surface is a plane turned more than that from the checked one (it crosses the plane,
    it is not of it: a kitchen's sloped or slanted surfaces 14-35 degrees off a wall, near its plane).

    Why: a real wall or floor is not one plane across a room (a fused map's pose drift, a floor that is not
    flat). Measured on the kitchen: wall blocks whose own crossings lie 93-100 % within 2 voxels of their plane,
    5-6 degrees off the wall's fitted plane, had 11-15 % of their decoded surface over a voxel and a half off it
    and failed PURITY as if they held a second surface."""
    g = _GRID.reshape(-1, 3)
    n = (rel @ g) / _GRID_SQ  # each block's normal (rel is affine in the grid: rel = c + g . n)
    n /= np.maximum(np.linalg.norm(n, axis=1), 1e-12)[:, None]
    dd = dec.astype(np.float64)
    local = rel
    for _ in range(2):  # fitted, then refitted around its own fit (a band about the checked plane biases it to it)
        use = (surf & (np.abs(local) <= LOCAL_BAND_VOXELS)).astype(np.float64)
        cnt = use.sum(axis=1)
        w = use / np.maximum(cnt, 1.0)[:, None]
        # the surface points p = g - dec n (each voxel moved back along the normal), their weighted mean mu and
        # covariance sum w p p^T - mu mu^T from the weighted moments of g and dec: products with the (4096, k)
        # grid tables, never the (b, 4096, 3) points (4x faster; float64, the points within a block: no
        # cancellation to speak of)
        wd = w * dd
        sdg = wd @ g
        mu = w @ g - wd.sum(axis=1)[:, None] * n
        cross = sdg[:, :, None] * n[:, None, :]
        cov = ((w @ _GRID_OUTER).reshape(-1, 3, 3) - cross - cross.transpose(0, 2, 1)
               + (wd * dd).sum(axis=1)[:, None, None] * (n[:, :, None] * n[:, None, :])
               - mu[:, :, None] * mu[:, None, :])
        val, vec = np.linalg.eigh(cov)
        nl = vec[:, :, 0] * np.where(np.einsum("bk,bk->b", vec[:, :, 0], n) < 0, -1.0, 1.0)[:, None]
        # a plane: the points' rms off it under a voxel, spread across the block (not a line where surfaces meet)
        planar = (cnt >= MIN_VERDICT_SURFACE) & (val[:, 0] <= 1.0) & (val[:, 1] >= 4.0)
        local = np.where(planar[:, None], nl @ g.T - (mu * nl).sum(axis=1)[:, None], rel)  # (g - mu) . nl
    turned = np.einsum("bk,bk->b", nl, n) < np.cos(np.radians(LOCAL_PLANE_DEG))
    # the block's own plane stands in for the checked one only where it passes within PLANE_TOL_VOXELS of it (at
    # its points' centre; the map-level stage's tolerance for blocks of one plane): a surface farther off the
    # plane is another surface, not the plane bent
    near = np.abs(rel.mean(axis=1) + np.einsum("bk,bk->b", mu, n)) <= PLANE_TOL_VOXELS
    return np.where((planar & ~turned & near)[:, None], local, rel), planar & turned


def _surface_offset(x: np.ndarray, observed: np.ndarray, rel: np.ndarray, centres: np.ndarray, normal: np.ndarray,
                    d: float, *, voxel_size: float, truncation: tuple[float, float]) -> float:
    """The offset ``d`` of a plane with ``normal`` through the decoded surface of blocks of it: the median of
    ``normal . p`` over the points ``p`` where their observed voxels within :data:`BAND_VOXELS` of the plane
    (``rel``, voxels) that decode within half a voxel of zero put the surface (the voxel moved along the normal
    by its decoded distance). Sub-voxel: the block moves the check tries are half a voxel apart, and whether a
    plane a voxel from a block's last layer crosses it is decided within a tenth of a voxel. Returns ``d`` when
    fewer than :data:`MIN_VERDICT_SURFACE` such voxels exist."""
    d_min, d_max = truncation
    dec = x * (d_max - d_min) + d_min  # metres, positive on the free side
    use = observed & (np.abs(dec) <= 0.5 * voxel_size) & (np.abs(rel) <= BAND_VOXELS)
    if use.sum() < MIN_VERDICT_SURFACE:
        return d
    b, v = np.nonzero(use)
    pts = centres[b] + voxel_size * _GRID.reshape(-1, 3)[v] - dec[b, v][:, None] * normal[None, :]
    return float(np.median(pts @ normal))


def _rise(x: np.ndarray, observed: np.ndarray, rel: np.ndarray, normal: np.ndarray, *, voxel_size: float,
          truncation: tuple[float, float]) -> np.ndarray:
    """``(n,)`` how much each block's decoded field rises along the plane's normal near it, as a share of what the
    plane's own field rises: the median, over pairs of observed voxels one step apart along the grid axis nearest
    the normal, both within a voxel beyond :data:`BAND_VOXELS` of the plane (``rel``: voxels from it; a plane
    in a block's last layer leaves a pair only so) and neither decoded at a truncation bound, of the decoded
    difference (voxels), divided by that axis' component of the normal (an exact plane's field: 1; a stretched
    one, more). NaN where under :data:`MIN_VERDICT_SURFACE` pairs: no verdict."""
    d_min, d_max = (t / voxel_size for t in truncation)
    a = int(np.argmax(np.abs(normal)))
    dec = _voxels(x, voxel_size=voxel_size, truncation=truncation).reshape(-1, BLOCK, BLOCK, BLOCK)
    ok = (observed.reshape(dec.shape) & (np.abs(rel).reshape(dec.shape) <= BAND_VOXELS + 1.0)
          & (dec > d_min + 0.25) & (dec < d_max - 0.25))
    lo, hi = _neighbours(a)
    step = (dec[hi] - dec[lo]) * np.sign(normal[a])
    both = (ok[hi] & ok[lo]).reshape(len(dec), -1)
    count = both.sum(axis=1)
    # every row's median at once, as np.median takes it (the middle one or the mean of the middle two)
    srt, rows = np.sort(np.where(both, step.reshape(len(dec), -1), np.inf), axis=1), np.arange(len(dec))
    mid = (srt[rows, np.maximum(count - 1, 0) // 2] + srt[rows, count // 2 - (count == 0)]) / 2
    return np.where(count >= MIN_VERDICT_SURFACE, mid / abs(normal[a]), np.nan)


def _plane_cover(x: np.ndarray, observed: np.ndarray, rel: np.ndarray, *, voxel_size: float,
                 truncation: tuple[float, float], within: float, behind: str) -> np.ndarray:
    """``(n,)`` of the observed voxels within a voxel of a plane (``rel``: voxels from it), the share that decode
    within ``within`` voxels of zero, or, in an unobserved-behind field, behind the plane and negative (there
    nothing but a surface in front makes a voxel negative; the band's jump to d_max smears it far from zero): the
    plane is in the block across its section, not ending inside it."""
    near = observed & (np.abs(rel) <= 1.0)
    dec = _voxels(x, voxel_size=voxel_size, truncation=truncation)
    shown = np.abs(dec) <= within
    if behind == "unobserved":
        shown |= (rel < 0) & (dec < 0)
    return (shown & near).sum(axis=1) / np.maximum(near.sum(axis=1), 1)


def _crossing(normal: np.ndarray) -> float:
    """Voxels from a block's centre within which a plane of this normal still holds surface voxels of the block
    (as the models' planes: :func:`sdfcodec.search.shapes._extent`)."""
    return float(_CENTRE * np.abs(normal).sum() + 1.0)


def verify_threshold(normal: np.ndarray | None, codec: Codec, *, voxel_size: float,
                     truncation: tuple[float, float], behind: str, weighted: bool, stretches: np.ndarray, tol: float,
                     samples: int, quantile: float, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Residuals of simulated clean blocks of the plane with ``normal`` (grid axes): ``samples`` instances at
    offsets uniform across the block (corner slivers redrawn), the checked plane off the true one by up to
    ``tol`` voxels, the field stretched within ``stretches``' range, stored per ``behind``, encoded the map's way
    (``weighted``: surface-true with the observation mask, as the map's writer does) and decoded with
    ``codec``. ``normal=None``: each instance's normal drawn uniformly over the sphere (the calibration of
    surface-true maps, :func:`clean_residuals`). Returns the residuals ``(samples,)`` and how many observed
    surface voxels each had."""
    from .models import encode_query_blocks

    rng = np.random.default_rng([int(seed), 29])
    g = _GRID.reshape(-1, 3)
    n = None if normal is None else np.asarray(normal, np.float64) / np.linalg.norm(normal)
    true_d, shown_d = [], []
    while len(true_d) < samples:
        nk = n
        if nk is None:
            nk = rng.normal(size=3)
            nk /= max(float(np.linalg.norm(nk)), 1e-12)
        along = g @ nk  # voxels along the normal from the block centre
        ext = _crossing(nk)
        c = rng.uniform(-ext, ext)
        if (np.abs(along - c) <= 1.0).sum() < MIN_SHAPE_SURFACE:
            continue
        true_d.append(along - c)
        shown_d.append(along - (c + rng.uniform(-tol, tol)))
    true_d, shown_d = np.asarray(true_d), np.asarray(shown_d)
    st = rng.uniform(float(np.min(stretches)), float(np.max(stretches)), (samples, 1))
    d = true_d * st * voxel_size
    v = normalise(truncate(d, truncation, behind), *truncation).reshape(samples, BLOCK, BLOCK, BLOCK)
    seen = (d >= truncation[0]) if behind == "unobserved" and weighted else np.ones(d.shape, bool)
    codes = encode_query_blocks(codec, v, seen.reshape(v.shape), truncation, voxel_size, weighted)
    x = _decode(codec, codes)
    return plane_residuals(x, seen, shown_d, voxel_size=voxel_size, truncation=truncation, behind=behind,
                           stretches=np.asarray(stretches, np.float64), tol=tol)[:2]


def clean_residuals(normal: np.ndarray, codec: Codec, state_sha256: str | None, *, quantile: float, **kw: Any
                    ) -> tuple[float, float]:
    """The ``quantile`` and the median of :func:`verify_threshold`'s residuals (``kw``: its other arguments;
    ``state_sha256``: :func:`~sdfcodec.search.models.codec_state_sha256` of ``codec``),
    through the query cache (:mod:`sdfcodec.search.cache`, with the tables shipped for the shipped codecs first):
    the simulated instances are seeded, so they depend on nothing but what the key names. A change to what the
    residuals measure MUST bump :data:`~sdfcodec.search.cache.BUILD_VERSION`.

    Surface-true maps (``weighted``) are calibrated once for every plane, over normals drawn uniformly over the
    sphere (``normal`` and ``seed`` are not used): their clean residuals do not depend on the plane's direction
    beyond the calibration's own sampling noise (pca-64, the fused kitchen's context, 256 instances per normal:
    99 % quantiles 1.93-2.61 over 14 normals, axis-aligned, diagonal and random, with no order among them; 1,024
    instances of four of those normals, two seeds each: 2.26-2.68), and each calibration is a weighted encode
    of ``samples`` simulated blocks, most of a cold search's time (the kitchen's walls: 11.5 of 21.8 s for 11
    planes and refits). Others keep one calibration per normal: a plain projection is cheap, and an exact field's
    residuals do depend on it (pca-64: 1.01 axis-aligned, 1.32 along a cube diagonal)."""
    from .cache import cached_threshold

    key, kw = plane_check_key(normal, codec, state_sha256, quantile=quantile, **kw)
    pooled = bool(kw.get("weighted"))

    def compute() -> tuple[float, dict]:
        sim, _ = verify_threshold(None if pooled else normal, codec, quantile=quantile, **kw)
        return float(np.quantile(sim, quantile)), {"median": float(np.median(sim))}

    facing = "planes of any direction" if pooled else f"a plane facing {np.round(normal, 2).tolist()}"
    t, info = cached_threshold(key, compute,
                               valid=lambda info: isinstance(info.get("median"), float) and np.isfinite(info["median"]),
                               what=f"calibrating the plane check of {facing} for {codec.codec_id}-{codec.code_size}")
    return t, info["median"]


def plane_check_key(normal: np.ndarray | None, codec: Codec, state_sha256: str | None, *, quantile: float,
                    **kw: Any) -> tuple[str, dict]:
    """The cache key of :func:`clean_residuals`' calibration and the :func:`verify_threshold` arguments it is
    computed with (``kw`` with, for surface-true maps, the seed and the rounded tolerance that calibration uses):
    also the key of the tables shipped for the shipped codecs (:func:`sdfcodec.search.cache.shipped_thresholds`)."""
    from .cache import cache_key

    pooled = bool(kw.get("weighted"))
    if pooled:  # and at the plane tolerance rounded to the moves' step: a refit's tolerance is any number, but
        # the clean residuals move with it less than with the sampling (1.0, 1.5, 2.0 voxels: 2.30, 2.17, 2.08)
        kw = {**kw, "seed": 0, "tol": float(max(VERIFY_STEP, VERIFY_STEP * np.round(kw["tol"] / VERIFY_STEP)))}
    key = cache_key("plane-check", normal=None if pooled else np.asarray(normal, np.float64),
                    codec=codec.get_config(), state=state_sha256, quantile=float(quantile),
                    **{k: np.asarray(v, np.float64) if k == "stretches" else v for k, v in kw.items()})
    return key, kw


def verify_planes(view: Any, planes: list[tuple[np.ndarray, float]], coded: np.ndarray, strong: np.ndarray,
                  codes_of: Any, *, behind: str, weighted: bool, stretches: Any, quantile: float, samples: int,
                  tol: float
                  ) -> tuple[np.ndarray, np.ndarray, dict]:
    """Check every coded block each plane crosses against it (module docstring).

    Parameters
    ----------
    view : Map
        The map searched.
    planes : list of (normal (3,), d)
        The chosen planes ``n . p = d`` (metres, world frame; ``n`` unit, pointing into free space).
    coded : np.ndarray
        ``(B, 3)`` int64 every coded block.
    strong : np.ndarray
        ``(S, 3)`` int64 blocks the map-level stage kept with a score under the threshold: the blocks that
        measure how much noisier the map is than the simulated instances.
    codes_of : callable
        ``coords (N, 3) -> codes (N, L)``: the blocks' codes at the search's level (held from its stream).
    behind, weighted, stretches :
        How the map stores and encodes its fields (the query model's ``spec``).
    quantile, samples, tol :
        The calibration's quantile and instance count; the plane tolerance (voxels).

    Returns
    -------
    accepted : np.ndarray
        ``(A, 3)`` int64 blocks whose residual is under the threshold of the plane they were checked against.
    undecided : np.ndarray
        ``(U, 3)`` int64 blocks crossed by a plane but observed too little to check.
    impure : np.ndarray
        ``(I, 3)`` int64 checked blocks holding another surface besides the plane (under :data:`PURITY`), unless
        they lie :data:`PURITY` on another plane checked, show it (:data:`MIN_VERDICT_SURFACE` voxels on it) and fit
        it (residual under its threshold and under a solid or free block's).
    info : dict
        JSON-able: per plane, the calibrated threshold, the noise added, the blocks checked, accepted,
        rejected and undecided.
    """
    codec = view.codec
    vs, trunc = view.voxel_size, view.truncation
    origin = np.asarray(view.origin, np.float64)
    st = np.asarray(stretches if stretches is not None else [1.0], np.float64)
    centres = origin + vs * (BLOCK * coded.astype(np.float64) + _CENTRE)
    strong_set = {tuple(c) for c in np.asarray(strong).tolist()}
    is_coded = None  # the grid's coded blocks, for the feet rule (maps without an observation record)
    if not weighted:
        is_coded = np.zeros(tuple(int(g) for g in view.grid_blocks), bool)
        is_coded[tuple(coded.T)] = True
    sha = codec_state_sha256(codec)  # names the codec's state in the calibration's cache key
    accepted, undecided, impure, pure, crossed, report = [], [], [], [], [], []

    def crossing(n: np.ndarray, d: float, move: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The coded blocks the plane, moved up to ``move`` voxels along its normal (as the check moves it),
        crosses by more than a corner sliver: indices into ``coded``, the voxels' distances to the unmoved plane
        ``(K, 4096)`` (voxels, + free side) and each block's centre offset (voxels). The move matters for a plane
        at a block face: a refit a third of a voxel off would otherwise drop every block on one side of it."""
        off = (centres @ n - d) / vs  # voxels from each block's centre to the plane
        near = np.flatnonzero(np.abs(off) <= _crossing(n) + move)
        dist = (off[near, None] + (_GRID.reshape(-1, 3) @ n)[None, :]).astype(np.float32)
        holds = np.zeros(len(near), bool)
        for m in np.arange(-move, move + 1e-9, VERIFY_STEP):
            holds |= (np.abs(dist - np.float32(m)) <= 1.0).sum(axis=1) >= MIN_SHAPE_SURFACE
        return near[holds], dist[holds], off[near[holds]]

    for k, (normal, d) in enumerate(planes):
        n = np.asarray(normal, np.float64)
        near, dist, off = crossing(n, d, 0.0)
        first = coded[near]  # crossed by the plane the map-level stage chose
        if not len(near):
            report.append({"normal": [round(float(v), 4) for v in n], "checked": 0})
            continue
        t_used = tol
        for rnd in range(2):
            c = coded[near]
            x = _decode(codec, codes_of(c))
            obs = scored_voxels(view, c).reshape(len(c), -1) if weighted else np.ones(x.shape, bool)
            on = np.array([tuple(b) in strong_set for b in c.tolist()], bool)
            r, seen, moved, const, share, on_plane, off_plane = plane_residuals(
                x, obs, dist, voxel_size=vs, truncation=trunc, behind=behind, stretches=st, tol=t_used,
                crossings=weighted)
            if not weighted:
                # surfaces standing on the plane whose foot in the block the codec smeared away (_feet): the share
                # counted with the foot the neighbour beyond the block's face shows. Not in maps that record their
                # observation: there it cost the rendered fused rooms more than it gained (tilted floors, seeds
                # 9301-9303: 0.870 / 0.836 -> 0.906 / 0.786; counting only the neighbour's voxels beside a zero
                # crossing, 0.887 / 0.808), and their surface-true codes keep more of a foot in the block itself
                x_next = _next_blocks(codec, c, n, is_coded, codes_of)
                feet = _feet(x_next, dist - moved[:, None], n, voxel_size=vs, truncation=trunc)
                share = np.where(feet > off_plane, np.minimum(share, on_plane / np.maximum(on_plane + feet, 1)),
                                 share)
            t_clean, sim_median = clean_residuals(n, codec, sha, voxel_size=vs, truncation=trunc, behind=behind,
                                                  weighted=weighted, stretches=st, tol=t_used, samples=samples,
                                                  quantile=quantile, seed=k)
            meas = on & (seen >= MIN_VERDICT_SURFACE)
            excess = max(0.0, float(np.median(r[meas]) - sim_median)) if meas.any() else 0.0
            t = t_clean + excess
            decided = seen >= MIN_VERDICT_SURFACE
            # the block shows the plane: as many decoded surface voxels on it as a check needs observed, or a whole
            # shape's worth of observed voxels within a voxel of the fitted plane itself (not moved), at least
            # PURITY of them decoding near zero (_plane_cover: a floor ending inside the block does not). A codec
            # smears a surface at a block face: the block on the far side of a plane through the voxel centres of its
            # neighbour holds the plane a voxel from its last layer, which pca-64 decodes 1.2 voxels from zero
            # (measured: a level exact floor at a block face lost the 100 blocks below it, recall 0.44), and an
            # unobserved-behind field's 2-voxel band before the jump to d_max, stretched by fusion, decodes farther
            # still. A block of solid or free space the plane only reaches by a move fails here and on r < const.
            cover = _plane_cover(x, obs, dist - moved[:, None], voxel_size=vs, truncation=trunc,
                                 within=SECOND_SURFACE_VOXELS * float(st.max()), behind=behind)
            shows = (on_plane >= MIN_VERDICT_SURFACE) | ((seen >= MIN_SHAPE_SURFACE) & (cover >= PURITY))
            # crossed by the plane itself, not only moved into the block
            held = (np.abs(dist) <= 1.0).sum(axis=1) >= MIN_SHAPE_SURFACE
            # and, in a map that records its observation, its observed field rises along the plane's normal there
            # (RISE_SHARE; no verdict on too few pairs). Not in other maps: an exact field's solid holds no band to
            # pass for a plane, and a band-limited one's jump to d_max, read as observed and smeared by the codec,
            # falls along the normal (applied to them: fused-style walls' recall 0.992 -> 0.468, seeds 7901-7903)
            rises = (~(_rise(x, obs, dist - moved[:, None], n, voxel_size=vs, truncation=trunc) < RISE_SHARE)
                     if weighted else np.ones(len(c), bool))
            ok = decided & (r <= t) & (r < const) & (share >= PURITY) & shows & held & rises
            fit = ok & on
            if rnd or fit.sum() < 3:
                break
            # the plane refitted through where its accepted blocks put it (each block's best move; its offset through
            # their decoded surface, _surface_offset), then checked
            # again, on the blocks the refitted plane crosses (a plane first fitted a few degrees off leaves the far
            # blocks of a tilted floor out), with the moves those blocks needed (their 95th percentile, at least
            # one step)
            q = centres[near] - ((off - moved)[:, None] * vs) * n[None, :]
            mu = q[fit].mean(axis=0)
            n2 = np.linalg.svd(q[fit] - mu, full_matrices=False)[2][2]
            n2 = n2 if n2 @ n >= 0 else -n2
            if np.degrees(np.arccos(min(1.0, float(n2 @ n)))) > PLANE_REFIT_DEG:
                n2 = n  # too few blocks, or all in a line: keep the normal, refit the offset
            n, d = n2, float(n2 @ mu)
            # rounded to the moves' step: the moves tried are then whole steps (0 among them), and the few
            # tolerances that remain share their calibrations (clean_residuals)
            t_used = float(min(tol, VERIFY_STEP + np.quantile(np.abs((q[fit] - mu) @ n) / vs, 0.95)))
            if len(st) == 1:  # a stretched (fused) field's decoded distances are not Euclidean: no sub-voxel fit
                d = _surface_offset(x[fit], obs[fit], dist[fit] - moved[fit, None], centres[near[fit]], n, d,
                                    voxel_size=vs, truncation=trunc)
            near, dist, off = crossing(n, d, t_used)
        accepted.append(c[ok])
        # undecided: crossed by the plane itself (not moved) but observed too little; a block only a move reaches is
        # no block of the plane
        undecided.append(c[~decided & held])
        # impure: another surface besides the plane, or (ABSENT) the plane observed across a shape's worth of
        # voxels but not there: fewer decoded surface voxels on it than a verdict needs, and most of the observed
        # voxels on it decoding away from zero (measured: a kitchen block beside a wall, 437 observed voxels on
        # the wall's plane, 2 decoding on it, kept by the map-level stage)
        absent = (seen >= MIN_SHAPE_SURFACE) & (on_plane < MIN_VERDICT_SURFACE) & (cover < ABSENT_COVER)
        # a block observed too little on the plane to check (undecided) whose observed surface lies elsewhere, on the
        # plane's free side (as many voxels of it as a verdict needs), holds another surface too (measured: kitchen
        # blocks no observed voxel of which lies on the floor's plane, holding a surface 2-6 voxels above it, were
        # kept as floor because the stage's 4-voxel level tolerance joined them)
        elsewhere = ~decided & (off_plane >= MIN_VERDICT_SURFACE) & (share < PURITY)
        # a block whose field does not rise along the plane's normal (RISE_SHARE) holds another surface's field
        impure.append(c[(decided & ((share < PURITY) | absent | ~rises)) | elsewhere])
        # pure on this plane, for the rescue below: PURITY on it, showing it, and fitting it (its residual under this
        # plane's threshold and under a solid or free block's): a block whose field is far from the plane (measured: a
        # kitchen block kept as wall through a plane it met with 32 surface voxels at a residual of 84 against a
        # threshold of 11, its own wall's share 0.77) does not lie on it, however few of its voxels lie off it
        pure.append(c[decided & (share >= PURITY) & (on_plane >= MIN_VERDICT_SURFACE) & (r <= t) & (r < const)
                      & rises])
        # crossed, for pruning: by the stage's plane or the refitted one, not moved (the moves widen what is
        # checked, not what is kept; a refit through a wall seen in pieces can miss blocks the stage's plane crossed)
        crossed.append(first.tolist() + c[held].tolist())
        report.append({"normal": [round(float(v), 4) for v in n], "d": round(float(d), 4), "checked": int(len(c)),
                       "move_voxels": round(t_used, 3), "threshold": round(t, 4),
                       "simulated_threshold": round(t_clean, 4),
                       "noise_excess": round(excess, 4), "measured_on": int(on.sum()), "accepted": int(ok.sum()),
                       "rejected": int((decided & ~ok).sum()), "undecided": int((~decided).sum())})
    cat = (lambda parts: np.unique(np.concatenate(parts), axis=0) if parts else np.zeros((0, 3), np.int64))
    info = {"rule": (f"every coded block a chosen plane crosses, checked against that plane (moved up to {tol:g} "
                     f"voxels, {'stretched, ' if len(st) > 1 else ''}over its observed voxels) with a threshold "
                     f"keeping {quantile:.0%} of simulated clean blocks of it, plus the map's measured excess noise"),
            "planes": report, "crossed": crossed}
    # impure only against every plane that was checked on it: a block of one wall that another wall's plane (its
    # extension past a corner) also crosses holds a surface off that plane but lies on its own (measured, kitchen
    # walls: 0.923 / 0.522 without this, 0.857 / 0.783 with it; on a rendered development room, seed 801, it cost
    # wall precision: 0.840 / 0.837 -> 0.823 / 0.884); and only where the block also fits that plane (pure above:
    # kitchen walls 0.857 / 0.783 -> 0.900 / 0.783, rendered tilted development rooms 801-806 0.837 / 0.879 -> 0.842 /
    # 0.876; no effect on maps without an observation record, whose selection is what the check accepts)
    impure_c = cat(impure)
    if len(impure_c) and pure:
        shows = {tuple(c) for c in cat(pure).tolist()}
        impure_c = impure_c[np.array([tuple(c) not in shows for c in impure_c.tolist()], bool)].reshape(-1, 3)
    return cat(accepted).astype(np.int64), cat(undecided).astype(np.int64), impure_c.astype(np.int64), info


def check_planes(view: Any, model: QueryModel, scene_info: dict, kept: np.ndarray, kept_strong: np.ndarray,
                 coded: np.ndarray, codes_of: Any) -> np.ndarray:
    """The final selection of a staged floor, ceiling or wall search: the blocks the planes the map-level stage
    chose (``scene_info["planes"]``, moved to ``scene_info["plane_check"]`` with the check's report) accept,
    plus the blocks it kept that were observed too little to check (maps that record their observation: see the
    comment in the body). ``kept`` ``(K, 3)``: the map-level stage's blocks, ``kept_strong`` ``(K,)`` bool: those
    scoring under the threshold; ``coded``: every coded block; ``codes_of``: see :func:`verify_planes`."""
    from .calibrate import CALIBRATION_QUANTILE, CALIBRATION_SAMPLES

    spec = model.spec or {}
    planes = [(np.asarray(p["normal"], np.float64), float(p["d"])) for p in scene_info.pop("planes", [])]
    if not planes:
        return kept
    # the walls of a map that records its observation keep some of the stage's blocks and add none (below): the
    # selection reads the verdicts of those only, and the refits and noise measure come from its strong blocks, so
    # only the stage's blocks are checked (the kitchen: 170 checks instead of 509, the same verdicts and selection)
    walls = bool(spec.get("weighted")) and spec.get("shape") == "wall"
    acc, undecided, impure, info = verify_planes(
        view, planes, kept if walls else coded, kept[kept_strong], codes_of, behind=spec.get("behind", "solid"),
        weighted=bool(spec.get("weighted")), stretches=spec.get("stretch"), quantile=CALIBRATION_QUANTILE,
        samples=CALIBRATION_SAMPLES, tol=PLANE_TOL_VOXELS)
    if spec.get("weighted"):
        # a map that records its observation was fused from views: its blocks of a plane are seen in parts and
        # stretched, and the residual alone, over a block seen through one voxel layer, does not tell the plane from
        # another shape (measured: the rendered rooms' floor blocks seen that way score like furniture). Here the
        # stage's blocks are kept unless they hold another surface besides the plane or the plane does not cross them
        # (the stage joins blocks to a level within its 4-voxel tolerance); blocks are added only when the check
        # accepts them with all its rules.
        bad = {tuple(c) for c in impure.tolist()}
        crossed = {tuple(c) for p in info["crossed"] for c in p}
        # kept: crossed by a chosen plane (more than a corner sliver of it) and not holding another surface
        stay = (np.array([tuple(c) not in bad and tuple(c) in crossed for c in kept.tolist()], bool) if len(kept)
                else np.zeros(0, bool))
        info["rule"] = (f"the map-level stage's blocks that a chosen plane crosses, whose decoded surface lies at "
                        f"least {PURITY:.0%} on it, plus "
                        "for floors and ceilings the blocks the plane crosses that the check accepts (a map that "
                        "records its observation)")
        info.pop("crossed")
        info["dropped"] = int((~stay).sum())
        # plus, for floors and ceilings, the crossed blocks the check accepts (residual, purity, the plane shown):
        # blocks of the plane the lattice model scored poorly, e.g. a floor at a block face seen through one layer
        have = {tuple(c) for c in kept[stay].tolist()}
        add = np.array([tuple(c) not in have for c in acc.tolist()], bool) if len(acc) else np.zeros(0, bool)
        # not for walls: on the kitchen the blocks a wall's check accepted were mostly cabinet fronts and appliance
        # sides coplanar with a wall plane (20 added, precision 0.89 -> 0.47 against its bounding-wall labels)
        add &= spec.get("shape") != "wall"
        out = np.concatenate([kept[stay], acc[add]]) if add.any() else kept[stay]
        info["added"] = int(add.sum())
        info["selected"] = int(len(out))
        scene_info["plane_check"] = info
        return out.astype(np.int64).reshape(-1, 3)
    und = {tuple(c) for c in undecided.tolist()}
    stay = np.array([tuple(c) in und for c in kept.tolist()], bool) if len(kept) else np.zeros(0, bool)
    out = np.unique(np.concatenate([acc, kept[stay]]), axis=0) if len(acc) or stay.any() else acc
    info.pop("crossed")
    info["kept_unchecked"] = int(stay.sum())
    info["selected"] = int(len(out))
    scene_info["plane_check"] = info
    return out.astype(np.int64).reshape(-1, 3)
