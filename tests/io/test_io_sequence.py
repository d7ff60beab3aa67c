"""Sequence folders (KITTI, Argoverse 2, nuScenes) as input: poses, frame selection, errors, CLI.

The KITTI folder is built here from the format's facts (velodyne/NNNNNN.bin float32 x,y,z,i; poses.txt one
3x4 camera-0 pose per line; calib.txt `Tr:` velodyne -> camera 0), around known velodyne poses, so the
reader must undo Tr to recover them. The AV2 and nuScenes cases use the real files in tests/data/real.
"""
from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from hgca_core.errors import InputError
from hgca_core.io import read_scans
from hgca_core.io.sequence import open_sequence, parse_frames, read_inputs, read_sequence

AV2_7FAB = "av2/7fab2350-7eaf-3b7e-a39d-6937a4c1bede"
AV2_ADCF = "av2/adcf7d18-0510-35b0-a2fa-b4cea13a6d76"
NUSCENES = "nuscenes_lidar_top_1532402927647951.pcd.bin"
# A KITTI-like Tr: velodyne x forward, y left, z up -> camera x right, y down, z forward, with an offset.
TR = np.array([[0.0, -1.0, 0.0, -0.004], [0.0, 0.0, -1.0, -0.076], [1.0, 0.0, 0.0, -0.27], [0, 0, 0, 1.0]])


def rigid(yaw_deg: float, t: tuple[float, float, float], tilt_deg: float = 0.0) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = Rotation.from_euler("zx", [yaw_deg, tilt_deg], degrees=True).as_matrix()
    m[:3, 3] = t
    return m


def velodyne_poses(n: int = 7) -> list[np.ndarray]:
    """Known velodyne->world poses of a short drive (x forward 1.5 m per frame, turning, slightly tilted)."""
    return [rigid(4.0 * i, (1.5 * i, 0.2 * i * i, 0.01 * i), tilt_deg=0.3 * i) for i in range(n)]


def world_scene(seed: int = 0) -> np.ndarray:
    """A street: ground, two walls and a box, as points in the world frame."""
    rng = np.random.default_rng(seed)
    ground = np.c_[rng.uniform(-5, 20, (4000, 2)), rng.normal(-1.7, 0.01, 4000)]
    walls = np.concatenate([np.c_[rng.uniform(-5, 20, 2000), np.full(2000, y), rng.uniform(-1.7, 3, 2000)]
                            for y in (-6.0, 7.0)])
    box = np.c_[rng.uniform(4, 6, 800), rng.uniform(1, 3, 800), rng.uniform(-1.7, 0, 800)]
    return np.concatenate([ground, walls, box])


def make_kitti(root: Path, poses: list[np.ndarray], calib: str | None = None, pose_lines: int | None = None,
               labels: bool = True) -> tuple[Path, list[np.ndarray]]:
    """A KITTI odometry sequence folder whose frame i sees `world_scene` from velodyne pose `poses[i]`."""
    scene = world_scene()
    (root / "velodyne").mkdir(parents=True)
    local_scans = []
    for i, v in enumerate(poses):
        rng = np.random.default_rng(i)
        pts = scene[rng.random(len(scene)) < 0.5]
        local = (pts - v[:3, 3]) @ v[:3, :3]  # world -> velodyne i
        rows = np.c_[local, rng.random(len(local))].astype("<f4")
        rows.tofile(root / "velodyne" / f"{i:06d}.bin")
        local_scans.append(rows[:, :3].astype(np.float64))
        if labels:
            (root / "labels").mkdir(exist_ok=True)
            np.zeros(len(rows), "<u4").tofile(root / "labels" / f"{i:06d}.label")
    tr_inv = np.linalg.inv(TR)
    cams = [TR @ v @ tr_inv for v in poses]  # P_i: camera 0 frame, so that V_i = Tr^-1 P_i Tr
    lines = [" ".join(f"{x:.12e}" for x in p[:3].reshape(-1)) for p in cams][: pose_lines or len(cams)]
    (root / "poses.txt").write_text("\n".join(lines) + "\n")
    p0 = "P0: 7.18e+02 0 6.07e+02 0 0 7.18e+02 1.85e+02 0 0 0 1 0"
    tr_line = "Tr: " + " ".join(f"{x:.12e}" for x in TR[:3].reshape(-1))
    (root / "calib.txt").write_text(calib if calib is not None else f"{p0}\n{tr_line}\n")
    return root, local_scans


def poses_json(path: Path, files: list[Path], poses: list[np.ndarray]) -> Path:
    path.write_text(json.dumps({"scans": [{"file": str(f), "pose": p.tolist()} for f, p in zip(files, poses)]}))
    return path


def cli(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "hgca_core.cli", *map(str, args)], capture_output=True,
                          text=True, timeout=300, cwd=cwd)


