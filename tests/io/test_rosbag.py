"""ROS 1 and ROS 2 bags (sqlite3, MCAP, bare storage files) as input, written here from the real Argoverse 2
sweeps of tests/data/real: each sweep a PointCloud2 in its sensor frame, /tf (+ /tf_static) carrying the
log's own ego poses. A bag must then read, and complete, exactly like the log folder it was made from."""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from bagwriter import CLOUD, TF, Bag, cloud, storage_file, tf_message
from scipy.spatial.transform import Rotation

from hgca_core.errors import InputError
from hgca_core.io.rosbag import describe_bag, open_bag
from hgca_core.io.rosbag_cloud import decode_cloud, relative_time
from hgca_core.io.sequence import open_sequence, read_sequence

AV2_7FAB = "av2/7fab2350-7eaf-3b7e-a39d-6937a4c1bede"
REGION = "5224,2385,69,9.6,9.6,6.4"  # around the first sweep's ego position (city frame)
# base_link -> lidar: the sensor 1.2 m ahead, 1.8 m up, turned 90 degrees, so the chain's order matters
LIDAR = np.eye(4)
LIDAR[:3, :3] = Rotation.from_euler("zy", [90.0, 2.0], degrees=True).as_matrix()
LIDAR[:3, 3] = (1.2, 0.1, 1.8)


def cli(*args):
    return subprocess.run([sys.executable, "-m", "hgca_core.cli", *map(str, args)], capture_output=True, text=True,
                          timeout=300)


def av2_sweeps(log: Path) -> list[tuple[int, object, np.ndarray]]:
    """(stamp ns, ego-frame Scan, ego->city pose) of each sweep of the log."""
    seq = open_sequence(log)
    return [(int(Path(f).name[:-len(".feather")]), seq.read_frame(i), seq.poses[i]) for i, f in enumerate(seq.files)]


def columns(scan, to_sensor: np.ndarray | None = None) -> dict[str, np.ndarray]:
    pts = scan.points if to_sensor is None else scan.points @ to_sensor[:3, :3].T + to_sensor[:3, 3]
    return {"x": pts[:, 0], "y": pts[:, 1], "z": pts[:, 2],
            "intensity": scan.attributes["intensity"].astype(np.float32),
            "ring": scan.attributes["laser_number"].astype(np.uint16), "t": scan.attributes["offset_ns"]}


def turn(m: np.ndarray, angle: float, shift: np.ndarray) -> np.ndarray:
    out = m.copy()
    out[:3, :3] = m[:3, :3] @ Rotation.from_euler("z", angle).as_matrix()
    out[:3, 3] = m[:3, 3] + shift
    return out


def av2_bag(path: Path, kind: str, sweeps, layout: str = "base", topic: str = "/points",
            compress: bool = False) -> Path:
    """The sweeps as a bag. layout "base": clouds in base_link, /tf odom -> base_link at the sweep stamps and
    /tf_static map -> odom (identity); "lidar": clouds in a lidar frame (/tf_static base_link -> lidar) with
    /tf samples 50 ms either side of each sweep, whose interpolation is the sweep's pose; "none": no tf."""
    bag = Bag(kind, compress=compress)
    st = bag.store
    for stamp, scan, pose in sweeps:
        to_sensor = np.linalg.inv(LIDAR) if layout == "lidar" else None
        frame = "lidar" if layout == "lidar" else "base_link"
        bag.add(topic, CLOUD, stamp + 3_000_000, cloud(st, stamp, frame, columns(scan, to_sensor)))
        if layout == "base":
            bag.add("/tf", TF, stamp, tf_message(st, [(stamp, "odom", "base_link", pose)]))
        elif layout == "lidar":
            v = np.array([8.0, -3.0, 0.2]) * 0.05  # 8 m/s, turning at 1 rad/s: the samples bracket the pose
            for dt, sign in ((-50_000_000, -1), (50_000_000, 1)):
                bag.add("/tf", TF, stamp + dt, tf_message(st, [(stamp + dt, "odom", "base_link",
                                                                turn(pose, 0.05 * sign, v * sign))]))
    first = sweeps[0][0]
    if layout != "none":
        statics = [(first, "map", "odom", np.eye(4))] + ([(first, "base_link", "lidar", LIDAR)]
                                                         if layout == "lidar" else [])
        bag.add("/tf_static", TF, first - 1, tf_message(st, statics))
    return bag.write(path)


