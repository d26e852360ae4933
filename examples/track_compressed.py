"""Track a depth camera against a compressed map, decoding blocks on demand, and compare with the original.

    python examples/track_compressed.py                        # render a synthetic room, fuse, encode, track
    python examples/track_compressed.py --frames 20            # shorter
    python examples/track_compressed.py --sequence SEQ         # a TUM RGB-D or 7-Scenes folder with ground truth

The map is fused from the sequence's ground-truth poses (lossless ``raw``), encoded with the shipped pca-64,
and the SDF Tracker follows the sequence from the first ground-truth pose in both. Prints the ATE and the
decoded-block cache's statistics. The same as ``sdfcodec track MAP SEQ -o TRAJ.txt``.
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import sdfcodec
from sdfcodec.data.render import render_sequence
from sdfcodec.data.sequences import open_sequence
from sdfcodec.evaluation.tracking import EVAL_TRACKER_CONFIG
from sdfcodec.fusion.tsdf import fuse
from sdfcodec.tracking.mapfield import MapField
from sdfcodec.core.metrics import Trajectory, ate
from sdfcodec.tracking.tracker import SDFTracker, TrackerConfig

TRUNC = (-0.04, 0.1)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sequence", type=Path, help="TUM RGB-D or 7-Scenes folder (default: render a synthetic one)")
    ap.add_argument("--frames", type=int, default=40, help="frames to fuse and track (default 40)")
    ap.add_argument("--stride", type=int, default=1, help="use every N-th frame")
    ap.add_argument("--level", type=int, help="track against the first LEVEL code elements only")
    ap.add_argument("--out", type=Path, help="output folder (default: a temporary one)")
    args = ap.parse_args(argv)
    out = args.out or Path(tempfile.mkdtemp(prefix="sdfcodec-track-"))
    out.mkdir(parents=True, exist_ok=True)
    seq_dir = args.sequence or render_sequence(out / "sequence", "slow-noisy", seed=0, frames=args.frames,
                                               overwrite=True)
    seq = open_sequence(seq_dir)[::args.stride][:args.frames]

    fused = fuse(seq, truncation=TRUNC, quiet=True)
    maps = {}
    for name, codec in (("original", sdfcodec.get_codec("raw")), ("pca-64", sdfcodec.pretrained_codec("pca", 64))):
        with sdfcodec.create_map(out / f"{name}.sdfz", codec=codec, voxel_size=fused.voxel_size, truncation=TRUNC,
                                 origin=tuple(fused.origin), overwrite=True) as m:
            m.write_blocks(fused.coords, fused.tsdf)
        maps[name] = sdfcodec.open_map(out / f"{name}.sdfz")

    depths = [f.depth for f in seq]
    gt = seq.poses
    k = seq.intrinsics
    for name, m in maps.items():
        field = MapField(m, level=args.level if name != "original" else None, cache_bytes=64 << 20)
        with SDFTracker(field, (k.fx, k.fy, k.cx, k.cy), TrackerConfig(**EVAL_TRACKER_CONFIG)) as tracker:
            tracked = tracker.track_sequence(depths, gt[0])
        st = ate(Trajectory.from_poses(gt), Trajectory.from_poses(tracked.poses))
        c = field.stats()
        print(f"{name:>8}: {len(depths)} frames, ATE RMSE {1000 * st.rmse:.1f} mm (max {1000 * st.max:.1f} mm), "
              f"{len(tracked.failures)} failed; {c['blocks_decoded']} blocks decoded for {c['coded_blocks']} coded, "
              f"cache hit rate {c['hit_rate']:.3f}")


if __name__ == "__main__":
    main()
