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
