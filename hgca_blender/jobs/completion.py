"""Completion jobs: `hgca complete` on the source points, its results turned into one mesh per sample.

The generic part (subprocess, reader threads, progress queue, cancel, `poll_once`) is `core.Job`; this module
decides the command line, how far along a completion is, and what its outputs become. Blender data is only
touched by `poll_once()`, which the UI calls from a `bpy.app.timers` callback (main thread) and which batch
runs and tests call in a loop, because timers never fire in `blender --background` nor in the bpy module.
"""
from __future__ import annotations

import atexit
import math
import shutil
import tempfile
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from typing import Any

import bpy
import numpy as np

from .. import settings
from ..scene import result_insert
from . import messages
from .core import CoreError, Job, check_python, core_command
from .job_inputs import ScanFiles

STAGES = ("read", "coarse", "fine", "mesh", "write")
# Share of the progress bar each stage gets; a coarse-only run has no "fine" stage.
STAGE_WEIGHTS = {"read": 0.05, "coarse": 0.45, "fine": 0.25, "mesh": 0.2, "write": 0.05}
PER_SAMPLE_STAGES = ("coarse", "fine", "mesh")
POLL_INTERVAL_S = 0.2
INSERT_INTERVAL_S = 0.02   # between two slices of results going in (result_insert.SLICE_S each)


@dataclass
class CompletionParams:
    """Everything one completion needs; built by the operator from the scene, or directly by batch/tests."""

    python: str
    points: np.ndarray  # (N, 3) world-space points
    region: tuple[float, ...]  # cx, cy, cz, sx, sy, sz, yaw_deg (world)
    samples: int = settings.default("samples")    # defaults: the core's (settings)
    seed: int = settings.default("seed")
    stage: str = settings.default("stage")        # as `hgca complete` and the panel: preview, coarse or full
    quality: str = settings.default("quality")    # `hgca complete --quality`: fast (the few-step students) or best
    device: str = settings.default("device")
    t1: int = 0                  # 0: the core's default, from the weights
    t2: int = 0                  # 0: the core's default, from the weights
    max_faces: int = 0           # 0: no limit
    decimate_to: int = 0         # > 0: every triangle kept, a Decimate modifier shows this many
    semantics: bool = False      # `--semantics`: a class per face, a material per class
    class_collections: bool = False   # with semantics: a collection per class as well
    scene_name: str = ""
    run_name: str = ""
    extra_args: list[str] = field(default_factory=list)
    origins: np.ndarray | None = None        # (S, 3) world sensor origins: the rays of the observed free space
    origin_index: np.ndarray | None = None   # (N,) each point's row in `origins`
    files: ScanFiles | None = None           # the scan files themselves, when the points are exactly theirs


