"""Recordings through the add-on: a ROS 2 bag and an E57 written from two real Argoverse 2 sweeps import as the
CLI's `hgca read` reads them, the Topic option lists the bag's cloud topics, the imported bag's completion argv
carries --topic, and Estimate Poses on a folder of sweeps without poses writes poses.json (a cancel leaves none).
No completions run here."""
from __future__ import annotations

import json
import subprocess
import tempfile
import time
from pathlib import Path
from types import SimpleNamespace

import bpy
import numpy as np
import pytest

from bl_helpers import CORE_PYTHON, FIXTURES, REPO, addon_module, core_arrays, require_fixture, snapshot

AV2_LOG = FIXTURES / "av2" / "7fab2350-7eaf-3b7e-a39d-6937a4c1bede"

# Runs in the core's interpreter (rosbags, pye57, scipy): the log's sweeps (ego frame) and ego poses written as
# a ROS 2 sqlite3 bag (clouds on /points and half of each on /points_half, poses on /tf), a one-topic MCAP bag
# and an E57 with one posed scan a sweep.
WRITE_RECORDINGS = """
sys.path.insert(0, {tests_io!r})
from pathlib import Path
from scipy.spatial.transform import Rotation
from bagwriter import CLOUD, TF, Bag, cloud, storage_file, tf_message
from e57_files import cartesian, write_e57
from hgca_core.io import av2
from hgca_core.io.sequence import open_sequence

seq = open_sequence({log!r})
out = Path({out!r})
sqlite, mcap, scans = Bag("sqlite3"), Bag("mcap"), []
for i in range(len(seq)):
    scan, pose = seq.read_frame(i), seq.poses[i]
    stamp = av2.sweep_timestamp(seq.files[i])
    cols = {{"x": scan.points[:, 0].astype(np.float32), "y": scan.points[:, 1].astype(np.float32),
             "z": scan.points[:, 2].astype(np.float32),
             "intensity": scan.attributes["intensity"].astype(np.float32)}}
    half = {{k: v[::2].copy() for k, v in cols.items()}}
    for bag in (sqlite, mcap):
        bag.add("/points", CLOUD, stamp, cloud(bag.store, stamp, "lidar", cols))
        bag.add("/tf", TF, stamp, tf_message(bag.store, [(stamp, "map", "lidar", pose)]))
    sqlite.add("/points_half", CLOUD, stamp, cloud(sqlite.store, stamp, "lidar", half))
    w, x, y, z = np.roll(Rotation.from_matrix(pose[:3, :3]).as_quat(), 1)
    scans.append(cartesian(scan.points, intensity=cols["intensity"].astype(np.float64),
                           intensity_limits=(0.0, 255.0), rotation=(w, x, y, z), translation=tuple(pose[:3, 3])))
sqlite.write(out / "drive_ros2")
mcap_file = storage_file(mcap.write(out / "one_topic"))
write_e57(out / "scans.e57", scans)
"""


