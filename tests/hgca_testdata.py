"""Tiny synthetic samples in the CONTRACTS.md format, made without the simulator so model and trainer
tests stay fast and independent of the scene generator, and the one way to reach the real LiDAR fixtures
(importable from any test as `hgca_testdata`)."""
from __future__ import annotations

import contextlib
import os
from pathlib import Path

import numpy as np
import pytest

# The real LiDAR files live in the repository (tests/data/real, with their licences), so a clone runs every test.
REAL_FIXTURES = Path(__file__).resolve().parent / "data" / "real"


def in_ci() -> bool:
    """True when the environment variable CI is set (to anything but '', 0, false or no)."""
    return os.environ.get("CI", "").strip().lower() not in ("", "0", "false", "no")


def require_real(path: Path | None = None) -> Path:
    """A real LiDAR fixture (default: the folder tests/data/real). When it is missing the test is skipped on a
    developer's machine (e.g. a checkout that left the data out), but FAILS under CI: a clone holds the folder,
    so a missing fixture there means the real-file tests silently stopped running."""
    p = REAL_FIXTURES if path is None else Path(path)
    if not p.exists():
        msg = f"real LiDAR fixture missing: {p} (expected in tests/data/real)"
        if in_ci():
            pytest.fail(f"{msg}; CI is set, so this is a failure, not a skip", pytrace=False)
        pytest.skip(msg)
    return p


def tiny_sample(seed: int, size: float = 6.0) -> dict[str, np.ndarray]:
    """A ground plane, a wall and a box in a size x size x 4 m region; the input sees the lower part only."""
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


# Realistic georeferenced places: a UTM easting/northing in the northern hemisphere, and a northing near
# 1e7 m (southern hemisphere false northing) where float32 has a 1 m spacing.
UTM_OFFSETS = {"utm": (500_000.0, 5_000_000.0, 100.0), "utm_1e7": (500_000.0, 9_999_000.0, 100.0)}


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


@contextlib.contextmanager
def small_tmpfs(root: Path, size: str):
    """`root` made a tmpfs of `size` (e.g. "64k": a real ENOSPC once full) for the block; a skip where mounting is
    not allowed (not root, no mount)."""
    import shutil
    import subprocess

    root.mkdir()
    if shutil.which("mount") is None or os.geteuid() != 0:
        pytest.skip("mounting a tmpfs needs root")
    res = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(root)], capture_output=True)
    if res.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs: {res.stderr.decode()[:200]}")
    try:
        yield root
    finally:
        subprocess.run(["umount", str(root)], capture_output=True)


def tiny_scan_file(folder: Path) -> Path:
    """tiny_sample(3)'s input as a user's scan file: world points 100 / 200 / -1 m from its region frame, with its
    sensor origin (the region "103,203,1,6,6,4" holds it)."""
    s = tiny_sample(3)
    path = folder / "scan.npz"
    world = s["input_points"].astype(np.float64) + np.array([100.0, 200.0, -1.0])
    np.savez(path, points=world, origins=np.array([[103.0, 203.0, 2.0]]))
    return path
