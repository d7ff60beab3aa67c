"""Hostile-input campaign for the `hgca` CLI: bad files of every format, bad poses, bad flags, bad outputs.

Each case builds its files in an empty folder and returns the command line. The expectation is the same for
all: exit status 2, an `error:` line and no Python traceback on stderr, every file in the folder unchanged
and nothing new written. tests/test_hostile_inputs.py runs every case in-process (fast); the benchmark
benchmarks/hostile_inputs.py runs them as real subprocesses and writes a results page. The cases are test data, so
they live in tests/ and the benchmark imports them (tests never import benchmarks/, the reverse is allowed).
"""
from __future__ import annotations

import json
import os
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from builders import tiny_sample, write_las


@dataclass(frozen=True)
class Case:
    name: str
    build: Callable[[Path], list[str]]  # makes files under the folder, returns argv (after `hgca`)
    expect: str = ""  # a piece of the error message that names the problem
    group: str = ""  # bad files, paths, poses, outputs, flags, degenerate scans


CASES: list[Case] = []


def case(name: str, expect: str = "", group: str = ""):
    def register(build: Callable[[Path], list[str]]) -> Callable[[Path], list[str]]:
        CASES.append(Case(name, build, expect, group))
        return build
    return register


def scene_points() -> np.ndarray:
    return tiny_sample(3)["input_points"].astype(np.float64)


def good_npz(d: Path, name: str = "scan.npz") -> Path:
    np.savez(d / name, points=scene_points())
    return d / name


def good_las(d: Path, name: str = "scan.las") -> Path:
    write_las(d / name, scene_points() + [500_000.0, 5_000_000.0, 0.0])
    return d / name


def write(d: Path, name: str, data: bytes | str) -> Path:
    path = d / name
    path.write_bytes(data.encode() if isinstance(data, str) else data)
    return path


def special_file(d: Path, name: str, kind: str) -> Path:
    """`d/name` made as something a reader must refuse before it opens it for content: a fifo (a read would
    hang), a symlink loop, a dangling symlink, a folder, or an empty file."""
    path = d / name
    if kind == "fifo":
        os.mkfifo(path)
    elif kind == "symlink loop":
        path.symlink_to(path)
    elif kind == "dangling symlink":
        path.symlink_to(d / f"nowhere{path.suffix}")
    elif kind == "folder":
        path.mkdir()
    elif kind == "empty":
        path.write_text("")
    else:
        raise ValueError(kind)
    return path


def special_file_cases(group: str, cmd: Callable[[Path, Path], list[str]],
                       table: list[tuple[str, str, str, str]]) -> None:
    """A case for each (name, expected message, file name, kind) of `table`: `cmd(d, path)` given the
    `special_file` it makes."""
    for name, expect, file, kind in table:
        case(name, expect, group=group)(lambda d, f=file, k=kind: cmd(d, special_file(d, f, k)))


def read_cmd(scan: Path, d: Path, *extra) -> list[str]:
    return ["read", str(scan), *map(str, extra), "-o", str(d / "out.npz")]


def complete_cmd(scan: Path, d: Path, *extra) -> list[str]:
    return ["complete", str(scan), *map(str, extra), "-o", str(d / "out.npz"), "--progress", "none"]


# --- file contents, one reader after the other (through `hgca read`, `hgca info` and `hgca complete`) --------

RANDOM = bytes(np.random.default_rng(0).integers(0, 256, 4096, dtype=np.uint8))
PLY_HEAD = "ply\nformat binary_little_endian 1.0\nelement vertex {n}\nproperty float x\nproperty float y\n" \
           "property float z\nend_header\n"
PCD_HEAD = "VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH {w}\nHEIGHT {h}\n" \
           "POINTS {n}\nDATA {mode}\n"

