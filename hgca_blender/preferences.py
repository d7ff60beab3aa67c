"""Add-on preferences: which Python interpreter runs hgca_core, found automatically when possible.

Blender's own Python lacks torch, so the core runs in another interpreter. Detection order:
HGCA_PYTHON, the interpreter in the shebang of an `hgca` script on PATH, the repository's
`.venv/bin/python` when the add-on runs from a checkout, and finally the interpreter running Blender
itself when it can find hgca_core (the bpy-module case; checked with `find_spec`, nothing imported).
"""

import importlib.util
import os
import shlex
import shutil
import sys
from pathlib import Path

import bpy
from bpy.props import EnumProperty, FloatProperty, StringProperty

from .jobs import core, installer

ENV_VAR = "HGCA_PYTHON"


def _python_from_script(script: Path) -> str:
    """Interpreter a console script runs with: its `#!` line, or pip's `/bin/sh` exec trampoline."""
    try:
        with open(script, "rb") as fh:
            head = fh.read(1024).decode("utf-8", "replace").splitlines()
    except OSError:
        return ""
    if not head or not head[0].startswith("#!"):
        return ""
    parts = shlex.split(head[0][2:].strip()) or [""]
    if Path(parts[0]).name == "env" and len(parts) > 1:
        found = shutil.which(parts[1])
        return found or ""
    if Path(parts[0]).name in ("sh", "bash") and len(head) > 1 and "exec" in head[1]:
        # pip writes: '''exec' "/long/path/python" "$0" "$@"
        quoted = [p for p in head[1].split('"') if p.strip() and not p.startswith("$")]
        return quoted[0] if quoted and Path(quoted[0]).is_file() else ""
    return parts[0] if Path(parts[0]).is_file() else ""


def _repo_venv_python() -> str:
    root = Path(__file__).resolve().parents[1]
    for rel in (".venv/bin/python", ".venv/Scripts/python.exe"):
        if (root / rel).is_file() and (root / "hgca_core").is_dir():
            return str(root / rel)
    return ""


def detect_python() -> str:
    """Best guess for the core's interpreter, or "" when nothing was found."""
    env = os.environ.get(ENV_VAR, "").strip()
    if env:
        return env
    installed = installer.installed_python()   # what *Install Core* made, when the preference is not at hand
    if installed:
        return installed
    script = shutil.which("hgca")
    if script:
        found = _python_from_script(Path(script))
        if found:
            return found
    found = _repo_venv_python()
    if found:
        return found
    if importlib.util.find_spec("hgca_core") is not None and Path(sys.executable).is_file():
        return sys.executable
    return ""


def addon_preferences(context: bpy.types.Context | None = None) -> "HGCA_AddonPreferences | None":
    """This add-on's preferences when it is enabled (as extension or add-on), else None (batch runs)."""
    ctx = context or bpy.context
    addon = ctx.preferences.addons.get(__package__)
    return addon.preferences if addon is not None else None


def core_python(context: bpy.types.Context | None = None) -> str:
    """The interpreter to run hgca_core with: the preference when set, else auto-detected."""
    prefs = addon_preferences(context)
    if prefs is not None and prefs.python_path.strip():
        return bpy.path.abspath(prefs.python_path.strip())
    return detect_python()


def core_extra_args(context: bpy.types.Context | None = None) -> list[str]:
    """Extra `hgca complete` options chosen in the preferences (custom weights)."""
    prefs = addon_preferences(context)
    if prefs is not None and prefs.weights_path.strip():
        return ["--weights", bpy.path.abspath(prefs.weights_path.strip())]
    return []


class HGCA_OT_check_python(bpy.types.Operator):
    """Check that the core's Python runs a completion's first steps: torch and hgca_core import, the shipped
    weights load"""

    bl_idname = "hgca.check_python"
    bl_label = "Check"
    bl_options = {"INTERNAL"}

    def execute(self, context: bpy.types.Context) -> set[str]:
        python = core_python(context)
        prefs = addon_preferences(context)
        try:
            if not bpy.app.background:   # the interface: on a thread, the answer in a few seconds (no freeze)
                installer.start_check(python)
                if prefs is not None:
                    prefs.check_result = f"Checking {python}: importing torch and loading the weights ..."
                return {"FINISHED"}
            found = installer.check_core(python)
        except core.CoreError as exc:
            if prefs is not None:
                prefs.check_result = f"Error: {exc}"
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        text = installer.check_text(found, python)
        if prefs is not None:
            prefs.check_result = text
        self.report({"INFO"}, text)
        return {"FINISHED"}


