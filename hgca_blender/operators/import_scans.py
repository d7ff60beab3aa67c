"""File > Import > LiDAR Scan (hgca): read scans with `hgca read` and add them as one point object.

Reading is the core's job (all formats, poses, accumulation, sequence folders: a KITTI sequence, an
Argoverse 2 log or nuScenes sweeps with `--frames`; ROS bags with `--topic`, E57 scans); the add-on only turns
the resulting .npz into a vertex-only mesh with point attributes. On any error nothing is added to the file.
In the interface the core reads on a thread (`background`) and the object is added by a timer, so Blender never
waits on it; scripts and batch runs import synchronously.
"""

import shutil
import tempfile
from pathlib import Path

import bpy
import numpy as np
from bpy.props import BoolProperty, CollectionProperty, EnumProperty, FloatProperty, StringProperty
from bpy_extras.io_utils import ImportHelper

from .. import preferences
from ..jobs import background, core, job_inputs
from ..scene import colors, georef, mesh_build, sources
from . import recordings
from .recordings import NO_TOPIC, bag_of, input_paths, topic_items

EXTENSIONS = (".ply", ".las", ".laz", ".pcd", ".xyz", ".csv", ".txt", ".npy", ".npz", ".bin", ".feather",
              *recordings.CONTAINER_EXTENSIONS)
READ_TIMEOUT_S = 3600


# what `hgca read` writes beside the per-point attributes: the frame and the georeferencing of the whole scan
NOT_ATTRIBUTES = ("points", "origins", "offset", "crs", "unit", "unit_metres")

def object_name(paths: list[Path], frames: str = "") -> str:
    """Name after the first file ("scan", or "scan +4" for five files; drops double suffixes), or after a
    sequence folder, bag or E57 and its frames ("00 [0:5]")."""
    if len(paths) == 1 and paths[0].is_dir():
        return f"{paths[0].name} [{frames}]" if frames else paths[0].name
    stem = paths[0].name
    for suffix in (".pcd.bin", ".copc.laz", *EXTENSIONS):
        if stem.lower().endswith(suffix):
            stem = stem[: -len(suffix)]
            break
    if frames and recordings.is_sequence(paths):
        return f"{stem} [{frames}]"
    return stem if len(paths) == 1 else f"{stem} +{len(paths) - 1}"


def check_inputs(paths: list[Path], poses: Path | None, frames: str, topic: str
                 ) -> tuple[list[Path], Path | None]:
    """Absolute paths (the core runs in a temporary folder; poses then match scans by their resolved paths), and
    the poses (the given ones, else those Estimate Poses wrote for a KITTI / AV2 folder without its own),
    refusing at once what the core would refuse later: missing files, frames or a topic without a sequence."""
    paths = [Path(p).absolute() for p in paths]
    poses = Path(poses).absolute() if poses is not None else None
    folder = len(paths) == 1 and paths[0].is_dir()
    if folder and poses is None:   # a KITTI / AV2 folder placed by Estimate Poses, not by its own table
        poses = recordings.estimated_poses(paths[0])
    missing = [str(p) for p in paths if not (folder or p.is_file())]
    if missing:
        raise core.CoreError(f"file not found: {', '.join(missing)}")
    if frames and not recordings.is_sequence(paths):
        raise core.CoreError("frames apply to a sequence folder, a ROS bag or an E57, not to scan files")
    if topic and not (len(paths) == 1 and recordings.container_kind(paths[0]) == "rosbag"):
        raise core.CoreError("a topic applies to a ROS bag (.bag, .mcap, .db3 or a ROS 2 bag folder)")
    return paths, poses


