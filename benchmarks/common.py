"""What the benchmark scripts share, and the builders their tests use too: writing a results page (JSON, Markdown,
PNG), the tiny synthetic sample, LAS files, the real sweeps of tests/data/real as arrays, and a folder's state.

Scripts import it as `common` (they run as `python benchmarks/<name>.py`, whose folder Python puts first on the
path); tests reach it through tests/hgca_testdata.py, which adds this folder to theirs. Only data files are read
from tests/data; nothing here imports pytest or a module of tests/, so one copy serves both."""
from __future__ import annotations

import json
import os
import stat
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np

REPO = Path(__file__).resolve().parents[1]
# The real LiDAR files live in the repository (tests/data/real, with their licences), so a clone runs everything.
REAL_FIXTURES = REPO / "tests" / "data" / "real"
# Realistic georeferenced places: a UTM easting/northing in the northern hemisphere, and a northing near
# 1e7 m (southern hemisphere false northing) where float32 has a 1 m spacing.
UTM_OFFSETS = {"utm": (500_000.0, 5_000_000.0, 100.0), "utm_1e7": (500_000.0, 9_999_000.0, 100.0)}


def write_page(folder: Path, name: str, result: dict[str, Any], page: Callable[[dict[str, Any]], str],
               plot: Callable[[dict[str, Any], Path], None] | None = None) -> str:
    """Write `name`.json, `name`.md (and `name`.png when `plot` is given) into `folder`; returns the Markdown."""
    folder.mkdir(parents=True, exist_ok=True)
    (folder / f"{name}.json").write_text(json.dumps(result, indent=1))
    text = page(result)
    (folder / f"{name}.md").write_text(text)
    if plot is not None:
        plot(result, folder / f"{name}.png")
    return text


