"""Georeferenced coordinates survive every writer and `hgca read` to well within 1 mm (issue 11, item 3).

At y ~ 1e7 m float32 has a 1 m spacing; before, every writer stored float32 world coordinates.
"""
from __future__ import annotations

import json
import struct
import sys

import numpy as np
import pytest
import trimesh

from hgca_testdata import UTM_OFFSETS, write_las
from hgca_core.cli import main
from hgca_core.io import read_scan, write_mesh, write_mesh_npz, write_points

MM = 1e-3


def cloud(place: str, n: int = 3000, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return rng.uniform([-20, -20, 0], [20, 20, 8], (n, 3)) + np.array(UTM_OFFSETS[place])


def mesh_at(place: str) -> trimesh.Trimesh:
    box = trimesh.creation.box(extents=(3.3, 2.1, 1.7))
    box.vertices = box.vertices + np.array(UTM_OFFSETS[place]) + np.array([0.123, 0.457, 0.789])
    box.vertex_attributes["observed_distance"] = np.linspace(0, 1, len(box.vertices)).astype(np.float32)
    return box


@pytest.mark.parametrize("place", sorted(UTM_OFFSETS))
@pytest.mark.parametrize("ext", [".npz", ".ply"])
def test_points_round_trip_exact(tmp_path, place, ext):
    pts = np.round(cloud(place), 3)  # a mm grid, like LAS
    path = write_points(tmp_path / f"p{ext}", pts, {"intensity": np.arange(len(pts), dtype=np.uint16)},
                        origins=pts[:1])
    back = read_scan(path)
    assert np.abs(back.points - pts).max() < 0.01 * MM
    np.testing.assert_array_equal(back.attributes["intensity"], np.arange(len(pts)))
    if ext == ".npz":
        with np.load(path) as z:
            assert z["points"].dtype == np.float32 and np.abs(z["points"]).max() < 100  # local numbers
            assert z["offset"].dtype == np.float64 and np.all(z["offset"] == np.round(z["offset"]))


def test_local_data_keeps_its_numbers(tmp_path):
    """Near the origin nothing changes: zero offset in .npz, float32 x/y/z in .ply."""
    from plyfile import PlyData

    pts = np.random.default_rng(1).uniform(-50, 50, (100, 3))
    with np.load(write_points(tmp_path / "p.npz", pts)) as z:
        assert np.all(z["offset"] == 0) and np.array_equal(z["points"], pts.astype(np.float32))
    ply = PlyData.read(str(write_points(tmp_path / "p.ply", pts)))
    assert ply["vertex"].data.dtype["x"] == np.dtype("<f4")


@pytest.mark.parametrize("place", sorted(UTM_OFFSETS))
@pytest.mark.parametrize("ext", [".ply", ".obj", ".glb"])
def test_mesh_files_read_back_exact_by_trimesh(tmp_path, place, ext):
    mesh = mesh_at(place)
    path = write_mesh(tmp_path / f"m{ext}", mesh)
    loaded = trimesh.load(path, process=False)
    if isinstance(loaded, trimesh.Scene):
        loaded = loaded.to_geometry()  # applies the node transform (float64) to the float32 vertices
    got = np.asarray(loaded.vertices, dtype=np.float64)
    assert got.shape == mesh.vertices.shape
    assert np.abs(np.sort(got, axis=0) - np.sort(mesh.vertices, axis=0)).max() < 0.01 * MM


def test_ply_mesh_is_float64_for_plyfile_too(tmp_path):
    from plyfile import PlyData

    mesh = mesh_at("utm_1e7")
    v = PlyData.read(str(write_mesh(tmp_path / "m.ply", mesh)))["vertex"].data
    assert v.dtype["x"] == np.dtype("<f8")
    np.testing.assert_array_equal(np.column_stack([v["x"], v["y"], v["z"]]), mesh.vertices)
    np.testing.assert_array_equal(v["observed_distance"], mesh.vertex_attributes["observed_distance"])


def test_glb_node_translation_is_the_exact_offset(tmp_path):
    mesh = mesh_at("utm_1e7")
    data = write_mesh(tmp_path / "m.glb", mesh)
    raw = open(data, "rb").read()
    length = struct.unpack("<I", raw[12:16])[0]
    doc = json.loads(raw[20:20 + length])
    (node,) = [n for n in doc["nodes"] if "mesh" in n]
    translation = np.array(node["matrix"][12:15])
    np.testing.assert_array_equal(translation, np.round((mesh.vertices.min(0) + mesh.vertices.max(0)) / 2))
    assert node["matrix"][:12] == [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0]
    assert doc["accessors"][doc["meshes"][0]["primitives"][0]["attributes"]["POSITION"]]["max"][1] < 10


def test_mesh_npz_vertices_plus_offset(tmp_path):
    mesh = mesh_at("utm_1e7")
    path = write_mesh_npz(tmp_path / "m.npz", mesh.vertices, mesh.faces, mesh.vertex_attributes["observed_distance"])
    with np.load(path) as z:
        world = z["vertices"].astype(np.float64) + z["offset"]
    assert np.abs(world - mesh.vertices).max() < 0.01 * MM


@pytest.mark.parametrize("place", sorted(UTM_OFFSETS))
def test_read_command_keeps_las_coordinates_to_the_mm(tmp_path, monkeypatch, capsys, place):
    """`hgca read` of a LAS at a UTM position, as the Blender import uses it."""
    held = write_las(tmp_path / "scan.las", cloud(place))
    monkeypatch.setattr(sys, "argv", ["hgca"])
    assert main(["read", str(tmp_path / "scan.las"), "-o", str(tmp_path / "scan.npz")]) == 0
    capsys.readouterr()
    with np.load(tmp_path / "scan.npz") as z:
        world = z["points"].astype(np.float64) + z["offset"]
    assert np.abs(world - held).max() < 0.01 * MM
    assert np.abs(read_scan(tmp_path / "scan.npz").points - held).max() < 0.01 * MM


# --- one offset per file: a stray point must not move it (check_coordinates) -----------------------------------

def with_strays(place: str, strays: np.ndarray, n: int = 3000) -> np.ndarray:
    pts = np.round(cloud(place, n), 3)
    pts[: len(strays)] = strays
    return pts


@pytest.mark.parametrize("stray", [[0.0, 0.0, 0.0], [0.0, 5_000_000.0, 100.0], [1e7, -1e7, 0.0]])
def test_a_stray_point_is_refused_not_written_off_by_centimetres(tmp_path, stray):
    """Before, the bounds midpoint of UTM points and one point at (0, 0, 0) sat 2.5e6 m from both, and every
    point of the .npz was off by up to 0.25 m."""
    from hgca_core.errors import InputError

    pts = with_strays("utm", np.array([stray]))
    with pytest.raises(InputError, match=r"1 of 3000 points lies [0-9.e+]+ m from the others \(first at row 0"):
        write_points(tmp_path / "p.npz", pts)
    assert not (tmp_path / "p.npz").exists()


def test_every_point_round_trips_within_1_mm_or_the_read_is_refused(tmp_path, monkeypatch, capsys):
    """Clouds out to the frame's reach and past it, with and without far points: `hgca read -o .npz` either
    keeps every point to 1 mm or exits 2 naming the file and how many points lie apart."""
    from hgca_core.io.georef import FRAME_RADIUS

    rng = np.random.default_rng(3)
    worst, refused = 0.0, 0
    monkeypatch.setattr(sys, "argv", ["hgca"])
    for trial in range(24):
        half = [10.0, 8000.0, FRAME_RADIUS - 2, FRAME_RADIUS + 3][trial % 4]
        local = rng.uniform(-half, half, (500, 3))
        local[:2, 0] = -half, half                          # the cloud spans exactly 2 * half
        pts = local + [rng.uniform(-1e7, 1e7), rng.uniform(0, 1e7), 100.0]
        strays = trial % 3
        if strays:
            pts[rng.choice(np.arange(2, 500), strays, replace=False)] = rng.uniform(-1e8, 1e8, (strays, 3))
        src = tmp_path / f"s{trial}.npy"
        np.save(src, pts)
        code = main(["read", str(src), "-o", str(tmp_path / f"o{trial}.npz")])
        err = capsys.readouterr().err
        if code == 2:
            refused += 1
            apart = f"{strays} of 500 points lie" if strays and half < FRAME_RADIUS else "of 500 points lie"
            assert str(src) in err and apart in err, err
            assert not (tmp_path / f"o{trial}.npz").exists()
            continue
        assert code == 0 and strays == 0 and half < FRAME_RADIUS, err
        with np.load(tmp_path / f"o{trial}.npz") as z:
            worst = max(worst, float(np.abs(z["points"].astype(np.float64) + z["offset"] - pts).max()))
    assert worst < MM and refused == 24 - 6   # 16 clouds with strays, 2 too wide: refused; 6 kept
    print(f"worst error of the kept clouds: {worst * 1e3:.3f} mm")


def test_local_offset_refuses_what_no_frame_holds():
    from hgca_core.errors import InputError
    from hgca_core.io.georef import local_offset

    pts = with_strays("utm_1e7", np.array([[0.0, 0.0, 0.0], [1.0, 2.0, 3.0], [4.0, 0.0, 0.0]]))
    with pytest.raises(InputError, match="3 of 3000 points lie"):
        local_offset(pts)
    with pytest.raises(InputError, match="beyond 1e\\+09 m"):
        local_offset(np.array([[1e305, 0.0, 0.0], [1e305, 1.0, 0.0]]))
