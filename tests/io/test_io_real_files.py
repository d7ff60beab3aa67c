"""Readers on real sensor data: counts and coordinates must match what laspy / the raw layout say."""
from __future__ import annotations

import laspy
import numpy as np
import pytest

from hgca_core.errors import InputError
from hgca_core.io import read_scan, read_scans
from hgca_core.io.las import las_header_info
from hgca_core.io.sensor_bin import EGO_RETURNS

LAS_FILES = ("simple.las", "simple.laz", "simple1_4.las", "plane.laz", "simple.copc.laz", "autzen_trim.laz")
NUSCENES = "nuscenes_lidar_top_1532402927647951.pcd.bin"


@pytest.mark.parametrize("name", LAS_FILES)
def test_las_matches_laspy(real_dir, name):
    path = real_dir / name
    las = laspy.read(path)
    scan = read_scan(path)
    assert len(scan) == las.header.point_count > 0
    np.testing.assert_array_equal(scan.points[:, 0], np.asarray(las.x))
    np.testing.assert_array_equal(scan.points[:, 1], np.asarray(las.y))
    np.testing.assert_array_equal(scan.points[:, 2], np.asarray(las.z))
    np.testing.assert_array_equal(scan.attributes["intensity"], np.asarray(las.intensity))
    np.testing.assert_array_equal(scan.attributes["classification"], np.asarray(las.classification))
    np.testing.assert_array_equal(scan.attributes["return_number"], np.asarray(las.return_number))
    np.testing.assert_array_equal(scan.attributes["gps_time"], np.asarray(las.gps_time))
    assert scan.origins is None
    assert scan.points.dtype == np.float64


def test_las_offsets_are_applied(real_dir):
    """plane.laz has offsets of ~1e6 m: raw integers times scale alone would be far off."""
    scan = read_scan(real_dir / "plane.laz")
    las = laspy.read(real_dir / "plane.laz")
    assert scan.points[:, 1].min() > 4.0e6
    np.testing.assert_allclose(scan.points[:, 0], las.X * las.header.scales[0] + las.header.offsets[0])


def test_copc_and_laz_equal_las(real_dir):
    ref = read_scan(real_dir / "simple.las")
    laz = read_scan(real_dir / "simple.laz")
    np.testing.assert_array_equal(ref.points, laz.points)
    copc = read_scan(real_dir / "simple.copc.laz")
    assert len(copc) == 1065
    # COPC reorders points into its octree; the set of points is the same.
    key = lambda p: p[np.lexsort(p.T[::-1])]  # noqa: E731
    np.testing.assert_allclose(key(copc.points), key(ref.points), atol=1e-9)
    info = las_header_info(real_dir / "simple.copc.laz")
    assert info["copc"] and info["compressed"] and info["version"] == "1.4"


def on_own_car(raw: np.ndarray) -> np.ndarray:
    """Reference, written apart from the reader: a nuScenes return lies on the own car when it is within 1 m
    across and -1.8 to 2.6 m along (y forward) of the roof LiDAR and not above it (the Renault Zoe is 1.73 m
    wide and 4.08 m long, the LiDAR 0.99 m ahead of its rear axle)."""
    return np.array([abs(x) <= 1.0 and -1.8 <= y <= 2.6 and -2.5 <= z <= 0.2 for x, y, z in raw[:, :3]])


def test_nuscenes_sweep(real_dir):
    path = real_dir / NUSCENES
    raw = np.fromfile(path, dtype="<f4")
    assert raw.size % 5 == 0
    raw = raw.reshape(-1, 5)
    assert raw.shape == (34688, 5)
    scan = read_scan(path)
    ego = on_own_car(raw)
    kept = raw[~ego]
    assert len(scan) == len(kept) and scan.dropped == {EGO_RETURNS: int(ego.sum())}
    np.testing.assert_array_equal(scan.points, kept[:, :3].astype(np.float64))
    np.testing.assert_array_equal(scan.attributes["intensity"], kept[:, 3])
    np.testing.assert_array_equal(scan.attributes["ring"], kept[:, 4].astype(np.uint16))
    assert scan.attributes["ring"].max() == 31  # HDL-32E
    np.testing.assert_array_equal(scan.origins, [[0.0, 0.0, 0.0]])


def test_nuscenes_drops_the_own_car_only(real_dir):
    """The returns off the car are a quarter of this sweep, all within 2 m of the sensor and at most 1 m below it;
    every return farther than 2.5 m is kept."""
    raw = np.fromfile(real_dir / NUSCENES, dtype="<f4").reshape(-1, 5)
    scan = read_scan(real_dir / NUSCENES)
    near = np.hypot(raw[:, 0], raw[:, 1]) < 2.0
    assert 0.2 < near.mean() < 0.3 and (raw[near, 2] > -1.0).all()
    assert scan.dropped[EGO_RETURNS] == near.sum()
    assert (np.hypot(scan.points[:, 0], scan.points[:, 1]) >= 2.5).all()
    assert len(scan) == (np.hypot(raw[:, 0], raw[:, 1]) >= 2.5).sum()


def test_nuscenes_file_near_the_sensor_only_is_not_emptied(tmp_path):
    """A sweep whose every return falls in the car's box (a tiny test file) is read as it is, not emptied."""
    rows = np.array([[0.1, 0.2, -0.5, 1.0, 3.0], [0.3, -0.4, -0.2, 2.0, 4.0]], dtype="<f4")
    (tmp_path / "tiny.pcd.bin").write_bytes(rows.tobytes())
    scan = read_scan(tmp_path / "tiny.pcd.bin")
    assert len(scan) == 2 and scan.dropped == {}


def test_accumulate_real_las_keeps_common_attributes(real_dir, tmp_path):
    las = laspy.read(real_dir / "simple.las")   # moved from its UTM place next to the sweep: one float32 frame
    shift = np.floor(las.header.mins)
    local = [np.asarray(las.x) - shift[0], np.asarray(las.y) - shift[1], np.asarray(las.z) - shift[2]]
    las.header.offsets = np.zeros(3)
    las.x, las.y, las.z = local
    las.write(tmp_path / "simple.las")
    scan = read_scans([tmp_path / "simple.las", real_dir / NUSCENES], poses=[np.eye(4), np.eye(4)])
    nuscenes = read_scan(real_dir / NUSCENES)
    assert len(scan) == 1065 + len(nuscenes) and scan.dropped == nuscenes.dropped
    assert set(scan.attributes) == {"intensity", "scan_index"}
    assert scan.attributes["scan_index"].dtype == np.uint16
    assert (scan.attributes["scan_index"][:1065] == 0).all() and (scan.attributes["scan_index"][1065:] == 1).all()
    # With poses each scan has an origin (the LAS its pose's); without, only the nuScenes sweep knows its sensor,
    # and the LAS points' rays would be cast from it: refused.
    np.testing.assert_array_equal(scan.origins, [[0.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    with pytest.raises(InputError, match="no sensor origin but .*has one"):
        read_scans([tmp_path / "simple.las", real_dir / NUSCENES])
