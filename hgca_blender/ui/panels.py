"""The "hGCA" tab in the 3D viewport's sidebar (N panel)."""
from __future__ import annotations

import bpy

from ..jobs import completion
from ..operators import poses, recordings, results
from ..scene import georef, mesh_build


class _SidebarTab:
    """Where every hGCA panel lives: the "hGCA" tab of the 3D viewport's sidebar."""

    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "hGCA"


class _Section(_SidebarTab):
    """A section under the main panel, closed until opened (its settings drawn by `split`)."""

    bl_parent_id = "HGCA_PT_main"
    bl_options = {"DEFAULT_CLOSED"}


def split(layout: bpy.types.UILayout) -> bpy.types.UILayout:
    """`layout` with its settings as label / value columns."""
    layout.use_property_split = True
    return layout


def draw_point_size(layout: bpy.types.UILayout, obj: bpy.types.Object | None) -> None:
    """The active scan's point radius: the input of its "hGCA Points" modifier (a display setting only)."""
    if obj is None or obj.get(mesh_build.ROLE_KEY) != "scan":
        return
    for mod in obj.modifiers:
        group = mod.node_group if mod.type == "NODES" else None
        item = group.interface.items_tree.get(mesh_build.RADIUS_INPUT) if group is not None else None
        if item is not None and group.get(mesh_build.ROLE_KEY) == "points":
            layout.prop(mod, f'["{item.identifier}"]', text="Point Radius")
            as_points = group.interface.items_tree.get(mesh_build.RENDER_POINTS_INPUT)
            if as_points is not None:
                layout.prop(mod, f'["{as_points.identifier}"]', text="Render as Points")
            return


def draw_georef(layout: bpy.types.UILayout, scene: bpy.types.Scene) -> None:
    """The scene's georeference origin and CRS (BlenderGIS's keys), and the button that sets them."""
    box = layout.box()
    crs = scene.get(georef.GIS_CRS)
    if georef.has_origin(scene):
        try:
            x, y, z = georef.scene_origin(scene)
            box.label(text=f"Origin {x:.3f}, {y:.3f}, {z:.3f}", icon="WORLD")
        except ValueError as exc:
            box.label(text=str(exc), icon="ERROR")
    else:
        box.label(text="No georeference origin", icon="WORLD")
    if crs:
        box.label(text=f"CRS {georef.short_crs(str(crs))}")
    box.operator("hgca.set_origin", icon="ORIENTATION_GLOBAL")


def draw_results(layout: bpy.types.UILayout, obj: bpy.types.Object | None) -> None:
    """For an active completion result: which sample it is, stepping through them, and its colours."""
    objects = results.run_objects(obj)
    if not objects:
        return
    col = layout.column(heading="Result")
    row = col.row(align=True)
    row.operator("hgca.step_sample", text="", icon="TRIA_LEFT").step = -1
    row.label(text=f"Sample {int(obj[results.SAMPLE_KEY])} of {len(objects)}")
    row.operator("hgca.step_sample", text="", icon="TRIA_RIGHT").step = 1
    row = col.row(align=True)
    row.operator("hgca.result_colors", text="Generated").mode = "OBSERVED"
    row.operator("hgca.result_colors", text="Agreement").mode = "AGREEMENT"
    mod = obj.modifiers.get(mesh_build.DECIMATE_MODIFIER)
    if mod is not None and mod.type == "DECIMATE":
        col.prop(mod, "ratio", text="Decimate Ratio")
        col.label(text=f"{mod.face_count:,} of {len(obj.data.polygons):,} triangles shown")


class HGCA_PT_main(_SidebarTab, bpy.types.Panel):
    bl_idname = "HGCA_PT_main"
    bl_label = "hGCA Scene Completion"

    def draw(self, context: bpy.types.Context) -> None:
        layout = self.layout
        props = context.scene.hgca
        layout.use_property_split = True
        layout.use_property_decorate = False

        col = layout.column(heading="Source")
        col.prop(props, "source_mode", expand=True)
        if props.source_mode == "COLLECTION":
            col.prop(props, "source_collection")
        else:
            n = sum(1 for o in context.selected_objects if o.type in {"MESH", "POINTCLOUD"})
            col.label(text=f"{n} selected object(s)")

        folder = getattr(context.scene, poses.FOLDER_PROPERTY, "")
        if folder.strip() and recordings.missing_poses(bpy.path.abspath(folder)):   # an import found no poses
            poses.draw_poses(layout, context)
        draw_point_size(layout, context.active_object)
        draw_results(layout, context.active_object)

        col = layout.column(heading="Region")
        col.prop(props, "region_mode", expand=True)
        if props.region_mode == "BOX":
            col.prop(props, "region_object")
        else:
            col.prop(props, "region_center")
            col.prop(props, "region_size")
            col.prop(props, "region_yaw")
        col.operator("hgca.add_region_box", icon="CUBE")
        draw_georef(layout, context.scene)

        col = layout.column()
        col.prop(props, "samples")
        col.prop(props, "seed")
        col.prop(props, "stage")
        col.prop(props, "quality")
        row = col.row(heading="Max Faces", align=True)
        row.prop(props, "keep_all_faces", text="All")
        sub = row.row(align=True)
        sub.active = not props.keep_all_faces
        sub.prop(props, "max_faces", text="")
        row = col.row()
        row.active = not props.keep_all_faces
        row.prop(props, "face_limit_mode", expand=True)
        col.prop(props, "semantics")
        row = col.row()
        row.active = props.semantics
        row.prop(props, "class_collections")
        col.prop(props, "device")


