"""Chamfer distance as the paper reports it: the mean of the two directed mean nearest-neighbour distances.

Units are metres (the paper's tables multiply by 10; only `evaluate.format_table` does that). Empty sets
have no nearest neighbours, so the plain functions refuse them; `chamfer_or_penalty` is the variant the
evaluation uses, where an empty prediction is a legitimate (bad) outcome that must score, not crash.
"""
from __future__ import annotations

import numpy as np

from hgca_core.geometry.nearest import PointIndex
from hgca_core.geometry.points import check_points


def as_points(a: np.ndarray, name: str = "points", allow_empty: bool = False) -> np.ndarray:
    """(N, 3) float64 view of `a` (`geometry.points.check_points`: wrong shapes, non-finite values, emptiness)."""
    return check_points(a, name, allow_empty)


def nn_distances(query: np.ndarray, reference: np.ndarray | PointIndex) -> np.ndarray:
    """Distance from each query point to its nearest reference point (a prebuilt index may be passed)."""
    index = reference if isinstance(reference, PointIndex) else PointIndex(reference)
    return index.distances(query)


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
