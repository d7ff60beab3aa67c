"""Completion jobs on real bpy and the real `hgca complete`, driven by poll_once() as in batch mode."""
from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import bpy
import numpy as np
import pytest

from bl_helpers import CORE_PYTHON, NUSCENES, SMALL_REGION, addon_module, prefs, require_fixture, snapshot

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


def test_completion_adds_one_mesh_per_sample_and_leaves_inputs_alone(addon) -> None:
    jobs = addon_module("jobs.completion")
    scan = import_nuscenes()
    use_numbers(SMALL_REGION, samples=2)
    before = snapshot()

    assert bpy.ops.hgca.complete() == {"FINISHED"}
    job = jobs.active_job(bpy.context.scene.name)
    assert job is not None and job.workdir.is_dir()
    assert "--samples" in job.cmd and job.cmd[job.cmd.index("--samples") + 1] == "2"
    assert any(a.startswith("--region=") for a in job.cmd) and job.cmd[job.cmd.index("--t1") + 1] == "2"
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


def test_cancel_leaves_the_scene_unchanged(addon) -> None:
    jobs = addon_module("jobs.completion")
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


def test_core_error_is_reported_and_nothing_is_added(addon) -> None:
    jobs = addon_module("jobs.completion")
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
    jobs = addon_module("jobs.completion")
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


def core_region(*args: str) -> list[float]:
    """What `hgca region ... --json` says, run with the core's interpreter as the add-on runs it."""
    proc = subprocess.run([CORE_PYTHON, "-m", "hgca_core.cli", "region", *args, "--json"], capture_output=True,
                          text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout)["region"]


def test_add_region_box_places_the_box_hgca_region_gives(addon, tmp_path: Path) -> None:
    """One default region: the box the add-on adds around imported scans is the one `hgca region` (and so
    `hgca complete` without --region) gives for the same files, centred on the sensor, not on the points."""
    region = addon_module("scene.region")
    path = require_fixture(NUSCENES)
    pose = np.eye(4)
    pose[:3, :3] = [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]
    pose[:3, 3] = (100.0, -20.0, 3.0)
    poses = tmp_path / "poses.json"
    poses.write_text(json.dumps({"scans": [{"file": str(path), "pose": pose.tolist()}]}))
    before = snapshot()
    assert bpy.ops.import_scene.hgca_lidar(filepath=str(path), poses_path=str(poses)) == {"FINISHED"}
    (scan,) = [o for o in bpy.data.objects if o.name not in before["objects"]]
    scan.select_set(True)
    bpy.context.view_layer.objects.active = scan
    before = snapshot()

    assert bpy.ops.hgca.add_region_box() == {"FINISHED"}
    props = bpy.context.scene.hgca
    box = props.region_object
    assert box is not None and props.region_mode == "BOX" and box.get("hgca_role") == "region"
    got = region.region_from_object(box)
    expected = core_region(str(path), "--poses", str(poses))
    np.testing.assert_allclose(got, expected, atol=1e-4)       # the box Blender shows (float32)
    exact = region.world_region_of(bpy.context.scene, box)     # what goes to the core: bit for bit the CLI's
    assert list(exact) == expected and exact[2] != got[2]
    box.location.z += 0.01                                     # a moved box is read as it stands
    assert region.world_region_of(bpy.context.scene, box)[2] == region.decimal32(box.location.z)
    box.location.z -= 0.01
    np.testing.assert_allclose(got[:2], (100.0, -20.0), atol=1e-4)  # the sensor, where the pose put it
    # nuScenes: the HDL-32E sits 1.84 m above the road, so the road is near z = 3 - 1.84 and the box's bottom
    # 1 m below it (the ground estimator fits the road within a few cm on this sweep)
    assert abs((got[2] - got[5] / 2) - (3.0 - 1.84 - 1.0)) < 0.1
    after = snapshot()
    assert {k: after["objects"][k] for k in before["objects"]} == before["objects"]
    # the box is not a source: the scan alone is
    assert addon_module("operators.complete").source_objects(bpy.context) == [scan]

    # the panel's size goes to `hgca region --size`; moving the scan object moves its sensor with it
    scan.location = (5.0, 0.0, 0.0)
    props.region_size = (20.0, 10.0, 6.0)
    assert bpy.ops.hgca.add_region_box() == {"FINISHED"}
    got = region.region_from_object(props.region_object)
    np.testing.assert_allclose(got[:2], (105.0, -20.0), atol=1e-4)
    np.testing.assert_allclose(got[3:], (20.0, 10.0, 6.0, 0.0), atol=1e-4)


