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
from bpy.props import StringProperty

from . import core

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
    """Run `<python> -m hgca_core.cli --version` to see whether the core can be used"""

    bl_idname = "hgca.check_python"
    bl_label = "Check"
    bl_options = {"INTERNAL"}

    def execute(self, context: bpy.types.Context) -> set[str]:
        python = core_python(context)
        prefs = addon_preferences(context)
        try:
            proc = core.run_core(python, ["--version"], timeout=120)
        except core.CoreError as exc:
            if prefs is not None:
                prefs.check_result = f"Error: {exc}"
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        version = (proc.stdout.strip() or proc.stderr.strip()).splitlines()[-1]
        if prefs is not None:
            prefs.check_result = f"{version} ({python})"
        self.report({"INFO"}, f"{version} ({python})")
        return {"FINISHED"}


class HGCA_AddonPreferences(bpy.types.AddonPreferences):
    bl_idname = __package__

    python_path: StringProperty(
        name="Core Python",
        subtype="FILE_PATH",
        description="Python interpreter that has hgca_core installed; empty = detect automatically",
    )
    weights_path: StringProperty(
        name="Coarse Weights",
        subtype="FILE_PATH",
        description="Weights file from `hgca train` (passed as --weights); empty = the shipped weights",
    )
    check_result: StringProperty(name="Check result", options={"SKIP_SAVE"})

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


CLASSES = (HGCA_OT_check_python, HGCA_AddonPreferences)


register, unregister = bpy.utils.register_classes_factory(CLASSES)
