"""`hgca drive SCAN... --poses P --out DIR` (or a sequence folder): a whole drive, tile by tile along its
trajectory (`hgca_core.drive`).

Writes DIR/tiles/<i>_s<k>.ply, DIR/drive_s<k>.ply (one merged mesh per sample) and DIR/drive.json. Running
the same command again resumes: finished tiles are kept. `--workers N` runs tiles in parallel on a Ray started
in this process; `--address ray://host:port` on an existing cluster. `--plan-only` prints where the tiles go
(the Blender add-on draws them) and writes nothing.
"""
from __future__ import annotations

import argparse
import json
import sys

from hgca_core.commands.arguments import (add_completion_arguments, add_config_arguments, add_format_argument,
                                          add_frames_argument, add_json_argument, add_out_argument,
                                          add_poses_argument, add_progress_argument, check_device,
                                          completion_config, positive_float)
from hgca_core.config import DriveConfig
from hgca_core.errors import InputError

DEFAULTS = DriveConfig()


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("scans", nargs="+", help="scan files in any order (taken in the drive's: --poses' order, else time "
                   "stamps, else the chain of sensor positions; any format `hgca complete` reads), or one sequence "
                   "folder (KITTI, Argoverse 2 log, nuScenes sweeps)")
    add_out_argument(p, "DIR", help="the drive folder (created; re-running resumes): tiles/<i>_s<k>.<format>, "
                                    "drive_s<k>.<format> and drive.json")
    add_poses_argument(p)
    add_frames_argument(p, "frames of a sequence folder (default: all of them)")
    add_format_argument(p)
    add_config_arguments(p, ("size", "overlap", "scans_per_tile"), DriveConfig)
    p.add_argument("--plan-only", action="store_true",
                   help="print the tiles (regions along the trajectory, their scans) and stop; writes nothing")
    add_json_argument(p, "--plan-only: print the plan as one JSON object")
    add_completion_arguments(p, seed={"help": "sample k of tile i uses seed + i * samples + k"},
                             max_faces={"help": "simplify each tile's mesh to at most N triangles (default 0: every "
                                                "triangle, so the tiles' surfaces meet at the seams as computed)"})
    add_config_arguments(p, ("seams", "workers", "address", "threads"), DriveConfig,
                         seams={"help": "do not condition tiles on their finished neighbours (faster start, joins "
                                        "may disagree)"})
    # GiB on the command line, bytes in the config
    p.add_argument("--tile-memory", type=positive_float, default=None, metavar="GIB",
                   help="memory each tile declares to Ray (default: estimated from the tile's area)")
    add_config_arguments(p, ("mesh_format",), DriveConfig)
    add_progress_argument(p)


def drive_config(args: argparse.Namespace) -> DriveConfig:
    """The `DriveConfig` of `hgca drive`'s parsed options."""
    return DriveConfig(completion=completion_config(args, DEFAULTS.completion), size=args.size,
                       overlap=args.overlap, scans_per_tile=args.scans_per_tile, seams=args.seams,
                       workers=args.workers, address=args.address, threads=args.threads,
                       tile_memory=args.tile_memory * 2**30 if args.tile_memory else None,
                       mesh_format=args.mesh_format)


def run(args: argparse.Namespace) -> int:
    from hgca_core.io.memory import check_read_memory

    if args.plan_only:
        drive_config(args)
        return _plan_only(args)
    from hgca_core.progress import Progress
    from hgca_core.tiling.run import drive

    progress = Progress(args.progress if args.progress != "bar" else "none", samples=args.samples)
    with progress.failures_reported():
        config = drive_config(args)
        check_device(args.device)
        check_read_memory(args.scans)
        if not args.out:
            raise InputError("--out DIR is required (the drive folder), except with --plan-only")
    bar = None

    def on_tile(done: int, total: int, index: int, state: str) -> None:
        nonlocal bar
        if args.progress == "bar":
            if bar is None:
                from tqdm import tqdm

                bar = tqdm(total=total, initial=done, desc="tiles", unit="tile", file=sys.stderr, smoothing=0.1)
            else:
                bar.update(done - bar.n)
        progress.record("tile", done, total, f"tile {index} {state}", tile=index, state=state)

    def on_plan(plan: dict) -> None:
        progress.record("plan", 0, len(plan["tiles"]), f"{len(plan['tiles'])} tiles", plan=plan)

    def on_step(index: int, stage: str, step: int, total: int) -> None:
        """A chain step of the tile running here: a `tile-step` record (the add-on's bar moves within a tile)."""
        if bar is not None and total:
            bar.set_postfix_str(f"tile {index}: {stage} {step}/{total}")
        progress.record("tile-step", step, total, f"tile {index}: {stage} {step}/{total}", tile=index, chain=stage)

    try:
        with progress.failures_reported():
            doc = drive(args.scans, args.out, poses=args.poses, fmt=args.fmt, frames=args.frames, topic=args.topic,
                        config=config, report=progress, on_tile=on_tile, on_plan=on_plan, on_step=on_step)
    finally:
        if bar is not None:
            bar.close()
    progress.done(doc["outputs"])
    if args.progress == "bar":
        t = doc["timings"]
        print(f"{len(doc['tiles'])} tiles ({t['tiles_computed']} computed in {t['tiles_s']:.1f} s), "
              f"merged in {t['merge_s']:.1f} s: {', '.join(doc['outputs'])}", file=sys.stderr)
    return 0


def _plan_only(args: argparse.Namespace) -> int:
    """Read the scans, place the tiles, print them (`run.plan_drive`; the add-on's boxes come from here)."""
    from hgca_core.tiling.inputs import read_drive_inputs
    from hgca_core.tiling.run import plan_drive

    scans = read_drive_inputs(args.scans, args.poses, args.fmt, args.frames, topic=args.topic)
    _, _, plan = plan_drive(scans, args.size, args.overlap, args.scans_per_tile)
    if args.json:
        print(json.dumps(plan))
        return 0
    print(f"{len(plan['tiles'])} tiles along {plan['length']:.1f} m ({len(scans)} scans)")
    for t in plan["tiles"]:
        print(f"tile {t['index']} (phase {t['phase']}): --region={','.join(repr(v) for v in t['region'])} "
              f"scans {t['scans']}")
    return 0
