"""Observed free space: the cells a LiDAR's rays passed through before they hit something.

A ray from the sensor to a return proves the space it crossed empty (the beam went through). We walk every
ray from its sensor origin to `stop_short` metres before its hit over the region's 20 cm grid, exactly (every
cell the segment enters, Amanatides-Woo style), and drop cells next to any hit (26-neighbourhood), since a
grazing ray near a surface says little about the surface's own cell. Geometry in these cells contradicts a
ray, yet a ray that crossed only part of a cell (over the ground between rings, through a porous crown)
leaves room for a surface in the rest: on synthetic single sweeps 80 % of the completion cells found there
are true (`benchmarks/results/freespace_calibration.md`, in git at 7f06b18). `swept` says how much of each cell the rays crossed,
walking the same rays over 5 cm sub-cells. The model reads the free space as an input and `hgca eval-real`
scores with it, so it is vectorised: every boundary crossing of every ray is one array element, and each
crossing names the cell it enters on its own (no sort), marked in a dense grid.

Cells follow the project's voxeliser (`hgca_core.geometry.voxel`): a 20 cm cell c holds region-frame points
p with floor((p + 0.05) / 0.2) = c, i.e. points that round to the 10 cm cells 2c and 2c + 1.
"""
from __future__ import annotations

import numpy as np

from hgca_core.errors import InputError
from hgca_core.geometry.voxel import COARSE, lower_corner, voxelize

STOP_SHORT = 0.4      # metres before the hit where a ray stops proving emptiness
SUB = 4               # `swept`: 5 cm sub-cells, 64 to a 20 cm cell
HALF = SUB ** 3 // 2  # `swept` counts from which rays crossed at least half a cell
SHIFT = -lower_corner(COARSE)  # 20 cm cell c spans [c * 0.2 - 0.05, c * 0.2 + 0.15)
CHUNK_EVENTS = 8_000_000  # crossings per chunk: bounds memory at a few hundred MB


def ray_origins(origins: np.ndarray | None, attributes: dict[str, np.ndarray], points: np.ndarray) -> np.ndarray:
    """(N,) index into `origins` of each point's sensor: `origin_index` when the reader gave it, else the
    scan's origin (`scan_index`, one origin per scan), else the only origin, else the nearest one."""
    if origins is None or len(origins) == 0:
        raise InputError("observed free space needs the sensor origins, and these scans have none")
    n = len(points)
    if "origin_index" in attributes and int(attributes["origin_index"].max()) < len(origins):
        return attributes["origin_index"].astype(np.int64)
    if len(origins) == 1:
        return np.zeros(n, dtype=np.int64)
    if "scan_index" in attributes and int(attributes["scan_index"].max()) + 1 == len(origins):
        return attributes["scan_index"].astype(np.int64)
    from hgca_core.geometry.nearest import PointIndex

    return PointIndex(origins).nearest(points)[1]


