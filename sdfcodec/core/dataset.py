"""Training data sets: normalised 16^3 blocks in a chunked Zarr group, split like the paper.

Layout (a Zarr v3 group; attribute ``sdfcodec_dataset`` holds the metadata)::

    <dataset>/train        (N_train, 16, 16, 16) float16, one chunk per batch of ``batch_size`` blocks
    <dataset>/validation   (N_val,   16, 16, 16) float16
    <dataset>/test         (N_test,  16, 16, 16) float16

The paper shuffles its 200,000 samples into 400 batches of 500 and uses 300 for training, 50 for validation
and 50 for testing; :func:`build_dataset` splits the batches in the same 300 : 50 : 50 proportions whatever
the total. float16 halves the size at an error (about 2.4e-4 normalised, float16's step just below 1.0) far
below what any codec reaches. Every chunk is checksummed like maps are.
"""

from __future__ import annotations

import json
import os
import shutil
import uuid
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator

import numpy as np
import zarr
from zarr.codecs import BloscCodec, Crc32cCodec

from ..errors import FormatError, InvalidValueError, MapExistsError, MapNotFoundError, VersionError, WriteFailedError

__all__ = ["Dataset", "build_dataset", "open_dataset", "SPLITS"]

SPLITS = ("train", "validation", "test")
DATASET_FORMAT, DATASET_VERSION = "sdfcodec-dataset", 1


@dataclass
class Dataset:
    """An open data set: ``train``/``validation``/``test`` Zarr arrays plus metadata."""

    path: str
    group: zarr.Group
    meta: dict[str, Any]

    def split(self, name: str) -> zarr.Array:
        if name not in SPLITS:
            raise InvalidValueError(f"split must be one of {SPLITS}, got {name!r}")
        return self.group[name]

    def __len__(self) -> int:
        return sum(self.split(s).shape[0] for s in SPLITS)

    def iter_batches(self, name: str = "train", batch_size: int | None = None) -> Iterator[np.ndarray]:
        """Yield float32 batches ``(B, 16, 16, 16)`` of a split, one chunk-aligned read at a time."""
        arr = self.split(name)
        bs = batch_size or int(self.meta["batch_size"])
        for i in range(0, arr.shape[0], bs):
            yield np.asarray(arr[i:i + bs], dtype=np.float32)

    def load(self, name: str = "train", max_blocks: int | None = None) -> np.ndarray:
        """A split (or its first ``max_blocks``) as one float32 array in memory."""
        arr = self.split(name)
        n = arr.shape[0] if max_blocks is None else min(max_blocks, arr.shape[0])
        return np.asarray(arr[:n], dtype=np.float32)


def _compressors() -> list:
    return [BloscCodec(cname="zstd", clevel=3, shuffle="shuffle"), Crc32cCodec()]


