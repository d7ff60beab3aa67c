"""Voxelisation exactly as the paper's appendix says: round to 10 cm cells, floor those to 20 cm cells."""
from __future__ import annotations

import numpy as np

FINE = 0.1    # metres, cGCA / upsampling resolution
COARSE = 0.2  # metres, GCA / coarse resolution


def voxelize_fine(local: np.ndarray, grid_shape: tuple[int, int, int]) -> np.ndarray:
    """Unique 10 cm cells (int32, (N, 3)) of region-frame points, by rounding; cells outside the grid dropped."""
    c = np.round(np.asarray(local, dtype=np.float64) / FINE).astype(np.int64)
    keep = np.all((c >= 0) & (c < np.asarray(grid_shape)), axis=1)
    return unique_rows(c[keep]).astype(np.int32)


def downsample(coords: np.ndarray, factor: int = 2) -> np.ndarray:
    """Parent cells by flooring (10 cm -> 20 cm for factor 2)."""
    return unique_rows(np.floor_divide(np.asarray(coords, dtype=np.int64), factor)).astype(np.int32)


def voxelize_coarse(local: np.ndarray, fine_shape: tuple[int, int, int]) -> np.ndarray:
    """Unique 20 cm cells: the 10 cm cells floored, as the paper does (not a direct floor of the points)."""
    return downsample(voxelize_fine(local, fine_shape), 2)


def cell_centers(coords: np.ndarray, voxel: float) -> np.ndarray:
    """Region-frame centres of cells. A 10 cm cell c holds points rounding to c, so its centre is c * 0.1;
    a 20 cm cell holds 10 cm cells 2c and 2c+1, so its centre is (2c + 0.5) * 0.1 = (c + 0.25) * 0.2."""
    c = np.asarray(coords, dtype=np.float64)
    return c * FINE if voxel == FINE else (2 * c + 0.5) * FINE


def unique_rows(a: np.ndarray) -> np.ndarray:
    """Row-unique integer array, sorted lexicographically."""
    if len(a) == 0:
        return np.zeros((0, a.shape[1] if a.ndim == 2 else 3), dtype=np.int64)
    return np.unique(a, axis=0)
