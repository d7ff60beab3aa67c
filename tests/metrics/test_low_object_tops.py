"""benchmarks/low_object_tops.py: over a 1.5 m post, an observed crown is "structure", rays that cross the space
above it to a wall beyond the region make it "seen open", and with neither it is "unseen"."""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
from low_object_tops import tops_above  # noqa: E402

SENSOR = np.array([[0.0, 0.0, 1.8]])


def scene(crown: bool, far_wall: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    g = np.arange(-18.0, 18.0, 0.1)
    ground = np.stack(np.meshgrid(g, g, indexing="ij"), -1).reshape(-1, 2)
    parts = [np.c_[ground, np.zeros(len(ground))]]
    s = np.arange(-0.1, 0.11, 0.05)
    post = np.stack(np.meshgrid(5.0 + s, s, np.arange(0.0, 1.5, 0.05), indexing="ij"), -1).reshape(-1, 3)
    parts.append(post)
    if crown:
        parts.append(np.c_[post[:, :2], np.full(len(post), 3.0)])                 # a crown 3 m up
    if far_wall:
        # hits 40 m out, 6-12 m up: their rays cross x = 5 m 2.3-3.1 m above the ground, right over the post
        z = np.arange(6.0, 12.0, 0.05)
        parts.append(np.stack(np.meshgrid([40.0], np.arange(-0.8, 0.81, 0.05), z, indexing="ij"), -1).reshape(-1, 3))
    pts = np.concatenate(parts)
    return pts, SENSOR, np.zeros(len(pts), dtype=np.int64)


def test_what_stands_over_a_post() -> None:
    crown = tops_above(*scene(crown=True, far_wall=False))
    assert crown["low_object_columns"] > 0
    assert crown["structure_above_pct"] == 100.0 and crown["seen_open_above_pct"] == 0.0
    open_ = tops_above(*scene(crown=False, far_wall=True))
    assert open_["low_object_columns"] == crown["low_object_columns"]
    assert open_["seen_open_above_pct"] == 100.0 and open_["unseen_pct"] == 0.0
    assert open_["returns_above_sensor_pct"] > 0 and open_["their_range_m_p50_p90"][0] == 40.0
    unseen = tops_above(*scene(crown=False, far_wall=False))
    assert unseen["unseen_pct"] == 100.0 and unseen["returns_above_sensor_pct"] == 0.0
    assert unseen["their_range_m_p50_p90"] is None
