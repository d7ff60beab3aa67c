"""Looking through a completion's k samples: step from one to the next, and colour them by what was generated or
by how many samples agree. Both change only how the add-on's own result objects are shown."""
from __future__ import annotations

import bpy
from bpy.props import EnumProperty, IntProperty

from ..scene import mesh_build

SAMPLE_KEY = "hgca_sample"


def run_objects(obj: bpy.types.Object | None) -> list[bpy.types.Object]:
    """The result objects of the run `obj` belongs to, in sample order ([] when it is no result)."""
    if obj is None or obj.get(mesh_build.ROLE_KEY) != "result" or SAMPLE_KEY not in obj:
        return []
    for coll in obj.users_collection:  # a run's samples share its collection
        found = [o for o in coll.objects if o.get(mesh_build.ROLE_KEY) == "result" and SAMPLE_KEY in o]
        if found:
            return sorted(found, key=lambda o: int(o[SAMPLE_KEY]))
    return [obj]


def show_only(context: bpy.types.Context, objects: list[bpy.types.Object], keep: bpy.types.Object) -> None:
    """Show `keep` (viewport and render) and hide its siblings; `keep` becomes the active object."""
    for o in objects:
        hidden = o is not keep
        o.hide_render = hidden
        o.hide_set(hidden, view_layer=context.view_layer)
    context.view_layer.objects.active = keep


class HGCA_OT_step_sample(bpy.types.Operator):
    """Show the next (or previous) sample of this completion and hide the others"""

    bl_idname = "hgca.step_sample"
    bl_label = "Step Sample"
    bl_options = {"REGISTER", "UNDO"}

    step: IntProperty(default=1)

    @classmethod
    def poll(cls, context: bpy.types.Context) -> bool:
        return len(run_objects(context.active_object)) > 1

    def execute(self, context: bpy.types.Context) -> set[str]:
        objects = run_objects(context.active_object)
        i = objects.index(context.active_object)
        keep = objects[(i + self.step) % len(objects)]
        show_only(context, objects, keep)
        self.report({"INFO"}, f"Showing sample {int(keep[SAMPLE_KEY])} of {len(objects)}")
        return {"FINISHED"}


class HGCA_OT_result_colors(bpy.types.Operator):
    """Colour this completion's meshes in Solid view (colour = Attribute) by observed/generated or by agreement"""

    bl_idname = "hgca.result_colors"
    bl_label = "Result Colours"
    bl_options = {"REGISTER", "UNDO"}

    mode: EnumProperty(items=[("OBSERVED", "Observed / Generated", "Grey near the scan, orange where generated"),
                              ("AGREEMENT", "Agreement", "How many of the k samples put a surface there")])

    @classmethod
    def poll(cls, context: bpy.types.Context) -> bool:
        return bool(run_objects(context.active_object))

    def execute(self, context: bpy.types.Context) -> set[str]:
        name = mesh_build.OBSERVED_COLOR if self.mode == "OBSERVED" else mesh_build.AGREEMENT_COLOR
        changed = mesh_build.color_results_by(run_objects(context.active_object), name)
        if not changed:
            self.report({"WARNING"}, "agreement needs a completion with 2 or more samples")
            return {"CANCELLED"}
        return {"FINISHED"}


CLASSES = (HGCA_OT_step_sample, HGCA_OT_result_colors)

register, unregister = bpy.utils.register_classes_factory(CLASSES)
