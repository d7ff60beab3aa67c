"""benchmarks/violation_anatomy.py's column kinds: a thin wall along a grid axis, a block 60 cm across or more;
a wall at the angle of a real street (15 deg) or a short piece is neither."""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
from violation_anatomy import column_kinds  # noqa: E402


def test_column_kinds() -> None:
    grid = np.zeros((60, 60), dtype=bool)
    grid[5, 2:30] = True                     # 5.6 m along y
    grid[40:52, 50] = True                   # 2.4 m along x
    grid[20, 40:47] = True                   # 1.4 m: too short
    grid[30:34, 5:15] = True                 # a 0.8 x 2 m block
    x = np.arange(45)
    grid[10 + x, np.floor(20 + x * np.tan(np.radians(15))).astype(int)] = True   # 9 m at 15 deg
    wall, block = column_kinds(grid, 10)
    assert wall[5, 2:30].all() and wall[40:52, 50].all() and wall.sum() == 28 + 12
    assert block[30:34, 5:15].all() and block.sum() == 40
    assert not (wall & block).any()
