"""Recordings the import reads as one sequence: ROS bags (a cloud topic picked from the bag's own list), E57 scans,
and folders whose frames lack poses (the panel's *Estimate Poses* makes them).

The topic list comes from the core (`hgca info BAG --json`), asked on a thread by the interface (the file
browser redraws with the answer) and synchronously by scripts; the import operators' Topic option shows it.
Whether a folder lacks poses is read from the files it holds, so the import can say why a folder did not read and
what to do about it.
"""
from __future__ import annotations

import json
import os
from pathlib import Path

import bpy

from .. import preferences
from ..jobs import background, core

BAG_EXTENSIONS = (".bag", ".mcap", ".db3")
E57_EXTENSIONS = (".e57",)
CONTAINER_EXTENSIONS = (*BAG_EXTENSIONS, *E57_EXTENSIONS)
# Message types a point cloud topic carries (ROS 1 and ROS 2 spellings)
CLOUD_TYPES = ("sensor_msgs/PointCloud2", "sensor_msgs/msg/PointCloud2")
# Scan files a folder of sweeps may hold (`hgca poses --estimate` reads these in name order)
SCAN_EXTENSIONS = (".ply", ".las", ".laz", ".pcd", ".xyz", ".csv", ".txt", ".npy", ".npz", ".bin", ".feather")
POSES_FILE = "poses.json"
INFO_TIMEOUT_S = 600
NO_TOPIC = "-"   # the topic enum's identifier for "none chosen" (ROS topic names start with "/")


def container_kind(path: Path) -> str | None:
    """"rosbag" for a ROS 1/2 bag file or a ROS 2 bag folder (metadata.yaml), "e57" for an E57 file, else None
    (the core's own routing, `hgca_core.io.sequence.container_layout`)."""
    path = Path(path)
    if path.is_dir():
        return "rosbag" if (path / "metadata.yaml").is_file() else None
    name = path.name.lower()
    if name.endswith(BAG_EXTENSIONS):
        return "rosbag"
    return "e57" if name.endswith(E57_EXTENSIONS) else None


def is_sequence(paths: list[Path]) -> bool:
    """One input read as a sequence of frames: a folder (sequence layout, bag folder) or a bag or E57 file."""
    return len(paths) == 1 and (Path(paths[0]).is_dir() or container_kind(Path(paths[0])) is not None)


def cloud_topics(info: dict) -> list[str]:
    """The point cloud topics an `hgca info BAG --json` document lists, in its order."""
    files = info.get("files")
    entry = files[0] if isinstance(files, list) and files and isinstance(files[0], dict) else {}
    bag = entry.get("bag")
    listed = bag.get("topics") if isinstance(bag, dict) else None
    if not isinstance(listed, list):
        raise core.CoreError("hgca info listed no topics for the bag: install the hgca version that matches the "
                             "add-on")
    topics = []
    for item in listed:
        if isinstance(item, str):
            name, kind = item, None
        elif isinstance(item, dict) and isinstance(item.get("name", item.get("topic")), str):
            name, kind = item.get("name", item.get("topic")), item.get("type", item.get("msgtype"))
        else:
            continue
        if (kind is None or kind in CLOUD_TYPES) and name not in topics:
            topics.append(name)
    return topics


def bag_topics(python: str, bag: Path) -> list[str]:
    """The bag's point cloud topics as the core lists them (a few seconds: the core starts and reads the index;
    with one cloud topic it describes that topic's first frame too, so only that one is read)."""
    proc = core.run_core(python, ["info", str(Path(bag).absolute()), "--frames", "0:1", "--json"],
                         timeout=INFO_TIMEOUT_S)
    try:
        info = json.loads(proc.stdout)   # one indented document
    except ValueError:
        info = None
    if not isinstance(info, dict):
        raise core.CoreError(f"hgca info printed no JSON document: {proc.stdout[-200:]!r}")
    return cloud_topics(info)


def _scan_files(folder: Path) -> list[Path]:
    return sorted(p for p in folder.iterdir() if p.is_file() and p.name.lower().endswith(SCAN_EXTENSIONS)
                  and not p.name.startswith("."))   # hidden files (a writer's temp file) are no sweeps


def missing_poses(folder: Path) -> str:
    """Why the frames of `folder` have no poses ("" when they have them or need none): a folder of scan files or
    a KITTI / Argoverse 2 / nuScenes folder without its pose table. `hgca poses --estimate` fills the gap."""
    folder = Path(folder)
    if not folder.is_dir() or (folder / POSES_FILE).is_file() or (folder / "metadata.yaml").is_file():
        return ""
    if (folder / "velodyne").is_dir():
        return "" if (folder / "poses.txt").is_file() else "the KITTI sequence has no poses.txt"
    if (folder / "sensors" / "lidar").is_dir():
        table = "city_SE3_egovehicle.feather"
        return "" if (folder / table).is_file() else f"the Argoverse 2 log has no {table}"
    try:
        scans = _scan_files(folder)
    except OSError:
        return ""
    if len(scans) < 2:   # a single sweep stays in its sensor frame: nothing to line up
        return ""
    return f"its {len(scans)} scans have no {POSES_FILE}"


