"""Compile the package's numba kernels into numba's on-disk cache before the suite's workers need them
(tests/conftest.py starts one process per job below while the xdist workers collect).

In a fresh checkout no kernel is cached: each worker, and every subprocess a test started in the meantime,
compiled the same kernels itself (writing the first pca map compiles the masked encode, ~35 CPU-s; the pinned
masks and the entropy coder more). Run once, split over the two cores, the workers then load them from the cache.
The jobs run the package's own paths on small inputs (no signature is written down here to go stale); a job that
fails only leaves its kernels to be compiled where they are used, as before.

    python tests/numba_warm.py pca|pinned
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import numpy as np

VS, TRUNC = 0.02, (-0.04, 0.1)


def _volume() -> np.ndarray:
    from sdfcodec.core.sdf import sample_volume
    from sdfcodec.testing import analytic_scene

    return sample_volume(analytic_scene(), (64, 48, 32), VS, truncation=TRUNC)


def pca(d: Path) -> None:
    """The writer's masked encode (sdfcodec_pca.kernels): a pca map written with fusion weights."""
    import sdfcodec
    from sdfcodec.core.blocks import split_blocks

    vol = _volume()
    blocks = split_blocks(vol, fill=TRUNC[1]).reshape(-1, 16, 16, 16)
    coords = np.argwhere(np.ones(split_blocks(vol, fill=TRUNC[1]).shape[:3], bool))
    codec = sdfcodec.get_codec("pca", code_size=16).fit(((blocks - TRUNC[0]) / (TRUNC[1] - TRUNC[0])))
    weights = np.ones(blocks.shape, np.float32)
    with sdfcodec.create_map(d / "w.sdfz", codec=codec, voxel_size=VS, truncation=TRUNC,
                             keep_weights=True) as m:
        m.write_blocks(coords, blocks, weights=weights)
    sdfcodec.open_map(d / "w.sdfz").decode_region()


def pinned(d: Path) -> None:
    """The pinned masks and the entropy coder (sdfcodec.core.pinkernels, anskernels): a map encoded at a low
    target rate by the command line, then read."""
    from sdfcodec_pca import truncated
    from typer.testing import CliRunner

    import sdfcodec
    from sdfcodec.cli import app
    from sdfcodec.core.blocks import split_blocks

    # the writer's encode takes its torch path here (the same codes): the pca job compiles the masked encode
    truncated.available = lambda: False
    # as fusion leaves it: voxels deeper than |d_min| behind a surface unobserved (the mask the pins store)
    vol = _volume()
    observed = vol > TRUNC[0] + 1e-6
    vol = np.where(observed, vol, np.float32(TRUNC[1])).astype(np.float32)
    blocks = split_blocks(vol, fill=TRUNC[1])
    coords = np.argwhere(np.ones(blocks.shape[:3], bool))
    obs = split_blocks(observed.astype(np.float32), fill=1.0).reshape(-1, 16, 16, 16) > 0.5
    with sdfcodec.create_map(d / "room.sdfz", codec=sdfcodec.get_codec("raw"), voxel_size=VS,
                             truncation=TRUNC, shape_voxels=vol.shape) as m:
        m.write_blocks(coords, blocks.reshape(-1, 16, 16, 16), observed=obs)
    # 128 B a block: plain pins; 384 B: a refined map (its pins read through the refined float decode)
    for target in ("128", "384"):
        out = d / f"p{target}.sdfz"
        r = CliRunner().invoke(app, ["encode", str(d / "room.sdfz"), str(out), "--target-bytes", target])
        if r.exit_code != 0:
            raise SystemExit(r.output)
        sdfcodec.open_map(out).decode_region()


if __name__ == "__main__":
    with tempfile.TemporaryDirectory(prefix="sdfcodec-warm-") as tmp:
        {"pca": pca, "pinned": pinned}[sys.argv[1]](Path(tmp))