# ---------------------------------------------------------------- frames


@pytest.mark.parametrize("spec, count, expected", [
    (None, 20, [7, 8, 9, 10, 11]), (None, 6, [0, 1, 2, 3, 4]), (None, 3, [0, 1, 2]), (None, 1, [0]),
    ("0:2", 5, [0, 1]), ("2:", 5, [2, 3, 4]), (":4:2", 9, [0, 2]), ("-2:", 5, [3, 4]), ("0:100", 3, [0, 1, 2]),
])
def test_parse_frames(spec, count, expected):
    assert parse_frames(spec, count) == expected


@pytest.mark.parametrize("spec", ["5", "a:b", "1:2:0", "1:2:3:4", "4:2"])
def test_parse_frames_rejects(spec):
    with pytest.raises(InputError):
        parse_frames(spec, 5)


# ---------------------------------------------------------------- KITTI


def test_kitti_recovers_velodyne_poses(tmp_path):
    poses = velodyne_poses()
    root, local = make_kitti(tmp_path / "seq", poses)
    seq = open_sequence(root)
    assert seq.layout == "kitti" and len(seq) == len(poses)
    for got, want in zip(seq.poses, poses):
        np.testing.assert_allclose(got, want, atol=1e-9)
    scan = read_sequence(root, "1:4")
    # the accumulated scans line up in the world frame (float32 files: ~1e-6 m)
    want = np.concatenate([loc @ poses[i][:3, :3].T + poses[i][:3, 3] for i, loc in zip(range(1, 4), local[1:4])])
    np.testing.assert_allclose(scan.points, want, atol=1e-5)
    np.testing.assert_allclose(scan.origins, [poses[i][:3, 3] for i in range(1, 4)], atol=1e-9)
    assert scan.points.dtype == np.float64 and set(scan.attributes) == {"intensity", "scan_index"}


def test_kitti_default_frames_are_the_middle_five(tmp_path):
    root, _ = make_kitti(tmp_path / "seq", velodyne_poses(9))
    scan = read_sequence(root)
    assert int(scan.attributes["scan_index"].max()) == 4
    np.testing.assert_allclose(scan.origins[0], velodyne_poses(9)[2][:3, 3], atol=1e-9)


@pytest.mark.parametrize("case, message", [
    ("no_tr", "no 'Tr:' line"), ("no_calib", "no calib.txt"), ("short_poses", "no pose for 2 sweep"),
    ("bad_pose", "not 12 numbers"),
])
def test_kitti_errors(tmp_path, case, message):
    poses = velodyne_poses(5)
    if case == "no_tr":
        root, _ = make_kitti(tmp_path / "seq", poses, calib="P0: 1 0 0 0 0 1 0 0 0 0 1 0\n")
    elif case == "short_poses":
        root, _ = make_kitti(tmp_path / "seq", poses, pose_lines=3)
    else:
        root, _ = make_kitti(tmp_path / "seq", poses)
        if case == "no_calib":
            (root / "calib.txt").unlink()
        else:
            (root / "poses.txt").write_text("1 0 0 0 0 1 0 0 0 0 1 x\n" * 5)
    with pytest.raises(InputError, match=message):
        read_sequence(root, "0:2")
    res = cli("read", root, "--frames", "0:2", "-o", tmp_path / "out.npz")
    assert res.returncode == 2 and message in res.stderr and "Traceback" not in res.stderr
    assert not (tmp_path / "out.npz").exists()


def test_kitti_folder_completes_like_files_with_poses_json(tmp_path, small_weights):
    """Same completion (coarse stage, 3 steps, fixed seed) from the folder as from its files + a poses JSON
    written from the known velodyne poses (not from the reader)."""
    poses = velodyne_poses(6)
    root, _ = make_kitti(tmp_path / "seq", poses)
    files = [root / "velodyne" / f"{i:06d}.bin" for i in range(1, 6)]
    pj = poses_json(tmp_path / "poses.json", files, poses[1:6])
    region = "6,0.5,0,9.6,9.6,6.4"
    common = ["--weights", small_weights, "--stage", "coarse", "--seed", 3, "--region", region, "--progress", "none"]
    a = cli("complete", root, "--frames", "1:6", "-o", tmp_path / "a.npz", *common)
    b = cli("complete", *files, "--poses", pj, "-o", tmp_path / "b.npz", *common)
    assert a.returncode == 0 and b.returncode == 0, a.stderr + b.stderr
    ma, mb = np.load(tmp_path / "a_s0.npz"), np.load(tmp_path / "b_s0.npz")
    assert len(ma["faces"]) > 100
    np.testing.assert_array_equal(ma["faces"], mb["faces"])
    np.testing.assert_allclose(ma["vertices"], mb["vertices"], atol=1e-6)
    # and a wrong pose changes it (the comparison can fail)
    bad = poses_json(tmp_path / "bad.json", files, [poses[1]] * 5)
    c = cli("complete", *files, "--poses", bad, "-o", tmp_path / "c.npz", *common)
    assert c.returncode == 0, c.stderr
    mc = np.load(tmp_path / "c_s0.npz")
    assert len(mc["faces"]) != len(ma["faces"]) or not np.allclose(mc["vertices"], ma["vertices"])