@pytest.fixture(scope="module")
def recordings(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """The three recordings, written once for the module."""
    require_fixture(AV2_LOG / "city_SE3_egovehicle.feather")
    out = tmp_path_factory.mktemp("recordings")
    got = core_arrays(WRITE_RECORDINGS.format(tests_io=str(REPO / "tests" / "io"), log=str(AV2_LOG), out=str(out)),
                      mcap="str(mcap_file)")
    return {"ros2": out / "drive_ros2", "mcap": Path(str(got["mcap"])), "e57": out / "scans.e57"}


def cli_read(path: Path, *args: str) -> np.ndarray:
    """World points (float64) of `hgca read PATH ARGS` run as a user runs it."""
    with tempfile.TemporaryDirectory(prefix="hgca_cli_read_") as tmp:
        out = Path(tmp) / "read.npz"
        done = subprocess.run([CORE_PYTHON, "-m", "hgca_core.cli", "read", str(path), *args, "-o", str(out)],
                              capture_output=True, text=True, timeout=600, cwd=tmp)
        assert done.returncode == 0, done.stderr
        with np.load(out) as data:
            offset = data["offset"] if "offset" in data.files else np.zeros(3)
            return data["points"].astype(np.float64) + offset


def world_vertices(obj: bpy.types.Object) -> np.ndarray:
    co = np.empty(len(obj.data.vertices) * 3, dtype=np.float32)
    obj.data.vertices.foreach_get("co", co)
    m = np.array(obj.matrix_world)
    origin = np.array(bpy.context.scene.get("hgca_origin", (0.0, 0.0, 0.0)), dtype=np.float64)
    return co.reshape(-1, 3).astype(np.float64) @ m[:3, :3].T + m[:3, 3] + origin


def imported(before: dict) -> bpy.types.Object:
    (obj,) = [o for o in bpy.data.objects if o.name not in before["objects"]]
    return obj


def test_ros2_bag_imports_as_the_cli_reads_it(addon, recordings) -> None:
    bag = recordings["ros2"]
    before = snapshot()
    assert bpy.ops.hgca.import_scan(directory=str(bag), frames="0:2", topic="/points") == {"FINISHED"}
    obj = imported(before)
    want = cli_read(bag, "--topic", "/points", "--frames", "0:2")
    assert len(obj.data.vertices) == len(want) > 150_000     # both sweeps, not one, not the half topic
    assert np.abs(world_vertices(obj) - want).max() < 2e-3   # city coordinates, float32 about the scene origin
    # its completion hands the core the bag itself, with the topic and frames it was read with
    scene = bpy.context.scene
    jobs, job_inputs = addon_module("jobs.completion"), addon_module("jobs.job_inputs")
    inputs = job_inputs.source_inputs(scene, [obj])
    assert inputs["files"].args() == [str(bag), "--frames", "0:2", "--topic", "/points"]
    params = jobs.CompletionParams(python=CORE_PYTHON, region=(0, 0, 0, 9.6, 9.6, 4.0, 0), **inputs)
    argv = jobs.completion_args(params, Path("in.npz"), Path("out.npz"))
    assert argv[:6] == ["complete", str(bag), "--frames", "0:2", "--topic", "/points"]


def test_the_other_topic_reads_its_own_cloud(addon, recordings) -> None:
    bag = recordings["ros2"]
    before = snapshot()
    assert bpy.ops.hgca.import_scan(directory=str(bag), frames="0:1", topic="/points_half") == {"FINISHED"}
    obj = imported(before)
    want = cli_read(bag, "--topic", "/points_half", "--frames", "0:1")
    assert len(obj.data.vertices) == len(want)
    assert np.abs(world_vertices(obj) - want).max() < 2e-3
    assert json.loads(obj["hgca_source"])["topic"] == "/points_half"


def test_topic_option_lists_the_bags_cloud_topics(addon, recordings) -> None:
    rec = addon_module("operators.recordings")
    two = SimpleNamespace(files=[], directory=str(recordings["ros2"]), filepath="")
    items = rec.topic_items(two, bpy.context)
    assert [i[0] for i in items] == [rec.NO_TOPIC, "/points", "/points_half"]   # several: none chosen for you
    one = SimpleNamespace(files=[], directory="", filepath=str(recordings["mcap"]))
    assert [i[0] for i in rec.topic_items(one, bpy.context)] == ["/points"]      # one: it is the choice
    not_bag = SimpleNamespace(files=[], directory="", filepath=str(recordings["e57"]))
    assert [i[0] for i in rec.topic_items(not_bag, bpy.context)] == [rec.NO_TOPIC]
    with pytest.raises(TypeError, match="/points_half"):   # a topic the bag lacks is refused, the real ones named
        bpy.ops.hgca.import_scan(directory=str(recordings["ros2"]), topic="/camera")


def test_single_topic_bag_records_its_topic(addon, recordings) -> None:
    mcap = recordings["mcap"]
    before = snapshot()
    assert bpy.ops.hgca.import_scan(filepath=str(mcap), frames="0:2") == {"FINISHED"}
    obj = imported(before)
    assert np.abs(world_vertices(obj) - cli_read(mcap, "--frames", "0:2")).max() < 2e-3
    assert json.loads(obj["hgca_source"])["topic"] == "/points"


def test_e57_imports_as_the_cli_reads_it(addon, recordings) -> None:
    e57 = recordings["e57"]
    before = snapshot()
    assert bpy.ops.hgca.import_scan(filepath=str(e57), frames="0:2") == {"FINISHED"}
    obj = imported(before)
    want = cli_read(e57, "--frames", "0:2")
    assert len(obj.data.vertices) == len(want) > 150_000
    assert np.abs(world_vertices(obj) - want).max() < 2e-3
    intensity = np.empty(len(want), dtype=np.float32)
    obj.data.attributes["intensity"].data.foreach_get("value", intensity)
    assert intensity.std() > 0
    assert obj.name == "scans [0:2]"


def test_interface_import_reads_on_a_thread(addon, recordings) -> None:
    """The path the interface takes: `start_import` returns at once, the core reads on a thread, and the object is
    added on the main thread by the poll (a timer in Blender; called here, as timers never fire in bpy)."""
    ops, background = addon_module("operators.import_scans"), addon_module("jobs.background")
    e57 = recordings["e57"]
    before = snapshot()
    started = time.monotonic()
    ops.start_import(bpy.context, CORE_PYTHON, [e57], None, bpy.context.scene.collection,
                     {"show_points": True, "frames": "0:1", "color_by": "AUTO", "point_size": 0.0, "topic": ""})
    assert time.monotonic() - started < 1.0 and snapshot() == before   # nothing waited for, nothing added yet
    deadline = time.monotonic() + 300
    while (text := background.poll("import")) is None and time.monotonic() < deadline:
        time.sleep(0.05)
    obj = imported(before)
    assert text == f"Imported {len(obj.data.vertices):,} points as '{obj.name}'"
    assert bpy.context.view_layer.objects.active == obj and obj.select_get()
    assert np.abs(world_vertices(obj) - cli_read(e57, "--frames", "0:1")).max() < 2e-3


def test_bag_errors_are_the_cores_line_and_add_nothing(addon, tmp_path: Path) -> None:
    bad = tmp_path / "broken.bag"
    bad.write_bytes(b"#ROSBAG V2.0\n" + b"\x00" * 64)
    before = snapshot()
    with pytest.raises(RuntimeError, match="broken.bag"):
        bpy.ops.hgca.import_scan(filepath=str(bad))
    assert snapshot() == before


# -- a folder of sweeps without poses ---------------------------------------------------------------------------

def sweeps_folder(tmp_path: Path) -> Path:
    """The log's two sweeps as a bare folder of scan files: no pose table beside them."""
    folder = tmp_path / "sweeps"
    folder.mkdir()
    for sweep in sorted((AV2_LOG / "sensors" / "lidar").glob("*.feather")):
        (folder / sweep.name).write_bytes(require_fixture(sweep).read_bytes())
    return folder


def listing(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir())}


