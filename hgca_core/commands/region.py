"""`hgca region SCAN... [--poses P] [--size SX,SY,SZ] [--json]`: the default region `hgca complete` would use.

The Blender add-on's "Add Region Box" asks this command instead of estimating a box itself, so the CLI and
the add-on place the same box around the same scans (one estimator: `geometry.region.default_region`).
Plain output is the `--region` text (`hgca complete --region "$(hgca region scan.las)"`); `--json` adds
the ground height and where the centre came from (docs/CONTRACTS.md, "Region CLI").
"""
from __future__ import annotations

import argparse
import json
import math

from hgca_core.commands.arguments import add_format_argument, add_json_argument, add_poses_argument
from hgca_core.errors import InputError


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("scans", nargs="+", help="scan files (any format `hgca read` accepts)")
    add_poses_argument(p)
    add_format_argument(p)
    p.add_argument("--size", metavar="SX,SY,SZ", default=None,
                   help="box size in metres (default 38.4,38.4,8: the paper's region)")
    add_json_argument(p, "print one JSON object instead of the --region text")


def parse_size(text: str | None) -> tuple[float, float, float]:
    from hgca_core.geometry.region import DEFAULT_SIZE

    if text is None:
        return DEFAULT_SIZE
    try:
        vals = tuple(float(v) for v in text.split(","))
    except ValueError as exc:
        raise InputError(f"--size must be three numbers 'sx,sy,sz', got {text!r}") from exc
    if len(vals) != 3 or not all(math.isfinite(v) and v > 0 for v in vals):
        raise InputError(f"--size must be three positive numbers 'sx,sy,sz', got {text!r}")
    return vals  # type: ignore[return-value]


def run(args: argparse.Namespace) -> int:
    from hgca_core.geometry.region import default_region, ground_height
    from hgca_core.io import read_scans

    from hgca_core.io.memory import check_read_memory

    size = parse_size(args.size)
    check_read_memory(args.scans)
    scan = read_scans(args.scans, poses=args.poses, fmt=args.fmt)
    region = default_region(scan.points, scan.origins, size=size)
    values = [float(v) for v in region.as_tuple()]
    text = ",".join(repr(v) for v in values)
    if not args.json:
        print(text)
        return 0
    has_sensor = scan.origins is not None and len(scan.origins) > 0
    print(json.dumps({
        "region": values,                      # cx, cy, cz, sx, sy, sz, yaw_deg: the --region numbers
        "region_arg": text,                    # the same as `--region` text
        "center": values[:3], "size": values[3:6], "yaw_deg": values[6],
        "ground_z": ground_height(region),
        "centred_on": "sensor" if has_sensor else "median",
        "points": int(len(scan.points)),
    }))
    return 0
