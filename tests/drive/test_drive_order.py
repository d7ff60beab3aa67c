"""The path follows the drive whatever order its files come in: unpadded names in the shell's glob order
(scan_0, scan_1, scan_10, ..., scan_2) are put in the drive's order by the poses file, by time stamps, or by the
chain of sensor positions, and a jump between consecutive scans is reported naming the two files."""
import json
import warnings

import numpy as np
import pytest

from drive_data import street_surface, write_drive
from hgca_core.errors import HgcaWarning
from hgca_core.tiling.inputs import read_drive_inputs
from hgca_core.tiling.order import chain, order_scans
from hgca_core.tiling.run import plan_drive

UNPADDED = "scan_{}.npz"


def glob_order(folder):
    """What `scan_*.npz` expands to in a shell: sorted as strings."""
    return sorted(folder.glob("scan_*.npz"), key=lambda p: p.name)


def yaws(doc):
    return np.radians([t["region"][6] for t in doc["tiles"]])


def test_glob_order_with_poses_plans_the_ordered_drive(tmp_path):
    # the drive: 17 scans along a straight 100 m street, listed in order in the poses file
    files, poses = write_drive(tmp_path / "s", length=100.0, spacing=6.25, weave=0.0, name=UNPADDED)
    shuffled = glob_order(tmp_path / "s")
    assert [p.name for p in shuffled[:4]] == ["scan_0.npz", "scan_1.npz", "scan_10.npz", "scan_11.npz"]
    with warnings.catch_warnings():
        warnings.simplefilter("error", HgcaWarning)          # an ordered drive has no jump to report
        _, _, doc = plan_drive(read_drive_inputs(shuffled, poses))
    _, _, want = plan_drive(read_drive_inputs(files, poses))
    assert len(doc["tiles"]) == len(want["tiles"]) == 4      # 106.4 m to cover at a 32 m stride from 38.4 m
    assert np.allclose(yaws(doc), 0.0, atol=np.radians(1.0))
    assert [s["name"] for s in doc["scans"]] == [str(p) for p in files]
    assert doc["length"] == pytest.approx(100.0, abs=0.01)


def world_scans(folder, xs, names, times=None, seed=0):
    """Scans already in world coordinates with their sensor origin (no poses file), optionally a per-point
    `time`; file k is named names[k] and taken at xs[k]."""
    rng = np.random.default_rng(seed)
    surface = street_surface(float(max(xs)), 0.0, rng, density=10.0)
    folder.mkdir()
    paths = []
    for k, (x, name) in enumerate(zip(xs, names)):
        pos = np.array([x, 0.0, 2.0])
        pts = surface[np.linalg.norm(surface[:, :2] - pos[:2], axis=1) < 14.0]
        extra = {} if times is None else {"time": np.full(len(pts), times[k])}
        np.savez(folder / name, points=pts, origins=pos[None], **extra)
        paths.append(folder / name)
    return paths


def test_without_poses_the_chain_of_positions_orders_the_drive(tmp_path):
    xs = np.arange(0.0, 100.1, 6.25)
    files = world_scans(tmp_path / "s", xs, [UNPADDED.format(i) for i in range(len(xs))])
    scans = read_drive_inputs(glob_order(tmp_path / "s"))
    _, _, doc = plan_drive(scans)
    assert len(doc["tiles"]) == 4 and np.allclose(yaws(doc), 0.0, atol=np.radians(1.0))
    assert [s.name for s in scans] == [str(p) for p in files]


def test_time_stamps_order_scans_whose_names_say_nothing(tmp_path):
    xs = np.arange(0.0, 60.1, 5.0)
    names = [f"{h}.npz" for h in ("f3", "a9", "k2", "b1", "x7", "c5", "m0", "d4", "z6", "e8", "q1", "g2", "h0")]
    files = world_scans(tmp_path / "s", xs, names, times=1.7e9 + 0.1 * np.arange(len(xs)))
    scans = read_drive_inputs(sorted(files))
    assert [s.name for s in scans] == [str(p) for p in files]
    assert [s.time for s in scans] == pytest.approx(1.7e9 + 0.1 * np.arange(len(xs)))


def test_a_drive_that_turns_back_on_its_street_keeps_its_order():
    # out along y = 0 and back along y = 3: the chain would zig-zag across the street, the given order does not
    out = np.c_[np.arange(0, 80.1, 4.0), np.zeros(21), np.zeros(21)]
    back = np.c_[np.arange(80, -0.1, -4.0), np.full(21, 3.0), np.zeros(21)]
    pos = np.concatenate([out, back])
    order, how = order_scans([f"s{i:02d}" for i in range(len(pos))], pos, [None] * len(pos))
    assert order == list(range(len(pos))) and how == "given"


def test_chain_starts_at_the_end_nearer_the_first_file():
    pos = np.c_[np.arange(10.0), np.zeros(10), np.zeros(10)][[9, 3, 7, 1, 5, 0, 8, 2, 6, 4]]
    assert pos[chain(pos, 0)][:, 0].tolist() == list(range(9, -1, -1))


def test_a_jump_between_consecutive_scans_names_the_two_files(tmp_path):
    xs = np.r_[np.arange(0.0, 40.1, 4.0), np.arange(120.0, 160.1, 4.0)]          # 80 m without a scan
    files, poses = write_drive(tmp_path / "s", length=160.0, spacing=4.0, weave=0.0, name=UNPADDED)
    keep = [f for f in files if int(f.stem.split("_")[1]) * 4.0 in xs]
    entries = [e for e in json.loads(poses.read_text())["scans"] if tmp_path / "s" / e["file"] in keep]
    poses.write_text(json.dumps({"scans": entries}))
    with pytest.warns(HgcaWarning) as caught:
        read_drive_inputs(sorted(keep), poses)
    [w] = [str(c.message) for c in caught if "jumps" in str(c.message)]
    assert "scan_10.npz -> scan_30.npz: 80.0 m" in w and "median step is 4.0 m" in w


def test_a_jump_warning_is_one_line_on_the_command_line(tmp_path, capsys):
    from hgca_core.cli import main

    files, poses = write_drive(tmp_path / "s", length=100.0, spacing=6.25, weave=0.0, name=UNPADDED)
    entries = json.loads(poses.read_text())["scans"]
    entries.sort(key=lambda e: e["file"])                   # a poses file written in glob order
    poses.write_text(json.dumps({"scans": entries}))
    assert main(["drive", *map(str, glob_order(tmp_path / "s")), "--poses", str(poses), "--out",
                 str(tmp_path / "d"), "--plan-only", "--json"]) == 0
    err = [line for line in capsys.readouterr().err.splitlines() if "jumps" in line]
    assert len(err) == 1 and err[0].startswith("hgca drive: warning: ")
    assert "scan_1.npz -> scan_10.npz: 56.2 m" in err[0]
