"""E57 files as input: one frame per scan with the pose the file gives it.

The main file is written with pye57 (`write_scan_raw`, as scanner software exports) from the two real
Argoverse 2 sweeps in tests/data/real, each in its ego frame with its true pose (the log's ego->city quaternion
and translation), so reading the E57 must give what reading the AV2 log gives. Files pye57 cannot write
(double-precision UTM coordinates, spherical scans, 16-bit colour) come from tests/e57_files.py.
"""
from __future__ import annotations

import contextlib
import io
import json
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest

from e57_files import cartesian, write_e57
from hgca_core.cli import main
from hgca_core.errors import InputError
from hgca_core.io.av2 import quat_pose
from hgca_core.io.e57 import INVALID, open_e57
from hgca_core.io.sequence import open_sequence, read_sequence

AV2_7FAB = "av2/7fab2350-7eaf-3b7e-a39d-6937a4c1bede"
UTM = np.array([500000.0, 5400000.0, 250.0])  # a UTM-like easting, northing, height


def hgca(*argv) -> tuple[int, str, str]:
    """The CLI in this process (no torch start-up per call): exit status, stdout, stderr."""
    out, err, saved = io.StringIO(), io.StringIO(), sys.argv[:]
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            code = main([str(a) for a in argv])
    finally:
        sys.argv[:] = saved
    return code, out.getvalue(), err.getvalue()


def world(npz: Path) -> dict[str, np.ndarray]:
    """An `hgca read` / `hgca complete` .npz with its points (or vertices) back in float64 world metres."""
    with np.load(npz) as z:
        arrays = {k: z[k] for k in z.files}
    for key in ("points", "vertices"):
        if key in arrays:
            arrays[key] = arrays[key].astype(np.float64) + arrays["offset"]
    return arrays


def true_quaternions(log: Path, files: tuple[str, ...]) -> list[tuple[np.ndarray, np.ndarray]]:
    """(w, x, y, z), translation of each sweep from the log's own pose table, as written to the E57."""
    import pyarrow.feather as feather

    table = feather.read_table(log / "city_SE3_egovehicle.feather").to_pydict()
    rows = [table["timestamp_ns"].index(int(Path(f).stem)) for f in files]
    return [(np.array([table[c][r] for c in ("qw", "qx", "qy", "qz")]),
             np.array([table[c][r] for c in ("tx_m", "ty_m", "tz_m")])) for r in rows]


@pytest.fixture(scope="module")
def site(real_dir, tmp_path_factory) -> dict:
    """The AV2 log (copied without its calibration: an E57 scan has one scanner position, its frame's origin,
    so the folder's origins must be the ego origin too for completions to match) and `site.e57` made of its
    two sweeps: x, y, z, intensity, a colour made from the laser numbers, and 5 % of points marked invalid
    (moved far away, so a reader keeping them would be seen)."""
    import pye57

    root = tmp_path_factory.mktemp("e57")
    log = root / "log"
    shutil.copytree(real_dir / AV2_7FAB, log, ignore=shutil.ignore_patterns("calibration"))
    seq = open_sequence(log)
    rng = np.random.default_rng(0)
    path = root / "site.e57"
    scans = []
    with pye57.E57(str(path), mode="w") as e57:
        for i, (q, t) in enumerate(true_quaternions(log, seq.files)):
            scan = seq.read_frame(i)
            n = len(scan)
            invalid = rng.random(n) < 0.05
            pts = scan.points.copy()
            pts[invalid] += 50.0  # where no real point is
            laser = scan.attributes["laser_number"].astype(np.int64)
            colour = [(laser * 4 % 256).astype(np.uint8), (255 - laser * 3).astype(np.uint8),
                      scan.attributes["intensity"].astype(np.uint8)]
            intensity = scan.attributes["intensity"].astype(np.float32)
            e57.write_scan_raw({"cartesianX": pts[:, 0], "cartesianY": pts[:, 1], "cartesianZ": pts[:, 2],
                                "intensity": intensity, "colorRed": colour[0], "colorGreen": colour[1],
                                "colorBlue": colour[2], "cartesianInvalidState": (invalid * 2).astype(np.int8)},
                               rotation=q, translation=t)
            scans.append({"q": q, "t": t, "invalid": invalid, "intensity": intensity, "colour": colour})
    return {"log": log, "e57": path, "root": root, "seq": seq, "scans": scans}


