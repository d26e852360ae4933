"""The automatic threshold of a search, calibrated on the map searched (:func:`calibrate_threshold`): clean
instances of the query's shape, stored, encoded and scored the map's way, and the share of them kept. Below the
search itself, so that what a map says about itself (:mod:`sdfcodec.search.context`) and the plane check
(:mod:`sdfcodec.search.plane_check`) calibrate the same way."""

from __future__ import annotations

import json
from typing import Any

import numpy as np

from ..codec import Codec
from .arrays import decode_array, encode_array
from .cache import cache_key, cached_threshold
from .models import QueryModel, codec_state_sha256, encode_query_blocks
from .scoring import ObservedScorer, Scorer, score_codes
from .shapes import NEAR_MISSES, sample_shapes

__all__ = ["CALIBRATION_QUANTILE", "CALIBRATION_SAMPLES", "LIKE_SHIFT", "SURFACE_SHARE", "calibrate_threshold", "cone_angle"]


#: :func:`calibrate_threshold`: the share of simulated clean instances of the query's shape kept.
CALIBRATION_QUANTILE = 0.99


#: :func:`calibrate_threshold`: how many instances are simulated.
CALIBRATION_SAMPLES = 256


def cone_angle(rotations: Any) -> float:
    """The cone angle (degrees) of a built-in model's rotations as its spec records them (0: none)."""
    if isinstance(rotations, dict) and "cone" in rotations:
        return float(rotations["cone"])
    if isinstance(rotations, str) and rotations.startswith("cone"):
        parts = rotations.split(":")
        return float(parts[1]) if len(parts) > 1 else 10.0
    return 0.0


def calibrate_threshold(model: QueryModel, codec: Codec, level: int, scorer: "Scorer",
                        observed_scorer: ObservedScorer | None = None, samples: int = CALIBRATION_SAMPLES
                        ) -> tuple[float, dict]:
    """An automatic threshold calibrated for the map being searched: :data:`CALIBRATION_SAMPLES` clean
    instances of the model's shape with continuous parameters (plane offsets anywhere in the block, any wall
    yaw, tilts within the model's cone; :func:`sdfcodec.search.shapes.sample_shapes`) are made at the map's
    voxel size and truncation, stored the map's way (``behind``), encoded with the map's codec the map's way
    (plain, or surface-true with their observation mask), and scored against the model exactly as the map's
    blocks are; the threshold keeps :data:`CALIBRATION_QUANTILE` of them. It follows the codec, code size,
    level, truncation and model resolution of each search, with no constant taken from any room.

    Models without a built-in shape (user blocks, ``like:``) are calibrated on copies of their blocks shifted by
    up to half a voxel (:func:`_calibrate_blocks`).

    Returns
    -------
    threshold : float
    info : dict
        ``method`` ("calibrated" or "calibrated on shifted copies"), ``samples``,
        ``quantile``, ``simulated`` (the simulated scores' 50/90/95/100 % quantiles) and ``tilt_deg``.
    """

    spec = model.spec
    if spec is None or "shape" not in spec:
        return _calibrate_blocks(model, codec, level, scorer, samples)
    # the calibration depends on nothing but what the key names (the simulated instances are seeded): cached
    key = cache_key("threshold", spec={k: v for k, v in spec.items() if k != "context"},
                    descriptors=model.descriptors[:, :level], codec=codec.get_config(),
                    state=codec_state_sha256(codec), level=level,
                    samples=int(samples), observed=observed_scorer is not None, voxel_size=model.voxel_size,
                    truncation=list(model.truncation))
    t, info = cached_threshold(key, lambda: _calibrate(model, codec, level, scorer, observed_scorer, samples),
                               what=f"calibrating the {spec['shape']} threshold for {codec.codec_id}-{codec.code_size}")
    return t, json.loads(json.dumps(info))  # a copy: the caller may add to its report


#: :func:`_calibrate_blocks`: "like these blocks" means the same shape up to this shift (voxels, per axis).
LIKE_SHIFT = 0.5


