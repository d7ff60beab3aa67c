"""*Install Core* and *Check* in the add-on's preferences: hgca_core and torch in a venv of the extension's user
folder, set up without a terminal.

The work is `install_core.py` (no bpy) run by a base Python as a background `core.Job`: progress in the
preferences and the status bar, a log file, Cancel, errors through `report`. The base Python is the one
running Blender (its `sys.executable`: Blender's bundled 3.11 in Blender 4.2-5.0, the host interpreter for the
bpy module) unless the user picks another Python 3.11+ in the preferences. hgca's wheel travels inside the
extension (`core/`, put there by `build_extension`); torch and the other dependencies come from the package
index (torch's CPU index by default), which needs Blender's online access, or from a folder of wheels offline.

Tested on Linux with the bpy module (4.2, 5.0), whose `sys.executable` is the host Python. In Blender itself
`sys.executable` is its bundled Python, which ships venv and ensurepip on Linux; where a build lacks them the
check says so and the user picks a Python 3.11 as Base Python. Windows (Scripts/python.exe) and macOS go through
the same code but are untested: on macOS PyPI's torch is the CPU/MPS build, so its Torch Index can be empty.
"""
from __future__ import annotations

import json
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

import bpy

from . import core, messages

PACKAGE = (__package__ or "hgca_blender.jobs").rpartition(".")[0]   # the add-on itself (its preferences, its folder)
INSTALLER = Path(__file__).resolve().parent / "install_core.py"
WHEEL_DIR = Path(__file__).resolve().parents[1] / "core"             # the extension's core/ (build_extension)
ENV_NAME = "core_env"
# the installer's stages and their share of the bar (measured: venv 5 s, collecting 15 s, unpacking 60 s, check 10 s)
STAGE_SHARE = {"venv": (0.0, 0.05), "pip": (0.05, 0.3), "install": (0.3, 0.9), "check": (0.9, 1.0)}
CHECK_TIMEOUT_S = 300
TORCH_CPU_INDEX = "https://download.pytorch.org/whl/cpu"  # torch without CUDA (the PyPI build on Linux has it)


def user_folder(create: bool = True) -> Path:
    """The extension's own user folder (kept across updates of the extension); a folder under Blender's user
    scripts when the add-on runs as a legacy add-on."""
    try:
        return Path(bpy.utils.extension_path_user(PACKAGE, create=create))
    except (ValueError, TypeError):
        return Path(bpy.utils.user_resource("SCRIPTS", path="hgca", create=create))


def env_dir(create: bool = True) -> Path:
    return user_folder(create) / ENV_NAME


def installed_python() -> str:
    """The interpreter of a finished install, or "" when there is none (looking creates no folder)."""
    name = "Scripts/python.exe" if sys.platform == "win32" else "bin/python"
    python = env_dir(create=False) / name
    return str(python) if python.exists() else ""


def shipped_wheel(folder: Path = WHEEL_DIR) -> Path:
    """hgca's wheel inside the extension; CoreError when this build carries none (a source checkout)."""
    wheels = sorted(folder.glob("hgca-*.whl"))
    if not wheels:
        raise core.CoreError(f"this copy of the add-on carries no hgca wheel ({folder}): install the extension "
                             "zip built by `make extension`, or set the Core Python by hand")
    return wheels[-1]


def check_base_python(python: str) -> str:
    """The base Python's version when it can make a venv with pip (3.11 or newer), else CoreError saying why."""
    core.check_python(python)
    probe = "import sys, venv, ensurepip; print('%d.%d' % sys.version_info[:2])"
    try:
        done = subprocess.run([python, "-I", "-c", probe], capture_output=True, text=True, timeout=60,
                              stdin=subprocess.DEVNULL)
    except (OSError, subprocess.SubprocessError) as exc:
        raise core.CoreError(f"could not run {python}: {exc}") from exc
    if done.returncode != 0:
        raise core.CoreError(f"{python} cannot make a virtual environment ({core.error_message(done.stderr, 1)}): "
                             "choose a Python 3.11 as the Base Python in the hGCA preferences")
    version = done.stdout.strip()
    if tuple(int(v) for v in version.split(".")) < (3, 11):
        raise core.CoreError(f"{python} is Python {version}; hgca needs 3.11 or newer: choose another Base Python")
    return version


def install_args(env: Path, wheel: Path, wheels: str, torch: str, torch_index: str, log: Path) -> list[str]:
    """The installer's command line; `torch_index` "" leaves torch to pip's own index (PyPI: CUDA on Linux)."""
    args = [str(INSTALLER), "install", "--env", str(env), "--wheel", str(wheel), "--torch", torch,
            "--torch-index", torch_index, "--log", str(log)]
    return args + (["--wheels", wheels] if wheels else [])


