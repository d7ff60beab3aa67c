"""Local implicit autoencoder of the fine stage (cGCA's g_xi / f_omega, paper Sec. 3.3), K latents per 10 cm cell.

Frames and units: the *cell frame* puts the centre of 10 cm cell c at c * voxel (the region frame, since 10 cm
cells are made by rounding). Internally distances and offsets are in cell units (metres / voxel).

Encoder g: a PointNet over the (offset of the point from the cell centre, distance) pairs in and around each cell
(offset in [-1.5, 1.5]^3 with the 26 neighbours, distance clamped at one cell), with two max-pools per cell
(ConvONet's local pooling), vectorised with `scatter_reduce`. The neighbours matter for our data: the synthetic
samples hold ~0.8 distance pairs per GT 10 cm cell and half of the GT cells have none of their own. At inference
the input cells see raw LiDAR points with distance 0; in training the encoder sees random subsets of distance
pairs at varying density, mixed with such zero-distance points, so both kinds of input land in the same latent
space.

Decoder f: two submanifold 3x3x3 convolutions over the latent grid (so a cell's code is read in the context of
its neighbours') give a feature h_c per occupied cell; an MLP on (query offset from a cell centre, h_c) gives
that cell's estimate of the unsigned distance. A query q is decoded from the occupied cells among its 8 nearest
cell centres, blending their estimates with trilinear weights renormalised over the occupied ones:

    d(q) = sum_i w_i(q) f(q - c_i, h_i) / sum_i w_i(q)   (i over occupied corners),   d(q) = 1 cell if none.

This is continuous in q wherever an occupied corner has a non-zero weight (no seams at cell faces, which a
nearest-cell rule would have), costs one MLP row per (query, occupied corner) pair with non-zero weight (on the
5 cm meshing grid: 27 per occupied cell, see `grid_udf`), and gives the MLP the query position explicitly,
which a feature-interpolation decoder (cGCA's) does not. Output: one cell * sigmoid, i.e. metres
clamped at 0.1 m; training uses L1 on distances clamped at one cell, like cGCA.
"""
from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

from hgca_core.geometry import coords as cs
from hgca_core.geometry.keys import delta
from hgca_core.models.config import Config
from hgca_core.nn.sparse import SparseLinear, SparseTensor, SubMConv3d

_CORNERS = torch.tensor(list(itertools.product((0, 1), repeat=3)), dtype=torch.long)  # (8, 3)


@dataclass
class AutoencoderConfig(Config):
    latent: int = 32            # K
    enc_hidden: int = 32
    enc_blocks: int = 3         # >= 1; every block after the first sees the cell's max-pooled features
    dec_channels: int = 32      # width of the sparse conv features h_c
    mlp_hidden: int = 32        # the MLP runs ~27 times per occupied cell when meshing: keep it small
    mlp_blocks: int = 1
    voxel: float = 0.1
    enc_radius: int = 1         # 0: a cell pools its own pairs; 1: also its 26 neighbours' (sparse data, see encode)
    cap: int = 16               # pairs pooled per cell, nearest first (max-pooling saturates; bounds dense LiDAR)
    reg: float = 1e-3           # weight of the latent-norm penalty (cGCA), keeps the code scale fixed for cGCA
    steps: int = 4              # training: uses of one example (crop) before the chain buffer draws a new one
    queries: int = 12000        # training: distance pairs supervised per example and step
    crop: int | None = 64       # training: x/y crop in 10 cm cells