@pytest.fixture(scope="module")
def log(real_dir) -> Path:
    return real_dir / AV2_7FAB


@pytest.fixture(scope="module")
def sweeps(log):
    return av2_sweeps(log)


@pytest.fixture(scope="module")
def bags(tmp_path_factory, sweeps) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("bags")
    out = {"ros1": av2_bag(root / "drive.bag", "ros1", sweeps, "lidar", compress=True),  # LZ4 chunks
           "sqlite3": av2_bag(root / "drive_db3", "sqlite3", sweeps),
           "mcap": av2_bag(root / "drive_mcap", "mcap", sweeps),
           "none": av2_bag(root / "still.bag", "ros1", sweeps, "none")}
    out["bare_db3"] = storage_file(out["sqlite3"])
    out["bare_mcap"] = storage_file(out["mcap"])
    return out


@pytest.fixture(scope="module")
def folder_points(log, tmp_path_factory) -> np.ndarray:
    out = tmp_path_factory.mktemp("folder") / "folder.npz"
    res = cli("read", log, "-o", out)
    assert res.returncode == 0, res.stderr
    with np.load(out) as z:
        return z["points"].astype(np.float64) + z["offset"]


@pytest.mark.parametrize("kind", ["ros1", "sqlite3", "mcap", "bare_db3", "bare_mcap"])
def test_bag_reads_like_the_log_folder(kind, bags, folder_points, tmp_path):
    """`hgca read BAG` gives the log folder's accumulated points (tf chain composed, interpolated in "ros1")."""
    out = tmp_path / "bag.npz"
    res = cli("read", bags[kind], "-o", out)
    assert res.returncode == 0, res.stderr
    with np.load(out) as z:
        points = z["points"].astype(np.float64) + z["offset"]
        assert {"intensity", "ring", "time"} <= set(z.files)
    assert points.shape == folder_points.shape and len(points) > 150_000
    np.testing.assert_allclose(points, folder_points, rtol=0, atol=1e-6)


def test_frames_keep_attributes_and_sensor_frame(bags, sweeps):
    seq = open_bag(bags["mcap"], None)
    assert seq.layout == "rosbag" and seq.files == (f"{bags['mcap']}#0", f"{bags['mcap']}#1")
    for i, (stamp, scan, pose) in enumerate(sweeps):
        frame = seq.read_frame(i)
        np.testing.assert_array_equal(frame.points, scan.points)
        np.testing.assert_array_equal(frame.origins, [[0.0, 0.0, 0.0]])
        np.testing.assert_array_equal(frame.attributes["ring"], scan.attributes["laser_number"])
        np.testing.assert_allclose(frame.attributes["time"], scan.attributes["offset_ns"] / 1e9, atol=1e-12)
        np.testing.assert_allclose(seq.poses[i], pose, atol=1e-12)


def test_tf_chain_is_interpolated_at_the_stamp(bags, sweeps):
    """The ros1 bag's poses come from samples 50 ms away on both sides, through a static lidar mount."""
    seq = open_bag(bags["ros1"], None)
    for i, (_, _, pose) in enumerate(sweeps):
        np.testing.assert_allclose(seq.poses[i], pose @ LIDAR, atol=1e-9)


def test_tf_far_from_the_stamp_is_refused(tmp_path, sweeps):
    """A cloud 0.3 s after the last /tf sample has no pose: picking it is refused naming the frame (not
    extrapolated), while the frames tf covers stay usable; within 0.1 s of the span the end pose holds."""
    bag = Bag("mcap")
    st = bag.store
    for stamp, scan, pose in sweeps:
        bag.add("/tf", TF, stamp, tf_message(st, [(stamp, "odom", "base_link", pose)]))
    clouds = {"late": 300_000_000, "near": 60_000_000}
    for name, after in clouds.items():
        bag.messages = [m for m in bag.messages if m[0] == "/tf"]
        for k, (stamp, scan, _) in enumerate(sweeps):
            s = stamp + after * k
            bag.add("/points", CLOUD, s, cloud(st, s, "base_link", _small(scan)))
        seq = open_bag(bag.write(tmp_path / name), None)
        np.testing.assert_allclose(seq.poses[0], sweeps[0][2], atol=1e-12)
        if name == "near":
            np.testing.assert_allclose(seq.poses[1], sweeps[1][2], atol=1e-12)
            continue
        with pytest.raises(InputError, match=r"topic /points, frame 1: no tf for frame 'base_link' \(in 'odom'\) "
                                             r"at the cloud stamp 315966265.660 s: /tf covers it from "
                                             r"315966265.260 to 315966265.360 s"):
            seq.poses[1]
        assert len(read_sequence(tmp_path / name, "0:1")) == 1200
        assert "1 frame(s) outside tf's time span" in describe_bag(str(tmp_path / name), None)["cloud"]["poses"]


