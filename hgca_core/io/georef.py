"""Georeferenced coordinates: float32 arrays in a local frame plus a float64 offset, exact to well below 1 mm.

float32 has 24 bits of mantissa: at y = 1e7 m (UTM northing) its spacing is 1 m, at 5e6 m 0.5 m. Points are
read and processed in float64; wherever a file format stores float32 (the `.npz` layouts, glTF buffers),
coordinates are written relative to an offset in whole metres that the file carries in float64 (`offset`
array, glTF node translation). Below `LOCAL_LIMIT` the offset is zero, so local scans keep their numbers.

One offset serves a whole file, so the promise holds only while every point lies within `FRAME_RADIUS` of it.
A stray point (a (0, 0, 0) return among UTM points, a 1e30 float in a sensor dump) would pull a bounds
midpoint half-way to it and cost every other point up to 0.25 m, so a scan whose points cannot share one
frame is refused, with the number of points that lie apart and how far (`check_coordinates`), instead.
"""
from __future__ import annotations

from typing import Callable

import numpy as np

from hgca_core.errors import InputError

# float32 spacing is 2**-10 m (0.98 mm) between 8192 and 16384 m: below 8192 m rounding stays under 0.5 mm.
LOCAL_LIMIT = 8192.0
# Around an offset, float32 rounds |p - offset| < 16384 m by at most 2**-11 m (0.49 mm): the frame's reach.
FRAME_RADIUS = 16384.0
# Beyond 1e9 m (25 times the Earth's circumference) a coordinate is no place on Earth in metres: a corrupt
# file, a wrong scale or a pose in other units. Below it float64 keeps 1.2e-7 m, so offset + local stays exact.
COORD_LIMIT = 1e9


def needs_offset(points: np.ndarray) -> bool:
    """True when float32 world coordinates would be off by 0.5 mm or more somewhere."""
    pts = np.asarray(points)
    return bool(len(pts)) and float(np.abs(_bounds(pts)).max()) >= LOCAL_LIMIT


def _bounds(pts: np.ndarray) -> np.ndarray:
    """(2, 3) per-axis min and max, without a copy of the points (50 M points are 1.2 GB)."""
    pts = pts.reshape(-1, 3)
    columns = [pts[:, axis] for axis in range(3)]          # column by column: 7x faster than axis=0 on (N, 3)
    return np.array([[c.min() for c in columns], [c.max() for c in columns]], dtype=np.float64)


def _row(values: np.ndarray) -> str:
    return ", ".join(f"{v:.10g}" for v in values)


def _at(row: int, locate: Callable[[int], str] | None) -> str:
    return f"row {row}" + (f" ({locate(row)})" if locate is not None else "")


def check_bound(points: np.ndarray, where: str | None = None, what: str = "point",
                locate: Callable[[int], str] | None = None) -> None:
    """Raise InputError for any coordinate beyond `COORD_LIMIT` (or not finite), counting the rows; `locate`
    names the source of a row (e.g. which of several accumulated scans)."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(pts):
        _check_bound(pts, _bounds(pts), where, what, locate)


def _check_bound(pts: np.ndarray, bounds: np.ndarray, where: str | None, what: str,
                 locate: Callable[[int], str] | None) -> None:
    if np.abs(bounds).max() <= COORD_LIMIT:
        return
    big = ~(np.abs(pts).max(axis=1) <= COORD_LIMIT)
    if big.any():
        first = int(np.flatnonzero(big)[0])
        raise InputError(f"{int(big.sum())} {what}(s) have coordinates beyond {COORD_LIMIT:.0e} m (first at "
                         f"{_at(first, locate)}: {_row(pts[first])}): no place on Earth in metres (corrupt file "
                         "or wrong scale)", where)


def check_coordinates(points: np.ndarray, where: str | None = None, what: str = "point",
                      locate: Callable[[int], str] | None = None) -> None:
    """Raise InputError unless every point lies within `COORD_LIMIT` of zero and all can share one float32
    frame (a bounds midpoint within `FRAME_RADIUS` of each). The message counts the points that lie apart
    from the others (farther than `FRAME_RADIUS` from the median, which one outlier cannot move)."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if not len(pts):
        return
    bounds = _bounds(pts)
    _check_bound(pts, bounds, where, what, locate)
    if _frame_fits(bounds, _midpoint(bounds)):
        return
    inside = _densest_box(pts)
    apart = ~inside
    below, above = pts[inside].min(axis=0), pts[inside].max(axis=0)
    dist = np.maximum(below - pts, pts - above).max(axis=1)
    first = int(np.flatnonzero(apart)[0])
    n = int(apart.sum())
    near, far = float(dist[apart].min()), float(dist[apart].max())
    span = f"{near:.3g} m" if near > 0.5 * far else f"{near:.3g} to {far:.3g} m"
    verb = "lies" if n == 1 else "lie"
    raise InputError(f"{n} of {len(pts)} {what}s {verb} {span} from the others (first at {_at(first, locate)}: "
                     f"{_row(pts[first])}); one float32 frame with a float64 offset holds points within "
                     f"{FRAME_RADIUS:.0f} m of its centre to 1 mm: remove the stray points or split the scan", where)


