"""Messages where Blender users look: the Info editor and the status bar, also for jobs that end in a timer.

An operator's `self.report` is the one way into Blender's report list (the Info editor, the status bar line,
the console in background mode), but a job ends long after its operator returned, inside a timer. So the
add-on keeps one internal operator whose only work is to report what it is given; `report()` calls it.
"""
from __future__ import annotations

import sys

import bpy
from bpy.props import EnumProperty, StringProperty

LEVELS = ("INFO", "WARNING", "ERROR")


class HGCA_OT_report(bpy.types.Operator):
    """Show a message of the hGCA add-on in the Info editor and the status bar"""

    bl_idname = "hgca.report"
    bl_label = "hGCA Message"
    bl_options = {"INTERNAL"}

    level: EnumProperty(items=[(v, v.title(), "") for v in LEVELS], default="INFO")
    message: StringProperty()

    def execute(self, context: bpy.types.Context) -> set[str]:
        self.report({self.level}, self.message)
        return {"FINISHED"}


def report(level: str, message: str) -> None:
    """Report `message` through Blender's report list (ERROR, WARNING or INFO); stderr when that fails."""
    level = level if level in LEVELS else "INFO"
    try:
        wm = getattr(bpy.context, "window_manager", None)
        windows = list(wm.windows) if wm is not None else []
        if windows:
            with bpy.context.temp_override(window=windows[0]):
                bpy.ops.hgca.report(level=level, message=message)
        else:
            bpy.ops.hgca.report(level=level, message=message)
    except RuntimeError:  # an ERROR report raises in the caller once it has been shown
        if level != "ERROR":
            print(f"hGCA: {level.lower()}: {message}", file=sys.stderr)
    except AttributeError:  # the add-on is being unregistered: the operator is gone
        print(f"hGCA: {level.lower()}: {message}", file=sys.stderr)


def job_messages(job) -> list[tuple[str, str]]:
    """(level, text) of what an ended job has to say: the core's warnings, then its error."""
    out = [("WARNING", f"hgca: {w}") for w in getattr(job, "warnings", [])]
    if job.state == "error" and job.error:
        out.append(("ERROR", f"hGCA job failed: {job.error}"))
    elif job.state == "done":
        out.append(("INFO", f"hGCA: {job.success_status()}"))
    elif job.state == "cancelled":
        out.append(("INFO", "hGCA: job cancelled"))
    return out


def report_job(job) -> None:
    for level, text in job_messages(job):
        report(level, text)


CLASSES = (HGCA_OT_report,)

register, unregister = bpy.utils.register_classes_factory(CLASSES)