def test_add_region_box_without_the_core_adds_nothing(addon, tmp_path: Path) -> None:
    import_nuscenes()
    prefs().python_path = "/nonexistent/bin/python"
    before = snapshot()
    with pytest.raises(RuntimeError, match="Python interpreter not found"):
        bpy.ops.hgca.add_region_box()
    assert snapshot() == before and bpy.context.scene.hgca.region_object is None
    # a core from before `hgca region` existed: argparse refuses the command; the add-on says what to do
    old = tmp_path / "python"
    old.write_text("#!/bin/sh\necho \"hgca: error: argument command: invalid choice: 'region' "
                   "(choose from 'info', 'complete')\" >&2\nexit 2\n")
    old.chmod(0o755)
    prefs().python_path = str(old)
    with pytest.raises(RuntimeError, match="lacks a command this add-on needs: install the hgca version"):
        bpy.ops.hgca.add_region_box()
    assert snapshot() == before and bpy.context.scene.hgca.region_object is None


def test_panel_steps_default_to_the_weights(addon) -> None:
    """T1 = T2 = 0 in the panel means "the weights' own step counts": no --t1/--t2 goes to `hgca complete`."""
    jobs = addon_module("jobs.completion")
    props = bpy.context.scene.hgca
    assert (props.t1, props.t2) == (0, 0)
    params = jobs.CompletionParams(python=CORE_PYTHON, points=np.zeros((1, 3)), region=SMALL_REGION)
    args = jobs.completion_args(params, Path("in.npz"), Path("out.npz"))
    assert not [a for a in args if a.startswith(("--t1", "--t2"))], args
    params.t1 = 4
    args = jobs.completion_args(params, Path("in.npz"), Path("out.npz"))
    assert [a for a in args if a.startswith("--t")] == ["--t1"] and args[args.index("--t1") + 1] == "4"


def test_region_from_a_rotated_scaled_box(addon) -> None:
    region = addon_module("scene.region")
    box = region.create_region_box(bpy.context.scene.collection, (10.0, -4.0, 2.0, 20.0, 30.0, 6.0, 30.0))
    got = region.region_from_object(box)
    np.testing.assert_allclose(got, (10.0, -4.0, 2.0, 20.0, 30.0, 6.0, 30.0), atol=1e-4)
    box.rotation_euler[0] = 0.3
    with pytest.raises(region.RegionError, match="tilted"):
        region.region_from_object(box)
    camera = bpy.data.objects.new("Cam", bpy.data.cameras.new("Cam"))
    with pytest.raises(region.RegionError, match="'Cam' is a camera: use a mesh box or an empty"):
        region.region_from_object(camera)


def test_failed_result_build_rolls_back(addon, tmp_path: Path) -> None:
    mesh_build = addon_module("scene.mesh_build")
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


