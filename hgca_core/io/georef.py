"""Georeferenced coordinates: float32 arrays in a local frame plus a float64 offset, exact to well below 1 mm.

float32 has 24 bits of mantissa: at y = 1e7 m (UTM northing) its spacing is 1 m, at 5e6 m 0.5 m. Points are
read and processed in float64; wherever a file format stores float32 (the `.npz` layouts, glTF buffers),
coordinates are written relative to an offset in whole metres that the file carries in float64 (`offset`
array, glTF node translation). Below `LOCAL_LIMIT` the offset is zero, so local scans keep their numbers.
"""
from __future__ import annotations

import numpy as np

from hgca_core.errors import InputError

# float32 spacing is 2**-10 m (0.98 mm) between 8192 and 16384 m: below 8192 m rounding stays under 0.5 mm.
LOCAL_LIMIT = 8192.0


def needs_offset(points: np.ndarray) -> bool:
    """True when float32 world coordinates would be off by 0.5 mm or more somewhere."""
    pts = np.asarray(points)
    return bool(len(pts)) and float(np.abs(pts).max()) >= LOCAL_LIMIT


def local_offset(points: np.ndarray) -> np.ndarray:
    """(3,) float64: the centre of the points' bounds in whole metres, or zeros when they are near the origin.

    Whole metres keep the offset readable and exactly representable everywhere (a float32 object location in
    Blender holds every integer up to 16,777,216 m)."""
    pts = np.asarray(points, dtype=np.float64)
    if not needs_offset(pts):
        return np.zeros(3)
    return np.round((pts.min(axis=0) + pts.max(axis=0)) / 2)


def to_local32(points: np.ndarray, offset: np.ndarray) -> np.ndarray:
    """float32 coordinates relative to `offset` (the subtraction happens in float64)."""
    return (np.asarray(points, dtype=np.float64) - offset).astype(np.float32)


def read_offset(value: np.ndarray, path: str) -> np.ndarray:
    """The `offset` array of an .npz, checked: 3 finite numbers."""
    off = np.asarray(value)
    if off.dtype.kind not in "iuf" or off.shape != (3,) or not np.all(np.isfinite(off)):
        raise InputError(f"'offset' must be 3 finite numbers, got shape {off.shape} {off.dtype}", path)
    return off.astype(np.float64)
