"""`hgca poses SEQUENCE -o poses.json [--frames A:B]`: a sequence folder's poses in our JSON, so the scan
files of a KITTI sequence, an Argoverse 2 log or nuScenes sweeps can be read by every tool (and the add-on)
with `--poses`, exactly as the folder itself places them."""
from __future__ import annotations

import argparse
import json
import os

from hgca_core.commands.arguments import add_frames_argument, add_out_argument
from hgca_core.errors import InputError


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("sequence", help="sequence folder (KITTI velodyne/ + poses.txt + calib.txt, Argoverse 2 log, "
                                    "nuScenes *.pcd.bin with poses.json)")
    add_frames_argument(p, "frames to write (default: all)")
    add_out_argument(p, "FILE.json", required=True, help="output JSON (docs/CONTRACTS.md)")


def run(args: argparse.Namespace) -> int:
    from hgca_core.io.atomic import atomic_write
    from hgca_core.io.sequence import open_sequence, poses_document

    from hgca_core.io.paths import check_outputs

    if os.path.splitext(args.out)[1].lower() != ".json":
        raise InputError("output must end in .json", args.out)
    check_outputs([args.out], [args.sequence])     # the folder's own poses.json is an input it reads
    out_dir = os.path.dirname(os.path.abspath(args.out))
    doc = poses_document(open_sequence(args.sequence), args.frames, out_dir)
    text = json.dumps(doc, indent=1).encode("utf-8")
    atomic_write(args.out, lambda f: f.write(text))
    print(f"{args.out}: poses of {len(doc['scans'])} {doc['layout']} scan(s)")
    return 0
