"""LAS / LAZ / COPC via laspy (+ lazrs): scaled and offset coordinates, a few standard per-point fields.

Coordinates are `X * scale + offset` in float64 (laspy's scaled views), so UTM eastings and northings keep
the file's own precision. The header is checked before any point is read: a zero or non-finite scale makes
every point the same (corrupt), and a point count the file cannot hold (4.29 billion points in a few kB)
is a truncated or corrupt file, not a request to allocate 146 GB. Points are read in chunks, so memory only
grows with points that are really there.
"""
from __future__ import annotations

import os
from typing import Any

import numpy as np

from hgca_core.errors import InputError
from hgca_core.io.scan import Scan

# Per-point fields worth carrying (intensity for display, returns and class for filtering, time for ordering).
LAS_ATTRIBUTES = ("intensity", "return_number", "classification", "gps_time")


CHUNK = 1 << 20


def check_header(header: Any, path: str) -> None:
    """Scale, offset and point count against what a sane file of this size can hold."""
    for axis, scale, offset in zip("xyz", header.scales, header.offsets):
        if not np.isfinite(scale) or scale == 0:
            raise InputError(f"corrupt LAS header: {axis} scale is {scale} (every point would get the same {axis})",
                             path)
        if not np.isfinite(offset):
            raise InputError(f"corrupt LAS header: {axis} offset is {offset}", path)
    count = int(header.point_count)
    if not header.are_points_compressed:
        need = int(header.offset_to_point_data) + count * int(header.point_format.size)
        size = os.path.getsize(path)
        if need > size:
            raise InputError(f"truncated or corrupt LAS file: header says {count} points ({need} bytes with the "
                             f"header), the file has {size} bytes", path)


def read_las(path: str) -> Scan:
    """Read every point; a file holding fewer points than its header promises is truncated or corrupt."""
    import laspy

    with laspy.open(path) as reader:
        header = reader.header
        check_header(header, path)
        count = int(header.point_count)
        present = set(header.point_format.dimension_names)
        names = [name for name in LAS_ATTRIBUTES if name in present]
        xyz: list[np.ndarray] = []
        columns: dict[str, list[np.ndarray]] = {name: [] for name in names}
        read = 0
        try:
            for chunk in reader.chunk_iterator(CHUNK):
                xyz.append(np.column_stack([np.asarray(chunk.x, dtype=np.float64), np.asarray(chunk.y, dtype=np.float64),
                                            np.asarray(chunk.z, dtype=np.float64)]))
                for name in names:
                    columns[name].append(np.array(chunk[name]))
                read += len(chunk)
        except MemoryError:
            raise
        except Exception as exc:  # noqa: BLE001 - lazrs/laspy raise many types for a file that ends early
            raise InputError(f"truncated or corrupt LAS/LAZ file: header says {count} points, reading stopped "
                             f"after {read} ({type(exc).__name__}: {exc})", path) from None
    if read != count:
        raise InputError(f"truncated LAS/LAZ file: header says {count} points, file holds {read}", path)
    points = np.concatenate(xyz) if xyz else np.zeros((0, 3))
    attributes = {name: np.concatenate(parts) for name, parts in columns.items() if parts}
    return Scan(points, attributes, None, path)


def las_header_info(path: str) -> dict[str, Any]:
    """Header facts `hgca info` shows (version, point format, counts, scale, offset) without reading points."""
    import laspy

    with laspy.open(path) as reader:
        h = reader.header
        vlr_ids = {(v.user_id, v.record_id) for v in h.vlrs}
        return {
            "version": f"{h.version.major}.{h.version.minor}",
            "point_format": int(h.point_format.id),
            "header_point_count": int(h.point_count),
            "scale": [float(v) for v in h.scales],
            "offset": [float(v) for v in h.offsets],
            "compressed": bool(h.are_points_compressed),
            "copc": ("copc", 1) in vlr_ids,
            "header_min": [float(v) for v in h.mins],
            "header_max": [float(v) for v in h.maxs],
        }