def _small(scan, n: int = 1200) -> dict[str, np.ndarray]:
    return {k: v[:n] for k, v in columns(scan).items()}


def test_field_layouts_decode_to_the_same_points(sweeps):
    """Organised (4 rows) with padding after fields and rows, and big-endian, decode as the plain layout."""
    store = Bag("sqlite3").store
    cols = _small(sweeps[0][1])
    stamp = sweeps[0][0]

    def decoded(**layout):
        msg = cloud(store, stamp, "lidar", cols, **layout)
        msg = store.deserialize_cdr(store.serialize_cdr(msg, CLOUD), CLOUD)
        return decode_cloud(msg, stamp, "x.bag#0")

    plain = decoded()
    np.testing.assert_array_equal(plain.points, np.c_[cols["x"], cols["y"], cols["z"]])
    for layout in ({"height": 4, "pad": 3, "row_pad": 7}, {"big_endian": True}, {"big_endian": True, "pad": 1}):
        other = decoded(**layout)
        np.testing.assert_array_equal(other.points, plain.points)
        for name in ("intensity", "ring", "time"):
            np.testing.assert_array_equal(other.attributes[name], plain.attributes[name])


def test_no_return_rows_are_dropped(tmp_path, sweeps):
    """An organised cloud's NaN placeholder rows are left out (finalize's policy), the rest kept in order."""
    cols = _small(sweeps[0][1], 1000)
    gone = np.zeros(1000, dtype=bool)
    gone[::7] = True
    for a in "xyz":
        cols[a] = np.where(gone, np.nan, cols[a])
    bag = Bag("ros1")
    bag.add("/points", CLOUD, 10**18, cloud(bag.store, 10**18, "lidar", cols, height=10))
    frame = open_bag(bag.write(tmp_path / "nan.bag"), None).read_frame(0)
    assert len(frame) == int((~gone).sum())
    np.testing.assert_array_equal(frame.points[:, 0], cols["x"][~gone])


def test_time_fields_in_any_unit():
    stamp = 1_700_000_000_123_000_000
    rel = np.array([0.0, 0.05, 0.099])
    np.testing.assert_allclose(relative_time((rel * 1e9).astype(np.uint32), stamp), rel, atol=1e-9)  # Ouster t
    np.testing.assert_allclose(relative_time(rel.astype(np.float32), stamp), rel, atol=1e-7)  # Velodyne time
    np.testing.assert_allclose(relative_time(stamp / 1e9 + rel, stamp), rel, atol=1e-6)  # absolute seconds
    np.testing.assert_allclose(relative_time(np.uint64(stamp) + (rel * 1e9).astype(np.uint64), stamp), rel, atol=1e-9)


def test_topic_choice(tmp_path, sweeps):
    """Two cloud topics: --topic is needed, and picks; a bag with one cloud topic needs none."""
    bag = Bag("sqlite3")
    for stamp, scan, _ in sweeps:
        bag.add("/front", CLOUD, stamp, cloud(bag.store, stamp, "front", _small(scan)))
    bag.add("/rear", CLOUD, sweeps[0][0], cloud(bag.store, sweeps[0][0], "rear", _small(sweeps[0][1], 50)))
    path = bag.write(tmp_path / "two")
    with pytest.raises(InputError, match=r"--topic is needed: the bag has 2 point cloud topics: /front \(2\), "
                                         r"/rear \(1\)"):
        open_bag(path, None)
    assert len(open_bag(path, "/rear")) == 1 and len(open_bag(path, "/front").read_frame(0)) == 1200
    listing = describe_bag(str(path), None)
    assert listing["cloud"] is None and [t["messages"] for t in listing["topics"]] == [2, 1]


