"""What a drive reads and how a run owns its folder: sequence folders (the real Argoverse 2 log, a KITTI folder
built here), accumulated files split by `scan_index`, the scans' origins reaching each tile's observed free
space, `--plan-only`, one run per folder (DIR/.lock) and drive.json after a signal."""
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

import hgca_core
from drive_data import write_drive, write_kitti
from hgca_core.errors import InputError
from hgca_testdata import REAL_FIXTURES, require_real
from hgca_core.tiling.inputs import read_drive_inputs
from hgca_core.tiling.store import DriveStore

SMALL = {"size": 12.8, "overlap": 3.2, "stage": "coarse", "t1": 2, "threads": 1}
CLI_SMALL = ["--size", "12.8", "--overlap", "3.2", "--stage", "coarse", "--t1", "3", "--threads", "1"]
AV2_LOG = REAL_FIXTURES / "av2" / "7fab2350-7eaf-3b7e-a39d-6937a4c1bede"


def _cli(*args):
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(Path(hgca_core.__file__).parents[1]),
                                                        os.environ.get("PYTHONPATH", "")])}
    return subprocess.Popen([sys.executable, "-m", "hgca_core.cli", "drive", *map(str, args)], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def test_av2_log_is_a_drive_of_its_sweeps_with_their_rays(drive_weights, tmp_path):
    """The real AV2 log (2 sweeps, two lidars each): each sweep is one scan whose points, origins and rays are the
    ones `read_sequence` gives; the tile's free space comes from those rays."""
    from hgca_core.io.sequence import read_sequence

    log = require_real(AV2_LOG)
    doc = hgca_core.drive([log], tmp_path / "d", weights=str(drive_weights), free_space="mask", **SMALL)
    whole = read_sequence(log, frames="0:2")
    assert [Path(s["file"]).name for s in doc["scans"]] == sorted(p.name for p in (log / "sensors/lidar").iterdir())
    assert [s["points"] for s in doc["scans"]] == np.bincount(whole.attributes["scan_index"]).tolist()
    assert [s["origins"] for s in doc["scans"]] == [2, 2]
    for k, s in enumerate(doc["scans"]):
        assert np.allclose(s["position"], whole.origins[2 * k:2 * k + 2].mean(axis=0), atol=1e-9)
    (tile,) = doc["tiles"]
    assert doc["status"] == "complete" and tile["scans"] == [0, 1] and tile["free_cells"][0] > 1000
    assert Path(doc["outputs"][0]).stat().st_size > 0


def test_kitti_folder_drives_its_frames_with_their_poses(drive_weights, tmp_path):
    poses = write_kitti(tmp_path / "seq", length=24.0)
    scans = read_drive_inputs([tmp_path / "seq"], frames="1:7:2")
    assert [Path(s.name).name for s in scans] == ["000001.bin", "000003.bin", "000005.bin"]
    for s, v in zip(scans, poses[1:7:2]):
        assert np.allclose(s.origins, v[:3, 3][None], atol=1e-9) and (s.origin_index == 0).all()
    assert len(read_drive_inputs([tmp_path / "seq"])) == len(poses), "all frames by default"
    from hgca_core.cli import main

    out = tmp_path / "d"
    assert main(["drive", str(tmp_path / "seq"), "--frames", "0:7", "--out", str(out), "--weights",
                 str(drive_weights), *CLI_SMALL, "--progress", "none"]) == 0
    doc = json.loads((out / "drive.json").read_text())
    assert doc["status"] == "complete" and len(doc["scans"]) == 7 and len(doc["tiles"]) == 3
    assert np.allclose([s["position"] for s in doc["scans"]], [v[:3, 3] for v in poses[:7]], atol=1e-9)
    with pytest.raises(InputError, match="--frames needs a sequence folder"):
        read_drive_inputs([tmp_path / "seq" / "velodyne" / "000000.bin"], frames="0:2")


def test_accumulated_file_is_split_into_its_scans(tmp_path):
    """What `hgca read` writes (and the Blender add-on sends): one file, `scan_index` per point, an origin per scan;
    the drive sees the scans the separate files give, each with its own origin."""
    from hgca_core.io import read_scans

    files, poses = write_drive(tmp_path / "scans", length=12.0)
    whole = read_scans(files, poses=poses)
    acc = tmp_path / "acc.npz"
    np.savez(acc, points=whole.points, origins=whole.origins, scan_index=whole.attributes["scan_index"])
    split = read_drive_inputs([acc])
    separate = read_drive_inputs(files, poses=poses)
    assert len(split) == len(separate) == 4
    for a, b in zip(split, separate):
        assert np.array_equal(a.points, b.points) and np.array_equal(a.origins, b.origins)
        assert a.digest() == b.digest()
    moved = type(split[0])("x", split[0].points, split[0].origins + 1.0, split[0].origin_index)
    assert moved.digest() != split[0].digest(), "a scan's key covers its origins (they change the free space)"


def test_each_tile_gets_its_scans_rays_as_free_space(drive_weights, tmp_path):
    """Free space inside a drive: every tile's input has seen-empty cells, exactly those its scans' rays give in
    its box; `off` gives none, and the setting is part of the tiles' keys."""
    from hgca_core.geometry.freespace import observed_empty
    from hgca_core.geometry.region import Region

    files, poses = write_drive(tmp_path / "scans", length=16.0)
    doc = hgca_core.drive(files, tmp_path / "mask", poses=poses, weights=str(drive_weights), free_space="mask",
                          **SMALL)
    assert len(doc["tiles"]) == 2 and all(t["free_cells"][0] > 1000 for t in doc["tiles"])
    scans = read_drive_inputs(files, poses=poses)
    tile = doc["tiles"][1]
    region = Region.from_tuple(tile["region"])
    mine = [scans[i] for i in tile["scans"]]
    first = np.cumsum([0] + [len(s.origins) for s in mine[:-1]])
    free = observed_empty(region.to_local(np.concatenate([s.points for s in mine])),
                          region.to_local(np.concatenate([s.origins for s in mine])),
                          np.concatenate([s.origin_index + f for s, f in zip(mine, first)]),
                          region.grid_shape(0.2))
    assert tile["free_cells"][0] == int(free.sum())
    off = hgca_core.drive(files, tmp_path / "off", poses=poses, weights=str(drive_weights), free_space="off",
                          **SMALL)
    assert all(t["free_cells"] == [None] for t in off["tiles"])
    assert not {t["key"] for t in off["tiles"]} & {t["key"] for t in doc["tiles"]}


def test_plan_only_prints_the_plan_a_run_uses_and_writes_nothing(tmp_path, capsys):
    from hgca_core.cli import main

    files, poses = write_drive(tmp_path / "scans", length=30.0)
    out = tmp_path / "never"
    assert main(["drive", *map(str, files), "--poses", str(poses), "--out", str(out), "--size", "12.8",
                 "--overlap", "3.2", "--plan-only", "--json"]) == 0
    plan = json.loads(capsys.readouterr().out)
    assert not out.exists()
    from hgca_core.tiling.plan import plan_tiles

    scans = read_drive_inputs(files, poses=poses)
    expected = plan_tiles(np.array([s.position for s in scans]), 12.8, 3.2, 5)
    assert [t["index"] for t in plan["tiles"]] == list(range(len(expected))) == list(range(3))
    for t, e in zip(plan["tiles"], expected):
        assert np.allclose(t["region"][:2], e.center_xy) and np.isclose(np.radians(t["region"][6]), e.yaw)
        assert t["scans"] == list(e.scans) and t["region"][3:6] == [12.8, 12.8, 8.0]
    assert np.allclose(plan["trajectory"], [s.position for s in scans])


def test_lock_refuses_a_second_writer_and_dies_with_its_holder(tmp_path):
    a, b = DriveStore(tmp_path / "d"), DriveStore(tmp_path / "d")
    a.prepare()
    with pytest.raises(InputError, match=f"another hgca drive is writing this folder \\(pid {os.getpid()}"):
        b.prepare()
    a.unlock()
    b.prepare()
    b.unlock()
    # a holder that is killed (no cleanup at all) leaves the file but not the lock
    holder = subprocess.Popen([sys.executable, "-c", "import sys, time; sys.path.insert(0, sys.argv[1]);"
                               "from hgca_core.tiling.store import DriveStore; DriveStore(sys.argv[2]).prepare();"
                               "print('locked', flush=True); time.sleep(60)",
                               str(Path(hgca_core.__file__).parents[1]), str(tmp_path / "d")],
                              stdout=subprocess.PIPE, text=True)
    assert holder.stdout.readline().strip() == "locked"
    with pytest.raises(InputError, match=f"pid {holder.pid}"):
        b.prepare()
    holder.kill()
    holder.wait(timeout=30)
    assert (tmp_path / "d" / ".lock").is_file()
    b.prepare()
    b.unlock()


def test_second_run_on_the_same_folder_is_refused_and_sigint_marks_interrupted(drive_weights, tmp_path):
    files, poses = write_drive(tmp_path / "scans", length=60.0)
    out = tmp_path / "d"
    args = [*files, "--poses", poses, "--out", out, "--weights", drive_weights, *CLI_SMALL, "--progress", "none"]
    first = _cli(*args, "--t1", 40)           # slow enough to be still at work when the second run gives up
    deadline = time.time() + 240
    while first.poll() is None and time.time() < deadline:
        try:
            if json.loads((out / "drive.json").read_text())["status"] == "running":
                break
        except (OSError, ValueError, KeyError):
            pass
        time.sleep(0.05)
    second = _cli(*args)
    _, err = second.communicate(timeout=120)
    assert second.returncode == 2 and "another hgca drive is writing this folder" in err, err[-2000:]
    assert f"pid {first.pid}" in err and "Traceback" not in err
    assert first.poll() is None, "the first run goes on"
    first.send_signal(signal.SIGINT)
    _, err = first.communicate(timeout=60)
    assert first.returncode == 130 and "hgca drive: interrupted (SIGINT)" in err, err[-2000:]
    doc = json.loads((out / "drive.json").read_text())
    assert doc["status"] == "interrupted" and "SIGINT" in doc["error"] and doc["pid"] == first.pid
    assert any(t["status"] == "pending" for t in doc["tiles"])
