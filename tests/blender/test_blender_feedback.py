"""Feedback where Blender users look: Esc cancels, errors in the report list, limits the core accepts, no stale
labels."""
from __future__ import annotations

import time
from pathlib import Path
from types import SimpleNamespace

import bpy
import numpy as np
import pytest

from bl_helpers import CORE_PYTHON, NUSCENES, SMALL_REGION, addon_module, prefs, require_fixture


def start_completion(t1: int = 30):
    require_fixture(NUSCENES)
    assert bpy.ops.import_scene.hgca_lidar(filepath=str(NUSCENES)) == {"FINISHED"}
    scan = next(o for o in bpy.data.objects if o.get("hgca_role") == "scan")
    scan.select_set(True)
    bpy.context.view_layer.objects.active = scan
    props = bpy.context.scene.hgca
    props.region_mode = "NUMBERS"
    props.region_center, props.region_size = SMALL_REGION[:3], SMALL_REGION[3:6]
    props.samples, props.stage, props.t1 = 1, "coarse", t1
    assert bpy.ops.hgca.complete() == {"FINISHED"}
    return addon_module("jobs.completion").active_job(bpy.context.scene.name)


def test_escape_in_the_modal_cancels_the_running_job(addon) -> None:
    job = start_completion()
    ops = addon_module("operators.complete")
    reports = []
    watcher = SimpleNamespace(_timer=None, report=lambda kind, text: reports.append((kind, text)),
                              cancel_message=ops.HGCA_OT_complete.cancel_message,
                              status_text=ops.HGCA_OT_complete.status_text,
                              _finish=lambda context: ops.HGCA_OT_complete._finish(watcher, context))
    other = SimpleNamespace(type="MOUSEMOVE", value="NOTHING")
    assert ops.HGCA_OT_complete.modal(watcher, bpy.context, other) == {"PASS_THROUGH"}
    assert job.running
    esc = SimpleNamespace(type="ESC", value="PRESS")
    assert ops.HGCA_OT_complete.modal(watcher, bpy.context, esc) == {"FINISHED"}
    assert job.state == "cancelled" and not job.workdir.exists()
    assert reports and "cancelled" in reports[-1][1]
    assert not any(c.name.startswith("hGCA ") for c in bpy.data.collections)


def test_modal_ends_with_the_job(addon) -> None:
    job = start_completion(t1=2)
    ops = addon_module("operators.complete")
    watcher = SimpleNamespace(_timer=None, report=lambda *a: None, status_text=ops.HGCA_OT_complete.status_text,
                              _finish=lambda context: ops.HGCA_OT_complete._finish(watcher, context))
    deadline = time.monotonic() + 240
    while job.poll_once():
        assert time.monotonic() < deadline
        time.sleep(0.05)
    addon_module("jobs.completion").poll_all()
    tick = SimpleNamespace(type="TIMER", value="NOTHING")
    assert ops.HGCA_OT_complete.modal(watcher, bpy.context, tick) == {"FINISHED"}


def test_job_error_reaches_the_report_list(addon, tmp_path: Path, capfd) -> None:
    """A completion that fails in the core says why through Blender's reports, not only on stderr."""
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"not weights")
    prefs().weights_path = str(bad)
    job = start_completion(t1=2)
    capfd.readouterr()
    while job.poll_once():
        time.sleep(0.05)
    assert job.state == "error"
    printed = capfd.readouterr()
    assert "Error: hGCA job failed:" in printed.out + printed.err


@pytest.mark.parametrize("typed, kept", [(0, 1000), (1, 1000), (999, 1000), (1000, 1000), (25000, 25000)])
def test_max_faces_takes_only_what_the_core_accepts(addon, typed: int, kept: int) -> None:
    """The core takes 0 (keep all: its own toggle) or at least 1000 triangles; the field holds nothing else."""
    props = bpy.context.scene.hgca
    props.max_faces = typed
    assert props.max_faces == kept
    props.keep_all_faces = False
    assert addon_module("properties").face_limit(props) == kept
    props.keep_all_faces = True
    assert addon_module("properties").face_limit(props) == 0


def test_status_saved_mid_job_is_cleared_on_load(addon, tmp_path: Path) -> None:
    props = bpy.context.scene.hgca
    props.status, props.progress = "Coarse 3/30", 0.4
    path = tmp_path / "mid.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(path))
    bpy.ops.wm.open_mainfile(filepath=str(path))
    props = bpy.context.scene.hgca
    assert props.status == "" and props.progress == 0.0


def test_check_result_is_cleared_when_the_python_changes(addon) -> None:
    prefs().python_path = CORE_PYTHON
    prefs().check_result = "hgca 0.1.0, torch 2.13.0: the shipped weights load"
    prefs().python_path = "/usr/bin/python3"
    assert prefs().check_result == ""


def test_region_numbers_reach_the_core_as_typed(addon) -> None:
    """Float32 properties hold 9.600000381...; the core gets the 9.6 the user typed."""
    props = bpy.context.scene.hgca
    props.region_mode = "NUMBERS"
    props.region_center, props.region_size, props.region_yaw = (1.1, -2.3, 0.7), (9.6, 12.8, 4.4), np.radians(30)
    got = addon_module("operators.complete").panel_region(bpy.context)
    assert got == (1.1, -2.3, 0.7, 9.6, 12.8, 4.4, 30.0)


def test_operators_are_callable_from_scripts_under_hgca(addon, tmp_path: Path) -> None:
    """A script imports, boxes and completes with `bpy.ops.hgca.*` alone (the drive operators live there too)."""
    require_fixture(NUSCENES)
    assert bpy.ops.hgca.import_scan(filepath=str(NUSCENES), color_by="HEIGHT") == {"FINISHED"}
    scan = next(o for o in bpy.data.objects if o.get("hgca_role") == "scan")
    scan.select_set(True)
    bpy.context.view_layer.objects.active = scan
    bpy.context.scene.hgca.region_size = (9.6, 9.6, 4.0)
    assert bpy.ops.hgca.add_region_box() == {"FINISHED"}
    assert {"complete", "cancel", "drive", "drive_plan"} <= set(dir(bpy.ops.hgca))


def test_time_left_follows_the_rate_so_far(addon) -> None:
    jobs = addon_module("jobs.completion")
    job = SimpleNamespace(progress=0.25, started=time.monotonic() - 30.0)
    assert jobs.time_left(job) == ", about 1 min 30 s left"
    job.progress = 0.01
    assert jobs.time_left(job) == ""