@pytest.fixture(scope="module")
def reads(site) -> dict:
    """`hgca read` of the E57 and of the log, both frames."""
    out = {}
    for name, src in (("e57", site["e57"]), ("log", site["log"])):
        npz = site["root"] / f"read_{name}.npz"
        code, stdout, err = hgca("read", src, "--frames", "0:2", "-o", npz)
        assert code == 0, err
        out[name] = world(npz)
        out[name + "_stdout"] = stdout
    return out


def test_e57_points_and_poses_round_trip(site, reads):
    e57, log = reads["e57"], reads["log"]
    valid = np.concatenate([~s["invalid"] for s in site["scans"]])
    np.testing.assert_allclose(e57["points"], log["points"][valid], rtol=0, atol=1e-6)
    np.testing.assert_array_equal(e57["scan_index"], log["scan_index"][valid])
    seq = open_e57(str(site["e57"]), None)
    assert seq.layout == "e57" and seq.files == (f"{site['e57']}#0", f"{site['e57']}#1")
    for pose, written, folder in zip(seq.poses, site["scans"], site["seq"].poses):
        np.testing.assert_allclose(pose, quat_pose(written["q"], written["t"]), rtol=0, atol=1e-9)
        np.testing.assert_allclose(pose, folder, rtol=0, atol=1e-9)
        assert abs(pose[0, 3]) > 1000  # the city frame's km-scale translation, kept
    # the scanner sits at each scan's origin: the origins are the poses' translations
    np.testing.assert_allclose(e57["origins"], [s["t"] for s in site["scans"]], rtol=0, atol=1e-9)


def test_e57_intensity_colour_and_invalid_points(site, reads):
    e57 = reads["e57"]
    index = e57["scan_index"]
    for i, s in enumerate(site["scans"]):
        keep = ~s["invalid"]
        low, high = s["intensity"].min(), s["intensity"].max()  # pye57 writes these as intensityLimits
        got = e57["intensity"][index == i]
        assert got.dtype == np.float32 and 0.0 <= got.min() and got.max() <= 1.0
        np.testing.assert_allclose(got, (s["intensity"][keep] - low) / (high - low), atol=1e-6)
        for name, values in zip(("red", "green", "blue"), s["colour"]):
            assert e57[name].dtype == np.uint8
            np.testing.assert_array_equal(e57[name][index == i], values[keep])
    dropped = sum(int(s["invalid"].sum()) for s in site["scans"])
    assert dropped > 1000 and f"left out {dropped} {INVALID}" in reads["e57_stdout"]
    assert open_e57(str(site["e57"]), None).read_frame(1).dropped == {INVALID: int(site["scans"][1]["invalid"].sum())}


def test_e57_info_shows_the_scans(site):
    code, out, err = hgca("info", site["e57"])
    assert code == 0, err
    assert "e57 sequence" in out and "frames:     2 of 2 (0 to 1): site.e57#0, site.e57#1" in out
    code, out, err = hgca("info", site["e57"], "--json")
    info = json.loads(out)["files"][0]
    valid = [int((~s["invalid"]).sum()) for s in site["scans"]]
    assert info["frames_total"] == 2 and info["points"] == sum(valid)
    assert info["dropped"] == {INVALID: sum(len(s["invalid"]) for s in site["scans"]) - sum(valid)}
    kept = {"intensity": "float32", "red": "uint8", "green": "uint8", "blue": "uint8"}
    assert kept.items() <= info["attributes"].items()


def test_e57_frames_picks_one_scan(site, reads, tmp_path):
    code, _, err = hgca("read", site["e57"], "--frames", "1:2", "-o", tmp_path / "one.npz")
    assert code == 0, err
    one = world(tmp_path / "one.npz")
    both = reads["e57"]
    np.testing.assert_allclose(one["points"], both["points"][both["scan_index"] == 1], rtol=0, atol=1e-6)
    np.testing.assert_allclose(one["origins"], [site["scans"][1]["t"]], rtol=0, atol=1e-9)


