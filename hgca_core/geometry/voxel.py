"""Voxelisation exactly as the paper's appendix says: round to 10 cm cells, floor those to 20 cm cells.

`voxelize` is the project's only point -> cell conversion (pipeline, training data, ground truth, metrics and
baselines all call it), so the input the model sees, the ground truth it is scored against and the baselines
beside it are cut the same way.
"""
from __future__ import annotations

from typing import Sequence

import numpy as np

from hgca_core.errors import InputError
from hgca_core.geometry.keys import unique_rows

FINE = 0.1    # metres, cGCA / upsampling resolution
COARSE = 0.2  # metres, GCA / coarse resolution
# Bounded grids up to this many cells are marked in a dense boolean array (64 MB at most) instead of sorting
# keys: `argwhere` returns the cells unique and sorted, ~10x faster than a sort for millions of points.
DENSE_CELLS = 1 << 26


def grid_shape(size: Sequence[float] | np.ndarray, voxel: float) -> tuple[int, int, int]:
    """Cells of `voxel` metres along each axis of a region of `size` metres (rounded to whole cells)."""
    n = np.round(np.asarray(size, dtype=np.float64).reshape(3) / voxel).astype(int)
    return int(n[0]), int(n[1]), int(n[2])


def _factor(voxel: float) -> int:
    if np.isclose(voxel, FINE):
        return 1
    if np.isclose(voxel, COARSE):
        return 2
    raise InputError(f"voxel must be {FINE} or {COARSE} m (the model's two resolutions), got {voxel}")


def point_cells(local: np.ndarray, voxel: float = COARSE) -> np.ndarray:
    """The cell (int64 (N, 3)) of each region-frame point, one row per point: the 10 cm cell by rounding,
    the 20 cm cell by flooring that 10 cm cell (not by flooring the point)."""
    c = np.round(np.asarray(local, dtype=np.float64).reshape(-1, 3) / FINE).astype(np.int64)
    return c if _factor(voxel) == 1 else np.floor_divide(c, 2)


def voxelize(local: np.ndarray, voxel: float = COARSE,
             region_size: Sequence[float] | np.ndarray | None = None) -> np.ndarray:
    """Unique cells (int64 (M, 3), sorted lexicographically) of region-frame points, by `point_cells`.

    With `region_size` (metres), 10 cm cells outside the region's 10 cm grid [0, grid_shape(size, 0.1)) are
    dropped before flooring, so a region's 20 cm cells are made of its own 10 cm cells (an odd 10 cm grid
    keeps a half-filled last 20 cm layer). Without it nothing is dropped.
    """
    factor = _factor(voxel)
    c = point_cells(local, FINE)
    if region_size is None:
        return unique_rows(np.floor_divide(c, factor))
    fine = np.asarray(grid_shape(region_size, FINE))
    c = c[np.all((c >= 0) & (c < fine), axis=1)] // factor
    shape = (fine + factor - 1) // factor
    if int(np.prod(shape)) > DENSE_CELLS:
        return unique_rows(c)
    occ = np.zeros(tuple(shape), dtype=bool)
    occ[c[:, 0], c[:, 1], c[:, 2]] = True
    return np.argwhere(occ).astype(np.int64)


def downsample(coords: np.ndarray, factor: int = 2) -> np.ndarray:
    """Parent cells (int64, unique, sorted) by flooring (10 cm -> 20 cm for factor 2)."""
    return unique_rows(np.floor_divide(np.asarray(coords, dtype=np.int64), factor))


def column_tops(occ: np.ndarray) -> np.ndarray:
    """(X, Y) int: the z index of the highest occupied cell of each column of a dense (X, Y, Z) bool grid, -1 where
    the column is empty."""
    return np.where(occ.any(axis=2), occ.shape[2] - 1 - np.argmax(occ[:, :, ::-1], axis=2), -1)


def cell_centers(coords: np.ndarray, voxel: float) -> np.ndarray:
    """Region-frame centres of cells. A 10 cm cell c holds points rounding to c, so its centre is c * 0.1;
    a 20 cm cell holds 10 cm cells 2c and 2c+1, so its centre is (2c + 0.5) * 0.1 = (c + 0.25) * 0.2."""
    c = np.asarray(coords, dtype=np.float64)
    return c * FINE if _factor(voxel) == 1 else (2 * c + 0.5) * FINE


def lower_corner(voxel: float) -> float:
    """Where cell 0's box starts on each axis (cell c spans [corner + c * voxel, corner + (c + 1) * voxel)):
    -5 cm for both resolutions, since 10 cm cells are centred on multiples of 10 cm."""
    return float(cell_centers(np.zeros(1), voxel)[0]) - voxel / 2
