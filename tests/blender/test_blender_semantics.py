"""Labelled results (`hgca complete --semantics`): one shared material per class, each face its class's slot,
an editable palette, and a collection per class on request."""
from __future__ import annotations

from pathlib import Path

import bpy
import numpy as np
import pytest

from bl_helpers import addon_module

NAMES = ("road", "sidewalk", "building", "car", "tree", "pole", "fence", "shelter", "person")


def write_labelled(path: Path, labels: np.ndarray, agreement: np.ndarray | None = None) -> Path:
    n = len(labels)
    verts = np.c_[np.arange(3 * n) % 7, np.arange(3 * n) // 7, np.zeros(3 * n)].astype(np.float32)
    faces = np.arange(3 * n, dtype=np.int32).reshape(-1, 3)
    extra = {} if agreement is None else {"face_label_agreement": agreement.astype(np.float32)}
    np.savez(path, vertices=verts, faces=faces, observed_distance=np.zeros(3 * n, np.float32),
             face_label=labels.astype(np.uint8), label_names=np.array(NAMES), **extra)
    return path


def face_materials(obj: bpy.types.Object) -> list[str]:
    index = np.empty(len(obj.data.polygons), np.int32)
    obj.data.polygons.foreach_get("material_index", index)
    return [obj.data.materials[i].name for i in index]


def test_each_face_gets_its_class_material(addon, tmp_path: Path) -> None:
    mesh_build = addon_module("scene.mesh_build")
    labels = np.array([0, 2, 2, 4, 0, 5])
    out = write_labelled(tmp_path / "out_s0.npz", labels, np.linspace(0.5, 1, 6))
    (obj,) = mesh_build.build_results(bpy.context.scene, [out], "hGCA test").objects
    assert face_materials(obj) == [f"hGCA {NAMES[v]}" for v in labels]
    got = np.empty(6, np.int32)
    obj.data.attributes["hgca_label"].data.foreach_get("value", got)
    np.testing.assert_array_equal(got, labels)
    share = np.empty(6, np.float32)
    obj.data.attributes["hgca_label_agreement"].data.foreach_get("value", share)
    np.testing.assert_allclose(share, np.linspace(0.5, 1, 6))
    road = bpy.data.materials["hGCA road"]
    tree = bpy.data.materials["hGCA tree"]
    assert tuple(road.diffuse_color) != tuple(tree.diffuse_color)


def test_palette_is_shared_and_kept(addon, tmp_path: Path) -> None:
    mesh_build = addon_module("scene.mesh_build")
    semantics = addon_module("scene.semantics")
    a = write_labelled(tmp_path / "a_s0.npz", np.array([0, 2]))
    mesh_build.build_results(bpy.context.scene, [a], "run A")
    assert semantics.set_palette({"road": (1.0, 0.0, 0.0, 1.0)}) == 1
    b = write_labelled(tmp_path / "b_s0.npz", np.array([0, 3]))
    (obj,) = mesh_build.build_results(bpy.context.scene, [b], "run B").objects
    road = obj.data.materials["hGCA road"]
    assert road is bpy.data.materials["hGCA road"]           # one material per class in the file
    assert tuple(road.diffuse_color) == pytest.approx((1.0, 0.0, 0.0, 1.0))   # the user's colour survives
    assert len([m for m in bpy.data.materials if m.name.startswith("hGCA road")]) == 1


def test_collection_per_class(addon, tmp_path: Path) -> None:
    mesh_build = addon_module("scene.mesh_build")
    labels = np.array([0, 2, 2, 4])
    out = write_labelled(tmp_path / "out_s0.npz", labels)
    coll = mesh_build.build_results(bpy.context.scene, [out], "hGCA test", class_collections=True)
    children = {c.name: c for c in coll.children}
    assert set(children) == {"hGCA test road", "hGCA test building", "hGCA test tree"}
    (bldg,) = children["hGCA test building"].objects
    assert len(bldg.data.polygons) == 2 and bldg.data.materials[0].name == "hGCA building"


def test_results_without_labels_are_unchanged(addon, tmp_path: Path) -> None:
    mesh_build = addon_module("scene.mesh_build")
    path = tmp_path / "out_s0.npz"
    np.savez(path, vertices=np.eye(3, dtype=np.float32), faces=np.array([[0, 1, 2]], np.int32),
             observed_distance=np.zeros(3, np.float32))
    (obj,) = mesh_build.build_results(bpy.context.scene, [path], "hGCA test").objects
    assert [m.name for m in obj.data.materials] == ["hGCA test observed/generated"]
    assert "hgca_label" not in obj.data.attributes


def test_bad_labels_leave_the_file_as_it_was(addon, tmp_path: Path) -> None:
    mesh_build = addon_module("scene.mesh_build")
    path = write_labelled(tmp_path / "out_s0.npz", np.array([0, 1]))
    with np.load(path) as z:
        arrays = dict(z)
    arrays["face_label"] = np.array([0, 40], np.uint8)
    np.savez(path, **arrays)
    before = (len(bpy.data.objects), len(bpy.data.meshes), len(bpy.data.materials), len(bpy.data.collections))
    with pytest.raises(ValueError, match="face_label"):
        mesh_build.build_results(bpy.context.scene, [path], "hGCA test")
    assert (len(bpy.data.objects), len(bpy.data.meshes), len(bpy.data.materials), len(bpy.data.collections)) == before


def test_panel_classes_reach_the_core_command_line(addon) -> None:
    """The panel's Classes box asks the core for `--semantics`; off, the command is the plain completion."""
    jobs = addon_module("jobs.completion")
    props = bpy.context.scene.hgca
    assert props.semantics is False and props.class_collections is False
    base = dict(python="python", points=np.zeros((1, 3)), region=(0.0, 0.0, 0.0, 9.6, 9.6, 8.0, 0.0))
    plain = jobs.completion_args(jobs.CompletionParams(**base), Path("in.npz"), Path("out.npz"))
    labelled = jobs.completion_args(jobs.CompletionParams(**base, semantics=True), Path("in.npz"), Path("out.npz"))
    assert "--semantics" not in plain
    assert [a for a in labelled if a not in plain] == ["--semantics"]