class HGCA_PT_advanced(_Section, bpy.types.Panel):
    bl_label = "Advanced"

    def draw(self, context: bpy.types.Context) -> None:
        layout = split(self.layout)
        props = context.scene.hgca
        layout.prop(props, "t1")
        row = layout.row()
        row.enabled = props.stage == "full"
        row.prop(props, "t2")


_SIZES: dict[str, tuple[float, int | None]] = {}   # folder -> (when measured, bytes): redraws reuse it for 5 s
SIZE_EVERY_S = 5.0


def folder_size(folder: str) -> int | None:
    """Bytes the drive folder holds (its tile cache, meshes and record), None when it does not exist; measured at
    most every SIZE_EVERY_S seconds, since the panel redraws often."""
    import os
    import time

    now = time.monotonic()
    when, size = _SIZES.get(folder, (-1e9, None))
    if now - when < SIZE_EVERY_S:
        return size
    size = None
    if os.path.isdir(folder):
        size = 0
        for root, _dirs, files in os.walk(folder):
            for name in files:
                try:
                    size += os.path.getsize(os.path.join(root, name))
                except OSError:
                    pass
    _SIZES[folder] = (now, size)
    return size


class HGCA_PT_drive(_Section, bpy.types.Panel):
    """Complete along drive: tiles along the sources' sensor path, kept in a folder, resumable."""

    bl_label = "Complete Along Drive"

    def draw(self, context: bpy.types.Context) -> None:
        layout = split(self.layout)
        layout.use_property_decorate = False
        props = context.scene.hgca
        layout.prop(props, "drive_dir")
        from ..operators.drive import drive_folder

        folder = drive_folder(context)
        used = folder_size(folder)
        layout.label(text=f"{folder}: {used / 2**20:,.0f} MiB" if used is not None else f"{folder}: empty",
                     icon="FILE_FOLDER")
        layout.prop(props, "drive_tile_size")
        layout.prop(props, "drive_overlap")
        layout.prop(props, "drive_workers")
        job = completion.active_job(context.scene.name)
        row = layout.row(align=True)
        row.enabled = job is None
        row.operator("hgca.drive_plan", icon="CUBE")
        row.operator("hgca.drive", icon="PLAY")
        states = getattr(job, "tile_states", None)
        if states:
            counts = {s: sum(v == s for v in states.values()) for s in ("done", "cached", "running", "queued")}
            layout.label(text=", ".join(f"{n} {s}" for s, n in counts.items() if n) + f" of {len(states)} tiles",
                         icon="INFO")


class HGCA_PT_poses(_Section, bpy.types.Panel):
    """Estimate Poses for a folder of sweeps that has none (LiDAR odometry, written to the folder's poses.json)."""

    bl_label = "Estimate Poses"

    def draw(self, context: bpy.types.Context) -> None:
        poses.draw_poses(self.layout, context)


class HGCA_PT_job(_SidebarTab, bpy.types.Panel):
    bl_label = "Job"
    bl_parent_id = "HGCA_PT_main"
    bl_options = {"HIDE_HEADER"}

    def draw(self, context: bpy.types.Context) -> None:
        layout = self.layout
        props = context.scene.hgca
        running = completion.active_job(context.scene.name) is not None
        row = layout.row(align=True)
        row.scale_y = 1.4
        if running:
            row.operator("hgca.cancel", icon="CANCEL")
            if hasattr(layout, "progress"):
                layout.progress(factor=props.progress, type="BAR", text=props.status or "Running")
            else:
                layout.prop(props, "progress", slider=True, text=props.status or "Running")
        else:
            row.operator("hgca.complete", icon="PLAY").preview = False
            row.operator("hgca.complete", text="Preview", icon="HIDE_OFF").preview = True
            if props.status:
                layout.label(text=props.status, icon="ERROR" if props.status_is_error else "INFO")


CLASSES = (HGCA_PT_main, HGCA_PT_advanced, HGCA_PT_drive, HGCA_PT_poses, HGCA_PT_job)


register, unregister = bpy.utils.register_classes_factory(CLASSES)
