"""Hostile inputs that a reader could get silently wrong: header counts that lie, named columns, byte-order
marks, transposed arrays, repeated fields, georeferenced outliers. Each case appends to cases.CASES."""
from __future__ import annotations

import json
import os
import struct
from pathlib import Path
from typing import Callable

import numpy as np

from .cases import EYE, PCD_HEAD, PLY_HEAD, _laz, case, good_las, good_npz, read_cmd, write
from builders import write_las

UTM = np.array([500_000.0, 5_000_000.0, 100.0])
POINTS = 2000


def utm_cloud(n: int = POINTS, seed: int = 0) -> np.ndarray:
    return np.round(np.random.default_rng(seed).uniform([0, 0, 0], [40, 40, 6], (n, 3)) + UTM, 3)


def ply_bytes(points: np.ndarray, declared: int | None = None, double: bool = False) -> bytes:
    head = PLY_HEAD.format(n=len(points) if declared is None else declared)
    if double:
        head = head.replace("property float", "property double")
    return head.encode() + np.asarray(points, "<f8" if double else "<f4").tobytes()


def info_or_read(name: str, expect: str, build, group: str) -> None:
    """The same bad file through `hgca read` and `hgca info`."""
    @case(f"read: {name}", expect, group)
    def _(d, build=build):
        return read_cmd(build(d), d)

    @case(f"info: {name}", expect, group)
    def _(d, build=build):
        return ["info", str(build(d))]


def info_or_read_each(group: str, table: list[tuple[str, str, Callable[[Path], Path]]]) -> None:
    """`info_or_read` of every (name, expected message, file builder) of `table`."""
    for name, expect, build in table:
        info_or_read(name, expect, build, group)


# --- georeferenced precision: points that no float32 frame with one float64 offset holds to 1 mm ---------------

def _stray_ply(d: Path) -> Path:
    pts = utm_cloud()
    pts[17] = 0.0
    return write(d, "stray.ply", ply_bytes(pts, double=True))


def _stray_las(d: Path) -> Path:
    pts = utm_cloud()
    pts[5] = 0.0
    write_las(d / "stray.las", pts, scale=0.01, offset=[0.0, 0.0, 0.0])
    return d / "stray.las"


def _three_far_xyz(d: Path) -> Path:
    pts = np.random.default_rng(1).uniform(0, 30, (500, 3))
    pts[[3, 50, 400]] += 1e8
    return write(d, "far.xyz", "\n".join(" ".join(f"{v:.4f}" for v in p) for p in pts) + "\n")


def _kitti_1e30(d: Path) -> Path:
    rows = np.random.default_rng(2).uniform(-20, 20, (1000, 4)).astype("<f4")
    rows[5, :3] = 1e30
    return write(d, "k.bin", rows.tobytes())


def _las_scale_1e300(d: Path) -> Path:
    raw = bytearray(good_las(d, "src.las").read_bytes())
    (d / "src.las").unlink()
    for axis in range(3):
        struct.pack_into("<d", raw, 131 + 8 * axis, 1e300)
    return write(d, "huge.las", bytes(raw))


def _nuscenes_far(d: Path) -> Path:
    rows = np.random.default_rng(3).uniform(5, 30, (800, 5)).astype("<f4")
    rows[:, 4] = 7
    rows[100, 0] = 3e7
    return write(d, "far.pcd.bin", rows.tobytes())


def _pcd_viewpoint_far(d: Path) -> Path:
    return write(d, "vp.pcd", PCD_HEAD.format(w=3, h=1, n=3, mode="ascii").replace(
        "POINTS", "VIEWPOINT 1e30 0 0 1 0 0 0\nPOINTS") + "1 2 3\n4 5 6\n7 8 9\n")


def _npz_offset_1e300(d: Path) -> Path:
    np.savez(d / "off.npz", points=np.random.default_rng(4).uniform(0, 5, (50, 3)), offset=np.array([1e300, 0, 0]))
    return d / "off.npz"


def _npy_stray(d: Path) -> Path:
    pts = utm_cloud(300)
    pts[-1] = [0.0, 0.0, 0.0]
    np.save(d / "stray.npy", pts)
    return d / "stray.npy"


