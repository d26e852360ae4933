"""Golden fixtures: a codec's configuration, state, an input batch and its codes and decoded blocks, written
once and checked forever, so a change of numerics or format shows as a failing test."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..codec import Codec
from ..model import load_state_file, save_state_file
from ..registry import get_codec
from ._compare import assert_close
from ._data import analytic_blocks

__all__ = ["GOLDEN_FILES", "golden_dir_files", "write_golden", "check_golden"]

GOLDEN_FILES = ("config.json", "state.npz", "input.npy", "codes.npy", "decoded.npy")


def golden_dir_files(path: str | Path) -> list[Path]:
    """The files a golden fixture directory holds."""
    return [Path(path) / f for f in GOLDEN_FILES]


def write_golden(codec: Codec, path: str | Path) -> None:
    """(Re)write the fixture at ``path`` from ``codec``: 8 analytic blocks (seed 2024) ``(8, 16, 16, 16)``
    float32, their codes ``(8, code_size)`` and decoded blocks, plus the config (JSON) and state (``.npz``)."""
    cfg_p, state_p, in_p, codes_p, dec_p = golden_dir_files(path)
    Path(path).mkdir(parents=True, exist_ok=True)
    x = analytic_blocks(8, seed=2024)
    codes = codec.encode(x)
    cfg_p.write_text(json.dumps(codec.get_config(), indent=2, sort_keys=True) + "\n")
    save_state_file(state_p, codec.state_dict())
    np.save(in_p, x)
    np.save(codes_p, codes)
    np.save(dec_p, codec.decode(codes))


def check_golden(path: str | Path, atol: float) -> None:
    """The codec rebuilt from the fixture's config and state alone reproduces its codes and decoded blocks."""
    path = Path(path)
    cfg_p, state_p, in_p, codes_p, dec_p = golden_dir_files(path)
    missing = [p.name for p in golden_dir_files(path) if not p.exists()]
    assert not missing, f"golden: {path} lacks {missing}; create it once with regen_golden=True " \
                        "(pytest --regen-golden) and commit it"
    g = get_codec(json.loads(cfg_p.read_text())).load_state_dict(load_state_file(state_p))
    x = np.load(in_p, allow_pickle=False)
    codes = np.load(codes_p, allow_pickle=False)
    assert_close(g.encode(x), codes, atol, f"golden: codes of {path}")
    assert_close(g.decode(codes), np.load(dec_p, allow_pickle=False), atol, f"golden: decoded blocks of {path}")