def read_scans(python: str, paths: list[Path], poses: Path | None = None, frames: str = "", topic: str = ""
               ) -> tuple[np.ndarray, dict[str, np.ndarray], np.ndarray | None, np.ndarray, str | None,
                          dict[str, int]]:
    """Run `hgca read` into a temporary .npz; returns (points (N,3) float32, per-point attributes, sensor
    origins (world, float64) or None, the points' float64 offset: world = points + offset, the CRS the LAS/LAZ
    files declare ("EPSG:n" or WKT) or None, the returns the reader left out by reason, e.g.
    {"returns off the recording vehicle": 8526}). `paths` may be one sequence folder, bag or E57,
    with `frames` START:STOP[:STEP] (empty: the core's default, 5 around the middle) and a bag's `topic`.
    A folder that failed for want of poses says so, and that Estimate Poses makes them."""
    tmpdir = Path(tempfile.mkdtemp(prefix="hgca_read_"))
    try:
        out = tmpdir / "scan.npz"
        args = ["read", *[str(p) for p in paths]]
        if poses is not None:
            args += ["--poses", str(poses)]
        if frames:
            args += ["--frames", frames]
        if topic:
            args += ["--topic", topic]
        try:
            summary = core.run_core_json(python, [*args, "-o", str(out), "--json"], timeout=READ_TIMEOUT_S,
                                         cwd=tmpdir)
        except core.CoreError as exc:
            hint = recordings.poses_hint(paths[0]) if len(paths) == 1 and poses is None else ""
            raise core.CoreError(f"{exc} ({hint})" if hint else str(exc)) from None
        if not out.is_file():
            raise core.CoreError("hgca read finished but wrote no output")
        with np.load(out, allow_pickle=False) as data:
            if "points" not in data.files:
                raise core.CoreError("hgca read wrote no 'points' array")
            points = np.asarray(data["points"])
            offset = np.asarray(data["offset"], dtype=np.float64) if "offset" in data.files else np.zeros(3)
            attributes = {k: np.asarray(data[k]) for k in data.files if k not in NOT_ATTRIBUTES}
            origins = np.asarray(data["origins"], dtype=np.float64) if "origins" in data.files else None
    finally:
        shutil.rmtree(tmpdir, ignore_errors=True)
    if points.ndim != 2 or points.shape[1] != 3 or len(points) == 0:
        raise core.CoreError(f"no points read from {', '.join(p.name for p in paths)}")
    if offset.shape != (3,) or not np.all(np.isfinite(offset)):
        raise core.CoreError(f"hgca read wrote a bad offset {offset.tolist()}")
    dropped = summary.get("dropped") or {}
    if not isinstance(dropped, dict) or not all(isinstance(n, int) for n in dropped.values()):
        raise core.CoreError(f"hgca read printed a bad 'dropped' record {dropped!r}")
    crs = summary.get("crs")
    if crs is not None and not isinstance(crs, str):
        raise core.CoreError(f"hgca read printed a bad 'crs' {crs!r}")
    return points, attributes, origins, offset, crs or None, dropped


def dropped_text(dropped: dict[str, int]) -> str:
    """"left out 8,526 returns off the recording vehicle" (joined by "; "), or "" when the reader kept every row."""
    return "; ".join(f"left out {n:,} {why}" for why, n in dropped.items() if n)


def import_scans(python: str, paths: list[Path], collection: bpy.types.Collection, poses: Path | None = None,
                 name: str = "", show_points: bool = True, scene: bpy.types.Scene | None = None,
                 frames: str = "", color_by: str = "AUTO", point_size: float = 0.0, topic: str = ""
                 ) -> tuple[bpy.types.Object, list[str], dict[str, int]]:
    """Read and add one point object to `collection`, placed relative to `scene`'s georeference origin (set
    here when the scene has none and the scans lie far from zero); returns it, the attributes not stored and the
    returns the reader left out by reason (`read_scans`).
    `paths` is scan files or one sequence folder, bag or E57 (`frames` picks its frames, `topic` a bag's cloud).
    Points are coloured by `color_by` (`colors.MODES`) and drawn `point_size` metres wide (0:
    `colors.default_point_radius` for the data)."""
    paths, poses = check_inputs(paths, poses, frames, topic)
    # a poses path that is no file (missing, a folder, a link loop) is described by `hgca read` itself
    read = read_scans(python, paths, poses, frames, topic)
    return add_scans(read, paths, collection, poses, name, show_points, scene, frames, color_by, point_size,
                     topic)


