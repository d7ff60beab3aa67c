"""Where the tiles of a drive go: square regions along the trajectory, oriented with it, overlapping.

The trajectory is the scans' sensor positions in scan order, as a polyline parametrised by arc length. Tile
centres sit on it every `size - overlap` metres (so consecutive tiles of a straight drive overlap by exactly
`overlap`; on a bend the chord is shorter than the arc and they overlap more), each yawed along the path's
heading around its centre, its bottom 1 m below the ground estimated from its own scans (the default region's
rule: `Region.around`), so hills and slopes keep each tile on its ground. Everything is float64 world metres:
georeferenced drives (UTM, 1e6 m) place tiles exactly.

Ownership: a point belongs to the tile whose centre is nearest (in x/y) among the tiles whose footprint holds
it. On a straight drive that is the midline of each overlap; in general it splits every overlap once, so
merged meshes have each place from exactly one tile (`owned`).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from hgca_core.config import check_stride as config_check_stride
from hgca_core.errors import InputError
from hgca_core.geometry.region import DEFAULT_SIZE, Region

MIN_OVERLAP = 6.4       # metres: 32 coarse cells, wider than the GCA's receptive field on either side
HEADING_SPAN = 0.25     # the heading is the chord over +- this fraction of the tile length (smooths GPS jitter)


@dataclass(frozen=True)
class Trajectory:
    """A polyline in arc length: positions (P, 3) float64 with consecutive duplicates removed."""

    points: np.ndarray
    s: np.ndarray = field(init=False)

    def __post_init__(self) -> None:
        p = np.asarray(self.points, dtype=np.float64).reshape(-1, 3)
        if len(p) == 0:
            raise InputError("a drive needs at least one scan position")
        if not np.all(np.isfinite(p)):
            raise InputError("scan positions have NaN or infinite coordinates")
        step = np.linalg.norm(np.diff(p[:, :2], axis=0), axis=1)
        keep = np.concatenate([[True], step > 1e-6])
        p = p[keep]
        object.__setattr__(self, "points", p)
        object.__setattr__(self, "s", np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(p[:, :2], axis=0),
                                                                                         axis=1))]))

    @property
    def length(self) -> float:
        return float(self.s[-1])

    def position(self, s: float) -> np.ndarray:
        """The point at arc length s (clamped to the ends)."""
        if len(self.points) == 1:
            return self.points[0].copy()
        return np.array([np.interp(s, self.s, self.points[:, i]) for i in range(3)])

    def heading(self, s: float, half: float) -> float:
        """Yaw (radians) of the chord from s - half to s + half (clamped); 0 for a path that does not move."""
        d = self.position(min(s + half, self.length)) - self.position(max(s - half, 0.0))
        if np.hypot(d[0], d[1]) < 1e-9:
            return 0.0
        return float(np.arctan2(d[1], d[0]))


@dataclass(frozen=True)
class TilePlan:
    """One tile before its ground is known: arc length, centre x/y, yaw, and the scans it is completed from."""

    index: int
    arc: float
    center_xy: np.ndarray
    yaw: float
    scans: tuple[int, ...]

    @property
    def phase(self) -> int:
        """1 for even tiles (completed first), 2 for odd ones (conditioned on their finished neighbours)."""
        return 1 + self.index % 2


MAX_TILES = 100_000    # a drive of 3,200 km at the default stride; more is a typo, not a drive


def check_stride(size: float, overlap: float) -> float:
    """The stride `size - overlap` between tiles, or an `InputError` naming the flags (`config.check_stride`,
    the drive settings' one check)."""
    return config_check_stride(size, overlap)


def plan_tiles(positions: np.ndarray, size: float = DEFAULT_SIZE[0], overlap: float = MIN_OVERLAP,
               scans_per_tile: int = 5) -> list[TilePlan]:
    """Tiles covering the trajectory through `positions` (the scans' sensor positions, in scan order) with
    `overlap` metres between consecutive tiles and a margin of overlap / 2 before the first and after the last
    position; each tile takes the `scans_per_tile` scans nearest its centre (all of them when there are fewer)."""
    stride = check_stride(size, overlap)
    if scans_per_tile < 1:
        raise InputError(f"scans per tile must be at least 1, got {scans_per_tile}")
    pos = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    path = Trajectory(pos)
    span = path.length + overlap            # cover [-overlap/2, length + overlap/2]
    n = 1 + int(np.ceil(max(0.0, span - size) / stride - 1e-9))
    if n > MAX_TILES:
        raise InputError(f"the drive would need {n:,} tiles ({path.length:,.1f} m at a stride of {stride:g} m); "
                         f"at most {MAX_TILES:,}: give fewer scans or a larger --size - --overlap")
    first = (path.length - (n - 1) * stride) / 2
    tiles = []
    for i in range(n):
        arc = first + i * stride
        centre = _extended(path, arc)
        near = np.argsort(np.linalg.norm(pos[:, :2] - centre[:2], axis=1), kind="stable")[:scans_per_tile]
        tiles.append(TilePlan(i, float(arc), centre[:2], path.heading(min(max(arc, 0.0), path.length),
                                                                     size * HEADING_SPAN),
                              tuple(int(j) for j in np.sort(near))))
    return tiles


def _extended(path: Trajectory, arc: float) -> np.ndarray:
    """The trajectory point at `arc`, continued straight along the end headings beyond either end."""
    if 0.0 <= arc <= path.length or path.length == 0.0:
        return path.position(min(max(arc, 0.0), path.length))
    end = 0.0 if arc < 0 else path.length
    yaw = path.heading(end, 1.0)
    return path.position(end) + (arc - end) * np.array([np.cos(yaw), np.sin(yaw), 0.0])


def tile_region(tile: TilePlan, points: np.ndarray, size: tuple[float, float, float]) -> Region:
    """The tile's box: centred on its trajectory point, yawed with the path, its bottom 1 m below the ground
    estimated from its own points around that centre (`Region.around`, the default region's rule)."""
    if len(points) == 0:
        raise InputError(f"tile {tile.index} has no input points (its scans {list(tile.scans)} are empty)")
    sensor = np.array([tile.center_xy[0], tile.center_xy[1], 0.0])
    return Region.around(points, sensor=sensor, size=size, yaw=tile.yaw)


def footprint_contains(region: Region, xy: np.ndarray) -> np.ndarray:
    """Whether world x/y points (N, 2) lie inside the region's footprint (its box ignoring z)."""
    c, s = np.cos(region.yaw), np.sin(region.yaw)
    d = np.asarray(xy, dtype=np.float64) - region.center[:2]
    u = d[:, 0] * c + d[:, 1] * s
    v = -d[:, 0] * s + d[:, 1] * c
    return (np.abs(u) <= region.size[0] / 2) & (np.abs(v) <= region.size[1] / 2)


def owned(xy: np.ndarray, index: int, regions: list[Region]) -> np.ndarray:
    """Which world x/y points (N, 2) tile `index` owns: of the tiles whose footprint holds a point, the one
    with the nearest centre (ties to the lower index). Points in no footprint belong to no tile."""
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    reach = float(np.hypot(*regions[index].size[:2]))
    best = np.full(len(xy), np.inf)
    owner = np.full(len(xy), -1)
    for j, r in enumerate(regions):
        if np.linalg.norm(r.center[:2] - regions[index].center[:2]) > reach:
            continue                                   # cannot share a point with tile `index`
        dist = np.linalg.norm(xy - r.center[:2], axis=1)
        better = footprint_contains(r, xy) & (dist < best)
        best[better] = dist[better]
        owner[better] = j
    return owner == index


def neighbours(index: int, count: int) -> tuple[int, ...]:
    """The tiles before and after `index` along the path (the ones a phase-two tile is conditioned on)."""
    return tuple(j for j in (index - 1, index + 1) if 0 <= j < count)
