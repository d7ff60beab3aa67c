"""Builders shared by the tests and the benchmarks: the tiny synthetic sample, LAS files, a folder's state, the real
sweeps of tests/data/real as arrays, a simulated drive of raw sweeps.

Why here: the rule runs one way, tests never import benchmarks/ (tests/test_layering.py), so what both need lives
with the tests, as PyTorch3D keeps its shared builders and naive references in tests/. Benchmarks reach it through
benchmarks/common.py, which puts this folder on their path. It is not product code (nothing in hgca_core needs
it), so it stays out of the package; it imports neither pytest nor another module of tests/, so a benchmark run
outside pytest can import it (tests/hgca_testdata.py adds what is pytest's: skip or fail on a missing fixture)."""
from __future__ import annotations

import os
import stat
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

# The real LiDAR files live in the repository (tests/data/real, with their licences), so a clone runs everything.
REAL_FIXTURES = Path(__file__).resolve().parent / "data" / "real"
# Realistic georeferenced places: a UTM easting/northing in the northern hemisphere, and a northing near
# 1e7 m (southern hemisphere false northing) where float32 has a 1 m spacing.
UTM_OFFSETS = {"utm": (500_000.0, 5_000_000.0, 100.0), "utm_1e7": (500_000.0, 9_999_000.0, 100.0)}


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


def geokeys(*pairs: tuple[int, int]):
    """A LAS GeoKeyDirectory record holding `(key id, value)` pairs (e.g. (3072, 32633): projected CRS EPSG:32633),
    as GIS software writes them."""
    from laspy.vlrs.known import GeoKeyDirectoryVlr, GeoKeyEntryStruct

    vlr = GeoKeyDirectoryVlr()
    vlr.geo_keys_header.key_directory_version, vlr.geo_keys_header.key_revision = 1, 1
    vlr.geo_keys_header.number_of_keys = len(pairs)
    vlr.geo_keys = []
    for key_id, value in pairs:
        entry = GeoKeyEntryStruct()
        entry.id, entry.tiff_tag_location, entry.count, entry.value_offset = key_id, 0, 1, value
        vlr.geo_keys.append(entry)
    return vlr


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


def simulate_drive(seed: int = 3, frames: int = 10, speed: float = 10.0, rate_hz: float = 10.0,
                   weave: float = 1.5, period: float = 24.0, azimuth: int = 900, noise: float = 0.01):
    """Raw sweeps of a synthetic street (`hgca_core.synth.scene`) by an HDL-64E-like sensor 1.73 m above the road,
    driving `speed` m/s along the street's lane with a sideways weave (`weave` m, `period` m: headings swing by
    about atan(2 pi weave / period), 21 deg by default). Each sweep is one revolution during which the sensor
    moves on (rolling shutter), its points in the sensor frame at their firing time with a per-point `time`
    (s from the sweep's start), `noise` m of range noise. Returns (scans, true sensor->world poses at each sweep's
    start, frame times (s), names)."""
    from hgca_core.geometry.raycast import Sensor, column_poses, make_intersector
    from hgca_core.io.scan import Scan
    from hgca_core.synth.dataset import Drive
    from hgca_core.synth.lidar import HDL64E
    from hgca_core.synth.scene import make_scene

    scene = make_scene(seed)
    base = Drive(scene.drive, scene.drive_up)
    s0 = base.length / 2 - speed * frames / rate_hz / 2
    s = base.s
    heading = np.gradient(base.points[:, :2], s, axis=0)
    left = np.c_[-heading[:, 1], heading[:, 0]] / np.linalg.norm(heading, axis=1, keepdims=True)
    shift = weave * np.sin(2 * np.pi * (s - s0) / period)
    drive = Drive(np.c_[base.points[:, :2] + shift[:, None] * left, base.points[:, 2]], base.up)
    sensor = Sensor(HDL64E.elevations_deg, azimuth, 100.0, 2.5)
    mount = np.eye(4)
    mount[2, 3] = 1.73
    inter = make_intersector(scene.mesh)
    rng = np.random.default_rng(seed)
    scans, poses, times, names = [], [], [], []
    dirs = sensor.directions()                                             # (E, A, 3) sensor frame
    column_time = np.arange(azimuth) / azimuth / rate_hz
    for k in range(frames):
        a0 = s0 + speed * k / rate_hz
        p0, p1 = drive.pose(a0) @ mount, drive.pose(a0 + speed / rate_hz) @ mount
        rots, origins = column_poses(p0, p1, azimuth)
        d_world = np.einsum("aij,eaj->eai", rots, dirs)
        o = np.broadcast_to(origins[None], d_world.shape)
        dist, _ = inter.first_hits(np.ascontiguousarray(o.reshape(-1, 3)), np.ascontiguousarray(d_world.reshape(-1, 3)))
        dist = dist.reshape(d_world.shape[:2]) + rng.normal(0.0, noise, d_world.shape[:2])
        e, a = np.nonzero(np.isfinite(dist) & (dist >= sensor.min_range) & (dist <= sensor.max_range))
        local = dirs[e, a] * dist[e, a][:, None]
        scans.append(Scan(local, {"time": column_time[a], "ring": e.astype(np.int16)}, origins=np.zeros((1, 3))))
        poses.append(p0)
        times.append(k / rate_hz)
        names.append(f"sweep_{k:03d}.npz")
    return scans, poses, times, names
