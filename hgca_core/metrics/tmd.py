"""Total Mutual Difference (Wu et al. 2020, used by GCA/cGCA/hGCA): diversity of k completions of one input,
the mean Chamfer distance over all k(k-1)/2 pairs. Higher = more diverse."""
from __future__ import annotations

from itertools import combinations
from typing import Sequence

import numpy as np
from hgca_core.geometry.nearest import PointIndex

from hgca_core.errors import InputError
from hgca_core.metrics.chamfer import as_points, nn_distances


def tmd(samples: Sequence[np.ndarray], empty_penalty: float | None = None) -> float:
    """2 / (k (k-1)) * sum_{i<j} CD(S_i, S_j) in metres, for k >= 2 point sets.

    Without `empty_penalty` an empty sample is an error; with it, a pair of empty samples scores 0 and a
    pair with one empty sample scores the penalty (as in `chamfer_or_penalty`). Each sample's KD-tree is
    built once and shared by its k-1 pairs.
    """
    if len(samples) < 2:
        raise InputError(f"TMD needs at least 2 samples, got {len(samples)}")
    pts = [as_points(s, f"sample {i}", allow_empty=empty_penalty is not None) for i, s in enumerate(samples)]
    trees = [PointIndex(p) if len(p) else None for p in pts]
    pair_cd = []
    for i, j in combinations(range(len(pts)), 2):
        if trees[i] is None or trees[j] is None:
            pair_cd.append(0.0 if trees[i] is None and trees[j] is None else float(empty_penalty))
        else:
            pair_cd.append(0.5 * (nn_distances(pts[i], trees[j]).mean() + nn_distances(pts[j], trees[i]).mean()))
    return float(np.mean(pair_cd))