def estimated_poses(folder: Path) -> Path | None:
    """The poses.json Estimate Poses wrote into a KITTI or Argoverse 2 folder that lacks its own pose table:
    those layouts read only their own table, so the import hands this one over as `--poses` (a folder of scan
    files and nuScenes sweeps read their poses.json by themselves)."""
    folder = Path(folder)
    own = folder / POSES_FILE
    if not folder.is_dir() or not own.is_file():
        return None
    kitti = (folder / "velodyne").is_dir() and not (folder / "poses.txt").is_file()
    av2 = (folder / "sensors" / "lidar").is_dir() and not (folder / "city_SE3_egovehicle.feather").is_file()
    return own if kitti or av2 else None


def poses_hint(folder: Path) -> str:
    """The sentence the import adds when a folder failed to read for want of poses, else ""."""
    why = missing_poses(folder)
    return (f"{Path(folder).name}: {why}: press Estimate Poses in the hGCA panel (sidebar), then import the "
            "folder again") if why else ""


def leftover_temp_files(target: Path, pid: int) -> list[Path]:
    """Temp files the core (process `pid`) was writing for `target` when it was stopped
    (`hgca_core.io.atomic.temp_prefix`: `.<name>.<pid>.*.tmp`): a cancelled estimate must leave none."""
    prefix = f".{Path(target).name}.{pid}."
    try:
        return [Path(target).parent / n for n in os.listdir(Path(target).parent)
                if n.startswith(prefix) and n.endswith(".tmp")]
    except OSError:
        return []


# -- a bag's point cloud topics, for the import's Topic option ------------------------------------------------

_TOPICS: dict[str, list[str] | str] = {}   # bag path -> its cloud topics, or why they could not be listed
_ITEMS: dict[str, list[tuple[str, str, str]]] = {}   # bag path -> the enum items (Blender needs them kept alive)
_NOT_A_BAG = [(NO_TOPIC, "None", "Topics apply to ROS bags")]


def input_paths(props) -> list[Path]:
    """The paths the operator's properties name: selected files, one file, or a folder opened with no file
    selected (the folder is the input: a sequence, or a ROS 2 bag)."""
    names = [f.name for f in getattr(props, "files", []) if f.name]
    directory = getattr(props, "directory", "")
    if names and directory:
        return [Path(directory) / n for n in names]
    filepath = getattr(props, "filepath", "")
    if filepath and not filepath.endswith(("/", "\\")):
        return [Path(bpy.path.abspath(filepath))]
    if directory or filepath:
        return [Path(bpy.path.abspath(directory or filepath))]
    return []


def bag_of(paths: list[Path]) -> Path | None:
    if len(paths) == 1 and container_kind(paths[0]) == "rosbag":
        return paths[0].absolute()
    return None


def _redraw_all() -> None:
    wm = getattr(bpy.context, "window_manager", None)
    for window in (wm.windows if wm is not None else []):
        for area in window.screen.areas:
            area.tag_redraw()


def list_topics(context: bpy.types.Context, bag: Path) -> list[str] | str | None:
    """The bag's cloud topics (or the core's error), None while they are being listed. The interface asks the
    core on a thread (the file browser redraws with the answer); scripts wait for it."""
    try:
        key = f"{bag}@{bag.stat().st_mtime_ns}"   # a bag written again is listed again
    except OSError:
        key = str(bag)
    if key in _TOPICS:
        return _TOPICS[key]
    python = preferences.core_python(context)

    def work() -> list[str] | str:
        try:
            return bag_topics(python, bag)
        except core.CoreError as exc:
            return str(exc)

    if bpy.app.background or context.window_manager is None or not context.window_manager.windows:
        _TOPICS[key] = work()
        return _TOPICS[key]

    def finish(found: list[str] | str) -> str:
        _TOPICS[key] = found
        _redraw_all()
        return f"{bag.name}: " + (", ".join(found) or "no point cloud topic" if isinstance(found, list) else found)

    task = f"topics:{key}"
    if not background.busy(task):
        background.start(task, f"Listing the topics of {bag.name}", work, finish, undo=False)
    return None


def topic_items(self, context: bpy.types.Context) -> list[tuple[str, str, str]]:
    """The Topic option's choices: the bag's point cloud topics (the only one chosen by itself; with several, a
    "choose" entry first), or an entry saying they are being listed or could not be."""
    bag = bag_of(input_paths(self))
    if bag is None or context is None:
        return _NOT_A_BAG
    found = list_topics(context, bag)
    if found is None:
        items = [(NO_TOPIC, "Listing topics ...", "The core is reading the bag's index")]
    elif isinstance(found, str):
        items = [(NO_TOPIC, "No topics", found)]
    elif not found:
        items = [(NO_TOPIC, "No point cloud topic", "The bag holds no sensor_msgs/PointCloud2 topic")]
    else:
        items = [(t, t, f"Point cloud topic {t}") for t in found]
        if len(found) > 1:
            items.insert(0, (NO_TOPIC, "Choose a topic", f"The bag has {len(found)} point cloud topics"))
    if _ITEMS.get(str(bag)) != items:   # Blender reads the strings after this returns: keep them, and the same
        _ITEMS[str(bag)] = items         # list while they do not change
    return _ITEMS[str(bag)]