class InstallJob(core.Job):
    """`install_core.py install` in the background; on success the preferences point at the new core."""

    def __init__(self, cmd: list[str], workdir: Path, env: Path, log: Path) -> None:
        self.env, self.log = env, log
        self.python = ""
        super().__init__(cmd, workdir)

    def on_progress(self, stage: str, event: dict[str, Any]) -> None:
        lo, hi = STAGE_SHARE.get(stage, (self.progress, self.progress))
        step, total = event.get("step"), event.get("total")
        frac = float(step) / float(total) if isinstance(step, int) and isinstance(total, int) and total > 0 else 0
        self.progress = max(self.progress, lo + (hi - lo) * min(max(frac, 0.0), 1.0))
        self.status = str(event.get("message") or stage)[:200]

    def on_success(self, outputs: list[Path]) -> None:
        self.python = str(outputs[0])
        prefs = _prefs()
        if prefs is not None:
            prefs.python_path = self.python

    def success_status(self) -> str:
        return f"Installed: {self.python}"

    def cancel(self) -> None:
        super().cancel()
        shutil.rmtree(self.env.with_name(self.env.name + ".new"), ignore_errors=True)

    def publish(self) -> None:
        prefs = _prefs()
        if prefs is not None:
            if abs(prefs.install_progress - self.progress) > 1e-6:
                prefs.install_progress = self.progress
            if prefs.install_status != self.status:
                prefs.install_status = self.status[:1000]
        wm = bpy.context.window_manager
        if wm is not None and not bpy.app.background:
            if self.running:
                wm.progress_update(self.progress * 100)
            else:
                wm.progress_end()
        _redraw_preferences()

    def on_end(self) -> None:
        messages.report_job(self)   # done: "Installed: <python>" in the Info log


INSTALL: dict[str, InstallJob] = {}


def running_install() -> InstallJob | None:
    job = INSTALL.get("job")
    return job if job is not None and job.running else None


def _prefs():
    addon = bpy.context.preferences.addons.get(PACKAGE)
    return addon.preferences if addon is not None else None


def _redraw_preferences() -> None:
    wm = bpy.context.window_manager
    for window in (wm.windows if wm is not None else []):
        for area in window.screen.areas:
            if area.type == "PREFERENCES":
                area.tag_redraw()


def start_install(base_python: str, wheels: str = "", torch: str = "cpu", torch_index: str = TORCH_CPU_INDEX,
                  online: bool | None = None) -> InstallJob:
    """Check what the install needs and start it; CoreError (nothing started) when something is missing."""
    if running_install() is not None:
        raise core.CoreError("the core is already being installed")
    online = bpy.app.online_access if online is None else online
    wheels = wheels.strip()
    if wheels and not Path(wheels).is_dir():
        raise core.CoreError(f"the folder of wheels does not exist: {wheels}")
    if not wheels and not online:
        raise core.CoreError("Blender's online access is off (Preferences > System > Network): allow it to "
                             "install from the package index, or choose a folder of wheels for an offline install")
    wheel = shipped_wheel()
    check_base_python(base_python)
    env = env_dir()
    log = env.with_name("install.log")
    workdir = Path(tempfile.mkdtemp(prefix="hgca_install_"))
    cmd = [base_python, "-I", *install_args(env, wheel, wheels, torch, torch_index.strip(), log)]
    job = InstallJob(cmd, workdir, env, log)
    INSTALL["job"] = job
    wm = bpy.context.window_manager
    if wm is not None and not bpy.app.background:
        wm.progress_begin(0, 100)
    job.publish()
    if not bpy.app.timers.is_registered(_tick):
        bpy.app.timers.register(_tick, first_interval=0.2)
    return job


def _tick() -> float | None:
    job = INSTALL.get("job")
    return 0.2 if job is not None and job.poll_once() else None


def check_core(python: str) -> dict[str, Any]:
    """Run the installer's `check` in `python`: torch and hgca_core import and the shipped weights load."""
    core.check_python(python)
    try:
        done = subprocess.run([python, str(INSTALLER), "check"], capture_output=True, text=True,
                              timeout=CHECK_TIMEOUT_S, stdin=subprocess.DEVNULL, cwd=tempfile.gettempdir())
    except (OSError, subprocess.SubprocessError) as exc:
        raise core.CoreError(f"could not run {python}: {exc}") from exc
    if done.returncode != 0:
        raise core.CoreError(core.error_message(done.stderr, done.returncode, python))
    lines = [ln for ln in done.stdout.splitlines() if ln.strip()]
    try:
        return json.loads(lines[-1])
    except (IndexError, ValueError) as exc:
        raise core.CoreError(f"the check printed no result: {done.stdout[-200:]!r}") from exc


def check_text(found: dict[str, Any], python: str) -> str:
    return (f"hgca {found.get('hgca', '?')}, torch {found.get('torch', '?')}"
            f"{', CUDA' if found.get('cuda') else ''}: the shipped weights load ({python})")


def start_check(python: str) -> None:
    """*Check* in the interface (returns at once): `check_core` runs on a thread, since torch's import and the
    weights' load take 5-10 s, and the answer reaches the preferences on the main thread (`background`;
    `background.poll("check")` outside the interface)."""
    from . import background

    core.check_python(python)   # a missing interpreter is said at once, not after a thread

    def finish(found: dict[str, Any]) -> str:
        text = check_text(found, python)
        prefs = _prefs()
        if prefs is not None:
            prefs.check_result = text
        _redraw_preferences()
        return text

    def failed(exc: Exception) -> None:
        prefs = _prefs()
        if prefs is not None:
            prefs.check_result = f"Error: {exc}"
        _redraw_preferences()

    background.start("check", "hGCA check", lambda: check_core(python), finish, on_error=failed, undo=False)


def cancel_install() -> None:
    job = running_install()
    if job is not None:
        job.cancel()
        job.poll_once()


def unregister() -> None:
    cancel_install()
    if bpy.app.timers.is_registered(_tick):
        bpy.app.timers.unregister(_tick)
