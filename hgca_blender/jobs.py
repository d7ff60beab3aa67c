"""Running hgca_core as a subprocess: one-shot commands and long completion jobs.

The add-on never imports torch or hgca_core: everything the model does happens in
`<python> -m hgca_core.cli ...`, with arrays passed as .npz files. A completion `Job` owns a temporary
folder, a `subprocess.Popen` and two reader threads; the stdout thread parses the `--progress jsonl`
lines into a queue. Blender data is only touched by `poll_once()`, which the UI calls from a
`bpy.app.timers` callback (main thread) and which batch runs and tests call in a loop, because timers
never fire in `blender --background` nor in the bpy module.
"""
from __future__ import annotations

import atexit
import json
import math
import os
import queue
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from typing import Any, Callable

import bpy
import numpy as np

from . import mesh_build

CORE_MODULE = "hgca_core.cli"
STAGES = ("read", "coarse", "fine", "mesh", "write")
# Share of the progress bar each stage gets; a coarse-only run has no "fine" stage.
STAGE_WEIGHTS = {"read": 0.05, "coarse": 0.45, "fine": 0.25, "mesh": 0.2, "write": 0.05}
PER_SAMPLE_STAGES = ("coarse", "fine", "mesh")
POLL_INTERVAL_S = 0.2
KILL_GRACE_S = 3.0


class CoreError(RuntimeError):
    """The core could not be run or reported an error; the message is meant for the user."""


def core_command(python: str, args: list[str]) -> list[str]:
    """`<python> -m hgca_core.cli ARGS`: the only way the add-on reaches the core."""
    return [python, "-m", CORE_MODULE, *[str(a) for a in args]]


def _child_env() -> dict[str, str]:
    """Environment for the core: unbuffered so progress lines arrive as they are printed."""
    env = dict(os.environ)
    env["PYTHONUNBUFFERED"] = "1"
    return env


def _group_kwargs() -> dict[str, Any]:
    """Start the core in its own process group so cancel can stop it and any children it spawned."""
    if os.name == "nt":
        return {"creationflags": subprocess.CREATE_NEW_PROCESS_GROUP}
    return {"start_new_session": True}


def _check_python(python: str) -> None:
    if not python:
        raise CoreError("No Python interpreter for hgca_core is set: choose one in the hGCA add-on preferences")
    if not Path(python).is_file():
        raise CoreError(f"Python interpreter not found: {python} (set it in the hGCA add-on preferences)")


def error_message(stderr: str, returncode: int | None, python: str = "") -> str:
    """The most useful line of a failed run: the core's 'error:' line, else the last line printed."""
    lines = [ln.strip() for ln in stderr.splitlines() if ln.strip()]
    if any("No module named" in ln and "hgca_core" in ln for ln in lines):
        return (f"hgca_core is not installed for {python or 'this interpreter'}: "
                "set the core's Python in the hGCA add-on preferences")
    for ln in reversed(lines):
        if "error:" in ln.lower():
            return ln
    if lines:
        return lines[-1]
    return f"hgca_core exited with status {returncode}"


def run_core(python: str, args: list[str], timeout: float | None = None,
             cwd: str | Path | None = None) -> subprocess.CompletedProcess:
    """Run one core command to completion (used for `read` and `--version`); CoreError on failure.

    It runs in a temporary folder by default: `python -m` puts the working directory first on
    sys.path, and Blender's working directory must not decide which hgca_core gets imported.
    """
    _check_python(python)
    try:
        proc = subprocess.run(core_command(python, args), capture_output=True, text=True, timeout=timeout,
                              stdin=subprocess.DEVNULL, env=_child_env(), cwd=str(cwd or tempfile.gettempdir()))
    except (OSError, subprocess.SubprocessError) as exc:
        raise CoreError(f"could not run {python}: {exc}") from exc
    if proc.returncode != 0:
        raise CoreError(error_message(proc.stderr, proc.returncode, python))
    return proc


def parse_progress_line(line: str) -> dict[str, Any]:
    """One stdout line -> event dict; lines that are not JSON objects become 'log' events."""
    text = line.strip()
    try:
        event = json.loads(text)
    except ValueError:
        return {"stage": "log", "message": text}
    if not isinstance(event, dict) or "stage" not in event:
        return {"stage": "log", "message": text}
    return event


