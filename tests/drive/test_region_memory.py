"""The memory benchmark (`benchmarks/region_memory.py`) must report each child's own peak and CPU, catch a child
that ran another tree than the one named, and call old and new equal only when their meshes are."""
from __future__ import annotations

import sys
from pathlib import Path

import pytest

import hgca_core
import hgca_testdata  # noqa: F401  (puts benchmarks/ on the path)
import region_memory

ROOT = Path(hgca_core.__file__).resolve().parents[1]
# a stand-in child: touches 300 MiB, spins about 0.4 s of CPU, prints a row as the real child does
FAKE = """
import json, sys, time
import hgca_core
block = bytearray(300 * 2**20)
for i in range(0, len(block), 4096):
    block[i] = 1
t = time.process_time()
while time.process_time() - t < 0.4:
    pass
print(json.dumps({"coarse_cells": 7, "triangles": 9, "mesh_sha256": "ab", "points": 1, "stages_s": {},
                  "seconds": 0.5, "package": hgca_core.__file__}))
"""


def test_measure_reports_the_childs_own_peak_and_cpu(monkeypatch):
    monkeypatch.setattr(region_memory, "CHILD", FAKE)
    # The parent holds 1 GiB more than the child ever does: wait4's ru_maxrss would count it (the spawn records the
    # parent's resident set), the child's own high-water mark does not.
    ballast = bytearray(2**30)
    for i in range(0, len(ballast), 4096):
        ballast[i] = 1
    row = region_memory.measure(ROOT, "default", 1, sys.executable, timeout=120)
    del ballast
    assert row["exit"] == 0 and "error" not in row
    assert 300 <= row["peak_rss_mib"] < 700           # the child's 300 MiB + its interpreter, not the parent's
    assert row["cpu_s"] >= 0.35 and row["wall_s"] >= row["cpu_s"] - 0.1
    assert (row["coarse_cells"], row["triangles"], row["mesh_sha256"]) == (7, 9, "ab")


def test_measure_refuses_a_child_that_imported_another_tree(monkeypatch, tmp_path):
    monkeypatch.setattr(region_memory, "CHILD", FAKE)
    (tmp_path / "empty").mkdir()            # nothing to import there: the child falls back to the installed package
    with pytest.raises(SystemExit, match="not the tree"):
        region_memory.measure(tmp_path / "empty", "default", 1, sys.executable, timeout=120)


def _row(side: str, rss: float, sha: str) -> dict:
    return {"side": side, "region": "default", "threads": 2, "load_at_start": 1.0, "peak_rss_mib": rss,
            "cpu_s": 10.0, "wall_s": 12.0, "coarse_cells": 5, "triangles": 8, "mesh_sha256": sha}


def test_summary_pairs_runs_and_says_whether_the_meshes_agree():
    same = region_memory.summary([_row("new", 900, "x"), _row("old", 1000, "x"), _row("new", 950, "x"),
                                  _row("old", 950, "x")], {"new": "n", "old": "o"})["regions"]["default"]
    assert same["same_output"] and same["runs"] == [2, 2]
    assert same["peak_rss_mib"]["ratio"] == [0.9, 0.95, 1.0]        # pair by pair: 900/1000, 950/950
    differ = region_memory.summary([_row("new", 900, "x"), _row("old", 1000, "y")], {"new": "n", "old": "o"})
    assert not differ["regions"]["default"]["same_output"]
    assert "different outputs" in region_memory.page(differ)
