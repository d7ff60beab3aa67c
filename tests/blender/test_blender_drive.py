"""Complete along drive in the panel, on real bpy and the real `hgca drive`: the tiles the core plans drawn as
boxes, a run to completion with one object per tile per sample, resuming, and cancel keeping finished tiles.

A small synthetic drive (tests/drive/drive_data.py, numpy only) is imported as one sequence object; the core
runs small untrained weights (made by the core's own interpreter) on 12.8 m tiles, coarse stage, so a tile
takes a second or so."""
from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import bpy
import numpy as np
import pytest

from bl_helpers import REPO, addon_module, core_arrays, prefs, snapshot

sys.path.insert(0, str(REPO / "tests" / "drive"))
from drive_data import write_drive  # noqa: E402

TIMEOUT_S = 300


@pytest.fixture(scope="module")
def small_weights(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("w") / "coarse_small.pt"
    core_arrays("import torch\nfrom hgca_core.models.gca import GCAConfig, GCAKernel\n"
                "from hgca_core.training.export import save_weights\ntorch.manual_seed(0)\n"
                f"save_weights({str(path)!r}, GCAKernel(GCAConfig(channels=(8, 8, 16, 16, 16), steps=3)), "
                "{'stage': 'test'})", ok="1")
    return path


def import_drive(folder: Path, length: float) -> tuple[bpy.types.Object, list[Path], Path]:
    """The drive's scans imported as one object (scan files + poses: a sequence import), selected."""
    files, poses = write_drive(folder, length=length)
    before = set(bpy.data.objects.keys())
    assert bpy.ops.import_scene.hgca_lidar(files=[{"name": f.name} for f in files], directory=str(folder),
                                           poses_path=str(poses)) == {"FINISHED"}
    (name,) = set(bpy.data.objects.keys()) - before
    obj = bpy.data.objects[name]
    obj.select_set(True)
    bpy.context.view_layer.objects.active = obj
    return obj, files, poses


def use_drive_settings(weights: Path, folder: Path, samples: int = 1, t1: int = 2) -> None:
    prefs().weights_path = str(weights)
    props = bpy.context.scene.hgca
    props.samples, props.seed, props.stage, props.t1, props.keep_all_faces = samples, 3, "coarse", t1, True
    props.drive_tile_size, props.drive_overlap, props.drive_dir = 12.8, 3.2, str(folder)


def user_objects_unchanged(before: dict) -> None:
    after = snapshot()
    for name, entry in before["objects"].items():
        assert after["objects"].get(name) == entry, f"{name} changed"


def run_to_end(job, until=None) -> list[float]:
    seen, deadline = [], time.monotonic() + TIMEOUT_S
    while job.poll_once():
        seen.append(job.progress)
        if until is not None and until(job):
            break
        assert time.monotonic() < deadline, f"drive still running after {TIMEOUT_S} s: {job.status}"
        time.sleep(0.05)
    return seen


def world_regions(objects) -> np.ndarray:
    region, georef = addon_module("scene.region"), addon_module("scene.georef")
    return np.array([georef.region_to_world(bpy.context.scene, region.region_from_object(o)) for o in objects])


def test_show_tiles_draws_the_core_plan_as_boxes(addon, small_weights, tmp_path) -> None:
    _, files, poses = import_drive(tmp_path / "scans", length=30.0)
    use_drive_settings(small_weights, tmp_path / "drive")
    before = snapshot()
    for _ in range(2):                                 # a second plan replaces the first one's boxes
        assert bpy.ops.hgca.drive_plan() == {"FINISHED"}
    user_objects_unchanged(before)
    (coll,) = [c for c in bpy.context.scene.collection.children if c.get("hgca_role") == "drive_plan"]
    boxes = sorted(coll.objects, key=lambda o: o["hgca_tile"])
    assert [o["hgca_tile"] for o in boxes] == [0, 1, 2]
    assert sum(o.get("hgca_tile") is not None for o in bpy.data.objects) == 3 and not (tmp_path / "drive").exists()
    # the core's plan from the scan files themselves (float64), not from what the add-on sent
    expected = core_arrays(
        "from hgca_core.tiling.inputs import read_drive_inputs\nfrom hgca_core.tiling.run import plan_drive\n"
        f"scans = read_drive_inputs({[str(f) for f in files]!r}, poses={str(poses)!r})\n"
        "_, regions, _ = plan_drive(scans, 12.8, 3.2, 5)", regions="[r.as_tuple() for r in regions]")["regions"]
    got = world_regions(boxes)
    assert np.allclose(got[:, :6], expected[:, :6], atol=2e-3), (got, expected)
    assert np.allclose(got[:, 6], expected[:, 6], atol=1e-3)
    assert all(o.display_type == "WIRE" and o.hide_render for o in boxes)


def test_drive_completes_one_object_per_tile_per_sample_and_resumes(addon, small_weights, tmp_path) -> None:
    jobs = addon_module("jobs.completion")
    scan, _, _ = import_drive(tmp_path / "scans", length=16.0)
    folder = tmp_path / "drive"
    use_drive_settings(small_weights, folder, samples=2)
    before = snapshot()
    assert bpy.ops.hgca.drive() == {"FINISHED"}
    job = jobs.active_job(bpy.context.scene.name)
    assert job is not None and not bpy.ops.hgca.drive.poll(), "one job per scene"
    progress = run_to_end(job)
    assert job.state == "done", job.error
    assert progress == sorted(progress) and job.progress == 1.0
    assert job.status == f"Done: 2 tiles x 2 sample(s) in '{job.collection_name}'"
    assert job.tile_states == {0: "done", 1: "done"} and not job.workdir.exists()
    doc = json.loads((folder / "drive.json").read_text())
    assert doc["status"] == "complete" and len(doc["scans"]) == 5, "the one imported object is five scans"
    assert all(t["free_cells"][0] is None for t in doc["tiles"])       # auto: these weights take no free space
    coll = bpy.data.collections[job.collection_name]
    objs = sorted(coll.objects, key=lambda o: (o["hgca_tile"], o["hgca_sample"]))
    assert [(o["hgca_tile"], o["hgca_sample"]) for o in objs] == [(0, 0), (0, 1), (1, 0), (1, 1)]
    assert all(len(o.data.polygons) > 0 and o["hgca_role"] == "result" for o in objs)
    assert [o.hide_render for o in objs] == [False, True, False, True]
    boxes = [o for o in bpy.data.objects if o.get("hgca_tile") is not None and o.get("hgca_role") == "region"]
    assert np.allclose(world_regions(sorted(boxes, key=lambda o: o["hgca_tile"])),
                       [t["region"] for t in doc["tiles"]], atol=1e-4), "the run's boxes are its tiles"
    user_objects_unchanged(before)
    assert len(scan.data.vertices) == sum(s["points"] for s in doc["scans"])

    assert bpy.ops.hgca.drive() == {"FINISHED"}               # the same drive again: every tile from DIR
    again = jobs.active_job(bpy.context.scene.name)
    run_to_end(again)
    assert again.state == "done" and again.tile_states == {0: "cached", 1: "cached"}
    assert json.loads((folder / "drive.json").read_text())["timings"]["tiles_computed"] == 0
    assert len(bpy.data.collections[again.collection_name].objects) == 4


def test_cancel_keeps_finished_tiles_and_leaves_user_objects(addon, small_weights, tmp_path) -> None:
    jobs = addon_module("jobs.completion")
    import_drive(tmp_path / "scans", length=40.0)
    folder = tmp_path / "drive"
    use_drive_settings(small_weights, folder, t1=12)
    before = snapshot()
    assert bpy.ops.hgca.drive() == {"FINISHED"}
    job = jobs.active_job(bpy.context.scene.name)
    run_to_end(job, until=lambda j: "done" in j.tile_states.values())
    assert job.state == "running", "cancelled mid-run"
    assert bpy.ops.hgca.cancel() == {"FINISHED"}
    assert job.state == "cancelled" and jobs.active_job(bpy.context.scene.name) is None
    doc = json.loads((folder / "drive.json").read_text())
    done = {t["index"] for t in doc["tiles"] if t["status"] == "done"}
    assert doc["status"] == "interrupted" and 1 <= len(done) < len(doc["tiles"]) == 5
    coll = bpy.data.collections[job.collection_name]
    assert {o["hgca_tile"] for o in coll.objects} == done == job.results.tiles and len(coll.objects) == len(done)
    assert job.status.startswith(f"Cancelled: {len(done)} finished tile(s) kept")
    user_objects_unchanged(before)
    assert not job.workdir.exists()


def test_drive_panel_draws_its_settings(addon) -> None:
    from test_blender_ui import draw

    log = draw(addon_module("ui.panels").HGCA_PT_drive)
    assert {n for k, n in log if k == "prop"} == {"drive_dir", "drive_tile_size", "drive_overlap", "drive_workers"}
    assert {n for k, n in log if k == "operator"} == {"hgca.drive_plan", "hgca.drive"}


def test_drive_panel_shows_the_folder_and_its_size(addon, tmp_path) -> None:
    """The panel names the drive folder and what it holds on disk (its tile cache grows ~100 MiB a tile)."""
    from test_blender_ui import draw

    panels = addon_module("ui.panels")
    folder = tmp_path / "drive"
    bpy.context.scene.hgca.drive_dir = str(folder)
    labels = [n for k, n in draw(panels.HGCA_PT_drive) if k == "label"]
    assert any(lbl.endswith(": empty") and str(folder) in lbl for lbl in labels), labels
    folder.mkdir()
    (folder / "tile.npz").write_bytes(b"0" * (3 * 2**20))
    panels._SIZES.clear()
    labels = [n for k, n in draw(panels.HGCA_PT_drive) if k == "label"]
    assert any(lbl.endswith(": 3 MiB") for lbl in labels), labels


def test_the_panels_steps_reach_the_drive_command(addon) -> None:
    """T1 and T2 set in the panel go to `hgca drive` as they go to `hgca complete` (T2 was once dropped)."""
    props = bpy.context.scene.hgca
    props.t1, props.t2 = 7, 3
    args = addon_module("jobs.drive_job").drive_args(addon_module("operators.drive").drive_params(bpy.context))
    assert args[args.index("--t1") + 1] == "7" and args[args.index("--t2") + 1] == "3"
    props.t1, props.t2 = 0, 0
    args = addon_module("jobs.drive_job").drive_args(addon_module("operators.drive").drive_params(bpy.context))
    assert "--t1" not in args and "--t2" not in args


def test_the_bar_moves_within_a_tile_on_its_chain_steps(addon) -> None:
    """`tile-step` records (a tile's chain steps) move the drive's bar between two finished tiles."""
    drive_job = addon_module("jobs.drive_job")
    job = object.__new__(drive_job.DriveJob)
    job.tiles, job.tiles_done, job.progress, job.status = 4, 1, 0.0, ""
    seen = []
    for step in range(1, 11):
        job._on_step({"stage": "tile-step", "step": step, "total": 10, "chain": "coarse", "tile": 1})
        seen.append(job.progress)
    one = drive_job.WEIGHTS["tile"] / 4
    assert seen == sorted(seen) and len(set(seen)) == 10
    assert drive_job.WEIGHTS["read"] + one < seen[0] and seen[-1] < drive_job.WEIGHTS["read"] + 2 * one
    assert job.status.startswith("Tiles 1/4 done: tile 1 coarse 10/10")


def test_show_tiles_in_the_interface_returns_at_once(addon, small_weights, tmp_path) -> None:
    """The interface's Show Tiles plans on a thread: starting takes well under a second, the boxes arrive on a
    later main-thread poll, the same three tiles as the synchronous path."""
    import time as time_

    background, drive_job, ops = addon_module("jobs.background"), addon_module("jobs.drive_job"), addon_module("operators.drive")
    import_drive(tmp_path / "scans", length=30.0)
    use_drive_settings(small_weights, tmp_path / "drive")
    t = time_.monotonic()
    drive_job.start_plan(bpy.context.scene, ops.drive_params(bpy.context), ops.drive_sources(bpy.context))
    assert time_.monotonic() - t < 1.0
    with pytest.raises(RuntimeError, match="still running"):
        drive_job.start_plan(bpy.context.scene, ops.drive_params(bpy.context), ops.drive_sources(bpy.context))
    deadline = time_.monotonic() + TIMEOUT_S
    while (text := background.poll("drive_plan")) is None:
        assert time_.monotonic() < deadline
        time_.sleep(0.1)
    assert text.startswith("3 tiles in")
    assert sum(o.get("hgca_tile") is not None for o in bpy.data.objects) == 3
