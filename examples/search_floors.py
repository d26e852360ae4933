"""Find the floors of a compressed map from its codes alone, then decode only those blocks.

    python examples/search_floors.py                       # a synthetic room with known floor, encoded pca-64
    python examples/search_floors.py room.sdfz --top 50    # your own map (any codec)

Prints how many blocks were scored and selected, and the bytes read for the search and for the expansion
against the whole map; for the synthetic room also precision and recall against its analytic floor. With
--picture, writes the paper's Fig. 7-style picture (the map from above, the selection outlined).
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import sdfcodec
from sdfcodec.search.engine import expand, search


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("map", nargs="?", help="a map path or URL (default: make a synthetic pca-64 room)")
    ap.add_argument("--size", type=float, default=3.0, help="synthetic room floor edge in metres (default 3)")
    ap.add_argument("--level", type=int, help="compare only the first LEVEL code elements (pca maps)")
    ap.add_argument("--threshold", type=float, help="select scores <= this (default: automatic)")
    ap.add_argument("--top", type=int, help="select at most this many blocks")
    ap.add_argument("--picture", type=Path, help="write a top-down picture of the selection here (.png)")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="sdfcodec-floors-") as work:  # the synthetic room's map, removed after
        _report(args, Path(work) / "room.sdfz")


def _report(args: argparse.Namespace, scratch: Path) -> None:
    room = None
    path = args.map
    if path is None:
        from sdfcodec.search.rooms import synthetic_room

        room = synthetic_room(0, size=(args.size, args.size, 2.0))          # exact TSDF with labelled primitives
        path = scratch
        with sdfcodec.create_map(path, codec=sdfcodec.pretrained_codec("pca", 64), voxel_size=room.voxel_size,
                                 truncation=room.truncation, origin=tuple(room.origin)) as m:
            m.write_volume(room.volume)
    m = sdfcodec.open_map(path)

    threshold = args.threshold if args.threshold is not None else ("auto" if args.top is None else None)
    up = room.up if room is not None else (0.0, 0.0, 1.0)
    res = search(m, "floor" if room is None else _floor_query(m, up), level=args.level, threshold=threshold,
                 top=args.top, keep_scores=args.picture is not None)
    exp = expand(m, res, as_="blocks")                                       # decodes the selection, nothing else
    info = m.info()
    read_search = sum(res.stats["bytes_read"].values())
    read_expand = sum(exp.stats["bytes_read"].values())
    print(f"{path}: {info['codec']['id']}-{m.code_size}, {res.stats['blocks_scored']} coded blocks scored at level "
          f"{res.level} in {res.stats['seconds']:.2f} s; threshold {res.threshold}")
    print(f"selected {len(res)} blocks; decoded {exp.stats['blocks_decoded']} of {exp.stats['coded_blocks']} "
          f"({exp.blocks.shape})")
    on_disk = info["bytes_on_disk"]
    print(f"bytes read: search {read_search / 1024:.0f} KiB, expansion {read_expand / 1024:.0f} KiB"
          + (f", whole map on disk {on_disk / 1024:.0f} KiB" if on_disk else ""))
    if room is not None:
        truth = room.scene.floor_blocks(res.coords, room.origin, room.voxel_size) if len(res) else []
        all_floor = room.scene.floor_blocks(_coded(m), room.origin, room.voxel_size)
        tp = int(sum(truth))
        print(f"against the analytic floor ({int(all_floor.sum())} blocks): precision {tp / max(len(res), 1):.2f}, "
              f"recall {tp / max(int(all_floor.sum()), 1):.2f}")
    if args.picture is not None:
        from sdfcodec.view.search import search_picture

        print(f"picture: {search_picture(m, res, args.picture, up=up)}")


def _floor_query(m, up):
    """The built-in floor model for this map, posed with the room's up direction."""
    from sdfcodec.search.query import build_query

    return build_query("floor", map=m, up=tuple(float(u) for u in up))


def _coded(m):
    import numpy as np

    return np.argwhere(m.block_states() == 2)


if __name__ == "__main__":
    main()