def _clip(o: np.ndarray, e: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Segments o->e clipped to the box [lo, hi] (slab method): (start, end, keep)."""
    d = e - o
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / d
        t0 = (lo - o) * inv
        t1 = (hi - o) * inv
    tmin = np.where(d == 0, -np.inf, np.minimum(t0, t1))
    tmax = np.where(d == 0, np.inf, np.maximum(t0, t1))
    inside_flat = (d != 0) | ((o >= lo) & (o <= hi))
    enter = np.maximum(tmin.max(axis=1), 0.0)
    leave = np.minimum(tmax.min(axis=1), 1.0)
    keep = inside_flat.all(axis=1) & (enter < leave)
    return o + enter[:, None] * d, o + leave[:, None] * d, keep


def _cell(p: np.ndarray, size: float = COARSE) -> np.ndarray:
    return np.floor((p + SHIFT) / size).astype(np.int64)


def _mark_crossings(start: np.ndarray, end: np.ndarray, grid: np.ndarray, size: float = COARSE) -> None:
    """Mark in `grid` every cell the segments start->end touch: their start cells and, for every crossing
    of a cell boundary plane, the cell entered there.

    Along a ray the k-th crossing of axis a's planes is at t_k = t_0 + k dt, so the entered cell's other
    two coordinates are floor(C + k E) with per-ray C, E: a few per-ray numbers repeated per crossing, no
    sort. The segments lie inside the grid (clipped by the caller); indices are clamped to it only against
    rounding at its faces. `size`: the grid's cell (any size whose cells nest in the 20 cm ones: 20 / n cm)."""
    shape = np.asarray(grid.shape)
    flat = grid.reshape(-1)
    strides = (int(shape[1] * shape[2]), int(shape[2]), 1)
    top = shape - 1

    s_cell, e_cell = _cell(start, size), _cell(end, size)
    first = np.clip(s_cell, 0, top)
    flat[first[:, 0] * strides[0] + first[:, 1] * strides[1] + first[:, 2]] = True
    d = end - start
    for axis in range(3):
        n = np.abs(e_cell[:, axis] - s_cell[:, axis])
        rays = np.flatnonzero(n)
        if len(rays) == 0:
            continue
        counts = n[rays]
        k = np.arange(int(counts.sum()), dtype=np.float64)
        k -= np.repeat((np.cumsum(counts) - counts).astype(np.float64), counts)  # 0..n-1 per ray
        da = d[rays, axis]
        step = np.sign(da)
        entered0 = s_cell[rays, axis] + step
        t0 = (np.where(step > 0, entered0, entered0 + 1) * size - SHIFT - start[rays, axis]) / da
        dt = size / np.abs(da)
        index = np.repeat(entered0 * strides[axis], counts) + k * np.repeat(step * strides[axis], counts)
        for b in range(3):
            if b == axis:
                continue
            db = d[rays, b] / size
            c = np.repeat((start[rays, b] + SHIFT) / size + t0 * db, counts)
            c += k * np.repeat(dt * db, counts)
            np.floor(c, out=c)
            np.clip(c, 0, top[b], out=c)
            c *= strides[b]
            index += c
        flat[index.astype(np.int64)] = True


def _rays(points: np.ndarray, origins: np.ndarray, origin_index: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """(hits (N, 3), each hit's origin (N, 3)), the origin index checked."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    org = np.asarray(origins, dtype=np.float64).reshape(-1, 3)
    idx = np.zeros(len(pts), dtype=np.int64) if origin_index is None else np.asarray(origin_index, np.int64)
    if len(idx) != len(pts) or (len(idx) and (idx.min() < 0 or idx.max() >= len(org))):
        raise InputError(f"origin_index must name one of {len(org)} origins for each of {len(pts)} points")
    return pts, org[idx]


def default_workers() -> int:
    """Threads for the ray walk: torch's thread count where torch is loaded (the pipeline's, so a Ray worker with one
    thread per tile stays on its core), else 1."""
    import sys

    torch = sys.modules.get("torch")
    return max(1, int(torch.get_num_threads())) if torch is not None else 1


def _walk(pts: np.ndarray, o: np.ndarray, shape: tuple[int, ...], size: float, stop_short: float,
          workers: int = 1) -> np.ndarray:
    """Dense bool grid of `size` cells (covering the 20 cm grid `shape`) every ray o -> pts touches until
    `stop_short` metres before its hit. Chunks of rays are marked by `workers` threads side by side (numpy's
    kernels release the GIL; every thread only sets cells True, so the grid is the same whatever the count), each
    chunk at most CHUNK_EVENTS / workers crossings, so the memory in flight stays that of one thread."""
    n = int(round(COARSE / size))
    fine = tuple(int(v) * n for v in shape)
    grid = np.zeros(fine, dtype=bool)
    ray = pts - o
    length = np.linalg.norm(ray, axis=1)
    far = length > stop_short
    o, pts_far, ray, length = o[far], pts[far], ray[far], length[far]
    end = pts_far - ray * (stop_short / length)[:, None]
    lo = np.full(3, -SHIFT + 1e-9)
    hi = np.asarray(shape) * COARSE - SHIFT - 1e-9
    start, end, keep = _clip(o, end, lo, hi)
    start, end = start[keep], end[keep]
    if len(start):
        cum = np.cumsum(np.abs(_cell(end, size) - _cell(start, size)).sum(axis=1) + 1)
        per = max(1, min(CHUNK_EVENTS // workers, -(-int(cum[-1]) // workers)))   # >= `workers` chunks
        cuts = np.searchsorted(cum, np.arange(per, cum[-1], per))
        spans = [(a, b) for a, b in zip(np.r_[0, cuts], np.r_[cuts, len(start)]) if b > a]
        if workers > 1 and len(spans) > 1:
            from concurrent.futures import ThreadPoolExecutor

            with ThreadPoolExecutor(workers) as pool:
                list(pool.map(lambda ab: _mark_crossings(start[ab[0]:ab[1]], end[ab[0]:ab[1]], grid, size), spans))
        else:
            for a, b in spans:
                _mark_crossings(start[a:b], end[a:b], grid, size)
    return grid


def observed_empty(points: np.ndarray, origins: np.ndarray, origin_index: np.ndarray | None,
                   grid_shape: tuple[int, int, int], stop_short: float = STOP_SHORT,
                   workers: int | None = None) -> np.ndarray:
    """Dense bool grid (20 cm cells, region frame) of cells observed empty.

    `points` (N, 3) are hits and `origins` (S, 3) sensor positions, both in the region frame;
    `origin_index` (N,) names each point's origin (None: all from origins[0]). Every hit in `points` counts
    for the "next to a hit" rule, inside the region or not. `workers`: threads of the walk (default
    `default_workers()`); the grid does not depend on it.
    """
    pts, o = _rays(points, origins, origin_index)
    shape = tuple(int(v) for v in grid_shape)
    workers = default_workers() if workers is None else max(1, int(workers))
    return _walk(pts, o, shape, COARSE, stop_short, workers) & ~dense(voxelize(pts, COARSE), shape, dilate=1)


def swept(points: np.ndarray, origins: np.ndarray, origin_index: np.ndarray | None,
          grid_shape: tuple[int, int, int], sub: int = SUB, stop_short: float = STOP_SHORT) -> np.ndarray:
    """(X, Y, Z) uint8 grid: per 20 cm cell, how many of its sub^3 sub-cells (20 / sub cm) the rays crossed
    (arguments as `observed_empty`; cells next to a hit count 0, as there).

    Why: a completion cell says "surface somewhere in these 20 cm". A ray through the cell disproves that only
    where it passed; a ray grazing a ground cell's top leaves its bottom unseen, which is why a perfect
    completion of a single sweep puts 1-14 % of its cells in `observed_empty` and 0-1.5 % in cells swept half
    (`benchmarks/results/freespace_floor_val64.md`, in git at 7f06b18). The more
    of a cell's volume the rays swept, the less room is left for a surface in it: `swept(...) >= sub ** 3 // 2`
    asks that rays crossed at least half of it (`HALF`)."""
    if not 1 <= sub <= 6:
        raise ValueError("sub must be 1..6 (sub-cells of 20 / sub cm; at most 216 to a cell, one uint8)")
    pts, o = _rays(points, origins, origin_index)
    shape = tuple(int(v) for v in grid_shape)
    fine = _walk(pts, o, shape, COARSE / sub, stop_short)
    counts = fine.reshape(shape[0], sub, shape[1], sub, shape[2], sub).sum(axis=(1, 3, 5), dtype=np.int64)
    counts[dense(voxelize(pts, COARSE), shape, dilate=1)] = 0
    return counts.astype(np.uint8)


def confident(free: np.ndarray) -> np.ndarray:
    """The core of the free space: seen-empty cells whose six face neighbours are seen empty too (cells outside
    the grid count as unknown).

    Why: the free space's one-cell rim is where rays pass just over a surface without hitting it: the top of
    ground cells between LiDAR rings at grazing angles, glass, porous crowns. On 16 synth2 val scenes 0.9 to 10 %
    (mean 4.6 %) of the true cells a perfect completion of one sweep would add lie in its free space, at most
    0.14 % in the core (`benchmarks/results/freespace_floor.md`, in git at 7f06b18): forbidding the core costs true geometry almost
    nothing, forbidding the whole free space does."""
    g = np.asarray(free, dtype=bool)
    core = g.copy()
    for axis in range(g.ndim):
        lo, hi = [slice(None)] * g.ndim, [slice(None)] * g.ndim
        lo[axis], hi[axis] = slice(None, -1), slice(1, None)
        core[tuple(lo)] &= g[tuple(hi)]
        core[tuple(hi)] &= g[tuple(lo)]
        edge = [slice(None)] * g.ndim
        for end in (0, -1):
            edge[axis] = end
            core[tuple(edge)] = False
    return core


def dense(cells: np.ndarray, shape: tuple[int, int, int], dilate: int = 0) -> np.ndarray:
    """Bool grid of `cells` (those outside `shape` dropped), grown by `dilate` cells in every direction
    (a (2 dilate + 1)^3 box: 26-neighbourhood for 1). Cells just outside the grid still grow into it."""
    c = np.asarray(cells, dtype=np.int64).reshape(-1, 3)
    shp = np.asarray(shape)
    c = c[np.all((c >= -dilate) & (c < shp + dilate), axis=1)] + dilate
    grid = np.zeros(tuple(shp + 2 * dilate), dtype=bool)
    grid[c[:, 0], c[:, 1], c[:, 2]] = True
    for _ in range(dilate):
        for axis in range(3):
            grown = grid.copy()
            a, b = [slice(None)] * 3, [slice(None)] * 3
            a[axis], b[axis] = slice(1, None), slice(None, -1)
            grown[tuple(a)] |= grid[tuple(b)]
            grown[tuple(b)] |= grid[tuple(a)]
            grid = grown
    inner = tuple(slice(dilate, dilate + int(n)) for n in shp)
    return np.ascontiguousarray(grid[inner])