def add_scans(read: tuple, paths: list[Path], collection: bpy.types.Collection, poses: Path | None = None,
              name: str = "", show_points: bool = True, scene: bpy.types.Scene | None = None, frames: str = "",
              color_by: str = "AUTO", point_size: float = 0.0, topic: str = ""
              ) -> tuple[bpy.types.Object, list[str], dict[str, int]]:
    """The object of what `read_scans` returned (main thread); nothing is added when it refuses."""
    points, attributes, origins, offset, crs, dropped = read
    rgba, _mode = colors.point_colors(color_by, points, attributes)  # before anything is added: may refuse
    scene = scene or bpy.context.scene
    georef.check_crs(scene, crs)
    radius = point_size / 2 if point_size > 0 else colors.default_point_radius(points, origins is not None)
    centre = offset + (points.min(axis=0).astype(np.float64) + points.max(axis=0)) / 2
    previous = georef.origin_keys(scene)
    placed = [o for o in scene.objects if o.get(mesh_build.ROLE_KEY) in ("scan", "result", "region")]
    origin = georef.ensure_origin(scene, centre, placed)
    georef.set_crs(scene, crs)
    vertices, location = georef.place(points, offset, origin)
    try:
        obj, skipped = mesh_build.build_point_object(name or object_name(paths, frames), vertices, attributes,
                                                     collection, show_points, location, radius, rgba)
    except Exception:
        georef.restore_keys(scene, previous)  # leave the scene as it was
        raise
    if origins is not None:  # the default region is centred on the first one (Blender coordinates)
        sources.set_sensor_origins(obj, origins - origin)
    job_inputs.remember_files(scene, obj, job_inputs.ScanFiles([str(p) for p in paths], frames,
                                                               str(poses) if poses is not None else "", topic))
    return obj, skipped, dropped


def select_only(context: bpy.types.Context, obj: bpy.types.Object,
                view_layer: bpy.types.ViewLayer | None = None) -> None:
    """The imported scan becomes the selection and the active object, as Blender's own importers leave theirs, so
    the panel's next step (Add Region Box, Complete) works on it and not on what was selected before (the
    startup Cube)."""
    view_layer = view_layer or context.view_layer
    if view_layer is not None and view_layer.objects.get(obj.name) is None:
        view_layer.update()   # a new object is in the view layer once it is synced
    if view_layer is None or view_layer.objects.get(obj.name) is None:
        return
    for other in view_layer.objects:
        if other.select_get(view_layer=view_layer):
            other.select_set(False, view_layer=view_layer)
    obj.select_set(True, view_layer=view_layer)
    view_layer.objects.active = obj


TOPIC_DESCRIPTION = "The bag's point cloud topic to read (listed by `hgca info`)"


