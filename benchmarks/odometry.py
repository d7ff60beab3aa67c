"""Poses from the scans (`hgca poses --estimate`, KISS-ICP odometry) against true poses, and what they do to a
completion.

Measured: the drift of the estimated poses (translation error per metre travelled, rotation error in degrees per
metre) on the Argoverse 2 log of tests/data/real (2 sweeps, true poses from its city_SE3_egovehicle table) and on
a simulated drive (a synthetic street scanned by a spinning 64-beam sensor that moves and turns during each sweep:
raw, motion-distorted sweeps with per-point times, as a real sensor gives them); and the "done means": the AV2
sweeps with their poses removed, `hgca poses --estimate`, `hgca complete --stage coarse`, against the completion
from the true poses (same seed and region): the chamfer distance between the two meshes' surfaces, beside the
chamfer between two seeds of the true-pose completion (the seed band). Writes benchmarks/results/odometry.{json,md,png}.

    .venv/bin/python benchmarks/odometry.py

`simulate_drive` is also the tests' simulated drive (tests/io/test_odometry.py).
"""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
AV2_LOG = REPO / "tests" / "data" / "real" / "av2" / "7fab2350-7eaf-3b7e-a39d-6937a4c1bede"


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
