"""ROS 1 `.bag`, ROS 2 bag folders (sqlite3 `.db3` or MCAP storage) and bare `.db3` / `.mcap` files as a sequence.

A bag records a drive: sensor_msgs/PointCloud2 sweeps on one topic, each in its sensor frame, and usually /tf
and /tf_static placing that frame in a fixed frame (map, odom, world). `open_bag` lists the chosen topic's
clouds as frames (`BAG#N`, in header-stamp order, else receive-time order) with sensor->fixed-frame poses from
tf (`hgca_core.io.rosbag_tf`); a bag without usable tf gets its poses from LiDAR odometry over the frames that are
read. Decoding is numpy only (`hgca_core.io.rosbag_cloud`); the `rosbags` library (the recordings extra) reads
the containers, so no ROS installation is needed.
"""
from __future__ import annotations

import contextlib
import os
import threading
from collections.abc import Sequence as SequenceABC
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from hgca_core.errors import InputError
from hgca_core.io.paths import check_readable
from hgca_core.io.rosbag_cloud import decode_cloud
from hgca_core.io.rosbag_tf import TfTree, frame_name
from hgca_core.io.scan import Scan, finalize
from hgca_core.io.sequence import Sequence

CLOUD = "sensor_msgs/msg/PointCloud2"
TF_TOPICS = {"/tf": False, "/tf_static": True}  # topic -> static
TF_TYPES = ("tf2_msgs/msg/TFMessage", "tf/msg/tfMessage")  # tf2's, and ROS 1's older tf (the same fields)
EXTRA = "reading ROS bags needs the recordings extra (pip install 'hgca[recordings]')"


def _anyreader(path: str) -> Any:
    """An AnyReader for the bag (not opened), with ROS 2 Humble types for bags that embed no definitions."""
    try:
        from rosbags.highlevel import AnyReader
        from rosbags.typesys import Stores, get_typestore
    except ImportError:
        raise InputError(EXTRA, path) from None
    store = get_typestore(Stores.ROS1_NOETIC if path.lower().endswith(".bag") else Stores.ROS2_HUMBLE)
    return AnyReader([Path(path)], default_typestore=store)


def _bad(exc: Exception, path: str, topic: str | None) -> InputError:
    """A library failure as one line naming the bag and the topic."""
    if isinstance(exc, InputError):
        return exc
    if isinstance(exc, MemoryError):
        return InputError("bag is too large to read into memory", path)
    about = f" (topic {topic})" if topic else ""
    text = str(exc).strip().splitlines()[0] if str(exc).strip() else ""
    if type(exc).__name__ not in ("AnyReaderError", "ReaderError") or not text:
        text = f"{type(exc).__name__}: {text}".rstrip(": ")
    hint = ("; an unfinished ROS 1 recording can be repaired with `rosbag reindex`"
            if path.lower().endswith(".bag") and "index" in text.lower() else "")
    return InputError(f"corrupt or truncated bag{about}: {text}{hint}", path)


def _clean(path: str | os.PathLike) -> str:
    """The bag's path as given, less trailing separators: a bag folder given as "drive/" names its frames
    "drive#N"."""
    path = os.fspath(path)
    return path.rstrip("/\\") or path


def _stamp_ns(msg: Any) -> int:
    return int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec)


@dataclass(frozen=True)
class Frame:
    """Where one cloud is in the bag: receive time (ns), its place among messages of that time, stamp, frame."""

    received: int
    nth: int
    stamp: int
    frame_id: str


@dataclass(frozen=True)
class BagIndex:
    """What one pass over a bag finds: every topic (type, count), the cloud topic's frames, the tf tree."""

    path: str
    topics: dict[str, tuple[str, int]]
    topic: str | None
    frames: tuple[Frame, ...]
    tf: TfTree | None


def cloud_topics(topics: dict[str, tuple[str, int]]) -> list[str]:
    return sorted(t for t, (kind, _) in topics.items() if kind == CLOUD)


