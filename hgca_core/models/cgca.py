"""The fine stage: a continuous GCA (cGCA) that upsamples the coarse completion to 10 cm cells with latents.

State x = {(c, o_c, z_c)}: occupied 10 cm cells with a K-dim latent of the implicit autoencoder each (paper
Sec. 3.3). The transition kernel p(x^{t+1} | x^t, x^0) is a sparse U-Net evaluated on the neighbourhood N(x^t);
its input per cell is [c in x^t, c in x^0, z^t_c, z^0_c] (zeros where absent), projected per cell to a narrower
width, plus a 3D sinusoidal positional encoding; its output is an occupancy logit and a latent mean mu_c. A
transition samples o_c ~ Bernoulli(sigmoid(logit)) and z_c ~ N(mu_c, sigma^2 I) with a small fixed sigma; the
last of the T2 = 15 steps takes the most likely state (o_c = [p > 0.5], z_c = mu_c).

Neighbourhood metric: cells within L1 distance 2 of an occupied cell (the octahedron of 25 offsets; cGCA's
"hypercross" padding). On the thin shells a scene is made of, every radius-2 metric grows a layer to the same
thickness (5 cells), so the metrics differ at edges and corners only: on a default-region sample (x^t = the GT
10 cm cells, 262,713) N(x^t) holds 1,098,430 cells for L1, 1,104,965 for L2 and 1,228,100 for the Chebyshev
cube (+12 %); from x^0 (487,678 cells) 1,341,810 vs 1,446,184 (+8 %). Every kernel layer scales with that count;
a chain still crosses the 3-cell body diagonal in two steps. The dilation itself runs on a dense boolean grid
(~0.1 s for any metric; sorting the ~5 M candidate keys took 3 s for L1 and 21 s for the cube).

Kernel layout (`unet_stride`, see CGCAKernel): by default the U-Net runs on the 20 cm parents of N(x^t), with
per-child layers in and out at 10 cm; 3.4 s instead of 12-17 s per step on the default region on one busy core.

x^0 = union(cells of the input points at 10 cm, with latents encoded from the raw points at distance 0;
upsample2(coarse cells) with zero latents), as in the paper.

Observed free space (beyond the paper; `free_space`): one more input column, last, "in free" = the 10 cm cell lies
in a 20 cm cell the sensor's rays crossed (`hgca_core.models.free`); `sample(forbid=...)` drops given cells
(the children of the free space's core) from every sampled state. Without it the model is exactly the one before
the field existed.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
import torch
from torch import nn

from hgca_core.geometry import coords as cs
from hgca_core.models.autoencoder import Autoencoder
from hgca_core.models import free as fs
from hgca_core.models.config import Config
from hgca_core.nn.encoding import sinusoidal
from hgca_core.nn.row_grid import member_rows
from hgca_core.nn.sparse import CellState, SparseConv3d, SparseConvTranspose3d, SparseTensor
from hgca_core.nn.unet import SparseUNet


@dataclass
class CGCAConfig(Config):
    latent: int = 32                                   # K, must match the autoencoder
    channels: tuple[int, ...] = (16, 24, 32, 48, 64)   # U-Net widths per level (4 stride-2 levels)
    blocks: int = 1
    in_proj: int = 24                                  # per-cell projection of the 2 + 2K + PE input features
    unet_stride: int = 2                               # 1: U-Net on the 10 cm cells; 2: on their 20 cm parents
    radius: int = 2
    metric: str = "l1"
    pe_freq: int = 3
    pe_axes: str = "z"                                 # axes in the positional encoding (see CGCAKernel)
    steps: int = 15                                    # T2
    alpha0: float = 0.15                               # infusion alpha_t = alpha0 + alpha1 * t
    alpha1: float = 0.005
    sigma: float = 0.05                                # std of the latent transition N(mu, sigma^2 I)
    latent_weight: float = 1.0                         # weight of the latent NLL term (1 / 2 sigma^2 folded in)
    crop: int | None = 64                              # training: x/y crop in 10 cm cells
    grid: tuple[int, int, int] = (384, 384, 80)
    free_space: bool = False                           # observed free space as the last input column


def _table(cells: torch.Tensor, z: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(sorted keys, latents in key order) of a batched cell set."""
    keys, order = torch.sort(cs.pack(cells))
    return keys, z[order]


