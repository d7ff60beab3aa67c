"""Observed free space: the vectorised ray walk against a naive per-ray voxel traversal written here."""
from __future__ import annotations

import math

import numpy as np
import pytest

from hgca_core.errors import InputError
from hgca_core.geometry.freespace import HALF, STOP_SHORT, confident, observed_empty, ray_origins, swept
from hgca_core.geometry.voxel import COARSE, voxelize

V, S = 0.2, 0.05  # cell size, shift: cell c spans [c V - S, c V + V - S)


def naive_walk(o: np.ndarray, e: np.ndarray, shape: tuple[int, int, int], V: float = V
               ) -> set[tuple[int, int, int]]:
    """Cells (of size V, nested in the 20 cm ones) the segment o->e passes through, by Amanatides & Woo, one ray
    at a time in plain Python, restricted to the grid."""
    d = e - o
    cell = [math.floor((o[a] + S) / V) for a in range(3)]
    last = [math.floor((e[a] + S) / V) for a in range(3)]
    step, t_next, t_delta = [0] * 3, [math.inf] * 3, [math.inf] * 3
    for a in range(3):
        if d[a] > 0:
            step[a], t_next[a] = 1, ((cell[a] + 1) * V - S - o[a]) / d[a]
        elif d[a] < 0:
            step[a], t_next[a] = -1, (cell[a] * V - S - o[a]) / d[a]
        if d[a] != 0:
            t_delta[a] = V / abs(d[a])
    out = set()
    remaining = sum(abs(last[a] - cell[a]) for a in range(3))
    while True:
        if all(0 <= cell[a] < shape[a] for a in range(3)):
            out.add(tuple(cell))
        if remaining == 0:
            return out
        a = min(range(3), key=lambda i: t_next[i])
        cell[a] += step[a]
        t_next[a] += t_delta[a]
        remaining -= 1