def _npz_stray(d: Path) -> Path:
    pts = utm_cloud(300) - UTM
    pts[0] = -UTM                                  # (0, 0, 0) once the offset is added
    np.savez(d / "stray.npz", points=pts.astype(np.float32), offset=UTM)
    return d / "stray.npz"


def _pcd_stray(d: Path) -> Path:
    pts = utm_cloud(200)
    pts[9] = 0.0
    head = PCD_HEAD.format(w=200, h=1, n=200, mode="binary").replace("SIZE 4 4 4", "SIZE 8 8 8")
    return write(d, "stray.pcd", head.encode() + pts.astype("<f8").tobytes())


info_or_read_each("georeferenced precision", [
    ("ply stray point at (0, 0, 0) among UTM points", "1 of 2000 points lies", _stray_ply),
    ("las stray point at (0, 0, 0) among UTM points", "1 of 2000 points lies", _stray_las),
    ("xyz 3 points 1e8 m from the others", "3 of 500 points lie", _three_far_xyz),
    ("kitti one point at 1e30", "beyond 1e+09 m", _kitti_1e30),
    ("las scale 1e300", "beyond 1e+09 m", _las_scale_1e300),
    ("nuscenes one return 3e7 m out", "1 of ", _nuscenes_far),
    ("pcd viewpoint at 1e30", "sensor origin(s) have coordinates beyond", _pcd_viewpoint_far),
    ("npz offset 1e300", "'offset'", _npz_offset_1e300),
    ("npy stray point at (0, 0, 0) among UTM points", "1 of 300 points lies", _npy_stray),
    ("npz stray point at (0, 0, 0) after its offset", "1 of 300 points lies", _npz_stray),
    ("pcd stray point at (0, 0, 0) among UTM points", "1 of 200 points lies", _pcd_stray),
])


def _posed(d: Path, poses: list[np.ndarray], scans: int = 1) -> list[str]:
    paths = [good_npz(d, f"s{i}.npz") for i in range(scans)]
    doc = {"scans": [{"file": p.name, "pose": np.asarray(m).tolist()} for p, m in zip(paths, poses)]}
    (d / "poses.json").write_text(json.dumps(doc))
    return ["read", *map(str, paths), "--poses", str(d / "poses.json"), "-o", str(d / "out.npz")]


def _moved(t: tuple[float, float, float]) -> np.ndarray:
    m = np.eye(4)
    m[:3, 3] = t
    return m


@case("read: poses translated by 1e308", "beyond 1e+09 m", "georeferenced precision")
def _(d):
    return _posed(d, [_moved((1e308, 0.0, 0.0))])


@case("read: poses translated by 5e8 on top of 6e8 m points", "beyond 1e+09 m", "georeferenced precision")
def _(d):
    np.savez(d / "s0.npz", points=np.random.default_rng(5).uniform(0, 5, (100, 3)), offset=np.array([6e8, 0, 0]))
    (d / "poses.json").write_text(json.dumps({"scans": [{"file": "s0.npz", "pose": _moved((5e8, 0, 0)).tolist()}]}))
    return ["read", str(d / "s0.npz"), "--poses", str(d / "poses.json"), "-o", str(d / "out.npz")]


@case("read: poses put one of two scans 2e6 m away", "from the others (first at row", "georeferenced precision")
def _(d):
    return _posed(d, [_moved(tuple(UTM)), _moved(tuple(UTM + [2e6, 0, 0]))], scans=2)


@case("read: two UTM scans 900 km apart without poses", "lie 9e+05 m from the others", "georeferenced precision")
def _(d):
    write_las(d / "a.las", utm_cloud(400))
    write_las(d / "b.las", utm_cloud(500, seed=1) + [9e5, 0, 0])
    return ["read", str(d / "a.las"), str(d / "b.las"), "-o", str(d / "out.npz")]


@case("read: kitti sequence pose translated by 1e308", "beyond 1e+09 m", "georeferenced precision")
def _(d):
    root = _kitti(d)
    lines = ["1 0 0 0 0 1 0 0 0 0 1 0", "1 0 0 1e308 0 1 0 0 0 0 1 0"]
    (root / "poses.txt").write_text("\n".join(lines) + "\n")
    return ["read", str(root), "--frames", "0:2", "-o", str(d / "out.npz")]


