"""Driving sequences as input: a KITTI odometry / SemanticKITTI sequence, an Argoverse 2 sensor log, or a
folder of nuScenes sweeps, read as the frames a user picks and accumulated with the sequence's own poses.

Every layout is turned into (scan file, sensor->world pose) pairs and handed to `read_scans`, so a sequence
gives exactly what the same files give with an equivalent poses JSON (`hgca poses` writes that JSON).
Layouts:
- KITTI: `velodyne/NNNNNN.bin`, `poses.txt` (one 3x4 camera-0 pose per line, line i for frame i) and
  `calib.txt` (`Tr:` velodyne -> camera 0); scan i's pose is Tr^-1 . P_i . Tr. `labels/` is ignored.
- AV2: `sensors/lidar/<timestamp_ns>.feather` with `city_SE3_egovehicle.feather` (see `hgca_core.io.av2`).
- nuScenes: `*.pcd.bin` sweeps, with poses from `poses.json` in the folder (or `--poses`); a single sweep
  needs none (it stays in its sensor frame).
- files: any other folder of scan files of one known format (ply, pcd, las, ...), in natural name order
  (scan2 before scan10), with poses from `poses.json` beside them (`hgca poses --estimate` writes it).
A poses JSON given explicitly (`--poses`) replaces the layout's own poses for any layout.
"""
from __future__ import annotations

import glob
import importlib
import os
import re
from dataclasses import dataclass
from typing import Callable

import numpy as np

from hgca_core.errors import InputError
from hgca_core.io import av2
from hgca_core.io.poses import load_poses, match_poses, validate_pose
from hgca_core.io.scan import Scan

DEFAULT_FRAMES = 5  # the paper accumulates 5 scans
KITTI_NAME = re.compile(r"^(\d+)\.bin$")


@dataclass(frozen=True)
class Sequence:
    """A sequence's frames in time order: scan files, float64 sensor->world poses, reader format."""

    layout: str
    root: str
    files: tuple[str, ...]  # each frame's scan file; a container's frames are named "CONTAINER#N"
    poses: tuple[np.ndarray, ...] | None  # None: no poses needed (a single sweep) or given later
    fmt: str
    reader: Callable[[int], Scan] | None = None  # a container's frame i in its sensor frame (files: read_scan)

    def __len__(self) -> int:
        return len(self.files)

    def read_frame(self, i: int) -> Scan:
        """Frame i as its reader gives it (sensor frame for posed layouts), with the usual checks."""
        if self.reader is not None:
            return self.reader(i)
        from hgca_core.io.read import read_scan

        return read_scan(self.files[i], self.fmt)

    def accumulate(self, files: list[str], poses: list[np.ndarray] | None) -> Scan:
        """The frames named `files` (from `select`) with their `poses` in one world frame: scan files through
        `read_scans` (its repeat and pose checks), a container's frames through their reader."""
        from hgca_core.io.read import accumulate, read_scans

        if self.reader is None:
            return read_scans(files, poses=poses, fmt=self.fmt)
        index = {name: i for i, name in enumerate(self.files)}
        return accumulate([self.read_frame(index[f]) for f in files], files, poses)


# Files and folders that hold a whole sequence in one container: layout -> "module:opener", each opener
# `open(path, topic) -> Sequence` (the module is imported only when such an input is given).
CONTAINERS: dict[str, str] = {
    "rosbag": "hgca_core.io.rosbag:open_bag",
    "e57": "hgca_core.io.e57:open_e57",
}
CONTAINER_EXTENSIONS: tuple[tuple[str, str], ...] = ((".bag", "rosbag"), (".mcap", "rosbag"), (".db3", "rosbag"),
                                                     (".e57", "e57"))


def container_layout(path: str) -> str | None:
    """The container layout of a file (ROS 1/2 bag, E57) or of a ROS 2 bag folder, or None."""
    if os.path.isdir(path):
        return "rosbag" if os.path.isfile(os.path.join(path, "metadata.yaml")) else None
    name = os.path.basename(path).lower()
    return next((layout for ext, layout in CONTAINER_EXTENSIONS if name.endswith(ext)), None)


def _open_container(layout: str, path: str, topic: str | None) -> Sequence:
    module, _, name = CONTAINERS[layout].partition(":")
    return getattr(importlib.import_module(module), name)(path, topic)


