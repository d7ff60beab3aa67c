"""Every kind of bad input raises InputError naming the file, never a library traceback."""
from __future__ import annotations

import shutil

import laspy
import numpy as np
import pytest
from plyfile import PlyData, PlyElement

from hgca_core.errors import InputError
from hgca_core.io import read_scan, write_points

NUSCENES = "nuscenes_lidar_top_1532402927647951.pcd.bin"


def raises_naming(path, match: str | None = None, **kw) -> InputError:
    with pytest.raises(InputError) as exc:
        read_scan(path, **kw)
    msg = str(exc.value)
    assert str(path.name) in msg, msg
    if match:
        assert match in msg, msg
    assert exc.value.__cause__ is None or isinstance(exc.value.__cause__, InputError)
    return exc.value


def test_missing_file(tmp_path):
    raises_naming(tmp_path / "nothing_here.las", "not found")


def test_directory(tmp_path):
    (tmp_path / "dir.ply").mkdir()
    raises_naming(tmp_path / "dir.ply", "not a regular file")


@pytest.mark.parametrize("name", ["e.ply", "e.las", "e.laz", "e.pcd", "e.xyz", "e.npy", "e.npz", "e.bin",
                                  "e.pcd.bin"])
def test_empty_file(tmp_path, name):
    (tmp_path / name).write_bytes(b"")
    raises_naming(tmp_path / name, "empty")


def test_zero_points_each_format(tmp_path):
    v = np.zeros(0, dtype=[("x", "f4"), ("y", "f4"), ("z", "f4")])
    PlyData([PlyElement.describe(v, "vertex")]).write(str(tmp_path / "z.ply"))
    raises_naming(tmp_path / "z.ply", "no points")
    np.save(tmp_path / "z.npy", np.zeros((0, 3)))
    raises_naming(tmp_path / "z.npy", "no points")
    np.savez(tmp_path / "z.npz", points=np.zeros((0, 3)))
    raises_naming(tmp_path / "z.npz", "no points")
    (tmp_path / "z.csv").write_text("x,y,z\n")
    raises_naming(tmp_path / "z.csv", "no points")
    (tmp_path / "c.xyz").write_text("# only a comment\n\n")
    raises_naming(tmp_path / "c.xyz", "no points")
    las = laspy.LasData(laspy.LasHeader(point_format=3, version="1.2"))
    las.write(tmp_path / "z.las")
    raises_naming(tmp_path / "z.las", "no points")


