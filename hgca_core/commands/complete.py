"""`hgca complete SCAN... -o MESH`: one mesh per sample, written atomically as MESH_s<i>.<format>."""
from __future__ import annotations

import argparse
from pathlib import Path

from hgca_core.commands.arguments import (add_completion_arguments, add_config_arguments, add_format_argument,
                                          add_frames_argument, add_out_argument,
                                          add_poses_argument, add_progress_argument, completion_config)
from hgca_core.config import DriveConfig
from hgca_core.files import mesh_format, output_paths

__all__ = ["add_arguments", "run", "output_paths", "mesh_format"]


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("scans", nargs="+", help="scan files (ply, las/laz, pcd, xyz/csv, npy/npz, KITTI .bin, nuScenes "
                                            ".pcd.bin, AV2 .feather) or one sequence folder (KITTI, AV2, nuScenes)")
    add_frames_argument(p)
    add_out_argument(p, "MESH", required=True,
                     help="the mesh file's name; sample i goes to MESH_s<i>.<format>, the format from "
                          "--mesh-format or else MESH's extension (.ply, .obj, .glb, .npz)")
    add_config_arguments(p, ("mesh_format",), DriveConfig,
                         mesh_format={"default": None, "help": "mesh format (default: MESH's extension)"})
    add_poses_argument(p)
    add_format_argument(p)
    p.add_argument("--region", help="cx,cy,cz,sx,sy,sz[,yaw_deg] in the world frame (default: 38.4 x 38.4 x 8 m "
                                    "around the first scan's sensor, from 1 m below the ground)")
    add_completion_arguments(p)
    add_config_arguments(p, ("semantics", "semantics_weights"))
    add_progress_argument(p)


def run(args: argparse.Namespace) -> int:
    from hgca_core.progress import Progress

    progress = Progress(args.progress, samples=args.samples)
    with progress.failures_reported():
        outputs = _run(args, progress)
    progress.done([str(p) for p in outputs])
    return 0


def _run(args: argparse.Namespace, progress) -> list[Path]:
    from hgca_core.files import complete_files

    return complete_files(args.scans, args.out, completion_config(args), poses=args.poses, region=args.region,
                          frames=args.frames, topic=args.topic, fmt=args.fmt, mesh_format=args.mesh_format, progress=progress)
