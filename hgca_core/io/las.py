"""LAS / LAZ / COPC via laspy (+ lazrs): scaled and offset coordinates, a few standard per-point fields."""
from __future__ import annotations

from typing import Any

import numpy as np

from hgca_core.errors import InputError
from hgca_core.io.scan import Scan

# Per-point fields worth carrying (intensity for display, returns and class for filtering, time for ordering).
LAS_ATTRIBUTES = ("intensity", "return_number", "classification", "gps_time")


def read_las(path: str) -> Scan:
    """Read every point; a file holding fewer points than its header promises is reported as truncated."""
    import laspy

    las = laspy.read(path)
    header_count = int(las.header.point_count)
    if len(las.points) != header_count:
        raise InputError(f"truncated: header says {header_count} points, file holds {len(las.points)}", path)
    points = np.column_stack([np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)]).astype(np.float64)
    present = set(las.point_format.dimension_names)
    attributes = {name: np.array(las[name]) for name in LAS_ATTRIBUTES if name in present}
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
