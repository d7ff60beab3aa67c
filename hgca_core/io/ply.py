"""PLY point clouds (ascii or binary) via plyfile: x, y, z plus every other scalar vertex property."""
from __future__ import annotations

import numpy as np

from hgca_core.errors import InputError
from hgca_core.io.scan import Scan


def read_ply(path: str) -> Scan:
    """Read the `vertex` element; list properties (e.g. faces' indices) are not per-point and are skipped."""
    from plyfile import PlyData

    ply = PlyData.read(path)  # memory-mapped for binary files: ~1000x faster than streaming rows
    names = [e.name for e in ply.elements]
    if "vertex" not in names:
        raise InputError(f"PLY has no 'vertex' element (elements: {names})", path)
    vertex = ply["vertex"].data
    fields = vertex.dtype.names or ()
    missing = [c for c in ("x", "y", "z") if c not in fields]
    if missing:
        raise InputError(f"PLY vertex element lacks {', '.join(missing)} (properties: {list(fields)})", path)
    points = np.column_stack([np.asarray(vertex[c], dtype=np.float64) for c in ("x", "y", "z")])
    attributes = {
        name: np.array(vertex[name])  # copies: the result must not keep the file mapped
        for name in fields
        if name not in ("x", "y", "z") and vertex.dtype[name].shape == () and vertex.dtype[name] != object
    }
    return Scan(points, attributes, None, path)
