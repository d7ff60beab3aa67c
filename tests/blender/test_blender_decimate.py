"""Max Faces as a Decimate modifier: every triangle stays in the mesh, the modifier shows Max Faces, the user tunes
it live, and the colours Solid view draws survive the collapse."""
from __future__ import annotations

from pathlib import Path

import bpy
import numpy as np

from bl_helpers import addon_module


def write_grid(path: Path, n: int = 80) -> tuple[Path, int]:
    """A wavy n x n grid of 2 (n-1)^2 triangles, generated (orange) everywhere: one sample's .npz."""
    x, y = np.meshgrid(np.linspace(-2, 2, n), np.linspace(-2, 2, n))
    verts = np.column_stack([x.ravel(), y.ravel(), 0.1 * np.sin(3 * x.ravel()) * np.cos(2 * y.ravel())])
    i = np.arange(n * n).reshape(n, n)[:-1, :-1].ravel()
    faces = np.concatenate([np.column_stack([i, i + 1, i + n]), np.column_stack([i + 1, i + n + 1, i + n])])
    np.savez(path, vertices=verts.astype(np.float32), faces=faces.astype(np.int32),
             observed_distance=np.full(len(verts), 5.0, dtype=np.float32))
    return path, len(faces)


def shown(obj: bpy.types.Object) -> bpy.types.Mesh:
    return obj.evaluated_get(bpy.context.evaluated_depsgraph_get()).data


def test_modifier_shows_max_faces_and_keeps_every_triangle(addon, tmp_path: Path) -> None:
    mesh_build = addon_module("scene.mesh_build")
    path, total = write_grid(tmp_path / "out_s0.npz")
    (obj,) = mesh_build.build_results(bpy.context.scene, [path], "hGCA test", decimate_to=2000).objects
    mod = obj.modifiers[mesh_build.DECIMATE_MODIFIER]
    assert mod.type == "DECIMATE" and mod.decimate_type == "COLLAPSE"
    assert len(obj.data.polygons) == total  # the data keeps everything: nothing is lost
    first = len(shown(obj).polygons)
    assert 1800 <= first <= 2000, first
    assert shown(obj).color_attributes.active_color_name == mesh_build.OBSERVED_COLOR
    mod.ratio = 0.5  # tuned live
    assert abs(len(shown(obj).polygons) - total / 2) < 0.02 * total
    assert len(obj.data.polygons) == total


def test_no_modifier_when_baking_or_already_small(addon, tmp_path: Path) -> None:
    mesh_build = addon_module("scene.mesh_build")
    path, total = write_grid(tmp_path / "out_s0.npz", 20)
    (baked,) = mesh_build.build_results(bpy.context.scene, [path], "hGCA a").objects
    (small,) = mesh_build.build_results(bpy.context.scene, [path], "hGCA b", decimate_to=total).objects
    assert not baked.modifiers and not small.modifiers


def test_panel_setting_turns_max_faces_into_the_modifier(addon) -> None:
    props = bpy.context.scene.hgca
    properties = addon_module("properties")
    props.max_faces, props.keep_all_faces = 5000, False
    assert (properties.face_limit(props), properties.decimate_limit(props)) == (5000, 0)
    props.face_limit_mode = "MODIFIER"
    assert (properties.face_limit(props), properties.decimate_limit(props)) == (0, 5000)
    props.keep_all_faces = True
    assert (properties.face_limit(props), properties.decimate_limit(props)) == (0, 0)


def test_agreement_colours_reach_the_render_material(addon, tmp_path: Path) -> None:
    mesh_build = addon_module("scene.mesh_build")
    paths = [write_grid(tmp_path / f"out_s{i}.npz", 10)[0] for i in range(2)]
    objs = list(mesh_build.build_results(bpy.context.scene, paths, "hGCA test").objects)
    assert mesh_build.color_results_by(objs, mesh_build.AGREEMENT_COLOR) == 2
    mat = objs[0].data.materials[0]
    bsdf = next(n for n in mat.node_tree.nodes if n.bl_idname == "ShaderNodeBsdfPrincipled")
    (link,) = bsdf.inputs["Base Color"].links
    assert link.from_node.bl_idname == "ShaderNodeVertexColor"
    assert link.from_node.layer_name == mesh_build.AGREEMENT_COLOR
    assert mesh_build.color_results_by(objs, mesh_build.OBSERVED_COLOR) == 2
    (link,) = bsdf.inputs["Base Color"].links
    assert link.from_node.bl_idname == "ShaderNodeValToRGB"