def _terminate_tree(proc: subprocess.Popen) -> None:
    """Stop the process and everything in its group: SIGTERM, then SIGKILL after a grace period."""
    if proc.poll() is not None:
        return
    if os.name == "nt":
        subprocess.run(["taskkill", "/F", "/T", "/PID", str(proc.pid)], capture_output=True)
    else:
        try:
            os.killpg(proc.pid, signal.SIGTERM)
        except (ProcessLookupError, PermissionError):
            proc.terminate()
    try:
        proc.wait(timeout=KILL_GRACE_S)
        return
    except subprocess.TimeoutExpired:
        pass
    if os.name != "nt":
        try:
            os.killpg(proc.pid, signal.SIGKILL)
        except (ProcessLookupError, PermissionError):
            proc.kill()
    else:
        proc.kill()
    proc.wait(timeout=KILL_GRACE_S)


class Job:
    """A core subprocess speaking `--progress jsonl`, observed from the main thread via `poll_once()`.

    States: "running" -> "done" | "error" | "cancelled". The temporary folder is removed in every
    terminal state. Subclasses decide what success means (`on_success`) and where progress is shown
    (`publish`).
    """

    def __init__(self, cmd: list[str], workdir: Path, stage_names: tuple[str, ...] = STAGES, samples: int = 1) -> None:
        self.cmd = cmd
        self.samples = max(1, int(samples))
        self._sample = 0
        self._last_sample_key: tuple[int, float] | None = None
        self.workdir = Path(workdir)
        self.state = "running"
        self.progress = 0.0
        self.status = "Starting"
        self.error = ""
        self.outputs: list[Path] = []
        self.returncode: int | None = None
        self.started = time.monotonic()
        self._stage_names = tuple(s for s in stage_names if s in STAGE_WEIGHTS)
        self._events: queue.Queue[dict[str, Any]] = queue.Queue()
        self._stderr: deque[str] = deque(maxlen=200)
        self._reported_error = ""
        self._done_event: dict[str, Any] | None = None
        try:
            self._proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                          stdin=subprocess.DEVNULL, text=True, errors="replace", bufsize=1,
                                          env=_child_env(),
                                          cwd=str(self.workdir), **_group_kwargs())
        except OSError as exc:
            self._cleanup()
            raise CoreError(f"could not start {cmd[0]}: {exc}") from exc
        self._err_thread = threading.Thread(target=self._read_stderr, name="hgca-stderr", daemon=True)
        self._out_thread = threading.Thread(target=self._read_stdout, name="hgca-stdout", daemon=True)
        self._err_thread.start()
        self._out_thread.start()

    # -- reader threads (never touch bpy) ---------------------------------------------------------
    def _read_stderr(self) -> None:
        assert self._proc.stderr is not None
        try:
            for line in self._proc.stderr:
                self._stderr.append(line.rstrip("\n"))
        except (OSError, ValueError):
            pass

    def _read_stdout(self) -> None:
        assert self._proc.stdout is not None
        try:
            for line in self._proc.stdout:
                if line.strip():
                    self._events.put(parse_progress_line(line))
        except (OSError, ValueError) as exc:  # pipe closed under us (cancel) or unreadable output
            self._stderr.append(f"reading progress failed: {exc}")
        finally:
            # whatever happened, the main thread must learn that the process is over
            returncode = self._proc.wait()
            self._err_thread.join(timeout=5.0)
            self._events.put({"stage": "_exit", "returncode": returncode})

    # -- main thread --------------------------------------------------------------------------------
    @property
    def running(self) -> bool:
        return self.state == "running"

    @property
    def pid(self) -> int:
        return self._proc.pid

    def stderr_text(self) -> str:
        return "\n".join(self._stderr)

    def poll_once(self) -> bool:
        """Drain pending events, update progress, finish the job when the process has exited.

        Main thread only. Returns True while the job is still running.
        """
        if self.state != "running":
            return False
        while self.state == "running":
            try:
                event = self._events.get_nowait()
            except queue.Empty:
                break
            self._handle(event)
        self.publish()
        return self.state == "running"

    def wait(self, timeout: float | None = None, interval: float = 0.05,
             on_poll: Callable[["Job"], None] | None = None) -> str:
        """Drive `poll_once` until the job ends (batch mode and tests); cancels on timeout."""
        deadline = None if timeout is None else time.monotonic() + timeout
        while self.poll_once():
            if on_poll is not None:
                on_poll(self)
            if deadline is not None and time.monotonic() > deadline:
                self.cancel()
                self.error = f"timed out after {timeout:.0f} s"
                break
            time.sleep(interval)
        return self.state

    def kill(self) -> None:
        """Stop the process tree and remove the temporary files without touching Blender (interpreter exit)."""
        if self.state == "running":
            _terminate_tree(self._proc)
            self.state = "cancelled"
            self._cleanup()

    def cancel(self) -> None:
        """Kill the process (and its children) and drop the temporary files; nothing is built."""
        if self.state != "running":
            return
        _terminate_tree(self._proc)
        self._out_thread.join(timeout=5.0)
        self.state = "cancelled"
        self.status = "Cancelled"
        self._cleanup()
        self.publish()

    def _handle(self, event: dict[str, Any]) -> None:
        stage = str(event.get("stage", ""))
        if stage in STAGE_WEIGHTS:
            self._on_stage(stage, event)
        elif stage == "done":
            self._done_event = event
            self.status = "Building meshes"
        elif stage == "error":
            self._reported_error = str(event.get("message") or "hgca_core reported an error")
        elif stage == "_exit":
            self._finish(int(event["returncode"]))

    def _on_stage(self, stage: str, event: dict[str, Any]) -> None:
        step, total = event.get("step"), event.get("total")
        frac = 0.0
        if isinstance(step, (int, float)) and isinstance(total, (int, float)) and total > 0:
            frac = min(max(float(step) / float(total), 0.0), 1.0)
        value = self._overall(stage, frac)
        if math.isfinite(value):
            self.progress = max(self.progress, min(value, 1.0))
        message = str(event.get("message") or "")
        count = f" {step}/{total}" if isinstance(step, (int, float)) and isinstance(total, (int, float)) else ""
        self.status = f"{stage.capitalize()}{count}" + (f": {message}" if message else "")

    def _overall(self, stage: str, frac: float) -> float:
        """Whole-job fraction: read, then `samples` rounds of the per-sample stages, then write.

        The protocol has no sample index, so a new sample is recognised when a per-sample stage
        starts over (an earlier stage than the last one seen, or the same stage at a lower step).
        """
        names = self._stage_names if stage in self._stage_names else STAGES
        per_sample = [s for s in names if s in PER_SAMPLE_STAGES]
        total_w = sum(STAGE_WEIGHTS[s] for s in names)
        if stage not in PER_SAMPLE_STAGES:
            before = sum(STAGE_WEIGHTS[s] for s in names[:names.index(stage)])
            return (before + STAGE_WEIGHTS[stage] * frac) / total_w
        key = (per_sample.index(stage), frac)
        if self._last_sample_key is not None and key < self._last_sample_key:
            self._sample = min(self._sample + 1, self.samples - 1)
        self._last_sample_key = key
        ps_w = sum(STAGE_WEIGHTS[s] for s in per_sample)
        within = (sum(STAGE_WEIGHTS[s] for s in per_sample[:per_sample.index(stage)])
                  + STAGE_WEIGHTS[stage] * frac) / ps_w
        before = sum(STAGE_WEIGHTS[s] for s in names if s not in PER_SAMPLE_STAGES and names.index(s) < names.index(stage))
        return (before + ps_w * (self._sample + within) / self.samples) / total_w

    def _finish(self, returncode: int) -> None:
        self.returncode = returncode
        try:
            if returncode == 0 and self._done_event is not None:
                self.outputs = self._output_paths(self._done_event)
                self.on_success(self.outputs)
                self.state = "done"
                self.progress = 1.0
                self.status = self.success_status()
            else:
                if returncode == 0:
                    message = "hgca_core finished without reporting its outputs"
                else:
                    message = self._reported_error or error_message(self.stderr_text(), returncode, self.cmd[0])
                self._fail(message)
        except Exception as exc:  # building results failed: on_success rolled back, report why
            self._fail(f"could not load the results: {exc}")
        finally:
            self._cleanup()

    def _fail(self, message: str) -> None:
        self.state = "error"
        self.error = message
        self.status = f"Error: {message}"

    def _output_paths(self, done: dict[str, Any]) -> list[Path]:
        listed = done.get("outputs")
        if isinstance(listed, list) and listed:
            paths = [Path(p) if Path(p).is_absolute() else self.workdir / p for p in listed]
        else:
            paths = sorted(self.workdir.glob("out_s*.npz"), key=lambda p: int(p.stem.rsplit("_s", 1)[1]))
        missing = [str(p) for p in paths if not p.is_file()]
        if not paths or missing:
            raise CoreError(f"output files missing: {', '.join(missing) or 'none reported'}")
        return paths

    def _cleanup(self) -> None:
        shutil.rmtree(self.workdir, ignore_errors=True)

    # -- hooks ---------------------------------------------------------------------------------------
    def on_success(self, outputs: list[Path]) -> None:
        """Consume the outputs (main thread). Must leave Blender untouched if it raises."""

    def success_status(self) -> str:
        return "Done"

    def publish(self) -> None:
        """Show progress somewhere (main thread)."""


