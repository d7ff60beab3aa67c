"""The real sweeps of tests/data/real as plain arrays, for the sensor-profile tests and
benchmarks/sensor_profiles.py: nuScenes (HDL-32E, sensor frame) and Argoverse 2 (two VLP-32C, ego frame).

Missing files skip a test, except under CI, where they fail it (`hgca_testdata.require_real`).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hgca_testdata import REAL_FIXTURES as REAL


@dataclass
class Sweep:
    """Points (N, 3) float64 in the sensor's or vehicle's frame, the beam of each point, the sensor origin."""

    name: str
    points: np.ndarray
    ring: np.ndarray
    origin: np.ndarray


def need(path: Path) -> Path:
    from hgca_testdata import require_real

    return require_real(path)


def nuscenes_sweep(min_range: float = 2.5) -> Sweep:
    """The nuScenes LIDAR_TOP sweep: 5 float32 per point (x, y, z, intensity, ring). The file keeps a slot
    for every firing (1084 per ring); slots without a return hold points within ~1 m of the sensor, and
    the car's own roof lies within 2.5 m, so returns are the points beyond `min_range`."""
    files = sorted(REAL.glob("nuscenes_lidar_top_*.pcd.bin"))
    path = need(files[0] if files else REAL / "nuscenes_lidar_top_*.pcd.bin")
    a = np.fromfile(path, dtype=np.float32).reshape(-1, 5).astype(np.float64)
    keep = np.linalg.norm(a[:, :3], axis=1) > min_range
    return Sweep("nuScenes HDL-32E", a[keep, :3], a[keep, 4].astype(np.int64), np.zeros(3))


def av2_sweeps() -> list[Sweep]:
    """The three AV2 sweeps (ego frame; origin: the upper VLP-32C at (1.350, 0, 1.640) m)."""
    pytest_feather = __import__("pytest").importorskip("pyarrow.feather")
    files = sorted(need(REAL / "av2").glob("*/sensors/lidar/*.feather"))
    if not files:
        need(REAL / "av2" / "no sweeps")
    out = []
    for f in files:
        t = pytest_feather.read_table(f).to_pydict()
        pts = np.c_[t["x"], t["y"], t["z"]].astype(np.float64)
        out.append(Sweep(f"AV2 {f.parts[-4][:8]}/{f.stem}", pts, np.asarray(t["laser_number"], dtype=np.int64),
                         np.array([1.35018, 0.0, 1.64042])))
    return out


def elevations(points: np.ndarray, origin: np.ndarray, rotation: np.ndarray | None = None) -> np.ndarray:
    """Elevation (degrees) of each point seen from `origin`, in the frame turned by `rotation` (sensor->frame)."""
    rel = points - origin
    if rotation is not None:
        rel = rel @ rotation
    return np.degrees(np.arcsin(rel[:, 2] / np.linalg.norm(rel, axis=1)))
