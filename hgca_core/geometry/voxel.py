"""Voxelisation exactly as the paper's appendix says: round to 10 cm cells, floor those to 20 cm cells."""
from __future__ import annotations

import numpy as np

from hgca_core.errors import InputError

FINE = 0.1    # metres, cGCA / upsampling resolution
COARSE = 0.2  # metres, GCA / coarse resolution


def voxelize_fine(local: np.ndarray, grid_shape: tuple[int, int, int] | None) -> np.ndarray:
    """Unique 10 cm cells (int32, (N, 3)) of region-frame points, by rounding; cells outside the grid dropped
    (no bounds when grid_shape is None)."""
    c = np.round(np.asarray(local, dtype=np.float64).reshape(-1, 3) / FINE).astype(np.int64)
    if grid_shape is not None:
        c = c[np.all((c >= 0) & (c < np.asarray(grid_shape)), axis=1)]
    return unique_rows(c).astype(np.int32)


def downsample(coords: np.ndarray, factor: int = 2) -> np.ndarray:
    """Parent cells by flooring (10 cm -> 20 cm for factor 2)."""
    return unique_rows(np.floor_divide(np.asarray(coords, dtype=np.int64), factor)).astype(np.int32)


def voxelize_coarse(local: np.ndarray, fine_shape: tuple[int, int, int] | None) -> np.ndarray:
    """Unique 20 cm cells: the 10 cm cells floored, as the paper does (not a direct floor of the points)."""
    return downsample(voxelize_fine(local, fine_shape), 2)


def cell_centers(coords: np.ndarray, voxel: float) -> np.ndarray:
    """Region-frame centres of cells. A 10 cm cell c holds points rounding to c, so its centre is c * 0.1;
    a 20 cm cell holds 10 cm cells 2c and 2c+1, so its centre is (2c + 0.5) * 0.1 = (c + 0.25) * 0.2."""
    c = np.asarray(coords, dtype=np.float64)
    return c * FINE if voxel == FINE else (2 * c + 0.5) * FINE


_BITS, _OFF = 21, 1 << 20  # packed keys: each axis in [-2**20, 2**20) cells (+-100 km at 10 cm)


def unique_rows(a: np.ndarray) -> np.ndarray:
    """Row-unique (N, 3) integer array, sorted lexicographically, via 1-D packed keys (np.unique(axis=0)
    is many times slower on millions of rows)."""
    a = np.asarray(a, dtype=np.int64).reshape(-1, 3)
    if len(a) == 0:
        return np.zeros((0, 3), dtype=np.int64)
    if a.min() < -_OFF or a.max() >= _OFF:
        raise InputError(f"cell coordinates must lie in [-{_OFF}, {_OFF}) (points too far from the region)")
    u = a + _OFF
    keys = np.unique((u[:, 0] << (2 * _BITS)) | (u[:, 1] << _BITS) | u[:, 2])
    mask = (1 << _BITS) - 1
    return np.stack([keys >> (2 * _BITS), (keys >> _BITS) & mask, keys & mask], axis=1) - _OFF