class _ImportScan:
    """What both import operators share: the options, the paths picked, and the import itself."""

    filter_glob: StringProperty(default=";".join(f"*{e}" for e in EXTENSIONS), options={"HIDDEN"})
    files: CollectionProperty(type=bpy.types.OperatorFileListElement, options={"HIDDEN", "SKIP_SAVE"})
    directory: StringProperty(subtype="DIR_PATH", options={"HIDDEN", "SKIP_SAVE"})
    poses_path: StringProperty(name="Poses", subtype="FILE_PATH",
                               description="Optional poses JSON placing each scan in the world")
    show_points: BoolProperty(name="Show as Points", default=True,
                              description="Add a Geometry Nodes modifier that draws the vertices as points")
    frames: StringProperty(name="Frames", default="",
                           description="Frames of a sequence folder, ROS bag or E57 as START:STOP[:STEP] "
                                       "(empty: the 5 around the middle)")
    color_by: EnumProperty(
        name="Colour", default="AUTO",
        items=[("AUTO", "Automatic", "RGB when the file has it, else intensity, else height"),
               ("RGB", "RGB", "The file's own colours (LAS/PLY red, green, blue)"),
               ("INTENSITY", "Intensity", "Return strength, grey"),
               ("HEIGHT", "Height", "Height above the lowest points, as a colour ramp"),
               ("NONE", "None", "No colour attribute")])
    point_size: FloatProperty(name="Point Size", default=0.0, min=0.0, soft_max=5.0, unit="LENGTH",
                              description="Diameter of the drawn points (0: 6 cm for scans from a vehicle, about "
                                          "the point spacing for aerial scans)")

    def _paths(self) -> list[Path]:
        return input_paths(self)

    def _topic(self) -> str:
        return "" if bag_of(self._paths()) is None or self.topic in (NO_TOPIC, "") else self.topic

    def execute(self, context: bpy.types.Context) -> set[str]:
        paths = self._paths()
        if not paths:
            self.report({"ERROR"}, "No file selected")
            return {"CANCELLED"}
        poses = Path(bpy.path.abspath(self.poses_path)) if self.poses_path.strip() else None
        python = preferences.core_python(context)
        collection = context.collection or context.scene.collection
        options = {"show_points": self.show_points, "frames": self.frames.strip(), "color_by": self.color_by,
                   "point_size": self.point_size, "topic": self._topic()}
        try:
            if context.window is not None and not bpy.app.background:
                start_import(context, python, paths, poses, collection, options)
                self.report({"INFO"}, f"Reading {paths[0].name}{' ...' if len(paths) == 1 else ' and more ...'}")
                return {"FINISHED"}
            obj, skipped, dropped = import_scans(python, paths, collection, poses, scene=context.scene, **options)
        except (core.CoreError, ValueError, OSError, RuntimeError) as exc:
            note_missing_poses(context.scene, paths, poses)
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        select_only(context, obj)
        for level, text in imported_lines(obj, skipped, dropped):
            self.report({level}, text)
        return {"FINISHED"}

    def draw(self, context: bpy.types.Context) -> None:
        layout = self.layout
        layout.use_property_split = True
        layout.prop(self, "poses_path")
        paths = self._paths()
        sequence = recordings.is_sequence(paths)
        if bag_of(paths) is not None:
            layout.prop(self, "topic")
        row = layout.row()
        row.active = sequence   # frames apply to a sequence folder, a bag or an E57
        row.prop(self, "frames")
        layout.prop(self, "show_points")
        layout.prop(self, "color_by")
        layout.prop(self, "point_size")
        if len(paths) == 1 and not self.poses_path.strip():
            why = recordings.missing_poses(paths[0])
            if why:
                layout.label(text=f"No poses: {why}", icon="ERROR")
                layout.label(text="Estimate them in the hGCA panel first")


def imported_lines(obj: bpy.types.Object, skipped: list[str], dropped: dict[str, int]) -> list[tuple[str, str]]:
    """What the import reports: attributes it could not keep, then what it added."""
    lines = []
    if skipped:
        lines.append(("WARNING", f"attributes not imported (not one value per point): {', '.join(skipped)}"))
    left_out = dropped_text(dropped)
    lines.append(("INFO", f"Imported {len(obj.data.vertices):,} points as '{obj.name}'"
                  + (f" ({left_out})" if left_out else "")))
    return lines


def note_missing_poses(scene: bpy.types.Scene | None, paths: list[Path], poses: Path | None) -> None:
    """A folder that did not read for want of poses becomes the panel's Estimate Poses folder."""
    if scene is None or poses is not None or len(paths) != 1 or not hasattr(scene, "hgca_poses_folder"):
        return
    if recordings.missing_poses(paths[0]):
        scene.hgca_poses_folder = str(Path(paths[0]).absolute())


