"""hGCA panel operators: add a region box, start a completion job, cancel it.

"Complete" only gathers inputs and starts a `completion.CompletionJob`; the meshes are built later on the
main thread by `poll_once()` (driven by a timer in the UI), in slices of at most `result_insert.SLICE_S`; Esc or
Cancel then removes what was added so far.
"""
from __future__ import annotations

import math

import bpy

from .. import preferences, properties
from ..jobs import background, completion, core, default_region, job_inputs
from ..scene import georef, region, sources
from .watch import JobWatching


def _scene_props(context: bpy.types.Context):
    return context.scene.hgca


def refuse_start(op: bpy.types.Operator, context: bpy.types.Context, exc: Exception) -> set[str]:
    """A job that could not start: the reason on the panel's status line (in red) and in Blender's report."""
    props = _scene_props(context)
    props.status = f"Error: {exc}"
    props.status_is_error = True
    op.report({"ERROR"}, str(exc))
    return {"CANCELLED"}


def source_objects(context: bpy.types.Context) -> list[bpy.types.Object]:
    """The objects the panel's source settings name (the region box is never a source)."""
    props = _scene_props(context)
    box = props.region_object if props.region_mode == "BOX" else None
    if props.source_mode == "COLLECTION":
        if props.source_collection is None:
            raise sources.SourceError("choose a source collection")
        return sources.collection_sources(props.source_collection, exclude=box)
    return sources.selected_sources(context, exclude=box)


def panel_region(context: bpy.types.Context) -> region.Region:
    """The panel's region in world coordinates (the CLI's --region): a box made by Add Region Box and left where
    it stands gives the exact region `hgca region` gave, not its float32 transform."""
    props = _scene_props(context)
    if props.region_mode == "BOX":
        if props.region_object is None:
            raise region.RegionError("no region box: click 'Add Region Box' or pick an object")
        return region.world_region_of(context.scene, props.region_object)
    return georef.region_to_world(context.scene, region.region_from_numbers(
        tuple(props.region_center), tuple(props.region_size), props.region_yaw))


def gather_params(context: bpy.types.Context, preview: bool = False) -> completion.CompletionParams:
    """Everything the panel says, turned into job parameters (raises with a user-facing message). Points and
    region go to the core in world coordinates: Blender's plus the scene's georeference origin (float64), the
    points with their sensor origins; an unchanged imported scan goes as its files (`job_inputs`)."""
    props = _scene_props(context)
    scene = context.scene
    objects = source_objects(context)
    sources.world_points(objects)  # refuses an empty selection or objects without points, with the reason
    return completion.CompletionParams(
        python=preferences.core_python(context), **job_inputs.source_inputs(scene, objects),
        region=panel_region(context),
        # Preview: one sample of the fast coarse chain as a smooth surface, whatever the panel's stage says
        samples=1 if preview else props.samples, seed=props.seed, stage="preview" if preview else props.stage,
        quality="fast" if preview else props.quality, device=props.device,
        t1=props.t1, t2=props.t2, max_faces=properties.face_limit(props),
        decimate_to=properties.decimate_limit(props), semantics=props.semantics,
        class_collections=props.semantics and props.class_collections, scene_name=context.scene.name,
        extra_args=preferences.core_extra_args(context))


def place_region_box(scene: bpy.types.Scene, collection: bpy.types.Collection, world: region.Region,
                     names: list[str]) -> str:
    """The box of world region `world` in `scene`, made the panel's region; returns the report line."""
    props = scene.hgca
    box_region = georef.region_to_scene(scene, world)
    box = region.create_region_box(collection, box_region, world=world)
    props.region_object = box
    props.region_mode = "BOX"
    props.region_center = box_region[:3]
    props.region_yaw = math.radians(box_region[6])
    shown = ", ".join(f"'{n}'" for n in names[:3]) + (f" and {len(names) - 3} more" if len(names) > 3 else "")
    return f"Added '{box.name}' around {shown}"


