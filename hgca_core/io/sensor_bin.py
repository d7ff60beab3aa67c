"""Raw float32 sweeps in the sensor frame: KITTI `.bin` (x, y, z, intensity) and nuScenes `.pcd.bin`
(x, y, z, intensity, ring). Both have the sensor at the frame origin, so origins = [(0, 0, 0)].

nuScenes keeps the returns off its own car in the sweeps (the devkit drops them only when it merges sweeps,
`remove_close`); Argoverse 2 ships sweeps without them and the simulator makes none (its ego body only blocks
beams). In the real sweep of `tests/data/real`, 8,526 of 34,688 returns (25 %) lie on the car: x -0.62 to
0.64, y -1.12 to 1.81, z -0.92 to 0 m in the LIDAR_TOP frame (y forward), and the nearest other return is 3.04 m
out. Left in, they are a 1.3 x 2.9 m slab 0.9-1.8 m above the road at the sensor that the model completes as an
object, so the reader drops the returns inside the car's footprint below the sensor (`NUSCENES_EGO_BOX`, the
Renault Zoe's 1.73 x 4.08 m with the roof LiDAR 0.99 m ahead of the rear axle, plus margins) and says how many
in `Scan.dropped`."""
from __future__ import annotations

import os

import numpy as np

from hgca_core.errors import InputError
from hgca_core.io.scan import Scan


def _read_float_rows(path: str, columns: int, what: str) -> np.ndarray:
    row = 4 * columns
    size = os.path.getsize(path)
    if size % row:
        raise InputError(f"{what} size {size} bytes is not a multiple of {row} "
                         f"({columns} float32 per point): truncated or not a {what} file", path)
    return np.fromfile(path, dtype="<f4").reshape(-1, columns)


def read_kitti(path: str) -> Scan:
    """KITTI velodyne sweep: 16 bytes per point."""
    rows = _read_float_rows(path, 4, "KITTI .bin")
    return Scan(rows[:, :3].astype(np.float64), {"intensity": rows[:, 3].copy()}, np.zeros((1, 3)), path)


# (min, max) of x, y, z in the LIDAR_TOP frame (x right, y forward, z up; metres): the car below the sensor
NUSCENES_EGO_BOX = ((-1.0, 1.0), (-1.8, 2.6), (-2.5, 0.2))
EGO_RETURNS = "returns off the recording vehicle"   # the key of Scan.dropped


def in_box(xyz: np.ndarray, box: tuple[tuple[float, float], ...]) -> np.ndarray:
    """(N,) bool: rows of `xyz` inside the axis-aligned box ((x0, x1), (y0, y1), (z0, z1))."""
    inside = np.ones(len(xyz), dtype=bool)
    for axis, (lo, hi) in enumerate(box):
        inside &= (xyz[:, axis] >= lo) & (xyz[:, axis] <= hi)
    return inside


def read_nuscenes(path: str) -> Scan:
    """nuScenes LIDAR_TOP sweep: 20 bytes per point; the ring index is stored as float and kept as uint16. The
    returns off the own car (`NUSCENES_EGO_BOX`) are dropped and counted in `Scan.dropped` (module docstring)."""
    rows = _read_float_rows(path, 5, "nuScenes .pcd.bin")
    ego = in_box(rows[:, :3], NUSCENES_EGO_BOX)
    if ego.all():                       # a file of nothing but such rows is left as it is, to fail on its own
        ego[:] = False
    if ego.any():
        rows = rows[~ego]
    ring = rows[:, 4]
    integral = np.isfinite(ring).all() and (ring == np.round(ring)).all() and (ring >= 0).all() and (ring < 65536).all()
    attributes = {"intensity": rows[:, 3].copy(), "ring": ring.astype(np.uint16) if integral else ring.copy()}
    dropped = {EGO_RETURNS: int(ego.sum())} if ego.any() else {}
    return Scan(rows[:, :3].astype(np.float64), attributes, np.zeros((1, 3)), path, dropped)
