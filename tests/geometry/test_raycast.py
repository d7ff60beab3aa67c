"""The ray caster: analytic ranges on planes, rolling shutter, reuse of the BVH; metrics need no simulator."""
from __future__ import annotations

import subprocess
import sys

import numpy as np
import trimesh

from hgca_core.geometry.raycast import EVAL128, WAYMO64, Sensor, cast, make_intersector, range_image


def _pose(x=0.0, y=0.0, z=2.0, yaw=0.0) -> np.ndarray:
    m = np.eye(4)
    m[:2, :2] = [[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]]
    m[:3, 3] = [x, y, z]
    return m


def _ground(half: float = 200.0) -> trimesh.Trimesh:
    v = np.array([[-half, -half, 0], [half, -half, 0], [half, half, 0], [-half, half, 0]], dtype=float)
    return trimesh.Trimesh(v, [[0, 1, 2], [0, 2, 3]], process=False)


def test_sensors_match_the_paper():
    assert WAYMO64.directions().shape == (64, 2650, 3)
    assert np.isclose(WAYMO64.elevations_deg.max(), 2.4) and np.isclose(WAYMO64.elevations_deg.min(), -17.6)
    assert EVAL128.directions().shape == (128, 2650, 3)
    assert np.isclose(EVAL128.elevations_deg.max(), 30.0) and WAYMO64.max_range == 75.0
    assert np.allclose(np.linalg.norm(EVAL128.directions(), axis=-1), 1.0)


def test_ground_plane_ranges_are_analytic():
    sensor = Sensor(np.array([-20.0, -10.0, -5.0, 5.0]), 360, 75.0)
    depth, _, _ = range_image(_ground(), _pose(3.0, -4.0, 2.0, 0.7), sensor)
    for row, el in enumerate(sensor.elevations_deg):
        expect = 2.0 / np.sin(np.radians(-el)) if el < 0 else np.inf
        if expect > 75.0:
            expect = np.inf
        assert np.allclose(depth[row], expect, rtol=1e-9, atol=1e-9), el
    pts = cast(_ground(), _pose(3.0, -4.0, 2.0, 0.7), sensor)
    assert len(pts) == 3 * 360 and np.allclose(pts[:, 2], 0.0, atol=1e-9)


def test_wall_range_and_direction():
    """A wall x = 10 in front of a sensor at the origin: range 10 / (cos(el) cos(az)) for beams that face it."""
    wall = trimesh.creation.box(extents=[0.2, 200, 200])
    wall.apply_translation([10.1, 0, 0])                     # front face at x = 10
    sensor = Sensor(np.array([0.0, 10.0]), 36, 75.0)
    depth, o, d = range_image(wall, _pose(0, 0, 0), sensor)
    az = np.radians(np.arange(36) * 10.0)
    for row, el in enumerate(np.radians(sensor.elevations_deg)):
        facing = np.cos(az) > 0.2
        assert np.allclose(depth[row, facing], 10.0 / (np.cos(el) * np.cos(az[facing])), rtol=1e-9)
        assert np.all(np.isinf(depth[row, np.cos(az) < 0]))
    hits = o[np.isfinite(depth)] + depth[np.isfinite(depth)][:, None] * d[np.isfinite(depth)]
    assert np.allclose(hits[:, 0], 10.0)


def test_range_window_drops_near_and_far_returns():
    sensor = Sensor(np.array([-1.0, -30.0, -80.0]), 8, 75.0, min_range=2.5)
    depth, _, _ = range_image(_ground(), _pose(z=2.0), sensor)
    assert np.all(np.isinf(depth[0]))                        # 2 / sin(1 deg) = 115 m: beyond max range
    assert np.allclose(depth[1], 4.0)                          # 2 / sin(30 deg)
    assert np.all(np.isinf(depth[2]))                          # 2.03 m: inside min range


def test_rolling_shutter_moves_the_origin_over_the_revolution():
    sensor = Sensor(np.array([-10.0]), 100, 75.0)
    depth, o, _ = range_image(_ground(), _pose(0, 0, 2), sensor, pose_end=_pose(1.0, 0, 2))
    assert np.allclose(o[0, 0], [0, 0, 2]) and np.allclose(o[0, -1], [0.99, 0, 2])
    assert np.allclose(depth, 2.0 / np.sin(np.radians(10.0)))


def test_intersector_is_reusable_and_equivalent():
    mesh = trimesh.creation.icosphere(3, radius=3.0)
    mesh.apply_translation([8.0, 2.0, 2.0])
    inter = make_intersector(mesh)
    assert make_intersector(inter) is inter
    sensor = Sensor(np.linspace(-15, 15, 16), 720, 75.0)
    a = cast(mesh, _pose(), sensor)
    b = cast(inter, _pose(), sensor)
    assert len(a) > 100 and np.array_equal(a, b)
    assert np.allclose(np.linalg.norm(a - [8.0, 2.0, 2.0], axis=1), 3.0, atol=0.03)  # on the icosphere


def test_empty_mesh_gives_no_points():
    empty = trimesh.Trimesh(np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64), process=False)
    assert cast(empty, _pose(), Sensor(np.array([0.0]), 10, 75.0)).shape == (0, 3)


def test_metrics_and_geometry_import_no_simulator():
    """The evaluation code scores with the ray caster alone: importing it pulls in nothing of synth/."""
    code = ("import sys, hgca_core.metrics.evaluate, hgca_core.metrics.resim, hgca_core.geometry.raycast; "
            "bad = sorted(m for m in sys.modules if m.startswith('hgca_core.synth')); print(bad); sys.exit(bool(bad))")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert res.returncode == 0, res.stdout + res.stderr