class HGCA_OT_install_core(bpy.types.Operator):
    """Create a Python environment in the extension's user folder with hgca (from this extension) and torch
    (from the package index, or from a folder of wheels), in the background"""

    bl_idname = "hgca.install_core"
    bl_label = "Install Core"
    bl_options = {"INTERNAL"}

    def execute(self, context: bpy.types.Context) -> set[str]:
        prefs = addon_preferences(context)
        base = bpy.path.abspath(prefs.base_python.strip()) if prefs is not None and prefs.base_python.strip() \
            else sys.executable
        wheels = bpy.path.abspath(prefs.wheels_dir.strip()) if prefs is not None and prefs.wheels_dir.strip() else ""
        kind = prefs.torch_kind if prefs is not None else "cpu"
        index = (prefs.torch_index.strip() if kind == "cpu" else "") if prefs is not None else \
            installer.TORCH_CPU_INDEX
        try:
            job = installer.start_install(base, wheels, kind, index)
        except core.CoreError as exc:
            if prefs is not None:
                prefs.install_status = f"Error: {exc}"
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        self.report({"INFO"}, f"Installing the hGCA core into {job.env} (log: {job.log})")
        return {"FINISHED"}


class HGCA_OT_cancel_install(bpy.types.Operator):
    """Stop installing the core; the environment installed before (if any) stays as it was"""

    bl_idname = "hgca.cancel_install"
    bl_label = "Cancel"
    bl_options = {"INTERNAL"}

    @classmethod
    def poll(cls, context: bpy.types.Context) -> bool:
        return installer.running_install() is not None

    def execute(self, context: bpy.types.Context) -> set[str]:
        installer.cancel_install()
        self.report({"INFO"}, "hGCA core install cancelled")
        return {"FINISHED"}


class HGCA_AddonPreferences(bpy.types.AddonPreferences):
    bl_idname = __package__

    python_path: StringProperty(
        name="Core Python",
        subtype="FILE_PATH",
        update=lambda self, _context: setattr(self, "check_result", "") if self.check_result else None,
        description="Python interpreter that has hgca_core installed; empty = detect automatically",
    )
    weights_path: StringProperty(
        name="Coarse Weights",
        subtype="FILE_PATH",
        description="Weights file from `hgca train` (passed as --weights); empty = the shipped weights",
    )
    check_result: StringProperty(name="Check result", options={"SKIP_SAVE"})
    base_python: StringProperty(
        name="Base Python", subtype="FILE_PATH",
        description="Python 3.11+ that makes the core's environment; empty = the Python running Blender")
    wheels_dir: StringProperty(
        name="Wheels Folder", subtype="DIR_PATH",
        description="Offline install: a folder holding torch's and the other dependencies' wheels; empty = the "
                    "package index (needs online access)")
    torch_kind: EnumProperty(
        name="Torch", items=[("cpu", "CPU", "torch without CUDA (smaller download)"),
                             ("cuda", "CUDA", "torch with CUDA for NVIDIA GPUs (PyPI's Linux build, ~3 GB)")],
        default="cpu")
    torch_index: StringProperty(
        name="Torch Index", default=installer.TORCH_CPU_INDEX,
        description="Extra package index for the CPU torch; empty = only pip's own index")
    install_status: StringProperty(name="Install status", options={"SKIP_SAVE"})
    install_progress: FloatProperty(name="Install progress", min=0.0, max=1.0, subtype="FACTOR",
                                    options={"SKIP_SAVE"})

    def draw(self, context: bpy.types.Context) -> None:
        layout = self.layout
        row = layout.row(align=True)
        row.prop(self, "python_path")
        row.operator(HGCA_OT_check_python.bl_idname, icon="CHECKMARK")
        if not self.python_path.strip():
            detected = detect_python()
            layout.label(text=f"Detected: {detected}" if detected else
                         f"Not found: set it here or in the {ENV_VAR} environment variable", icon="INFO")
        layout.prop(self, "weights_path")
        if self.check_result:
            icon = "ERROR" if self.check_result.startswith("Error") else "CHECKMARK"
            layout.label(text=self.check_result, icon=icon)
        box = layout.box()
        box.label(text=f"Core environment: {installer.env_dir()}", icon="PACKAGE")
        box.prop(self, "base_python")
        box.prop(self, "wheels_dir")
        row = box.row()
        row.prop(self, "torch_kind", expand=True)
        if self.torch_kind == "cpu":
            box.prop(self, "torch_index")
        if not bpy.app.online_access and not self.wheels_dir.strip():
            box.label(text="Online access is off: allow it (System > Network) or choose a wheels folder",
                      icon="INTERNET_OFFLINE")
        row = box.row(align=True)
        job = installer.running_install()
        if job is None:
            row.operator(HGCA_OT_install_core.bl_idname, icon="IMPORT")
        else:
            row.progress(factor=self.install_progress, text=f"{self.install_progress * 100:.0f}%")
            row.operator(HGCA_OT_cancel_install.bl_idname, icon="CANCEL")
        if self.install_status:
            icon = "ERROR" if self.install_status.startswith("Error") else "INFO"
            box.label(text=self.install_status[:160], icon=icon)


CLASSES = (HGCA_OT_check_python, HGCA_OT_install_core, HGCA_OT_cancel_install, HGCA_AddonPreferences)


_register_classes, _unregister_classes = bpy.utils.register_classes_factory(CLASSES)


def register() -> None:
    _register_classes()


def unregister() -> None:
    installer.unregister()  # a running install is stopped; its half-made environment is removed
    _unregister_classes()
