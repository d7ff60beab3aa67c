"""The coarse stage: a GCA transition kernel p_theta(s^{t+1} | s^t, s^0) at 20 cm, optionally with the planner.

The kernel is a sparse U-Net evaluated on the neighbourhood N(s^t) (cells within `radius` of occupied cells,
Chebyshev metric, i.e. the 3x3x3 cube for r = 1), with input features [in s^t, in s^0] + a sinusoidal
positional encoding (of height only by default: training sees random x/y crops, inference whole regions, so
an x/y encoding would mean different things in the two); it outputs one Bernoulli logit per cell (Eq. 2-3). With the planner, the decoder
features are de-normalised per BEV pillar by SPADE (gamma, beta) maps computed once from s^0.

Observed free space (beyond the paper; `free_space`): the kernel input becomes [in s^t, in s^0, in free] + PE,
where "free" are the cells the sensor's rays crossed (`hgca_core.models.free`), and the planner sees per pillar
the share of its cells seen empty per height bin. Without it (the default, and every file written before the
field existed) the model and its results are exactly those of before. `sample(forbid=...)` also drops
the given cells (the free space's core, `geometry.freespace.confident`) from every sampled state, whatever the
model learnt.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, ClassVar

import torch
from torch import nn

from hgca_core.geometry import coords as cs
from hgca_core.models import free as fs
from hgca_core.models.config import Config
from hgca_core.models.planner import BevOutput, Planner, pillar_index
from hgca_core.nn.encoding import sinusoidal
from hgca_core.nn.row_grid import member_rows
from hgca_core.nn.sparse import CellState, SparseTensor
from hgca_core.nn.unet import SparseUNet


@dataclass
class GCAConfig(Config):
    channels: tuple[int, ...] = (16, 32, 48, 64, 96)
    blocks: int = 1
    radius: int = 1
    pe_freq: int = 3
    pe_axes: str = "z"                # encoded axes: height only, so crops (training) and regions agree
    use_planner: bool = True
    z_r: int = 4
    beta: float = 0.1
    steps: int = 30                   # T1
    alpha0: float = 0.15              # infusion alpha_t = alpha0 + alpha1 * t
    alpha1: float = 0.005
    grid: tuple[int, int, int] = (192, 192, 40)
    free_space: bool = False          # observed free space as an input (kernel column, planner height bins)
    keep: float = 0.5                 # the last transition keeps cells with p > keep (0.5: the most likely state)
    bias: float = 0.0                 # added to every transition's logits when sampling (< 0: each step grows less)

    legacy: ClassVar[dict] = {"pe_axes": "xyz"}  # files written before pe_axes existed encoded all three axes


class GCAKernel(nn.Module):
    """Transition kernel; `forward` returns logits of lambda_theta on the given neighbourhood cells."""

    def __init__(self, cfg: GCAConfig) -> None:
        super().__init__()
        if not 0.0 < float(cfg.keep) < 1.0:   # 1 or more would end every chain empty, 0 or less keep every cell
            raise ValueError(f"keep must lie strictly between 0 and 1, not {cfg.keep!r}")
        if not math.isfinite(float(cfg.bias)):
            raise ValueError(f"bias must be a finite number, not {cfg.bias!r}")
        self.cfg = cfg
        self.pe_axes = ["xyz".index(a) for a in cfg.pe_axes]
        in_ch = 2 + int(cfg.free_space) + len(self.pe_axes) * 2 * cfg.pe_freq
        self.unet = SparseUNet(in_ch, 1, channels=cfg.channels, blocks=cfg.blocks)
        self.planner = Planner(list(self.unet.channels[: self.unet.num_levels]), z_r=cfg.z_r,
                               free_bins=cfg.z_r if cfg.free_space else 0) if cfg.use_planner else None

    def bev(self, s0: CellState, batch: int, free: torch.Tensor | None = None) -> BevOutput | None:
        if self.planner is None:
            return None
        return self.planner(s0, batch, free if self.cfg.free_space else None)

    def free_columns(self) -> dict[str, tuple[int, list[int]]]:
        """{parameter name: (dim, indices)}: where the free-space inputs enter the weights (empty without them).
        A model trained without free space warm-starts one with it by zeros there (`hgca_core.training.export.load_into`)."""
        if not self.cfg.free_space:
            return {}
        cols = {"unet.stem.0.weight": (1, [2])}    # SubMConv3d weight (K, C_in, C_out); column 2 = "in free"
        if self.planner is not None:
            cols.update(self.planner.free_columns("planner."))
        return cols

    def neighbourhood(self, state: CellState) -> CellState:
        return state.with_coords(cs.dilate(state.coords, self.cfg.radius, bounds=state.grid))

    def forward(self, nbhd: CellState, state: torch.Tensor, s0: torch.Tensor, bev: BevOutput | None,
                free: torch.Tensor | None = None) -> torch.Tensor:
        """Logits on the cells of `nbhd` (in its grid) given the (N, 4) cells of s^t and s^0, whose membership alone
        is read. `free`: (B, *grid) bool seen-empty cells (`hgca_core.models.free`); read only with
        cfg.free_space, where None means all unknown."""
        cells = nbhd.coords
        cols = [_isin(cells, state).float()[:, None], _isin(cells, s0).float()[:, None]]
        if self.cfg.free_space:
            cols.append(fs.at(free, cells).float()[:, None])
        g = torch.tensor(nbhd.grid, dtype=torch.float32, device=cells.device)[self.pe_axes]
        pe = sinusoidal((cells[:, 1:][:, self.pe_axes].float() + 0.5) / g, self.cfg.pe_freq)
        x = SparseTensor(cells, torch.cat([*cols, pe], dim=1), grid=nbhd.grid)
        out = self.unet(x, modulate=self._spade(bev) if bev is not None else None)
        return out.feats[:, 0]

    @staticmethod
    def _spade(bev: BevOutput) -> Callable[[int, SparseTensor], SparseTensor]:
        """SPADE by the BEV maps, each level's cells finding their pillar in the grid their tensor carries."""

        def modulate(level: int, x: SparseTensor) -> SparseTensor:
            gamma, beta = bev.spade[level]
            c = gamma.shape[1]
            idx = pillar_index(x.coords, x.stride, Planner.bev_shape(x.grid))
            g = gamma.permute(0, 2, 3, 1).reshape(-1, c)[idx]
            b = beta.permute(0, 2, 3, 1).reshape(-1, c)[idx]
            if torch.is_grad_enabled():
                return x.replace_feats(x.feats * (1 + g) + b)
            return x.replace_feats(x.feats.mul_(g.add_(1)).add_(b))     # inference: the U-Net's own map, in place

        return modulate