def _densest_box(pts: np.ndarray) -> np.ndarray:
    """(N,) bool: the points inside, on every axis, the window of width 2 `FRAME_RADIUS` - 2 that holds the
    most of them, so the points counted as lying apart are as few as one frame allows. Called only when the
    midpoint frame fails, i.e. the bounds span more than that width, so some point always lies outside."""
    width = 2 * FRAME_RADIUS - 2
    inside = np.ones(len(pts), dtype=bool)
    for axis in range(3):
        v = np.sort(pts[:, axis])
        ends = np.searchsorted(v, v + width, side="right")   # window [v[i], v[i] + width] holds ends[i] - i
        i = int(np.argmax(ends - np.arange(len(v))))
        inside &= (pts[:, axis] >= v[i]) & (pts[:, axis] <= v[i] + width)
    if not inside.any():                                     # windows of different points: keep the median's
        dist = np.abs(pts - np.median(pts, axis=0)).max(axis=1)
        inside = dist < FRAME_RADIUS - 1
        inside[int(np.argmin(dist))] = True
    return inside


def _midpoint(bounds: np.ndarray) -> np.ndarray:
    return np.round(bounds[0] / 2 + bounds[1] / 2)   # halves first: no overflow near 1.8e308


def _frame_fits(bounds: np.ndarray, offset: np.ndarray) -> bool:
    return bool(max((bounds[1] - offset).max(), (offset - bounds[0]).max()) < FRAME_RADIUS)


def local_offset(points: np.ndarray) -> np.ndarray:
    """(3,) float64: the centre of the points' bounds in whole metres, or zeros when they are near the origin.

    Whole metres keep the offset readable and exactly representable everywhere (a float32 object location in
    Blender holds every integer up to 16,777,216 m). Points that no single frame holds to 1 mm raise
    InputError (`check_coordinates`) rather than be written off by centimetres."""
    pts = np.asarray(points, dtype=np.float64)
    if not len(pts):
        return np.zeros(3)
    bounds = _bounds(pts)
    if not float(np.abs(bounds).max()) >= LOCAL_LIMIT:
        return np.zeros(3)
    offset = _midpoint(bounds)
    if not (np.abs(bounds).max() <= COORD_LIMIT) or not _frame_fits(bounds, offset):
        check_coordinates(pts)
    return offset


def to_local32(points: np.ndarray, offset: np.ndarray) -> np.ndarray:
    """float32 coordinates relative to `offset` (the subtraction happens in float64)."""
    return (np.asarray(points, dtype=np.float64) - offset).astype(np.float32)


def read_offset(value: np.ndarray, path: str) -> np.ndarray:
    """The `offset` array of an .npz, checked: 3 finite numbers within `COORD_LIMIT`."""
    off = np.asarray(value)
    if off.dtype.kind not in "iuf" or off.shape != (3,) or not np.all(np.isfinite(off)):
        raise InputError(f"'offset' must be 3 finite numbers, got shape {off.shape} {off.dtype}", path)
    if np.abs(off).max() > COORD_LIMIT:
        raise InputError(f"'offset' {_row(off)} lies beyond {COORD_LIMIT:.0e} m: no place on Earth in metres", path)
    return off.astype(np.float64)
