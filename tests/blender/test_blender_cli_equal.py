"""The panel's completion of an imported real scan is `hgca complete`'s on the same file, region and seed.

Both sides run the coarse stage with 2 steps of the shipped weights (a few seconds a run on 2 cores); the
equality is on the mesh Blender ends up with: the CLI's .npz placed by the add-on's own rule, vertex for
vertex and face for face.
"""
from __future__ import annotations

import subprocess
import time
from pathlib import Path

import bpy
import numpy as np
import pytest

from bl_helpers import CORE_PYTHON, FIXTURES, NUSCENES, SMALL_REGION, addon_module, require_fixture

AV2_LOG = FIXTURES / "av2" / "7fab2350-7eaf-3b7e-a39d-6937a4c1bede"
SEED, T1 = 7, 2
JOB_TIMEOUT_S = 300


def cli_mesh(tmp: Path, inputs: list[str], region: tuple[float, ...]) -> dict[str, np.ndarray]:
    """`hgca complete INPUTS` as a user types it, with the panel's settings."""
    out = tmp / "cli.npz"
    cmd = [CORE_PYTHON, "-m", "hgca_core.cli", "complete", *inputs,
           "--region=" + ",".join(repr(float(v)) for v in region), "--samples", "1", "--seed", str(SEED),
           "--stage", "coarse", f"--t1={T1}", "--max-faces", "0", "--progress", "none", "-o", str(out)]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=600, cwd=tmp)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "warning" not in done.stderr, done.stderr
    with np.load(tmp / "cli_s0.npz") as data:
        return {k: data[k] for k in data.files}


def panel_complete(obj: bpy.types.Object, scene_region: tuple[float, ...]):
    """Complete from the panel (numbers region) with the active object as the source; the finished job."""
    jobs = addon_module("jobs.completion")
    obj.select_set(True)
    bpy.context.view_layer.objects.active = obj
    props = bpy.context.scene.hgca
    props.region_mode = "NUMBERS"
    props.region_center = scene_region[:3]
    props.region_size = scene_region[3:6]
    props.region_yaw = np.radians(scene_region[6])
    props.samples, props.seed, props.stage, props.device, props.t1 = 1, SEED, "coarse", "cpu", T1
    props.keep_all_faces = True
    assert bpy.ops.hgca.complete() == {"FINISHED"}
    job = jobs.active_job(bpy.context.scene.name)
    deadline = time.monotonic() + JOB_TIMEOUT_S
    while job.poll_once():
        assert time.monotonic() < deadline, job.status
        time.sleep(0.05)
    assert job.state == "done", job.error
    return job


def assert_same_mesh(job, want: dict[str, np.ndarray]) -> None:
    """The result object holds exactly the CLI's mesh, placed as the add-on places any result."""
    georef = addon_module("scene.georef")
    (obj,) = bpy.data.collections[job.collection_name].objects
    mesh = obj.data
    vertices, location = georef.place(want["vertices"], want["offset"], georef.scene_origin(bpy.context.scene))
    co = np.empty(len(mesh.vertices) * 3, dtype=np.float32)
    mesh.vertices.foreach_get("co", co)
    loops = np.empty(len(mesh.loops), dtype=np.int32)
    mesh.loops.foreach_get("vertex_index", loops)
    assert len(mesh.polygons) == len(want["faces"]) > 100
    assert np.array_equal(co.reshape(-1, 3), vertices)
    assert np.array_equal(np.array(obj.location), location.astype(np.float32))
    assert np.array_equal(loops, want["faces"].astype(np.int32).ravel())


def import_scan(**kwargs) -> bpy.types.Object:
    before = set(bpy.data.objects.keys())
    assert bpy.ops.import_scene.hgca_lidar(**kwargs) == {"FINISHED"}
    (name,) = set(bpy.data.objects.keys()) - before
    return bpy.data.objects[name]


def test_nuscenes_sweep_panel_mesh_is_the_clis(addon, tmp_path: Path) -> None:
    require_fixture(NUSCENES)
    scan = import_scan(filepath=str(NUSCENES))
    job = panel_complete(scan, SMALL_REGION)
    assert not job.warnings, job.warnings  # no "no sensor origins: observed free space is unknown"
    assert str(NUSCENES) in job.cmd
    assert_same_mesh(job, cli_mesh(tmp_path, [str(NUSCENES)], SMALL_REGION))


def test_points_sent_without_the_file_carry_their_rays(addon, tmp_path: Path) -> None:
    """A scan that no longer names its file (here: the record removed) goes as points with its sensor origins
    and origin index; on the sensor-frame nuScenes sweep that is still the CLI's mesh."""
    require_fixture(NUSCENES)
    scan = import_scan(filepath=str(NUSCENES))
    del scan[addon_module("jobs.job_inputs").SOURCE_KEY]
    job = panel_complete(scan, SMALL_REGION)
    assert str(NUSCENES) not in job.cmd and not job.warnings, job.warnings
    assert_same_mesh(job, cli_mesh(tmp_path, [str(NUSCENES)], SMALL_REGION))


def test_moved_scan_is_sent_as_its_points(addon) -> None:
    require_fixture(NUSCENES)
    scan = import_scan(filepath=str(NUSCENES))
    scan.location.x += 1.0
    job_inputs = addon_module("jobs.job_inputs")
    assert job_inputs.unchanged_files(bpy.context.scene, [scan]) is None
    scan.location.x -= 1.0
    assert job_inputs.unchanged_files(bpy.context.scene, [scan]).paths == [str(NUSCENES)]


def test_av2_log_two_frames_panel_mesh_is_the_clis(addon, tmp_path: Path) -> None:
    if not AV2_LOG.is_dir():
        pytest.skip(f"real AV2 log missing: {AV2_LOG}")
    scan = import_scan(directory=str(AV2_LOG) + "/", frames="0:2")
    georef, sources = addon_module("scene.georef"), addon_module("scene.sources")
    first = georef.to_world(bpy.context.scene, sources.world_origins([scan]))[0]  # city frame, km from zero
    # as a user types it: centimetres, in the world frame the CLI takes
    world_region = (*(round(float(v), 2) for v in first[:2]), round(float(first[2]) - 1.0, 2), 9.6, 9.6, 4.0, 30.0)
    job = panel_complete(scan, georef.region_to_scene(bpy.context.scene, world_region))
    assert job.params.region == world_region
    assert not job.warnings, job.warnings
    assert_same_mesh(job, cli_mesh(tmp_path, [str(AV2_LOG), "--frames", "0:2"], world_region))


def test_core_warnings_reach_blenders_report_list(addon, tmp_path: Path, capfd) -> None:
    """Points with no sensor origins: the core's warning is the job's and goes through `report`."""
    require_fixture(NUSCENES)
    scan = import_scan(filepath=str(NUSCENES))
    del scan[addon_module("jobs.job_inputs").SOURCE_KEY]
    del scan[addon_module("scene.sources").ORIGINS_KEY]
    capfd.readouterr()
    job = panel_complete(scan, SMALL_REGION)
    assert any(w.startswith("no sensor origins") for w in job.warnings), job.warnings
    printed = capfd.readouterr()
    assert "no sensor origins" in printed.out + printed.err
