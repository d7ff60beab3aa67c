"""`hgca read SCAN... [--poses P] [--format F] [--json] -o OUT.npz`: accumulate scans into one .npz.

The Blender add-on imports scans through this command, so it gets every format and the poses logic
without importing laspy/plyfile (or torch) inside Blender.
"""
from __future__ import annotations

import argparse
import json
import os

from hgca_core.commands.arguments import (add_format_argument, add_frames_argument, add_json_argument,
                                          add_out_argument, add_poses_argument)
from hgca_core.errors import InputError


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("scans", nargs="+", help="scan files (ply, las/laz/copc, pcd, xyz/csv/txt, npy/npz, "
                                            "KITTI .bin, nuScenes .pcd.bin, AV2 .feather), or one sequence "
                                            "folder (KITTI, Argoverse 2 log, nuScenes sweeps)")
    add_frames_argument(p)
    add_poses_argument(p)
    add_format_argument(p)
    add_out_argument(p, "FILE.npz", required=True,
                     help="output .npz: points (N,3) f64 relative to offset (3,) f64, attributes (scan_index, "
                          "origin_index, ...), origins, and the inputs' crs")
    add_json_argument(p, "print one JSON object (out, points, scans, attributes, dropped: returns the reader left "
                         "out, by reason) instead of the sentence")


def run(args: argparse.Namespace) -> int:
    from hgca_core.io.memory import check_read_memory
    from hgca_core.io.paths import check_outputs

    if os.path.splitext(args.out)[1].lower() != ".npz":
        raise InputError("output must end in .npz", args.out)
    check_outputs([args.out], [*args.scans, args.poses])
    check_read_memory(args.scans)

    from hgca_core.io.arrays import READ_RESERVED, write_accumulated
    from hgca_core.io.las_crs import check_inputs
    from hgca_core.io.read import keep_units
    from hgca_core.io.sequence import read_inputs

    with keep_units():   # the files' own numbers, whatever their unit: the CRS written beside them says which
        scan = read_inputs(args.scans, poses=args.poses, fmt=args.fmt, frames=args.frames, topic=args.topic)
    crs, unit = check_inputs(args.scans, metric=False)
    attributes = {k: v for k, v in scan.attributes.items() if k not in READ_RESERVED}
    write_accumulated(args.out, scan, attributes, crs, unit)
    scans = int(scan.attributes["scan_index"].max()) + 1
    if args.json:
        print(json.dumps({"out": args.out, "points": len(scan), "scans": scans, "attributes": list(attributes),
                          "dropped": {why: int(n) for why, n in scan.dropped.items()}, "crs": crs}))
    else:
        print(f"{args.out}: {len(scan)} points from {scans} scan(s), attributes: {', '.join(attributes) or 'none'}"
              + "".join(f"; left out {n} {why}" for why, n in scan.dropped.items()))
    return 0
