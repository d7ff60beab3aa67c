"""Write small ROS 1 / ROS 2 bags for the tests with the `rosbags` writers and type stores (no ROS needed).

`cloud` packs columns into a sensor_msgs/PointCloud2 with any layout (padding after each field and each row,
big-endian, organised as several rows); `write_bag` writes clouds, /tf and /tf_static to a ROS 1 `.bag` or a
ROS 2 bag folder (sqlite3 or MCAP storage).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import StoragePlugin, Writer as Writer2
from rosbags.rosbag2.enums import CompressionFormat, CompressionMode
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from scipy.spatial.transform import Rotation

DATATYPE = {"i1": 1, "u1": 2, "i2": 3, "u2": 4, "i4": 5, "u4": 6, "f4": 7, "f8": 8}
CLOUD = "sensor_msgs/msg/PointCloud2"
TF = "tf2_msgs/msg/TFMessage"


def store_for(kind: str):
    """ROS 1 Noetic or ROS 2 Humble types; Noetic's store lacks tf2_msgs, registered here as ROS 1 defines it."""
    store = get_typestore(Stores.ROS1_NOETIC if kind == "ros1" else Stores.ROS2_HUMBLE)
    if TF not in store.types:
        store.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms", TF))
    return store


def _header(store, stamp_ns: int, frame_id: str):
    t = store.types["builtin_interfaces/msg/Time"](sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9)
    h = store.types["std_msgs/msg/Header"]
    fields = h.__dataclass_fields__
    return h(seq=0, stamp=t, frame_id=frame_id) if "seq" in fields else h(stamp=t, frame_id=frame_id)


def cloud(store, stamp_ns: int, frame_id: str, columns: dict[str, np.ndarray], big_endian: bool = False,
          pad: int = 0, height: int = 1, row_pad: int = 0):
    """A PointCloud2 holding `columns` (name -> (N,) array, each one field of its dtype) with `pad` spare
    bytes after every field, `height` rows (N divisible by it) and `row_pad` spare bytes after every row."""
    n = len(next(iter(columns.values())))
    assert n % height == 0
    width = n // height
    order = ">" if big_endian else "<"
    names, formats, offsets, pf = [], [], [], []
    offset = 0
    PointField = store.types["sensor_msgs/msg/PointField"]
    for name, values in columns.items():
        kind = np.dtype(values.dtype).str[1:]
        names.append(name)
        formats.append(order + kind)
        offsets.append(offset)
        pf.append(PointField(name=name, offset=offset, datatype=DATATYPE[kind], count=1))
        offset += np.dtype(kind).itemsize + pad
    step = offset
    dtype = np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": step})
    rec = np.full(n * step, 0xAB, dtype=np.uint8).view(dtype)  # padding bytes hold junk, as drivers leave them
    for name, values in columns.items():
        rec[name] = values
    rows = rec.view(np.uint8).reshape(height, width * step)
    data = np.concatenate([rows, np.full((height, row_pad), 0xAB, dtype=np.uint8)], axis=1).reshape(-1)
    return store.types[CLOUD](header=_header(store, stamp_ns, frame_id), height=height, width=width, fields=pf,
                              is_bigendian=big_endian, point_step=step, row_step=width * step + row_pad,
                              data=np.ascontiguousarray(data), is_dense=False)


def tf_message(store, transforms: list[tuple[int, str, str, np.ndarray]]):
    """A TFMessage of (stamp_ns, parent, child, 4x4 child->parent) transforms."""
    g = store.types
    out = []
    for stamp, parent, child, m in transforms:
        x, y, z, w = Rotation.from_matrix(m[:3, :3]).as_quat()
        out.append(g["geometry_msgs/msg/TransformStamped"](
            header=_header(store, stamp, parent), child_frame_id=child,
            transform=g["geometry_msgs/msg/Transform"](
                translation=g["geometry_msgs/msg/Vector3"](x=float(m[0, 3]), y=float(m[1, 3]), z=float(m[2, 3])),
                rotation=g["geometry_msgs/msg/Quaternion"](x=float(x), y=float(y), z=float(z), w=float(w)))))
    return g[TF](transforms=out)


@dataclass
class Bag:
    """What to write: (topic, msgtype, receive time ns, message) in any order."""

    kind: str  # ros1, sqlite3, mcap
    messages: list[tuple[str, str, int, object]] = field(default_factory=list)
    empty: list[tuple[str, str]] = field(default_factory=list)  # (topic, msgtype) connections without messages
    compress: bool = False  # ROS 1: LZ4 chunks; ROS 2: zstd per message

    @property
    def store(self):
        return store_for(self.kind)

    def add(self, topic: str, msgtype: str, received: int, msg: object) -> None:
        self.messages.append((topic, msgtype, received, msg))

    def write(self, path: Path) -> Path:
        store = self.store
        if self.kind == "ros1":
            writer = Writer1(path)
            if self.compress:
                writer.set_compression(Writer1.CompressionFormat.LZ4)
            serialize = store.serialize_ros1
        else:
            plugin = StoragePlugin.MCAP if self.kind == "mcap" else StoragePlugin.SQLITE3
            writer = Writer2(path, version=9, storage_plugin=plugin)
            if self.compress:
                writer.set_compression(CompressionMode.MESSAGE, CompressionFormat.ZSTD)
            serialize = store.serialize_cdr
        with writer:
            conns = {topic: writer.add_connection(topic, msgtype, typestore=store) for topic, msgtype in self.empty}
            for topic, msgtype, received, msg in sorted(self.messages, key=lambda m: m[2]):
                if topic not in conns:
                    conns[topic] = writer.add_connection(topic, msgtype, typestore=store)
                writer.write(conns[topic], received, serialize(msg, msgtype))
        return path


def storage_file(folder: Path) -> Path:
    """The single .db3 / .mcap file of a ROS 2 bag folder."""
    (found,) = [p for p in folder.iterdir() if p.suffix in (".db3", ".mcap")]
    return found
