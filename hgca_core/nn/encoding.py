"""Sinusoidal positional encodings (Vaswani et al.) for 3D cells and 2D BEV pixels.

The paper appends a 3D encoding to the GCA input features and adds a 2D encoding to the planner's BEV
pillars; both tell the local kernels where in the region (especially how high) a cell is.
"""
from __future__ import annotations

import math

import torch


def sinusoidal(x: torch.Tensor, n_freq: int) -> torch.Tensor:
    """x: (..., D) in [0, 1] -> (..., D * 2 * n_freq) with frequencies 2^k * pi, k < n_freq."""
    freqs = (2.0 ** torch.arange(n_freq, dtype=x.dtype, device=x.device)) * math.pi
    ang = x[..., None] * freqs                      # (..., D, F)
    return torch.cat([ang.sin(), ang.cos()], dim=-1).flatten(-2)


def grid_encoding_2d(h: int, w: int, channels: int, device: torch.device | str = "cpu") -> torch.Tensor:
    """(channels, h, w) encoding of normalised pixel positions; channels must be a multiple of 4."""
    n_freq = channels // 4
    ys = (torch.arange(h, device=device, dtype=torch.float32) + 0.5) / h
    xs = (torch.arange(w, device=device, dtype=torch.float32) + 0.5) / w
    grid = torch.stack(torch.meshgrid(xs, ys, indexing="xy"), dim=-1)  # (h, w, 2)
    return sinusoidal(grid, n_freq).permute(2, 0, 1).contiguous()
