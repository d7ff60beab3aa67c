"""The add-on's layout: its groups import one way, and the operators that start a job share one way to watch it."""
from __future__ import annotations

import ast
import time
from types import SimpleNamespace

import bpy
import pytest

from bl_helpers import REPO, addon_module

ADDON_DIR = REPO / "hgca_blender"
# Each group may import only groups of a lower rank (the root modules are groups of their own)
RANK = {"settings": 0, "scene": 1, "jobs": 2, "properties": 3, "preferences": 3, "operators": 4, "ui": 5,
        "batch": 6, "__init__": 6, "build_extension": 6}


def cross_group_imports() -> list[tuple[str, str, str]]:
    """(importing module, its group, imported group) for every relative import between two groups, lazy ones too."""
    found = []
    for path in sorted(ADDON_DIR.rglob("*.py")):
        if "__pycache__" in path.parts:
            continue
        parts = list(path.relative_to(ADDON_DIR).with_suffix("").parts)
        package = parts[:-1]
        for node in ast.walk(ast.parse(path.read_text())):
            if not isinstance(node, ast.ImportFrom) or not node.level:
                continue
            base = package[:len(package) - (node.level - 1)]
            targets = [base + node.module.split(".")] if node.module else [base + [a.name] for a in node.names]
            for target in targets:
                if target and target[0] != parts[0]:
                    found.append(("/".join(parts), parts[0], target[0]))
    return found


def test_groups_import_only_the_groups_below_them() -> None:
    found = cross_group_imports()
    assert {g for _, g, _ in found} >= {"jobs", "operators", "ui"}     # the walk sees the groups' imports at all
    upward = [(module, target) for module, group, target in found if RANK[target] >= RANK[group]]
    assert not upward, f"imports against the layering (settings < scene < jobs < properties < operators < ui): {upward}"


def test_scene_group_imports_no_other_group() -> None:
    assert not [(m, t) for m, g, t in cross_group_imports() if g == "scene"]


class StubJob:
    """A running job as the watching operators see it (a scene's entry in `ACTIVE`)."""

    def __init__(self) -> None:
        self.running, self.cancelled, self.finishing = True, False, None
        self.status, self.progress, self.started = "Tile 1 of 4", 0.25, time.monotonic()

    def cancel(self) -> None:
        self.running, self.cancelled = False, True

    def poll_once(self) -> bool:
        return self.running


WATCHING = [("operators.complete", "HGCA_OT_complete"), ("operators.drive", "HGCA_OT_drive"),
            ("operators.poses", "HGCA_OT_estimate_poses")]


@pytest.mark.parametrize("module, name", WATCHING)
def test_job_operators_watch_their_job_alike(addon, module: str, name: str) -> None:
    """Complete, Complete Along Drive and Estimate Poses: the same modal, Esc cancels, each reports its own line."""
    cls = getattr(addon_module(module), name)
    watching = addon_module("operators.watch").JobWatching
    assert issubclass(cls, watching)
    assert not {"invoke", "modal", "_finish"} & set(vars(cls))        # one copy of the watching, not one per operator
    jobs = addon_module("jobs.completion")
    job = jobs.ACTIVE[bpy.context.scene.name] = StubJob()
    reports: list = []
    watcher = SimpleNamespace(_timer=None, report=lambda kind, text: reports.append(text),
                              cancel_message=cls.cancel_message, status_text=cls.status_text,
                              _finish=lambda context: cls._finish(watcher, context))
    try:
        assert cls.modal(watcher, bpy.context, SimpleNamespace(type="MOUSEMOVE", value="NOTHING")) == {"PASS_THROUGH"}
        assert not job.cancelled and not reports
        shown = cls.status_text(job)
        assert callable(shown) or "Tile 1 of 4 (25%" in shown
        assert cls.modal(watcher, bpy.context, SimpleNamespace(type="ESC", value="PRESS")) == {"FINISHED"}
        assert job.cancelled and reports == [cls.cancel_message]
    finally:
        jobs.ACTIVE.pop(bpy.context.scene.name, None)


def test_each_cancel_says_what_it_leaves(addon) -> None:
    """A completion leaves nothing, a drive its finished tiles, Estimate Poses the folder as it was."""
    lines = {getattr(addon_module(module), name).cancel_message for module, name in WATCHING}
    assert len(lines) == len(WATCHING)
