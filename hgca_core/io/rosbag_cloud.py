"""sensor_msgs/PointCloud2 decoding with numpy alone (no ROS installation): any field layout a driver writes.

A cloud's `data` is `height` rows of `row_step` bytes, each holding `width` points of `point_step` bytes; every
field sits at its own `offset` in a point with one of the eight PointField datatypes, in the byte order
`is_bigendian` says. Each field we keep is read as a strided view of that buffer, so padding between fields,
after a point and after a row costs nothing and needs no special case.

Kept: x, y, z (required), `intensity` (else `reflectivity`) as float32, `ring` as uint16 and the per-point time
(`t`, `time`, `timestamp`, ...) as float64 seconds relative to the message stamp: drivers store it as
nanoseconds or seconds, relative to the sweep start or absolute, and the unit is told from the values (below).
"""
from __future__ import annotations

from typing import Any

import numpy as np

from hgca_core.errors import InputError
from hgca_core.io.scan import Scan

DATATYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}
TIME_FIELDS = ("t", "time", "timestamp", "time_offset", "offset_time", "time_stamp", "ts")
INTENSITY_FIELDS = ("intensity", "reflectivity")
ABSOLUTE_NS = 1e15  # larger per-point times are absolute nanoseconds (epoch 2001 = 1e18 ns)
ABSOLUTE_S = 1e6    # larger float times are absolute seconds (a sweep lasts well under a second)


def _field_table(msg: Any, where: str) -> dict[str, tuple[int, str]]:
    """name -> (offset, numpy type) of the single-valued fields that fit in a point. A field hgca does not read
    may be anything; x, y and z must be readable."""
    order = ">" if msg.is_bigendian else "<"
    step = int(msg.point_step)
    fields: dict[str, tuple[int, str]] = {}
    for f in msg.fields:
        name, kind, count, offset = str(f.name), DATATYPES.get(int(f.datatype)), int(f.count), int(f.offset)
        size = np.dtype(kind).itemsize * max(count, 1) if kind else 0
        problem = (f"has datatype {int(f.datatype)} (PointField datatypes are 1 to 8)" if kind is None else
                   f"has count {count} (one value per point is needed)" if count not in (0, 1) else
                   f"at offset {offset} ({size} bytes) does not fit in a point of point_step {step} bytes"
                   if offset < 0 or offset + size > step else "")
        if problem and name in ("x", "y", "z"):
            raise InputError(f"field {name!r} {problem}", where)
        if not problem and name not in fields:
            fields[name] = (offset, order + str(kind))
    return fields


def _column(data: np.ndarray, msg: Any, offset: int, kind: str) -> np.ndarray:
    """One field of every point (row-major), read through strides over the raw bytes."""
    height, width = int(msg.height), int(msg.width)
    view = np.ndarray((height, width), dtype=np.dtype(kind), buffer=data, offset=offset,
                      strides=(int(msg.row_step), int(msg.point_step)))
    return view.reshape(-1).astype(np.dtype(kind).newbyteorder("="))


def relative_time(values: np.ndarray, stamp_ns: int) -> np.ndarray:
    """Per-point times as float64 seconds after the message stamp. Integers are nanoseconds; floats above
    1e15 are absolute nanoseconds, above 1e6 absolute seconds, else seconds relative to the sweep start
    (which drivers stamp the message with)."""
    if len(values) == 0:
        return values.astype(np.float64)
    if values.dtype.kind in "iu":
        as_int = values.astype(np.int64)
        if np.abs(as_int).max() > ABSOLUTE_NS:
            return (as_int - np.int64(stamp_ns)).astype(np.float64) / 1e9
        return as_int.astype(np.float64) / 1e9
    v = values.astype(np.float64)
    peak = np.nanmax(np.abs(v)) if np.isfinite(v).any() else 0.0
    if peak > ABSOLUTE_NS:
        return (v - float(stamp_ns)) / 1e9
    if peak > ABSOLUTE_S:
        return v - stamp_ns / 1e9
    return v


def decode_cloud(msg: Any, stamp_ns: int, where: str) -> Scan:
    """The cloud's points (float64, sensor frame) with intensity, ring and time when present; origin at the
    sensor. Raises InputError (naming `where`) for a layout that does not fit its data or lacks x/y/z."""
    height, width, step, row = int(msg.height), int(msg.width), int(msg.point_step), int(msg.row_step)
    if step <= 0 and height * width:
        raise InputError(f"point_step is {step}: each point needs a positive size", where)
    fields = _field_table(msg, where)
    missing = [a for a in "xyz" if a not in fields]
    if missing:
        present = ", ".join(str(f.name) for f in msg.fields) or "none"
        raise InputError(f"point cloud has no {'/'.join(missing)} field (fields: {present})", where)
    data = np.frombuffer(memoryview(msg.data).cast("B"), dtype=np.uint8)
    if height * width:
        if row < width * step:
            raise InputError(f"row_step {row} is shorter than width {width} x point_step {step}", where)
        need = (height - 1) * row + width * step
        if len(data) < need:
            raise InputError(f"point cloud data holds {len(data)} bytes but height {height} x width {width} "
                             f"(row_step {row}, point_step {step}) needs {need}: truncated message", where)
    pts = np.stack([_column(data, msg, *fields[a]).astype(np.float64) for a in "xyz"], axis=1)
    attributes: dict[str, np.ndarray] = {}
    name = next((n for n in INTENSITY_FIELDS if n in fields), None)
    if name is not None:
        attributes["intensity"] = _column(data, msg, *fields[name]).astype(np.float32)
    if "ring" in fields:
        ring = _column(data, msg, *fields["ring"])
        whole = ring.dtype.kind in "iu" or bool(np.isfinite(ring).all() and (ring == np.round(ring)).all())
        ok = whole and (len(ring) == 0 or (ring.min() >= 0 and ring.max() < 65536))
        attributes["ring"] = ring.astype(np.uint16) if ok else ring.astype(np.float32)
    name = next((n for n in TIME_FIELDS if n in fields), None)
    if name is not None:
        attributes["time"] = relative_time(_column(data, msg, *fields[name]), stamp_ns)
    return Scan(pts, attributes, np.zeros((1, 3)), where)