def parse_frames(spec: str | None, count: int, what: str = "sequence") -> list[int]:
    """Frame indices of `START:STOP[:STEP]` (Python slice rules on the frames in time order); by default the
    5 frames around the middle. An empty selection is an error, not a silent no-op."""
    if count == 0:
        raise InputError("sequence has no frames", what)
    if spec is None:
        start = max(0, (count - DEFAULT_FRAMES) // 2)
        return list(range(start, min(count, start + DEFAULT_FRAMES)))
    parts = spec.split(":")
    try:
        if len(parts) not in (2, 3):
            raise ValueError
        values = [int(p) if p.strip() else None for p in parts]
    except ValueError:
        raise InputError(f"--frames must be START:STOP[:STEP] (integers), got {spec!r}") from None
    if len(values) == 3 and values[2] == 0:
        raise InputError("--frames step must not be 0")
    chosen = list(range(count))[slice(*values)]
    if not chosen:
        raise InputError(f"--frames {spec} selects no frame of the {count} in the sequence", what)
    return chosen


def detect_layout(root: str) -> str:
    """kitti, av2 or nuscenes, from the folder's contents; anything else is an InputError listing the layouts."""
    if os.path.isdir(os.path.join(root, "velodyne")):
        return "kitti"
    if os.path.isdir(os.path.join(root, "sensors", "lidar")):
        return "av2"
    if glob.glob(os.path.join(glob.escape(root), "*.pcd.bin")):
        return "nuscenes"
    if _scan_files(root):
        return "files"
    raise InputError("folder is not a known sequence layout: expected velodyne/ (KITTI), sensors/lidar/ "
                     "(Argoverse 2), *.pcd.bin sweeps (nuScenes) or scan files of one format", root)


def natural_key(path: str) -> list:
    """Sort key of a file name in natural order: scan2 before scan10."""
    return [(0, int(t), "") if t.isdigit() else (1, 0, t.lower()) for t in re.split(r"(\d+)", os.path.basename(path))]


def _scan_files(root: str) -> dict[str, list[str]]:
    """The folder's scan files by format (from the extension), each list in natural order."""
    from hgca_core.io.formats import format_from_extension

    found: dict[str, list[str]] = {}
    for name in os.listdir(root):
        path = os.path.join(root, name)
        fmt = format_from_extension(name)
        if fmt is not None and not name.startswith(".") and os.path.isfile(path):
            found.setdefault(fmt, []).append(path)
    return {fmt: sorted(paths, key=natural_key) for fmt, paths in found.items()}


def _files_format(root: str) -> str:
    """The one scan format of a "files" folder; several is an InputError naming them (which frames belong
    together is then unknown)."""
    found = _scan_files(root)
    if len(found) != 1:
        kinds = ", ".join(f"{len(v)} {k}" for k, v in sorted(found.items()))
        raise InputError(f"folder holds scan files of several formats ({kinds}): a sequence folder holds one "
                         "format; move the others out or give the files themselves", root)
    return next(iter(found))


def _kitti_matrix(values: list[str], what: str, path: str) -> np.ndarray:
    try:
        nums = [float(v) for v in values]
    except ValueError:
        raise InputError(f"{what}: not 12 numbers", path) from None
    if len(nums) != 12:
        raise InputError(f"{what}: expected 12 numbers (a 3x4 matrix), got {len(nums)}", path)
    m = np.eye(4)
    m[:3] = np.asarray(nums, dtype=np.float64).reshape(3, 4)
    return m


def kitti_calibration(path: str) -> np.ndarray:
    """Tr (velodyne -> camera 0) from calib.txt."""
    if not os.path.isfile(path):
        raise InputError("KITTI sequence has no calib.txt (needed for Tr, velodyne -> camera)", path)
    found = []
    with open(path, "r", encoding="utf-8-sig", errors="replace") as f:
        for line in f:
            key, _, rest = line.partition(":")
            if key.strip() == "Tr":
                found.append(validate_pose(_kitti_matrix(rest.split(), "Tr", path), "calib.txt Tr", path))
    if not found:
        raise InputError("calib.txt has no 'Tr:' line (velodyne -> camera 0 transform)", path)
    if len(found) > 1 and not all(np.array_equal(found[0], m) for m in found[1:]):
        raise InputError(f"calib.txt has {len(found)} different 'Tr:' lines: which one holds is unknown", path)
    return found[0]


def kitti_poses(path: str) -> list[np.ndarray]:
    """Camera-0 poses P_i, one 3x4 per line."""
    if not os.path.isfile(path):
        raise InputError("KITTI sequence has no poses.txt (give a poses JSON with --poses instead)", path)
    with open(path, "r", encoding="utf-8-sig", errors="replace") as f:
        lines = [ln.split() for ln in f]
    while lines and not lines[-1]:
        lines.pop()
    blank = [i + 1 for i, v in enumerate(lines) if not v]
    if blank:
        raise InputError(f"poses.txt line {blank[0]} is blank: line i holds frame i's pose, so a blank line "
                         "would give every later frame the next frame's pose", path)
    return [validate_pose(_kitti_matrix(v, f"line {i + 1}", path), f"line {i + 1}", path)
            for i, v in enumerate(lines)]


def _open_kitti(root: str) -> Sequence:
    files = _files_only(root, "kitti")
    if not files:
        raise InputError("KITTI velodyne/ folder holds no NNNNNN.bin sweeps", os.path.join(root, "velodyne"))
    tr = kitti_calibration(os.path.join(root, "calib.txt"))
    poses_path = os.path.join(root, "poses.txt")
    cams = kitti_poses(poses_path)
    numbers = [int(os.path.basename(f)[:-4]) for f in files]
    missing = [os.path.basename(f) for f, n in zip(files, numbers) if n >= len(cams)]
    if missing:
        raise InputError(f"no pose for {len(missing)} sweep(s) ({', '.join(missing[:3])}"
                         f"{', ...' if len(missing) > 3 else ''}): poses.txt has {len(cams)} lines", poses_path)
    tr_inv = np.linalg.inv(tr)
    return Sequence("kitti", root, files, tuple(tr_inv @ cams[n] @ tr for n in numbers), "kitti")


def _open_av2(root: str) -> Sequence:
    files = _files_only(root, "av2")
    if not files:
        raise InputError("AV2 sensors/lidar/ folder holds no <timestamp_ns>.feather sweeps",
                         os.path.join(root, "sensors", "lidar"))
    return Sequence("av2", root, files, tuple(av2.ego_poses(root, [av2.sweep_timestamp(f) for f in files])), "av2")


def _open_nuscenes(root: str, layout: str = "nuscenes", fmt: str = "nuscenes") -> Sequence:
    """Sweeps with poses from the poses.json beside them (nuScenes, and the "files" layout)."""
    files = _files_only(root, layout)
    own = os.path.join(root, "poses.json")
    poses = None
    if os.path.lexists(own) and not os.path.isfile(own):   # a folder, a dangling link, a device: say so
        kind = "a folder" if os.path.isdir(own) else "not a regular file"
        what = "nuScenes folder" if layout == "nuscenes" else "scan folder"
        raise InputError(f"the {what}'s poses.json is {kind}: it must be the poses JSON file (or give "
                         "--poses)", own)
    if os.path.isfile(own):
        poses = tuple(e.pose for e in match_poses(load_poses(own), list(files), own))
    return Sequence(layout, root, tuple(files), poses, fmt)


def open_sequence(root: str | os.PathLike, poses: str | os.PathLike | None = None,
                  topic: str | None = None, own_poses: bool = True) -> Sequence:
    """The sequence in folder `root` (or container file: a ROS bag, an E57); `poses` (our JSON) replaces the
    layout's own poses when given; `topic` picks a bag's point cloud topic; `own_poses=False` reads none (the
    frames only, for `hgca poses --estimate`)."""
    root = os.fspath(root)
    container = container_layout(root) if os.path.exists(root) else None
    if container is not None:
        seq = _open_container(container, root, topic)
        if not own_poses:
            return Sequence(seq.layout, seq.root, seq.files, None, seq.fmt, seq.reader)
        if poses is None:
            return seq
        pose_path = os.fspath(poses)
        entries = match_poses(load_poses(pose_path), list(seq.files), pose_path)
        return Sequence(seq.layout, seq.root, seq.files, tuple(e.pose for e in entries), seq.fmt, seq.reader)
    if topic is not None:
        raise InputError("--topic applies to a ROS bag (.bag, .mcap, .db3 or a ROS 2 bag folder)", root)
    if not os.path.isdir(root):
        raise InputError("sequence folder not found", root)
    layout = detect_layout(root)
    fmt = _files_format(root) if layout == "files" else _FORMAT[layout]
    if not own_poses:
        return Sequence(layout, root, _files_only(root, layout), None, fmt)
    if poses is not None:
        files = _files_only(root, layout)
        pose_path = os.fspath(poses)
        entries = match_poses(load_poses(pose_path), list(files), pose_path)
        return Sequence(layout, root, files, tuple(e.pose for e in entries), fmt)
    if layout == "files":
        return _open_nuscenes(root, "files", fmt)
    return {"kitti": _open_kitti, "av2": _open_av2, "nuscenes": _open_nuscenes}[layout](root)


_FORMAT = {"kitti": "kitti", "av2": "av2", "nuscenes": "nuscenes"}


def _files_only(root: str, layout: str) -> tuple[str, ...]:
    """The layout's scan files in time order, without reading any pose table."""
    if layout == "kitti":
        velodyne = os.path.join(root, "velodyne")
        named = sorted((int(n[:-4]), n) for n in os.listdir(velodyne) if KITTI_NAME.match(n))
        for (a, first), (b, second) in zip(named, named[1:]):
            if a == b:
                raise InputError(f"{first} and {second} are both frame {a}: which sweep is frame {a} is unknown",
                                 velodyne)
        return tuple(os.path.join(velodyne, n) for _, n in named)
    if layout == "av2":
        lidar = os.path.join(root, "sensors", "lidar")
        return tuple(sorted((os.path.join(lidar, n) for n in os.listdir(lidar) if n.endswith(".feather")),
                            key=av2.sweep_timestamp))
    if layout == "files":
        return tuple(_scan_files(root)[_files_format(root)])
    return tuple(sorted(glob.glob(os.path.join(glob.escape(root), "*.pcd.bin"))))


def select(seq: Sequence, frames: str | None) -> tuple[list[str], list[np.ndarray] | None]:
    """The chosen frames' files and poses; several frames without poses is an error (they would not line up)."""
    idx = parse_frames(frames, len(seq), seq.root)
    files = [seq.files[i] for i in idx]
    if seq.poses is None:
        if len(idx) > 1:
            raise InputError(f"{len(idx)} {seq.layout} sweeps selected but the folder has no poses.json: give "
                             "their poses with --poses, estimate them (hgca poses --estimate FOLDER -o "
                             "FOLDER/poses.json), or select one sweep with --frames", seq.root)
        return files, None
    return files, [seq.poses[i] for i in idx]


def read_sequence(root: str | os.PathLike, frames: str | None = None, poses: str | os.PathLike | None = None,
                  calibration: str | os.PathLike | None = None, topic: str | None = None) -> Scan:
    """The chosen frames of a sequence accumulated in its world frame (float64), via `read_scans`.

    `calibration` (AV2 only) is an egovehicle_SE3_sensor table to take the lidar origins from, for a log
    that lacks its own (the av2-api test logs): without one such a log's origins are the ego origins."""
    seq = open_sequence(root, poses, topic)
    files, mats = select(seq, frames)
    scan = seq.accumulate(files, mats)
    if calibration is not None:
        if seq.layout != "av2":
            raise InputError(f"a lidar calibration applies to Argoverse 2 logs, not to a {seq.layout} sequence",
                             os.fspath(calibration))
        local = av2.lidar_origins(os.fspath(calibration))
        scan.origins = np.concatenate([local @ m[:3, :3].T + m[:3, 3] for m in mats])
        scan.attributes["origin_index"] = (scan.attributes["scan_index"].astype(np.int64) * len(local)
                                           + scan.attributes["laser_number"] // 32).astype(np.uint16)
    return scan


def is_sequence(inputs: list[str]) -> bool:
    """True when the inputs are one folder (a sequence) or one container file (a ROS bag, an E57); a folder
    or container among other inputs is an error."""
    dirs = [p for p in inputs if os.path.isdir(p) or container_layout(p) is not None]
    if dirs and len(inputs) > 1:
        raise InputError(f"give one sequence folder, bag or E57, or scan files, not both ({len(dirs)} "
                         f"sequence(s) among {len(inputs)} inputs)", dirs[0])
    return bool(dirs)


def read_inputs(inputs: list[str], poses: str | None = None, fmt: str | None = None,
                frames: str | None = None, topic: str | None = None) -> Scan:
    """What `hgca read` and `hgca complete` read: one sequence folder, bag or E57 (with --frames, --topic) or
    scan files."""
    from hgca_core.io.read import read_scans

    if is_sequence(inputs):
        if fmt is not None:
            raise InputError("--format applies to scan files, not to a sequence folder", inputs[0])
        return read_sequence(inputs[0], frames, poses, topic=topic)
    if topic is not None:
        raise InputError("--topic applies to a ROS bag (.bag, .mcap, .db3 or a ROS 2 bag folder)", inputs[0])
    if frames is not None:
        raise InputError("--frames needs a sequence folder (KITTI, Argoverse 2 or nuScenes), not scan files")
    return read_scans(inputs, poses=poses, fmt=fmt)


def poses_document(seq: Sequence, frames: str | None, out_dir: str) -> dict:
    """Our poses JSON for the chosen frames; files relative to the JSON's folder when they can be."""
    idx = list(range(len(seq))) if frames is None else parse_frames(frames, len(seq), seq.root)
    if seq.poses is None:
        if len(idx) > 1:
            raise InputError(f"the {seq.layout} folder has no poses.json: its {len(idx)} sweeps have no poses "
                             "to write (--estimate estimates them from the scans)", seq.root)
        mats = [np.eye(4)]
    else:
        mats = [seq.poses[i] for i in idx]
    scans = []
    for i, m in zip(idx, mats):
        path = os.path.abspath(seq.files[i])
        try:
            name = os.path.relpath(path, os.path.abspath(out_dir))
        except ValueError:  # another drive (Windows)
            name = path
        scans.append({"file": name, "pose": np.asarray(m, dtype=np.float64).tolist()})
    return {"layout": seq.layout, "sequence": os.path.abspath(seq.root), "scans": scans}
