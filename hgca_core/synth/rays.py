"""The input rays of a synthetic sample: every hit its scans returned, inside the region and beyond it.

Why: a real scan holds every return, and `hgca complete` walks the free space along all of them: rays that cross the
region to hit a facade or a tree 40 m out mark the space above cars and between facades as seen empty. Samples up to
format 2 kept only the hits inside the region, so the free space the coarse model trained on lacked those rays (over
low objects the space above was seen open in 26 % of synthetic columns against 37-71 % on the real inputs:
benchmarks/results/low_object_tops.md in git at 7f06b18). From format 3 a sample also stores the hits beyond the region
(`input_far_points`, `input_far_scan_index`); this module is the one place that joins them. Numpy only: the trainer
imports it on machines without the scene generator's dependencies.
"""
from __future__ import annotations

from collections.abc import Mapping

import numpy as np


def input_rays(sample: Mapping, scan: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(points (N, 3) float64 in the region frame, each point's scan index (N,) int64): the hits inside the region
    (`input_points`, first) then those beyond it (format 3 on; absent from older samples). With `scan`, only that
    scan's. `sample` is a dict of arrays or an open `np.load` file."""
    parts = [("input_points", "input_scan_index")]
    if "input_far_points" in sample:
        parts.append(("input_far_points", "input_far_scan_index"))
    points = np.concatenate([np.asarray(sample[p], dtype=np.float64).reshape(-1, 3) for p, _ in parts])
    index = np.concatenate([np.asarray(sample[i], dtype=np.int64).reshape(-1) for _, i in parts])
    if scan is not None:
        keep = index == scan
        points, index = points[keep], index[keep]
    return points, index
