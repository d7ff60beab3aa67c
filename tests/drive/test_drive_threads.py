"""`hgca drive --threads 1` and `--threads 2` give the same tiles under the same keys (default precision), and at
a precision whose result may depend on the thread count the thread count is part of the key."""
from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys

import numpy as np

from drive_data import write_drive
from hgca_core.config import DriveConfig
from hgca_core.tiling.tile import Settings


def _settings(threads: int, precision: str | None = None) -> Settings:
    c = DriveConfig().completion
    return Settings(c if precision is None else c.with_(precision=precision), threads)


def test_thread_count_enters_the_key_only_where_it_can_change_the_result():
    assert _settings(1).keyed() == _settings(2).keyed()
    assert _settings(1, "bf16").keyed() != _settings(2, "bf16").keyed()
    assert _settings(1, "auto").keyed() != _settings(2, "auto").keyed()


def test_drive_on_1_and_2_threads_gives_the_same_tiles_and_keys(tmp_path, drive_weights):
    scans, poses = write_drive(tmp_path / "scans", length=12.0, weave=0.0)
    env = {k: v for k, v in os.environ.items() if k != "MKL_CBWR"}
    found = []
    for threads in (1, 2):
        out = tmp_path / f"t{threads}"
        subprocess.run([sys.executable, "-m", "hgca_core.cli", "drive", *map(str, scans), "--poses", str(poses),
                        "--size", "12.8", "--overlap", "3.2", "--stage", "coarse", "--t1", "3",
                        "--threads", str(threads), "--weights", str(drive_weights), "--progress", "none",
                        "-o", str(out)], env=env, check=True, capture_output=True, timeout=600)
        tiles = json.loads((out / "drive.json").read_text())["tiles"]
        meshes = [out / "drive_s0.ply", *sorted((out / "tiles").glob("*.ply"))]
        found.append(([t["key"] for t in tiles], [hashlib.sha256(p.read_bytes()).hexdigest() for p in meshes],
                      [_arrays(p) for p in sorted((out / "cache").glob("*.npz"))]))
    assert len(found[0][0]) >= 2 and len(found[0][1]) >= 3
    assert found[0][:2] == found[1][:2]
    for a, b in zip(found[0][2], found[1][2]):   # the cache entries: every array but the timing record
        assert a.keys() == b.keys() and all(np.array_equal(a[k], b[k]) for k in a)


def _arrays(path) -> dict:
    with np.load(path, allow_pickle=False) as z:
        return {k: z[k] for k in z.files if k != "meta"}
