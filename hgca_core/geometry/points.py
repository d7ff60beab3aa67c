"""The one check of "finite (N, 3) points" that every entry point runs on user points before any work."""
from __future__ import annotations

import numpy as np

from hgca_core.errors import InputError


def check_points(points: np.ndarray, what: str = "input", allow_empty: bool = False) -> np.ndarray:
    """`points` as an (N, 3) float64 array, or an `InputError` naming `what` and the problem: another shape,
    no points (unless `allow_empty`), or NaN / infinite coordinates (with how many rows hold them)."""
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise InputError(f"{what}: points must be an (N, 3) array, got shape {p.shape}")
    if len(p) == 0 and not allow_empty:
        raise InputError(f"{what} is empty: there are no points")
    if not np.all(np.isfinite(p)):
        raise InputError(f"{what}: {int((~np.isfinite(p)).any(1).sum())} points have NaN or infinite coordinates")
    return p
