"""Poses from the scans (`hgca_core.io.odometry`, `hgca poses --estimate`): KISS-ICP odometry against true poses
(the real Argoverse 2 log, a simulated drive that turns), every failure named by its frame, and the "files" layout
that makes an estimated folder a posed sequence for `hgca complete`."""
from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from hgca_testdata import REAL_FIXTURES, require_real
from builders import simulate_drive   # tests/builders.py (benchmarks/odometry.py measures the same drive)

from hgca_core.errors import InputError
from hgca_core.io.odometry import (MAX_SPEED, MIN_CONSTRAINT, MIN_FITNESS, estimate, estimate_poses, frame_times,
                                   name_time)
from hgca_core.io.scan import Scan
from hgca_core.io.sequence import detect_layout, open_sequence, read_sequence

AV2_LOG = REAL_FIXTURES / "av2" / "7fab2350-7eaf-3b7e-a39d-6937a4c1bede"
FRAMES = 10


def pose_error(truth: np.ndarray, est: np.ndarray) -> tuple[float, float]:
    """Translation (m) and rotation (deg) of truth^-1 est."""
    d = np.linalg.inv(truth) @ est
    return float(np.linalg.norm(d[:3, 3])), float(np.degrees(np.arccos(np.clip((np.trace(d[:3, :3]) - 1) / 2, -1, 1))))


def cli(*args):
    return subprocess.run([sys.executable, "-m", "hgca_core.cli", *map(str, args)], capture_output=True, text=True,
                          timeout=300)


@pytest.fixture(scope="module")
def drive():
    """10 raw sweeps (per-point times, rolling shutter) of a synthetic street, driving 10 m/s and weaving."""
    scans, poses, times, names = simulate_drive(seed=3, frames=FRAMES)
    return scans, [np.linalg.inv(poses[0]) @ p for p in poses], times, names


@pytest.fixture(scope="module")
def drive_estimate(drive):
    scans, _, times, names = drive
    seen = []
    found = estimate(scans, times, names, progress=lambda i, n: seen.append((i, n)))
    return found, seen


# ---------------------------------------------------------------- (a) the real AV2 log


def test_av2_relative_pose_from_the_sweeps_alone(tmp_path):
    """The log's 2 sweeps copied to a folder without its poses ("files" layout): the estimated relative pose is
    within half the true motion of the true one, a bound identity poses and a swapped frame order both miss."""
    log = require_real(AV2_LOG)
    truth_seq = open_sequence(log)
    truth = np.linalg.inv(truth_seq.poses[0]) @ truth_seq.poses[1]
    for f in truth_seq.files:
        shutil.copy(f, tmp_path)
    seq = open_sequence(tmp_path)
    assert seq.layout == "files" and seq.poses is None and seq.fmt == "av2"
    names = list(seq.files)
    times = frame_times(names)
    assert times is not None and 0.09 < times[1] - times[0] < 0.11        # 10 Hz, from the names (ns)
    poses = estimate_poses([seq.read_frame(i) for i in range(2)], times, names)
    np.testing.assert_array_equal(poses[0], np.eye(4))
    moved, turned = pose_error(np.eye(4), truth)                            # 0.066 m, 0.36 deg
    t_bound, r_bound = moved / 2, turned / 2
    t_err, r_err = pose_error(truth, poses[1])
    assert t_err < t_bound and r_err < r_bound, (t_err, r_err)
    for broken in (np.eye(4), np.linalg.inv(truth)):                        # identity; frames swapped
        bt, br = pose_error(truth, broken)
        assert bt > t_bound and br > r_bound


# ---------------------------------------------------------------- (b) a simulated drive


def test_synthetic_drive_drift(drive, drive_estimate):
    """Raw, motion-distorted sweeps of a drive that turns ~20 deg: the estimated trajectory drifts < 3 % of the
    distance and < 0.1 deg/m, every frame is checked, and progress is reported once per frame."""
    _, truth, _, _ = drive
    found, seen = drive_estimate
    assert seen == [(i + 1, FRAMES) for i in range(FRAMES)]
    assert found.settings["deskew"] is True
    yaw = [np.degrees(np.arctan2(p[1, 0], p[0, 0])) for p in truth]
    assert max(yaw) - min(yaw) > 10.0                                        # it does turn
    travelled = sum(np.linalg.norm(b[:3, 3] - a[:3, 3]) for a, b in zip(truth, truth[1:]))
    t_err, r_err = pose_error(truth[-1], found.poses[-1])
    assert t_err / travelled < 0.03 and r_err / travelled < 0.1, (t_err / travelled, r_err / travelled)
    t_still, _ = pose_error(truth[-1], np.eye(4))
    assert t_still / travelled > 0.9                                         # standing still misses the bound
    checked = found.frames[1:]
    assert all(f["fitness"] >= MIN_FITNESS and f["constraint"] >= MIN_CONSTRAINT for f in checked)
    record = found.record()
    assert record["method"] == "kiss-icp" and record["version"] and record["settings"]["voxel_size"] > 0