def build_dataset(path: str | os.PathLike, sources: Iterable[tuple[str, Iterable[np.ndarray]]], *,
                  batch_size: int = 500, proportions: tuple[int, int, int] = (300, 50, 50), seed: int = 0,
                  voxel_size: float | None = None, truncation: tuple[float, float] = (-0.04, 0.1),
                  overwrite: bool = False, progress: Callable[[int], None] | None = None) -> Dataset:
    """Collect normalised blocks from ``sources``, shuffle them, split them by batches and write a data set.

    Args:
        sources: ``(name, iterable of (B, 16, 16, 16) normalised batches)`` pairs; names are recorded.
        batch_size: blocks per batch (and per chunk).
        proportions: relative numbers of train/validation/test batches (the paper's 300/50/50).
        seed: shuffling seed.
        voxel_size, truncation: recorded in the metadata (blocks are already normalised).
        overwrite: replace an existing data set at ``path``.

    The blocks are shuffled in memory (float16, 8 KiB per block: 200,000 blocks are 1.6 GiB). The data set is
    written beside ``path`` and moved into place when complete.
    """
    final = Path(path)
    if os.path.lexists(final) and not overwrite:
        raise MapExistsError(f"{final} exists; pass overwrite=True (CLI: --overwrite) to replace it")
    _check_replaceable(final)
    parts, counts = [], {}
    for name, batches in sources:
        n0 = sum(len(p) for p in parts)
        for b in batches:
            b = np.asarray(b)
            if b.ndim != 4 or b.shape[1:] != (16, 16, 16):
                raise InvalidValueError(f"source {name!r} gave blocks of shape {b.shape}, need (B, 16, 16, 16)")
            if not np.isfinite(b).all() or b.min() < -1e-3 or b.max() > 1 + 1e-3:
                raise InvalidValueError(f"source {name!r} gave values outside [0, 1] or non-finite: blocks must be "
                                        "normalised (sdfcodec.core.blocks.normalise)")
            parts.append(b.astype(np.float16))
            if progress:
                progress(len(b))
        counts[name] = sum(len(p) for p in parts) - n0
    blocks = np.concatenate(parts) if parts else np.zeros((0, 16, 16, 16), np.float16)
    n = len(blocks)
    if n < 3 * batch_size:
        raise InvalidValueError(f"only {n} blocks: a data set needs at least 3 batches of {batch_size} "
                                "(one per split); add sources or lower batch_size")
    blocks = blocks[np.random.default_rng(seed).permutation(n)]
    n_batches = n // batch_size  # a last partial batch is dropped, as the paper uses whole batches
    w = np.asarray(proportions, dtype=np.float64)
    nb_val = max(1, int(round(n_batches * w[1] / w.sum())))
    nb_test = max(1, int(round(n_batches * w[2] / w.sum())))
    nb_train = n_batches - nb_val - nb_test
    if nb_train < 1:
        raise InvalidValueError(f"{n_batches} batches cannot be split {proportions}; add data")
    bounds = np.cumsum([0, nb_train, nb_val, nb_test]) * batch_size

    tmp = final.with_name(f".{final.name}.tmp-{uuid.uuid4().hex[:8]}")
    try:
        final.parent.mkdir(parents=True, exist_ok=True)
        group = zarr.open_group(zarr.storage.LocalStore(str(tmp)), mode="w", zarr_format=3)
        for split, lo, hi in zip(SPLITS, bounds[:-1], bounds[1:]):
            arr = group.create_array(split, shape=(int(hi - lo), 16, 16, 16), dtype="float16",
                                     chunks=(batch_size, 16, 16, 16), compressors=_compressors(), fill_value=1.0)
            arr[...] = blocks[lo:hi]
        group.attrs["sdfcodec_dataset"] = {
            "format": DATASET_FORMAT, "format_version": DATASET_VERSION, "batch_size": batch_size,
            "proportions": list(proportions), "seed": seed, "voxel_size": voxel_size,
            "truncation": list(truncation), "sources": counts,
            "splits": {s: int(h - lo) for s, lo, h in zip(SPLITS, bounds[:-1], bounds[1:])},
        }
        _check_replaceable(final)  # again: something else may have been put there meanwhile
        if final.exists():
            shutil.rmtree(final)
        os.replace(tmp, final)
    except BaseException as e:
        shutil.rmtree(tmp, ignore_errors=True)
        if isinstance(e, OSError) and not isinstance(e, WriteFailedError):
            outcome = ("the data set there is unchanged" if final.exists() else "nothing was written there")
            raise WriteFailedError.from_os_error(e, final, "writing the data set",
                                                 f"{outcome} and no temporary files are left") from e
        raise
    return open_dataset(final)


def _check_replaceable(final: Path) -> None:
    """Refuse to replace anything at ``final`` but a data set or an empty directory (``overwrite`` must never
    delete a directory of other files, a plain file, a device or a link's target)."""
    if not os.path.lexists(final):
        return
    if final.is_symlink() or not final.is_dir():
        raise MapExistsError(f"{final} exists and is not a data set directory; refusing to replace it (remove it "
                             "yourself or write elsewhere)")
    if not any(final.iterdir()):
        return
    try:
        open_dataset(final)
    except (FormatError, MapNotFoundError, VersionError) as e:
        raise MapExistsError(f"{final} exists and is not an sdfcodec data set ({e}); refusing to replace it "
                             "(remove it yourself or write elsewhere)") from None


def open_dataset(path: str | os.PathLike) -> Dataset:
    """Open a data set written by :func:`build_dataset`."""
    p = Path(path)
    if not p.exists():
        raise MapNotFoundError(f"no data set at {p}")
    try:
        group = zarr.open_group(str(p), mode="r", zarr_format=3)
    except Exception as e:
        raise FormatError(f"{p}: not a readable Zarr v3 group ({e})") from e
    meta = group.attrs.get("sdfcodec_dataset")
    if not isinstance(meta, dict) or meta.get("format") != DATASET_FORMAT:
        raise FormatError(f"{p}: not an sdfcodec data set (build one with `sdfcodec dataset`)")
    if meta.get("format_version", 0) > DATASET_VERSION:
        raise VersionError(f"{p}: data set format version {meta.get('format_version')} is newer than this "
                           f"sdfcodec reads ({DATASET_VERSION})")
    missing = [s for s in SPLITS if s not in group]
    if missing:
        raise FormatError(f"{p}: data set lacks split(s) {missing}")
    return Dataset(str(p), group, json.loads(json.dumps(meta)))