def naive_observed_empty(points, origins, index, shape, stop_short=STOP_SHORT, sub: int = 1) -> np.ndarray:
    """The free space walked cell by cell; with `sub` > 1 the count of (20 / sub) cm sub-cells crossed per 20 cm
    cell instead."""
    fine = tuple(n * sub for n in shape)
    grid = np.zeros(fine, dtype=bool)
    for p, i in zip(points, index):
        o = origins[i]
        length = np.linalg.norm(p - o)
        if length <= stop_short:
            continue
        for c in naive_walk(o, p - (p - o) * (stop_short / length), fine, V / sub):
            grid[c] = True
    out = grid if sub == 1 else np.zeros(shape, dtype=np.int64)
    if sub > 1:
        for c in np.argwhere(grid):
            out[tuple(c // sub)] += 1
    hits = voxelize(points, COARSE)
    for c in hits:
        lo, hi = np.maximum(c - 1, 0), np.minimum(c + 2, shape)
        if np.all(lo < hi):
            out[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]] = 0
    return out


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_matches_naive_walk(seed):
    rng = np.random.default_rng(seed)
    shape = (24, 20, 10)
    size = np.array(shape) * V
    origins = np.array([[2.4, 2.0, 1.7], [2.41, 2.02, 1.55], [-3.0, 1.0, 1.0]])  # the last lies outside the grid
    # hits inside, beyond and below the grid, some within stop_short of their sensor
    pts = rng.uniform(-2.0, size + 2.0, (1500, 3))
    pts[:100] = origins[0] + rng.normal(0, 0.2, (100, 3))
    index = rng.integers(0, len(origins), len(pts))
    got = observed_empty(pts, origins, index, shape)
    want = naive_observed_empty(pts, origins, index, shape)
    assert want.sum() > 200  # a real comparison, not two empty grids
    np.testing.assert_array_equal(got, want)


@pytest.mark.parametrize("sub", [2, 4])
def test_swept_counts_match_a_naive_walk_of_sub_cells(sub):
    rng = np.random.default_rng(sub)
    shape = (12, 10, 6)
    size = np.array(shape) * V
    origins = np.array([[1.2, 1.0, 0.9], [-1.0, 0.5, 0.6]])
    pts = rng.uniform(-1.0, size + 1.0, (400, 3))
    index = rng.integers(0, len(origins), len(pts))
    got = swept(pts, origins, index, shape, sub=sub)
    want = naive_observed_empty(pts, origins, index, shape, sub=sub)
    assert got.dtype == np.uint8 and want.max() >= sub ** 2 and (want > 0).sum() > 50
    np.testing.assert_array_equal(got, want)
    # any sub-cell crossed <=> the 20 cm cell crossed: the same free space as observed_empty's
    np.testing.assert_array_equal(got > 0, observed_empty(pts, origins, index, shape))


def test_swept_tells_grazed_ground_from_air_the_rays_cross():
    """The ring scan of `test_grazing_rays_put_ground_in_the_free_space_but_not_in_its_core`: rays to the far rings
    cross a thin slice of the ground cells between the rings, rays through the air near the sensor whole cells."""
    shape = (200, 200, 20)
    ground_z = 1.0
    origin = np.array([[20.0, 20.0, ground_z + 1.8]])
    az = np.radians(np.arange(0.0, 360.0, 0.4))
    r, a = np.meshgrid(np.array([4.0, 6.0, 9.0, 13.0, 18.0]), az)
    pts = np.c_[20.0 + (r * np.cos(a)).ravel(), 20.0 + (r * np.sin(a)).ravel(), np.full(r.size, ground_z)]
    counts = swept(pts, origin, None, shape)
    free = observed_empty(pts, origin, None, shape)
    ground = np.zeros(shape, dtype=bool)
    ground[:, :, int(np.floor((ground_z + S) / V))] = True
    assert (free & ground).sum() > 100                        # the cell measure counts grazed ground as seen empty
    assert (counts[free & ground] < HALF).all()               # rays swept at most a slice of any ground cell
    assert (counts >= HALF).sum() > 500                       # but half or more of air cells near the sensor


def test_street_like_scene():
    """A sensor 1.8 m above flat ground and a wall: the air between is empty, the ground, the wall and the
    cells beyond the wall are not."""
    shape = (50, 50, 20)
    rng = np.random.default_rng(0)
    xy = rng.uniform(0.5, 9.0, (20000, 2))
    ground = np.c_[xy, np.full(len(xy), 1.0)]
    wall = np.c_[np.full(5000, 8.0), rng.uniform(0.5, 9.5, 5000), rng.uniform(1.0, 3.5, 5000)]
    pts = np.concatenate([ground, wall])
    origin = np.array([[5.0, 5.0, 2.8]])
    grid = observed_empty(pts, origin, None, shape)
    cell = lambda p: tuple(np.floor((np.asarray(p) + S) / V).astype(int))  # noqa: E731
    assert grid[cell([3.0, 3.0, 2.0])] and grid[cell([6.0, 6.0, 2.6])]
    assert not grid[cell([3.0, 3.0, 1.0])]     # a ground hit
    assert not grid[cell([3.0, 3.0, 1.2])]     # next to a ground hit
    assert not grid[cell([9.0, 5.0, 2.0])]     # behind the wall: never seen
    assert not grid[cell([3.0, 3.0, 0.6])]     # below the ground
    assert not grid[cell([5.0, 5.0, 3.6])]     # above the sensor: no ray went up


def test_stop_short_keeps_the_last_cells_before_a_hit():
    shape = (60, 5, 5)
    pts = np.array([[10.0, 0.5, 0.5]])
    o = np.array([[0.5, 0.5, 0.5]])
    near = observed_empty(pts, o, None, shape, stop_short=0.0)
    far = observed_empty(pts, o, None, shape, stop_short=2.0)
    x = lambda g: np.flatnonzero(g[:, 2, 2])  # noqa: E731
    assert x(near).max() == 48  # up to the cells next to the hit's cell (50)
    assert x(far).max() == 40   # 8.0 m: cell floor(8.05 / 0.2) = 40


def naive_core(free: np.ndarray) -> np.ndarray:
    out = np.zeros_like(free)
    for c in np.argwhere(free):
        nbrs = [c + d for d in np.vstack([np.eye(3, dtype=int), -np.eye(3, dtype=int)])]
        out[tuple(c)] = all(np.all((n >= 0) & (n < free.shape)) and free[tuple(n)] for n in nbrs)
    return out


def test_core_is_the_free_cells_with_six_free_neighbours():
    rng = np.random.default_rng(0)
    free = rng.random((9, 8, 7)) < 0.8
    free[2:7, 2:7, 1:6] = True
    core = confident(free)
    np.testing.assert_array_equal(core, naive_core(free))
    assert core[3:6, 3:6, 2:5].all() and 27 <= core.sum() < free.sum()
    assert not core[0].any() and not core[:, :, -1].any()     # beyond the grid is unknown


def test_grazing_rays_put_ground_in_the_free_space_but_not_in_its_core():
    """One ring scan of flat ground from 1.8 m: rays to the far rings pass a few cm over the ground between the
    rings, so true ground cells are 'seen empty' (the rim), while the core holds none of them."""
    shape = (200, 200, 20)
    ground_z = 1.0
    origin = np.array([[20.0, 20.0, ground_z + 1.8]])
    az = np.radians(np.arange(0.0, 360.0, 0.4))
    ranges = np.array([4.0, 6.0, 9.0, 13.0, 18.0])           # ring spacing growing with range, as a LiDAR's
    r, a = np.meshgrid(ranges, az)
    pts = np.c_[20.0 + (r * np.cos(a)).ravel(), 20.0 + (r * np.sin(a)).ravel(), np.full(r.size, ground_z)]
    free = observed_empty(pts, origin, None, shape)
    core = confident(free)
    gz = int(np.floor((ground_z + S) / V))                     # the ground cells' layer
    ground = np.zeros(shape, dtype=bool)
    yy, xx = np.meshgrid(np.arange(shape[1]), np.arange(shape[0]))
    ground[:, :, gz] = np.hypot(xx * V - 20.0, yy * V - 20.0) < 18.0
    assert (free & ground).sum() > 100                         # the rim holds true surface
    assert (core & ground).sum() == 0
    assert core.sum() > 1000                                   # the air near the sensor, which all rings' rays cross


def test_ray_origins():
    pts = np.zeros((4, 3))
    origins = np.array([[0, 0, 0], [1, 0, 0.0]])
    attrs = {"scan_index": np.array([0, 0, 1, 1], np.uint16)}
    np.testing.assert_array_equal(ray_origins(origins, attrs, pts), [0, 0, 1, 1])
    attrs["origin_index"] = np.array([1, 0, 1, 0], np.uint16)
    np.testing.assert_array_equal(ray_origins(origins, attrs, pts), [1, 0, 1, 0])
    np.testing.assert_array_equal(ray_origins(origins[:1], {}, pts), [0, 0, 0, 0])
    with pytest.raises(InputError, match="sensor origins"):
        ray_origins(None, {}, pts)
    with pytest.raises(InputError, match="origin_index"):
        observed_empty(pts, origins, np.array([0, 1, 2, 0]), (4, 4, 4))