def _calibrate_blocks(model: QueryModel, codec: Codec, level: int, scorer: "Scorer", samples: int
                      ) -> tuple[float, dict]:
    """The threshold of a model of user blocks or of a map's own blocks (``like:``): the model's blocks (decoded
    from its descriptors when it holds none) shifted by random offsets of up to :data:`LIKE_SHIFT` voxel per axis
    (trilinear, nearest value beyond the block), encoded with the map's codec and scored against the model; the
    threshold keeps :data:`CALIBRATION_QUANTILE` of them: "like these" is the same shape up to half a voxel."""
    from scipy.ndimage import shift as nd_shift

    if model.blocks is not None:
        v = np.asarray(model.blocks, np.float32)
    else:
        codes = model.descriptors
        if codes.shape[1] < codec.code_size:
            codes = np.pad(codes, ((0, 0), (0, codec.code_size - codes.shape[1])))
        v = decode_array(codec, codes).reshape(len(codes), 16, 16, 16)
    rng = np.random.default_rng(23)
    pick = rng.integers(len(v), size=int(samples))
    moved = np.stack([nd_shift(v[i], rng.uniform(-LIKE_SHIFT, LIKE_SHIFT, 3), order=1, mode="nearest") for i in pick])
    s, _ = scorer(encode_array(codec, np.clip(moved, 0.0, 1.0))[:, :level])
    q = np.quantile(s, [0.5, 0.9, CALIBRATION_QUANTILE, 1.0])
    return float(q[2]), {"method": "calibrated on shifted copies", "samples": int(samples),
                         "quantile": CALIBRATION_QUANTILE, "shift_voxels": LIKE_SHIFT,
                         "simulated": {"q50": float(q[0]), "q90": float(q[1]),
                                       f"q{round(100 * CALIBRATION_QUANTILE)}": float(q[2]), "max": float(q[3])}}


def _calibrate(model: QueryModel, codec: Codec, level: int, scorer: "Scorer",
               observed_scorer: ObservedScorer | None, samples: int) -> tuple[float, dict]:
    spec = model.spec
    tilt = cone_angle(spec.get("rotations"))
    v, seen = sample_shapes(spec["shape"], int(samples), voxel_size=model.voxel_size,
                            truncation=model.truncation, up=spec["up"], tilt_deg=tilt, behind=spec["behind"],
                            stretch=(min(spec.get("stretch", [1.0])), max(spec.get("stretch", [1.0]))))
    codes = encode_query_blocks(codec, v, seen, model.truncation, model.voxel_size, bool(spec.get("weighted")))
    weighted = bool(spec.get("weighted"))
    s, _ = score_codes(scorer, observed_scorer, codes[:, :level], seen if weighted else None)
    q = np.quantile(s, [0.5, 0.9, CALIBRATION_QUANTILE, 1.0])
    info = {"method": "calibrated", "samples": int(samples), "quantile": CALIBRATION_QUANTILE, "tilt_deg": tilt,
            "simulated": {"q50": float(q[0]), "q90": float(q[1]), f"q{round(100 * CALIBRATION_QUANTILE)}": float(q[2]),
                          "max": float(q[3])}}
    t = float(q[2])
    others = NEAR_MISSES.get(spec["shape"], ())
    if others:
        # shapes the query must not match (an edge model is no plane detector): the threshold also keeps at most
        # 1 - CALIBRATION_QUANTILE of them
        per = -(-int(samples) // len(others))
        vs_, ss_ = zip(*(sample_shapes(o, per, voxel_size=model.voxel_size, truncation=model.truncation,
                                       up=spec["up"], tilt_deg=tilt, behind=spec["behind"], seed=1 + k,
                                       stretch=(min(spec.get("stretch", [1.0])), max(spec.get("stretch", [1.0]))))
                         for k, o in enumerate(others)))
        nv, ns = np.concatenate(vs_), np.concatenate(ss_)
        nc = encode_query_blocks(codec, nv, ns, model.truncation, model.voxel_size, weighted)
        sn, _ = score_codes(scorer, observed_scorer, nc[:, :level], ns if weighted else None)
        miss = float(np.quantile(sn, 1.0 - CALIBRATION_QUANTILE))
        info["near_misses"] = {"shapes": list(others), "samples": int(len(sn)),
                               f"q{round(100 * (1 - CALIBRATION_QUANTILE))}": miss,
                               "kept_share_of_clean": float(np.mean(s <= min(t, miss)))}
        t = min(t, miss)
    return t, info


#: ``sdfcodec.search.engine``'s surface test and :func:`~sdfcodec.search.context.estimate_up`: a block within this share of the query's threshold of a block of solid or free space
#: holds no surface (an exact SDF's solid blocks are at 0; a plane clipping a corner is far beyond).
SURFACE_SHARE = 0.1
