"""``edgevo map info FILE``: what a saved keyframe map holds (``map.archive``): its
keyframes, their extent, its size, camera and settings, and the library that wrote it.
``edgevo map export FILE OUT.ply``: its edges as a coloured point cloud (``map.export``)."""

from __future__ import annotations

import argparse
from pathlib import Path


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Add ``edgevo map`` and its subcommands to the subcommands ``sub``."""
    p = sub.add_parser("map", help="look at a saved keyframe map (--save-map's file)")
    kinds = p.add_subparsers(dest="map_command", required=True)
    info = kinds.add_parser("info", help="its keyframes, extent, size and camera")
    info.add_argument("file", type=Path, help="a map file written by --save-map")
    export = kinds.add_parser(
        "export", help="its keyframes' edges as a coloured point cloud (PLY)",
        description="Write the keyframes' edges, lifted with their depth, in the map's "
                    "frame, as a binary PLY any point-cloud viewer opens; colour: when the "
                    "keyframe was made (first dark blue, last yellow).")
    export.add_argument("file", type=Path, help="a map file written by --save-map")
    export.add_argument("out", type=Path, help="the PLY file to write")
    export.add_argument("--max-depth", type=float, default=None, metavar="M",
                        help="only edges nearer than M metres to their keyframe's camera")


def command(args: argparse.Namespace) -> int:
    """``edgevo map info``: print the map's summary; ``edgevo map export``: write the PLY
    and say how many points. MapFileError (a ValueError: exit 2) for a file that is no
    readable map."""
    if args.map_command == "export":
        from ..io import check_output
        from ..map.export import export_ply

        if args.out.suffix.lower() != ".ply":
            raise ValueError(f"{args.out}: the point cloud is written as PLY: name it .ply")
        check_output(args.out, what="the PLY file", make_folders=True)
        n = export_ply(args.file, args.out, max_depth=args.max_depth)
        print(f"wrote {args.out} ({n:,} points)")
        return 0
    print(info_text(args.file))
    return 0


def info_text(path: Path) -> str:
    """The lines ``edgevo map info`` prints for the map file at ``path``."""
    import numpy as np

    from ..map.archive import read_header, read_keyframe_table

    header = read_header(path)
    table = read_keyframe_table(path)
    cam = header["camera"]
    fx, fy, cx, cy = cam["intrinsics"]
    n = int(header["keyframes"])
    centres = table["pose"][:, :3, 3]
    lo, hi = centres.min(axis=0), centres.max(axis=0)
    span = float(table["timestamp"].max() - table["timestamp"].min())
    size = path.stat().st_size
    anchored = int(np.count_nonzero(table["anchored"]))
    return "\n".join([
        f"map           {path} ({header['format']} version {header['version']}, written "
        f"by edgevo_jax {header['library']})",
        f"keyframes     {n} ({anchored} tied to the map, {n - anchored} in chains made at a "
        f"guess), over {span:.1f} s",
        f"extent        x {lo[0]:.2f}..{hi[0]:.2f}  y {lo[1]:.2f}..{hi[1]:.2f}  z "
        f"{lo[2]:.2f}..{hi[2]:.2f} m (keyframe centres, the map's frame)",
        f"size          {size / 1e6:.2f} MB ({size / max(n, 1) / 1e3:.0f} kB a keyframe)",
        f"camera        {cam['width']}x{cam['height']}, fx {fx:g} fy {fy:g} cx {cx:g} cy "
        f"{cy:g}",
        "settings      " + ", ".join(f"{k} {v}" for k, v in sorted(header["settings"].items())),
    ])