def test_header_stamp_order_beats_receive_order(tmp_path, sweeps):
    """Clouds received out of stamp order (less than a frame interval apart) are frames in stamp order."""
    bag = Bag("mcap")
    base = sweeps[0][0]
    for k, got in enumerate([0, 250, 120, 300]):  # received ms; stamps 0, 100, 200, 300 ms
        stamp = base + k * 100_000_000
        msg = cloud(bag.store, stamp, "lidar", _small(sweeps[0][1], 10 + k))
        bag.add("/points", CLOUD, base + got * 1_000_000, msg)
    seq = open_bag(bag.write(tmp_path / "jitter"), None)
    assert [len(seq.read_frame(i)) for i in range(4)] == [10, 11, 12, 13]


def test_info_lists_the_bag(bags):
    res = cli("info", bags["ros1"])
    assert res.returncode == 0, res.stderr
    text = res.stdout
    for line in ("/points", "sensor_msgs/msg/PointCloud2  2", "/tf_static", "tf2_msgs/msg/TFMessage  4",
                 "2 frames over 0.100 s", "from tf (lidar in map)"):
        assert line in text, text
    res = cli("info", bags["none"])
    assert res.returncode == 0 and "LiDAR odometry (tf does not place base_link)" in res.stdout, res.stdout + res.stderr


@pytest.fixture(scope="module")
def completions(bags, log, small_weights, tmp_path_factory):
    """One coarse completion of the sqlite3 bag and one of the log folder (copied without its calibration,
    so that both give each sweep one sensor origin at the ego position)."""
    root = tmp_path_factory.mktemp("complete")
    folder = root / "log"
    shutil.copytree(log, folder, ignore=shutil.ignore_patterns("calibration"))
    common = ["--weights", small_weights, "--stage", "coarse", "--seed", 3, "--region", REGION, "--progress", "none"]
    out = {}
    for name, src in (("bag", bags["sqlite3"]), ("ros1", bags["ros1"]), ("folder", folder)):
        res = cli("complete", src, "--frames", "0:2", "-o", root / f"{name}.npz", *common)
        assert res.returncode == 0, res.stderr
        with np.load(root / f"{name}_s0.npz") as z:
            out[name] = (z["vertices"].astype(np.float64), z["faces"].copy())
    return out


@pytest.mark.parametrize("bag", ["bag", "ros1"], ids=["ros2-sqlite3", "ros1-tf-interpolated"])
def test_bag_completes_like_the_log_folder(completions, bag):
    (va, fa), (vb, fb) = completions[bag], completions["folder"]
    assert len(fa) > 100
    np.testing.assert_array_equal(fa, fb)
    np.testing.assert_allclose(va, vb, rtol=0, atol=1e-6)


def test_without_tf_poses_come_from_odometry(tmp_path, sweeps):
    """No /tf: the frames (one sweep seen from three places 1.5 m and 3 degrees apart) are placed by LiDAR
    odometry, so they accumulate onto the first frame's points."""
    stamp0, scan, _ = sweeps[0]
    moves = [np.eye(4)]
    for k in (1, 2):
        moves.append(turn(np.eye(4), np.radians(3.0 * k), np.array([1.5 * k, 0.1 * k, 0.0])))
    bag = Bag("mcap")
    for k, m in enumerate(moves):
        cols = {n: v for n, v in columns(scan, np.linalg.inv(m)).items() if n != "t"}  # no times: no deskew
        stamp = stamp0 + k * 100_000_000
        bag.add("/points", CLOUD, stamp, cloud(bag.store, stamp, "lidar", cols))
    path = bag.write(tmp_path / "no_tf")
    assert describe_bag(str(path), None)["cloud"]["poses"].startswith("LiDAR odometry")
    accumulated = read_sequence(path, "0:3")
    n = len(scan)
    assert len(accumulated) == 3 * n
    for k in (1, 2):
        gap = np.linalg.norm(accumulated.points[k * n:(k + 1) * n] - scan.points, axis=1)
        assert np.median(gap) < 0.02 and np.percentile(gap, 99) < 0.05, (k, np.median(gap))