def _gather(nbhd_keys: torch.Tensor, keys: torch.Tensor, z: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(membership (M, 1) float, latents (M, K), zero where absent) of neighbourhood cells in a state."""
    idx = cs.lookup(nbhd_keys, keys)
    found = idx >= 0
    out = z.new_zeros((len(idx), z.shape[1]))
    out[found] = z[idx[found]]
    return found.float()[:, None], out


class CGCAKernel(nn.Module):
    """Transition kernel; `forward` returns (occupancy logits (M,), latent means (M, K)) on N(x^t).

    unet_stride 1: the sparse U-Net runs on the 10 cm cells of N(x^t) (the paper's layout).
    unet_stride 2 (the CPU default): the 10 cm cells keep only per-cell layers; a stride-2 conv gathers each
    2 x 2 x 2 block of children (one weight per child position) into its 20 cm parent, the U-Net runs on the
    parents, and a transposed conv hands every child its own decoding of its parent's features, concatenated
    with the child's input features for the per-cell head. Every 3 x 3 x 3 conv then runs on ~1/3 of the cells
    with ~1/2 of the pairs per cell, which on 2 CPU cores is the difference between ~15 s and ~4 s per step on
    the default region (one 3 x 3 x 3 conv over its ~1.1 M cells costs ~1.5 s whatever the width).

    Positional encoding: of the height only by default (pe_axes = "z"). Training runs on x/y crops with random
    flips, so an x/y encoding would be crop-relative in training and region-relative at inference; height (ground,
    kerb, facade, roof) means the same in both. pe_axes = "xyz" gives the paper's 3D encoding.
    """

    def __init__(self, cfg: CGCAConfig) -> None:
        super().__init__()
        self.cfg = cfg
        self.pe_axes = ["xyz".index(a) for a in cfg.pe_axes]
        self.pe_dim = len(self.pe_axes) * 2 * cfg.pe_freq
        in_ch = 2 + 2 * cfg.latent + self.pe_dim + int(cfg.free_space)
        # The projection keeps the first conv at in_proj input channels rather than ~80.
        self.proj = nn.Sequential(nn.Linear(in_ch, cfg.in_proj), nn.ReLU())
        if cfg.unet_stride == 1:
            self.unet = SparseUNet(cfg.in_proj, 1 + cfg.latent, channels=cfg.channels, blocks=cfg.blocks)
        elif cfg.unet_stride == 2:
            c0 = cfg.channels[0]
            self.down = SparseConv3d(cfg.in_proj, c0, 2, 2, bias=True)
            self.unet = SparseUNet(c0, c0, channels=cfg.channels, blocks=cfg.blocks)
            self.up = SparseConvTranspose3d(c0, c0, 2, 2, bias=True)
            self.head = nn.Sequential(nn.Linear(cfg.in_proj + c0, c0), nn.ReLU(), nn.Linear(c0, 1 + cfg.latent))
        else:
            raise ValueError(f"unet_stride must be 1 or 2, got {cfg.unet_stride}")

    def neighbourhood(self, state: CellState) -> CellState:
        return state.with_coords(cs.dilate(state.coords, self.cfg.radius, self.cfg.metric, state.grid))

    def free_columns(self) -> dict[str, tuple[int, list[int]]]:
        """{parameter name: (dim, indices)} where the free-space input enters (see GCAKernel.free_columns)."""
        return {"proj.0.weight": (1, [self.proj[0].in_features - 1])} if self.cfg.free_space else {}

    def forward(self, nbhd: CellState, state: torch.Tensor, z_state: torch.Tensor, x0: torch.Tensor,
                z0: torch.Tensor, free: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """nbhd: (M, 4) sorted unique cells in their grid; state / x0 (N, 4) cells with latents (N, K);
        free (B, *grid) bool seen-empty 10 cm cells (read only with cfg.free_space; None: all unknown)."""
        feats = self.project(nbhd, state, z_state, x0, z0, free)
        x = SparseTensor(nbhd.coords, feats, check=False, grid=nbhd.grid)
        if self.cfg.unet_stride == 1:
            out = self.unet(x).feats
        else:
            p = self.down(x)                                   # parents, coords multiples of 2, stride 2
            pc = p.coords.clone()
            pc[:, 1:] = torch.div(pc[:, 1:], 2, rounding_mode="floor")    # the same cells in 20 cm units
            grid20 = tuple(-(-g // 2) for g in nbhd.grid)
            h = self.unet(SparseTensor(pc, p.feats, check=False, grid=grid20)).feats
            u = self.up(SparseTensor(p.coords, h, 2, p.cache, check=False, grid=p.grid), x)  # reuses the down map
            # head(cat([feats, relu(u)])) with its first layer split by input block: no (M, 40) concatenation
            first, c = self.head[0], feats.shape[1]
            hid = torch.addmm(first.bias, feats, first.weight[:, :c].T)
            hid.addmm_(torch.relu_(u.feats), first.weight[:, c:].T)     # u, hid: maps of our own, changed in place
            out = self.head[2](torch.relu_(hid))
        return out[:, 0], out[:, 1:]

    def project(self, nbhd: CellState, state: torch.Tensor, z_state: torch.Tensor, x0: torch.Tensor,
                z0: torch.Tensor, free: torch.Tensor | None = None) -> torch.Tensor:
        """relu(proj([in x^t, in x^0, z^t, z^0, PE (, in free)])) per neighbourhood cell, computed block by block.

        The same linear map as on the concatenated (M, 2 + 2K + PE) input, but the latent blocks are multiplied
        only on the rows that have a latent (the ~20 % of N(x) in x^t or x^0; the rest are zeros), and a height-only
        encoding is a per-z table: on the default region this drops a 1.2 M x 78 concatenation and most of the
        projection's multiply-adds, every step.
        """
        grid, nbhd = nbhd.grid, nbhd.coords                             # (M, 4) cells from here on
        lin, k = self.proj[0], self.cfg.latent
        w = lin.weight                                                  # (P, 2 + 2K + PE (+ 1))
        w_pe = w[:, 2 + 2 * k: 2 + 2 * k + self.pe_dim]
        g = torch.tensor(grid, dtype=torch.float32, device=nbhd.device)[self.pe_axes]
        if self.pe_axes == [2]:
            levels = sinusoidal(((torch.arange(grid[2], device=nbhd.device).float() + 0.5) / g)[:, None],
                                self.cfg.pe_freq)
            h = torch.addmm(lin.bias, levels, w_pe.T)[nbhd[:, 3]]
        else:
            pe = sinusoidal((nbhd[:, 1:][:, self.pe_axes].float() + 0.5) / g, self.cfg.pe_freq)
            h = torch.addmm(lin.bias, pe, w_pe.T)
        if self.cfg.free_space and free is not None:
            rows = fs.at(free, nbhd).nonzero().squeeze(1)
            h.index_add_(0, rows, w[:, -1].expand(len(rows), -1))
        nk = None
        for col, (cells, z) in enumerate(((state, z_state), (x0, z0))):
            idx, zs = member_rows(nbhd, cells), z        # rows of the (unique) cells: a dense grid's gather
            if idx is None:                              # a box too large for the grid: the sorted keys
                nk = cs.pack(nbhd) if nk is None else nk
                keys, zs = _table(cells, z)
                idx = cs.lookup(nk, keys)
            rows = (idx >= 0).nonzero().squeeze(1)
            lat = w[:, 2 + col * k: 2 + (col + 1) * k]
            h.index_add_(0, rows, (zs[idx[rows]] @ lat.T) + w[:, col])   # membership flag + latent block
        return torch.relu_(h)


@torch.no_grad()
def sample(model: CGCAKernel, x0: CellState, z0: torch.Tensor, steps: int,
           generator: torch.Generator, progress: Callable[[int, int], None] | None = None,
           free: torch.Tensor | None = None, forbid: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Run the chain from x^0 for `steps` transitions; the last one by maximum likelihood.

    x0: (N, 4) batched cells in their grid, z0: (N, K). Returns the final (cells (M, 4), latents (M, K)). All
    randomness comes from `generator`, so a seed names one result. free: (B, *grid) bool seen-empty 10 cm cells (the
    model's input when it has free_space); forbid: (B, *grid) bool 10 cm cells dropped from every sampled state (the
    same random draws either way).
    """
    model.eval()
    state, z = x0, z0
    for t in range(steps):
        nbhd = model.neighbourhood(state)
        logits, mu = model(nbhd, state.coords, z, x0.coords, z0, free)
        last = t == steps - 1
        if last:
            keep = logits > 0
        else:
            # drawn where the generator is (the CPU's: `pipeline`), so a seed gives one chain on any device
            keep = (torch.rand(logits.shape, generator=generator, device=generator.device).to(logits.device)
                    < torch.sigmoid(logits))
        if forbid is not None:
            keep &= ~fs.at(forbid, nbhd.coords)
        state, z = nbhd[keep], mu[keep]
        if not last:   # latent noise only for the cells kept (~1/5 of N(x))
            z = z + model.cfg.sigma * torch.randn(z.shape, generator=generator, device=generator.device).to(z.device)
        if progress is not None:
            progress(t + 1, steps)
        if len(state) == 0:  # the chain died out: nothing left to grow from
            break
    return state.coords, z


def input_cells(autoencoder: Autoencoder, points_local: np.ndarray | torch.Tensor,
                grid: tuple[int, int, int]) -> tuple[torch.Tensor, torch.Tensor]:
    """Cells (N, 4) of the input points at 10 cm (by rounding, inside the grid) and their encoder latents from
    the raw points at distance 0 (what a LiDAR point says: the surface passes here)."""
    dev = next(autoencoder.parameters()).device
    p = torch.as_tensor(np.asarray(points_local, dtype=np.float32) if not isinstance(points_local, torch.Tensor)
                        else points_local, dtype=torch.float32).reshape(-1, 3).to(dev)
    c = torch.round(p / autoencoder.cfg.voxel)
    inside = ((c >= 0) & (c < torch.tensor(grid, device=dev))).all(1)
    p = p[inside]
    with torch.no_grad():
        return autoencoder.encode(p, torch.zeros(len(p), device=dev))


def initial_state(autoencoder: Autoencoder, points_local: np.ndarray | torch.Tensor,
                  coarse_cells: np.ndarray | torch.Tensor, grid: tuple[int, int, int]
                  ) -> tuple[CellState, torch.Tensor]:
    """x^0 = union(input cells with encoder latents, upsample2(coarse 20 cm cells) with zero latents), in `grid`
    (the 10 cm grid, where the chain's state is made), and its latents."""
    dev = next(autoencoder.parameters()).device
    in_cells, z_in = input_cells(autoencoder, points_local, grid)
    coarse = torch.as_tensor(np.asarray(coarse_cells) if not isinstance(coarse_cells, torch.Tensor) else coarse_cells)
    up = cs.upsample2(cs.with_batch(coarse.reshape(-1, 3).long().to(dev)))
    up = up[((up[:, 1:] >= 0) & (up[:, 1:] < torch.tensor(grid, device=dev))).all(1)]
    x0 = cs.union(in_cells, up)
    z0 = z_in.new_zeros((len(x0), z_in.shape[1]))
    z0[cs.lookup(in_cells, cs.pack(x0))] = z_in
    return CellState(x0, grid), z0


def upsample(model: CGCAKernel, autoencoder: Autoencoder, input_points_local: np.ndarray | torch.Tensor,
             coarse_cells: np.ndarray | torch.Tensor, grid10: tuple[int, int, int], steps: int | None,
             generator: torch.Generator, progress: Callable[[int, int], None] | None = None,
             free20: torch.Tensor | None = None, forbid20: torch.Tensor | None = None
             ) -> tuple[torch.Tensor, torch.Tensor]:
    """The fine stage of one sample: x^0 from the input and the coarse cells, then T2 cGCA steps.

    input_points_local: (P, 3) region-frame points (metres); coarse_cells: (M, 3) int 20 cm cells (s^T1);
    grid10: the 10 cm grid shape (Region.grid_shape(0.1)); free20: (1, X, Y, Z) bool seen-empty 20 cm cells or
    None, given to the model as 10 cm cells; forbid20: the 20 cm cells whose 10 cm children are never output
    (`--free-space mask`), or None. Returns (cells (N, 3) int64, latents
    (N, K) float32) on the model's device, which the pipeline meshes (`meshing.fine.udf_mesh`).
    """
    x0, z0 = initial_state(autoencoder, input_points_local, coarse_cells, grid10)
    free = fs.upsample(free20, tuple(grid10)) if free20 is not None and model.cfg.free_space else None
    forbid = fs.upsample(forbid20, tuple(grid10)) if forbid20 is not None else None
    cells, z = sample(model, x0, z0, steps or model.cfg.steps, generator, progress, free, forbid)
    return cells[:, 1:], z
