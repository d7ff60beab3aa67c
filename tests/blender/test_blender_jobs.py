"""Completion jobs on real bpy and the real `hgca complete`, driven by poll_once() as in batch mode."""
from __future__ import annotations

import os
import time
from pathlib import Path

import bpy
import numpy as np
import pytest

from bl_helpers import NUSCENES, SMALL_REGION, addon_module, prefs, require_fixture, snapshot

JOB_TIMEOUT_S = 240


def import_nuscenes() -> bpy.types.Object:
    require_fixture(NUSCENES)
    before = set(bpy.data.objects.keys())
    assert bpy.ops.import_scene.hgca_lidar(filepath=str(NUSCENES)) == {"FINISHED"}
    (name,) = set(bpy.data.objects.keys()) - before
    obj = bpy.data.objects[name]
    obj.select_set(True)
    bpy.context.view_layer.objects.active = obj
    return obj


def use_numbers(region: tuple[float, ...], samples: int = 2, t1: int = 2) -> None:
    props = bpy.context.scene.hgca
    props.region_mode = "NUMBERS"
    props.region_center = region[:3]
    props.region_size = region[3:6]
    props.region_yaw = np.radians(region[6])
    props.samples, props.seed, props.stage, props.device, props.t1 = samples, 7, "coarse", "cpu", t1


def drive(job, timeout: float = JOB_TIMEOUT_S) -> list[float]:
    """poll_once() in a loop, as batch mode does; returns the progress values seen."""
    seen = []
    deadline = time.monotonic() + timeout
    while job.poll_once():
        seen.append(job.progress)
        assert time.monotonic() < deadline, f"job still running after {timeout} s: {job.status}"
        time.sleep(0.05)
    return seen


def test_completion_adds_one_mesh_per_sample_and_leaves_inputs_alone(addon, coarse_weights: str) -> None:
    jobs = addon_module("jobs")
    prefs().weights_path = coarse_weights
    scan = import_nuscenes()
    use_numbers(SMALL_REGION, samples=2)
    before = snapshot()

    assert bpy.ops.hgca.complete() == {"FINISHED"}
    job = jobs.active_job(bpy.context.scene.name)
    assert job is not None and job.workdir.is_dir()
    assert "--samples" in job.cmd and job.cmd[job.cmd.index("--samples") + 1] == "2"
    assert any(a.startswith("--region=") for a in job.cmd)
    progress = drive(job)

    assert job.state == "done", job.error
    assert not job.workdir.exists(), "temporary files must be removed"
    assert progress == sorted(progress) and job.progress == 1.0
    props = bpy.context.scene.hgca
    assert props.progress == 1.0 and props.status.startswith("Done") and not props.status_is_error

    after = snapshot()
    new_collections = set(after["collections"]) - set(before["collections"])
    assert len(new_collections) == 1
    coll = bpy.data.collections[new_collections.pop()]
    assert coll.name.startswith("hGCA ") and coll.name in after["scene_children"]
    results = sorted(coll.objects, key=lambda o: o["hgca_sample"])
    assert [o["hgca_sample"] for o in results] == [0, 1]
    for obj in results:
        mesh = obj.data
        assert obj.type == "MESH" and len(mesh.polygons) > 0 and len(mesh.edges) > 0
        attr = mesh.attributes["observed_distance"]
        assert attr.domain == "POINT" and attr.data_type == "FLOAT"
        dist = np.empty(len(mesh.vertices), dtype=np.float32)
        attr.data.foreach_get("value", dist)
        assert np.all(np.isfinite(dist)) and dist.min() >= 0
        mat = mesh.materials[0]
        node = next(n for n in mat.node_tree.nodes if n.bl_idname == "ShaderNodeAttribute")
        assert node.attribute_name == "observed_distance"
        bsdf = next(n for n in mat.node_tree.nodes if n.bl_idname == "ShaderNodeBsdfPrincipled")
        assert bsdf.inputs["Base Color"].is_linked
        co = np.empty(len(mesh.vertices) * 3, dtype=np.float32)
        mesh.vertices.foreach_get("co", co)
        lo, hi = np.array(SMALL_REGION[:3]) - 5.0, np.array(SMALL_REGION[:3]) + 5.0
        assert np.all(co.reshape(-1, 3) >= lo) and np.all(co.reshape(-1, 3) <= hi), "meshes stay in the region"
    assert results[0].visible_get() and not results[0].hide_render
    assert not results[1].visible_get() and results[1].hide_render

    # inputs unchanged: every object that existed before is identical, only new ones were added
    assert {k: after["objects"][k] for k in before["objects"]} == before["objects"]
    assert len(after["objects"]) == len(before["objects"]) + 2
    assert scan.name in after["objects"]


