"""Set the scene's georeference origin and CRS from the panel (the keys BlenderGIS reads: `crs`, `crs x`, `crs y`).

Numbers are typed as text and kept as float64: a Blender float property is float32, which holds a UTM northing
only to half a metre. The origin can be set only while the scene holds nothing the add-on placed, since those
objects lie relative to it: changing it under them would move every one of them in the world.
"""
from __future__ import annotations

from decimal import Decimal, InvalidOperation

import bpy
from bpy.props import StringProperty

from ..scene import georef, mesh_build


def placed_objects(scene: bpy.types.Scene) -> list[str]:
    """Names of the scene's objects that the add-on placed relative to the origin."""
    return sorted(o.name for o in scene.objects if o.get(mesh_build.ROLE_KEY) in {"scan", "result", "region"})


def parse_origin(x: str, y: str, z: str) -> list[float]:
    """Three finite numbers from text (ValueError naming the bad one)."""
    values = []
    for axis, text in zip("xyz", (x, y, z)):
        try:
            value = Decimal(text.strip() or "0")
        except InvalidOperation:
            raise ValueError(f"origin {axis} is not a number: {text!r}") from None
        if not value.is_finite() or abs(value) > Decimal("1e9"):
            raise ValueError(f"origin {axis} must be a finite number within 1e9 m, got {text!r}")
        values.append(float(value))
    return values


class HGCA_OT_set_origin(bpy.types.Operator):
    """Set the scene's georeference origin (world coordinates of Blender's 0, 0, 0) and its CRS"""

    bl_idname = "hgca.set_origin"
    bl_label = "Set Georeference Origin"
    bl_options = {"REGISTER", "UNDO"}

    x: StringProperty(name="X (Easting)", description="World x of Blender's origin, in the CRS's unit")
    y: StringProperty(name="Y (Northing)", description="World y of Blender's origin, in the CRS's unit")
    z: StringProperty(name="Z", default="0", description="World z of Blender's origin")
    crs: StringProperty(name="CRS", description='The coordinate reference system, e.g. "EPSG:32617" (may be empty)')

    def invoke(self, context: bpy.types.Context, event: bpy.types.Event) -> set[str]:
        scene = context.scene
        if georef.has_origin(scene):
            try:
                self.x, self.y, self.z = (repr(float(v)) for v in georef.scene_origin(scene))
            except ValueError:
                pass
        self.crs = str(scene.get(georef.GIS_CRS, ""))
        return context.window_manager.invoke_props_dialog(self)

    def execute(self, context: bpy.types.Context) -> set[str]:
        scene = context.scene
        try:
            origin = parse_origin(self.x, self.y, self.z)
        except ValueError as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        placed = placed_objects(scene)
        if placed and (not georef.has_origin(scene) or list(georef.scene_origin(scene)) != origin):
            self.report({"ERROR"}, f"the scene holds {len(placed)} object(s) placed relative to the current origin "
                                   f"({', '.join(placed[:3])}{', ...' if len(placed) > 3 else ''}): set the origin "
                                   "in a scene without them")
            return {"CANCELLED"}
        scene[georef.ORIGIN_KEY] = origin
        scene[georef.GIS_X], scene[georef.GIS_Y] = origin[0], origin[1]
        crs = self.crs.strip()
        if crs:
            scene[georef.GIS_CRS] = crs
        elif georef.GIS_CRS in scene:
            del scene[georef.GIS_CRS]
        self.report({"INFO"}, f"Georeference origin {origin[0]!r}, {origin[1]!r}, {origin[2]!r}"
                              + (f" ({georef.short_crs(crs)})" if crs else ""))
        return {"FINISHED"}


CLASSES = (HGCA_OT_set_origin,)

register, unregister = bpy.utils.register_classes_factory(CLASSES)
