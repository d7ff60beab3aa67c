"""Training examples from synthetic samples: sparse voxel sets, random crops and flips."""
from __future__ import annotations

from functools import lru_cache
from pathlib import Path

import numpy as np
import torch

from hgca_core.errors import InputError
from hgca_core.geometry.voxel import COARSE, FINE, voxelize_coarse



def split_files(data_dir: str | Path, split: str) -> list[Path]:
    """Sample files of a split, sorted, so that an index names the same sample on every run."""
    files = sorted(Path(data_dir, split).glob("sample_*.npz"))
    if not files:
        raise InputError(f"no samples in {Path(data_dir, split)}; make them with `hgca synth --split {split}`")
    return files


@lru_cache(maxsize=64)
def load_arrays(path: str, keys: tuple[str, ...]) -> dict[str, np.ndarray]:
    """Load only the named arrays of a sample (npz members load lazily), cached across chain resets."""
    with np.load(path, allow_pickle=False) as z:
        return {k: z[k] for k in keys}


def grids(path: str | Path) -> tuple[tuple[int, int, int], tuple[int, int, int]]:
    """(10 cm grid, 20 cm grid) of a sample's region, from its stored size."""
    size = load_arrays(str(path), ("region",))["region"][3:6]
    fine = tuple(int(v) for v in np.round(size / FINE))
    coarse = tuple(int(v) for v in np.round(size / COARSE))
    return fine, coarse


def coarse_pair(path: str | Path) -> tuple[np.ndarray, np.ndarray, tuple[int, int, int]]:
    """(s0, gt, grid) at 20 cm for a sample: the input voxelised as the paper says, and the ground truth."""
    a = load_arrays(str(path), ("input_points", "gt_occ20"))
    fine, coarse = grids(path)
    return voxelize_coarse(a["input_points"], fine).astype(np.int64), a["gt_occ20"].astype(np.int64), coarse


def crop_flip(sets: list[np.ndarray], grid: tuple[int, int, int], crop: int | None,
              rng: np.random.Generator) -> tuple[list[torch.Tensor], tuple[int, int, int]]:
    """Cut the same random x/y window from every set and flip it at random; returns tensors and the grid."""
    if crop is None or crop >= grid[0]:
        ox = oy = 0
        out_grid = grid
    else:
        ox, oy = (int(rng.integers(0, g - crop + 1)) for g in grid[:2])
        out_grid = (crop, crop, grid[2])
    fx, fy = rng.random() < 0.5, rng.random() < 0.5
    out = []
    for s in sets:
        c = s - np.array([ox, oy, 0])
        c = c[(c[:, 0] >= 0) & (c[:, 0] < out_grid[0]) & (c[:, 1] >= 0) & (c[:, 1] < out_grid[1])]
        if fx:
            c[:, 0] = out_grid[0] - 1 - c[:, 0]
        if fy:
            c[:, 1] = out_grid[1] - 1 - c[:, 1]
        out.append(torch.from_numpy(np.ascontiguousarray(c)).long())
    return out, out_grid
