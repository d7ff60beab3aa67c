"""Street CD (paper, Sec. 4 and App. "Evaluation Metric"): Chamfer distance on the objects standing on the
main street only, ground removed by a 20 cm height threshold. It is the one metric that sees geometry no
street-level sensor pose can observe, such as the sidewalk side of parked cars.
"""
from __future__ import annotations

from typing import Sequence

import numpy as np

from hgca_core.errors import InputError
from hgca_core.geometry.region import ground_at
from hgca_core.metrics.chamfer import as_points, chamfer_or_penalty

GROUND_MARGIN = 0.2  # metres above ground_z that still count as ground (paper: "thresholding ... with 20cm")


def street_points(points: np.ndarray, street_box: Sequence[float] | np.ndarray, ground_z: float,
                  ground_margin: float = GROUND_MARGIN, ground_grid: np.ndarray | None = None) -> np.ndarray:
    """Points inside the street box (x/y: xmin <= x < xmax, ymin <= y < ymax) and above the ground + margin:
    ground_z, or with `ground_grid` (a sample's `ground_height`) the ground under each point (sloped streets)."""
    p = as_points(points, "points", allow_empty=True)
    b = np.asarray(street_box, dtype=np.float64).reshape(-1)
    if b.shape != (4,) or not (b[0] < b[2] and b[1] < b[3]):
        raise InputError(f"street_box must be (xmin, ymin, xmax, ymax) with min < max, got {b.tolist()}")
    ground = float(ground_z) if ground_grid is None else ground_at(ground_grid, p[:, :2])
    keep = ((p[:, 0] >= b[0]) & (p[:, 0] < b[2]) & (p[:, 1] >= b[1]) & (p[:, 1] < b[3])
            & (p[:, 2] > ground + ground_margin))
    return p[keep]


def street_penalty(street_box: Sequence[float] | np.ndarray) -> float:
    """Score for a side with no object points while the other has some: the box's x/y diagonal, the
    farthest two points on the street can be apart horizontally."""
    b = np.asarray(street_box, dtype=np.float64).reshape(-1)
    return float(np.hypot(b[2] - b[0], b[3] - b[1]))


def street_cd(pred_points: np.ndarray, gt_surface: np.ndarray, street_box: Sequence[float] | np.ndarray,
              ground_z: float, ground_margin: float = GROUND_MARGIN, empty_penalty: float | None = None,
              ground_grid: np.ndarray | None = None) -> float:
    """Chamfer distance (metres) between predicted and ground-truth points on the street above the ground.

    Both sides empty after filtering -> 0; one side empty -> `empty_penalty` (default: `street_penalty`).
    """
    a = street_points(pred_points, street_box, ground_z, ground_margin, ground_grid)
    b = street_points(gt_surface, street_box, ground_z, ground_margin, ground_grid)
    pen = street_penalty(street_box) if empty_penalty is None else empty_penalty
    return chamfer_or_penalty(a, b, pen)
