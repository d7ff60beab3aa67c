"""benchmarks/freespace_calibration.py: flagged generated cells checked against the truth, and its table."""
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
import freespace_calibration as fc  # noqa: E402


def test_classify_counts_flagged_cells_that_are_wrong_and_far():
    shape = (8, 4, 4)
    truth = np.zeros(shape, bool)
    truth[0, 0, 0] = True
    gen = np.zeros(shape, bool)
    gen[0, 0, 0] = gen[1, 0, 0] = gen[5, 0, 0] = gen[7, 3, 3] = True   # true, next to the truth, far, far
    flag = np.zeros(shape, bool)
    flag[:2] = True                                                     # flags the true cell and its neighbour
    other = np.zeros(shape, bool)
    other[4:] = True
    got = fc.classify(gen, truth, {"a": flag, "b": other})
    assert got["all"] == {"cells": 4, "wrong": 3, "far": 2}
    assert got["a"] == {"cells": 2, "wrong": 1, "far": 0}
    assert got["b"] == {"cells": 2, "wrong": 2, "far": 2}


def test_table_rows_and_shares():
    rows = {name: {"cells": 10, "wrong": 2, "far": 1} for name in fc.MEASURES}
    rows["all"] = {"cells": 200, "wrong": 50, "far": 20}
    rows["swept"] = {"cells": 0, "wrong": 0, "far": 0}
    lines = fc.table({"whole": rows})
    assert len(lines) == 2 + 1 + len(fc.MEASURES)
    assert lines[2] == "| single sweep, whole | generated | 200 | 100.0 | 25.0 | 10.0 |  |"
    assert lines[3] == "| single sweep, whole | free | 10 | 5.0 | 20.0 | 10.0 | 100.0 |"
    assert lines[-1] == "| single sweep, whole | swept | 0 | 0.0 | - | - | 0.0 |"


def test_by_profile_groups_scenes_by_the_profile_their_seed_draws():
    def rows(up, up_free, whole, wrong):
        return {"cut": {"all": {"cells": up}, "free": {"cells": up_free}},
                "whole": {"all": {"cells": whole}, "free": {"wrong": wrong}}}
    # val seeds 1,000,000 and 1,000,003 draw hdl64, 1,000,001 hdl32 (docs/data/synth2f_recipe.json)
    per_scene = {"sample_1000000.npz": rows(100, 10, 1000, 10), "sample_1000003.npz": rows(300, 10, 1000, 0),
                 "sample_1000001.npz": rows(50, 0, 500, 5)}
    lines = fc.by_profile(per_scene)
    assert lines[2:] == ["| hdl32 | 1 | 50 | 0.0 | 500 | 1.00 |", "| hdl64 | 2 | 400 | 5.0 | 2,000 | 0.50 |"]