def start_import(context: bpy.types.Context, python: str, paths: list[Path], poses: Path | None,
                 collection: bpy.types.Collection, options: dict) -> None:
    """Begin an import in the interface (returns at once): `hgca read` runs on a thread, the object is added by a
    timer on the main thread (`background`), and the outcome lands in the Info log."""
    from ..jobs import messages

    paths, poses = check_inputs(paths, poses, options["frames"], options["topic"])
    scene_name, collection_name = context.scene.name, collection.name
    if background.busy("import"):
        raise RuntimeError("an import is still reading: wait for it to finish")

    def work() -> tuple:
        return read_scans(python, paths, poses, options["frames"], options["topic"])

    def finish(read: tuple) -> str:
        scene = bpy.data.scenes.get(scene_name)
        if scene is None:
            raise core.CoreError(f"scene {scene_name!r} no longer exists")
        target = bpy.data.collections.get(collection_name) or scene.collection
        obj, skipped, dropped = add_scans(read, paths, target, poses, scene=scene, **options)
        same = bpy.context.scene == scene and bpy.context.view_layer is not None
        select_only(bpy.context, obj, bpy.context.view_layer if same else scene.view_layers[0])
        lines = imported_lines(obj, skipped, dropped)
        for level, text in lines[:-1]:
            messages.report(level, text)
        return lines[-1][1]

    def on_error(_exc: Exception) -> None:
        note_missing_poses(bpy.data.scenes.get(scene_name), paths, poses)

    background.start("import", "Import LiDAR Scan", work, finish, on_error=on_error)


class HGCA_OT_import_scan(_ImportScan, bpy.types.Operator, ImportHelper):
    """Import LiDAR scans (PLY, LAS/LAZ, PCD, XYZ/CSV, NPY/NPZ, KITTI/nuScenes .bin, AV2 .feather) as one point
    object, a sequence folder (KITTI, Argoverse 2 log, nuScenes sweeps: open the folder, select no file), a ROS
    bag (.bag, .mcap, .db3, a ROS 2 bag folder) or an E57"""

    bl_idname = "import_scene.hgca_lidar"
    bl_label = "Import LiDAR Scan"
    bl_options = {"REGISTER", "UNDO"}

    # after the paths (registered with the bases), so scripts' `filepath=` is set before the topic is checked
    topic: EnumProperty(name="Topic", items=topic_items, description=TOPIC_DESCRIPTION)

    def invoke(self, context: bpy.types.Context, event: bpy.types.Event) -> set[str]:
        # files dropped on the viewport (FileHandler) arrive with paths set: confirm in a popup
        if self.properties.is_property_set("filepath") and hasattr(self, "invoke_popup"):
            return self.invoke_popup(context)
        return ImportHelper.invoke(self, context, event)


class HGCA_OT_import_scan_script(_ImportScan, bpy.types.Operator):
    """Import LiDAR scans as one point object (File > Import's operator under the add-on's own name, for
    scripts: `bpy.ops.hgca.import_scan(filepath=...)`, `directory=FOLDER, frames="0:5"`, or
    `filepath=BAG, topic="/points"`)"""

    bl_idname = "hgca.import_scan"
    bl_label = "Import LiDAR Scan"
    bl_options = {"REGISTER", "UNDO"}

    filepath: StringProperty(name="File Path", subtype="FILE_PATH", options={"SKIP_SAVE"})
    topic: EnumProperty(name="Topic", items=topic_items, description=TOPIC_DESCRIPTION)


class HGCA_FH_lidar(bpy.types.FileHandler):
    """Drag and drop of scan files onto the 3D viewport or outliner (Blender 4.1+).

    Generic text and PLY extensions are left out so dropping them keeps going to Blender's importers.
    """

    bl_idname = "HGCA_FH_lidar"
    bl_label = "LiDAR Scan (hgca)"
    bl_import_operator = HGCA_OT_import_scan.bl_idname
    bl_file_extensions = ".las;.laz;.pcd;.bin;.xyz;.npz;.feather;.bag;.mcap;.db3;.e57"

    @classmethod
    def poll_drop(cls, context: bpy.types.Context) -> bool:
        return context.area is not None and context.area.type in {"VIEW_3D", "OUTLINER"}


def menu_import(self: bpy.types.Menu, _context: bpy.types.Context) -> None:
    self.layout.operator(HGCA_OT_import_scan.bl_idname, text="LiDAR Scan (hgca)")


CLASSES = (HGCA_OT_import_scan, HGCA_OT_import_scan_script, HGCA_FH_lidar)


_register_classes, _unregister_classes = bpy.utils.register_classes_factory(CLASSES)


def register() -> None:
    _register_classes()
    bpy.types.TOPBAR_MT_file_import.append(menu_import)


def unregister() -> None:
    bpy.types.TOPBAR_MT_file_import.remove(menu_import)
    _unregister_classes()
