"""Crops drawn toward where the error is (issue 13, item 4): missed cells 3 m or more above the ground."""
from __future__ import annotations

import numpy as np
import pytest

from hgca_core.errors import InputError
from hgca_core.training.recipes import parse_sets, resolve
from hgca_core.training.data import FOCUS_HEIGHT, draw_crop, focus_cells


def _street() -> tuple[np.ndarray, np.ndarray]:
    """A 100 x 100 cell ground plane at z = 5 and a 12 m wall at x = 80 (z 5..64); the input sees the ground and
    the wall's lowest 2 m only."""
    xx, yy = np.meshgrid(np.arange(100), np.arange(100), indexing="ij")
    ground = np.c_[xx.ravel(), yy.ravel(), np.full(xx.size, 5)]
    wy, wz = np.meshgrid(np.arange(100), np.arange(5, 65), indexing="ij")
    wall = np.c_[np.full(wy.size, 80), wy.ravel(), wz.ravel()]
    gt = np.unique(np.r_[ground, wall], axis=0)
    s0 = np.unique(np.r_[ground, wall[wall[:, 2] < 15]], axis=0)
    return s0, gt


def test_focus_cells_are_the_missed_cells_high_above_their_column() -> None:
    s0, gt = _street()
    focus = focus_cells(s0, gt)
    assert len(focus) and np.all(focus[:, 0] == 80)           # only the wall
    assert focus[:, 2].min() == 5 + FOCUS_HEIGHT                # 3 m above the lowest true cell of the column
    assert len(focus) == 100 * (65 - 5 - FOCUS_HEIGHT)          # every missed wall cell up high, no more
    # the seen part of the wall and anything below 3 m is never a focus cell
    assert not len(focus_cells(gt, gt)) and not len(focus_cells(s0, gt, height=61))


def test_focus_share_puts_that_share_of_crops_over_the_focus_cells() -> None:
    s0, gt = _street()
    focus = focus_cells(s0, gt)
    rng = np.random.default_rng(0)

    def hits(share: float) -> float:
        crops = [draw_crop((100, 100, 70), 16, rng, focus, share) for _ in range(2000)]
        return np.mean([c.ox <= 80 < c.ox + 16 for c in crops])

    uniform, focused = hits(0.0), hits(0.5)
    assert uniform == pytest.approx(16 / 85, abs=0.03)           # a uniform offset in [0, 84]
    assert focused == pytest.approx(0.5 + 0.5 * 16 / 85, abs=0.04)
    assert hits(1.0) == 1.0
    # crops stay inside the grid, whatever the focus
    for c in (draw_crop((100, 100, 70), 16, rng, np.array([[99, 0, 30]]), 1.0) for _ in range(50)):
        assert 0 <= c.ox <= 84 and 0 <= c.oy <= 84


def test_focus_share_must_be_a_share() -> None:
    assert resolve("coarse", parse_sets(["focus=0.25"])).focus == 0.25
    for bad in ("1.5", "-0.1", "nan"):
        with pytest.raises(InputError, match="focus"):
            resolve("coarse", parse_sets([f"focus={bad}"]))