# ---------------------------------------------------------------------------------------------------
# Completion jobs

@dataclass
class CompletionParams:
    """Everything one completion needs; built by the operator from the scene, or directly by batch/tests."""

    python: str
    points: np.ndarray  # (N, 3) world-space points
    region: tuple[float, ...]  # cx, cy, cz, sx, sy, sz, yaw_deg (world)
    samples: int = 1
    seed: int = 0
    stage: str = "coarse"
    device: str = "cpu"
    t1: int = 30
    t2: int = 15
    max_faces: int = 0           # 0: no limit
    scene_name: str = ""
    run_name: str = ""
    extra_args: list[str] = field(default_factory=list)


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
    if not 1 <= int(params.samples) <= 8:
        raise CoreError(f"sample count must be 1..8, got {params.samples}")
    if params.stage not in ("coarse", "full"):
        raise CoreError(f"stage must be 'coarse' or 'full', got {params.stage!r}")
    if params.device not in ("cpu", "cuda"):
        raise CoreError(f"device must be 'cpu' or 'cuda', got {params.device!r}")
    if int(params.t1) < 1 or int(params.t2) < 1:
        raise CoreError("T1 and T2 must be at least 1")
    if int(params.max_faces) != 0 and int(params.max_faces) < 1000:
        raise CoreError(f"max faces must be 0 (no limit) or at least 1000, got {params.max_faces}")
    return pts


