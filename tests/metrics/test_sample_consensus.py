"""benchmarks/sample_consensus.py: the cells at least m of k samples hold, and its table."""
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
import sample_consensus  # noqa: E402


def test_consensus_keeps_the_cells_at_least_m_samples_hold():
    a = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0]])
    b = np.array([[0, 0, 0], [1, 0, 0]])
    c = np.array([[0, 0, 0], [5, 5, 5]])
    rows = lambda cells: sorted(map(tuple, cells))  # noqa: E731
    assert rows(sample_consensus.consensus([a, b, c], 1)) == [(0, 0, 0), (1, 0, 0), (2, 0, 0), (5, 5, 5)]
    assert rows(sample_consensus.consensus([a, b, c], 2)) == [(0, 0, 0), (1, 0, 0)]
    assert rows(sample_consensus.consensus([a, b, c], 3)) == [(0, 0, 0)]
    assert len(sample_consensus.consensus([a, b, c], 4)) == 0


def test_table_has_a_line_per_sample_count_and_the_single_sample_mean():
    s = {"recall": 0.5, "generated_above": 1234.0, "above_empty_share": 0.081, "above_core_share": 0.0123}
    result = {"inputs": {"log": {"k": 2, "single": s, "consensus": {"1": s, "2": {**s, "recall": 0.25}}}}}
    lines = sample_consensus.table(result).splitlines()
    assert len(lines) == 2 + 3
    assert lines[2] == "| log | one sample (mean of k) | 50.0 | 1,234 | 8.1 | 1.23 |"
    assert lines[4].startswith("| log | in >= 2 of 2 samples | 25.0 |")
