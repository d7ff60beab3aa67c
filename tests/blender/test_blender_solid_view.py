"""What Solid view shows: Workbench (its renderer) with colour = Attribute paints scans and results in their colours.

Workbench colours only meshes by a colour attribute; a Geometry Nodes point cloud comes out in its material's
grey. So a scan's viewport shapes must be a mesh that keeps the scan's active colour attribute.
"""
from __future__ import annotations

from pathlib import Path

import bpy
import numpy as np

from bl_helpers import addon_module, ply_rgb, workbench_pixels

RED_POINT = ply_rgb([(0, 0, 0, 255, 0, 0)])
SIZE = 32


def covered(pixels: np.ndarray) -> np.ndarray:
    """(K, 3) colours of the pixels the object covers fully (the background is transparent)."""
    return pixels[pixels[..., 3] > 0.99][:, :3]


def import_red_point(tmp_path: Path) -> bpy.types.Object:
    path = tmp_path / "red.ply"
    path.write_text(RED_POINT)
    assert bpy.ops.import_scene.hgca_lidar(filepath=str(path), point_size=1.6) == {"FINISHED"}
    (obj,) = bpy.data.objects
    return obj


def test_scan_shows_as_a_mesh_with_its_colour_attribute_in_the_viewport(addon, tmp_path: Path) -> None:
    obj = import_red_point(tmp_path)
    shown = obj.evaluated_get(bpy.context.evaluated_depsgraph_get()).data
    assert len(shown.polygons) > 0  # a mesh with faces, not a point cloud
    assert shown.color_attributes.active_color_name == addon_module("scene.colors").COLOR_ATTRIBUTE


def test_solid_view_paints_a_scan_in_its_colour(addon, tmp_path: Path) -> None:
    """The viewport shapes, rendered by Workbench ("Render as Points" off), are red, not the material's grey."""
    obj = import_red_point(tmp_path)
    assert addon_module("scene.mesh_build").set_render_points(obj, False)
    rgb = covered(workbench_pixels(tmp_path, SIZE))
    assert len(rgb) >= 4, "the scan's shapes cover no pixel"
    r, g, b = np.median(rgb, axis=0)
    assert r > 0.8 and g < 0.3 and b < 0.3, (r, g, b)


def test_renders_keep_round_points_by_default(addon, tmp_path: Path) -> None:
    """With "Render as Points" on (the default), a render draws the point cloud, which Workbench greys."""
    import_red_point(tmp_path)
    rgb = covered(workbench_pixels(tmp_path, SIZE))
    assert len(rgb) >= 4
    r, g, b = np.median(rgb, axis=0)
    assert abs(r - g) < 0.05 and abs(g - b) < 0.05, (r, g, b)