def start_region_box(context: bpy.types.Context) -> None:
    """Begin Add Region Box in the interface (returns at once): the scene is read here, `hgca region` (3-5 s: the
    core's Python starting, the scan read) answers on a thread, and the box is added on the main thread
    (`background`; `background.poll("region_box")` outside the interface). Raises CoreError / SourceError /
    RegionError for what can be said at once."""
    import shutil
    import tempfile
    from pathlib import Path

    if background.busy("region_box"):
        raise RuntimeError("Add Region Box is still running")
    objs = source_objects(context)
    sources.world_points(objs)   # refuses an empty selection or objects without points, with the reason
    python = preferences.core_python(context)
    core.check_python(python)
    folder = Path(tempfile.mkdtemp(prefix="hgca_region_"))
    try:
        args = default_region.region_request(context.scene, objs, tuple(context.scene.hgca.region_size), folder)
    except Exception:
        shutil.rmtree(folder, ignore_errors=True)
        raise
    scene_name, names = context.scene.name, [o.name for o in objs]
    collection = (context.collection or context.scene.collection).name

    def work() -> region.Region:
        try:
            return default_region.ask_core(python, args, folder)
        finally:
            shutil.rmtree(folder, ignore_errors=True)

    def finish(world: region.Region) -> str:
        scene = bpy.data.scenes[scene_name]
        return place_region_box(scene, bpy.data.collections.get(collection) or scene.collection, world, names)

    background.start("region_box", "Add Region Box", work, finish)


class HGCA_OT_add_region_box(bpy.types.Operator):
    """Add the box `hgca region` gives around the source points: centred on the sensor, 1 m below the ground"""

    bl_idname = "hgca.add_region_box"
    bl_label = "Add Region Box"
    bl_options = {"REGISTER", "UNDO"}

    def execute(self, context: bpy.types.Context) -> set[str]:
        props = _scene_props(context)
        try:
            if context.window is not None and not bpy.app.background:
                start_region_box(context)   # the core answers on a thread; a timer adds the box
                self.report({"INFO"}, "Placing the region box ...")
                return {"FINISHED"}
            objs = source_objects(context)
            sources.world_points(objs)   # refuses an empty selection or objects without points, with the reason
            world = default_region.default_world_region(preferences.core_python(context), context.scene, objs,
                                                        tuple(props.region_size))
        except (core.CoreError, sources.SourceError, region.RegionError, RuntimeError) as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        text = place_region_box(context.scene, context.collection or context.scene.collection, world,
                                [o.name for o in objs])
        self.report({"INFO"}, text)
        return {"FINISHED"}


class HGCA_OT_complete(JobWatching, bpy.types.Operator):
    """Complete the source scans inside the region with hGCA (runs in the background; Esc cancels)"""

    bl_idname = "hgca.complete"
    bl_label = "Complete"

    preview: bpy.props.BoolProperty(
        name="Preview", default=False, options={"SKIP_SAVE"},
        description="One sample of the fast coarse chain as a smooth surface, in seconds: to decide where the "
                    "region goes before a full completion")
    cancel_message = "hGCA completion cancelled (Esc)"

    @classmethod
    def description(cls, context: bpy.types.Context, properties) -> str:
        if properties.preview:
            return ("Preview the region in seconds: one sample of the fast coarse chain as a smooth surface "
                    "(runs in the background; Esc cancels)")
        return cls.__doc__

    @classmethod
    def poll(cls, context: bpy.types.Context) -> bool:
        return context.scene is not None and completion.active_job(context.scene.name) is None

    def execute(self, context: bpy.types.Context) -> set[str]:
        try:
            params = gather_params(context, preview=self.preview)
            job = completion.start_job(params)
        except (core.CoreError, sources.SourceError, region.RegionError) as exc:
            return refuse_start(self, context, exc)
        completion.ensure_timer()
        self.report({"INFO"}, f"hGCA started on {len(params.points):,} points (process {job.pid})")
        return {"FINISHED"}


class HGCA_OT_cancel(bpy.types.Operator):
    """Stop the running completion; nothing is added to the scene (results going in are removed again)"""

    bl_idname = "hgca.cancel"
    bl_label = "Cancel"

    @classmethod
    def poll(cls, context: bpy.types.Context) -> bool:
        return context.scene is not None and completion.active_job(context.scene.name) is not None

    def execute(self, context: bpy.types.Context) -> set[str]:
        job = completion.active_job(context.scene.name)
        if job is None:
            return {"CANCELLED"}
        job.cancel()
        completion.poll_all()
        self.report({"INFO"}, "hGCA completion cancelled")
        return {"FINISHED"}


CLASSES = (HGCA_OT_add_region_box, HGCA_OT_complete, HGCA_OT_cancel)


register, unregister = bpy.utils.register_classes_factory(CLASSES)