def _choose_topic(path: str, topics: dict[str, tuple[str, int]], topic: str | None, required: bool) -> str | None:
    clouds = cloud_topics(topics)
    listing = ", ".join(f"{t} ({topics[t][1]})" for t in clouds)
    if topic is None:
        if len(clouds) == 1:
            return clouds[0]
        if not required:
            return None
        if not clouds:
            raise InputError("the bag has no sensor_msgs/PointCloud2 topic (topics: "
                             + (", ".join(f"{t} ({k})" for t, (k, _) in sorted(topics.items())) or "none") + ")", path)
        raise InputError(f"--topic is needed: the bag has {len(clouds)} point cloud topics: {listing}", path)
    if topic not in topics:
        raise InputError(f"the bag has no topic {topic} (point cloud topics: {listing or 'none'})", path)
    if topics[topic][0] != CLOUD:
        raise InputError(f"topic {topic} holds {topics[topic][0]} messages, not sensor_msgs/PointCloud2 "
                         f"(point cloud topics: {listing or 'none'})", path)
    if topics[topic][1] == 0:
        raise InputError(f"topic {topic} has no messages", path)
    return topic


def _order(path: str, topic: str, frames: list[Frame]) -> tuple[Frame, ...]:
    """Frames in header-stamp order (receive time when any stamp is zero); stamps going backwards by more
    than the frame interval mean out-of-order clocks, which sorting would silently hide."""
    if not frames:
        raise InputError(f"topic {topic} has no messages", path)
    if any(f.stamp <= 0 for f in frames):
        frames = [Frame(f.received, f.nth, f.received, f.frame_id) for f in frames]
    stamps = np.array([f.stamp for f in frames], dtype=np.int64)
    steps = np.diff(stamps)
    forward = steps[steps > 0]
    interval = int(np.median(forward)) if len(forward) else 0
    back = np.flatnonzero(steps < -interval)
    if len(back):
        k = int(back[0]) + 1
        raise InputError(f"topic {topic}: header stamps go backwards by {-steps[k - 1] / 1e9:.3f} s at message {k} "
                         f"in recording order (frame interval {interval / 1e9:.3f} s): the clocks are out of order", path)
    order = np.argsort(stamps, kind="stable")
    return tuple(frames[i] for i in order)


def _signature(path: str) -> tuple:
    """What changes when the bag does: size and time of the file, or of every file in a bag folder."""
    files = [os.path.join(path, n) for n in sorted(os.listdir(path))] if os.path.isdir(path) else [path]
    return tuple((f, os.stat(f).st_size, os.stat(f).st_mtime_ns) for f in files if os.path.isfile(f))


_LAST: dict[tuple, BagIndex] = {}  # the last index made: `hgca info` lists a bag, then opens it


def index_bag(path: str, topic: str | None, required: bool = True) -> BagIndex:
    """One pass over the bag: topics, the cloud topic's frames in time order and the tf tree."""
    path = os.fspath(path)
    if not os.path.isdir(path):
        check_readable(path, "bag")  # missing, empty, unreadable: said as such, not as a corrupt bag
    elif not os.path.isfile(os.path.join(path, "metadata.yaml")):
        raise InputError("folder is not a ROS 2 bag: it has no metadata.yaml", path)
    key = (path, topic, _signature(path))
    if key in _LAST:
        return _LAST[key]
    index = _index(path, topic, required)
    if index.topic is not None:
        _LAST.clear()
        _LAST[key] = index
    return index


def _index(path: str, topic: str | None, required: bool) -> BagIndex:
    chosen = topic
    try:
        with _anyreader(path) as reader:
            topics = {t: (info.msgtype or "?", int(info.msgcount)) for t, info in reader.topics.items()}
            chosen = _choose_topic(path, topics, topic, required)
            tf = TfTree(path)
            wanted = [c for c in reader.connections if c.topic == chosen or c.topic in TF_TOPICS]
            frames: list[Frame] = []
            last, nth = None, 0
            for conn, received, raw in reader.messages(connections=wanted) if wanted else ():
                if conn.topic in TF_TOPICS:
                    if conn.msgtype in TF_TYPES:
                        tf.add(reader.deserialize(raw, conn.msgtype), TF_TOPICS[conn.topic])
                    continue
                nth = nth + 1 if received == last else 0
                last = received
                msg = reader.deserialize(raw, conn.msgtype)
                frames.append(Frame(received, nth, _stamp_ns(msg), frame_name(msg.header.frame_id)))
    except Exception as exc:  # noqa: BLE001 - any library failure is a bad bag, said in one line
        raise _bad(exc, path, chosen) from None
    ordered = _order(path, chosen, frames) if chosen is not None else ()
    return BagIndex(path, topics, chosen, ordered, tf if tf.edges else None)


