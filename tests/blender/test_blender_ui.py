"""Panels, preferences and registration: the UI code runs against a recording layout.

The bpy module has no windows, so `draw()` is called with a stand-in layout that checks every property
and operator it is asked to show really exists (a typo there would otherwise only show in the GUI).
"""
from __future__ import annotations

import addon_utils
import bpy
import pytest

from bl_helpers import ADDON, addon_module


class Recorder:
    """A UILayout stand-in: validates names and records what would be drawn."""

    def __init__(self, log: list[tuple[str, str]]) -> None:
        self.log = log
        self.use_property_split = self.use_property_decorate = False
        self.enabled = True
        self.scale_y = 1.0

    def _sub(self, *_a, **_k) -> "Recorder":
        return Recorder(self.log)

    row = column = box = split = _sub

    def prop(self, data, name: str, **_k) -> None:
        if name.startswith('["'):  # an ID property (a modifier's node-group input)
            assert name[2:-2] in data.keys(), f"{data.name!r} has no input {name!r}"
        else:
            assert name in data.bl_rna.properties, f"{type(data).__name__} has no property {name!r}"
        self.log.append(("prop", name))

    def operator(self, idname: str, **_k):
        category, name = idname.split(".")
        assert hasattr(getattr(bpy.ops, category), name), f"no operator {idname}"
        self.log.append(("operator", idname))
        return type("OperatorProperties", (), {})()

    def label(self, text: str = "", **_k) -> None:
        self.log.append(("label", text))

    def progress(self, factor: float = 0.0, type: str = "BAR", text: str = "") -> None:  # noqa: A002
        assert 0.0 <= factor <= 1.0
        self.log.append(("progress", text))


def draw(panel_cls, context=None) -> list[tuple[str, str]]:
    log: list[tuple[str, str]] = []
    fake = type("P", (), {"layout": Recorder(log)})()
    panel_cls.draw(fake, context or bpy.context)
    return log


def test_panels_draw_every_setting(addon) -> None:
    panels = addon_module("ui.panels")
    props = bpy.context.scene.hgca
    main = draw(panels.HGCA_PT_main)
    shown = {name for kind, name in main if kind == "prop"}
    assert {"source_mode", "region_mode", "region_object", "samples", "seed", "stage", "quality", "max_faces",
            "device"} <= shown
    props.region_mode, props.source_mode = "NUMBERS", "COLLECTION"
    shown = {name for kind, name in draw(panels.HGCA_PT_main) if kind == "prop"}
    assert {"region_center", "region_size", "region_yaw", "source_collection"} <= shown
    assert ("operator", "hgca.add_region_box") in main
    assert {name for kind, name in draw(panels.HGCA_PT_advanced) if kind == "prop"} == {"t1", "t2"}
    assert panels.HGCA_PT_main.bl_category == "hGCA" and panels.HGCA_PT_main.bl_region_type == "UI"


def test_main_panel_shows_the_active_scans_point_size_and_a_results_samples(addon, tmp_path) -> None:
    import numpy as np

    panels, mesh_build = addon_module("ui.panels"), addon_module("scene.mesh_build")
    pts = np.random.default_rng(0).uniform(0, 1, (50, 3)).astype(np.float32)
    scan, _ = mesh_build.build_point_object("scan", pts, {}, bpy.context.scene.collection)
    bpy.context.view_layer.objects.active = scan
    assert any(kind == "prop" and name.startswith('["') for kind, name in draw(panels.HGCA_PT_main))
    paths = []
    for i in range(2):
        paths.append(tmp_path / f"out_s{i}.npz")
        np.savez(paths[-1], vertices=np.eye(3, dtype=np.float32) + i, faces=np.array([[0, 1, 2]], np.int32),
                 observed_distance=np.zeros(3, np.float32))
    coll = mesh_build.build_results(bpy.context.scene, paths, "hGCA test")
    bpy.context.view_layer.objects.active = next(o for o in coll.objects if o["hgca_sample"] == 0)
    log = draw(panels.HGCA_PT_main)
    assert ("label", "Sample 0 of 2") in log and ("operator", "hgca.step_sample") in log
    assert ("operator", "hgca.result_colors") in log