def test_odometry_poses_stay_in_the_first_asked_frame(monkeypatch):
    """Frames asked for one by one, forwards then backwards, get poses in one world frame: the first asked
    frame's sensor frame; the odometry runs over growing spans, not once per frame."""
    import hgca_core.io.odometry as odometry
    from hgca_core.io.rosbag import OdometryPoses

    truth = [turn(np.eye(4), 0.1 * i, np.array([2.0 * i, 0.3 * i * i, 0.0])) for i in range(12)]
    spans = []

    def fake(scans, times, names, progress=None):
        idx = [int(n.rsplit("#", 1)[1]) for n in names]
        spans.append((idx[0], idx[-1]))
        return [np.linalg.inv(truth[idx[0]]) @ truth[i] for i in idx]

    monkeypatch.setattr(odometry, "estimate_poses", fake)
    names = [f"d.bag#{i}" for i in range(12)]
    poses = OdometryPoses(lambda i: None, 12, [i * 10**8 for i in range(12)], names)
    asked = [5, 6, 7, 8, 9, 3, 2, 11]
    for i in asked:
        np.testing.assert_allclose(poses[i], np.linalg.inv(truth[5]) @ truth[i], atol=1e-12)
    assert len(spans) <= 4 and spans[0][0] == 5 and spans[-1][0] <= 2 and spans[-1][1] == 11
    spans.clear()
    assert np.array_equal(OdometryPoses(lambda i: None, 12, [0] * 12, names)[4], np.eye(4)) and not spans


def test_field_problems_only_matter_for_xyz(sweeps):
    """A field hgca does not read may be anything; x, y, z must be single values inside the point."""
    store = Bag("sqlite3").store
    cols = {**_small(sweeps[0][1], 100), "junk": np.zeros(100, dtype=np.float32)}
    stamp = sweeps[0][0]

    def decode(field: str, **change):
        msg = cloud(store, stamp, "lidar", cols)
        for f in msg.fields:
            if f.name == field:
                for k, v in change.items():
                    setattr(f, k, v)
        return decode_cloud(msg, stamp, "x.bag#0")

    assert len(decode("junk", datatype=9)) == 100 and len(decode("junk", offset=1000)) == 100
    with pytest.raises(InputError, match="field 'x' has count 3"):
        decode("x", count=3)
    with pytest.raises(InputError, match="field 'z' has datatype 0"):
        decode("z", datatype=0)
    with pytest.raises(InputError, match="field 'y' at offset 38 \\(8 bytes\\) does not fit in a point of "
                                         "point_step 38 bytes"):
        decode("y", offset=38, datatype=8)


def test_tf_tree_with_two_parents_matters_only_on_the_chain():
    """A frame given two parents makes the tree ambiguous: refused when the sensor's chain passes through it,
    ignored elsewhere (a camera's mount on another branch)."""
    from hgca_core.io.rosbag_tf import TfTree

    store = Bag("sqlite3").store
    up = np.eye(4)
    up[2, 3] = 1.0
    tree = TfTree("x.bag")
    tree.add(tf_message(store, [(5, "odom", "base_link", up), (5, "base_link", "/lidar", up),
                                (5, "base_link", "camera", up), (5, "lidar", "camera", up)]), static=False)
    assert tree.chain("lidar") == ["lidar", "base_link", "odom"]
    mats, problems = tree.poses("lidar", np.array([5]))
    assert mats[0][2, 3] == 2.0 and problems == [None]
    with pytest.raises(InputError, match="tf frame 'camera' has two parents, 'base_link' and 'lidar'"):
        tree.chain("camera")


def test_eval_real_reads_a_bag_with_its_topic(bags, folder_points):
    """`hgca eval-real BAG --topic T` scores the bag's clouds (its inputs go through `read_sequence` with the
    topic), not an error or the wrong topic."""
    import argparse

    from hgca_core.commands.eval_real import inputs_of
    from hgca_core.metrics.real_eval import read_input

    args = argparse.Namespace(inputs=[str(bags["mcap"])], frames=None, calibration=None, topic="/points")
    (item,) = inputs_of(args)
    scan = read_input(item)
    assert np.allclose(np.sort(scan.points, axis=0), np.sort(folder_points, axis=0), atol=1e-6, rtol=0)
    args.topic = "/not_there"
    with pytest.raises(InputError, match="/not_there"):
        read_input(inputs_of(args)[0])
