"""Least-squares planes z = a x + b y + c of many groups of points at once (vectorised normal equations).

One fit serves the ground fairing's local slopes (`hgca_core.meshing.fairing`) and the flatness benchmark's
per-patch residuals and reference planes (`hgca_core.metrics.flatness`). Sums are taken about each group's
(weighted) centroid, so heights of hundreds of metres (georeferenced frames) lose no precision.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class Planes:
    """Per group: centroid (G, 3), slope (G, 2) = (a, b), total weight (G,), the centred second moments of x and
    y (sxx, syy) and the determinant of the 2 x 2 system (det; ~0: the points are collinear, no plane), and the
    weighted residual sum of squares of z about the plane (rss)."""

    centroid: np.ndarray
    slope: np.ndarray
    weight: np.ndarray
    sxx: np.ndarray
    syy: np.ndarray
    det: np.ndarray
    rss: np.ndarray

    def height(self, group: np.ndarray, xy: np.ndarray) -> np.ndarray:
        """The plane of each point's group evaluated at its x, y."""
        c = self.centroid[group]
        return c[:, 2] + np.einsum("ij,ij->i", self.slope[group], np.asarray(xy)[:, :2] - c[:, :2])


def fit_planes(points: np.ndarray, group: np.ndarray, n_groups: int, weight: np.ndarray | None = None) -> Planes:
    """Planes of the points (N, 3) of each group (N,) in range(n_groups), optionally weighted (N,). Degenerate
    groups (fewer than 3 points, collinear, or empty) get slope 0; check `det` and `weight` before trusting one."""
    p = np.asarray(points, dtype=np.float64)
    g = np.asarray(group)
    w = np.ones(len(p)) if weight is None else np.asarray(weight, dtype=np.float64)

    def s(x: np.ndarray) -> np.ndarray:
        return np.bincount(g, weights=w * x, minlength=n_groups)

    total = np.bincount(g, weights=w, minlength=n_groups)
    centroid = np.stack([s(p[:, a]) for a in range(3)], 1) / np.maximum(total, 1e-300)[:, None]
    q = p - centroid[g]
    x, y, z = q[:, 0], q[:, 1], q[:, 2]
    sxx, sxy, syy, sxz, syz, szz = s(x * x), s(x * y), s(y * y), s(x * z), s(y * z), s(z * z)
    det = sxx * syy - sxy * sxy
    solvable = det > 1e-300
    d = np.where(solvable, det, 1.0)
    a = np.where(solvable, (sxz * syy - syz * sxy) / d, 0.0)
    b = np.where(solvable, (syz * sxx - sxz * sxy) / d, 0.0)
    rss = np.maximum(szz - 2 * a * sxz - 2 * b * syz + a * a * sxx + 2 * a * b * sxy + b * b * syy, 0.0)
    return Planes(centroid, np.c_[a, b], total, sxx, syy, det, rss)
