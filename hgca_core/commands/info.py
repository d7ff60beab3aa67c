"""`hgca info FILE... [--json] [--format F]`: what a scan file holds, to check a file before completing it."""
from __future__ import annotations

import argparse
import json
import os
import sys
from typing import Any


def add_arguments(p: argparse.ArgumentParser) -> None:
    from hgca_core.commands.arguments import (add_format_argument, add_frames_argument, add_json_argument,
                                              add_poses_argument)

    p.add_argument("files", nargs="+", help="scan files (ply, las/laz/copc, pcd, xyz/csv/txt, npy/npz, "
                                            "KITTI .bin, nuScenes .pcd.bin, AV2 .feather), or one sequence folder")
    add_frames_argument(p)
    add_poses_argument(p, "poses JSON replacing a sequence folder's own poses")
    add_json_argument(p, "print one JSON document instead of text")
    add_format_argument(p)


def _facts(scan) -> dict[str, Any]:  # noqa: ANN001 - a hgca_core.io.Scan (imported lazily)
    """What `hgca info` says of any read scan: point count, bounds, attributes, origins, rows left out."""
    return {
        "points": len(scan),
        "bounds": {"min": scan.points.min(axis=0).tolist(), "max": scan.points.max(axis=0).tolist()},
        "attributes": {name: str(values.dtype) for name, values in scan.attributes.items()},
        "origins": None if scan.origins is None else scan.origins.tolist(),
        "dropped": dict(scan.dropped),
    }


def describe(path: str, fmt: str | None = None) -> dict[str, Any]:
    """Facts about one file as plain JSON-able values (raises InputError for bad files)."""
    from hgca_core.io import read_scan, resolve_format
    from hgca_core.io.las import las_header_info

    scan = read_scan(path, fmt)  # raises InputError for anything wrong with the file
    chosen = resolve_format(path, fmt)
    info: dict[str, Any] = {"file": path, "format": chosen, **_facts(scan)}
    if chosen == "las":
        info["las"] = las_header_info(path)
    return info


def describe_sequence(root: str, frames: str | None, poses: str | None, topic: str | None = None) -> dict[str, Any]:
    """Facts about the chosen frames of a sequence folder (bag, E57), accumulated with its poses."""
    from hgca_core.io.sequence import open_sequence, parse_frames, select

    seq = open_sequence(root, poses, topic)
    files, mats = select(seq, frames)
    scan = seq.accumulate(files, mats)
    return {
        "file": root,
        "format": f"{seq.layout} sequence",
        "frames_total": len(seq),
        "frames": parse_frames(frames, len(seq), root),
        "scans": files,
        **_facts(scan),
    }


def _sequence_info(root: str, frames: str | None, poses: str | None, topic: str | None) -> dict[str, Any]:
    """describe_sequence, and for a ROS bag its topics listing first (alone when no cloud topic is chosen)."""
    from hgca_core.io.sequence import container_layout

    if container_layout(root) != "rosbag":
        return describe_sequence(root, frames, poses, topic)
    from hgca_core.io.rosbag import describe_bag

    bag = describe_bag(root, topic)
    if bag["cloud"] is None:
        return {"file": root, "format": "rosbag", "bag": bag}
    return {**describe_sequence(root, frames, poses, topic), "bag": bag}


def _bag_text(bag: dict[str, Any]) -> list[str]:
    width = max(len(t["topic"]) for t in bag["topics"]) if bag["topics"] else 0
    lines = ["  topics:", *[f"    {t['topic']:<{width}}  {t['type']}  {t['messages']}" for t in bag["topics"]]]
    c = bag["cloud"]
    clouds = [t["topic"] for t in bag["topics"] if t["type"] == "sensor_msgs/msg/PointCloud2"]
    if c is None:
        return lines + [f"  cloud:      give --topic ({len(clouds)} point cloud topics: {', '.join(clouds) or 'none'})"]
    return lines + [f"  cloud:      {c['topic']}: {c['frames']} frames over {c['duration_s']:.3f} s "
                    f"({c['start_s']:.3f} to {c['end_s']:.3f}), frame {', '.join(c['sensor_frames'])}",
                    f"  poses:      {c['poses']}"]


def _text(info: dict[str, Any]) -> str:
    def fmt3(v: list[float]) -> str:
        return " ".join(f"{x:.3f}" for x in v)

    bag = _bag_text(info["bag"]) if "bag" in info else []
    if "points" not in info:
        return "\n".join([info["file"], f"  format:     {info['format']}", *bag])
    lines = [
        *([info["file"], f"  format:     {info['format']}", *bag] if bag else []),
        *([] if bag else [info["file"], f"  format:     {info['format']}"]),
        *([f"  frames:     {len(info['frames'])} of {info['frames_total']} "
           f"({info['frames'][0]} to {info['frames'][-1]}): "
           + ", ".join(os.path.basename(f) for f in info["scans"][:3]) + (" ..." if len(info["scans"]) > 3 else "")]
          if "frames" in info else []),
        f"  points:     {info['points']}",
        f"  bounds min: {fmt3(info['bounds']['min'])}",
        f"  bounds max: {fmt3(info['bounds']['max'])}",
        "  attributes: " + (", ".join(f"{k} ({v})" for k, v in info["attributes"].items()) or "none"),
        "  origins:    " + ("unknown" if info["origins"] is None
                            else "; ".join(fmt3(o) for o in info["origins"][:4])
                            + (f" ... ({len(info['origins'])} in all)" if len(info["origins"]) > 4 else "")),
        *[f"  dropped:    {n} {why}" for why, n in info.get("dropped", {}).items()],
    ]
    las = info.get("las")
    if las:
        kind = "COPC" if las["copc"] else ("LAZ" if las["compressed"] else "LAS")
        lines += [
            f"  las:        {kind} {las['version']}, point format {las['point_format']}, "
            f"header point count {las['header_point_count']}",
            f"  scale:      {' '.join(repr(v) for v in las['scale'])}",
            f"  offset:     {' '.join(repr(v) for v in las['offset'])}",
        ]
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    from hgca_core.errors import InputError
    from hgca_core.io.sequence import is_sequence

    files = [os.fspath(f) for f in args.files]
    if is_sequence(files):
        if args.fmt is not None:
            raise InputError("--format applies to scan files, not to a sequence folder", files[0])
        infos = [_sequence_info(files[0], args.frames, args.poses, args.topic)]
    elif args.frames is not None or args.poses is not None or args.topic is not None:
        raise InputError("--frames, --poses and --topic need a sequence folder (KITTI, Argoverse 2 or nuScenes), "
                         "a ROS bag or an E57")
    else:
        infos = [describe(f, args.fmt) for f in files]
    if args.json:
        json.dump({"files": infos}, sys.stdout, indent=2)
        sys.stdout.write("\n")
    else:
        print("\n".join(_text(i) for i in infos))
    return 0