def test_deskewing_helps_on_raw_sweeps(drive, drive_estimate):
    """The same sweeps without their per-point times (no deskewing) end further from the truth: the times are
    used, not just carried."""
    scans, truth, times, names = drive
    plain = estimate([Scan(s.points, {}, s.origins) for s in scans], times, names)
    assert plain.settings["deskew"] is False
    assert pose_error(truth[-1], plain.poses[-1])[0] > pose_error(truth[-1], drive_estimate[0].poses[-1])[0]


# ---------------------------------------------------------------- (c) failures, each named by its frame


def test_too_few_points_names_the_frame(drive):
    scans, _, times, names = drive
    bad = list(scans)
    near = np.flatnonzero(np.linalg.norm(scans[3].points, axis=1) < 30.0)[:200]
    bad[3] = Scan(scans[3].points[near], {"time": scans[3].attributes["time"][near]})
    with pytest.raises(InputError, match=r"frame 3 of 10 has 200 point\(s\).*at least 1000") as info:
        estimate(bad, times, names)
    assert names[3] in str(info.value)


def test_time_gap_and_order_name_the_frame(drive):
    scans, _, times, names = drive
    gap = [t + (1.0 if i >= 5 else 0.0) for i, t in enumerate(times)]
    with pytest.raises(InputError, match=r"sweep_005.npz: frame 5 of 10 comes 1.100 s after frame 4"):
        estimate(scans, gap, names)
    swapped = list(times)
    swapped[6], swapped[7] = swapped[7], swapped[6]
    with pytest.raises(InputError, match=r"sweep_007.npz: frame 7 of 10 is not later than frame 6"):
        estimate(scans, swapped, names)


def test_frame_of_another_place_is_refused(drive):
    """A sweep of another street spliced in as frame 6: refused as a jump or a misfit, naming frame 6."""
    scans, _, times, names = drive
    other, _, _, _ = simulate_drive(seed=5, frames=1)
    spliced = scans[:6] + other + scans[7:]
    with pytest.raises(InputError, match=r"sweep_006.npz: frame 6 of 10 (jumps|does not fit)"):
        estimate(spliced, times, names)
    with pytest.raises(InputError, match=r"sweep_006.npz: frame 6 of 10 (jumps|does not fit)"):
        estimate(spliced, None, names)                                    # per-frame bound without times


def test_motion_beyond_a_vehicle_is_a_jump(drive):
    """The drive's sweeps stamped 10x closer in time: 1 m per 0.01 s (100 m/s) is no vehicle's motion, so the first
    moving frame is refused as a jump, however well it registers."""
    scans, _, times, names = drive
    with pytest.raises(InputError, match=rf"sweep_001.npz: frame 1 of 10 jumps .* at most {MAX_SPEED:g} m/s"):
        estimate(scans, [t / 10 for t in times], names)


def test_corridor_of_two_parallel_walls_is_degenerate():
    """Two parallel walls and nothing else: motion along them is unmeasured, so frame 1 is refused."""
    rng = np.random.default_rng(0)
    scans = []
    for _ in range(4):
        n = 20000
        scans.append(Scan(np.c_[rng.uniform(-25, 25, n), rng.choice([-3.0, 3.0], n), rng.uniform(-1.5, 1.5, n)]))
    with pytest.raises(InputError, match=r"c1: frame 1 of 4: the registration is degenerate"):
        estimate(scans, [0.1 * i for i in range(4)], [f"c{i}" for i in range(4)])


def test_missing_library_names_the_extra(monkeypatch, drive):
    scans, _, times, names = drive
    monkeypatch.setitem(sys.modules, "kiss_icp", None)
    with pytest.raises(InputError, match=r"needs the recordings extra \(pip install 'hgca\[recordings\]'\)"):
        estimate(scans[:2], times[:2], names[:2])


