"""A small synthetic drive made with numpy (no simulator): a straight street rising along x, walls on both
sides with gaps, a few boxes; scans every few metres of the surface around each sensor position, stored in
the sensor frame with a poses JSON, so `hgca drive` reads them the way it reads a real drive."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np


def street_surface(length: float, slope: float, rng: np.random.Generator, density: float = 40.0) -> np.ndarray:
    """Points on the ground (z = slope * x), two walls (y = +-6 m, 3 m high, with gaps) and boxes."""
    x0, x1 = -15.0, length + 15.0
    area = (x1 - x0) * 24.0
    g = np.c_[rng.uniform(x0, x1, int(area * density)), rng.uniform(-12, 12, int(area * density))]
    ground = np.c_[g, slope * g[:, 0]]
    walls = []
    for side in (-6.0, 6.0):
        n = int((x1 - x0) * 3.0 * density)
        x = rng.uniform(x0, x1, n)
        x = x[(x % 17.0) > 3.0]                       # a gap every 17 m
        z = rng.uniform(0, 3.0, len(x))
        walls.append(np.c_[x, np.full(len(x), side), slope * x + z])
    boxes = []
    for bx in np.arange(5.0, length, 11.0):
        n = int(6.0 * density)
        p = rng.uniform([0, 0, 0], [2.0, 1.5, 1.5], (n, 3)) + [bx, 2.5 if int(bx) % 2 else -4.0, slope * bx]
        boxes.append(p)
    return np.concatenate([ground, *walls, *boxes])


def save_scans(folder: Path, scans_world: list[np.ndarray], poses: list[np.ndarray],
               name: str = "scan_{:03d}.npz") -> tuple[list[Path], Path]:
    """Each scan (world points, float64) in its sensor frame as `name`.format(i) (scan_<i>.npz), and poses.json
    (sensor->world), its entries in scan order."""
    folder.mkdir(parents=True, exist_ok=True)
    paths, entries = [], []
    for i, (pts, pose) in enumerate(zip(scans_world, poses)):
        pose = np.asarray(pose, dtype=np.float64)
        path = folder / name.format(i)
        np.savez(path, points=(np.asarray(pts, dtype=np.float64) - pose[:3, 3]) @ pose[:3, :3])
        paths.append(path)
        entries.append({"file": path.name, "pose": pose.tolist()})
    poses_path = folder / "poses.json"
    poses_path.write_text(json.dumps({"scans": entries}))
    return paths, poses_path


def write_drive(folder: Path, length: float = 40.0, spacing: float = 4.0, slope: float = 0.0, seed: int = 0,
                offset=(0.0, 0.0, 0.0), radius: float = 14.0, weave: float = 0.3,
                name: str = "scan_{:03d}.npz") -> tuple[list[Path], Path]:
    """Scans (npz, sensor frame) every `spacing` m along x from 0 to `length`, sensor 2 m above the ground, and
    the poses JSON; the path weaves `weave` m sideways; the whole drive is shifted by `offset` (float64, e.g.
    UTM-sized)."""
    rng = np.random.default_rng(seed)
    surface = street_surface(length, slope, rng)
    off = np.asarray(offset, dtype=np.float64)
    scans, poses = [], []
    for x in np.arange(0.0, length + 1e-9, spacing):
        pos = np.array([x, weave * np.sin(x / 9.0), slope * x + 2.0])
        near = surface[np.linalg.norm(surface[:, :2] - pos[:2], axis=1) < radius]
        scans.append(near + rng.normal(0, 0.005, near.shape) + off)
        pose = np.eye(4)
        pose[:3, 3] = pos + off
        poses.append(pose)
    return save_scans(folder, scans, poses, name)


# A KITTI-like velodyne -> camera 0 transform (x forward, y left, z up -> x right, y down, z forward, an offset)
KITTI_TR = np.array([[0.0, -1.0, 0.0, -0.004], [0.0, 0.0, -1.0, -0.076], [1.0, 0.0, 0.0, -0.27], [0, 0, 0, 1.0]])


def write_kitti(folder: Path, length: float = 24.0, spacing: float = 4.0, seed: int = 0,
                radius: float = 14.0) -> list[np.ndarray]:
    """The street of `write_drive` as a KITTI odometry sequence folder (velodyne/NNNNNN.bin float32 x, y, z, i in
    the sensor frame; poses.txt: camera-0 poses P_i = Tr V_i Tr^-1; calib.txt `Tr:`); returns the velodyne->world
    poses V_i the reader must recover."""
    rng = np.random.default_rng(seed)
    surface = street_surface(length, 0.0, rng)
    (folder / "velodyne").mkdir(parents=True)
    poses, lines = [], []
    for i, x in enumerate(np.arange(0.0, length + 1e-9, spacing)):
        v = np.eye(4)
        yaw = 0.02 * i
        v[:2, :2] = [[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]]
        v[:3, 3] = [x, 0.3 * np.sin(x / 9.0), 2.0]
        near = surface[np.linalg.norm(surface[:, :2] - v[:2, 3], axis=1) < radius]
        local = (near - v[:3, 3]) @ v[:3, :3]
        np.c_[local, rng.random(len(local))].astype("<f4").tofile(folder / "velodyne" / f"{i:06d}.bin")
        p = KITTI_TR @ v @ np.linalg.inv(KITTI_TR)
        lines.append(" ".join(f"{c:.12e}" for c in p[:3].reshape(-1)))
        poses.append(v)
    (folder / "poses.txt").write_text("\n".join(lines) + "\n")
    (folder / "calib.txt").write_text("Tr: " + " ".join(f"{c:.12e}" for c in KITTI_TR[:3].reshape(-1)) + "\n")
    return poses
