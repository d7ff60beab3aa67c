"""Tiles declare their memory to Ray: a node runs no more tiles at once than fit, and a tile that fits no node is
refused up front with a clear error (rather than waiting forever)."""
import numpy as np
import pytest

import hgca_core
from drive_data import write_drive
from hgca_core.errors import InputError

SMALL = {"size": 12.8, "overlap": 3.2, "stage": "coarse", "t1": 3, "threads": 1}


def overlapping(tiles) -> int:
    spans = sorted((t["started"], t["finished"]) for t in tiles)
    return sum(b[0] < a[1] for a, b in zip(spans, spans[1:]))


@pytest.mark.slow   # several Ray workers: `make test-slow` (CI runs it)
def test_declared_memory_limits_tiles_at_once(drive_weights, tmp_path):
    ray = pytest.importorskip("ray")
    scans, poses = write_drive(tmp_path / "scans", length=30.0)
    ray.init(num_cpus=2, include_dashboard=False, object_store_memory=100 * 2**20, log_to_driver=False)
    try:
        node = max(n["Resources"]["memory"] for n in ray.nodes() if n["Alive"])
        # two workers up and warm (torch imported), so tile times, not worker start-up, decide what overlaps
        def warm_worker() -> int:          # nested: Ray ships it by value (the test module is not importable there)
            import os
            import time

            import hgca_core.pipeline  # noqa: F401

            time.sleep(2.0)
            return os.getpid()

        assert len(set(ray.get([ray.remote(warm_worker).remote() for _ in range(2)]))) == 2
        run = {"poses": poses, "weights": str(drive_weights), "workers": 2, "seams": False, **SMALL}
        narrow = hgca_core.drive(scans, tmp_path / "narrow", tile_memory=0.6 * node, **run)
        assert narrow["tile_memory"] == 0.6 * node and overlapping(narrow["tiles"]) == 0
        wide = hgca_core.drive(scans, tmp_path / "wide", tile_memory=0.1 * node, seed=1, **run)
        assert overlapping(wide["tiles"]) > 0, "with room for two, two tiles ran at once"
        with pytest.raises(InputError, match="largest Ray node offers"):
            hgca_core.drive(scans, tmp_path / "none", tile_memory=2 * node, seed=2, **run)
        assert ray.is_initialized(), "a Ray the caller started is left running"
    finally:
        ray.shutdown()
    assert len({t["key"] for t in narrow["tiles"]}) == len(narrow["tiles"]) == 3
    assert np.all([t["status"] == "done" for t in narrow["tiles"] + wide["tiles"]])