class ResBlockFC(nn.Module):
    """Pre-activation residual MLP block (ConvONet / cGCA), with a linear shortcut when widths differ."""

    def __init__(self, cin: int, cout: int | None = None) -> None:
        super().__init__()
        cout = cin if cout is None else cout
        self.fc0 = nn.Linear(cin, min(cin, cout))
        self.fc1 = nn.Linear(min(cin, cout), cout)
        nn.init.zeros_(self.fc1.weight)  # each block starts as the identity: deep MLPs train from step 0
        self.short = None if cin == cout else nn.Linear(cin, cout, bias=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        dx = self.fc1(torch.relu(self.fc0(torch.relu(x))))
        return (x if self.short is None else self.short(x)) + dx

    def infer_(self, x: torch.Tensor, nonneg: bool = False) -> torch.Tensor:
        """`forward(x)` bit for bit, without autograd, on fresh buffers of its own (the ReLUs in place, the sum
        into the branch's output; `nonneg`: x is known to be >= 0, so its ReLU is x itself). x is not changed."""
        dx = self.fc1(torch.relu_(self.fc0(x if nonneg else torch.relu(x))))
        return dx.add_(x if self.short is None else self.short(x))


def scatter_max(x: torch.Tensor, index: torch.Tensor, n: int) -> torch.Tensor:
    """Per-group max of rows (groups without rows get 0)."""
    out = x.new_zeros((n, x.shape[1]))
    return out.scatter_reduce(0, index[:, None].expand(-1, x.shape[1]), x, reduce="amax", include_self=False)


class CellEncoder(nn.Module):
    """g_xi: (offset, distance) pairs of each cell -> one latent per cell."""

    def __init__(self, cfg: AutoencoderConfig) -> None:
        super().__init__()
        h = cfg.enc_hidden
        self.fc_in = nn.Linear(4, 2 * h)
        self.blocks = nn.ModuleList([ResBlockFC(2 * h, h) for _ in range(max(1, cfg.enc_blocks))])
        self.fc_z = nn.Linear(h, cfg.latent)

    def forward(self, feats: torch.Tensor, cell: torch.Tensor, n_cells: int) -> torch.Tensor:
        """feats (P, 4) = [offset (cell units), distance (cell units)], cell (P,) in [0, n_cells) -> (n_cells, K)."""
        x = self.blocks[0](self.fc_in(feats))
        for block in self.blocks[1:]:
            x = block(torch.cat([x, scatter_max(x, cell, n_cells)[cell]], dim=1))
        return scatter_max(self.fc_z(x), cell, n_cells)


def _sorted(cells4: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(sorted keys, order, sorted cells) of a batched cell set, which must hold no duplicates."""
    keys = cs.pack(cells4)
    keys_s, order = torch.sort(keys)
    if keys_s.numel() > 1 and bool((keys_s[1:] == keys_s[:-1]).any()):
        raise ValueError("cells must be unique")
    return keys_s, order, cells4[order]


def batched_cells(cells: torch.Tensor) -> torch.Tensor:
    """(N, 3) -> (N, 4) with batch 0; (N, 4) unchanged."""
    cells = cells.long()
    return cs.with_batch(cells) if cells.shape[1] == 3 else cells


class UdfField:
    """The decoded field of one set of cells and latents: call it on (Q, 3) cell-frame points in metres.

    The sparse convolutions run once, at construction; each call then costs one MLP row per (query, occupied
    corner) pair. Differentiable in the query points (used to project onto the zero level).
    """

    def __init__(self, model: "Autoencoder", cells: torch.Tensor, latents: torch.Tensor) -> None:
        self.model = model
        c4 = batched_cells(cells).to(latents.device)
        self.keys, order, _ = _sorted(c4)
        self.hp = model.cell_features(c4[order], latents[order])

    def __call__(self, q: torch.Tensor, batch: torch.Tensor | None = None) -> torch.Tensor:
        return self.model.query(self.keys, self.hp, q, batch) * self.model.cfg.voxel


class Autoencoder(nn.Module):
    """Encoder g (points -> latents per cell) and decoder f (latents -> unsigned distance at any point)."""

    def __init__(self, cfg: AutoencoderConfig | None = None) -> None:
        super().__init__()
        self.cfg = cfg = cfg or AutoencoderConfig()
        self.encoder = CellEncoder(cfg)
        c = cfg.dec_channels
        self.conv1 = SubMConv3d(cfg.latent, c, 3, bias=True)
        self.conv2 = SubMConv3d(c, c, 3, bias=True)
        self.skip = SparseLinear(cfg.latent, c)
        self.lin_h = nn.Linear(c, cfg.mlp_hidden)                 # first MLP layer, split: feature part ...
        self.lin_o = nn.Linear(3, cfg.mlp_hidden, bias=False)     # ... and query-offset part (exact, cheaper)
        self.blocks = nn.ModuleList([ResBlockFC(cfg.mlp_hidden) for _ in range(cfg.mlp_blocks)])
        self.fc_out = nn.Linear(cfg.mlp_hidden, 1)

    # -- encoder ------------------------------------------------------------------------------------------------
    def encode(self, points: torch.Tensor, dist: torch.Tensor, batch: torch.Tensor | None = None,
               cells: torch.Tensor | None = None, cap: int | None = None,
               chunk_points: int = 1 << 13) -> tuple[torch.Tensor, torch.Tensor]:
        """Latents of the cells holding the points.

        points (P, 3) cell-frame metres, dist (P,) metres (0 for raw LiDAR points), batch (P,) sample index.
        Each cell pools the pairs in its own cell and, with cfg.enc_radius = 1, its 26 neighbours (offsets then
        span [-1.5, 1.5] cells), keeping the `cap` pairs nearest to its centre (default cfg.cap): own-cell pairs
        first, so dense LiDAR cells stay local while sparse ones borrow from around them.
        cells: the cells to encode ((N, 3) or (N, 4)); cells without pairs get zero latents. Default: every
        cell that holds a point.
        Returns (cells (N, 4) sorted by key, latents (N, K)). Without autograd the pairs are processed in
        chunks of whole cells, so a dense scan does not allocate per-pair features all at once.
        """
        v = self.cfg.voxel
        dev = self.encoder.fc_z.weight.device
        points, dist = points.to(dev, torch.float32), dist.to(dev, torch.float32)
        u = points / v
        pc = torch.round(u).long()
        b = torch.zeros(len(pc), dtype=torch.long, device=dev) if batch is None else batch.to(dev).long()
        pc4 = torch.cat([b[:, None], pc], dim=1)
        if cells is None:
            keys = torch.unique(cs.pack(pc4))
            cells4 = cs.unpack(keys)
        else:
            keys, _, cells4 = _sorted(batched_cells(cells).to(dev))
        if len(pc4) == 0 or len(keys) == 0:
            return cells4, torch.zeros((len(keys), self.cfg.latent), device=dev)
        offs = cs.offsets(self.cfg.enc_radius, device=dev) if self.cfg.enc_radius > 0 else \
            torch.zeros((1, 3), dtype=torch.long, device=dev)
        pts, cell = [], []
        step = max(1, (1 << 20) // len(offs))                     # bounded candidate rows per pass
        for a in range(0, len(pc4), step):
            cand = pc4[a:a + step, None, :].clone().repeat(1, len(offs), 1)
            cand[:, :, 1:] += offs[None]
            idx = cs.lookup(cs.pack(cand.reshape(-1, 4)), keys).view(-1, len(offs))
            i, o = torch.nonzero(idx >= 0, as_tuple=True)
            pts.append(i + a)
            cell.append(idx[i, o])
        pi, cell = torch.cat(pts), torch.cat(cell)
        off = u[pi] - cells4[cell, 1:].float()
        # one sort by (cell, squared distance to its centre quantised to 2^-18 cells^2): grouped, nearest first
        near = ((off * off).sum(1) * (1 << 18)).long().clamp_(max=(1 << 22) - 1)
        order = torch.sort(cell * (1 << 22) + near).indices
        pi, cell, off = pi[order], cell[order], off[order]
        cap = self.cfg.cap if cap is None else cap
        if cap is not None and cap > 0:
            keep = _rank_in_sorted(cell) < cap
            pi, cell, off = pi[keep], cell[keep], off[keep]
        feats = torch.cat([off, (dist[pi] / v).clamp(0, 1)[:, None]], dim=1)
        n = len(keys)
        if torch.is_grad_enabled() or len(pi) <= chunk_points:
            return cells4, self.encoder(feats, cell, n)
        z = feats.new_zeros((n, self.cfg.latent))
        a = 0
        while a < len(pi):  # cut at cell boundaries: every cell's pairs stay in one chunk
            e = min(len(pi), a + chunk_points)
            if e < len(pi):
                e = int(torch.searchsorted(cell, cell[e], right=False))
                e = e if e > a else int(torch.searchsorted(cell, cell[a], right=True))
            c0, c1 = int(cell[a]), int(cell[e - 1]) + 1
            z[c0:c1] = self.encoder(feats[a:e], cell[a:e] - c0, c1 - c0)
            a = e
        return cells4, z

    # -- decoder ------------------------------------------------------------------------------------------------
    def cell_features(self, cells4: torch.Tensor, latents: torch.Tensor) -> torch.Tensor:
        """Per-cell first-layer MLP features lin_h(h_c), h_c from the sparse convs (cells sorted by key)."""
        x = SparseTensor(cells4, latents.float(), check=False)
        h = self.conv2(x.replace_feats(torch.relu_(self.conv1(x).feats)))   # in place: maps of our own
        h = torch.relu_(h.feats.add_(self.skip(x).feats))
        return self.lin_h(h)

    def blend(self, keys: torch.Tensor, hp: torch.Tensor, q: torch.Tensor,
              batch: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """(unsigned distance in cell units clamped at 1, covered) at points q (Q, 3) metres, from sorted cell
        keys and their `cell_features`; covered = some occupied cell among the 8 nearest centres has weight > 0
        (elsewhere the distance is the clamp). See the module docstring for the blending rule."""
        u = q.to(hp.device, torch.float32) / self.cfg.voxel
        base = torch.floor(u.detach()).long()
        frac = u - base                                                   # (Q, 3) in [0, 1), differentiable
        corners = _CORNERS.to(u.device)
        w = torch.where(corners[None].bool(), frac[:, None, :], 1 - frac[:, None, :]).prod(-1)   # (Q, 8)
        qi, ki = torch.nonzero(w.detach() > 0, as_tuple=True)
        cell = base[qi] + corners[ki]
        b = torch.zeros_like(qi) if batch is None else batch.to(u.device).long()[qi]
        idx = cs.lookup(torch.cat([b[:, None], cell], dim=1), keys)
        ok = idx >= 0
        qi, ki, idx = qi[ok], ki[ok], idx[ok]
        off = frac[qi] - corners[ki].to(frac.dtype)                      # query - cell centre, in (-1, 1)
        x = torch.relu(hp[idx] + self.lin_o(off))
        for blk in self.blocks:
            x = blk(x)
        d = torch.sigmoid(self.fc_out(torch.relu(x))[:, 0])
        wq = w[qi, ki]
        num = u.new_zeros(len(u)).index_add(0, qi, wq * d)
        den = u.new_zeros(len(u)).index_add(0, qi, wq)
        covered = den > 0
        return torch.where(covered, num / den.clamp(min=1e-12), torch.ones_like(den)), covered

    def query(self, keys: torch.Tensor, hp: torch.Tensor, q: torch.Tensor,
              batch: torch.Tensor | None = None) -> torch.Tensor:
        """Unsigned distance in cell units (clamped at 1); see `blend`."""
        return self.blend(keys, hp, q, batch)[0]

    @torch.no_grad()
    def grid_udf(self, cells: torch.Tensor, latents: torch.Tensor, res: float,
                 chunk: int = 1 << 15) -> tuple[torch.Tensor, torch.Tensor]:
        """The field on the res-grid around the cells, exactly `field` at those points, computed per cell.

        A grid point g (at g * res) has non-zero trilinear weight only for the cells whose closed box holds it,
        and a cell's box holds the (r + 1)^3 points r c + o, |o| <= r / 2 (r = voxel / res, even): so the
        (query, cell) pairs are (cell, o), with fixed offsets o / r and weights prod(1 - |o / r|). Evaluating
        them per cell needs no neighbour search and no gathers; the blend is one scatter over the grid.
        Returns (grid indices (G, 3) int64 sorted by key, distances (G,) metres). `chunk` bounds the pairs in
        flight.
        """
        v = self.cfg.voxel
        r = int(round(v / res))
        if r < 2 or r % 2 or abs(r * res - v) > 1e-9:
            raise ValueError(f"grid_udf needs voxel / res even, got {v} / {res}")
        c4 = batched_cells(cells).to(latents.device)
        _, order, c4 = _sorted(c4)
        hp = self.cell_features(c4, latents[order])
        h = r // 2
        rng = torch.arange(-h, h + 1, device=hp.device)
        o = torch.stack(torch.meshgrid(rng, rng, rng, indexing="ij"), -1).reshape(-1, 3)        # (P, 3)
        off = o.float() / r
        w = (1 - off.abs()).prod(1)                                                             # (P,)
        lo = self.lin_o(off)                                                                    # (P, H)
        # keys of r c + o: the packed key is linear in the coordinates, so one add per (cell, offset)
        scaled = c4.clone()
        scaled[:, 1:] *= r
        gk = (cs.pack(scaled)[:, None] + delta(o)[None]).reshape(-1)                            # (N P,)
        keys, inv = _unique_inverse(gk)
        num = hp.new_zeros(len(keys))
        den = hp.new_zeros(len(keys)).index_add_(0, inv, w.repeat(len(c4)))
        per = max(1, chunk // len(o))
        for a in range(0, len(c4), per):
            x = torch.relu_(hp[a:a + per, None, :] + lo[None])
            for k, blk in enumerate(self.blocks):
                x = blk.infer_(x, nonneg=k == 0)
            d = torch.sigmoid_(self.fc_out(torch.relu_(x))[..., 0])                           # (n, P)
            num.index_add_(0, inv[a * len(o):(a + per) * len(o)], (d * w).reshape(-1))
        return cs.unpack(keys)[:, 1:], num / den * v

    def field(self, cells: torch.Tensor, latents: torch.Tensor) -> UdfField:
        """The decoded distance field (metres) of occupied cells with latents (what meshing calls)."""
        return UdfField(self, cells, latents)


def _unique_inverse(keys: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """`torch.unique(keys, return_inverse=True)`, the same tensors. On the CPU by numpy's stable sort: the grid
    keys come in runs (each cell's 27 points ascend, neighbouring cells overlap), which its merge sort exploits,
    ~2x faster than torch's unique on a default region's 4.9 M keys (benchmarks/results/meshing_time.md)."""
    if keys.device.type != "cpu" or len(keys) == 0:
        return torch.unique(keys, return_inverse=True)
    a = keys.numpy()
    order = np.argsort(a, kind="stable")
    s = a[order]
    new = np.empty(len(s), dtype=bool)
    new[0] = True
    np.not_equal(s[1:], s[:-1], out=new[1:])
    inv = np.empty(len(s), dtype=np.int64)
    inv[order] = np.cumsum(new) - 1
    # .to(keys.device) is a no-op here; it keeps the contract that results live on the keys' device
    return torch.from_numpy(s[new]).to(keys.device), torch.from_numpy(inv).to(keys.device)


def _rank_in_sorted(group: torch.Tensor) -> torch.Tensor:
    """Position of each element within its run of equal values (group must be sorted)."""
    n = len(group)
    start = torch.ones(n, dtype=torch.bool, device=group.device)
    start[1:] = group[1:] != group[:-1]
    pos = torch.arange(n, device=group.device)
    return pos - torch.cummax(torch.where(start, pos, torch.zeros_like(pos)), 0).values