def test_poses_command_round_trips(tmp_path):
    poses = velodyne_poses(6)
    root, _ = make_kitti(tmp_path / "seq", poses)
    out = tmp_path / "sub" / "poses.json"
    out.parent.mkdir()
    res = cli("poses", root, "--frames", "2:5", "-o", out)
    assert res.returncode == 0, res.stderr
    doc = json.loads(out.read_text())
    assert [Path(s["file"]).name for s in doc["scans"]] == ["000002.bin", "000003.bin", "000004.bin"]
    assert not Path(doc["scans"][0]["file"]).is_absolute()
    via_json = read_scans([root / "velodyne" / f"{i:06d}.bin" for i in (2, 3, 4)], poses=out)
    via_folder = read_sequence(root, "2:5")
    np.testing.assert_array_equal(via_json.points, via_folder.points)
    np.testing.assert_array_equal(via_json.origins, via_folder.origins)


# ---------------------------------------------------------------- Argoverse 2 (real files)


def av2_quat_pose(row: dict) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = Rotation.from_quat([row["qx"], row["qy"], row["qz"], row["qw"]]).as_matrix()
    m[:3, 3] = [row["tx_m"], row["ty_m"], row["tz_m"]]
    return m


def test_av2_log_poses_and_alignment(real_dir):
    import pyarrow.feather as feather

    log = real_dir / AV2_7FAB
    seq = open_sequence(log)
    assert seq.layout == "av2" and len(seq) == 2
    table = feather.read_table(log / "city_SE3_egovehicle.feather").to_pydict()
    for f, pose in zip(seq.files, seq.poses):
        i = table["timestamp_ns"].index(int(Path(f).stem))
        np.testing.assert_allclose(pose, av2_quat_pose({k: v[i] for k, v in table.items()}), atol=1e-12)
        assert pose.dtype == np.float64 and abs(pose[0, 3]) > 1000  # city frame, km-scale, not down-cast
    scan = read_sequence(log, "0:2")
    assert len(scan) == 99229 + 99466
    assert scan.points.dtype == np.float64 and scan.origins.shape == (4, 3)
    # two lidars per sweep: up_lidar above down_lidar, each point's origin_index names its lidar
    assert scan.origins[0, 2] - scan.origins[1, 2] == pytest.approx(0.115, abs=0.01)
    laser, sweep = scan.attributes["laser_number"].astype(int), scan.attributes["scan_index"].astype(int)
    np.testing.assert_array_equal(scan.attributes["origin_index"], 2 * sweep + laser // 32)
    a, b = scan.points[sweep == 0], scan.points[sweep == 1]
    aligned = np.median(cKDTree(a).query(b)[0])
    unposed = read_scans(seq.files)  # both sweeps left in their own ego frames
    raw = np.median(cKDTree(unposed.points[unposed.attributes["scan_index"] == 0]).query(
        unposed.points[unposed.attributes["scan_index"] == 1])[0])
    assert aligned < 0.05 and aligned < 0.8 * raw


def test_av2_sweep_file_with_poses_json_equals_log(real_dir, tmp_path):
    log = real_dir / AV2_7FAB
    out = tmp_path / "poses.json"
    assert cli("poses", log, "-o", out).returncode == 0
    files = [log / "sensors/lidar" / (Path(s["file"]).name) for s in json.loads(out.read_text())["scans"]]
    via_json = read_scans(files, poses=out)
    via_log = read_sequence(log, "0:2")
    np.testing.assert_array_equal(via_json.points, via_log.points)
    np.testing.assert_array_equal(via_json.origins, via_log.origins)
    np.testing.assert_array_equal(via_json.attributes["origin_index"], via_log.attributes["origin_index"])


def test_av2_log_without_calibration(real_dir):
    """adcf7d18 ships no calibration: origins fall back to the ego origin, or come from a given table."""
    log = real_dir / AV2_ADCF
    scan = read_sequence(log)
    assert len(scan) == 100660 and scan.origins.shape == (1, 3) and "origin_index" not in scan.attributes
    calib = real_dir / AV2_7FAB / "calibration/egovehicle_SE3_sensor.feather"
    with_calib = read_sequence(log, calibration=calib)
    assert with_calib.origins.shape == (2, 3)
    assert with_calib.origins[0, 2] - scan.origins[0, 2] == pytest.approx(1.64, abs=0.05)  # up_lidar height


def copy_av2(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst)
    return dst


def test_av2_pose_table_must_cover_the_sweep(real_dir, tmp_path):
    import pyarrow as pa
    import pyarrow.feather as feather

    log = copy_av2(real_dir / AV2_7FAB, tmp_path / "log")
    table = feather.read_table(log / "city_SE3_egovehicle.feather")
    ts = table.column("timestamp_ns").to_numpy()
    stamp = 315966265360032000
    feather.write_feather(table.filter(pa.array(ts < stamp)), str(log / "city_SE3_egovehicle.feather"))
    with pytest.raises(InputError, match=f"no ego pose for sweep timestamp {stamp}.*covers"):
        open_sequence(log)
    # inside the table's span but without a row at the sweep's time
    feather.write_feather(table.filter(pa.array(ts != stamp)), str(log / "city_SE3_egovehicle.feather"))
    with pytest.raises(InputError, match="nearest row is"):
        open_sequence(log)
    res = cli("complete", log, "--frames", "0:2", "-o", tmp_path / "out.ply")
    assert res.returncode == 2 and "no ego pose" in res.stderr and not list(tmp_path.glob("out*.ply"))


def test_av2_missing_pose_table(real_dir, tmp_path):
    log = copy_av2(real_dir / AV2_7FAB, tmp_path / "log")
    (log / "city_SE3_egovehicle.feather").unlink()
    res = cli("info", log)
    assert res.returncode == 2 and "AV2 ego pose table not found" in res.stderr


def test_av2_cli_info_read(real_dir, tmp_path):
    log = real_dir / AV2_7FAB
    res = cli("info", log, "--frames", "0:2", "--json")
    assert res.returncode == 0, res.stderr
    info = json.loads(res.stdout)["files"][0]
    assert info["format"] == "av2 sequence" and info["points"] == 99229 + 99466 and info["frames"] == [0, 1]
    res = cli("read", log, "--frames", "1:2", "-o", tmp_path / "one.npz")
    assert res.returncode == 0, res.stderr
    with np.load(tmp_path / "one.npz") as z:
        assert len(z["points"]) == 99466 and z["origins"].shape == (2, 3)


# ---------------------------------------------------------------- nuScenes


def test_nuscenes_folder(real_dir, tmp_path):
    folder = tmp_path / "sweeps"
    folder.mkdir()
    shutil.copy(real_dir / NUSCENES, folder / NUSCENES)
    single = read_sequence(folder)
    np.testing.assert_array_equal(single.points, read_scans([real_dir / NUSCENES]).points)
    # two sweeps need poses: without them it is an error, with poses.json in the folder they are placed
    second = folder / "second.pcd.bin"
    shutil.copy(real_dir / NUSCENES, second)
    with pytest.raises(InputError, match="no poses.json"):
        read_sequence(folder, "0:2")
    shift = rigid(0.0, (2.0, 0.0, 0.0))
    poses_json(folder / "poses.json", [folder / NUSCENES, second], [np.eye(4), shift])
    both = read_sequence(folder, "0:2")
    n = len(single)
    # files sort by name: nuscenes_... before second...
    np.testing.assert_allclose(both.points[n:], single.points + [2.0, 0.0, 0.0])
    np.testing.assert_allclose(both.origins, [[0, 0, 0], [2.0, 0, 0]])


def test_folder_and_files_do_not_mix(real_dir, tmp_path):
    with pytest.raises(InputError, match="not both"):
        read_inputs([str(real_dir / AV2_7FAB), str(real_dir / NUSCENES)])
    with pytest.raises(InputError, match="--frames needs a sequence folder"):
        read_inputs([str(real_dir / NUSCENES)], frames="0:1")
    with pytest.raises(InputError, match="not a known sequence layout"):
        read_inputs([str(tmp_path)])


def test_complete_av2_log_in_city_frame(real_dir, tmp_path, small_weights):
    """`hgca complete <AV2 log> --frames 0:2` (small weights, 2 steps): the mesh lies around the ego in city
    coordinates (km), in the default region around the first sweep's up_lidar."""
    log = real_dir / AV2_7FAB
    out = tmp_path / "out.npz"
    res = cli("complete", log, "--frames", "0:2", "-o", out, "--weights", small_weights, "--stage", "coarse",
              "--t1", 2, "--progress", "none")
    assert res.returncode == 0, res.stderr
    with np.load(tmp_path / "out_s0.npz") as z:
        v = z["vertices"].astype(np.float64)
    origin = read_sequence(log, "0:2").origins[0]
    assert len(v) > 1000
    np.testing.assert_allclose(np.median(v[:, :2], axis=0), origin[:2], atol=15.0)
    assert np.abs(v[:, :2] - origin[:2]).max() < 38.4 / 2 * np.sqrt(2) + 0.5