def test_job_panel_shows_progress_and_cancel_while_running(addon) -> None:
    panels, jobs = addon_module("ui.panels"), addon_module("jobs.completion")
    job_panel = draw(panels.HGCA_PT_job)
    assert ("operator", "hgca.complete") in job_panel
    assert sum(1 for item in job_panel if item == ("operator", "hgca.complete")) == 2   # Complete and Preview

    class Running:
        running = True

    scene = bpy.context.scene
    scene.hgca.progress, scene.hgca.status = 0.25, "Coarse 3/30"
    jobs.ACTIVE[scene.name] = Running()
    try:
        log = draw(panels.HGCA_PT_job)
    finally:
        jobs.ACTIVE.pop(scene.name)
    assert ("operator", "hgca.cancel") in log and ("progress", "Coarse 3/30") in log


def test_preferences_draw(addon) -> None:
    preferences = addon_module("preferences")
    prefs = bpy.context.preferences.addons[ADDON].preferences
    log: list[tuple[str, str]] = []
    fake = type("P", (), {"layout": Recorder(log), "python_path": "", "weights_path": "", "check_result": "",
                          "base_python": "", "wheels_dir": "", "torch_kind": "cpu", "torch_index": "",
                          "install_status": "", "install_progress": 0.0, "bl_rna": prefs.bl_rna})()
    preferences.HGCA_AddonPreferences.draw(fake, bpy.context)
    assert ("prop", "python_path") in log and ("operator", "hgca.check_python") in log
    assert ("operator", "hgca.install_core") in log and ("prop", "wheels_dir") in log


def test_disable_unregisters_everything_and_enable_restores(addon) -> None:
    addon_utils.disable(ADDON, default_set=True)
    try:
        assert not hasattr(bpy.types.Scene, "hgca")
        assert not _op_registered("import_scene.hgca_lidar")
        assert not _op_registered("hgca.complete")
    finally:
        assert addon_utils.enable(ADDON, default_set=True, handle_error=None) is not None
    assert hasattr(bpy.types.Scene, "hgca") and _op_registered("hgca.complete")


def _op_registered(idname: str) -> bool:
    category, name = idname.split(".")
    try:
        getattr(getattr(bpy.ops, category), name).get_rna_type()
    except KeyError:
        return False
    return True


def test_timer_is_registered_by_complete(addon) -> None:
    jobs = addon_module("jobs.completion")
    from bl_helpers import NUSCENES, SMALL_REGION, prefs, require_fixture

    require_fixture(NUSCENES)
    bpy.ops.import_scene.hgca_lidar(filepath=str(NUSCENES))
    obj = bpy.data.objects[0]
    obj.select_set(True)
    props = bpy.context.scene.hgca
    props.region_mode, props.region_center, props.region_size = "NUMBERS", SMALL_REGION[:3], SMALL_REGION[3:6]
    assert bpy.ops.hgca.complete() == {"FINISHED"}
    try:
        assert bpy.app.timers.is_registered(jobs._timer_tick)
        with pytest.raises(RuntimeError):  # one job per scene
            bpy.ops.hgca.complete()
    finally:
        jobs.cancel_all()


def test_registered_panel_properties_are_the_cores_settings(addon) -> None:
    """Defaults, bounds and choices of the panel's properties, read back from Blender's RNA, are the core's
    (`hgca_core.config.addon_limits`, carried by the zip's core_settings.json)."""
    from hgca_core.config import addon_limits

    rna = bpy.context.scene.hgca.bl_rna.properties
    for name, core in addon_limits().items():
        prop = rna[name]
        assert prop.default == pytest.approx(core["default"]) if prop.type != "ENUM" else prop.default == core[
            "default"], name
        if "choices" in core:
            assert {item.identifier for item in prop.enum_items} <= set(core["choices"]), name
        if core.get("min") is not None:
            assert prop.hard_min >= core["min"] - 1e-6, name
        if core.get("max") is not None:
            assert prop.hard_max <= core["max"], name