def test_frame_times_from_names():
    assert name_time("a/315966265259836000.feather") == pytest.approx(315966265.259836)
    assert name_time("n015__LIDAR_TOP__1532402927647951.pcd.bin") == pytest.approx(1532402927.647951)
    assert name_time("scan_001.ply") is None
    assert frame_times(["1532402927647951.pcd", "scan.pcd"]) is None


# ---------------------------------------------------------------- (d) the "files" layout and the CLI


def write_sweeps(folder: Path, scans: list[Scan], names: list[str]) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    for scan, name in zip(scans, names):
        np.savez(folder / name, points=scan.points, time=scan.attributes["time"])


def test_files_layout_natural_order_and_one_format(tmp_path):
    pts = np.random.default_rng(0).uniform(-5, 5, (50, 3))
    for i in (10, 2, 1):
        np.savez(tmp_path / f"scan{i}.npz", points=pts + i)
    assert detect_layout(str(tmp_path)) == "files"
    seq = open_sequence(tmp_path)
    assert [Path(f).name for f in seq.files] == ["scan1.npz", "scan2.npz", "scan10.npz"] and seq.poses is None
    with pytest.raises(InputError, match="3 files sweeps selected but the folder has no poses.json"):
        read_sequence(tmp_path, "0:3")
    shifts = [np.eye(4) for _ in range(3)]
    for k, m in enumerate(shifts):
        m[0, 3] = 10.0 * k
    (tmp_path / "poses.json").write_text(json.dumps(
        {"scans": [{"file": f"scan{i}.npz", "pose": m.tolist()} for i, m in zip((1, 2, 10), shifts)]}))
    both = read_sequence(tmp_path, "0:2")
    np.testing.assert_allclose(both.points[50:], pts + 2 + [10.0, 0, 0])
    np.save(tmp_path / "extra.npy", pts)
    with pytest.raises(InputError, match=r"several formats \(1 npy, 3 npz\)"):
        open_sequence(tmp_path)


def test_cli_estimate_then_complete_the_folder(drive, tmp_path, small_weights):
    """`hgca poses --estimate FOLDER -o FOLDER/poses.json` then `hgca complete FOLDER`: the folder reads as a posed
    sequence with the estimated poses, and a tiny coarse completion runs on it."""
    scans, truth, _, names = drive
    folder = tmp_path / "sweeps"
    write_sweeps(folder, scans[:5], names[:5])
    out = folder / "poses.json"
    res = cli("poses", "--estimate", folder, "-o", out, "--progress", "jsonl")
    assert res.returncode == 0, res.stderr
    records = [json.loads(line) for line in res.stdout.splitlines()]
    assert [r["step"] for r in records if r["stage"] == "odometry"] == [1, 2, 3, 4, 5]
    assert records[-1]["stage"] == "done"
    doc = json.loads(out.read_text())
    assert doc["estimated"]["method"] == "kiss-icp" and len(doc["estimated"]["frames"]) == 5
    assert [e["file"] for e in doc["scans"]] == names[:5]
    seq = open_sequence(folder)
    assert seq.layout == "files" and len(seq.poses) == 5
    assert pose_error(truth[4], seq.poses[4])[0] < 0.3                      # 4 m driven
    # a second estimate may overwrite the folder's own poses.json (it is no input of --estimate)
    again = cli("poses", "--estimate", str(folder / "*.npz"), "--frames", "0:3", "-o", out, "--progress", "none")
    assert again.returncode == 0, again.stderr
    assert len(json.loads(out.read_text())["scans"]) == 3
    cli("poses", "--estimate", folder, "-o", out, "--progress", "none")
    mesh = tmp_path / "street.npz"
    done = cli("complete", folder, "-o", mesh, "--weights", small_weights, "--stage", "coarse", "--t1", 2,
               "--region", "4,0,-0.5,9.6,9.6,4", "--progress", "none")
    assert done.returncode == 0, done.stderr
    with np.load(tmp_path / "street_s0.npz") as z:
        assert len(z["vertices"]) > 100


