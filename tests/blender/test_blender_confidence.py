"""What was generated and how sure the model is, as colour attributes of the result meshes (Solid view draws the
active one with colour = Attribute)."""
from __future__ import annotations

from pathlib import Path

import bpy
import numpy as np

from bl_helpers import addon_module, workbench_pixels


def write_sample(path: Path, vertices: np.ndarray, observed: np.ndarray) -> Path:
    faces = np.arange(len(vertices) - len(vertices) % 3, dtype=np.int32).reshape(-1, 3)
    np.savez(path, vertices=vertices.astype(np.float32), faces=faces, observed_distance=observed.astype(np.float32))
    return path


def colours(mesh: bpy.types.Mesh, name: str) -> np.ndarray:
    out = np.empty(len(mesh.vertices) * 4, dtype=np.float32)
    mesh.color_attributes[name].data.foreach_get("color", out)
    return out.reshape(-1, 4)


def values(mesh: bpy.types.Mesh, name: str) -> np.ndarray:
    out = np.empty(len(mesh.vertices), dtype=np.float32)
    mesh.attributes[name].data.foreach_get("value", out)
    return out


def test_observed_distance_is_the_active_colour(addon, tmp_path: Path) -> None:
    mesh_build = addon_module("scene.mesh_build")
    verts = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], dtype=np.float32)
    out = write_sample(tmp_path / "out_s0.npz", verts, np.array([0.0, 0.175, 5.0]))
    (obj,) = mesh_build.build_results(bpy.context.scene, [out], "hGCA test").objects
    mesh = obj.data
    assert mesh.color_attributes.active_color.name == mesh_build.OBSERVED_COLOR
    rgba = colours(mesh, mesh_build.OBSERVED_COLOR)
    np.testing.assert_allclose(rgba[0, :3], [0.55, 0.57, 0.6], atol=1e-6)   # observed: grey
    np.testing.assert_allclose(rgba[2, :3], [0.95, 0.45, 0.1], atol=1e-6)   # generated: orange
    np.testing.assert_allclose(rgba[1, :3], (rgba[0, :3] + rgba[2, :3]) / 2, atol=1e-6)
    assert mesh_build.AGREEMENT_ATTRIBUTE not in mesh.attributes  # one sample: nothing to agree with


def test_agreement_counts_the_samples_with_surface_there(addon, tmp_path: Path) -> None:
    """Three samples share a wall; one of them adds a far block, another a nearby one (within a cell)."""
    mesh_build = addon_module("scene.mesh_build")
    rng = np.random.default_rng(0)
    wall = np.c_[rng.uniform(0, 4, 300), np.zeros(300), rng.uniform(0, 2, 300)]
    far = wall[:30] + [0, 10, 0]        # only sample 0 has it
    near = wall[:30] + [0, 0.1, 0]      # sample 1's, half a cell beside the wall
    paths = [write_sample(tmp_path / f"out_s{i}.npz", np.r_[wall, extra], np.zeros(len(wall) + len(extra)))
             for i, extra in enumerate((far, near, np.zeros((0, 3))))]
    coll = mesh_build.build_results(bpy.context.scene, paths, "hGCA test")
    meshes = [o.data for o in sorted(coll.objects, key=lambda o: o["hgca_sample"])]
    shares = [values(m, mesh_build.AGREEMENT_ATTRIBUTE) for m in meshes]
    assert np.all(shares[0][:300] == 1.0) and np.allclose(shares[0][300:], 1 / 3)
    assert np.all(shares[1] == 1.0)      # the nearby block lies within a cell of everyone's wall
    assert np.all(shares[2] == 1.0)
    rgba = colours(meshes[0], mesh_build.AGREEMENT_COLOR)
    ramp = addon_module("scene.colors").RAMP
    np.testing.assert_allclose(rgba[0, :3], ramp[-1], atol=1e-6)
    assert not np.allclose(rgba[-1, :3], ramp[-1])


def test_solid_view_draws_the_generated_colour(addon, tmp_path: Path) -> None:
    """Workbench (the Solid view's renderer) with colour = Attribute paints a generated face orange."""
    mesh_build = addon_module("scene.mesh_build")
    verts = np.array([[-1, 0, -1], [1, 0, -1], [0, 0, 1.5]], dtype=np.float32)
    out = write_sample(tmp_path / "out_s0.npz", verts, np.full(3, 5.0))
    mesh_build.build_results(bpy.context.scene, [out], "hGCA test")
    r, g, b, _ = workbench_pixels(tmp_path, 16, distance=6.0)[8, 8]
    assert r > 0.9 and r - b > 0.5 and r > g > b, (r, g, b)  # orange (sRGB of 0.95, 0.45, 0.1), not grey


def test_step_through_samples_and_colour_by_agreement(addon, tmp_path: Path) -> None:
    mesh_build = addon_module("scene.mesh_build")
    verts = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], dtype=np.float32)
    paths = [write_sample(tmp_path / f"out_s{i}.npz", verts + [0, 0, i], np.zeros(3)) for i in range(3)]
    coll = mesh_build.build_results(bpy.context.scene, paths, "hGCA test")
    objs = sorted(coll.objects, key=lambda o: o["hgca_sample"])
    bpy.context.view_layer.objects.active = objs[0]
    assert bpy.ops.hgca.step_sample(step=1) == {"FINISHED"}
    assert bpy.context.view_layer.objects.active is objs[1]
    assert [o.visible_get() for o in objs] == [False, True, False] and not objs[1].hide_render
    assert bpy.ops.hgca.step_sample(step=-2) == {"FINISHED"}
    assert bpy.context.view_layer.objects.active is objs[2]
    assert bpy.ops.hgca.result_colors(mode="AGREEMENT") == {"FINISHED"}
    assert {o.data.color_attributes.active_color.name for o in objs} == {mesh_build.AGREEMENT_COLOR}
    assert bpy.ops.hgca.result_colors(mode="OBSERVED") == {"FINISHED"}
    assert {o.data.color_attributes.active_color.name for o in objs} == {mesh_build.OBSERVED_COLOR}


def test_solid_view_shows_observed_generated_for_several_samples(addon, tmp_path: Path) -> None:
    """With 2 or more samples the agreement attributes are added too; the colour Solid view draws stays the
    observed/generated one on every sample (and renders draw the same one)."""
    mesh_build = addon_module("scene.mesh_build")
    verts = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], dtype=np.float32)
    for k in (2, 3):
        paths = [write_sample(tmp_path / f"k{k}_s{i}.npz", verts + [0, 0, i], np.zeros(3)) for i in range(k)]
        coll = mesh_build.build_results(bpy.context.scene, paths, f"hGCA k{k}")
        for obj in coll.objects:
            attrs = obj.data.color_attributes
            assert attrs.active_color is not None, f"{obj.name}: no active colour attribute"
            assert attrs.active_color_name == mesh_build.OBSERVED_COLOR
            assert attrs[attrs.render_color_index].name == mesh_build.OBSERVED_COLOR