def completion_args(params: CompletionParams, in_path: Path, out_path: Path) -> list[str]:
    """The `hgca complete` command line from CONTRACTS.md ("Completion CLI")."""
    region = ",".join(repr(float(v)) for v in params.region)
    return ["complete", str(in_path), f"--region={region}", "--samples", str(int(params.samples)),
            "--seed", str(int(params.seed)), "--stage", params.stage, "--device", params.device,
            "--t1", str(int(params.t1)), "--t2", str(int(params.t2)), "--progress", "jsonl",
            "--max-faces", str(int(params.max_faces)),      # 0: every triangle (the core's default is 1 M)
            *params.extra_args, "-o", str(out_path)]


class CompletionJob(Job):
    """A completion whose results become one mesh per sample in a new collection of its scene."""

    def __init__(self, params: CompletionParams, workdir: Path, cmd: list[str]) -> None:
        self.params = params
        self.scene_name = params.scene_name
        self.run_name = params.run_name or f"hGCA {datetime.now():%Y-%m-%d %H:%M:%S}"
        self.collection_name = ""
        stages = ("read", "coarse", "mesh", "write") if params.stage == "coarse" else STAGES
        super().__init__(cmd, workdir, stages, samples=params.samples)

    def _scene(self) -> bpy.types.Scene | None:
        return bpy.data.scenes.get(self.scene_name)

    def on_success(self, outputs: list[Path]) -> None:
        scene = self._scene()
        if scene is None:
            raise CoreError(f"scene {self.scene_name!r} no longer exists")
        collection = mesh_build.build_results(scene, outputs, self.run_name)
        self.collection_name = collection.name
        _undo_push(f"hGCA: {self.run_name}")

    def success_status(self) -> str:
        n = len(self.outputs)
        return f"Done: {n} sample{'s' if n != 1 else ''} in '{self.collection_name}'"

    def publish(self) -> None:
        scene = self._scene()
        if scene is None or not hasattr(scene, "hgca"):
            return
        props = scene.hgca
        if abs(props.progress - self.progress) > 1e-6:
            props.progress = self.progress
        if props.status != self.status:
            props.status = self.status[:1000]
        props.status_is_error = self.state == "error"
        _redraw_view3d()


def _undo_push(message: str) -> None:
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


# Active jobs, one per scene (by name); the UI timer polls these.
ACTIVE: dict[str, CompletionJob] = {}


def active_job(scene_name: str) -> CompletionJob | None:
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
        raise CoreError(f"a completion is already running in scene {params.scene_name!r}")
    _check_python(params.python)
    pts = validate_params(params)
    workdir = Path(tempfile.mkdtemp(prefix="hgca_job_"))
    try:
        in_path = workdir / "in.npz"
        np.savez(in_path, points=pts)
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
            if job.state == "error":
                print(f"hGCA: completion failed: {job.error}", file=sys.stderr)
            del ACTIVE[name]
    return any_running


def _timer_tick() -> float | None:
    """bpy.app.timers callback: keeps polling while jobs run, then unregisters itself."""
    return POLL_INTERVAL_S if poll_all() else None


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


def register() -> None:
    if _on_load_pre not in bpy.app.handlers.load_pre:
        bpy.app.handlers.load_pre.append(_on_load_pre)
    atexit.register(_kill_all_at_exit)


def unregister() -> None:
    atexit.unregister(_kill_all_at_exit)
    cancel_all()
    if bpy.app.timers.is_registered(_timer_tick):
        bpy.app.timers.unregister(_timer_tick)
    if _on_load_pre in bpy.app.handlers.load_pre:
        bpy.app.handlers.load_pre.remove(_on_load_pre)