def test_estimate_poses_then_the_folder_imports(addon, tmp_path: Path) -> None:
    from test_blender_ui import draw

    folder = sweeps_folder(tmp_path)
    scene = bpy.context.scene
    before = snapshot()
    with pytest.raises(RuntimeError, match="Estimate Poses"):   # the import says why, and what to do
        bpy.ops.hgca.import_scan(directory=str(folder), frames="0:2")
    assert snapshot() == before
    assert scene.hgca_poses_folder == str(folder)               # the panel now offers it
    panels = addon_module("ui.panels")
    assert ("operator", "hgca.estimate_poses") in draw(panels.HGCA_PT_main)

    assert bpy.ops.hgca.estimate_poses() == {"FINISHED"}
    job = addon_module("jobs.completion").ACTIVE[scene.name]
    assert job.wait(timeout=300) == "done", job.error
    steps = [(r.get("step"), r.get("total")) for r in job.records if "total" in r]
    assert steps and steps[-1][0] == steps[-1][1] == 2        # progress per frame, up to both frames
    assert scene.hgca.progress == 1.0
    from test_blender_ui import Recorder

    shown: list = []   # the status bar's header while the job runs: a progress bar with the job's status
    addon_module("operators.poses")._status_drawer(job)(SimpleNamespace(layout=Recorder(shown)), bpy.context)
    assert ("progress", f"{job.status} (100%)") in shown
    doc = json.loads((folder / "poses.json").read_text())
    assert len(doc["scans"]) == 2
    assert ("operator", "hgca.import_scan") in draw(panels.HGCA_PT_poses)   # the box offers the import

    before = snapshot()
    assert bpy.ops.hgca.import_scan(directory=str(folder), frames="0:2") == {"FINISHED"}
    obj = imported(before)
    want = cli_read(folder, "--frames", "0:2")
    assert len(obj.data.vertices) == len(want) > 150_000
    assert np.abs(world_vertices(obj) - want).max() < 2e-3