def tiny_sample(seed: int, size: float = 6.0) -> dict[str, np.ndarray]:
    """A ground plane, a wall and a box in a size x size x 4 m region (the CONTRACTS.md sample format, made without
    the simulator so model tests stay fast); the input sees the lower part only."""
    rng = np.random.default_rng(seed)
    n = 6000
    ground = np.c_[rng.uniform(0, size, (n, 2)), np.full(n, 1.0)]
    wall_x = rng.uniform(1.0, size - 1.0)
    wall = np.c_[np.full(n, wall_x), rng.uniform(0, size, n), rng.uniform(1.0, 3.8, n)]
    bx = rng.uniform(1.0, size - 2.0, 2)
    box = np.c_[rng.uniform(bx[0], bx[0] + 1.0, n // 2), rng.uniform(bx[1], bx[1] + 1.0, n // 2),
                rng.uniform(1.0, 2.0, n // 2)]
    surface = np.concatenate([ground, wall, box])
    from hgca_core.geometry.voxel import downsample, voxelize

    occ10 = voxelize(surface, 0.1, (size, size, 4.0))
    occ20 = downsample(occ10)
    visible = surface[(surface[:, 2] < 3.0)]
    inp = visible[rng.random(len(visible)) < 0.05] + rng.normal(0, 0.01, (1, 3))
    inp = inp[inp[:, 2] < 2.2]
    return {
        "region": np.array([size / 2, size / 2, 1.0, size, size, 4.0, 0.0]),
        "input_points": inp.astype(np.float32),
        "input_scan_index": np.zeros(len(inp), np.uint8),
        "input_origins": np.array([[size / 2, size / 2, 3.0]], np.float32),
        "gt_occ20": occ20.astype(np.int16),
        "gt_occ10": occ10.astype(np.int16),
        "gt_surface": surface.astype(np.float32),
        "visible20": occ20.astype(np.int16),
    }


def with_distance_pairs(sample: dict[str, np.ndarray], size: float = 6.0) -> dict[str, np.ndarray]:
    """`sample` (a tiny_sample) with the distance pairs the autoencoder and the fine stage train on: every fifth
    surface point moved by 5 cm noise, kept inside the region, and its distance to the surface."""
    from scipy.spatial import cKDTree

    surface = sample["gt_surface"]
    rng = np.random.default_rng(0)
    q = surface[::5] + rng.normal(0, 0.05, (len(surface[::5]), 3)).astype(np.float32)
    q = q[np.all((q >= 0) & (q < [size, size, 4.0]), axis=1)]
    return {**sample, "udf_points": q.astype(np.float32),
            "udf_dist": cKDTree(surface).query(q)[0].astype(np.float32)}


def write_las(path, points: np.ndarray, scale: float = 0.001, offset=None) -> np.ndarray:
    """A LAS 1.2 file (point format 3, mm scale) of `points`; returns the float64 coordinates the file holds
    (`X * scale + offset`, as laspy reads them)."""
    import laspy

    pts = np.asarray(points, dtype=np.float64)
    header = laspy.LasHeader(point_format=3, version="1.2")
    header.scales = np.array([scale] * 3)
    header.offsets = np.floor(pts.min(axis=0)) if offset is None else np.asarray(offset, dtype=np.float64)
    las = laspy.LasData(header)
    las.x, las.y, las.z = pts[:, 0], pts[:, 1], pts[:, 2]
    las.intensity = np.arange(len(pts), dtype=np.uint16)
    las.write(str(path))
    back = laspy.read(str(path))
    return np.column_stack([np.asarray(back.x), np.asarray(back.y), np.asarray(back.z)])


def folder_state(root: Path) -> dict[str, object]:
    """Every entry under `root`: file bytes, link targets, the kind of anything else (fifos are not opened), so a
    before/after comparison shows any input changed and any output written."""
    state: dict[str, object] = {}
    for dirpath, dirnames, filenames in os.walk(root):
        for name in dirnames + filenames:
            path = Path(dirpath) / name
            mode = os.lstat(path).st_mode
            if stat.S_ISLNK(mode):
                state[str(path)] = ("link", os.readlink(path))
            elif stat.S_ISREG(mode):
                state[str(path)] = path.read_bytes()
            else:
                state[str(path)] = stat.S_IFMT(mode)
    return state


@dataclass
class Sweep:
    """A real sweep: points (N, 3) float64 in the sensor's or vehicle's frame, the beam of each point, the origin."""

    name: str
    points: np.ndarray
    ring: np.ndarray
    origin: np.ndarray


def present(path: Path) -> Path:
    """`path` when it exists, else a FileNotFoundError naming it (tests pass hgca_testdata.require_real instead)."""
    if not Path(path).exists():
        raise FileNotFoundError(f"real LiDAR fixture missing: {path} (expected in tests/data/real)")
    return Path(path)


def nuscenes_sweep(min_range: float = 2.5, need: Callable[[Path], Path] = present) -> Sweep:
    """The nuScenes LIDAR_TOP sweep: 5 float32 per point (x, y, z, intensity, ring). The file keeps a slot
    for every firing (1084 per ring); slots without a return hold points within ~1 m of the sensor, and
    the car's own roof lies within 2.5 m, so returns are the points beyond `min_range`."""
    files = sorted(REAL_FIXTURES.glob("nuscenes_lidar_top_*.pcd.bin"))
    path = need(files[0] if files else REAL_FIXTURES / "nuscenes_lidar_top_*.pcd.bin")
    a = np.fromfile(path, dtype=np.float32).reshape(-1, 5).astype(np.float64)
    keep = np.linalg.norm(a[:, :3], axis=1) > min_range
    return Sweep("nuScenes HDL-32E", a[keep, :3], a[keep, 4].astype(np.int64), np.zeros(3))


def av2_sweeps(need: Callable[[Path], Path] = present) -> list[Sweep]:
    """The three AV2 sweeps (ego frame; origin: the upper VLP-32C at (1.350, 0, 1.640) m); needs pyarrow."""
    from pyarrow import feather

    files = sorted(need(REAL_FIXTURES / "av2").glob("*/sensors/lidar/*.feather"))
    if not files:
        need(REAL_FIXTURES / "av2" / "no sweeps")
    out = []
    for f in files:
        t = feather.read_table(f).to_pydict()
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
