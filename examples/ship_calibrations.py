"""Write the calibrations shipped with sdfcodec (sdfcodec/search/shipped-calibrations.json), so that a first
floor, ceiling or wall search of a fused map spends no time on them.

    make calibrations        # = python examples/ship_calibrations.py

What is shipped: the plane check's clean residuals of surface-true (fused) maps
(``sdfcodec.search.plane_check.clean_residuals``), which depend on no map: not on the plane's direction (they are
calibrated over normals drawn over the sphere) nor on its position, only on the codec, the voxel size, the
truncation, the fusion stretches and the plane tolerance. One entry per shipped pca size (the prefixes of the
shipped eigenshapes), at the default 2 cm voxels and truncation [-0.04, 0.1] m, for each tolerance a search uses
(whole steps of ``VERIFY_STEP`` up to ``PLANE_TOL_VOXELS``). Each entry holds its key (the one a search computes;
it names the codec's state digest, so retrained eigenshapes miss the table and calibrate as before) and the
arguments it was computed with, so a test recomputes it. What depends on the map's up direction (the query
models and their thresholds) is not shipped: the disk cache keeps it after the first search.

Deterministic (seeded); about 2 s per entry on two cores.
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

import numpy as np

os.environ.setdefault("SDFCODEC_CACHE_DIR", "off")  # computed here, never read from a cache

from sdfcodec import pretrained_codec  # noqa: E402
from sdfcodec.map import state_digest  # noqa: E402
from sdfcodec.search import cache  # noqa: E402
from sdfcodec.search.calibrate import CALIBRATION_QUANTILE, CALIBRATION_SAMPLES  # noqa: E402
from sdfcodec.search.plane_check import VERIFY_STEP, plane_check_key, verify_threshold  # noqa: E402
from sdfcodec.search.query import FUSED_STRETCH  # noqa: E402
from sdfcodec.search.scene import PLANE_TOL_VOXELS  # noqa: E402

#: The shipped pca sizes, the defaults a fused map is made with.
SIZES = (32, 64, 128)
VOXEL_SIZE, TRUNCATION = 0.02, (-0.04, 0.1)


def entries(sizes=SIZES) -> dict:
    """``{key: {"threshold", "info", "codec", "args"}}`` for every shipped entry (module docstring)."""
    out = {}
    tols = VERIFY_STEP * np.arange(1, int(round(PLANE_TOL_VOXELS / VERIFY_STEP)) + 1)
    for size in sizes:
        codec = pretrained_codec("pca", size)
        sha = state_digest(codec.state_dict())
        for tol in tols:
            args = dict(voxel_size=VOXEL_SIZE, truncation=TRUNCATION, behind="unobserved", weighted=True,
                        stretches=np.asarray(FUSED_STRETCH, np.float64), tol=float(tol),
                        samples=CALIBRATION_SAMPLES)
            key, kw = plane_check_key(None, codec, sha, quantile=CALIBRATION_QUANTILE, **args)
            sim, _ = verify_threshold(None, codec, quantile=CALIBRATION_QUANTILE, **kw)
            out[key] = {"threshold": float(np.quantile(sim, CALIBRATION_QUANTILE)),
                        "info": {"median": float(np.median(sim))},
                        "codec": {"id": "pca", "code_size": size, "state_sha256": sha},
                        "args": {**{k: v for k, v in kw.items() if k != "stretches"},
                                 "truncation": list(TRUNCATION), "stretches": [float(s) for s in FUSED_STRETCH],
                                 "quantile": CALIBRATION_QUANTILE}}
            print(f"pca-{size} tol {tol:g}: {out[key]['threshold']:.4f}", flush=True)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=cache.SHIPPED_FILE)
    args = ap.parse_args(argv)
    doc = {"format": "sdfcodec-calibrations", "version": 1, "build": cache.BUILD_VERSION,
           "made_by": "examples/ship_calibrations.py", "entries": entries()}
    args.out.write_text(json.dumps(doc, indent=1, sort_keys=True) + "\n", encoding="utf-8")
    print(f"wrote {args.out}: {len(doc['entries'])} entries")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