def test_cancelled_estimate_leaves_the_folder_as_it_was(addon, tmp_path: Path) -> None:
    folder = sweeps_folder(tmp_path)
    was = listing(folder)
    scene = bpy.context.scene
    assert bpy.ops.hgca.estimate_poses(folder=str(folder)) == {"FINISHED"}
    jobs = addon_module("jobs.completion")
    job = jobs.ACTIVE[scene.name]
    deadline = time.monotonic() + 120
    while job.poll_once() and not job.records and time.monotonic() < deadline:
        time.sleep(0.01)                                       # until the core is estimating
    assert job.running, f"the estimate ended before it could be cancelled ({job.state})"
    job.cancel()
    jobs.poll_all()
    assert job.state == "cancelled" and job._proc.poll() is not None   # the core is gone: it writes nothing later
    assert listing(folder) == was                              # no poses.json, no temp file
    assert scene.hgca.status == "Cancelled" and jobs.active_job(scene.name) is None


def test_layout_folder_without_its_pose_table(addon, tmp_path: Path) -> None:
    """An Argoverse 2 log without city_SE3_egovehicle.feather: the import says so, Estimate Poses writes the
    folder's poses.json, and the import then hands that file to the core (the layout reads only its own table)."""
    import shutil

    log = tmp_path / "log"
    shutil.copytree(require_fixture(AV2_LOG), log, ignore=shutil.ignore_patterns("city_SE3_egovehicle.feather"))
    with pytest.raises(RuntimeError, match="has no city_SE3_egovehicle.feather: press Estimate Poses"):
        bpy.ops.hgca.import_scan(directory=str(log), frames="0:2")
    assert bpy.ops.hgca.estimate_poses(folder=str(log)) == {"FINISHED"}
    job = addon_module("jobs.completion").ACTIVE[bpy.context.scene.name]
    assert job.wait(timeout=300) == "done", job.error
    before = snapshot()
    assert bpy.ops.hgca.import_scan(directory=str(log), frames="0:2") == {"FINISHED"}
    obj = imported(before)
    poses = log / "poses.json"
    assert json.loads(obj["hgca_source"])["poses"] == str(poses)
    assert np.abs(world_vertices(obj) - cli_read(log, "--frames", "0:2", "--poses", str(poses))).max() < 2e-3


def test_estimate_error_is_the_cores_line(addon, tmp_path: Path) -> None:
    folder = tmp_path / "not_sweeps"
    folder.mkdir()
    (folder / "notes.md").write_text("no scans here\n")
    assert bpy.ops.hgca.estimate_poses(folder=str(folder)) == {"FINISHED"}
    job = addon_module("jobs.completion").ACTIVE[bpy.context.scene.name]
    assert job.wait(timeout=300) == "error"
    assert str(folder) in job.error and "\n" not in job.error
    assert bpy.context.scene.hgca.status_is_error and sorted(p.name for p in folder.iterdir()) == ["notes.md"]