# --- header counts that lie low: the reader would read the first points and drop the rest ---------------------

def _las_count_low(d: Path) -> Path:
    write_las(d / "src.las", utm_cloud())
    raw = bytearray((d / "src.las").read_bytes())
    (d / "src.las").unlink()
    struct.pack_into("<I", raw, 107, 1500)
    return write(d, "low.las", bytes(raw))


def _las14_count_low(d: Path) -> Path:
    import laspy

    las = laspy.LasData(laspy.LasHeader(point_format=6, version="1.4"))
    pts = utm_cloud()
    las.header.offsets, las.header.scales = np.floor(pts.min(0)), [0.001] * 3
    las.x, las.y, las.z = pts.T
    las.write(str(d / "src.las"))
    raw = bytearray((d / "src.las").read_bytes())
    (d / "src.las").unlink()
    struct.pack_into("<Q", raw, 247, 1500)
    return write(d, "low14.las", bytes(raw))


def _laz_count_low(d: Path) -> Path:
    raw = bytearray(_laz(d))
    struct.pack_into("<I", raw, 107, int(struct.unpack_from("<I", raw, 107)[0]) * 3 // 4)
    return write(d, "low.laz", bytes(raw))


def _ply_count_low(d: Path) -> Path:
    return write(d, "low.ply", ply_bytes(utm_cloud() - UTM, declared=1500))


def _ply_ascii_count_low(d: Path) -> Path:
    rows = "\n".join(" ".join(f"{v:.3f}" for v in p) for p in utm_cloud(20) - UTM)
    head = PLY_HEAD.format(n=15).replace("binary_little_endian", "ascii")
    return write(d, "low_ascii.ply", head + rows + "\n")


info_or_read_each("silently wrong reads", [
    ("las header counts 1500 of 2000 points", "file holds 2000 point records", _las_count_low),
    ("las 1.4 header counts 1500 of 2000 points", "file holds 2000 point records", _las14_count_low),
    ("laz header counts 3/4 of its points", "compressed data holds", _laz_count_low),
    ("ply header counts 1500 of 2000 vertices", "500 more vertex records", _ply_count_low),
    ("ply ascii header counts 15 of 20 vertices", "20 rows (5 more)", _ply_ascii_count_low),
])


# --- text tables: columns by name, not by position; numbers Python does not read ------------------------------

TEXT_FILES = {
    "csv header id,a,b,c": ("h.csv", "id,a,b,c\n1,2,3,4\n5,6,7,8\n", "names no x or y or z column"),
    "csv header lat,lon,alt": ("ll.csv", "lat,lon,alt\n45.1,7.6,300\n45.2,7.7,301\n", "degrees"),
    "csv header x,y,height,z": ("hz.csv", "x,y,height,z\n1,2,3,4\n", "names z twice"),
    "csv header x,x,z": ("xx.csv", "x,x,z\n1,2,3\n", "'x' 2 times"),
    "csv header x,y only of 3": ("xy.csv", "x,y,intensity\n1,2,3\n", "names no z column"),
    "csv hex floats": ("hex.csv", "0x1p3,0x1p2,0x1p1\n", "hexadecimal number '0x1p3'"),
    "csv hex floats under a header": ("hexh.csv", "x,y,z\n1,2,3\n0x1p3,0x1p2,0x1p1\n", "hexadecimal"),
    "csv decimal commas": ("dc.csv", "1,5;2,5;3,5\n4,5;5,5;6,5\n", "decimal comma"),
    "txt decimal commas between spaces": ("dc.txt", "1,5 2,5 3,5\n", "decimal comma"),
    "csv first row mixes names and numbers": ("mix.csv", "1,2,z\n4,5,6\n", "mixes numbers and names"),
}


def _utf16(d: Path) -> Path:
    return write(d, "u16.csv", "x,y,z\n1,2,3\n".encode("utf-16"))


info_or_read_each("silently wrong reads", [
    *[(n, e, lambda d, f=f, t=t: write(d, f, t)) for n, (f, t, e) in TEXT_FILES.items()],
    ("csv in utf-16", "UTF-16", _utf16),
])


# --- arrays, PCD, AV2 ------------------------------------------------------------------------------------------

def _npy_transposed(d: Path) -> Path:
    np.save(d / "t.npy", np.random.default_rng(6).uniform(0, 5, (3, 500)))
    return d / "t.npy"


def _npz_transposed(d: Path) -> Path:
    np.savez(d / "t.npz", points=np.random.default_rng(7).uniform(0, 5, (4, 500)))
    return d / "t.npz"


def _npz_origin_index(d: Path) -> Path:
    pts = np.random.default_rng(8).uniform(0, 5, (60, 3))
    np.savez(d / "oi.npz", points=pts, origins=np.zeros((2, 3)), origin_index=np.arange(60, dtype=np.uint16) % 3)
    return d / "oi.npz"


PCD_FILES = {
    "pcd field x twice": ("FIELDS x x y z\nSIZE 4 4 4 4\nTYPE F F F F\nCOUNT 1 1 1 1\nWIDTH 1\nHEIGHT 1\n"
                          "POINTS 1\nDATA ascii\n1 2 3 4\n", "lists 'x' 2 times"),
    "pcd two FIELDS lines": ("FIELDS x y z\nFIELDS z y x\nSIZE 4 4 4\nTYPE F F F\nWIDTH 1\nHEIGHT 1\nPOINTS 1\n"
                             "DATA ascii\n1 2 3\n", "two FIELDS lines"),
    "pcd viewpoint nan": (PCD_HEAD.format(w=1, h=1, n=1, mode="ascii").replace(
        "POINTS", "VIEWPOINT nan 0 0 1 0 0 0\nPOINTS") + "1 2 3\n", "VIEWPOINT has NaN"),
    "pcd viewpoint inf": (PCD_HEAD.format(w=1, h=1, n=1, mode="ascii").replace(
        "POINTS", "VIEWPOINT 0 inf 0 1 0 0 0\nPOINTS") + "1 2 3\n", "VIEWPOINT has NaN or infinite"),
}

info_or_read_each("silently wrong reads", [
    ("npy of shape (3, 500)", "more columns than rows", _npy_transposed),
    ("npz points of shape (4, 500)", "more columns than rows", _npz_transposed),
    ("npz origin_index beyond its origins", "2 sensor origin(s)", _npz_origin_index),
    *[(n, e, lambda d, t=t: write(d, "f.pcd", t)) for n, (t, e) in PCD_FILES.items()],
])


def _feather(path: Path, columns: dict) -> Path:
    import pyarrow as pa
    import pyarrow.feather as feather

    path.parent.mkdir(parents=True, exist_ok=True)
    feather.write_feather(pa.table(columns), str(path))
    return path


def _sweep_columns(n: int = 50) -> dict:
    rng = np.random.default_rng(9)
    return {"x": rng.uniform(-20, 20, n), "y": rng.uniform(-20, 20, n), "z": rng.uniform(-2, 3, n),
            "intensity": rng.integers(0, 255, n).astype(np.uint8), "laser_number": (np.arange(n) % 64).astype(np.uint8),
            "offset_ns": np.arange(n, dtype=np.int32) * 1000}


def _av2_sweep(d: Path, **change) -> Path:
    return _feather(d / "315966070159854000.feather", {**_sweep_columns(), **change})


info_or_read_each("silently wrong reads", [
    (n, e, lambda d, c=c: _av2_sweep(d, **c)) for n, c, e in [
        ("av2 sweep x column of strings", {"x": [f"{v:.3f}" for v in np.linspace(0, 5, 50)]}, "'x' holds strings"),
        ("av2 sweep z column of strings", {"z": ["1.0"] * 50}, "'z' holds strings"),
        ("av2 laser_number of fractions", {"laser_number": np.linspace(0, 3, 50)}, "whole numbers"),
        ("av2 intensity of strings", {"intensity": ["bright"] * 50}, "'intensity' holds strings"),
    ]])


def _av2_log(d: Path, poses: dict | None = None, calibration: dict | None = None) -> Path:
    log = d / "log"
    stamps = [315966070159854000, 315966070259854000]
    for s in stamps:
        _feather(log / "sensors" / "lidar" / f"{s}.feather", _sweep_columns())
    table = {"timestamp_ns": np.array(stamps, dtype=np.int64), "qw": [1.0, 1.0], "qx": [0.0, 0.0], "qy": [0.0, 0.0],
             "qz": [0.0, 0.0], "tx_m": [2000.0, 2001.0], "ty_m": [3000.0, 3000.0], "tz_m": [10.0, 10.0]}
    _feather(log / "city_SE3_egovehicle.feather", {**table, **(poses or {})})
    if calibration is not None:
        _feather(log / "calibration" / "egovehicle_SE3_sensor.feather", calibration)
    return log


@case("read: av2 pose table with two rows for one timestamp", "2 rows for timestamp", "silently wrong reads")
def _(d):
    stamps = np.array([315966070159854000, 315966070159854000], dtype=np.int64)
    return ["read", str(_av2_log(d, {"timestamp_ns": stamps, "tx_m": [2000.0, 2400.0]})), "--frames", "0:1",
            "-o", str(d / "out.npz")]


@case("read: av2 pose table translated by 1e308", "beyond 1e+09 m", "georeferenced precision")
def _(d):
    return ["read", str(_av2_log(d, {"tx_m": [1e308, 1e308]})), "--frames", "0:2", "-o", str(d / "out.npz")]


@case("read: av2 calibration with two up_lidar rows", "2 'up_lidar' rows", "silently wrong reads")
def _(d):
    calib = {"sensor_name": ["up_lidar", "down_lidar", "up_lidar"], "qw": [1.0] * 3, "qx": [0.0] * 3,
             "qy": [0.0] * 3, "qz": [0.0] * 3, "tx_m": [1.0, 1.0, 3.0], "ty_m": [0.0] * 3, "tz_m": [1.9, 1.7, 1.9]}
    return ["read", str(_av2_log(d, calibration=calib)), "--frames", "0:1", "-o", str(d / "out.npz")]


# --- poses and sequences: one file, two entries; frames that shift --------------------------------------------

def _two_entries(d: Path, link) -> list[str]:
    scan = good_npz(d)
    link(scan, d / "alias.npz")
    shifted = _moved((5.0, 0.0, 0.0)).tolist()
    (d / "poses.json").write_text(json.dumps({"scans": [{"file": "scan.npz", "pose": EYE},
                                                        {"file": "alias.npz", "pose": shifted}]}))
    return read_cmd(scan, d, "--poses", d / "poses.json")


@case("read: poses name one file twice, once through a symlink", "with different poses", "silently wrong reads")
def _(d):
    return _two_entries(d, lambda src, dst: dst.symlink_to(src.name))


@case("read: poses name one file twice, once through a hard link", "hard link", "silently wrong reads")
def _(d):
    return _two_entries(d, lambda src, dst: os.link(src, dst))


@case("read: same scan file given twice", "given twice", "silently wrong reads")
def _(d):
    scan = good_npz(d)
    return ["read", str(scan), str(scan), "-o", str(d / "out.npz")]


@case("read: same scan given twice, once through a symlink", "given twice", "silently wrong reads")
def _(d):
    scan = good_npz(d)
    (d / "alias.npz").symlink_to(scan.name)
    return ["read", str(scan), str(d / "alias.npz"), "-o", str(d / "out.npz")]


def _kitti(d: Path, names: tuple[str, ...] = ("000000.bin", "000001.bin")) -> Path:
    root = d / "seq"
    (root / "velodyne").mkdir(parents=True)
    for i, name in enumerate(names):
        rows = np.random.default_rng(10 + i).uniform(-10, 10, (400, 4)).astype("<f4")
        (root / "velodyne" / name).write_bytes(rows.tobytes())
    (root / "calib.txt").write_text("Tr: 1 0 0 0 0 1 0 0 0 0 1 0\n")
    (root / "poses.txt").write_text("1 0 0 0 0 1 0 0 0 0 1 0\n1 0 0 1 0 1 0 0 0 0 1 0\n1 0 0 2 0 1 0 0 0 0 1 0\n")
    return root


@case("read: kitti poses.txt with a blank line between frames", "line 2 is blank", "silently wrong reads")
def _(d):
    root = _kitti(d)
    (root / "poses.txt").write_text("1 0 0 0 0 1 0 0 0 0 1 0\n\n1 0 0 1 0 1 0 0 0 0 1 0\n1 0 0 2 0 1 0 0 0 0 1 0\n")
    return ["read", str(root), "--frames", "0:2", "-o", str(d / "out.npz")]


@case("read: kitti 000001.bin and 1.bin both frame 1", "both frame 1", "silently wrong reads")
def _(d):
    root = _kitti(d, ("000000.bin", "000001.bin", "1.bin"))
    return ["read", str(root), "--frames", "0:2", "-o", str(d / "out.npz")]


@case("read: kitti calib.txt with two different Tr lines", "2 different 'Tr:' lines", "silently wrong reads")
def _(d):
    root = _kitti(d)
    (root / "calib.txt").write_text("Tr: 1 0 0 0 0 1 0 0 0 0 1 0\nTr: 1 0 0 5 0 1 0 0 0 0 1 0\n")
    return ["read", str(root), "--frames", "0:2", "-o", str(d / "out.npz")]


def _av2_repeated_column(d: Path) -> Path:
    import pyarrow as pa
    import pyarrow.feather as feather

    cols = _sweep_columns()
    arrays = [pa.array(cols["x"]), pa.array(cols["x"] + 3.0), pa.array(cols["y"]), pa.array(cols["z"]),
              pa.array(cols["laser_number"])]
    path = d / "315966070159854000.feather"
    feather.write_feather(pa.Table.from_arrays(arrays, names=["x", "x", "y", "z", "laser_number"]), str(path))
    return path


info_or_read("av2 sweep with column x twice", "column 'x' 2 times", _av2_repeated_column, "silently wrong reads")
info_or_read("csv rows ending in a delimiter", "an empty value", lambda d: write(d, "t.csv", "1,2,3,\n4,5,6,\n"),
             "silently wrong reads")


def _npz_repeated_member(d: Path) -> Path:
    import io
    import warnings
    import zipfile

    def member(a: np.ndarray) -> bytes:
        buf = io.BytesIO()
        np.save(buf, a)
        return buf.getvalue()

    with warnings.catch_warnings():           # zipfile warns of the duplicate name it is told to write
        warnings.simplefilter("ignore")
        with zipfile.ZipFile(d / "dupe.npz", "w") as z:
            z.writestr("points.npy", member(np.zeros((50, 3))))
            z.writestr("points.npy", member(np.ones((50, 3))))
    return d / "dupe.npz"


info_or_read("npz holding 'points' twice", "'points' 2 times", _npz_repeated_member, "silently wrong reads")


@case("read: poses entry giving pose twice", "'pose' twice", "silently wrong reads")
def _(d):
    scan = good_npz(d)
    moved = json.dumps(_moved((4.0, 0.0, 0.0)).tolist())
    text = '{"scans": [{"file": "scan.npz", "pose": %s, "pose": %s}]}' % (json.dumps(EYE), moved)
    (d / "poses.json").write_text(text)
    return read_cmd(scan, d, "--poses", d / "poses.json")


@case("read: poses with two scans lists", "'scans' twice", "silently wrong reads")
def _(d):
    scan = good_npz(d)
    entry = json.dumps([{"file": "scan.npz", "pose": EYE}])
    moved = json.dumps([{"file": "scan.npz", "pose": _moved((4.0, 0.0, 0.0)).tolist()}])
    (d / "poses.json").write_text('{"scans": %s, "scans": %s}' % (entry, moved))
    return read_cmd(scan, d, "--poses", d / "poses.json")


@case("read: av2 calibration with a lidar 1e30 m out", "lidar position(s) have coordinates beyond",
      "georeferenced precision")
def _(d):
    calib = {"sensor_name": ["up_lidar", "down_lidar"], "qw": [1.0] * 2, "qx": [0.0] * 2, "qy": [0.0] * 2,
             "qz": [0.0] * 2, "tx_m": [1.0, 1e30], "ty_m": [0.0] * 2, "tz_m": [1.9, 1.7]}
    return ["read", str(_av2_log(d, calibration=calib)), "--frames", "0:1", "-o", str(d / "out.npz")]