BAD_FILES: dict[str, tuple[str, Callable[[Path], bytes | str], str]] = {
    # name: (file name, content, expected message part)
    "empty ply": ("e.ply", lambda d: b"", "empty"),
    "random ply": ("r.ply", lambda d: RANDOM, ""),
    "ply header only": ("h.ply", lambda d: "ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\n", ""),
    "ply truncated binary": ("t.ply", lambda d: PLY_HEAD.format(n=100).encode() + b"\0" * 600, ""),
    "ply 4 billion vertices": ("b.ply", lambda d: PLY_HEAD.format(n=4_294_967_295).encode() + b"\0" * 24, ""),
    "ply no z": ("z.ply", lambda d: "ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\n"
                                     "end_header\n1 2\n", "lacks z"),
    "ply text values": ("v.ply", lambda d: "ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\n"
                                           "property float y\nproperty float z\nend_header\na b c\n", ""),
    "ply nan": ("n.ply", lambda d: PLY_HEAD.format(n=2).encode() + np.array([[np.nan, 1, 2], [1, 2, 3]], "<f4").tobytes(),
                "NaN"),
    "ply no vertex element": ("f.ply", lambda d: "ply\nformat ascii 1.0\nelement face 0\n"
                                                 "property list uchar int vertex_indices\nend_header\n", "vertex"),
    "empty las": ("e.las", lambda d: b"", "empty"),
    "random las": ("r.las", lambda d: RANDOM, ""),
    "las magic only": ("m.las", lambda d: b"LASF" + b"\0" * 50, ""),
    "las header only": ("h.las", lambda d: (good_las(d, "src.las").read_bytes()[:227]), ""),
    "las cut in the points": ("c.las", lambda d: good_las(d, "src.las").read_bytes()[:5000], "truncated"),
    "las scale x 0": ("sx.las", lambda d: _patch(good_las(d, "src.las"), 131, "<d", 0.0), "x scale is 0"),
    "las scale z 0": ("sz.las", lambda d: _patch(good_las(d, "src.las"), 147, "<d", 0.0), "z scale is 0"),
    "las scale nan": ("sn.las", lambda d: _patch(good_las(d, "src.las"), 139, "<d", float("nan")), "scale"),
    "las offset inf": ("oi.las", lambda d: _patch(good_las(d, "src.las"), 155, "<d", float("inf")), "offset"),
    "las 4.29e9 points": ("p.las", lambda d: _patch(good_las(d, "src.las"), 107, "<I", 0xFFFFFFFF, cut=600),
                          "truncated or corrupt"),
    "las bad point format": ("pf.las", lambda d: _patch(good_las(d, "src.las"), 104, "<B", 99), ""),
    "las bad header size": ("hs.las", lambda d: _patch(good_las(d, "src.las"), 94, "<H", 10), ""),
    "laz cut in half": ("c.laz", lambda d: (lambda raw: raw[: len(raw) // 2])(_laz(d)), "truncated or corrupt"),
    "laz 4.29e9 points": ("p.laz", lambda d: _patch_bytes(_laz(d), 107, "<I", 0xFFFFFFFF), "truncated or corrupt"),
    "empty pcd": ("e.pcd", lambda d: b"", "empty"),
    "pcd no data line": ("n.pcd", lambda d: "FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nWIDTH 1\nHEIGHT 1\n", "DATA"),
    "pcd points vs rows": ("r.pcd", lambda d: PCD_HEAD.format(w=2, h=1, n=2, mode="ascii") + "1 2 3\n4 5 6\n7 8 9\n",
                           "POINTS"),
    "pcd width x height": ("w.pcd", lambda d: PCD_HEAD.format(w=5, h=1, n=3, mode="ascii") + "1 2 3\n" * 3,
                           "WIDTH x HEIGHT"),
    "pcd trailing garbage": ("g.pcd", lambda d: PCD_HEAD.format(w=3, h=1, n=3, mode="binary").encode()
                             + np.ones((3, 3), "<f4").tobytes() + b"garbage!", "POINTS"),
    "pcd truncated binary": ("t.pcd", lambda d: PCD_HEAD.format(w=3, h=1, n=3, mode="binary").encode() + b"\0" * 20,
                             "truncated"),
    "pcd huge points": ("h.pcd", lambda d: PCD_HEAD.format(w=2_000_000_000, h=2, n=4_000_000_000, mode="binary")
                        .encode() + b"\0" * 24, "truncated"),
    "pcd negative width": ("nw.pcd", lambda d: PCD_HEAD.format(w=-3, h=-1, n=3, mode="ascii") + "1 2 3\n" * 3, ""),
    "pcd unknown type": ("u.pcd", lambda d: "FIELDS x y z\nSIZE 4 4 4\nTYPE Q Q Q\nWIDTH 1\nHEIGHT 1\nDATA ascii\n"
                                            "1 2 3\n", "TYPE"),
    "pcd bad data mode": ("m.pcd", lambda d: PCD_HEAD.format(w=1, h=1, n=1, mode="zip") + "1 2 3\n", "DATA"),
    "pcd compressed sizes lie": ("c.pcd", lambda d: PCD_HEAD.format(w=3, h=1, n=3, mode="binary_compressed").encode()
                                 + struct.pack("<II", 10, 36) + b"\xff" * 10, ""),
    "pcd compressed trailing": ("ct.pcd", lambda d: PCD_HEAD.format(w=1, h=1, n=1, mode="binary_compressed").encode()
                                + struct.pack("<II", 13, 12) + bytes([11]) + b"\0" * 12 + b"junk after", "POINTS"),
    "pcd malformed number": ("mn.pcd", lambda d: "FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nWIDTH one\nHEIGHT 1\n"
                                                 "DATA ascii\n1 2 3\n", "malformed"),
    "xyz garbage": ("g.xyz", lambda d: "hello world\nthis is not a table\n", ""),
    "xyz two columns": ("t.xyz", lambda d: "1 2\n3 4\n", "3 columns"),
    "xyz comments only": ("c.xyz", lambda d: "# nothing\n\n# here\n", "no points"),
    "xyz nan": ("n.xyz", lambda d: "1 2 3\nnan 1 1\n", "NaN"),
    "csv ragged": ("r.csv", lambda d: "1,2,3\n4,5\n", ""),
    "txt inf": ("i.txt", lambda d: "1 2 3\ninf 0 0\n", "infinite"),
    "npy pickled objects": ("o.npy", lambda d: _npy_object(d), ""),
    "npy one dimension": ("1.npy", lambda d: _npy(d, np.arange(9.0)), "(N, >=3)"),
    "npy strings": ("s.npy", lambda d: _npy(d, np.array([["a", "b", "c"]])), "non-numeric"),
    "npy no xyz fields": ("f.npy", lambda d: _npy(d, np.zeros(3, dtype=[("a", "f4"), ("b", "f4")])), "x, y, z"),
    "npy random": ("r.npy", lambda d: RANDOM, ""),
    "npz no points": ("n.npz", lambda d: _npz(d, other=np.zeros((3, 3))), "no 'points'"),
    "npz points 2 columns": ("p.npz", lambda d: _npz(d, points=np.zeros((3, 2))), "(N, >=3)"),
    "npz offset bad shape": ("o.npz", lambda d: _npz(d, points=np.zeros((20, 3)), offset=np.zeros(2)), "offset"),
    "npz offset nan": ("on.npz", lambda d: _npz(d, points=np.zeros((20, 3)), offset=np.array([np.nan, 0, 0])),
                       "offset"),
    "npz pickled points": ("pk.npz", lambda d: _npz(d, points=np.array([{"a": 1}], dtype=object)), ""),
    "npz not a zip": ("z.npz", lambda d: b"PK\x03\x04" + RANDOM, ""),
    "npz all nan": ("a.npz", lambda d: _npz(d, points=np.full((5, 3), np.nan)), "no points"),
    "kitti odd size": ("k.bin", lambda d: b"\0" * 17, "multiple of 16"),
    "kitti nan": ("kn.bin", lambda d: np.array([[np.nan, 0, 0, 1], [1, 2, 3, 4]], "<f4").tobytes(), "NaN"),
    "nuscenes odd size": ("n.pcd.bin", lambda d: b"\0" * 21, "multiple of 20"),
    "ply content named las": ("x.las", lambda d: PLY_HEAD.format(n=0), "content is PLY"),
    "unknown extension": ("scan.rcp", lambda d: b"whatever", "unknown file extension"),
}


def _patch_bytes(raw: bytes, offset: int, fmt: str, value, cut: int | None = None) -> bytes:
    data = bytearray(raw)
    struct.pack_into(fmt, data, offset, value)
    return bytes(data[:cut] if cut else data)


def _patch(path: Path, offset: int, fmt: str, value, cut: int | None = None) -> bytes:
    data = _patch_bytes(path.read_bytes(), offset, fmt, value, cut)
    path.unlink()
    return data


def _laz(d: Path) -> bytes:
    import laspy

    src = good_las(d, "src.las")
    las = laspy.read(str(src))
    las.write(str(d / "src.laz"))
    src.unlink()
    data = (d / "src.laz").read_bytes()
    (d / "src.laz").unlink()
    return data


def _npy(d: Path, array: np.ndarray) -> bytes:
    np.save(d / "tmp.npy", array)
    data = (d / "tmp.npy").read_bytes()
    (d / "tmp.npy").unlink()
    return data


def _npy_object(d: Path) -> bytes:
    np.save(d / "tmp.npy", np.array([[1, 2, 3]], dtype=object), allow_pickle=True)
    data = (d / "tmp.npy").read_bytes()
    (d / "tmp.npy").unlink()
    return data


def _npz(d: Path, **arrays) -> bytes:
    np.savez(d / "tmp.npz", **arrays)
    data = (d / "tmp.npz").read_bytes()
    (d / "tmp.npz").unlink()
    return data


for _label, (_file, _content, _expect) in BAD_FILES.items():
    def _bad_file(d: Path, command: str, file=_file, content=_content) -> list[str]:
        path = write(d, file, content(d))
        if command == "info":
            return ["info", str(path)]
        return read_cmd(path, d) if command == "read" else complete_cmd(path, d)

    for _command in ("read", "info", "complete"):
        CASES.append(Case(f"{_command}: {_label}", lambda d, f=_bad_file, c=_command: f(d, c), _expect,
                          f"bad files ({_command})"))


# --- paths that are not files ---------------------------------------------------------------------------------

@case("read: a folder as scan", "folder is not a known sequence layout", group="paths")  # folders are sequences now
def _(d):
    (d / "dir.ply").mkdir()
    return read_cmd(d / "dir.ply", d)


special_file_cases("paths", lambda d, path: read_cmd(path, d), [
    ("read: symlink loop as scan", "symbolic link loop", "loop.las", "symlink loop"),
    ("read: dangling symlink as scan", "missing target", "gone.las", "dangling symlink"),
    ("read: a fifo as scan", "not a regular file", "pipe.xyz", "fifo"),
])


@case("read: /dev/zero as scan", "not a regular file", group="paths")
def _(d):
    return read_cmd(Path("/dev/zero"), d, "--format", "xyz")


@case("read: missing scan", "not found", group="paths")
def _(d):
    return read_cmd(d / "missing.ply", d)


@case("read: unknown --format", "unknown format", group="paths")
def _(d):
    return read_cmd(good_npz(d), d, "--format", "e57")


# --- poses ------------------------------------------------------------------------------------------------------

def poses_case(name: str, doc, expect: str = "") -> None:
    @case(f"read: poses {name}", expect, "poses")
    def _(d, doc=doc):
        scan = good_npz(d)
        text = doc(scan) if callable(doc) else doc
        (d / "poses.json").write_text(text if isinstance(text, str) else json.dumps(text))
        return read_cmd(scan, d, "--poses", d / "poses.json")


def _entry(pose, **extra):
    return lambda scan: {"scans": [{"file": scan.name, "pose": pose, **extra}]}


EYE = np.eye(4).tolist()
poses_case("not json", "{not json", "not valid JSON")
poses_case("empty object", "{}", '"scans" list')
poses_case("top-level list", "[]", '"scans" list')
poses_case("scans not a list", {"scans": 3}, '"scans" list')
poses_case("entry without file", {"scans": [{"pose": EYE}]}, '"file" string')
poses_case("file not a string", {"scans": [{"file": 3, "pose": EYE}]}, '"file" string')
poses_case("file with NUL", {"scans": [{"file": "a\u0000b.npz", "pose": EYE}]}, "NUL")
poses_case("no pose", lambda s: {"scans": [{"file": s.name}]}, 'no "pose"')
poses_case("3x3 pose", _entry(np.eye(3).tolist()), "4x4")
poses_case("string pose", _entry("identity"), "4x4")
poses_case("ragged pose", _entry([[1, 0, 0, 0], [0, 1, 0], [0, 0, 1, 0], [0, 0, 0, 1]]), "4x4")
poses_case("nan pose", lambda s: '{"scans": [{"file": "%s", "pose": [[NaN,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}]}'
           % s.name, "NaN")
poses_case("1e400 in pose", lambda s: '{"scans": [{"file": "%s", "pose": [[1e400,0,0,0],[0,1,0,0],[0,0,1,0],'
           '[0,0,0,1]]}]}' % s.name, "infinite")
poses_case("scaled pose", _entry((np.eye(4) * [2, 2, 2, 1]).tolist()), "orthonormal")
poses_case("reflection", _entry(np.diag([1.0, 1.0, -1.0, 1.0]).tolist()), "reflection")
poses_case("bad last row", _entry([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [1, 0, 0, 1]]), "last row")
poses_case("origin of 2 numbers", _entry(EYE, origin=[1, 2]), '"origin"')
poses_case("origin nan", lambda s: '{"scans": [{"file": "%s", "pose": %s, "origin": [NaN, 0, 0]}]}'
           % (s.name, json.dumps(EYE)), '"origin"')
poses_case("no entry for the scan", {"scans": [{"file": "other.npz", "pose": EYE}]}, "no pose for scan")
poses_case("another folder's file of the same name", lambda s: {"scans": [{"file": "/elsewhere/drive/" + s.name,
                                                                          "pose": EYE}]}, "another folder")
poses_case("same file twice", lambda s: {"scans": [{"file": s.name, "pose": EYE}, {"file": "./" + s.name, "pose": EYE}]},
           "same file")
poses_case("nested 100000 deep", '{"scans": ' + "[" * 100_000 + "]" * 100_000 + "}", "too deeply")
poses_case("utf-16", lambda s: json.dumps({"scans": []}).encode("utf-16").decode("latin-1"), "")


special_file_cases("poses", lambda d, path: read_cmd(good_npz(d), d, "--poses", path), [
    ("read: poses is a folder", "is a folder", "poses", "folder"),
    ("read: poses is a symlink loop", "symbolic link loop", "poses.json", "symlink loop"),
    ("read: poses is empty", "empty", "poses.json", "empty"),
])


# --- outputs ----------------------------------------------------------------------------------------------------

@case("read: output is the input", "overwrite an input", group="outputs")
def _(d):
    scan = good_npz(d)
    return ["read", str(scan), "-o", str(scan)]


@case("read: output is a hard link to the input", "overwrite an input", group="outputs")
def _(d):
    scan = good_npz(d)
    os.link(scan, d / "link.npz")
    return ["read", str(scan), "-o", str(d / "link.npz")]


@case("read: output is a symlink to the input", "overwrite an input", group="outputs")
def _(d):
    scan = good_npz(d)
    (d / "link.npz").symlink_to(scan)
    return ["read", str(scan), "-o", str(d / "link.npz")]


@case("read: output in a missing folder", "does not exist", group="outputs")
def _(d):
    return ["read", str(good_npz(d)), "-o", str(d / "missing" / "out.npz")]


@case("read: output is a folder", "existing folder", group="outputs")
def _(d):
    (d / "out.npz").mkdir()
    return ["read", str(good_npz(d)), "-o", str(d / "out.npz")]


@case("read: output extension", "must end in .npz", group="outputs")
def _(d):
    return ["read", str(good_npz(d)), "-o", str(d / "out.ply")]


@case("complete: sample 0 is the input", "overwrite an input", group="outputs")
def _(d):
    scan = good_npz(d, "a_s0.npz")
    return ["complete", str(scan), "-o", str(d / "a.npz")]


@case("complete: sample 1 is the poses file", "overwrite an input", group="outputs")
def _(d):
    scan = good_npz(d)
    (d / "p_s1.npz").write_text(json.dumps({"scans": [{"file": scan.name, "pose": EYE}]}))
    return ["complete", str(scan), "--poses", str(d / "p_s1.npz"), "--samples", "2", "-o", str(d / "p.npz")]


@case("complete: output under a file", "not a folder", group="outputs")
def _(d):
    (d / "file").write_text("x")
    return ["complete", str(good_npz(d)), "-o", str(d / "file" / "out.npz")]


@case("complete: output extension", "must end in", group="outputs")
def _(d):
    return ["complete", str(good_npz(d)), "-o", str(d / "out.stl")]


# --- flags --------------------------------------------------------------------------------------------------------

def flag_case(name: str, flags: list[str], expect: str = "") -> None:
    @case(f"complete: {name}", expect, "flags")
    def _(d, flags=flags):
        return complete_cmd(good_npz(d), d, *flags)


flag_case("--t1 -1", ["--t1", "-1"], "--t1")
flag_case("--t2 -5", ["--t2", "-5"], "--t2")
flag_case("--t1 abc", ["--t1", "abc"], "--t1")
flag_case("--t1 1.5", ["--t1", "1.5"], "--t1")
flag_case("--device tpu", ["--device", "tpu"], "unknown device")
flag_case("--device cuda:x", ["--device", "cuda:x"], "unknown device")
flag_case("--samples 0", ["--samples", "0"], "samples")
flag_case("--samples -2", ["--samples", "-2"], "samples")
flag_case("--max-faces 10", ["--max-faces", "10"], "argument --max-faces: must be 0")
flag_case("--region 2 numbers", ["--region", "1,2"], "6 or 7")
flag_case("--region words", ["--region", "a,b,c,d,e,f"], "numbers")
flag_case("--region zero size", ["--region", "3,3,1,0,6,4"], "positive")
flag_case("--region nan", ["--region", "nan,3,1,6,6,4"], "non-finite")
flag_case("--region inf size", ["--region", "3,3,1,inf,6,4"], "")
flag_case("--region far away", ["--region", "5000,5000,0,6,6,4"], "no input points inside the region")
flag_case("--region too large", ["--region", "3,3,1,100000,100000,8"], "GiB")
flag_case("--precision fp8", ["--precision", "fp8"], "precision")
flag_case("--format bogus", ["--format", "bogus"], "unknown format")
flag_case("--stage medium", ["--stage", "medium"], "stage")
flag_case("--progress xml", ["--progress", "xml"], "progress")
flag_case("--weights missing", ["--weights", "/nonexistent/coarse.pt"], "")
flag_case("--fine-weights missing", ["--stage", "full", "--fine-weights", "/nonexistent/fine.pt"], "")


@case("complete: --weights is random bytes", "", group="flags")
def _(d):
    (d / "w.pt").write_bytes(RANDOM)
    return complete_cmd(good_npz(d), d, "--weights", d / "w.pt")


special_file_cases("flags", lambda d, path: complete_cmd(good_npz(d), d, "--weights", path), [
    ("complete: --weights is a folder", "", "w.pt", "folder"),
])


# --- degenerate scans --------------------------------------------------------------------------------------------

def degenerate(name: str, points: np.ndarray, expect: str) -> None:
    @case(f"complete: {name}", expect, "degenerate scans")
    def _(d, points=points):
        np.savez(d / "scan.npz", points=points)
        return complete_cmd(d / "scan.npz", d)


degenerate("one point", np.array([[1.0, 2.0, 3.0]]), "too few input points")
degenerate("50k identical points", np.tile([[1.0, 2.0, 3.0]], (50_000, 1)), "all at the same spot")
degenerate("five points", np.random.default_rng(1).uniform(0, 5, (5, 3)), "too few input points")
degenerate("a vertical line of 3 cells", np.c_[np.zeros(300), np.zeros(300), np.linspace(0, 0.5, 300)],
           "too few input points")
degenerate("UTM point pair", np.array([[500_000.0, 5_000_000.0, 10.0], [500_000.0, 5_000_000.0, 10.1]]),
           "too few input points")


# --- further classes, each in a module of its own that appends to CASES ---------------------------------------
# (tests/hostile/__init__.py imports them: reads.py, silently wrong reads and georeferenced precision; cli.py,
# flags, outputs, hangs, late checks, disk full, signals)
