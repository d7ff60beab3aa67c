"""Voxel IoU at 20 cm over the cells the evaluation LiDAR can see (paper, App. "Evaluation Metric", IoU).

Cells are integer (N, 3) coordinates. Sets are compared through one packed int64 key per cell, so every
operation is a sort / `np.isin` over 1-D arrays rather than row-wise comparisons.
"""
from __future__ import annotations

import numpy as np

from hgca_core.errors import InputError
from hgca_core.geometry.voxel import FINE, voxelize_coarse

_BITS = 21
_OFF = 1 << (_BITS - 1)
_MASK = (1 << _BITS) - 1


def pack_cells(cells: np.ndarray, name: str = "cells") -> np.ndarray:
    """Unique sorted int64 keys of (N, 3) integer cells (each axis must lie in [-2**20, 2**20))."""
    c = np.asarray(cells)
    if c.ndim != 2 or c.shape[1] != 3:
        raise InputError(f"{name} must be an (N, 3) integer array, got shape {c.shape}")
    if c.size and not np.issubdtype(c.dtype, np.integer):
        if not np.all(c == np.round(c)):
            raise InputError(f"{name} must hold integer cell coordinates")
    c = c.astype(np.int64)
    if c.size and (c.min() < -_OFF or c.max() >= _OFF):
        raise InputError(f"{name} has coordinates outside [-{_OFF}, {_OFF})")
    keys = ((c[:, 0] + _OFF) << (2 * _BITS)) | ((c[:, 1] + _OFF) << _BITS) | (c[:, 2] + _OFF)
    return np.unique(keys)


def unpack_cells(keys: np.ndarray) -> np.ndarray:
    """Inverse of `pack_cells`: (N,) keys -> (N, 3) int64 cells."""
    k = np.asarray(keys, dtype=np.int64)
    return np.stack([((k >> (2 * _BITS)) & _MASK) - _OFF, ((k >> _BITS) & _MASK) - _OFF, (k & _MASK) - _OFF], 1)


def iou(pred: np.ndarray, gt: np.ndarray, visible: np.ndarray | None = None) -> float:
    """|P ∩ G ∩ V| / |(P ∪ G) ∩ V|, or plain |P ∩ G| / |P ∪ G| without a visibility set.

    Restricting to V (cells the high LiDAR sees in the ground truth) keeps building interiors, which no
    street sensor can check, out of the score. Returns NaN when the denominator is empty (nothing to
    compare); callers average with `np.nanmean`.
    """
    kp, kg = pack_cells(pred, "pred"), pack_cells(gt, "gt")
    if visible is not None:
        kv = pack_cells(visible, "visible")
        kp, kg = kp[np.isin(kp, kv, assume_unique=True)], kg[np.isin(kg, kv, assume_unique=True)]
    inter = np.intersect1d(kp, kg, assume_unique=True).size
    union = kp.size + kg.size - inter
    return float("nan") if union == 0 else inter / union


def points_to_cells20(points: np.ndarray, region_size: np.ndarray | None = None) -> np.ndarray:
    """Unique 20 cm cells of region-frame points, the paper's way: round to 10 cm, then floor by 2.

    Same cells as `hgca_core.geometry.voxel.voxelize_coarse` (cells outside the region dropped when
    `region_size` is given) but through 1-D packed keys, which is much faster for millions of points.
    """
    fine = None if region_size is None else tuple(np.round(np.asarray(region_size, float) / FINE).astype(int))
    return voxelize_coarse(np.asarray(points, dtype=np.float64), fine).astype(np.int64)
