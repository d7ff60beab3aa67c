"""Voxel IoU at 20 cm over the cells the evaluation LiDAR can see (paper, App. "Evaluation Metric", IoU).

Cells are integer (N, 3) coordinates. Sets are compared through one packed int64 key per cell, so every
operation is a sort / `np.isin` over 1-D arrays rather than row-wise comparisons.
"""
from __future__ import annotations

import numpy as np

from hgca_core.errors import InputError
from hgca_core.geometry.keys import check_range, pack


def pack_cells(cells: np.ndarray, name: str = "cells") -> np.ndarray:
    """Unique sorted keys (`hgca_core.geometry.keys.pack`) of (N, 3) integer cells, with a clear error for a
    wrong shape, non-integer values or coordinates a key cannot hold."""
    c = np.asarray(cells)
    if c.ndim != 2 or c.shape[1] != 3:
        raise InputError(f"{name} must be an (N, 3) integer array, got shape {c.shape}")
    if c.size and not np.issubdtype(c.dtype, np.integer):
        if not np.all(c == np.round(c)):
            raise InputError(f"{name} must hold integer cell coordinates")
    c = c.astype(np.int64)
    check_range(c, name)
    return np.unique(pack(c))


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