def test_progress_follows_the_records_sample_index(addon) -> None:
    """The whole-job fraction comes from each record's own `sample`/`samples`, not from guessing."""
    jobs, core = addon_module("jobs.completion"), addon_module("jobs.core")

    def fresh():
        job = jobs.CompletionJob.__new__(jobs.CompletionJob)  # the record handling, without a process
        job.samples, job.progress, job.status = 1, 0.0, ""
        job.stage_names = ("read", "coarse", "mesh", "write")
        return job

    def feed(job, stage, step, total, sample, samples=3):
        job.on_progress(stage, {"protocol": core.PROGRESS_PROTOCOL, "stage": stage, "step": step, "total": total,
                                "message": "m", "sample": sample, "samples": samples})
        return job.progress

    # weights of a coarse run: read 0.05, per sample coarse 0.45 + mesh 0.2, write 0.05 (of 0.75)
    assert feed(fresh(), "coarse", 1, 2, 2) == pytest.approx((0.05 + 0.65 * (2 + 0.225 / 0.65) / 3) / 0.75)
    job = fresh()
    records = [("read", 1, 1, 0), ("coarse", 1, 2, 0), ("coarse", 2, 2, 0), ("mesh", 1, 1, 0),
               ("coarse", 1, 2, 1), ("coarse", 2, 2, 1), ("mesh", 0, 1, 1), ("mesh", 1, 1, 1),
               ("coarse", 2, 2, 2), ("mesh", 1, 1, 2), ("write", 3, 3, 2)]
    values = [feed(job, *r) for r in records]
    assert values == sorted(values) and values[-1] == pytest.approx(1.0)
    assert values[3] == pytest.approx((0.05 + 0.65 / 3) / 0.75), "the first of three samples is a third"
    assert core.parse_progress_line("not json")["stage"] == "log"
    assert core.parse_progress_line('{"stage": "done", "outputs": []}')["stage"] == "done"


@pytest.mark.parametrize("record, message", [
    ({"protocol": 99, "stage": "read", "step": 0, "total": 1}, "writes progress protocol 99, this add-on reads"),
    ({"stage": "read", "step": 0, "total": 1}, "older than this add-on"),
])
def test_core_with_another_protocol_stops_with_a_clear_message(addon, tmp_path: Path, record: dict,
                                                              message: str) -> None:
    core = addon_module("jobs.core")
    workdir = tmp_path / "job"
    workdir.mkdir()
    script = f"import json, time; print(json.dumps({record!r}), flush=True); time.sleep(60)"
    t0 = time.monotonic()
    job = core.Job([sys.executable, "-c", script], workdir)
    assert job.wait(timeout=30) == "error"
    assert time.monotonic() - t0 < 10, "the core is stopped at its first record"
    assert message in job.error and "install" in job.error
    assert job._proc.poll() is not None and not workdir.exists()


def test_full_stage_with_shipped_weights_inserts_the_implicit_mesh(addon) -> None:
    """The default stage (full) on the shipped coarse and fine weights: one 10 cm implicit mesh, simplified to
    the panel's face limit, with the fine progress stage seen; the coarse stage passes no limit."""
    jobs = addon_module("jobs.completion")
    prefs().weights_path = ""                       # the shipped weights
    import_nuscenes()
    counts = {}
    for stage in ("coarse", "full"):
        use_numbers(SMALL_REGION, samples=1, t1=4)
        props = bpy.context.scene.hgca
        props.stage, props.t2, props.max_faces = stage, 2, 5000
        props.keep_all_faces = stage != "full"
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


def test_the_startup_cube_is_never_a_region_source(addon) -> None:
    """From Blender's startup file (the Cube selected and active): the import leaves the scan selected and active,
    so Add Region Box surrounds the scan; with only the Cube selected, the refusal names it."""
    bpy.ops.wm.read_homefile(use_empty=False, use_factory_startup=True)
    cube = bpy.data.objects["Cube"]
    assert cube.select_get() and bpy.context.view_layer.objects.active is cube
    require_fixture(NUSCENES)
    assert bpy.ops.import_scene.hgca_lidar(filepath=str(NUSCENES)) == {"FINISHED"}
    (scan,) = [o for o in bpy.data.objects if o.type == "MESH" and o.name not in ("Cube",)]
    assert bpy.context.view_layer.objects.active is scan and scan.select_get() and not cube.select_get()
    assert addon_module("operators.complete").source_objects(bpy.context) == [scan]

    scan.select_set(False)
    cube.select_set(True)
    bpy.context.view_layer.objects.active = cube
    before = snapshot()
    with pytest.raises(RuntimeError, match="'Cube' is a mesh with 6 face"):
        bpy.ops.hgca.add_region_box()
    with pytest.raises(RuntimeError, match="'Cube' is a mesh with 6 face"):
        bpy.ops.hgca.complete()
    assert snapshot() == before and bpy.context.scene.hgca.region_object is None