def validate_params(params: CompletionParams) -> np.ndarray:
    """Check inputs before a process is started, so errors show up at once; returns (N,3) float64 points."""
    pts = np.asarray(params.points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise CoreError(f"source points must be (N, 3), got {pts.shape}")
    if len(pts) == 0:
        raise CoreError("the source objects have no points")
    if not np.all(np.isfinite(pts)):
        raise CoreError("the source points contain NaN or infinite coordinates")
    region = tuple(float(v) for v in params.region)
    if len(region) != 7 or not all(math.isfinite(v) for v in region) or min(region[3:6]) <= 0:
        raise CoreError(f"region must be 7 finite numbers with positive size, got {region}")
    try:
        settings.core_args(setting_values(params))   # the core's own bounds and choices (core_settings.json)
    except ValueError as exc:
        raise CoreError(str(exc)) from None
    if params.device not in ("cpu", "cuda"):
        raise CoreError(f"device must be 'cpu' or 'cuda', got {params.device!r}")
    if int(params.decimate_to) < 0:
        raise CoreError(f"the Decimate modifier's face count must be 0 (none) or more, got {params.decimate_to}")
    if params.origins is not None:
        origins = np.asarray(params.origins, dtype=np.float64)
        index = np.asarray(params.origin_index if params.origin_index is not None else [], dtype=np.int64)
        if origins.ndim != 2 or origins.shape[1] != 3 or not len(origins) or not np.all(np.isfinite(origins)):
            raise CoreError(f"sensor origins must be finite (S, 3), got {origins.shape}")
        if index.shape != (len(pts),) or index.min() < 0 or index.max() >= len(origins):
            raise CoreError("every source point needs the index of its sensor origin")
    return pts


def input_arrays(params: CompletionParams, pts: np.ndarray) -> dict[str, np.ndarray]:
    """The .npz the core reads in place of scan files: world points and, when known, their rays."""
    arrays = {"points": pts}
    if params.origins is not None and params.origin_index is not None:
        arrays["origins"] = np.asarray(params.origins, dtype=np.float64)
        arrays["origin_index"] = np.asarray(params.origin_index, dtype=np.int64)
    return arrays


def setting_values(params) -> dict[str, Any]:
    """The core settings a job's parameters hold (a completion's or a drive's), by the schema's names."""
    return {"samples": int(params.samples), "seed": int(params.seed), "stage": params.stage,
            "quality": params.quality, "device": params.device, "t1": int(params.t1), "t2": int(params.t2),
            "max_faces": int(params.max_faces)}


def completion_args(params: CompletionParams, in_path: Path, out_path: Path) -> list[str]:
    """The `hgca complete` command line from CONTRACTS.md ("Completion CLI"): the settings through
    `settings.core_args` (T1/T2 of 0 left to the core; max faces 0 keeps every triangle). The input is the scan
    files when `params.files` names them, else the .npz at `in_path`."""
    region = ",".join(repr(float(v)) for v in params.region)
    inputs = params.files.args() if params.files is not None else [str(in_path)]
    return ["complete", *inputs, f"--region={region}", *settings.core_args(setting_values(params)),
            "--progress", "jsonl", *(["--semantics"] if params.semantics else []),
            *params.extra_args, "-o", str(out_path)]


class CompletionJob(Job):
    """A completion whose results become one mesh per sample in a new collection of its scene."""

    def __init__(self, params: CompletionParams, workdir: Path, cmd: list[str]) -> None:
        self.params = params
        self.samples = max(1, int(params.samples))
        self.scene_name = params.scene_name
        self.run_name = params.run_name or f"hGCA {datetime.now():%Y-%m-%d %H:%M:%S}"
        self.collection_name = ""
        self.stage_names = STAGES if params.stage == "full" else ("read", "coarse", "mesh", "write")
        super().__init__(cmd, workdir)

    def on_progress(self, stage: str, event: dict[str, Any]) -> None:
        if stage not in self.stage_names:  # voxelise, planner, and stages a newer core may add
            return
        step, total = event.get("step"), event.get("total")
        counted = isinstance(step, (int, float)) and isinstance(total, (int, float))
        frac = min(max(float(step) / float(total), 0.0), 1.0) if counted and total > 0 else 0.0
        samples = event.get("samples")
        samples = int(samples) if isinstance(samples, int) and samples >= 1 else self.samples
        sample = event.get("sample")
        sample = min(max(int(sample), 0), samples - 1) if isinstance(sample, int) else 0
        value = self._overall(stage, frac, sample, samples)
        if math.isfinite(value):
            self.progress = max(self.progress, min(value, 1.0))
        message = str(event.get("message") or "")
        count = f" {step}/{total}" if counted else ""
        self.status = f"{stage.capitalize()}{count}" + (f": {message}" if message else "")

    def _overall(self, stage: str, frac: float, sample: int, samples: int) -> float:
        """Whole-job fraction: read, then `samples` rounds of the per-sample stages, then write.

        `sample` is the record's own sample index (docs/CONTRACTS.md, "Progress records")."""
        names = self.stage_names
        total_w = sum(STAGE_WEIGHTS[s] for s in names)
        before = sum(STAGE_WEIGHTS[s] for s in names[:names.index(stage)])
        if stage not in PER_SAMPLE_STAGES:
            return (before + STAGE_WEIGHTS[stage] * frac) / total_w
        per_sample = [s for s in names if s in PER_SAMPLE_STAGES]
        ps_w = sum(STAGE_WEIGHTS[s] for s in per_sample)
        within = (sum(STAGE_WEIGHTS[s] for s in per_sample[:per_sample.index(stage)])
                  + STAGE_WEIGHTS[stage] * frac) / ps_w
        head = sum(STAGE_WEIGHTS[s] for s in names[:names.index(per_sample[0])])
        return (head + ps_w * (sample + within) / samples) / total_w

    def _scene(self) -> bpy.types.Scene | None:
        return bpy.data.scenes.get(self.scene_name)

    def on_success(self, outputs: list[Path]) -> result_insert.Insertion:
        """Begin adding the results: read on a thread, built in slices over the next polls (`result_insert`)."""
        scene = self._scene()
        if scene is None:
            raise CoreError(f"scene {self.scene_name!r} no longer exists")
        return result_insert.start_completion(scene, outputs, self.run_name, int(self.params.decimate_to),
                                              class_collections=bool(self.params.class_collections))

    def on_inserted(self, insertion: result_insert.Insertion) -> None:
        self.collection_name = insertion.result
        undo_push(f"hGCA: {self.run_name}")

    def success_status(self) -> str:
        n = len(self.outputs)
        return f"Done: {n} sample{'s' if n != 1 else ''} in '{self.collection_name}'"

    def publish(self) -> None:
        publish_state(self)

    def on_end(self) -> None:
        messages.report_job(self)


def publish_state(job: Job) -> None:
    """Show a job's progress and status in its scene's panel (`scene.hgca`); completion and drive jobs alike."""
    scene = bpy.data.scenes.get(job.scene_name)
    if scene is None or not hasattr(scene, "hgca"):
        return
    props = scene.hgca
    if abs(props.progress - job.progress) > 1e-6:
        props.progress = job.progress
    if props.status != job.status:
        props.status = job.status[:1000]
    props.status_is_error = job.state == "error"
    window_progress(job)
    _redraw_view3d()


_PROGRESS_SHOWN: set[int] = set()  # ids of jobs whose window-manager progress is showing


def window_progress(job: Job) -> None:
    """The job's progress in the window manager's progress indicator (`wm.progress_*`), ended with the job."""
    wm = getattr(bpy.context, "window_manager", None)
    if wm is None or bpy.app.background or not wm.windows:
        return
    if job.running:
        if id(job) not in _PROGRESS_SHOWN:
            wm.progress_begin(0.0, 1.0)
            _PROGRESS_SHOWN.add(id(job))
        wm.progress_update(job.progress)
    elif id(job) in _PROGRESS_SHOWN:
        _PROGRESS_SHOWN.discard(id(job))
        wm.progress_end()


def time_left(job: Job) -> str:
    """", about 1 min 20 s left" from the time so far and the share done; "" until there is enough to tell."""
    import time

    done, spent = job.progress, time.monotonic() - job.started
    if done < 0.05 or spent < 2.0:
        return ""
    left = spent * (1.0 - done) / done
    return f", about {int(left // 60)} min {int(left % 60)} s left" if left >= 60 else f", about {int(left)} s left"


def status_bar(context: bpy.types.Context, text: Any) -> None:
    """Text in the status bar while a job runs, or a header draw function (None gives the bar back to Blender)."""
    workspace = getattr(context, "workspace", None)
    if workspace is not None and not bpy.app.background:
        workspace.status_text_set(text)


def undo_push(message: str) -> None:
    """Record the results as an undo step: they are built by a timer, outside any operator."""
    if bpy.app.background:
        return
    wm = getattr(bpy.context, "window_manager", None)
    if wm is None or not wm.windows:
        return
    try:
        with bpy.context.temp_override(window=wm.windows[0]):
            bpy.ops.ed.undo_push(message=message)
    except RuntimeError:  # no undo stack in this context: the results are there, only not undoable
        pass


def _redraw_view3d() -> None:
    wm = getattr(bpy.context, "window_manager", None)
    if wm is None:
        return
    for window in wm.windows:
        for area in window.screen.areas:
            if area.type == "VIEW_3D":
                area.tag_redraw()


# Active jobs (completions and drives), one per scene (by name); the UI timer polls these.
ACTIVE: dict[str, Job] = {}


def active_job(scene_name: str) -> Job | None:
    job = ACTIVE.get(scene_name)
    return job if job is not None and job.running else None


def start_job(params: CompletionParams) -> CompletionJob:
    """Write the inputs, launch `hgca complete` and register the job for its scene.

    Raises CoreError (nothing started, nothing left on disk) for bad parameters or a missing interpreter.
    """
    if not params.scene_name:
        scene = bpy.context.scene
        params.scene_name = scene.name if scene is not None else ""
    if bpy.data.scenes.get(params.scene_name) is None:
        raise CoreError(f"no scene named {params.scene_name!r}")
    if active_job(params.scene_name) is not None:
        raise CoreError(f"a job is already running in scene {params.scene_name!r}")
    check_python(params.python)
    pts = validate_params(params)
    workdir = Path(tempfile.mkdtemp(prefix="hgca_job_"))
    try:
        in_path = workdir / "in.npz"
        if params.files is None:
            np.savez(in_path, **input_arrays(params, pts))
        cmd = core_command(params.python, completion_args(params, in_path, workdir / "out.npz"))
    except Exception:
        shutil.rmtree(workdir, ignore_errors=True)
        raise
    job = CompletionJob(params, workdir, cmd)
    ACTIVE[params.scene_name] = job
    job.publish()
    return job


def poll_all() -> bool:
    """Poll every active job once; True while any is still running."""
    any_running = False
    for name, job in list(ACTIVE.items()):
        if job.poll_once():
            any_running = True
        else:
            del ACTIVE[name]
    return any_running


def _timer_tick() -> float | None:
    """bpy.app.timers callback: keeps polling while jobs run, then unregisters itself; while results go in, again
    soon after each slice (the interface answers in between)."""
    if not poll_all():
        return None
    inserting = any(j.finishing is not None or getattr(j, "inserting", False) for j in ACTIVE.values())
    return INSERT_INTERVAL_S if inserting else POLL_INTERVAL_S


def ensure_timer() -> None:
    if not bpy.app.timers.is_registered(_timer_tick):
        bpy.app.timers.register(_timer_tick, first_interval=POLL_INTERVAL_S, persistent=True)


def cancel_all() -> None:
    """Cancel every running job (file load, add-on disable): their scenes are about to go away."""
    for job in list(ACTIVE.values()):
        job.cancel()
    ACTIVE.clear()


def _kill_all_at_exit() -> None:
    """The core runs in its own session, so it would outlive Blender: stop it when Python exits."""
    for job in list(ACTIVE.values()):
        job.kill()
    ACTIVE.clear()


@bpy.app.handlers.persistent
def _on_load_pre(*_args: Any) -> None:
    cancel_all()


@bpy.app.handlers.persistent
def _on_load_post(*_args: Any) -> None:
    """A file saved while a job ran keeps its progress and status: nothing runs after loading it, so clear them."""
    clear_stale_status()


def clear_stale_status() -> None:
    for scene in bpy.data.scenes:
        props = getattr(scene, "hgca", None)
        if props is not None and active_job(scene.name) is None and (props.status or props.progress):
            props.status, props.progress, props.status_is_error = "", 0.0, False


def register() -> None:
    if _on_load_pre not in bpy.app.handlers.load_pre:
        bpy.app.handlers.load_pre.append(_on_load_pre)
    if _on_load_post not in bpy.app.handlers.load_post:
        bpy.app.handlers.load_post.append(_on_load_post)
    atexit.register(_kill_all_at_exit)


def unregister() -> None:
    atexit.unregister(_kill_all_at_exit)
    cancel_all()
    if bpy.app.timers.is_registered(_timer_tick):
        bpy.app.timers.unregister(_timer_tick)
    if _on_load_pre in bpy.app.handlers.load_pre:
        bpy.app.handlers.load_pre.remove(_on_load_pre)
    if _on_load_post in bpy.app.handlers.load_post:
        bpy.app.handlers.load_post.remove(_on_load_post)
