"""Imported scans are coloured (RGB, intensity, height) by a colour attribute and drawn at a size that fits."""
from __future__ import annotations

from pathlib import Path

import bpy
import numpy as np
import pytest

from bl_helpers import FIXTURES, NUSCENES, addon_module, ply_rgb, require_fixture, snapshot

PLY_RGB = ply_rgb([(0, 0, 0, 255, 0, 0), (1, 0, 0, 0, 255, 0), (0, 1, 0, 0, 0, 255), (1, 1, 1, 255, 255, 51)])


def import_one(**kwargs) -> bpy.types.Object:
    before = set(bpy.data.objects.keys())
    assert bpy.ops.import_scene.hgca_lidar(**kwargs) == {"FINISHED"}
    (name,) = set(bpy.data.objects.keys()) - before
    return bpy.data.objects[name]


def colors_of(obj: bpy.types.Object) -> np.ndarray:
    attr = obj.data.color_attributes[addon_module("scene.colors").COLOR_ATTRIBUTE]
    out = np.empty(len(obj.data.vertices) * 4, dtype=np.float32)
    attr.data.foreach_get("color", out)
    return out.reshape(-1, 4)


def test_rgb_scan_keeps_its_colours_as_the_active_colour_attribute(addon, tmp_path: Path) -> None:
    path = tmp_path / "rgb.ply"
    path.write_text(PLY_RGB)
    obj = import_one(filepath=str(path))
    mesh = obj.data
    assert mesh.color_attributes.active_color.name == addon_module("scene.colors").COLOR_ATTRIBUTE
    np.testing.assert_allclose(colors_of(obj)[:, :3], [[1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 0.2]], atol=1e-6)
    material = mesh.materials[0]
    names = [n.attribute_name for n in material.node_tree.nodes if n.bl_idname == "ShaderNodeAttribute"]
    assert names == [addon_module("scene.colors").COLOR_ATTRIBUTE]


def test_sweep_defaults_to_intensity_grey_and_small_points(addon) -> None:
    require_fixture(NUSCENES)
    obj = import_one(filepath=str(NUSCENES))
    rgba = colors_of(obj)
    assert np.array_equal(rgba[:, 0], rgba[:, 1]) and np.array_equal(rgba[:, 1], rgba[:, 2])
    floor = addon_module("scene.colors").INTENSITY_FLOOR
    assert rgba[:, 0].min() >= floor and rgba[:, 0].max() == 1.0
    # readable on the dark viewport: the real sweep's heavy-tailed intensities spread over the grey range (a
    # linear scale between percentiles put its median near black)
    assert 0.4 < np.median(rgba[:, 0]) < 0.75 and np.mean(rgba[:, 0] < 0.2) < 0.2
    assert addon_module("scene.mesh_build").point_radius(obj) == pytest.approx(0.03)


def test_height_ramp_and_chosen_point_size(addon) -> None:
    require_fixture(NUSCENES)
    obj = import_one(filepath=str(NUSCENES), color_by="HEIGHT", point_size=0.1)
    rgba = colors_of(obj)
    z = np.empty(len(obj.data.vertices) * 3, dtype=np.float32)
    obj.data.vertices.foreach_get("co", z)
    z = z.reshape(-1, 3)[:, 2]
    ramp = addon_module("scene.colors").RAMP
    np.testing.assert_allclose(rgba[z.argmin(), :3], ramp[0], atol=1e-6)
    np.testing.assert_allclose(rgba[z.argmax(), :3], ramp[-1], atol=1e-6)
    assert addon_module("scene.mesh_build").point_radius(obj) == pytest.approx(0.05)


def test_aerial_scan_gets_points_as_large_as_its_spacing(addon) -> None:
    path = require_fixture(FIXTURES / "autzen_trim.laz")
    obj = import_one(filepath=str(path))
    radius = addon_module("scene.mesh_build").point_radius(obj)
    assert 0.1 < radius < 2.0  # aerial spacing is decimetres to metres, not a vehicle scan's 3 cm


def test_rgb_asked_of_a_scan_without_colours_adds_nothing(addon) -> None:
    require_fixture(NUSCENES)
    before = snapshot()
    with pytest.raises(RuntimeError, match="no RGB colours"):
        bpy.ops.import_scene.hgca_lidar(filepath=str(NUSCENES), color_by="RGB")
    assert snapshot() == before


def test_colour_scaling_is_robust() -> None:
    colors = pytest.importorskip("hgca_blender.scene.colors")
    sixteen = colors.rgb_of({"red": np.array([65535, 0]), "green": np.array([0, 32768]), "blue": np.array([0, 0])})
    np.testing.assert_allclose(sixteen, [[1, 0, 0], [0, 32768 / 65535, 0]], atol=1e-6)
    values = np.r_[np.linspace(0, 1, 999), 1e6]  # one wild return does not flatten the rest
    assert np.median(colors.normalised(values)) == pytest.approx(0.5, abs=0.02)
    assert colors.normalised(np.full(5, 3.0)).tolist() == [0.5] * 5


def test_las_rgb_is_imported_as_the_scans_colours(addon) -> None:
    """simple.las (point format 3) carries RGB: the import colours by it (stored 8-bit in its 16-bit fields)."""
    import laspy

    path = require_fixture(FIXTURES / "simple.las")
    las = laspy.read(str(path))
    obj = import_one(filepath=str(path))
    want = np.c_[las.red, las.green, las.blue].astype(np.float64) / 255.0
    got = colors_of(obj)[:, :3]
    assert len(got) == len(want)
    np.testing.assert_allclose(got, want, atol=1e-6)
