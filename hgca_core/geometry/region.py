"""Oriented completion regions and the frames the model works in.

The *region frame* has its origin at the box's minimum corner and its axes along the box (yaw about z),
so a point inside the default region has 0 <= x, y < 38.4 m and 0 <= z < 8 m. Voxel indices are taken in
this frame, which makes them non-negative and bounded by the grid shape.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from hgca_core.config import REGION_SIZE
from hgca_core.errors import InputError
from hgca_core.geometry.voxel import COARSE, grid_shape

DEFAULT_SIZE = REGION_SIZE
MIN_SIZE = COARSE   # metres: the thinnest region side, one coarse cell (grids are rounded to whole cells)
BELOW_GROUND = 1.0  # the box starts this far below the ground under the sensor (paper: [-1, 7] m)


def height_layer(height: float, cell: float) -> int:
    """Index of the layer of `cell`-metre cells that holds the height `height` m above the region's ground (the
    box starts BELOW_GROUND under it); a height on a cell boundary belongs to the layer above."""
    return int(np.floor((BELOW_GROUND + height) / cell + 1e-9))
GROUND_STEP = 1.0   # metres between the samples of a region's ground-height grid (x, y = i, j * GROUND_STEP)


@dataclass(frozen=True)
class Region:
    """An oriented box: centre (world, metres), size (metres) and yaw (radians, about +z)."""

    center: np.ndarray
    size: np.ndarray = field(default_factory=lambda: np.array(DEFAULT_SIZE))
    yaw: float = 0.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "center", np.asarray(self.center, dtype=np.float64).reshape(3))
        object.__setattr__(self, "size", np.asarray(self.size, dtype=np.float64).reshape(3))
        if not np.all(np.isfinite(self.center)) or not np.all(np.isfinite(self.size)) or not np.isfinite(self.yaw):
            raise InputError("region has non-finite numbers")
        if np.any(self.size <= 0):
            raise InputError(f"region size must be positive, got {self.size.tolist()}")
        if np.any(self.size < MIN_SIZE):   # thinner boxes hold no whole 20 cm cell along that axis: nothing to grow
            thin = ", ".join("xyz"[i] for i in np.flatnonzero(self.size < MIN_SIZE))
            raise InputError(f"region size must be at least {MIN_SIZE:g} m (one {COARSE * 100:.0f} cm cell) along each "
                             f"axis, got {self.size.tolist()} ({thin} too thin)")

    @property
    def rotation(self) -> np.ndarray:
        """3x3 rotation from region axes to world axes."""
        c, s = np.cos(self.yaw), np.sin(self.yaw)
        return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])

    @property
    def min_corner(self) -> np.ndarray:
        return self.center - self.rotation @ (self.size / 2)

    def to_local(self, points: np.ndarray) -> np.ndarray:
        """World -> region frame (origin at the minimum corner)."""
        p = np.asarray(points, dtype=np.float64)
        return (p - self.center) @ self.rotation + self.size / 2

    def to_world(self, local: np.ndarray) -> np.ndarray:
        """Region frame -> world."""
        q = np.asarray(local, dtype=np.float64) - self.size / 2
        return q @ self.rotation.T + self.center

    def local_matrix(self) -> np.ndarray:
        """4x4 transform world -> region frame (for poses)."""
        m = np.eye(4)
        m[:3, :3] = self.rotation.T
        m[:3, 3] = -self.rotation.T @ self.center + self.size / 2
        return m

    def contains_local(self, local: np.ndarray) -> np.ndarray:
        return np.all((local >= 0) & (local < self.size), axis=1)

    def grid_shape(self, voxel: float) -> tuple[int, int, int]:
        return grid_shape(self.size, voxel)

    def as_tuple(self) -> tuple[float, ...]:
        """(cx, cy, cz, sx, sy, sz, yaw_degrees): the CLI's --region form."""
        return (*self.center.tolist(), *self.size.tolist(), float(np.degrees(self.yaw)))

    @classmethod
    def parse(cls, text: str) -> "Region":
        """Parse 'cx,cy,cz,sx,sy,sz[,yaw_degrees]'."""
        try:
            vals = [float(v) for v in text.split(",")]
        except ValueError as exc:
            raise InputError(f"--region must be numbers 'cx,cy,cz,sx,sy,sz[,yaw]', got {text!r}") from exc
        if len(vals) not in (6, 7):
            raise InputError(f"--region needs 6 or 7 numbers 'cx,cy,cz,sx,sy,sz[,yaw]', got {len(vals)}")
        return cls.from_tuple(vals)

    @classmethod
    def from_tuple(cls, values: Sequence[float] | np.ndarray) -> "Region":
        """Inverse of `as_tuple`: (cx, cy, cz, sx, sy, sz[, yaw_degrees]), e.g. a synthetic sample's `region`."""
        v = [float(x) for x in values]
        return cls(center=np.array(v[:3]), size=np.array(v[3:6]), yaw=float(np.radians(v[6]) if len(v) == 7 else 0.0))

    @classmethod
    def around(cls, points: np.ndarray, sensor: np.ndarray | None = None, ground_z: float | None = None,
               size: tuple[float, float, float] = DEFAULT_SIZE, yaw: float = 0.0) -> "Region":
        """The paper's default box: centred on the sensor in x/y, from 1 m below the ground up.

        Without a sensor origin the centre is the median of the points in x/y; without a ground height
        it is estimated from the points near that centre.
        """
        pts = np.asarray(points, dtype=np.float64)
        if len(pts) == 0:
            raise InputError("cannot place a region around zero points")
        centre_xy = np.asarray(sensor, dtype=np.float64)[:2] if sensor is not None else np.median(pts[:, :2], axis=0)
        if ground_z is None:
            ground_z = estimate_ground(pts, centre_xy)
        sz = np.asarray(size, dtype=np.float64)
        centre = np.array([centre_xy[0], centre_xy[1], ground_z - BELOW_GROUND + sz[2] / 2])
        return cls(center=centre, size=sz, yaw=yaw)


