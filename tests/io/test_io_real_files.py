"""Readers on real sensor data: counts and coordinates must match what laspy / the raw layout say."""
from __future__ import annotations

import laspy
import numpy as np
import pytest

from hgca_core.io import read_scan, read_scans
from hgca_core.io.las import las_header_info

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


def test_nuscenes_sweep(real_dir):
    path = real_dir / NUSCENES
    raw = np.fromfile(path, dtype="<f4")
    assert raw.size % 5 == 0
    raw = raw.reshape(-1, 5)
    assert raw.shape == (34688, 5)
    scan = read_scan(path)
    assert len(scan) == 34688
    np.testing.assert_array_equal(scan.points, raw[:, :3].astype(np.float64))
    np.testing.assert_array_equal(scan.attributes["intensity"], raw[:, 3])
    np.testing.assert_array_equal(scan.attributes["ring"], raw[:, 4].astype(np.uint16))
    assert scan.attributes["ring"].max() == 31  # HDL-32E
    np.testing.assert_array_equal(scan.origins, [[0.0, 0.0, 0.0]])


def test_accumulate_real_las_keeps_common_attributes(real_dir):
    scan = read_scans([real_dir / "simple.las", real_dir / NUSCENES])
    assert len(scan) == 1065 + 34688
    assert set(scan.attributes) == {"intensity", "scan_index"}
    assert scan.attributes["scan_index"].dtype == np.uint16
    assert (scan.attributes["scan_index"][:1065] == 0).all() and (scan.attributes["scan_index"][1065:] == 1).all()
    # Only the nuScenes sweep knows its sensor origin.
    np.testing.assert_array_equal(scan.origins, [[0.0, 0.0, 0.0]])