def _isin(query: torch.Tensor, cells: torch.Tensor) -> torch.Tensor:
    """`coords.isin` by a dense grid's gather where the cells' box allows (the same answer, no sort and search)."""
    rows = member_rows(query, cells)
    return cs.isin(query, cells) if rows is None else rows >= 0


def transition(model: GCAKernel, state: CellState, s0: CellState, bev: BevOutput | None,
               free: torch.Tensor | None) -> tuple[CellState, torch.Tensor]:
    """One step of the chain: the candidate cells (the neighbourhood of `state`) and their occupancy
    probabilities, with cfg.bias added to the logits. Shared by sampling and BatchNorm re-estimation."""
    nbhd = model.neighbourhood(state)
    return nbhd, torch.sigmoid(model(nbhd, state.coords, s0.coords, bev, free) + model.cfg.bias)


@torch.no_grad()
def sample(model: GCAKernel, s0: CellState, steps: int,
           generator: torch.Generator, progress: Callable[[int, int], None] | None = None,
           free: torch.Tensor | None = None, forbid: torch.Tensor | None = None) -> torch.Tensor:
    """Run the Markov chain from s^0 for `steps` transitions (Eq. 1); the last one keeps the cells with p > cfg.keep
    (0.5: the most likely state, as the paper; a weights file may hold a higher one, chosen on val and real logs,
    to trade far cells the model is unsure of for fewer cells where a sensor would have seen empty space).
    cfg.bias (0 as the paper) shifts every step's logits: growth compounds over the T steps, so a small negative
    shift curbs long excursions more than the cells next to the input.

    s0: the (N, 4) cells of one or more samples (batch column) in their grid. Returns the final occupied set's
    (M, 4) cells.
    free: (B, *grid) bool seen-empty cells, the model's input when it has free_space; forbid: (B, *grid) bool cells
    dropped from every sampled state (`--free-space mask`; the random draws are the same with or without it).
    """
    model.eval()
    batch = int(s0.coords[:, 0].max().item()) + 1 if len(s0) else 1
    bev = model.bev(s0, batch, free)
    if progress is not None:  # the planner's share of the time ends here
        progress(0, steps)
    state = s0
    for t in range(steps):
        nbhd, prob = transition(model, state, s0, bev, free)
        if t == steps - 1:
            keep = prob > model.cfg.keep
        else:
            # drawn where the generator is (the CPU's: `pipeline`), so a seed gives one chain on any device
            keep = torch.rand(prob.shape, generator=generator, device=generator.device).to(prob.device) < prob
        if forbid is not None:
            keep &= ~fs.at(forbid, nbhd.coords)
        state = nbhd[keep]
        if progress is not None:
            progress(t + 1, steps)
        if len(state) == 0:  # the chain died: nothing left to grow from
            break
    return state.coords