def test_cancel_leaves_the_scene_unchanged(addon, coarse_weights: str) -> None:
    jobs = addon_module("jobs")
    prefs().weights_path = coarse_weights
    import_nuscenes()
    use_numbers(SMALL_REGION, samples=1, t1=30)
    before = snapshot()
    assert bpy.ops.hgca.complete() == {"FINISHED"}
    job = jobs.active_job(bpy.context.scene.name)
    job.poll_once()
    assert job.running
    assert bpy.ops.hgca.cancel() == {"FINISHED"}
    assert job.state == "cancelled" and job._proc.poll() is not None
    with pytest.raises(ProcessLookupError):
        os.kill(job.pid, 0)
    assert not job.workdir.exists()
    assert jobs.active_job(bpy.context.scene.name) is None
    assert not job.poll_once()
    assert snapshot() == before
    assert bpy.context.scene.hgca.status == "Cancelled"


def test_core_error_is_reported_and_nothing_is_added(addon, coarse_weights: str) -> None:
    jobs = addon_module("jobs")
    prefs().weights_path = coarse_weights
    import_nuscenes()
    use_numbers((5000.0, 5000.0, 0.0, 9.6, 9.6, 4.0, 0.0), samples=1)  # no scan points inside
    before = snapshot()
    assert bpy.ops.hgca.complete() == {"FINISHED"}
    job = jobs.active_job(bpy.context.scene.name)
    drive(job)
    assert job.state == "error" and job.returncode == 2
    assert "no input points inside the region" in job.error
    props = bpy.context.scene.hgca
    assert props.status_is_error and "no input points inside the region" in props.status
    assert not job.workdir.exists()
    assert snapshot() == before


def test_missing_interpreter_fails_before_starting(addon) -> None:
    jobs = addon_module("jobs")
    import_nuscenes()
    use_numbers(SMALL_REGION)
    prefs().python_path = "/nonexistent/bin/python"
    before = snapshot()
    with pytest.raises(RuntimeError, match="Python interpreter not found"):
        bpy.ops.hgca.complete()
    assert jobs.active_job(bpy.context.scene.name) is None
    assert snapshot() == before


def test_no_source_selected_reports_error(addon) -> None:
    use_numbers(SMALL_REGION)
    with pytest.raises(RuntimeError, match="no source objects"):
        bpy.ops.hgca.complete()


def test_add_region_box_places_the_default_box(addon) -> None:
    region = addon_module("region")
    scan = import_nuscenes()
    before = snapshot()
    assert bpy.ops.hgca.add_region_box() == {"FINISHED"}
    props = bpy.context.scene.hgca
    box = props.region_object
    assert box is not None and props.region_mode == "BOX" and box.get("hgca_role") == "region"
    cx, cy, cz, sx, sy, sz, yaw = region.region_from_object(box)
    np.testing.assert_allclose((sx, sy, sz, yaw), (38.4, 38.4, 8.0, 0.0), atol=1e-5)
    pts = np.fromfile(NUSCENES, dtype=np.float32).reshape(-1, 5)[:, :3]
    np.testing.assert_allclose((cx, cy), np.median(pts[:, :2], axis=0), atol=1e-3)
    bottom = cz - sz / 2
    # nuScenes: sensor ~1.8 m above the road, so the road is near z = -1.8 and the bottom 1 m below it
    assert -3.6 < bottom < -2.2
    after = snapshot()
    assert {k: after["objects"][k] for k in before["objects"]} == before["objects"]
    # the box is not a source: the scan alone is
    assert addon_module("operators_complete").source_objects(bpy.context) == [scan]


