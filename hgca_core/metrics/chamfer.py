"""Chamfer distance as the paper reports it: the mean of the two directed mean nearest-neighbour distances.

Units are metres (the paper's tables multiply by 10; only `evaluate.format_table` does that). Empty sets
have no nearest neighbours, so the plain functions refuse them; `chamfer_or_penalty` is the variant the
evaluation uses, where an empty prediction is a legitimate (bad) outcome that must score, not crash.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from hgca_core.errors import InputError


def as_points(a: np.ndarray, name: str = "points", allow_empty: bool = False) -> np.ndarray:
    """(N, 3) float64 view of `a`, with a clear error for wrong shapes, non-finite values or emptiness."""
    p = np.asarray(a, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise InputError(f"{name} must be an (N, 3) array, got shape {p.shape}")
    if len(p) == 0 and not allow_empty:
        raise InputError(f"{name} is empty: Chamfer distance needs at least one point on each side")
    if not np.all(np.isfinite(p)):
        raise InputError(f"{name} holds non-finite coordinates")
    return p


def nn_distances(query: np.ndarray, reference: np.ndarray | cKDTree) -> np.ndarray:
    """Distance from each query point to its nearest reference point (a prebuilt tree may be passed)."""
    tree = reference if isinstance(reference, cKDTree) else cKDTree(reference)
    d, _ = tree.query(query, k=1, workers=-1)
    return d


def directed_chamfer(a: np.ndarray, b: np.ndarray) -> float:
    """Mean distance from each point of `a` to its nearest point of `b` (accuracy if a = prediction)."""
    pa, pb = as_points(a, "a"), as_points(b, "b")
    return float(nn_distances(pa, pb).mean())


def chamfer(a: np.ndarray, b: np.ndarray) -> float:
    """Symmetric Chamfer distance in metres: (directed(a, b) + directed(b, a)) / 2."""
    pa, pb = as_points(a, "a"), as_points(b, "b")
    return 0.5 * (float(nn_distances(pa, pb).mean()) + float(nn_distances(pb, pa).mean()))


def chamfer_or_penalty(a: np.ndarray, b: np.ndarray, penalty: float) -> float:
    """Chamfer distance that stays defined on empty sets.

    Both empty: 0 (they agree that nothing is there). Exactly one empty: `penalty`, the caller's documented
    stand-in for "every point of the other set is unmatched" (e.g. the sensor range for a re-simulation
    that hits nothing). Otherwise the ordinary Chamfer distance.
    """
    pa = as_points(a, "a", allow_empty=True)
    pb = as_points(b, "b", allow_empty=True)
    if len(pa) == 0 and len(pb) == 0:
        return 0.0
    if len(pa) == 0 or len(pb) == 0:
        return float(penalty)
    return chamfer(pa, pb)