def test_truncated_las_and_laz(real_dir, tmp_path):
    for name in ("simple.las", "simple.laz", "autzen_trim.laz"):
        data = (real_dir / name).read_bytes()
        for keep in (200, len(data) // 2):
            path = tmp_path / f"cut{keep}_{name}"
            path.write_bytes(data[:keep])
            raises_naming(path, "LAS")


def test_truncated_binary_ply(tmp_path):
    path = write_points(tmp_path / "full.ply", np.random.default_rng(0).normal(size=(100, 3)))
    data = open(path, "rb").read()
    (tmp_path / "cut.ply").write_bytes(data[: len(data) - 700])
    raises_naming(tmp_path / "cut.ply", "PLY")
    (tmp_path / "hdr.ply").write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 3\n")
    raises_naming(tmp_path / "hdr.ply", "PLY")


def test_ply_without_xyz(tmp_path):
    v = np.zeros(3, dtype=[("u", "f4"), ("v", "f4")])
    PlyData([PlyElement.describe(v, "vertex")]).write(str(tmp_path / "uv.ply"))
    raises_naming(tmp_path / "uv.ply", "lacks x, y, z")


def test_corrupt_numpy_files(tmp_path):
    np.save(tmp_path / "t.npy", np.zeros((100, 3)))
    data = (tmp_path / "t.npy").read_bytes()
    (tmp_path / "t.npy").write_bytes(data[:300])
    raises_naming(tmp_path / "t.npy", "NumPy")
    (tmp_path / "junk.npz").write_bytes(b"this is not a zip archive at all")
    raises_naming(tmp_path / "junk.npz", "NumPy")
    np.savez(tmp_path / "nokey.npz", xyz=np.zeros((3, 3)))
    raises_naming(tmp_path / "nokey.npz", "no 'points'")
    np.save(tmp_path / "flat.npy", np.zeros(9))
    raises_naming(tmp_path / "flat.npy", "(N, >=3)")
    np.save(tmp_path / "obj.npy", np.array([{"a": 1}], dtype=object), allow_pickle=True)
    raises_naming(tmp_path / "obj.npy")


def test_malformed_text(tmp_path):
    (tmp_path / "rag.xyz").write_text("1 2 3\n4 5\n")
    raises_naming(tmp_path / "rag.xyz", "malformed")
    (tmp_path / "two.csv").write_text("1,2\n3,4\n")
    raises_naming(tmp_path / "two.csv", "at least 3 columns")


def test_wrong_extension(real_dir, tmp_path):
    shutil.copy(real_dir / "simple.las", tmp_path / "renamed.ply")
    err = raises_naming(tmp_path / "renamed.ply", "content is LAS")
    assert "--format las" in str(err)
    write_points(tmp_path / "real.ply", np.zeros((3, 3)))
    shutil.copy(tmp_path / "real.ply", tmp_path / "fake.laz")
    raises_naming(tmp_path / "fake.laz", "content is PLY")
    shutil.copy(real_dir / "simple.laz", tmp_path / "scan.bin")
    raises_naming(tmp_path / "scan.bin", "content is LAS")
    shutil.copy(real_dir / "simple.las", tmp_path / "scan.rcp")
    raises_naming(tmp_path / "scan.rcp", "unknown file extension '.rcp'")
    raises_naming(tmp_path / "real.ply", "unknown format", fmt="obj")
    raises_naming(tmp_path / "real.ply", "--format ply", fmt="las")


def test_kitti_size_not_multiple_of_16(tmp_path):
    (tmp_path / "odd.bin").write_bytes(np.zeros(9, dtype=np.float32).tobytes()[:34])
    raises_naming(tmp_path / "odd.bin", "not a multiple of 16")


def test_nuscenes_truncated(real_dir, tmp_path):
    data = (real_dir / NUSCENES).read_bytes()
    (tmp_path / "cut.pcd.bin").write_bytes(data[:-7])
    raises_naming(tmp_path / "cut.pcd.bin", "not a multiple of 20")


def npy(tmp_path, name, rows):
    np.save(tmp_path / name, np.array(rows, dtype=np.float64))
    return tmp_path / name


def test_all_nan_rows_dropped_silently(tmp_path):
    nan = float("nan")
    scan = read_scan(npy(tmp_path, "org.npy", [[nan, nan, nan, 1], [1, 2, 3, 2], [nan, nan, nan, 3]]))
    np.testing.assert_array_equal(scan.points, [[1, 2, 3]])
    np.testing.assert_array_equal(scan.attributes["column_3"], [2])


@pytest.mark.parametrize("bad", [[float("nan"), 0, 0], [0, float("inf"), 0], [0, 0, -float("inf")],
                                 [float("nan"), float("nan"), float("inf")]])
def test_other_non_finite_raises(tmp_path, bad):
    err = raises_naming(npy(tmp_path, "bad.npy", [[1, 2, 3], bad]), "NaN or infinite")
    assert "row 1" in str(err)


def test_only_no_return_rows_raises(tmp_path):
    nan = float("nan")
    raises_naming(npy(tmp_path, "allnan.npy", [[nan] * 3, [nan] * 3]), "no points")


def test_nan_in_text_and_kitti(tmp_path):
    (tmp_path / "n.xyz").write_text("1 2 3\nnan 4 5\n")
    raises_naming(tmp_path / "n.xyz", "NaN or infinite")
    np.array([[1, 2, 3, 0], [np.inf, 0, 0, 0]], dtype=np.float32).tofile(tmp_path / "inf.bin")
    raises_naming(tmp_path / "inf.bin", "NaN or infinite")


def test_non_finite_origin(tmp_path):
    np.savez(tmp_path / "o.npz", points=np.zeros((2, 3)), origins=np.array([[0, np.nan, 0]]))
    raises_naming(tmp_path / "o.npz", "origin")
