"""The real sweeps of tests/data/real as plain arrays for the sensor-profile tests: tests/builders.py's readers
(one copy, which benchmarks/sensor_profiles.py uses too), with a missing file skipping the test, except under CI,
where it fails it (`hgca_testdata.require_real`)."""
from __future__ import annotations

import pytest

import builders
from builders import Sweep, elevations
from hgca_testdata import require_real

__all__ = ["Sweep", "av2_sweeps", "elevations", "nuscenes_sweep"]


def nuscenes_sweep(min_range: float = 2.5) -> Sweep:
    """The nuScenes LIDAR_TOP sweep's returns beyond `min_range` (see builders.nuscenes_sweep)."""
    return builders.nuscenes_sweep(min_range, need=require_real)


def av2_sweeps() -> list[Sweep]:
    """The three AV2 sweeps in the ego frame (see builders.av2_sweeps); a skip without pyarrow."""
    pytest.importorskip("pyarrow.feather")
    return builders.av2_sweeps(need=require_real)
