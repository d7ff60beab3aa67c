"""Point and mesh writers: formats, the observed_distance attribute, atomic replacement."""
from __future__ import annotations

import os

import numpy as np
import pytest
import trimesh
from plyfile import PlyData
from scipy.spatial import cKDTree

from hgca_core.errors import InputError
from hgca_core.io import read_scan, write_mesh, write_mesh_npz, write_points
from hgca_core.io import atomic as atomic_mod


def box_mesh() -> trimesh.Trimesh:
    mesh = trimesh.creation.box(extents=(2, 3, 4))
    mesh.vertex_attributes["observed_distance"] = np.linspace(0, 1.4, len(mesh.vertices))
    return mesh


def test_write_mesh_ply_keeps_observed_distance(tmp_path):
    mesh = box_mesh()
    path = write_mesh(tmp_path / "m.ply", mesh)
    ply = PlyData.read(path)
    assert ply.text is False and ply.byte_order == "<"
    v = ply["vertex"].data
    np.testing.assert_allclose(np.column_stack([v["x"], v["y"], v["z"]]), mesh.vertices)
    np.testing.assert_allclose(v["observed_distance"], mesh.vertex_attributes["observed_distance"], rtol=1e-6)
    faces = np.vstack(ply["face"].data["vertex_indices"])
    np.testing.assert_array_equal(faces, mesh.faces)
    back = trimesh.load(path, process=False)  # other tools read it as an ordinary mesh
    np.testing.assert_array_equal(back.faces, mesh.faces)
    # and as a scan: vertices with the attribute
    scan = read_scan(path)
    assert set(scan.attributes) == {"observed_distance"}


def test_write_mesh_glb_and_obj(tmp_path):
    mesh = box_mesh()
    glb = write_mesh(tmp_path / "m.glb", mesh)
    scene = trimesh.load(glb, process=False)
    (loaded,) = scene.geometry.values()
    np.testing.assert_allclose(loaded.vertices, mesh.vertices, atol=1e-6)
    np.testing.assert_allclose(loaded.vertex_attributes["_observed_distance"].ravel(),
                               mesh.vertex_attributes["observed_distance"], rtol=1e-6)
    obj = write_mesh(tmp_path / "m.obj", mesh)
    back = trimesh.load(obj, process=False)
    assert len(back.faces) == len(mesh.faces)
    with pytest.raises(InputError, match="m.stl"):
        write_mesh(tmp_path / "m.stl", mesh)


def test_write_mesh_npz_layout(tmp_path):
    mesh = box_mesh()
    path = write_mesh_npz(tmp_path / "m.npz", mesh.vertices, mesh.faces, mesh.vertex_attributes["observed_distance"])
    with np.load(path) as z:
        assert set(z.keys()) == {"vertices", "offset", "faces", "observed_distance"}
        assert z["vertices"].dtype == np.float32 and z["vertices"].shape == (8, 3)
        assert z["faces"].dtype == np.int32 and z["faces"].shape == (12, 3)
        assert z["observed_distance"].dtype == np.float32 and z["observed_distance"].shape == (8,)
        np.testing.assert_array_equal(z["faces"], mesh.faces)
    with pytest.raises(ValueError):
        write_mesh_npz(tmp_path / "bad.npz", mesh.vertices, mesh.faces + 100, np.zeros(8))
    with pytest.raises(ValueError):
        write_mesh_npz(tmp_path / "bad.npz", mesh.vertices, mesh.faces, np.zeros(7))


def test_write_points_rejects_bad_extension_and_shapes(tmp_path):
    with pytest.raises(InputError, match="out.las"):
        write_points(tmp_path / "out.las", np.zeros((2, 3)))
    with pytest.raises(ValueError):
        write_points(tmp_path / "out.ply", np.zeros((2, 2)))
    with pytest.raises(ValueError):
        write_points(tmp_path / "out.npz", np.zeros((2, 3)), {"i": np.zeros(3)})
    with pytest.raises(ValueError):
        write_points(tmp_path / "out.npz", np.zeros((2, 3)), {"points": np.zeros(2)})


