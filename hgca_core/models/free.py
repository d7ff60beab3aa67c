"""Observed free space as a model input (beyond the paper): what the sensor saw through, per cell.

Both stages take it as a dense boolean grid `free` of shape (B, X, Y, Z) at their own resolution (20 cm for the
coarse GCA and its planner, 10 cm for the fine cGCA), True where rays proved the cell empty
(`hgca_core.geometry.freespace.observed_empty`); False means "unknown" or "seen occupied". A dense grid keeps
the per-step lookup a gather (31 ms of CPU for a million cells, against 96 ms for `coords.isin` on the sorted
free cells; measured on one thread) and a training crop's grid is small (64 x 64 x 40 = 164 kB).

The three readings of it:
- `at`: the per-cell "seen empty" input column of the GCA / cGCA kernels (and, on the free space's core, the hard
  mask of `--free-space mask`);
- `pillar_fractions`: per BEV pillar, the share of its cells seen empty in each of the planner's height bins;
- `upsample`: the 20 cm grid as 10 cm cells (a 10 cm cell is seen empty when its 20 cm parent is).
"""
from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F


def at(free: torch.Tensor | None, cells: torch.Tensor) -> torch.Tensor:
    """(N,) bool: cell rows [b, x, y, z] that are seen empty; cells outside the grid (or no grid) are not."""
    if free is None or len(cells) == 0:
        return torch.zeros(len(cells), dtype=torch.bool, device=cells.device)
    c = cells.long()
    shape = torch.tensor(free.shape, device=c.device)
    inside = ((c >= 0) & (c < shape)).all(1)
    out = torch.zeros(len(c), dtype=torch.bool, device=c.device)
    ci = c[inside]
    out[inside] = free[ci[:, 0], ci[:, 1], ci[:, 2], ci[:, 3]]
    return out


def from_cells(cells: list[torch.Tensor] | torch.Tensor, grid: tuple[int, int, int],
               device: torch.device | str | None = None) -> torch.Tensor:
    """(B, *grid) bool from per-sample (N, 3) cells (a list) or one (N, 3) set; cells outside the grid dropped."""
    sets = [cells] if isinstance(cells, torch.Tensor) else list(cells)
    dev = device if device is not None else (sets[0].device if sets else "cpu")
    out = torch.zeros((len(sets), *grid), dtype=torch.bool, device=dev)
    g = torch.tensor(grid, device=dev)
    for b, c in enumerate(sets):
        c = c.long().to(dev).reshape(-1, 3)
        c = c[((c >= 0) & (c < g)).all(1)]
        out[b, c[:, 0], c[:, 1], c[:, 2]] = True
    return out


def from_numpy(grid: np.ndarray, device: torch.device | str = "cpu") -> torch.Tensor:
    """A (X, Y, Z) numpy bool grid (`observed_empty`) as a (1, X, Y, Z) tensor on `device`."""
    return torch.from_numpy(np.ascontiguousarray(grid, dtype=bool))[None].to(device)


def upsample(free20: torch.Tensor, grid10: tuple[int, int, int]) -> torch.Tensor:
    """(B, *grid10) bool: each 20 cm cell's eight 10 cm children, cut or padded (False) to the 10 cm grid (a 10 cm
    grid of odd size has a half-filled last 20 cm layer, `hgca_core.geometry.voxel.voxelize`)."""
    up = free20.repeat_interleave(2, 1).repeat_interleave(2, 2).repeat_interleave(2, 3)
    up = up[:, : grid10[0], : grid10[1], : grid10[2]]
    pad = [0, grid10[2] - up.shape[3], 0, grid10[1] - up.shape[2], 0, grid10[0] - up.shape[1]]
    return F.pad(up, pad) if any(pad) else up.contiguous()


def height_bins(depth: int, bins: int) -> list[tuple[int, int]]:
    """[z0, z1) of each height bin: cell z is in bin z * bins // depth, as the planner's rough occupancy has it."""
    z = np.arange(depth) * bins // depth
    return [(int(np.searchsorted(z, b)), int(np.searchsorted(z, b, side="right"))) for b in range(bins)]


def pillar_fractions(free: torch.Tensor, pillar: int, bins: int) -> torch.Tensor:
    """(B, bins, ceil(X / pillar), ceil(Y / pillar)) float: the share of each pillar's cells (pillar x pillar
    columns, those inside the grid) in each height bin that are seen empty."""
    b, x, y, z = free.shape
    f = free.float()
    cols = torch.stack([f[..., z0:z1].mean(-1) if z1 > z0 else f.new_zeros((b, x, y))
                        for z0, z1 in height_bins(z, bins)], 1)           # (B, bins, X, Y)
    # ceil_mode windows at the far edges average only the columns inside the grid
    return F.avg_pool2d(cols, pillar, pillar, ceil_mode=True)
