"""What a map stores beside its codes, per array, and what its observation mask could cost
(docs/side-information.md).

    python examples/side_information.py MAP [MAP ...]                    # bytes per coded block, per array
    python examples/side_information.py --mask-study MAP                 # predicting the observation mask

The table counts every file of each map (``zarr.json`` metadata documents apart, as ``ARRAY/zarr.json``),
divided by the map's coded blocks; ``total`` leaves out the codec state (``codec/``), which a shipped model's
reference removes (spec section 6c).

``--mask-study`` takes a lossy map with an observation mask (a fused map transcoded with a block codec such as
pca) and measures, on its coded blocks, the predictors of the mask from the decoded field, each as the compressed
bytes per coded block of what would be stored (Blosc zstd level 9, 512 blocks per chunk, as dense as possible):

* ``plain``: the packed mask itself (what spec section 6b stores);
* ``decoded <= t``: unobserved predicted where the map's full decode (the codec's decode of the stored codes) is at or
  below ``t`` (normalised; 0 is ``d_min``), the exceptions stored as a packed XOR bitmap: the number of
  mispredicted voxels per block says how well the decoded field knows the mask;
* ``entropy, k causal neighbours``: the empirical conditional entropy of each bit given its ``k`` already-coded
  neighbours (a static context model, the table's cost left out): a lower bound for any coder of that kind,
  and the same with the decoded field (4 levels) added to the context.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numcodecs
import numpy as np

import sdfcodec
from sdfcodec.map.observed import read_observed

CHUNK = 512  # blocks per compressed chunk in the mask study
#: Causal neighbours (already coded in C order) of the context models, nearest first.
NEIGHBOURS = [(1, 0, 0), (0, 1, 0), (0, 0, 1), (1, 1, 0), (1, 0, 1), (0, 1, 1), (1, -1, 0), (1, 0, -1), (0, 1, -1)]


def array_bytes(path: Path) -> tuple[int, dict[str, int]]:
    """Coded blocks of the map at ``path`` and bytes of its files by array (``ARRAY/zarr.json`` apart)."""
    with sdfcodec.open_map(path) as m:
        coded = m.count_states()["coded"]
    rows: dict[str, int] = {}
    for f in sorted(path.rglob("*")):
        if not f.is_file():
            continue
        parts = f.relative_to(path).parts
        if len(parts) == 1:
            key = "zarr.json (group, header)"
        elif parts[0] == "codec":
            key = "codec/ (state)"
        else:
            key = parts[0] + ("/zarr.json" if f.name == "zarr.json" else "")
        rows[key] = rows.get(key, 0) + f.stat().st_size
    return coded, rows


def table(paths: list[Path]) -> str:
    """Markdown: bytes per coded block per array, one column per map."""
    got = [array_bytes(p) for p in paths]
    keys = sorted({k for _, r in got for k in r})
    lines = ["| array | " + " | ".join(p.name for p in paths) + " |", "|---|" + "---|" * len(paths)]
    for k in keys:
        lines.append(f"| {k} | " + " | ".join(f"{r.get(k, 0) / max(n, 1):.1f}" for n, r in got) + " |")
    totals = [sum(v for k, v in r.items() if not k.startswith("codec/")) / max(n, 1) for n, r in got]
    lines.append("| **total (no codec/)** | " + " | ".join(f"**{t:.1f}**" for t in totals) + " |")
    lines.append("| coded blocks | " + " | ".join(str(n) for n, _ in got) + " |")
    return "\n".join(lines)


def _compressed(rows: np.ndarray) -> float:
    """Bytes per row of ``rows`` ``(n, R)`` uint8, compressed CHUNK rows at a time (+4: the CRC32C)."""
    blosc = numcodecs.Blosc("zstd", 9, numcodecs.Blosc.NOSHUFFLE)
    return sum(len(blosc.encode(np.ascontiguousarray(rows[i:i + CHUNK]))) + 4
               for i in range(0, len(rows), CHUNK)) / max(len(rows), 1)


def _shifted(m: np.ndarray, d: tuple[int, int, int]) -> np.ndarray:
    """``m`` ``(n, 16, 16, 16)`` int moved by ``d`` voxels (each voxel sees its neighbour at ``-d``), 1 outside."""
    out = np.ones_like(m)
    dst = tuple(slice(max(a, 0), 16 + min(a, 0)) for a in d)
    src = tuple(slice(max(-a, 0), 16 - max(a, 0)) for a in d)
    out[(slice(None), *dst)] = m[(slice(None), *src)]
    return out


def _entropy(ctx: np.ndarray, bits: np.ndarray, n: int) -> float:
    """Empirical conditional entropy of ``bits`` given ``ctx`` (same shape, ints), bytes per block of ``n``."""
    c1 = np.bincount(ctx.ravel(), weights=bits.ravel())
    c = np.bincount(ctx.ravel()).astype(float)
    c0 = c - c1
    h = sum(-(x[x > 0] * np.log2(x[x > 0] / c[x > 0])).sum() for x in (c0, c1))
    return h / 8 / n


def mask_study(path: Path, thresholds=(0.02, 0.05, 0.1, 0.2)) -> list[tuple[str, float, float]]:
    """``(predictor, bytes per coded block, mispredicted voxels per block)`` of the map at ``path``."""
    m = sdfcodec.open_map(path)
    pairs = list(m.iter_codes())
    coords, codes = np.concatenate([c for c, _ in pairs]), np.concatenate([z for _, z in pairs])
    obs = read_observed(m.reader, coords)
    n = len(coords)
    flat = obs.reshape(n, -1)
    out = [("plain", _compressed(np.packbits(flat, axis=1)), float("nan"))]
    # the full decode of the stored codes (the codec's float32 decode, compared in float64)
    decoded = np.concatenate([np.asarray(m.reader.codec.decode(codes[i:i + 4096])).reshape(-1, 4096)
                              for i in range(0, n, 4096)]).astype(np.float64)
    for t in thresholds:
        wrong = (decoded > t) != flat
        out.append((f"decoded <= {t}", _compressed(np.packbits(wrong, axis=1)), float(wrong.sum(1).mean())))
    bits = obs.astype(np.int64)
    q = np.clip((decoded.reshape(obs.shape) * 4).astype(np.int64), 0, 3)
    for k in (3, 6, 9):
        ctx = np.zeros_like(bits)
        for i, d in enumerate(NEIGHBOURS[:k]):
            ctx |= _shifted(bits, d) << i
        out.append((f"entropy, {k} causal neighbours", _entropy(ctx, bits, n), float("nan")))
        out.append((f"entropy, {k} causal neighbours + decoded", _entropy(ctx | (q << k), bits, n), float("nan")))
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("maps", nargs="+", type=Path)
    ap.add_argument("--mask-study", action="store_true", help="Predictors of the observation mask (one map).")
    a = ap.parse_args(argv)
    if not a.mask_study:
        print(table(a.maps))
        return
    print("| predictor | B/block | mispredicted voxels/block |\n|---|---|---|")
    for name, b, wrong in mask_study(a.maps[0]):
        print(f"| {name} | {b:.1f} | {'' if np.isnan(wrong) else f'{wrong:.0f}'} |")


if __name__ == "__main__":
    main()