class OpenBag:
    """One reader kept open between frames: reopening a bag reads its whole index again (0.1 s for a few
    hundred clouds, more for a long drive), which reading frame after frame would pay each time."""

    def __init__(self, path: str) -> None:
        self.path = path
        self._reader: Any = None
        self._lock = threading.Lock()

    def message(self, topic: str, frame: Frame) -> Any:
        """The deserialised message of `frame`, or None when the bag no longer holds it."""
        with self._lock:
            if self._reader is None:
                reader = _anyreader(self.path)
                reader.open()
                self._reader = reader
            try:
                conns = [c for c in self._reader.connections if c.topic == topic]
                found = [(c, raw) for c, _, raw in
                         self._reader.messages(conns, start=frame.received, stop=frame.received + 1)]
                if len(found) <= frame.nth:
                    return None
                conn, raw = found[frame.nth]
                return self._reader.deserialize(raw, conn.msgtype)
            except BaseException:
                self.close()
                raise

    def close(self) -> None:
        reader, self._reader = self._reader, None
        if reader is not None:
            with contextlib.suppress(Exception):
                reader.close()

    def __del__(self) -> None:
        self.close()


def read_cloud(bag: OpenBag, topic: str, frame: Frame, index: int) -> Scan:
    """Frame `index` of the topic: its PointCloud2 decoded in the sensor frame, with the finite policy applied."""
    path = bag.path
    where = f"{path}#{index}"
    try:
        msg = bag.message(topic, frame)
    except Exception as exc:  # noqa: BLE001
        raise _bad(exc, path, topic) from None
    if msg is None:
        raise InputError(f"topic {topic}: frame {index} is no longer in the bag (changed since it was opened?)", path)
    try:
        return finalize(decode_cloud(msg, frame.stamp, where), where)
    except InputError as exc:
        text = str(exc)[len(where) + 2:] if str(exc).startswith(f"{where}: ") else str(exc)
        raise InputError(f"topic {topic}, frame {index}: {text}", path) from None


class TfPoses(SequenceABC):
    """Each frame's sensor->fixed-frame pose from tf; a frame tf does not cover (recorded before tf starts or
    after it stops) is refused when its pose is asked for, so the frames tf does cover stay usable."""

    def __init__(self, path: str, topic: str, mats: list[np.ndarray], problems: list[str | None]) -> None:
        self._path, self._topic, self._mats, self.problems = path, topic, mats, problems

    def __len__(self) -> int:
        return len(self._mats)

    def __getitem__(self, i: Any) -> Any:
        i = range(len(self._mats))[i]
        if self.problems[i]:
            raise InputError(f"topic {self._topic}, frame {i}: {self.problems[i]}", self._path)
        return self._mats[i]


def tf_poses(index: BagIndex) -> TfPoses | None:
    """The frames' poses from tf, or None when tf does not place the sensor frames."""
    if index.tf is None or index.topic is None:
        return None
    names = sorted({f.frame_id for f in index.frames})
    chains = {n: index.tf.chain(n) for n in names}
    if any(len(c) < 2 for c in chains.values()):
        return None
    roots = {c[-1] for c in chains.values()}
    if len(roots) > 1:
        raise InputError(f"the clouds' frames {', '.join(names)} belong to different tf trees "
                         f"({', '.join(sorted(roots))})", index.path)
    mats: list[np.ndarray] = [np.eye(4)] * len(index.frames)
    problems: list[str | None] = [None] * len(index.frames)
    for n in names:
        rows = [i for i, f in enumerate(index.frames) if f.frame_id == n]
        found, why = index.tf.poses(n, np.array([index.frames[i].stamp for i in rows]))
        for i, m, w in zip(rows, found, why):
            mats[i], problems[i] = m, w
    return TfPoses(index.path, index.topic, mats, problems)


class _LazyScans(SequenceABC):
    """The frames odometry runs over, read when it gets to each: a drive's thousands of sweeps would not fit
    in memory at once."""

    def __init__(self, read: Any, idx: list[int]) -> None:
        self._read, self._idx = read, idx

    def __len__(self) -> int:
        return len(self._idx)

    def __getitem__(self, k: Any) -> Any:
        if isinstance(k, slice):
            return [self._read(i) for i in self._idx[k]]
        return self._read(self._idx[k])