def test_e57_completion_equals_the_folders(site, small_weights):
    """One tiny completion of the E57 and of the log: the same mesh, vertex for vertex."""
    centre = site["scans"][0]["t"] + quat_pose(site["scans"][0]["q"], np.zeros(3))[:3, :3] @ [8.0, 0.0, 0.5]
    region = ",".join(f"{v:.3f}" for v in centre) + ",6.4,6.4,4"
    meshes = []
    for name, src in (("e57", site["e57"]), ("log", site["log"])):
        out = site["root"] / f"mesh_{name}.npz"
        code, _, err = hgca("complete", src, "--frames", "0:2", "-o", out, "--weights", small_weights, "--stage",
                            "coarse", "--t1", 2, "--region", region, "--seed", 3, "--progress", "none")
        assert code == 0, err
        meshes.append(world(next(site["root"].glob(f"mesh_{name}*.npz"))))
    assert len(meshes[0]["vertices"]) > 100
    np.testing.assert_allclose(meshes[0]["vertices"], meshes[1]["vertices"], rtol=0, atol=1e-6)
    np.testing.assert_array_equal(meshes[0]["faces"], meshes[1]["faces"])


def test_e57_utm_coordinates_stay_exact(tmp_path):
    """Georeferenced E57s: UTM coordinates in the points (a registered export, no pose) or in the pose (the
    points local) come back exact in float64, and within 0.5 mm through the float32 + offset .npz."""
    rng = np.random.default_rng(4)
    local = rng.uniform(-30, 30, (2000, 3)) + rng.random((2000, 3)) * 1e-3  # sub-mm detail
    in_points = local + UTM
    path = write_e57(tmp_path / "utm.e57", [cartesian(in_points),
                                             cartesian(local, rotation=(0.0, 0.0, 0.0, 1.0), translation=UTM)])
    seq = open_e57(str(path), None)
    np.testing.assert_array_equal(seq.poses[0], np.eye(4))  # no pose: identity
    scan = read_sequence(path, "0:2")
    np.testing.assert_array_equal(scan.points[:2000], in_points)
    # (0, 0, 0, 1) is a half turn about z: x, y -> -x, -y exactly
    np.testing.assert_array_equal(scan.points[2000:], local * [-1, -1, 1] + UTM)
    assert hgca("read", path, "--frames", "0:2", "-o", tmp_path / "utm.npz")[0] == 0
    back = world(tmp_path / "utm.npz")
    assert np.abs(back["offset"]).max() > 1e6  # float32 alone would be off by 0.5 m here
    np.testing.assert_allclose(back["points"], scan.points, rtol=0, atol=5e-4)


def test_e57_spherical_scan_and_16_bit_colour(tmp_path):
    rng = np.random.default_rng(5)
    r, az, el = rng.uniform(1, 80, 500), rng.uniform(-np.pi, np.pi, 500), rng.uniform(-0.5, 0.5, 500)
    expected = np.stack([r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az), r * np.sin(el)], axis=1)
    colour = rng.integers(0, 65536, (3, 500))
    raw = rng.uniform(0, 2047, 500)
    path = write_e57(tmp_path / "sph.e57", [{
        "sphericalRange": r, "sphericalAzimuth": az, "sphericalElevation": el, "intensity": raw,
        "intensity_limits": (0, 2047), "colorRed": colour[0], "colorGreen": colour[1], "colorBlue": colour[2],
        "colour_max": 65535}])
    scan = open_e57(str(path), None).read_frame(0)
    np.testing.assert_allclose(scan.points, expected, rtol=0, atol=1e-9)
    np.testing.assert_allclose(scan.attributes["intensity"], raw / 2047, rtol=1e-6)  # limits, not the data's span
    for name, values in zip(("red", "green", "blue"), colour):
        assert scan.attributes[name].dtype == np.uint16
        np.testing.assert_array_equal(scan.attributes[name], values)
    np.testing.assert_array_equal(scan.origins, [[0.0, 0.0, 0.0]])


def test_e57_refuses_a_topic_and_says_what_a_missing_library_needs(tmp_path, monkeypatch):
    path = write_e57(tmp_path / "a.e57", [cartesian(np.ones((5, 3)))])
    with pytest.raises(InputError, match="--topic applies to ROS bags"):
        open_sequence(path, topic="/points")
    monkeypatch.setitem(sys.modules, "pye57", None)  # as if the recordings extra were not installed
    with pytest.raises(InputError, match=r"recordings extra \(pip install 'hgca\[recordings\]'\)"):
        open_sequence(path)