def test_a_core_killed_from_outside_says_so_and_what_to_try(addon, tmp_path: Path) -> None:
    """The out-of-memory killer's SIGKILL ends the core mid-run: the job's error names the signal and what to try,
    not the core's last progress line; a job that ends reports to the Info log either way."""
    import signal as signal_

    jobs, messages = addon_module("jobs.completion"), addon_module("jobs.messages")
    fake = tmp_path / "python"
    fake.write_text("#!/bin/sh\necho '{\"protocol\": 1, \"stage\": \"coarse\", \"step\": 1, \"total\": 30, "
                    "\"message\": \"hgca complete: working\"}'\necho 'hgca complete: working' >&2\n"
                    "kill -KILL $$\n")
    fake.chmod(0o755)
    params = jobs.CompletionParams(python=str(fake), points=np.zeros((10, 3)), region=SMALL_REGION,
                                   scene_name=bpy.context.scene.name)
    before = snapshot()
    job = jobs.start_job(params)
    drive(job, timeout=60)
    assert job.state == "error" and job.returncode == -signal_.SIGKILL
    assert "killed (SIGKILL)" in job.error and "smaller region" in job.error and "working" not in job.error
    assert snapshot() == before
    assert messages.job_messages(job)[-1][0] == "ERROR"


def test_a_finished_job_reports_in_the_info_log(addon) -> None:
    messages = addon_module("jobs.messages")

    class Ended:
        warnings: list = []
        state, error = "done", ""

        def success_status(self) -> str:
            return "Added 2 sample(s) to 'hGCA run'"

    assert messages.job_messages(Ended()) == [("INFO", "hGCA: Added 2 sample(s) to 'hGCA run'")]


def test_preview_button_asks_the_core_for_one_fast_smooth_sample(addon, tmp_path: Path) -> None:
    """*Preview* is *Complete* with the preview stage, one sample, the fast students; the panel's own settings
    (quality, stage, samples) go to the core as `hgca complete` takes them."""
    jobs, ops = addon_module("jobs.completion"), addon_module("operators.complete")
    import_nuscenes()
    use_numbers(SMALL_REGION, samples=3)
    props = bpy.context.scene.hgca
    props.quality = "best"
    args = jobs.completion_args(ops.gather_params(bpy.context, preview=True), tmp_path / "in.npz",
                                tmp_path / "out.npz")
    assert args[args.index("--stage") + 1] == "preview" and args[args.index("--quality") + 1] == "fast"
    assert args[args.index("--samples") + 1] == "1"
    args = jobs.completion_args(ops.gather_params(bpy.context), tmp_path / "in.npz", tmp_path / "out.npz")
    assert args[args.index("--stage") + 1] == "coarse" and args[args.index("--quality") + 1] == "best"
    assert args[args.index("--samples") + 1] == "3"


def test_add_region_box_in_the_interface_returns_at_once_and_adds_the_box_later(addon) -> None:
    """The interface's Add Region Box asks `hgca region` on a thread: starting takes well under a second, and the
    box (the same exact region as the synchronous path) arrives on a later main-thread poll."""
    ops = addon_module("operators.complete")
    scan = import_nuscenes()
    t = time.monotonic()
    ops.start_region_box(bpy.context)
    assert time.monotonic() - t < 1.0
    assert bpy.context.scene.hgca.region_object is None
    deadline = time.monotonic() + 120
    while (text := addon_module("jobs.background").poll("region_box")) is None:
        assert time.monotonic() < deadline
        time.sleep(0.1)
    box = bpy.context.scene.hgca.region_object
    assert text.startswith("Added") and f"'{scan.name}'" in text and box is not None
    assert list(addon_module("scene.region").world_region_of(bpy.context.scene, box)) == core_region(str(NUSCENES))
