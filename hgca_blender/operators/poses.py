"""Estimate Poses: LiDAR odometry for a folder of sweeps that came without poses, so the import can read it as a
posed sequence.

A sequence is only worth completing when its sweeps line up, and many recordings (a folder of exported scans, a
KITTI folder without poses.txt) carry no poses. `hgca poses --estimate FOLDER -o FOLDER/poses.json --progress
jsonl` makes them; here it runs as a background job like a completion (`core.Job`, polled by `jobs`' timer, shown
by the panel's progress bar and Cancel, and by a progress bar in the status bar). The core writes poses.json
atomically; a cancel stops it and removes whatever it left, so the folder stays as it was.
"""
from __future__ import annotations

import json
import tempfile
from pathlib import Path
from typing import Any

import bpy
from bpy.props import StringProperty

from .. import preferences
from ..jobs import completion, core, messages
from . import recordings
from .watch import JobWatching

FOLDER_PROPERTY = "hgca_poses_folder"   # Scene property: the folder the panel offers to estimate poses for
# The progress bar's share of each stage the core reports (reading the frames, then registering them one by one)
STAGE_SHARE = {"read": (0.0, 0.3), "odometry": (0.3, 1.0)}


def estimate_args(folder: Path, out: Path, topic: str = "") -> list[str]:
    """The core's command line: `hgca poses --estimate FOLDER -o OUT --progress jsonl [--topic T]`."""
    return ["poses", "--estimate", str(folder), "-o", str(out), "--progress", "jsonl",
            *(["--topic", topic] if topic else [])]


class PosesJob(core.Job):
    """One `hgca poses --estimate`: progress per frame; its output is the poses JSON beside the sweeps."""

    def __init__(self, folder: Path, out: Path, scene_name: str, cmd: list[str], workdir: Path) -> None:
        self.folder, self.out, self.scene_name = Path(folder), Path(out), scene_name
        self.records: list[dict[str, Any]] = []     # the progress records seen, in order
        self.frames = 0
        self._before = self.out.read_bytes() if self.out.is_file() else None   # restored by a cancel
        super().__init__(cmd, workdir)

    def on_progress(self, stage: str, event: dict[str, Any]) -> None:
        self.records.append(event)
        step, total = event.get("step"), event.get("total")
        counted = isinstance(step, (int, float)) and isinstance(total, (int, float)) and total > 0
        if counted and stage in STAGE_SHARE:
            low, high = STAGE_SHARE[stage]
            share = low + (high - low) * min(max(float(step) / float(total), 0.0), 1.0)
            self.progress = max(self.progress, share)
        what = {"read": "Reading frame", "odometry": "Placing frame"}.get(stage, stage.capitalize())
        count = f" {int(step)} of {int(total)}" if counted else ""
        message = str(event.get("message") or "")
        self.status = f"{what}{count}" + (f": {message}" if message else "")

    def _output_paths(self, done: dict[str, Any]) -> list[Path]:
        if not self.out.is_file():
            raise core.CoreError(f"hgca poses finished but wrote no {self.out}")
        return [self.out]

    def on_success(self, outputs: list[Path]) -> None:
        try:
            self.frames = len(json.loads(self.out.read_text(encoding="utf-8")).get("scans", []))
        except (OSError, ValueError, AttributeError) as exc:
            raise core.CoreError(f"{self.out} is no poses JSON: {exc}") from None

    def success_status(self) -> str:
        return (f"poses of {self.frames} frames in {self.out}: import the folder '{self.folder.name}' to read them "
                "as a sequence")

    def cancel(self) -> None:
        super().cancel()
        self._restore()

    def kill(self) -> None:
        super().kill()
        self._restore()

    def _restore(self) -> None:
        """After a stop: no temp file of the core left, and poses.json as it was before the job."""
        for leftover in recordings.leftover_temp_files(self.out, self.pid):
            leftover.unlink(missing_ok=True)
        if self.state != "cancelled":
            return
        if self._before is None:
            self.out.unlink(missing_ok=True)    # written in the instant before the stop: not asked for any more
        elif not self.out.is_file() or self.out.read_bytes() != self._before:
            self.out.write_bytes(self._before)

    def publish(self) -> None:
        completion.publish_state(self)

    def on_end(self) -> None:
        messages.report_job(self)


