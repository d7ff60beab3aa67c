"""Per-scene settings of the hGCA panel (`scene.hgca`), and the job's progress shown there."""

import bpy
from bpy.props import (BoolProperty, EnumProperty, FloatProperty, FloatVectorProperty, IntProperty,
                       PointerProperty, StringProperty)

from . import settings as core

# Every default, bound and choice of a core setting below comes from the core's schema (`settings`, made from
# `hgca_core.config` by the extension build); only the labels and descriptions are the panel's own.
MIN_FACES = core.low("max_faces")  # the core's smallest face limit (hgca complete --max-faces: 0 or at least this)



def face_limit(props: "HGCA_PG_scene") -> int:
    """The `--max-faces` the settings ask for: 0 keeps every triangle (also when a modifier shows Max Faces)."""
    return 0 if props.keep_all_faces or props.face_limit_mode == "MODIFIER" else int(props.max_faces)


def decimate_limit(props: "HGCA_PG_scene") -> int:
    """The triangles a Decimate modifier on each result shows (0: no modifier)."""
    return int(props.max_faces) if props.face_limit_mode == "MODIFIER" and not props.keep_all_faces else 0


class HGCA_PG_scene(bpy.types.PropertyGroup):
    """Settings of one completion; stored with the scene so they survive saving the file."""

    source_mode: EnumProperty(
        name="Source",
        items=[("SELECTED", "Selected", "Use the selected point objects (or the active one)"),
               ("COLLECTION", "Collection", "Use every point object in a collection")],
        default="SELECTED",
    )
    source_collection: PointerProperty(name="Collection", type=bpy.types.Collection,
                                       description="Collection whose point objects are completed")

    region_mode: EnumProperty(
        name="Region",
        items=[("BOX", "Box Object", "Use an object's box (move, rotate about Z and scale it)"),
               ("NUMBERS", "Numbers", "Type the centre, size and yaw")],
        default="BOX",
    )
    # No `poll` filter here: on Blender 4.2 a PointerProperty poll callback makes Blender crash on quit once the
    # extension was uninstalled (fixed by 4.5). `region.region_from_object` refuses objects without a box.
    region_object: PointerProperty(name="Box", type=bpy.types.Object,
                                   description="Object whose bounding box is the completion region (a mesh or an empty)")
    region_center: FloatVectorProperty(name="Centre", size=3, subtype="TRANSLATION", unit="LENGTH",
                                       description="Centre of the region (scene coordinates: relative to the hGCA georeference origin, if any)")
    region_size: FloatVectorProperty(name="Size", size=3, default=core.REGION_SIZE, min=0.1, subtype="XYZ",
                                     unit="LENGTH", description="Size of the region")
    region_yaw: FloatProperty(name="Yaw", subtype="ANGLE", description="Rotation of the region about Z")

    samples: IntProperty(name="Samples", default=core.default("samples"), min=core.low("samples"),
                         max=core.high("samples"), soft_max=8,
                         description="Number of completions (one mesh each, different seeds)")
    seed: IntProperty(name="Seed", default=core.default("seed"), min=core.low("seed"), max=core.high("seed"),
                      description="Same seed and input give the same mesh")
    stage: EnumProperty(
        name="Stage",
        items=[("preview", "Preview", "The coarse 20 cm cells as a smooth surface, in seconds: to decide where "
                                      "the region goes"),
               ("coarse", "Coarse", "Coarse 20 cm stage only, as cubes (fast)"),
               ("full", "Full", "Coarse and fine stages")],
        default=core.default("stage"),
    )
    quality: EnumProperty(
        name="Quality",
        items=[("fast", "Fast", "The few-step students (T1 10, T2 5): several times faster"),
               ("best", "Best", "The paper's chains (T1 30, T2 15)")],
        default=core.default("quality"),
    )
    device: EnumProperty(
        name="Device",
        items=[("cpu", "CPU", "Run the model on the CPU"), ("cuda", "CUDA", "Run the model on an NVIDIA GPU")],
        default=core.default("device"),
    )
    show_advanced: BoolProperty(name="Advanced", default=False)
    t1: IntProperty(name="T1", default=core.default("t1"), min=core.low("t1"), max=core.high("t1"), soft_max=100,
                    description="Coarse GCA steps (0: the weights' own count, 30 at Best quality, 10 at Fast)")
    t2: IntProperty(name="T2", default=core.default("t2"), min=core.low("t2"), max=core.high("t2"), soft_max=100,
                    description="Fine cGCA steps (0: the weights' own count, 15 at Best quality, 5 at Fast)")
    # No `update` callback: on Blender 4.2 a scene property's callback crashes Blender on quit once the
    # extension was uninstalled. The core takes 0 (keep all) or >= MIN_FACES: a toggle and a hard minimum.
    keep_all_faces: BoolProperty(name="Keep All Faces", default=False,
                                 description="Keep every triangle (a default region's full-stage mesh has "
                                             "1.9-3.1 million) instead of simplifying to Max Faces")
    max_faces: IntProperty(name="Max Faces", default=core.default("max_faces"), min=MIN_FACES, soft_max=10_000_000,
                           description="Simplify each completed mesh to at most this many triangles")
    face_limit_mode: EnumProperty(
        name="Simplify", default="BAKE",
        items=[("BAKE", "Bake", "The core simplifies each mesh to Max Faces: smaller files, the rest is gone"),
               ("MODIFIER", "Modifier", "Keep every triangle and show Max Faces through a Decimate modifier: "
                                        "tune its ratio live, apply or remove it (larger files)")])

    semantics: BoolProperty(name="Classes", default=False,
                            description="Label every face with its class (road, sidewalk, building, car, tree, "
                                        "pole, ...) and give each class a material whose colour you can change")
    class_collections: BoolProperty(name="Collection per Class", default=False,
                                    description="Also split each labelled result into one collection per class")

    drive_dir: StringProperty(name="Drive Folder", subtype="DIR_PATH", default="",
                              description="Folder the drive's tiles are kept in (running again resumes; empty: "
                                          "hgca_drive beside the saved .blend, else in the temporary folder)")
    drive_tile_size: FloatProperty(name="Tile Size", default=core.default("drive_tile_size"),
                                   min=max(4.0, core.low("drive_tile_size")), soft_max=80.0, unit="LENGTH",
                                   description="Side of each square tile along the trajectory")
    drive_overlap: FloatProperty(name="Overlap", default=core.default("drive_overlap"),
                                 min=max(0.5, core.low("drive_overlap")), soft_max=20.0, unit="LENGTH",
                                 description="Overlap of consecutive tiles (the seams are conditioned across it)")
    drive_workers: IntProperty(name="Workers", default=core.default("drive_workers"), min=core.low("drive_workers"),
                               max=core.high("drive_workers"), soft_max=16,
                               description="Tiles at once (more than 1 runs them on a local Ray: needs hgca[ray])")

    progress: FloatProperty(name="Progress", default=0.0, min=0.0, max=1.0, subtype="FACTOR")
    status: StringProperty(name="Status", default="")
    status_is_error: BoolProperty(name="Error", default=False)


CLASSES = (HGCA_PG_scene,)


def register() -> None:
    for cls in CLASSES:
        bpy.utils.register_class(cls)
    bpy.types.Scene.hgca = PointerProperty(type=HGCA_PG_scene)


def unregister() -> None:
    del bpy.types.Scene.hgca
    for cls in reversed(CLASSES):
        bpy.utils.unregister_class(cls)
