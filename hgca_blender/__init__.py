"""hGCA Blender extension: import LiDAR scans and complete them into meshes with hgca_core.

The add-on is a thin layer (UI, a job runner, Blender data from arrays); the model runs in a separate
Python interpreter (`<python> -m hgca_core.cli`), so Blender never imports torch or hgca_core.
Submodules are imported in `register()` so that bpy-free tools in this package
(`python -m hgca_blender.build_extension`) do not start Blender.
"""
from __future__ import annotations

import importlib
from types import ModuleType

# Registration order: properties before the panels that draw them, preferences before operators use them.
_MODULES = ("properties", "messages", "preferences", "jobs", "operators_import", "operators_complete", "operators_drive",
            "operators_results", "operators_georef", "operators_poses", "panels")


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
