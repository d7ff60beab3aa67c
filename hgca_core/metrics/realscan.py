"""Label-free scores of completions of real scans (no ground-truth mesh exists for a real drive).

- Observed free space: generated cells (completion cells the input does not occupy) that lie where the
  input's own rays passed through (`hgca_core.geometry.freespace`) contradict a ray. On a whole sweep most of
  them are true surface that rays grazed (80 % on synthetic sweeps); above a height cut nearly all are errors
  (97 %; `benchmarks/results/freespace_calibration.md`, in git at 7f06b18).
- Height-cut extrapolation: the input is cut at h metres above the ground and completed; the real cells
  that were cut away are the target. Recall counts a target cell as found when a completion cell lies
  within one cell of it (26-neighbourhood); generated cells above the cut in the full input's observed free
  space are errors.
Each share is also given for the free space's core (`geometry.freespace.confident`, the free cells whose six
neighbours are free): the rim holds true surface (grazing rays over the ground), so even a perfect completion
scores a few % in the whole free space and ~0 in the core (`benchmarks/results/freespace_floor.md`, in git at 7f06b18); and, with a
`swept` grid, for the cells whose volume the rays crossed at least half of (`geometry.freespace.swept`, 5 cm
sub-cells): what rays disproved rather than grazed, also ~0 for a perfect completion, in the rim as in the core.
All cells are 20 cm cells in the region frame (`hgca_core.geometry.voxel`).
"""
from __future__ import annotations

from typing import Mapping, Sequence

import numpy as np

from hgca_core.geometry.freespace import confident, dense
from hgca_core.geometry.voxel import COARSE, cell_centers


def in_grid(cells: np.ndarray, grid: np.ndarray) -> np.ndarray:
    """Per cell: True where the dense bool `grid` is set (cells outside it: False)."""
    c = np.asarray(cells, dtype=np.int64).reshape(-1, 3)
    ok = np.all((c >= 0) & (c < np.asarray(grid.shape)), axis=1)
    out = np.zeros(len(c), dtype=bool)
    out[ok] = grid[c[ok, 0], c[ok, 1], c[ok, 2]]
    return out


def generated_cells(cells: np.ndarray, input_cells: np.ndarray, shape: tuple[int, int, int]) -> np.ndarray:
    """Completion cells (inside the grid) that the input does not occupy: what the method added."""
    c = np.asarray(cells, dtype=np.int64).reshape(-1, 3)
    c = c[np.all((c >= 0) & (c < np.asarray(shape)), axis=1)]
    return c[~in_grid(c, dense(input_cells, shape))]


def recall_within_one(target: np.ndarray, found: np.ndarray, shape: tuple[int, int, int]) -> float:
    """Share of `target` cells with a `found` cell in their 3x3x3 neighbourhood (NaN without targets)."""
    t = np.asarray(target, dtype=np.int64).reshape(-1, 3)
    if len(t) == 0:
        return float("nan")
    return float(in_grid(t, dense(found, shape, dilate=1)).mean())


def above(cells: np.ndarray, z: float) -> np.ndarray:
    """Per cell: its centre lies at or above region-frame height z."""
    return cell_centers(np.asarray(cells).reshape(-1, 3), COARSE)[:, 2] >= z


def _shares(gen: np.ndarray, empty: np.ndarray, core: np.ndarray | None, prefix: str = "",
            swept: np.ndarray | None = None) -> dict[str, float]:
    """Counts and shares of `gen` in the free space, in its core and (given) in the swept cells (NaN shares when
    nothing was generated)."""
    core = confident(empty) if core is None else core
    out = {}
    grids = (("empty", empty), ("core", core)) + ((("swept", swept),) if swept is not None else ())
    for name, grid in grids:
        bad = int(in_grid(gen, grid).sum())
        out[f"{prefix}in_{name}"] = bad
        out[f"{prefix}{name}_share"] = bad / len(gen) if len(gen) else float("nan")
    return out


def free_space_scores(cells: np.ndarray, input_cells: np.ndarray, empty: np.ndarray,
                      core: np.ndarray | None = None, swept: np.ndarray | None = None) -> dict[str, float]:
    """Generated cells and the share of them in observed-empty space, in its core (`core`: the
    `confident(empty)` grid, computed here when None) and in `swept` (bool grid: rays crossed half a cell or more;
    None: not scored)."""
    gen = generated_cells(cells, input_cells, empty.shape)
    return {"generated": len(gen), **_shares(gen, empty, core, swept=swept)}


def cut_scores(cells: np.ndarray, cut_input_cells: np.ndarray, cut_away: np.ndarray, cut_z: float,
               empty: np.ndarray, core: np.ndarray | None = None, swept: np.ndarray | None = None
               ) -> dict[str, float]:
    """Height-cut scores of one completion of the cut input (`empty`, `core`, `swept`: the whole input's)."""
    gen = generated_cells(cells, cut_input_cells, empty.shape)
    up = gen[above(gen, cut_z)]
    return {"recall": recall_within_one(cut_away, cells, empty.shape), "generated_above": len(up),
            **_shares(up, empty, core, "above_", swept)}


def summarise(per_sample: Sequence[Mapping[str, float]]) -> dict[str, dict[str, float]]:
    """min / mean / max / spread (max - min) of each score over the k samples (NaN-aware)."""
    out: dict[str, dict[str, float]] = {}
    for key in per_sample[0]:
        v = np.array([float(s[key]) for s in per_sample], dtype=np.float64)
        if not np.isfinite(v).any():
            out[key] = {"min": float("nan"), "mean": float("nan"), "max": float("nan"), "spread": float("nan")}
            continue
        lo, hi = float(np.nanmin(v)), float(np.nanmax(v))
        out[key] = {"min": lo, "mean": float(np.nanmean(v)), "max": hi, "spread": hi - lo}
    return out
