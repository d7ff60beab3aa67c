"""hGCA panel operators for whole drives: show the planned tiles, complete along the drive.

The scans are the panel's source objects (selected, or a collection), each with the sensor origins its import
stored; the core plans the tiles and runs them (`drive_job`). Cancel is the panel's Cancel (`hgca.cancel`) or Esc
(`watch.JobWatching`, as for a completion): finished tiles stay.
"""
from __future__ import annotations

import tempfile
from pathlib import Path

import bpy

from .. import preferences, properties
from ..jobs import completion, core, drive_job
from ..scene import sources
from . import complete
from .watch import JobWatching


def drive_folder(context: bpy.types.Context) -> str:
    """The drive's folder: the panel's, else hgca_drive beside the saved .blend, else in the temporary folder."""
    props = context.scene.hgca
    if props.drive_dir.strip():
        return bpy.path.abspath(props.drive_dir.strip())
    if bpy.data.filepath:
        return str(Path(bpy.path.abspath("//")) / "hgca_drive")
    return str(Path(tempfile.gettempdir()) / "hgca_drive")


def drive_params(context: bpy.types.Context) -> drive_job.DriveParams:
    """The panel's settings as drive parameters (the scans come from the source objects later)."""
    props = context.scene.hgca
    return drive_job.DriveParams(
        python=preferences.core_python(context), scans=[], out_dir=drive_folder(context), samples=props.samples,
        seed=props.seed, stage=props.stage, quality=props.quality, device=props.device, t1=props.t1, t2=props.t2,
        max_faces=properties.face_limit(props),
        workers=props.drive_workers, tile_size=props.drive_tile_size, overlap=props.drive_overlap,
        scene_name=context.scene.name, extra_args=preferences.core_extra_args(context))


def drive_sources(context: bpy.types.Context) -> list[bpy.types.Object]:
    objs = complete.source_objects(context)
    if not objs:
        raise sources.SourceError("no source objects: select imported scans (or pick a collection) first")
    return objs


class HGCA_OT_drive_plan(bpy.types.Operator):
    """Show where the tiles of a drive through the source scans go (boxes along the sensor's path)"""

    bl_idname = "hgca.drive_plan"
    bl_label = "Show Tiles"
    bl_options = {"REGISTER", "UNDO"}

    def execute(self, context: bpy.types.Context) -> set[str]:
        try:
            if context.window is not None and not bpy.app.background:   # the core plans on a thread: no freeze
                drive_job.start_plan(context.scene, drive_params(context), drive_sources(context))
                self.report({"INFO"}, "Planning the tiles ...")
                return {"FINISHED"}
            collection = drive_job.plan_objects(context.scene, drive_params(context), drive_sources(context))
        except (core.CoreError, sources.SourceError, RuntimeError) as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        self.report({"INFO"}, f"{len(collection.objects)} tiles in '{collection.name}'")
        return {"FINISHED"}


class HGCA_OT_drive(JobWatching, bpy.types.Operator):
    """Complete the whole drive through the source scans, tile by tile (runs in the background; finished tiles
    appear as they are done and stay when cancelled; Esc cancels)"""

    bl_idname = "hgca.drive"
    bl_label = "Complete Along Drive"
    cancel_message = "hGCA drive cancelled (Esc): finished tiles stay"

    @classmethod
    def poll(cls, context: bpy.types.Context) -> bool:
        return context.scene is not None and completion.active_job(context.scene.name) is None

    def execute(self, context: bpy.types.Context) -> set[str]:
        try:
            job = drive_job.start_drive_job(drive_params(context), drive_sources(context))
        except (core.CoreError, sources.SourceError) as exc:
            return complete.refuse_start(self, context, exc)
        completion.ensure_timer()
        self.report({"INFO"}, f"hGCA drive started into {job.params.out_dir} (process {job.pid})")
        return {"FINISHED"}


CLASSES = (HGCA_OT_drive_plan, HGCA_OT_drive)


register, unregister = bpy.utils.register_classes_factory(CLASSES)
