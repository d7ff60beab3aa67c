"""Hostile recordings (ROS bags, E57 files) through the CLI entry point in-process: exit 2, one `error:` line
naming the file (and the frame or scan where one is at fault), no traceback, inputs untouched, nothing written."""
from __future__ import annotations

import shutil
import sys
from pathlib import Path
from typing import Callable

import numpy as np
import pytest

from e57_files import cartesian, float_text, patch_xml, write_e57
from hgca_testdata import folder_state, require_real
from hgca_core.cli import main


def _e57_truncated(d: Path) -> Path:
    path = write_e57(d / "site.e57", [cartesian(np.random.default_rng(0).normal(size=(5000, 3)))])
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    return path


def _e57_renamed_las(d: Path) -> Path:
    return Path(shutil.copy(require_real() / "simple.las", d / "site.e57"))


def _e57_wrong_magic(d: Path) -> Path:
    path = d / "site.e57"
    path.write_bytes(b"ASTM-E56" + bytes(2040))
    return path


def _e57_no_scans(d: Path) -> Path:
    import pye57

    pye57.E57(str(d / "site.e57"), mode="w").close()  # the standard header, an empty data3D
    return d / "site.e57"


def _e57_no_coordinates(d: Path) -> Path:
    return write_e57(d / "site.e57", [cartesian(np.ones((4, 3))), {"intensity": np.ones(4)}])


def _e57_zero_quaternion(d: Path) -> Path:
    return write_e57(d / "site.e57", [cartesian(np.ones((4, 3))), cartesian(np.ones((4, 3)),
                                                                            rotation=(0.0, 0.0, 0.0, 0.0))])


def _e57_nan_quaternion(d: Path) -> Path:
    """A pose written as 'nan' by an exporter (libE57 reads 'nan' as 0, so this is the zero quaternion again)."""
    q = (0.111, 0.222, 0.333, 0.444)
    path = write_e57(d / "site.e57", [cartesian(np.ones((4, 3)), rotation=q, translation=(1.0, 2.0, 3.0))])
    for v in q:
        patch_xml(path, float_text(v), b"nan")
    return path


def _e57_overflowing_quaternion(d: Path) -> Path:
    """1e999 in the file: libE57 reads it as the largest double, whose square overflows."""
    path = write_e57(d / "site.e57", [cartesian(np.ones((4, 3)), rotation=(0.5, 0.111, 0.5, 0.5))])
    patch_xml(path, float_text(0.111), b"1e999")
    return path


def _e57_all_invalid(d: Path) -> Path:
    return write_e57(d / "site.e57", [cartesian(np.ones((5, 3)), cartesianInvalidState=np.full(5, 2))])


E57_CASES: dict[str, tuple[Callable[[Path], Path], str]] = {
    "truncated": (_e57_truncated, "corrupt or truncated E57 file"),
    "renamed LAS": (_e57_renamed_las, "not an E57 file: it does not start with the ASTM-E57 signature (its "
                                      "content is LAS/LAZ)"),
    "wrong magic": (_e57_wrong_magic, "not an E57 file"),
    "no scans": (_e57_no_scans, "E57 file holds no scans"),
    "no coordinates": (_e57_no_coordinates, "scan 1 has neither cartesian"),
    "zero quaternion": (_e57_zero_quaternion, "scan 1: pose rotation quaternion (w, x, y, z) = (0, 0, 0, 0) is zero"),
    "nan quaternion": (_e57_nan_quaternion, "scan 0: pose rotation quaternion (w, x, y, z) = (0, 0, 0, 0) is zero"),
    "overflowing quaternion": (_e57_overflowing_quaternion, "scan 0: pose rotation quaternion (w, x, y, z) = "
                                                            "(0.5, 1.79769e+308, 0.5, 0.5) is not finite"),
    "all points invalid": (_e57_all_invalid, "scan 0: all 5 points are marked invalid (cartesianInvalidState != 0)"),
}


def one_clear_error(command: str, path, extra: list, expect: str, tmp_path, monkeypatch, capsys) -> None:
    """`hgca COMMAND PATH [EXTRA]` ends with exit 2 and one line naming the file and `expect`, and the folder is
    as it was (no output, no changed input)."""
    argv = {"read": ["read", path, "-o", "out.npz"], "info": ["info", path],
            "complete": ["complete", path, "-o", "out.ply", "--stage", "coarse", "--progress", "none"]}[command]
    before = folder_state(tmp_path)
    monkeypatch.setattr(sys, "argv", ["hgca"])
    monkeypatch.chdir(tmp_path)
    code = main([str(a) for a in [*argv, *extra]])
    err = capsys.readouterr().err
    assert code == 2, f"exit {code}: {err[-1500:]}"
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in err, err
    assert lines[0].startswith(f"hgca {command}: error: {path}: "), err
    assert expect in lines[0], err
    assert folder_state(tmp_path) == before, "an input changed or an output appeared"


@pytest.mark.parametrize("command", ["read", "info", "complete"])
@pytest.mark.parametrize("case", list(E57_CASES))
def test_hostile_e57_is_one_clear_error(case: str, command: str, tmp_path, monkeypatch, capsys):
    build, expect = E57_CASES[case]
    one_clear_error(command, build(tmp_path), [], expect, tmp_path, monkeypatch, capsys)


# ---------------------------------------------------------------- ROS bags


def _bagwriter():
    """tests/io/bagwriter.py, the bag tests' writer (tests/io is not a package: imported from its folder)."""
    import importlib

    folder = str(Path(__file__).parent / "io")
    if folder not in sys.path:
        sys.path.append(folder)
    return importlib.import_module("bagwriter")


