"""What a drive is made of: its scans, one by one, each with its points, sensor origins and every point's origin.

`hgca drive` takes scan files (with --poses), one sequence folder (KITTI, Argoverse 2, nuScenes, with --frames:
all frames by default), or accumulated `.npz` files (`hgca read`'s output, or what the Blender add-on writes
for an imported sequence) whose `scan_index` attribute says which points came from which scan. Whatever the
input, a drive sees a list of `DriveScan`s in trajectory order: the tile planner needs each scan's sensor
position, and a tile's observed free space needs every point's ray (origin -> hit), so the origins travel with
the points into the tiles. The order of the files does not matter: `order` finds the drive's (a poses file's
order, else time stamps, else the chain of sensor positions) and reports a jump between consecutive scans.
"""
from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np

from hgca_core.errors import InputError

Report = Callable[[str, int, int, str, int], None]


@dataclass(frozen=True)
class DriveScan:
    """One scan: float64 world points (N, 3), its sensor origins (S, 3) float64 world, and each point's row in
    them (N,) int32. `name` says where it came from (a file, `file#k` for scan k of an accumulated file)."""

    name: str
    points: np.ndarray
    origins: np.ndarray
    origin_index: np.ndarray
    time: float | None = None          # when it was taken (`order.scan_time`), where the file says so

    @property
    def position(self) -> np.ndarray:
        """Where the sensor was (the mean of its origins: the two lidars of an AV2 sweep give the car)."""
        return self.origins.mean(axis=0)

    def digest(self) -> str:
        """sha256 of what a tile sees of this scan: points, origins and rays, whatever the file format."""
        h = hashlib.sha256()
        for a, dtype in ((self.points, np.float64), (self.origins, np.float64), (self.origin_index, np.int32)):
            h.update(np.ascontiguousarray(a, dtype=dtype).tobytes())
        return h.hexdigest()


def split_scans(scan, name: str) -> list[DriveScan]:
    """A read `Scan` -> its scans: one, or one per `scan_index` value (in that order) for an accumulated file.
    Each point keeps its origin (`origin_index`, else its scan's, else the only or the nearest one:
    `geometry.freespace.ray_origins`); each scan gets the origins its points use."""
    from hgca_core.geometry.freespace import ray_origins
    from hgca_core.tiling.order import scan_time

    if scan.origins is None or not len(scan.origins):
        raise InputError("a drive needs each scan's sensor position: this scan has no origin; give --poses "
                         "(sensor->world per scan)", name)
    origins = np.asarray(scan.origins, dtype=np.float64).reshape(-1, 3)
    index = ray_origins(origins, scan.attributes, scan.points)
    labels = scan.attributes.get("scan_index")
    values = np.unique(labels) if labels is not None else np.zeros(0)
    if len(values) <= 1:
        groups = [(name, np.ones(len(scan.points), dtype=bool))]
    else:
        groups = [(f"{name}#{int(v)}", labels == v) for v in values]
    out = []
    for label, mask in groups:
        own = index[mask]
        used = np.unique(own)
        out.append(DriveScan(label, np.ascontiguousarray(scan.points[mask], dtype=np.float64), origins[used],
                             np.searchsorted(used, own).astype(np.int32),
                             scan_time({k: v[mask] for k, v in scan.attributes.items()})))
    return out


def read_drive_inputs(inputs: Sequence[str | os.PathLike], poses: str | os.PathLike | None = None,
                      fmt: str | None = None, frames: str | None = None,
                      report: Report | None = None, topic: str | None = None) -> list[DriveScan]:
    """The drive's scans in trajectory order, read one file at a time (the same readers, pose matching and
    checks as `hgca complete`): a sequence folder's frames (`frames` START:STOP[:STEP], all by default, in time
    order), or the scan files, an accumulated file split by its `scan_index`, put in the drive's order
    (`order`: the poses file's, else time stamps, else the chain of sensor positions). A jump between
    consecutive scans is reported as a warning."""
    from hgca_core.io import read_scan, read_scans
    from hgca_core.io.sequence import is_sequence, open_sequence, select
    from hgca_core.tiling.order import order_scans, poses_order, warn_jumps

    say = report or (lambda *a: None)
    paths = [os.fspath(p) for p in inputs]
    if not paths:
        raise InputError("no scan files given")
    out: list[DriveScan] = []
    if is_sequence(paths):
        if fmt is not None:
            raise InputError("--format applies to scan files, not to a sequence folder", paths[0])
        seq = open_sequence(paths[0], poses, topic)
        files, mats = select(seq, frames if frames is not None else ":")
        for i, f in enumerate(files):
            scan = seq.accumulate([f], [mats[i]] if mats is not None else None)
            out.extend(split_scans(scan, f))
            say("read", i + 1, len(files), os.path.basename(f), 0)
        warn_jumps([s.name for s in out], np.array([s.position for s in out]))
        return out
    if topic is not None:
        raise InputError("--topic applies to a ROS bag (.bag, .mcap, .db3 or a ROS 2 bag folder)", paths[0])
    from hgca_core.io.las_crs import check_inputs

    check_inputs(paths)     # one CRS in metres across all the drive's files (each is read on its own below)
    if frames is not None:
        raise InputError("--frames needs a sequence folder (KITTI, Argoverse 2 or nuScenes), not scan files")
    if poses is not None:
        paths = [paths[i] for i in poses_order(paths, poses)]
    for i, p in enumerate(paths):
        # without poses a file is read as it is, keeping its own `scan_index` (an accumulated .npz)
        scan = read_scan(p, fmt) if poses is None else read_scans([p], poses=poses, fmt=fmt)
        out.extend(split_scans(scan, p))
        say("read", i + 1, len(paths), os.path.basename(p), 0)
    if poses is None:
        order, _ = order_scans([s.name for s in out], np.array([s.position for s in out]), [s.time for s in out])
        out = [out[i] for i in order]
    warn_jumps([s.name for s in out], np.array([s.position for s in out]))
    return out