def default_region(points: np.ndarray, origins: np.ndarray | None = None,
                   size: tuple[float, float, float] = DEFAULT_SIZE) -> Region:
    """The box used wherever none is given: `hgca complete` without --region, `hgca region`, and the add-on's
    "Add Region Box" (which asks `hgca region`). Centred on the first scan's sensor, or on the points' x/y median
    when no sensor origin is known; the bottom 1 m below the ground estimated around that centre."""
    sensor = None
    if origins is not None and len(origins):
        sensor = np.asarray(origins, dtype=np.float64).reshape(-1, 3)[0]
    return Region.around(points, sensor=sensor, size=size)


def ground_height(region: Region) -> float:
    """The ground height a default region was placed on (its bottom is BELOW_GROUND under it)."""
    return float(region.center[2] - region.size[2] / 2 + BELOW_GROUND)


def estimate_ground(points: np.ndarray, centre_xy: np.ndarray, radius: float = 15.0, cell: float = 2.0,
                    fit_radius: float = 8.0, above: float = 0.1) -> float:
    """Robust ground height at centre_xy, on flat and on sloped streets.

    Per 2 m cell within `radius`, a low percentile of z ignores cars, walls and trees (they only add points
    above the ground). A plane through the cell lows within `fit_radius` is then fitted to the lower
    envelope: cells more than `above` over the plane (sidewalks, car roofs where the road is hidden) or far
    under it are dropped and the fit repeated. The plane's height at the centre, lifted by the median
    offset of the points lying on it, is the answer: a slope no longer shifts the box by the slope times
    the offset of the seen cells from the sensor. With too few cells, or an implausible slope (> 0.3),
    the median of the cell lows is used.
    """
    pts = np.asarray(points, dtype=np.float64)
    centre_xy = np.asarray(centre_xy, dtype=np.float64)
    d = np.linalg.norm(pts[:, :2] - centre_xy, axis=1)
    near = pts[d < radius]
    if len(near) < 20:
        near = pts
    keys = np.floor(near[:, :2] / cell).astype(np.int64)
    cells, inv = np.unique(keys, axis=0, return_inverse=True)
    inv = inv.reshape(-1)
    order = np.lexsort((near[:, 2], inv))
    z_sorted, g_sorted = near[order, 2], inv[order]
    starts = np.searchsorted(g_sorted, np.arange(g_sorted.max() + 1))
    counts = np.bincount(g_sorted)
    lows = z_sorted[starts + (counts * 0.05).astype(np.int64)]
    full = counts >= 3
    median = float(np.median(lows[full])) if np.any(full) else float(np.median(lows))
    xy, z = (cells[full] + 0.5) * cell - centre_xy, lows[full]
    close = np.linalg.norm(xy, axis=1) < fit_radius
    keep = close & (np.abs(z - median) < 0.5)
    if keep.sum() < 8:
        return median
    design = np.c_[np.ones(len(z)), xy]
    for _ in range(5):
        coef = np.linalg.lstsq(design[keep], z[keep], rcond=None)[0]
        res = z - design @ coef
        new = close & (res < above) & (res > -0.5)
        if new.sum() < 8 or np.array_equal(new, keep):
            break
        keep = new
    if np.hypot(*coef[1:]) > 0.3:
        return median
    rel = near[:, :2] - centre_xy
    off = near[:, 2] - (coef[0] + rel @ coef[1:])
    on = (np.linalg.norm(rel, axis=1) < fit_radius) & (np.abs(off) < above)
    return float(coef[0] + (np.median(off[on]) if on.sum() > 20 else 0.0))


def ground_at(grid: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Ground height (region-frame z) under region-frame x, y, from a ground-height grid sampled every
    GROUND_STEP metres from the region's origin (a synthetic sample's `ground_height`): bilinear, clamped at
    the grid's edges. On sloped streets the ground under the sensor (`ground_z`) is not the ground elsewhere."""
    g = np.asarray(grid, dtype=np.float64)
    p = np.asarray(xy, dtype=np.float64).reshape(-1, 2) / GROUND_STEP
    f = np.clip(p, 0.0, np.array(g.shape, dtype=np.float64) - 1 - 1e-9)
    i, j = np.floor(f).astype(np.int64).T
    tx, ty = (f - np.floor(f)).T
    return ((1 - tx) * (1 - ty) * g[i, j] + tx * (1 - ty) * g[i + 1, j] + (1 - tx) * ty * g[i, j + 1]
            + tx * ty * g[i + 1, j + 1])
