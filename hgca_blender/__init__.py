"""hGCA Blender extension: import LiDAR scans and complete them into meshes with hgca_core.

The add-on is a thin layer; the model runs in a separate Python interpreter (`<python> -m hgca_core.cli`), so
Blender never imports torch or hgca_core. Its modules are grouped by what they are, each group importing only
those below it:

    ui/             the sidebar panels
    operators/      import, complete, drive, poses, georeference, results (and the Esc / status bar part they share)
    properties.py   the panel's settings (`scene.hgca`); preferences.py: the add-on's preferences
    jobs/           the core's process: one-shot calls, background jobs, Install Core, what a job hands the core
    scene/          Blender data from arrays: meshes, point clouds, colours, classes, regions, the georeference origin
    settings.py     the core's settings schema (defaults, bounds, flags) the properties and the jobs are made from

Submodules are imported in `register()` so that bpy-free tools in this package
(`python -m hgca_blender.build_extension`) do not start Blender.
"""
from __future__ import annotations

import importlib
from types import ModuleType

# Registration order: properties before the panels that draw them, preferences before operators use them.
_MODULES = ("properties", "jobs.messages", "preferences", "jobs.completion", "operators.import_scans",
            "operators.complete", "operators.drive", "operators.results", "operators.georef", "operators.poses",
            "ui.panels")


def _modules() -> list[ModuleType]:
    return [importlib.import_module(f"{__name__}.{name}") for name in _MODULES]


def register() -> None:
    done: list[ModuleType] = []
    try:
        for module in _modules():
            module.register()
            done.append(module)
    except Exception:
        for module in reversed(done):  # leave Blender as it was if any part fails to register
            module.unregister()
        raise


def unregister() -> None:
    for module in reversed(_modules()):
        module.unregister()