def test_atomic_write_leaves_old_file_on_failure(tmp_path, monkeypatch):
    path = tmp_path / "keep.npz"
    write_points(path, np.ones((4, 3)))
    before = path.read_bytes()

    def boom(*args, **kwargs):
        raise RuntimeError("disk on fire")

    monkeypatch.setattr(np, "savez", boom)
    with pytest.raises(RuntimeError):
        write_points(path, np.zeros((5, 3)))
    assert path.read_bytes() == before
    assert sorted(os.listdir(tmp_path)) == ["keep.npz"]  # temp file cleaned up


def test_atomic_write_replaces_via_os_replace(tmp_path, monkeypatch):
    calls = []
    real = os.replace

    def spy(src, dst):
        calls.append((os.path.dirname(src), os.path.basename(src), dst))
        return real(src, dst)

    monkeypatch.setattr(atomic_mod.os, "replace", spy)
    out = tmp_path / "sub" / "new.ply"
    write_points(out, np.zeros((3, 3)))
    ((src_dir, src_name, dst),) = calls
    assert src_dir == str(out.parent) and src_name.startswith(".new.ply.") and dst == str(out)
    mask = os.umask(0)
    os.umask(mask)
    assert out.stat().st_mode & 0o777 == 0o666 & ~mask  # as open() would give, not mkstemp's 0600


def test_unwritable_output_is_input_error(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    with pytest.raises(InputError, match="cannot write"):
        write_points(blocker / "out.npz", np.zeros((2, 3)))


def finished_mesh() -> trimesh.Trimesh:
    """A mesh as the pipeline returns it: normals, observed_distance, observed / generated face material."""
    from hgca_core.meshing.finish import finish_mesh

    mesh = trimesh.creation.icosphere(2)
    return finish_mesh(mesh, np.where(mesh.vertices[:, 0] > 0, 0.0, 1.0).astype(np.float32))


def test_mesh_normals_and_material_in_ply_npz_glb(tmp_path):
    mesh = finished_mesh()
    normals, material = np.asarray(mesh.vertex_normals), mesh.face_attributes["material"]
    assert set(np.unique(material)) == {0, 1}
    ply = PlyData.read(write_mesh(tmp_path / "m.ply", mesh))
    v = ply["vertex"].data
    np.testing.assert_allclose(np.column_stack([v["nx"], v["ny"], v["nz"]]), normals, atol=1e-6)
    np.testing.assert_array_equal(ply["face"].data["material"], material)
    np.testing.assert_array_equal(np.vstack(ply["face"].data["vertex_indices"]), mesh.faces)
    path = write_mesh_npz(tmp_path / "m.npz", mesh.vertices, mesh.faces, mesh.vertex_attributes["observed_distance"],
                          normals=normals, face_material=material)
    with np.load(path) as z:
        assert z["normals"].dtype == np.float32 and z["face_material"].dtype == np.uint8
        np.testing.assert_allclose(z["normals"], normals, atol=1e-6)
        np.testing.assert_array_equal(z["face_material"], material)
    with pytest.raises(ValueError, match="face_material"):
        write_mesh_npz(tmp_path / "x.npz", mesh.vertices, mesh.faces, mesh.vertex_attributes["observed_distance"],
                       face_material=material[:-1])
    scene = trimesh.load(write_mesh(tmp_path / "m.glb", mesh), process=False)
    parts = {g.visual.material.name: g for g in scene.geometry.values()}
    assert set(parts) == {"observed", "generated"}
    assert sum(len(g.faces) for g in parts.values()) == len(mesh.faces)
    for name, value in (("observed", 0), ("generated", 1)):
        g = parts[name]
        assert len(g.faces) == int((material == value).sum())
        d = g.vertex_attributes["_observed_distance"].ravel()
        assert np.all(d <= 0.15) if value == 0 else np.any(d > 0.15)
        # normals travel: every part vertex's normal is the mesh's normal at that position
        i = cKDTree(mesh.vertices).query(g.vertices)[1]
        np.testing.assert_allclose(g.vertex_normals, normals[i], atol=1e-5)
