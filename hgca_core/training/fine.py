"""Training of the fine stage: the implicit autoencoder, then the cGCA upsampler with infusion (paper Sec. 3.3).

Both are `Task`s for the shared loop `hgca_core.training.trainer.train` and keep their examples in its
`ChainBuffer`. An example is a random x/y crop (10 cm cells, flipped at random) of one synthetic sample, with
every point set moved into the crop's frame.

Autoencoder: a chain is one crop used for `cfg.steps` steps; each step draws a fresh encoder input from it
(random subsets of the distance pairs at varying density, mixed with zero-distance surface points, or LiDAR-like
zero-distance points alone) and fresh query pairs; loss = L1 on distances clamped at one cell + cGCA's small
latent-norm penalty.

cGCA: x^0 = union(input cells with encoder latents, upsample2(GT 20 cm occupancy) with zero latents) (the GT
low-resolution voxels, not the coarse model's output: the paper trains the two stages independently), GT
latents = the frozen encoder over all GT distance pairs and surface points of each GT 10 cm cell. Loss on N(x~^t):
BCE on occupancy + latent_weight * mean squared error of the latent mean on GT cells (the Gaussian NLL with
fixed sigma, up to its constant). Infusion: per cell, with probability alpha_t the next state copies the GT (GT
occupancy, and the GT latent where the GT cell is occupied), otherwise it samples the model.
With `CGCAConfig.free_space` a chain also carries its crop's observed free space as 10 cm cells (`extra["free"]`,
the children of the sample's seen-empty 20 cm cells, cut and flipped with the same crop).
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from hgca_core.geometry import coords as cs
from hgca_core.geometry.keys import unique_rows
from hgca_core.geometry.voxel import FINE
from hgca_core.meshing.field import udf_surface_points
from hgca_core.metrics.chamfer import chamfer_or_penalty
from hgca_core.models.autoencoder import Autoencoder, AutoencoderConfig
from hgca_core.models.cgca import CGCAConfig, CGCAKernel, _gather, _table, sample
from hgca_core.models import free as fs
from hgca_core.models.infusion import alpha
from hgca_core.models.weights import load_autoencoder, shipped, shown_path, trained_weights
from hgca_core.training.export import save_weights
from hgca_core.nn.sparse import CellState
from hgca_core.training.buffer import Chain
from hgca_core.dataset.packed import refuse_packed
from hgca_core.dataset.samples import load_arrays, split_files
from hgca_core.training.data import draw_crop, free_cells, grids
from hgca_core.training.selection import selected_run

KEYS = ("input_points", "gt_occ10", "gt_occ20", "gt_surface", "udf_points", "udf_dist")
CD_PENALTY = 1.0  # metres: Chamfer reported when a decoded crop has no surface at all


# -- crops ----------------------------------------------------------------------------------------------------------
def upsample2_np(c20: np.ndarray) -> np.ndarray:
    """20 cm cells -> their eight 10 cm children."""
    kids = np.stack(np.meshgrid((0, 1), (0, 1), (0, 1), indexing="ij"), -1).reshape(-1, 3)
    return unique_rows((np.asarray(c20, dtype=np.int64).reshape(-1, 1, 3) * 2 + kids[None]).reshape(-1, 3))


def crop_sample(path: str | Path, crop: int | None, rng: np.random.Generator,
                max_pairs: int | None = None, free: bool = False) -> tuple[dict[str, torch.Tensor], tuple[int, int, int]]:
    """Every set the fine stage trains on, cut to one random crop: cells gt10 and coarse10 (= upsampled GT
    20 cm), points lidar (input), surf (GT surface) and the distance pairs udf_p / udf_d (at most max_pairs);
    with `free`, free10: the 10 cm children of the seen-empty 20 cm cells (`free_cells`)."""
    a = load_arrays(str(path), KEYS)
    spec = draw_crop(grids(path)[0], crop, rng)
    udf_p, keep = spec.points(a["udf_points"])
    udf_d = np.asarray(a["udf_dist"], dtype=np.float32)[keep]
    if max_pairs is not None and len(udf_p) > max_pairs:
        pick = np.sort(rng.choice(len(udf_p), size=max_pairs, replace=False))
        udf_p, udf_d = udf_p[pick], udf_d[pick]
    out = {"gt10": spec.cells(a["gt_occ10"]), "coarse10": spec.cells(upsample2_np(a["gt_occ20"])),
           "lidar": spec.points(a["input_points"])[0], "surf": spec.points(a["gt_surface"])[0],
           "udf_p": udf_p, "udf_d": udf_d}
    if free:
        f20 = free_cells(path)
        lo, hi = spec.ox // 2, (spec.ox + spec.grid[0] - 1) // 2   # parents of the window's 10 cm cells only
        ly, hy = spec.oy // 2, (spec.oy + spec.grid[1] - 1) // 2
        f20 = f20[(f20[:, 0] >= lo) & (f20[:, 0] <= hi) & (f20[:, 1] >= ly) & (f20[:, 1] <= hy)]
        out["free10"] = spec.cells(upsample2_np(f20))
    return {k: torch.from_numpy(np.ascontiguousarray(v)) for k, v in out.items()}, spec.grid


@torch.no_grad()
def gt_latents(autoencoder: Autoencoder, cells: torch.Tensor, udf_p: torch.Tensor, udf_d: torch.Tensor,
               surf: torch.Tensor, seed: int = 0) -> torch.Tensor:
    """Latents (N, K) of the GT cells (N, 3) from all their distance pairs and surface points (distance 0).

    The pairs are shuffled with a fixed seed first, so the per-cell cap keeps a fair mix of both kinds.
    """
    p = torch.cat([udf_p.float(), surf.float()])
    d = torch.cat([udf_d.float(), torch.zeros(len(surf))])
    perm = torch.randperm(len(p), generator=torch.Generator().manual_seed(seed))
    cells4, z = autoencoder.encode(p[perm], d[perm], cells=cells)
    return z[cs.lookup(cs.with_batch(cells.long().to(cells4.device)), cs.pack(cells4))]  # the caller's cell order


# -- autoencoder ------------------------------------------------------------------------------------------------
class AutoencoderLoss(nn.Module):
    """One forward = encoder inputs drawn from each chain's crop, decoded distances at query pairs, loss."""

    lidar_prob = 0.35   # share of examples whose encoder sees zero-distance points only (the LiDAR case)

    def __init__(self, cfg: AutoencoderConfig) -> None:
        super().__init__()
        self.cfg = cfg
        self.model = Autoencoder(cfg)

    def _encoder_input(self, ex: dict[str, torch.Tensor],
                       gt: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Random (points, distances, cells to encode) for one example.

        LiDAR mode: zero-distance points alone, encoded into the cells they fall in (the inference input).
        GT mode: a random share of the distance pairs and of the surface points, encoded into the GT cells that
        have a pair within the encoder's reach (what `gt_latents` does with all of them).
        """
        v, dev = self.cfg.voxel, gt.device
        if float(torch.rand(())) < self.lidar_prob:
            src = ex["lidar"] if len(ex["lidar"]) and float(torch.rand(())) < 0.5 else ex["surf"]
            frac = 10 ** float(torch.empty(()).uniform_(-1.5, 0.0))
            p = src[torch.rand(len(src), device=dev) < frac]
            return p, torch.zeros(len(p), device=dev), torch.unique(torch.round(p / v).long(), dim=0)
        f_pairs = 10 ** float(torch.empty(()).uniform_(-1.5, 0.0))
        f_surf = float(torch.rand(())) if float(torch.rand(())) < 0.7 else 0.0
        mp = torch.rand(len(ex["udf_p"]), device=dev) < f_pairs
        ms = torch.rand(len(ex["surf"]), device=dev) < f_surf
        p = torch.cat([ex["udf_p"][mp], ex["surf"][ms]])
        d = torch.cat([ex["udf_d"][mp], torch.zeros(int(ms.sum()), device=dev)])
        own = cs.unique(cs.with_batch(torch.round(p / v).long()))
        reach = cs.dilate(own, self.cfg.enc_radius) if self.cfg.enc_radius > 0 else own
        return p, d, gt[cs.isin(cs.with_batch(gt), reach)]

    def forward(self, chains: list[Chain]) -> tuple[torch.Tensor, dict, list[torch.Tensor]]:
        cfg = self.cfg
        ps, ds, bs, cells, qs, qd, qb = [], [], [], [], [], [], []
        for b, ch in enumerate(chains):
            ex, dev = ch.extra, ch.gt.device
            p, d, c = self._encoder_input(ex, ch.gt)
            ps.append(p)
            ds.append(d)
            bs.append(torch.full((len(p),), b, device=dev))
            cells.append(cs.with_batch(c, b))
            n_pairs = min(len(ex["udf_p"]), cfg.queries)
            n_surf = min(len(ex["surf"]), cfg.queries // 4)
            ip = torch.randperm(len(ex["udf_p"]), device=dev)[:n_pairs]
            isf = torch.randperm(len(ex["surf"]), device=dev)[:n_surf]
            qs += [ex["udf_p"][ip], ex["surf"][isf]]
            qd += [ex["udf_d"][ip], torch.zeros(n_surf, device=dev)]
            qb.append(torch.full((n_pairs + n_surf,), b, device=dev))
        cells4, z = self.model.encode(torch.cat(ps), torch.cat(ds), torch.cat(bs), cells=torch.cat(cells))
        keys, order = torch.sort(cs.pack(cells4))
        hp = self.model.cell_features(cells4[order], z[order])
        q, qdist = torch.cat(qs), torch.cat(qd)
        pred, covered = self.model.blend(keys, hp, q, torch.cat(qb))
        target = (qdist / cfg.voxel).clamp(0, 1)
        err = (pred - target).abs()[covered]
        l1 = err.mean() if len(err) else pred.sum() * 0
        reg = z.norm(dim=1).mean() if len(z) else l1 * 0
        loss = l1 + cfg.reg * reg
        with torch.no_grad():
            on_surf = covered & (qdist == 0)
            stats = {"l1_cm": float(l1.detach()) * cfg.voxel * 100, "z_norm": float(reg.detach()),
                     "cells": len(z) / len(chains),
                     "surf_cm": float(pred[on_surf].mean()) * cfg.voxel * 100 if bool(on_surf.any()) else 0.0}
        return loss, stats, [ch.state for ch in chains]


@dataclass
class AutoencoderTask:
    """The autoencoder for the shared trainer (`hgca train autoencoder`)."""

    data_dir: str | Sequence[str]   # several: train on all their train splits, validate on the first's
    cfg: AutoencoderConfig = field(default_factory=AutoencoderConfig)
    val_count: int = 2
    max_pairs: int = 100_000
    name: str = "autoencoder"

    def __post_init__(self) -> None:
        self.train_files = split_files(self.data_dir, "train")
        refuse_packed(self.train_files, "the autoencoder")

    def build(self) -> AutoencoderLoss:
        return AutoencoderLoss(self.cfg)

    def new_example(self, rng: np.random.Generator) -> Chain:
        path = self.train_files[int(rng.integers(len(self.train_files)))]
        ex, grid = crop_sample(path, self.cfg.crop, rng, self.max_pairs)
        gt = ex.pop("gt10")
        ex.pop("coarse10")
        return Chain(s0=gt, gt=gt, state=gt, t=0, grid=grid, extra=ex)

    @torch.no_grad()
    def validate(self, loss_module: AutoencoderLoss, seed: int = 0) -> dict:
        """Chamfer (metres) between decoded surface points and the GT surface on fixed val crops: val_cd with
        latents from the GT pairs (what cGCA learns to produce), val_cd_lidar with latents from the input
        points alone, over the input's cells (what x^0 holds at inference)."""
        model = loss_module.model
        model.eval()
        cds, cds_lidar = [], []
        for k, path in enumerate(split_files(self.data_dir, "val")[: self.val_count]):
            ex, _ = crop_sample(path, self.cfg.crop, np.random.default_rng(1000 + k), self.max_pairs)
            z = gt_latents(model, ex["gt10"], ex["udf_p"], ex["udf_d"], ex["surf"], seed=seed)
            pts = udf_surface_points(model, ex["gt10"], z, project=1)
            cds.append(chamfer_or_penalty(pts, ex["surf"].numpy(), CD_PENALTY))
            if len(ex["lidar"]):
                cells4, zl = model.encode(ex["lidar"], torch.zeros(len(ex["lidar"])))
                pts = udf_surface_points(model, cells4[:, 1:], zl, project=1)
                near = cs.isin(cs.with_batch(torch.round(ex["surf"] / FINE).long()), cells4)
                cds_lidar.append(chamfer_or_penalty(pts, ex["surf"][near].numpy(), CD_PENALTY))
        loss_module.train()
        out = {"val_cd": float(np.mean(cds))}
        if cds_lidar:
            out["val_cd_lidar"] = float(np.mean(cds_lidar))
        return out


# -- cGCA ---------------------------------------------------------------------------------------------------------
def _batched(sets: list[torch.Tensor]) -> torch.Tensor:
    if not sets:
        return torch.zeros((0, 4), dtype=torch.long)
    return torch.cat([cs.with_batch(s, b) for b, s in enumerate(sets)])


class FineLoss(nn.Module):
    """Wraps the cGCA kernel so one forward computes the loss and the chains' next infusion states.

    The shared trainer hands `advance` only the next cells, so the latents that go with them are written to
    `chain.extra['zt']` here, row-aligned with the returned cells (both in key order).
    """

    def __init__(self, cfg: CGCAConfig) -> None:
        super().__init__()
        self.cfg = cfg
        self.model = CGCAKernel(cfg)

    def forward(self, chains: list[Chain]) -> tuple[torch.Tensor, dict, list[torch.Tensor]]:
        cfg, grid, b = self.cfg, chains[0].grid, len(chains)
        x0, st, gt = (_batched([getattr(c, k) for c in chains]) for k in ("s0", "state", "gt"))
        z0, zt, zgt = (torch.cat([c.extra[k] for c in chains]) for k in ("z0", "zt", "zgt"))
        free = torch.stack([c.extra["free"] for c in chains]) if cfg.free_space else None
        hood = self.model.neighbourhood(CellState(st, grid))
        logits, mu = self.model(hood, st, zt, x0, z0, free)
        nbhd = hood.coords
        in_gt, z_target = _gather(cs.pack(nbhd), *_table(gt, zgt))
        target = in_gt[:, 0]
        on = target > 0
        loss_occ = F.binary_cross_entropy_with_logits(logits, target)
        loss_lat = ((mu[on] - z_target[on]) ** 2).mean() if bool(on.any()) else mu.sum() * 0
        loss = loss_occ + cfg.latent_weight * loss_lat
        with torch.no_grad():
            dev = nbhd.device
            a = torch.tensor([alpha(cfg, c.t) for c in chains], device=dev)[nbhd[:, 0]]
            infuse = torch.rand(len(nbhd), device=dev) < a
            occ = torch.where(infuse, on, torch.rand(len(nbhd), device=dev) < torch.sigmoid(logits))
            z_next = mu + cfg.sigma * torch.randn(mu.shape, device=dev)
            z_next = torch.where((infuse & on)[:, None], z_target, z_next)
            nxt, zn = nbhd[occ], z_next[occ]
            new_states = []
            for i, ch in enumerate(chains):
                sel = nxt[:, 0] == i
                new_states.append(nxt[sel, 1:])
                ch.extra = {**ch.extra, "zt": zn[sel]}
            stats = {"loss_occ": float(loss_occ.detach()), "loss_lat": float(loss_lat.detach()),
                     "cells": float(len(nbhd)) / b}
        return loss, stats, new_states


@dataclass
class FineTask:
    """The cGCA upsampler for the shared trainer (`hgca train fine`); needs a trained autoencoder."""

    data_dir: str | Sequence[str]   # several: train on all their train splits, validate on the first's
    cfg: CGCAConfig
    autoencoder: str | Autoencoder
    val_count: int = 2
    max_pairs: int = 100_000
    name: str = "fine"

    def __post_init__(self) -> None:
        self.train_files = split_files(self.data_dir, "train")
        refuse_packed(self.train_files, "the fine stage")
        ae = load_autoencoder(str(self.autoencoder)) if isinstance(self.autoencoder, (str, Path)) else self.autoencoder
        self.ae = ae.eval()
        for p in self.ae.parameters():
            p.requires_grad_(False)
        if self.ae.cfg.latent != self.cfg.latent:
            raise ValueError(f"cGCA latent size {self.cfg.latent} != autoencoder's {self.ae.cfg.latent}")

    def build(self) -> FineLoss:
        return FineLoss(self.cfg)

    @torch.no_grad()
    def example(self, path: str | Path, rng: np.random.Generator) -> tuple[Chain, dict[str, torch.Tensor]]:
        """x^0 (input cells with latents + upsampled GT 20 cm cells), GT cells and GT latents of one crop."""
        ex, grid = crop_sample(path, self.cfg.crop, rng, self.max_pairs, free=self.cfg.free_space)
        lidar = ex["lidar"]
        inside = ((torch.round(lidar / FINE) >= 0) & (torch.round(lidar / FINE) < torch.tensor(grid))).all(1)
        in_cells, z_in = self.ae.encode(lidar[inside], torch.zeros(int(inside.sum())))
        x0 = cs.union(in_cells, cs.with_batch(ex["coarse10"]))
        z0 = torch.zeros((len(x0), self.cfg.latent))
        z0[cs.lookup(in_cells, cs.pack(x0))] = z_in
        zgt = gt_latents(self.ae, ex["gt10"], ex["udf_p"], ex["udf_d"], ex["surf"])
        x0_3 = x0[:, 1:].contiguous()
        extra = {"z0": z0, "zt": z0.clone(), "zgt": zgt}
        if self.cfg.free_space:
            extra["free"] = fs.from_cells(ex.pop("free10"), grid)[0]
        chain = Chain(s0=x0_3, gt=ex["gt10"], state=x0_3.clone(), t=0, grid=grid, extra=extra)
        return chain, ex

    def new_example(self, rng: np.random.Generator) -> Chain:
        return self.example(self.train_files[int(rng.integers(len(self.train_files)))], rng)[0]

    @torch.no_grad()
    def validate(self, loss_module: FineLoss, seed: int = 0) -> dict:
        """On fixed val crops, T2 steps from x^0: IoU of the 10 cm cells with the GT (val_iou) and Chamfer
        (metres) between the decoded surface points and the GT surface (val_cd)."""
        ious, cds = [], []
        for k, path in enumerate(split_files(self.data_dir, "val")[: self.val_count]):
            ch, ex = self.example(path, np.random.default_rng(1000 + k))
            gen = torch.Generator().manual_seed(seed + k)
            free = ch.extra["free"][None] if self.cfg.free_space else None
            cells, z = sample(loss_module.model, CellState(cs.with_batch(ch.s0), ch.grid), ch.extra["z0"],
                              self.cfg.steps, gen, free=free)
            pred, gt = cs.pack(cells), cs.pack(cs.with_batch(ch.gt))
            inter = int(torch.isin(pred, gt).sum())
            union = len(pred) + len(gt) - inter
            ious.append(inter / union if union else 1.0)
            pts = udf_surface_points(self.ae, cells[:, 1:], z, project=1) if len(cells) else np.zeros((0, 3))
            cds.append(chamfer_or_penalty(pts, ex["surf"].numpy(), CD_PENALTY))
        loss_module.train()
        return {"val_iou": float(np.mean(ious)), "val_cd": float(np.mean(cds))}


# -- export -------------------------------------------------------------------------------------------------------
def export_autoencoder(ckpt_path: str | Path, dest: str | Path | None = None, meta: dict | None = None) -> Path:
    """Write the autoencoder of a training run as weights (default: the packaged autoencoder.pt): the average the
    run selected on val (`selection.selected_run`: best.pt, else the checkpoint)."""
    ck, record, _ = selected_run(ckpt_path)
    module = AutoencoderLoss(AutoencoderConfig.from_dict(ck["config"]))
    module.load_state_dict(trained_weights(ck))
    return save_weights(dest or shipped("autoencoder"), module.model, {**record, **(meta or {})})


def export_fine(ckpt_path: str | Path, autoencoder: str | Path, dest: str | Path | None = None,
                meta: dict | None = None) -> Path:
    """Write the cGCA kernel of a training run together with its autoencoder (one file, kind 'fine'): the average
    the run selected on val (`selection.selected_run`: best.pt, else the checkpoint)."""
    ck, record, _ = selected_run(ckpt_path)
    module = FineLoss(CGCAConfig.from_dict(ck["config"]))
    module.load_state_dict(trained_weights(ck))
    return save_weights(dest or shipped("fine"), module.model,
                        {**record, "autoencoder": shown_path(autoencoder), **(meta or {})},
                        autoencoder=load_autoencoder(autoencoder))