class OdometryPoses(SequenceABC):
    """Poses from LiDAR odometry, computed only when asked for and only over the frames between the first
    and the last one asked for (a bag can hold thousands of sweeps; a completion reads a handful). The world
    frame is the first asked-for frame's sensor frame; a later request outside the computed span recomputes
    the whole span so that every pose handed out stays in that one frame."""

    def __init__(self, seq_reader: Any, count: int, stamps: list[int], names: list[str]) -> None:
        self._read, self._count, self._stamps, self._names = seq_reader, count, stamps, names
        self._span: tuple[int, int] | None = None
        self._poses: list[np.ndarray] = []
        self._anchor: int | None = None  # the first frame asked for: its sensor frame is the world frame

    def __len__(self) -> int:
        return self._count

    def __iter__(self) -> Iterator[np.ndarray]:
        return (self[i] for i in range(self._count))

    def _compute(self, lo: int, hi: int) -> None:
        from hgca_core.io.odometry import estimate_poses

        idx = list(range(lo, hi + 1))
        if lo == hi:  # one frame alone needs no odometry: it stays in its sensor frame
            self._anchor = lo if self._anchor is None else self._anchor
            self._poses, self._span = [np.eye(4)], (lo, hi)
            return
        scans: Any = _LazyScans(self._read, idx)
        found = estimate_poses(scans, [self._stamps[i] / 1e9 for i in idx], [self._names[i] for i in idx])
        if self._anchor is None:
            self._anchor = lo
        shift = np.linalg.inv(found[self._anchor - lo])  # the anchor at identity, whatever span was run
        self._poses = [shift @ np.asarray(m, dtype=np.float64) for m in found]
        self._span = (lo, hi)

    def __getitem__(self, i: int) -> np.ndarray:  # type: ignore[override]
        i = range(self._count)[i]
        if self._span is None or not self._span[0] <= i <= self._span[1]:
            lo, hi = (i, i) if self._span is None else (min(i, self._span[0]), max(i, self._span[1]))
            if self._span is not None:  # grow ahead, so frames asked one by one cost O(n) reads, not O(n^2)
                size = hi - lo + 1
                hi = min(self._count - 1, hi + size) if i > self._span[1] else hi
                lo = max(0, lo - size) if i < self._span[0] else lo
            self._compute(lo, hi)
        return self._poses[i - self._span[0]]  # type: ignore[index]


def open_bag(path: str | os.PathLike, topic: str | None = None) -> Sequence:
    """The bag's point cloud topic as a sequence (layout "rosbag"): frames `BAG#N` in time order, read with
    `read_frame`, posed by tf when it places the sensor frame, else by LiDAR odometry."""
    path = _clean(path)
    index = index_bag(path, topic)
    chosen = index.topic
    assert chosen is not None
    frames = index.frames
    names = tuple(f"{path}#{i}" for i in range(len(frames)))

    bag = OpenBag(path)

    def reader(i: int) -> Scan:
        return read_cloud(bag, chosen, frames[i], i)

    poses: Any = tf_poses(index)
    if poses is None:
        poses = OdometryPoses(reader, len(frames), [f.stamp for f in frames], list(names))
    return Sequence("rosbag", path, names, poses, "rosbag", reader)


def describe_bag(path: str, topic: str | None) -> dict[str, Any]:
    """What `hgca info BAG` lists: each topic with its type and count; for the cloud topic (the one given, else
    the only one) its frames, time span and whether tf gives the poses."""
    path = _clean(path)
    index = index_bag(path, topic, required=False)
    out: dict[str, Any] = {"topics": [{"topic": t, "type": k, "messages": n} for t, (k, n) in
                                      sorted(index.topics.items())], "cloud": None}
    if index.topic is not None:
        stamps = [f.stamp for f in index.frames]
        try:
            frames = sorted({f.frame_id for f in index.frames})
            posed = tf_poses(index)
            if posed is not None:
                why = f"from tf ({', '.join(frames)} in {index.tf.chain(frames[0])[-1]})"  # type: ignore[union-attr]
                uncovered = sum(1 for p in posed.problems if p)
                why += f"; {uncovered} frame(s) outside tf's time span have none" if uncovered else ""
            else:
                why = f"LiDAR odometry (tf does not place {', '.join(frames)})"
        except InputError as exc:
            why = f"tf unusable: {str(exc)[len(path) + 2:]}"
        out["cloud"] = {"topic": index.topic, "frames": len(index.frames), "start_s": min(stamps) / 1e9,
                        "end_s": max(stamps) / 1e9, "duration_s": (max(stamps) - min(stamps)) / 1e9,
                        "sensor_frames": sorted({f.frame_id for f in index.frames}), "poses": why}
    return out