def test_cli_estimate_refusals(tmp_path, drive):
    scans, _, _, names = drive
    folder = tmp_path / "sweeps"
    near = np.flatnonzero(np.linalg.norm(scans[1].points, axis=1) < 30.0)[:100]
    bad = [scans[0], Scan(scans[1].points[near], {"time": scans[1].attributes["time"][near]})]
    write_sweeps(folder, bad, names[:2])
    res = cli("poses", "--estimate", folder, "-o", tmp_path / "p.json", "--progress", "none")
    assert res.returncode == 2 and "frame 1 of 2 has 100 point(s)" in res.stderr and "sweep_001.npz" in res.stderr
    assert not (tmp_path / "p.json").exists()
    res = cli("poses", "--estimate", str(tmp_path / "none*.ply"), "-o", tmp_path / "p.json")
    assert res.returncode == 2 and "pattern matches no file" in res.stderr
    res = cli("poses", folder / names[0], folder / names[1], "-o", tmp_path / "p.json")
    assert res.returncode == 2 and "need --estimate" in res.stderr


def test_cli_estimate_scan_files_then_read_them_with_the_poses(tmp_path, drive):
    """Scan files given by name (in the order given), the JSON written elsewhere: `--poses` places them (the entries
    name the files relative to the JSON), and the accumulated frames line up with the truth."""
    scans, truth, _, names = drive
    folder = tmp_path / "sweeps"
    write_sweeps(folder, scans[:3], names[:3])
    out = tmp_path / "elsewhere" / "poses.json"
    out.parent.mkdir()
    files = [folder / n for n in names[:3]]
    res = cli("poses", "--estimate", *files, "-o", out, "--progress", "none")
    assert res.returncode == 0, res.stderr
    doc = json.loads(out.read_text())
    assert [e["file"] for e in doc["scans"]] == [f"../sweeps/{n}" for n in names[:3]] and doc["layout"] == "files"
    got = cli("read", *files, "--poses", out, "-o", tmp_path / "all.npz")
    assert got.returncode == 0, got.stderr
    with np.load(tmp_path / "all.npz") as z:
        assert len(z["points"]) == sum(len(s) for s in scans[:3])
    assert pose_error(truth[2], np.asarray(doc["scans"][2]["pose"]))[0] < 0.2     # 2 m driven


def test_kitti_times_txt_gives_the_frame_times(tmp_path):
    (tmp_path / "velodyne").mkdir()
    (tmp_path / "times.txt").write_text("0.0\n0.1036\n0.2073\n")
    names = [str(tmp_path / "velodyne" / f"{i:06d}.bin") for i in (1, 2)]
    assert frame_times(names, str(tmp_path)) == [0.1036, 0.2073]
    assert frame_times(names + [str(tmp_path / "velodyne" / "000009.bin")], str(tmp_path)) is None


def test_cli_estimate_a_bag_without_tf(tmp_path):
    """The AV2 sweeps as a ROS 1 bag without /tf: `hgca poses --estimate BAG` names the frames BAG#N, and `hgca read
    BAG --poses` places them with it; the relative pose is within half the true motion."""
    pytest.importorskip("rosbags")
    from bagwriter import CLOUD, Bag, cloud

    log = require_real(AV2_LOG)
    seq = open_sequence(log)
    bag = Bag("ros1")
    for i, f in enumerate(seq.files):
        scan, stamp = seq.read_frame(i), int(Path(f).name[:-len(".feather")])
        cols = {"x": scan.points[:, 0], "y": scan.points[:, 1], "z": scan.points[:, 2],
                "intensity": scan.attributes["intensity"].astype(np.float32)}
        bag.add("/points", CLOUD, stamp, cloud(bag.store, stamp, "base_link", cols))
    path = bag.write(tmp_path / "drive.bag")
    out = tmp_path / "poses.json"
    res = cli("poses", "--estimate", path, "--topic", "/points", "-o", out, "--progress", "none")
    assert res.returncode == 0, res.stderr
    doc = json.loads(out.read_text())
    assert [e["file"] for e in doc["scans"]] == ["drive.bag#0", "drive.bag#1"] and doc["layout"] == "rosbag"
    truth = np.linalg.inv(seq.poses[0]) @ seq.poses[1]
    moved, turned = pose_error(np.eye(4), truth)
    t_err, r_err = pose_error(truth, np.asarray(doc["scans"][1]["pose"]))
    assert t_err < moved / 2 and r_err < turned / 2, (t_err, r_err)
    got = cli("read", path, "--frames", "0:2", "--poses", out, "-o", tmp_path / "both.npz")
    assert got.returncode == 0, got.stderr