def start_estimate(python: str, folder: Path, scene_name: str, topic: str = "") -> PosesJob:
    """Launch the estimate for `folder` as its scene's job (one job a scene); CoreError when it cannot start."""
    folder = Path(folder).absolute()
    if not folder.is_dir() and recordings.container_kind(folder) is None:
        raise core.CoreError(f"folder not found: {folder}")
    if bpy.data.scenes.get(scene_name) is None:
        raise core.CoreError(f"no scene named {scene_name!r}")
    if completion.active_job(scene_name) is not None:
        raise core.CoreError(f"a job is already running in scene {scene_name!r}")
    core.check_python(python)
    out = (folder if folder.is_dir() else folder.parent) / recordings.POSES_FILE
    workdir = Path(tempfile.mkdtemp(prefix="hgca_poses_"))
    job = PosesJob(folder, out, scene_name, core.core_command(python, estimate_args(folder, out, topic)), workdir)
    completion.ACTIVE[scene_name] = job
    job.publish()
    return job


def _status_drawer(job: PosesJob):
    """A status bar header that draws the job's progress bar (`WorkSpace.status_text_set` takes a draw function)."""
    def draw(header: bpy.types.Header, _context: bpy.types.Context) -> None:
        row = header.layout.row()
        row.label(text="hGCA", icon="TRACKING")
        row.progress(factor=job.progress, type="BAR", text=f"{job.status} ({job.progress * 100:.0f}%)")
        row.label(text="Esc: cancel")
    return draw


class HGCA_OT_estimate_poses(JobWatching, bpy.types.Operator):
    """Estimate the sensor poses of a folder of sweeps with LiDAR odometry (KISS-ICP), written to poses.json in
    the folder, so the folder imports as one posed sequence (runs in the background; Esc cancels)"""

    bl_idname = "hgca.estimate_poses"
    bl_label = "Estimate Poses"

    folder: StringProperty(name="Folder", subtype="DIR_PATH", options={"SKIP_SAVE"},
                           description="Folder of sweeps without poses (default: the panel's)")
    topic: StringProperty(name="Topic", options={"SKIP_SAVE"}, description="A ROS bag's point cloud topic")
    cancel_message = "Estimate Poses cancelled (Esc): the folder is as it was"
    status_text = staticmethod(_status_drawer)   # a progress bar in the status bar

    @classmethod
    def poll(cls, context: bpy.types.Context) -> bool:
        return context.scene is not None and completion.active_job(context.scene.name) is None

    def _folder(self, context: bpy.types.Context) -> str:
        chosen = self.folder.strip() or getattr(context.scene, FOLDER_PROPERTY, "").strip()
        return bpy.path.abspath(chosen) if chosen else ""

    def execute(self, context: bpy.types.Context) -> set[str]:
        folder = self._folder(context)
        try:
            if not folder:
                raise core.CoreError("no folder: choose the folder of sweeps to estimate poses for")
            job = start_estimate(preferences.core_python(context), Path(folder), context.scene.name,
                                 self.topic.strip())
        except core.CoreError as exc:
            from .complete import refuse_start

            return refuse_start(self, context, exc)
        completion.ensure_timer()
        self.report({"INFO"}, f"Estimating the poses of {job.folder.name} (process {job.pid})")
        return {"FINISHED"}


def draw_poses(layout: bpy.types.UILayout, context: bpy.types.Context) -> None:
    """The panel's Poses box: the folder, why it needs poses, and Estimate Poses (hidden while a job runs)."""
    scene = context.scene
    folder = getattr(scene, FOLDER_PROPERTY, "")
    box = layout.box()
    box.prop(scene, FOLDER_PROPERTY)
    why = recordings.missing_poses(Path(bpy.path.abspath(folder))) if folder.strip() else ""
    if why:
        box.label(text=f"No poses: {why}", icon="ERROR")
    elif folder.strip() and (Path(bpy.path.abspath(folder)) / recordings.POSES_FILE).is_file():
        box.label(text="The folder has its poses.json", icon="CHECKMARK")
        box.operator("hgca.import_scan", text="Import Folder", icon="IMPORT").directory = bpy.path.abspath(folder)
    row = box.row()
    row.enabled = completion.active_job(scene.name) is None and bool(folder.strip())
    row.operator(HGCA_OT_estimate_poses.bl_idname, icon="TRACKING")


CLASSES = (HGCA_OT_estimate_poses,)

_register_classes, _unregister_classes = bpy.utils.register_classes_factory(CLASSES)


def register() -> None:
    setattr(bpy.types.Scene, FOLDER_PROPERTY, StringProperty(
        name="Sweeps Folder", subtype="DIR_PATH",
        description="A folder of sweeps without poses: Estimate Poses writes its poses.json"))
    _register_classes()


def unregister() -> None:
    _unregister_classes()
    if hasattr(bpy.types.Scene, FOLDER_PROPERTY):
        delattr(bpy.types.Scene, FOLDER_PROPERTY)
