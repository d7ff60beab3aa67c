"""PLY, KITTI, XYZ/CSV/TXT, NPY/NPZ readers and format selection."""
from __future__ import annotations

import numpy as np
import pytest
from plyfile import PlyData, PlyElement

from hgca_core.io import format_from_extension, read_scan, write_points


def cloud(n: int = 200, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).uniform(-30, 30, (n, 3))


def test_ply_round_trip_with_attributes(tmp_path):
    pts = cloud()
    attrs = {
        "intensity": np.linspace(0, 1, len(pts)).astype(np.float32),
        "scan_index": (np.arange(len(pts)) % 3).astype(np.uint16),
        "label": np.arange(len(pts), dtype=np.int64) - 50,  # int64 is not a PLY type: stored as int32
        "gps_time": np.linspace(3.0e8, 3.0e8 + 1, len(pts)),
    }
    path = write_points(tmp_path / "out.ply", pts, attrs)
    ply = PlyData.read(path)
    assert ply.text is False and ply.byte_order == "<"
    assert ply["vertex"].data.dtype["x"] == np.dtype("<f4")
    scan = read_scan(path)
    np.testing.assert_array_equal(scan.points, pts.astype(np.float32).astype(np.float64))
    assert set(scan.attributes) == set(attrs)
    for name, values in attrs.items():
        np.testing.assert_array_equal(scan.attributes[name], values)
    assert scan.attributes["label"].dtype == np.int32
    assert scan.attributes["gps_time"].dtype == np.float64


def test_ascii_ply_and_face_lists_skipped(tmp_path):
    v = np.array([(0, 0, 0, 7), (1, 0, 0, 8), (0, 1, 0, 9)], dtype=[("x", "f8"), ("y", "f8"), ("z", "f8"),
                                                                     ("intensity", "u1")])
    f = np.array([([0, 1, 2],)], dtype=[("vertex_indices", "i4", (3,))])
    path = tmp_path / "tri.ply"
    PlyData([PlyElement.describe(v, "vertex"), PlyElement.describe(f, "face")], text=True).write(str(path))
    scan = read_scan(path)
    np.testing.assert_array_equal(scan.points, [[0, 0, 0], [1, 0, 0], [0, 1, 0]])
    np.testing.assert_array_equal(scan.attributes["intensity"], [7, 8, 9])
    assert scan.origins is None


def test_kitti_bin(tmp_path):
    rows = np.column_stack([cloud(100), np.linspace(0, 1, 100)]).astype(np.float32)
    path = tmp_path / "000042.bin"
    rows.tofile(path)
    scan = read_scan(path)
    np.testing.assert_array_equal(scan.points, rows[:, :3].astype(np.float64))
    np.testing.assert_array_equal(scan.attributes["intensity"], rows[:, 3])
    np.testing.assert_array_equal(scan.origins, [[0, 0, 0]])


@pytest.mark.parametrize("name, sep, head", [
    ("a.xyz", " ", None),
    ("b.txt", "\t", None),
    ("c.csv", ",", "X,Y,Z,intensity"),
    ("d.csv", ";", None),
    ("e.txt", " ", "intensity x y z"),
])
def test_text_tables(tmp_path, name, sep, head):
    pts = np.round(cloud(50), 4)
    inten = np.arange(50) / 10
    cols = [inten, *pts.T] if head and head.startswith("intensity") else [*pts.T, inten]
    lines = [sep.join(f"{v:.4f}" for v in row) for row in np.column_stack(cols)]
    text = "# exported by a test\n" + (head.replace(",", sep) + "\n" if head else "") + "\n".join(lines) + "\n"
    path = tmp_path / name
    path.write_text(text)
    scan = read_scan(path)
    np.testing.assert_allclose(scan.points, pts, atol=1e-9)
    key = "intensity" if head else "column_3"
    np.testing.assert_allclose(scan.attributes[key], inten)
    assert list(scan.attributes) == [key]


def test_npy_plain_and_structured(tmp_path):
    a = np.column_stack([cloud(30), np.arange(30)]).astype(np.float32)
    np.save(tmp_path / "p.npy", a)
    scan = read_scan(tmp_path / "p.npy")
    np.testing.assert_array_equal(scan.points, a[:, :3].astype(np.float64))
    np.testing.assert_array_equal(scan.attributes["column_3"], a[:, 3])
    s = np.zeros(5, dtype=[("x", "f8"), ("y", "f8"), ("z", "f8"), ("intensity", "u2")])
    s["x"], s["intensity"] = np.arange(5), np.arange(5) * 2
    np.save(tmp_path / "s.npy", s)
    scan = read_scan(tmp_path / "s.npy")
    np.testing.assert_array_equal(scan.points[:, 0], np.arange(5))
    np.testing.assert_array_equal(scan.attributes["intensity"], np.arange(5) * 2)


def test_npz_attributes_origins_and_metadata(tmp_path):
    pts = cloud(40)
    np.savez(tmp_path / "s.npz", points=pts, intensity=np.arange(40, dtype=np.uint16),
             origins=np.array([[1.0, 2.0, 3.0]]), meta=np.array("json"), grid=np.zeros((40, 2)))
    scan = read_scan(tmp_path / "s.npz")
    np.testing.assert_array_equal(scan.points, pts)
    assert list(scan.attributes) == ["intensity"]
    np.testing.assert_array_equal(scan.origins, [[1, 2, 3]])


def test_npz_written_by_write_points_reads_back(tmp_path):
    pts = cloud(40)
    write_points(tmp_path / "w.npz", pts, {"ring": np.arange(40, dtype=np.uint8)}, origins=[[0, 0, 1.8]])
    scan = read_scan(tmp_path / "w.npz")
    np.testing.assert_array_equal(scan.points, pts.astype(np.float32))
    np.testing.assert_array_equal(scan.origins, [[0, 0, 1.8]])
    assert scan.attributes["ring"].dtype == np.uint8


def test_format_override_and_extension_table(tmp_path):
    rows = np.column_stack([cloud(10), np.zeros(10)]).astype(np.float32)
    rows.tofile(tmp_path / "sweep.dat")
    assert len(read_scan(tmp_path / "sweep.dat", fmt="kitti")) == 10
    assert format_from_extension("a/B.PCD.BIN") == "nuscenes"
    assert format_from_extension("x.copc.laz") == "las"
    assert format_from_extension("x.LAZ") == "las"
    assert format_from_extension("x.bin") == "kitti"
    assert format_from_extension("x.e57") is None