def _bag_of(d: Path, kind: str, name: str, stamps_ms=(0, 100), layout: dict | None = None, cols=None,
            tf_ms=None, **extra):
    """A small bag of clouds on /points (stamps in ms after 2023-11) and an identity /tf at those stamps (or at
    `tf_ms`), written by `kind`."""
    bw = _bagwriter()
    bag = bw.Bag(kind)
    rng = np.random.default_rng(0)
    base = 1_700_000_000 * 10**9
    for k, ms in enumerate(stamps_ms):
        stamp = base + ms * 1_000_000
        columns = cols or {a: rng.uniform(-20, 20, 400) for a in "xyz"}
        msg = bw.cloud(bag.store, stamp, "lidar", columns, **(layout or {}))
        bag.add("/points", bw.CLOUD, base + k * 100_000_000, msg)
    for ms in stamps_ms if tf_ms is None else tf_ms:
        stamp = base + ms * 1_000_000
        bag.add("/tf", bw.TF, stamp, bw.tf_message(bag.store, [(stamp, "odom", "lidar", np.eye(4))]))
    for key, value in extra.items():
        setattr(bag, key, value)
    return bag.write(d / name)


def _bag_truncated_ros1(d: Path):
    path = _bag_of(d, "ros1", "drive.bag")
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    return path, []


def _bag_truncated_mcap(d: Path):
    folder = _bag_of(d, "mcap", "drive")
    (mcap,) = folder.glob("*.mcap")
    mcap.write_bytes(mcap.read_bytes()[: mcap.stat().st_size * 3 // 4])
    return folder, []


def _bag_truncated_db3(d: Path):
    folder = _bag_of(d, "sqlite3", "drive")
    (db3,) = folder.glob("*.db3")
    db3.write_bytes(db3.read_bytes()[: db3.stat().st_size // 2])
    return db3, []


def _bag_truncated_message(d: Path):
    """A cloud whose data is shorter than its height x row_step (a cut-off message)."""
    bw = _bagwriter()
    bag = bw.Bag("ros1")
    msg = bw.cloud(bag.store, 1_700_000_000 * 10**9, "lidar", {a: np.ones(100, dtype=np.float32) for a in "xyz"})
    msg.data = msg.data[:-12]
    bag.add("/points", bw.CLOUD, 1, msg)
    return bag.write(d / "drive.bag"), []


def _bag_not_a_cloud(d: Path):
    return _bag_of(d, "ros1", "drive.bag"), ["--topic", "/tf"]


def _bag_missing_topic(d: Path):
    return _bag_of(d, "mcap", "drive"), ["--topic", "/velodyne_points"]


def _bag_empty_topic(d: Path):
    bw = _bagwriter()
    bag = bw.Bag("sqlite3", empty=[("/points", bw.CLOUD)])
    bag.add("/tf", bw.TF, 1, bw.tf_message(bag.store, [(1, "odom", "lidar", np.eye(4))]))
    return bag.write(d / "drive"), []


def _bag_no_xyz(d: Path):
    return _bag_of(d, "ros1", "drive.bag", cols={n: np.ones(50, dtype=np.float32) for n in ("a", "b", "c")}), []


def _bag_clock_backwards(d: Path):
    return _bag_of(d, "mcap", "drive", stamps_ms=(0, 100, 200, 50, 300)), []


def _bag_tf_ends_early(d: Path):
    return _bag_of(d, "ros1", "drive.bag", stamps_ms=(0, 100, 200, 300), tf_ms=(0, 100)), []


BAG_CASES: dict[str, tuple[Callable[[Path], tuple[Path, list[str]]], str]] = {
    "bag truncated ros1": (_bag_truncated_ros1, "corrupt or truncated bag: Bag index looks damaged"),
    "bag truncated mcap": (_bag_truncated_mcap, "corrupt or truncated bag"),
    "bag truncated db3": (_bag_truncated_db3, "corrupt or truncated bag: Cannot open database"),
    "bag truncated message": (_bag_truncated_message, "topic /points, frame 0: point cloud data holds 1188 bytes "
                                                      "but height 1 x width 100 (row_step 1200, point_step 12) "
                                                      "needs 1200: truncated message"),
    "bag topic not a cloud": (_bag_not_a_cloud, "topic /tf holds tf2_msgs/msg/TFMessage messages, not "
                                                "sensor_msgs/PointCloud2 (point cloud topics: /points (2))"),
    "bag missing topic": (_bag_missing_topic, "the bag has no topic /velodyne_points (point cloud topics: "
                                              "/points (2))"),
    "bag empty topic": (_bag_empty_topic, "topic /points has no messages"),
    "bag without xyz": (_bag_no_xyz, "topic /points, frame 0: point cloud has no x/y/z field (fields: a, b, c)"),
    "bag tf ends early": (_bag_tf_ends_early, "topic /points, frame 3: no tf for frame 'lidar' (in 'odom') at the "
                                              "cloud stamp 1700000000.300 s: /tf covers it from 1700000000.000 to "
                                              "1700000000.100 s"),
    "bag clocks backwards": (_bag_clock_backwards, "topic /points: header stamps go backwards by 0.150 s at "
                                                   "message 3 in recording order (frame interval 0.100 s)"),
}


@pytest.mark.parametrize("command", ["read", "info", "complete"])
@pytest.mark.parametrize("case", list(BAG_CASES))
def test_hostile_bag_is_one_clear_error(case: str, command: str, tmp_path, monkeypatch, capsys):
    build, expect = BAG_CASES[case]
    path, extra = build(tmp_path)
    one_clear_error(command, path, extra, expect, tmp_path, monkeypatch, capsys)
