"""Raw float32 sweeps in the sensor frame: KITTI `.bin` (x, y, z, intensity) and nuScenes `.pcd.bin`
(x, y, z, intensity, ring). Both have the sensor at the frame origin, so origins = [(0, 0, 0)]."""
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


def read_nuscenes(path: str) -> Scan:
    """nuScenes LIDAR_TOP sweep: 20 bytes per point; the ring index is stored as float and kept as uint16."""
    rows = _read_float_rows(path, 5, "nuScenes .pcd.bin")
    ring = rows[:, 4]
    integral = np.isfinite(ring).all() and (ring == np.round(ring)).all() and (ring >= 0).all() and (ring < 65536).all()
    attributes = {"intensity": rows[:, 3].copy(), "ring": ring.astype(np.uint16) if integral else ring.copy()}
    return Scan(rows[:, :3].astype(np.float64), attributes, np.zeros((1, 3)), path)
