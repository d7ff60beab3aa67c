"""The BEV planner (paper Sec. 3.2): global context for the local GCA kernel.

Pillars of 3 x 3 x z_max voxels of s^0 -> a local PointNet per pillar -> 2D positional encoding -> dense 2D
U-Net -> f_BEV; small conv heads turn f_BEV into SPADE (gamma, beta) maps for each sparse decoder level and a
rough dense occupancy O_r with z_r height bins, supervised by the BEV loss (Eq. 6). f_BEV depends on s^0
only, so it is computed once per completion and reused at every GCA step.

With `free_bins` > 0 (beyond the paper, `GCAConfig.free_space`), the 2D U-Net also sees per pillar the share of
its cells seen empty in each of `free_bins` height bins (`hgca_core.models.free.pillar_fractions`), concatenated
after the positional encoding so that a planner trained without them keeps its meaning when they are added as
zero-initialised input channels (warm start, `hgca_core.training.export.load_into`).
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn
import torch.nn.functional as F

from hgca_core.models import free as fs
from hgca_core.nn.encoding import grid_encoding_2d
from hgca_core.nn.sparse import CellState

PILLAR = 3  # voxels per pillar side (paper: h_r = h_max / 3)


@dataclass
class BevOutput:
    spade: list[tuple[torch.Tensor, torch.Tensor]]  # per decoder level: gamma, beta (B, C_l, H, W)
    rough: torch.Tensor                              # (B, z_r, H, W) logits of the rough occupancy O_r


class ResFC(nn.Module):
    def __init__(self, dim: int) -> None:
        super().__init__()
        self.fc1, self.fc2 = nn.Linear(dim, dim), nn.Linear(dim, dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.fc2(F.relu(self.fc1(F.relu(x))))


class PillarPointNet(nn.Module):
    """FC -> 3 residual FC blocks -> FC, max-pooled over the occupied voxels of each pillar."""

    def __init__(self, dim: int = 32) -> None:
        super().__init__()
        self.inp = nn.Linear(3, dim)
        self.blocks = nn.Sequential(*[ResFC(dim) for _ in range(3)])
        self.out = nn.Linear(dim, dim)
        self.dim = dim

    def forward(self, coords: torch.Tensor, batch: int, hw: tuple[int, int], z_max: int) -> torch.Tensor:
        """coords: (N, 4) [b, x, y, z] voxels of s^0 -> (B, dim, H, W) pillar features (0 for empty pillars)."""
        h, w = hw
        c = coords.long()
        px, py = torch.div(c[:, 1], PILLAR, rounding_mode="floor"), torch.div(c[:, 2], PILLAR, rounding_mode="floor")
        keep = (px >= 0) & (px < h) & (py >= 0) & (py < w)
        c, px, py = c[keep], px[keep], py[keep]
        rel = torch.stack([(c[:, 1] - px * PILLAR + 0.5) / PILLAR - 0.5,
                           (c[:, 2] - py * PILLAR + 0.5) / PILLAR - 0.5,
                           (c[:, 3].float() + 0.5) / z_max], dim=1).float()
        feat = self.out(self.blocks(self.inp(rel)))
        pix = (c[:, 0] * h + px) * w + py
        pooled = torch.full((batch * h * w, self.dim), float("-inf"), device=feat.device, dtype=feat.dtype)
        pooled = pooled.scatter_reduce(0, pix[:, None].expand(-1, self.dim), feat, reduce="amax", include_self=True)
        pooled = torch.where(torch.isinf(pooled), torch.zeros_like(pooled), pooled)
        return pooled.view(batch, h, w, self.dim).permute(0, 3, 1, 2).contiguous()


def _block(cin: int, cout: int) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(cin, cout, 3, padding=1), nn.GroupNorm(8, cout), nn.ReLU(inplace=True),
                         nn.Conv2d(cout, cout, 3, padding=1), nn.GroupNorm(8, cout), nn.ReLU(inplace=True))


class UNet2d(nn.Module):
    """A small dense 2D U-Net (after Pytorch-UNet) with padding so odd sizes work."""

    def __init__(self, cin: int, cout: int, widths: tuple[int, ...] = (32, 64, 128)) -> None:
        super().__init__()
        self.downs = nn.ModuleList()
        prev = cin
        for wd in widths:
            self.downs.append(_block(prev, wd))
            prev = wd
        self.ups = nn.ModuleList()
        self.upconvs = nn.ModuleList()
        for wd in reversed(widths[:-1]):
            self.upconvs.append(nn.ConvTranspose2d(prev, wd, 2, stride=2))
            self.ups.append(_block(2 * wd, wd))
            prev = wd
        self.head = nn.Conv2d(prev, cout, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        skips = []
        for i, down in enumerate(self.downs):
            if i:
                x = F.max_pool2d(x, 2, ceil_mode=True)
            x = down(x)
            skips.append(x)
        for upconv, up, skip in zip(self.upconvs, self.ups, reversed(skips[:-1])):
            x = upconv(x)[..., : skip.shape[-2], : skip.shape[-1]]
            x = F.pad(x, (0, skip.shape[-1] - x.shape[-1], 0, skip.shape[-2] - x.shape[-2]))
            x = up(torch.cat([x, skip], dim=1))
        return self.head(x)


class Planner(nn.Module):
    """s^0 -> SPADE maps per decoder level + rough occupancy logits."""

    def __init__(self, level_channels: list[int], z_r: int = 4, point_dim: int = 32, bev_dim: int = 64,
                 free_bins: int = 0) -> None:
        super().__init__()
        self.z_r, self.free_bins = z_r, free_bins
        self.pointnet = PillarPointNet(point_dim)
        self.unet = UNet2d(point_dim + free_bins, bev_dim)
        self.spade_heads = nn.ModuleList([
            nn.Sequential(_block(bev_dim, bev_dim), nn.Conv2d(bev_dim, 2 * ch, 1)) for ch in level_channels])
        self.rough_head = nn.Sequential(_block(bev_dim, bev_dim), nn.Conv2d(bev_dim, z_r, 1))
        for head in self.spade_heads:  # start as identity modulation: gamma = beta = 0
            nn.init.zeros_(head[-1].weight)
            nn.init.zeros_(head[-1].bias)

    @staticmethod
    def bev_shape(grid: tuple[int, int, int]) -> tuple[int, int]:
        return -(-grid[0] // PILLAR), -(-grid[1] // PILLAR)

    def forward(self, s0: CellState, batch: int, free: torch.Tensor | None = None) -> BevOutput:
        """The BEV maps of s^0's grid. `free`: (batch, *grid) bool seen-empty cells, used when the planner has
        free_bins (None: all unknown)."""
        hw = self.bev_shape(s0.grid)
        x = self.pointnet(s0.coords, batch, hw, s0.grid[2])
        x = x + grid_encoding_2d(hw[0], hw[1], x.shape[1], x.device)[None]
        if self.free_bins:
            frac = (fs.pillar_fractions(free, PILLAR, self.free_bins).to(x.dtype) if free is not None
                    else x.new_zeros((batch, self.free_bins, *hw)))
            x = torch.cat([x, frac], dim=1)
        f_bev = self.unet(x)
        spade = [tuple(head(f_bev).chunk(2, dim=1)) for head in self.spade_heads]
        return BevOutput(spade=spade, rough=self.rough_head(f_bev))

    def free_columns(self, prefix: str = "") -> dict[str, tuple[int, list[int]]]:
        """{parameter: (dim, indices)} of the weights that read the free-space inputs (see GCAKernel.free_columns)."""
        if not self.free_bins:
            return {}
        first = self.unet.downs[0][0].in_channels - self.free_bins
        return {f"{prefix}unet.downs.0.0.weight": (1, list(range(first, first + self.free_bins)))}


def rough_target(gt: torch.Tensor, batch: int, grid: tuple[int, int, int], z_r: int) -> torch.Tensor:
    """O_r^gt: (B, z_r, H, W) 1 where any ground-truth voxel falls in the pillar's height bin."""
    h, w = Planner.bev_shape(grid)
    c = gt.long()
    zb = torch.clamp(c[:, 3] * z_r // grid[2], 0, z_r - 1)
    px = torch.div(c[:, 1], PILLAR, rounding_mode="floor").clamp(0, h - 1)
    py = torch.div(c[:, 2], PILLAR, rounding_mode="floor").clamp(0, w - 1)
    target = torch.zeros(batch * z_r * h * w, device=gt.device)
    target[((c[:, 0] * z_r + zb) * h + px) * w + py] = 1.0
    return target.view(batch, z_r, h, w)


def pillar_index(coords: torch.Tensor, stride: int, hw: tuple[int, int]) -> torch.Tensor:
    """Flat (b, px, py) BEV index of sparse cells at a U-Net level whose cells are `stride` voxels wide.

    Coordinates are in finest-cell units at every level (hgca_core.nn.sparse), so a coarse cell's centre
    voxel is x + stride // 2 and its pillar is that divided by the pillar width."""
    c = coords.long()
    centre_x = c[:, 1] + stride // 2
    centre_y = c[:, 2] + stride // 2
    px = torch.div(centre_x, PILLAR, rounding_mode="floor").clamp(0, hw[0] - 1)
    py = torch.div(centre_y, PILLAR, rounding_mode="floor").clamp(0, hw[1] - 1)
    return (c[:, 0] * hw[0] + px) * hw[1] + py