def test_region_from_a_rotated_scaled_box(addon) -> None:
    region = addon_module("region")
    box = region.create_region_box(bpy.context.scene.collection, (10.0, -4.0, 2.0, 20.0, 30.0, 6.0, 30.0))
    got = region.region_from_object(box)
    np.testing.assert_allclose(got, (10.0, -4.0, 2.0, 20.0, 30.0, 6.0, 30.0), atol=1e-4)
    box.rotation_euler[0] = 0.3
    with pytest.raises(region.RegionError, match="tilted"):
        region.region_from_object(box)


def test_failed_result_build_rolls_back(addon, tmp_path: Path) -> None:
    mesh_build = addon_module("mesh_build")
    good = tmp_path / "out_s0.npz"
    bad = tmp_path / "out_s1.npz"
    np.savez(good, vertices=np.eye(3, dtype=np.float32), faces=np.array([[0, 1, 2]], np.int32),
             observed_distance=np.zeros(3, np.float32))
    np.savez(bad, vertices=np.eye(3, dtype=np.float32), faces=np.array([[0, 1, 7]], np.int32),
             observed_distance=np.zeros(3, np.float32))
    before = snapshot()
    with pytest.raises(ValueError, match="out of range"):
        mesh_build.build_results(bpy.context.scene, [good, bad], "hGCA test")
    assert snapshot() == before
    coll = mesh_build.build_results(bpy.context.scene, [good], "hGCA test")
    assert len(coll.objects) == 1 and len(coll.objects[0].data.polygons) == 1


def test_progress_parsing_tracks_samples(addon, tmp_path: Path) -> None:
    jobs = addon_module("jobs")
    job = jobs.Job.__new__(jobs.Job)  # exercise the event handling without a process
    job.samples, job._sample, job._last_sample_key, job.progress, job.status = 2, 0, None, 0.0, ""
    job._stage_names = ("read", "coarse", "mesh", "write")
    values = []
    for stage, step, total in [("read", 1, 1), ("coarse", 1, 2), ("coarse", 2, 2), ("mesh", 1, 2),
                               ("coarse", 1, 2), ("coarse", 2, 2), ("mesh", 2, 2), ("write", 2, 2)]:
        job._on_stage(stage, {"stage": stage, "step": step, "total": total, "message": "m"})
        values.append(job.progress)
    assert values == sorted(values) and values[-1] == pytest.approx(1.0)
    assert values[3] < 0.6 < values[4], "the second sample starts past the middle"
    assert jobs.parse_progress_line("not json")["stage"] == "log"
    assert jobs.parse_progress_line('{"stage": "done", "outputs": []}')["stage"] == "done"


def test_full_stage_with_shipped_weights_inserts_the_implicit_mesh(addon) -> None:
    """The default stage (full) on the shipped coarse and fine weights: one 10 cm implicit mesh, simplified to
    the panel's face limit, with the fine progress stage seen; the coarse stage passes no limit."""
    jobs = addon_module("jobs")
    prefs().weights_path = ""                       # the shipped weights
    import_nuscenes()
    counts = {}
    for stage in ("coarse", "full"):
        use_numbers(SMALL_REGION, samples=1, t1=4)
        props = bpy.context.scene.hgca
        props.stage, props.t2, props.max_faces = stage, 2, (5000 if stage == "full" else 0)
        before = snapshot()
        assert bpy.ops.hgca.complete() == {"FINISHED"}
        job = jobs.active_job(bpy.context.scene.name)
        stages = []
        deadline = time.monotonic() + JOB_TIMEOUT_S
        while job.poll_once():
            stages.append(props.status)
            assert time.monotonic() < deadline
            time.sleep(0.05)
        assert job.state == "done", job.error
        i = job.cmd.index("--max-faces")                   # always passed: 0 means every triangle
        assert job.cmd[i + 1] == ("5000" if stage == "full" else "0")
        assert any(st.startswith("Fine") for st in stages) == (stage == "full"), stages
        after = snapshot()
        (coll,) = set(after["collections"]) - set(before["collections"])
        (obj,) = bpy.data.collections[coll].objects
        counts[stage] = len(obj.data.polygons)
        assert "observed_distance" in obj.data.attributes
    assert counts["coarse"] > 0 and 0 < counts["full"] <= 5000
