"""Labels travel through every mesh format: PLY face property, NPZ arrays, one GLB primitive per class."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh
from plyfile import PlyData
from scipy.spatial import cKDTree

from hgca_core.io import write_mesh, write_mesh_npz
from hgca_core.io.classes import CLASS_NAMES
from hgca_core.io.writers import CLASS_MATERIALS
from hgca_core.meshing.finish import finish_mesh


def labelled_mesh(offset: float = 0.0) -> trimesh.Trimesh:
    mesh = trimesh.creation.icosphere(3)
    mesh.apply_translation((offset, offset, 0.0))
    mesh = finish_mesh(mesh, np.where(mesh.vertices[:, 0] > offset, 0.0, 1.0).astype(np.float32))
    c = mesh.triangles_center - offset
    label = np.where(c[:, 2] > 0.3, 2, np.where(c[:, 2] < -0.3, 0, 4)).astype(np.uint8)
    label[np.argmax(c[:, 0])] = 5
    mesh.face_attributes["label"] = label
    mesh.face_attributes["label_agreement"] = np.linspace(0.25, 1.0, len(label)).astype(np.float32)
    return mesh


def test_ply_keeps_label_and_agreement_per_face(tmp_path):
    mesh = labelled_mesh()
    ply = PlyData.read(write_mesh(tmp_path / "m.ply", mesh))
    face = ply["face"].data
    np.testing.assert_array_equal(face["label"], mesh.face_attributes["label"])
    assert face["label"].dtype == np.uint8
    np.testing.assert_allclose(face["label_agreement"], mesh.face_attributes["label_agreement"])
    np.testing.assert_array_equal(face["material"], mesh.face_attributes["material"])


def test_npz_keeps_label_agreement_and_names(tmp_path):
    mesh = labelled_mesh()
    label, agree = mesh.face_attributes["label"], mesh.face_attributes["label_agreement"]
    path = write_mesh_npz(tmp_path / "m.npz", mesh.vertices, mesh.faces, mesh.vertex_attributes["observed_distance"],
                          face_label=label, face_label_agreement=agree)
    with np.load(path) as z:
        np.testing.assert_array_equal(z["face_label"], label)
        np.testing.assert_allclose(z["face_label_agreement"], agree)
        assert tuple(z["label_names"]) == CLASS_NAMES
    plain = write_mesh_npz(tmp_path / "p.npz", mesh.vertices, mesh.faces, mesh.vertex_attributes["observed_distance"])
    with np.load(plain) as z:
        assert "face_label" not in z and "label_names" not in z
    with pytest.raises(ValueError, match="face_label"):
        write_mesh_npz(tmp_path / "x.npz", mesh.vertices, mesh.faces, mesh.vertex_attributes["observed_distance"],
                       face_label=label[:-1])


@pytest.mark.parametrize("offset", [0.0, 5e5])
def test_glb_has_one_named_primitive_per_class(tmp_path, offset):
    mesh = labelled_mesh(offset)
    label = mesh.face_attributes["label"]
    scene = trimesh.load(write_mesh(tmp_path / "m.glb", mesh), process=False)
    parts = {g.visual.material.name: (name, g) for name, g in scene.geometry.items()}
    present = {CLASS_NAMES[v] for v in np.unique(label)}
    assert set(parts) == present
    for cls, (_, g) in parts.items():
        assert len(g.faces) == int((label == CLASS_NAMES.index(cls)).sum())
        np.testing.assert_allclose(g.visual.material.baseColorFactor / 255.0, CLASS_MATERIALS[cls], atol=1 / 255)
        assert "_observed_distance" in g.vertex_attributes and "_label_agreement" in g.vertex_attributes
    # every face of a class lies where the mesh has a face of that class (world coordinates, offset applied)
    for cls, (name, g) in parts.items():
        world = trimesh.transform_points(g.triangles_center, scene.graph[name][0]) if name in scene.graph.nodes \
            else g.triangles_center
        i = cKDTree(mesh.triangles_center).query(world)[1]
        assert np.all(label[i] == CLASS_NAMES.index(cls))


def test_glb_without_labels_keeps_observed_and_generated(tmp_path):
    mesh = labelled_mesh()
    del mesh.face_attributes["label"]
    scene = trimesh.load(write_mesh(tmp_path / "m.glb", mesh), process=False)
    assert {g.visual.material.name for g in scene.geometry.values()} == {"observed", "generated"}
