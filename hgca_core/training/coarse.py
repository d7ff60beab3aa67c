"""Infusion training of the coarse GCA (+ planner): losses Eq. 5-7 on persistent chains.

With `GCAConfig.free_space` every chain also carries its crop's observed free space (`extra["free"]`, a dense
bool grid cut and flipped with the same crop as s^0 and the ground truth), which the kernel and the planner read."""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import nn
import torch.nn.functional as F

from hgca_core.geometry import coords as cs
from hgca_core.geometry.region import BELOW_GROUND
from hgca_core.geometry.voxel import COARSE
from hgca_core.models import free as fs
from hgca_core.models.gca import GCAConfig, GCAKernel, sample
from hgca_core.models.infusion import alpha
from hgca_core.models.planner import rough_target
from hgca_core.nn.sparse import CellState
from hgca_core.training.buffer import Chain
from hgca_core.dataset.samples import split_files
from hgca_core.training.data import coarse_pair, crop_flip, focus_cells, free_cells, turn_cells, visible_cells


CUT_HEIGHTS = (1.5, 3.0)  # m above the ground: `hgca eval-real` cuts real scans at 1.5 and 2 m


def cut_layer(height: float) -> int:
    """The first coarse cell layer (region z index) at or above a cut `height` m above the ground."""
    return int(np.ceil((BELOW_GROUND + height) / COARSE - 1e-9))


def height_cut(s0: np.ndarray, free: np.ndarray | None, height: float) -> tuple[np.ndarray, np.ndarray | None]:
    """An input cut `height` m above the region's ground (`BELOW_GROUND` in the region frame), as `hgca eval-real`
    cuts real scans to measure extrapolation: input cells whose bottom is at or above the cut go, and so does
    the seen-empty mark of the cells there (the rays to the cut-away points are gone; the rays to the kept
    points stay below the cut but for the few between it and a sensor mounted higher, which are left unknown).
    Trained on, it shows the model what a street holds above what the sensor saw, at its true rate."""
    top = cut_layer(height)
    s0 = s0[s0[:, 2] < top]
    return s0, None if free is None else free[free[:, 2] < top]


def batched(sets: list[torch.Tensor]) -> torch.Tensor:
    if not sets:
        return torch.zeros((0, 4), dtype=torch.long)
    return torch.cat([cs.with_batch(s, b) for b, s in enumerate(sets)])


class CoarseLoss(nn.Module):
    """Wraps the kernel so one forward computes the whole loss (what DDP must see) and the next states."""

    def __init__(self, cfg: GCAConfig, free_weight: float = 0.0, distill: float = 0.0,
                 teacher: GCAKernel | None = None) -> None:
        super().__init__()
        self.cfg = cfg
        self.free_weight = free_weight
        self.model = GCAKernel(cfg)
        self.distill = distill
        # kept out of the module tree (neither trained, checkpointed nor averaged) and in eval mode: the trainer's
        # train() calls never reach it
        self._teacher = [teacher.eval().requires_grad_(False)] if teacher is not None and distill else []

    def forward(self, chains: list[Chain]) -> tuple[torch.Tensor, dict, list[torch.Tensor]]:
        cfg, grid, b = self.cfg, chains[0].grid, len(chains)
        s0, st, gt = (batched([getattr(c, k) for c in chains]) for k in ("s0", "state", "gt"))
        free = torch.stack([c.extra["free"] for c in chains]) if cfg.free_space else None
        hood = self.model.neighbourhood(CellState(st, grid))
        bev = self.model.bev(CellState(s0, grid), b, free)
        logits = self.model(hood, st, s0, bev, free)
        nbhd = hood.coords
        target = cs.isin(nbhd, gt).float()
        weight = None
        stats = {}
        hard = target
        if self._teacher:
            target, stats["distilled"] = self._distilled(chains, hood, st, s0, free, target)
        if self.free_weight and free is not None:
            # growth into what the rays saw through is the error real scans punish most (10-15 % of generated
            # cells): its negatives weigh 1 + free_weight; a seen-empty cell that the ground truth fills keeps 1.
            # A cut input may carry what its uncut scan saw empty (`free_loss`), which the model does not see
            seen_by = torch.stack([c.extra.get("free_loss", c.extra["free"]) for c in chains])
            seen = (fs.at(seen_by, nbhd) & (hard == 0)).float()
            weight = 1.0 + self.free_weight * seen
            stats["seen_empty"] = float(seen.mean())
            if self._teacher:
                target = target * (1.0 - seen)   # what the rays saw empty stays empty, whatever the teacher grows
        loss_gca = F.binary_cross_entropy_with_logits(logits, target, weight=weight)
        loss = loss_gca
        stats["loss_gca"] = float(loss_gca.detach())
        if bev is not None:
            loss_bev = F.binary_cross_entropy_with_logits(bev.rough, rough_target(gt, b, grid, cfg.z_r))
            loss = loss + cfg.beta * loss_bev
            stats["loss_bev"] = float(loss_bev.detach())
        with torch.no_grad():  # infusion kernel q^t: Ber((1 - a_t) lambda + a_t 1[c in gt])
            a = torch.tensor([alpha(cfg, c.t) for c in chains], device=nbhd.device)[nbhd[:, 0]]
            p = (1 - a) * torch.sigmoid(logits) + a * hard
            keep = torch.rand(p.shape, device=p.device) < p
            nxt = nbhd[keep]
            new_states = [nxt[nxt[:, 0] == i, 1:] for i in range(b)]
            stats["cells"] = float(len(nbhd)) / b
        return loss, stats, new_states

    @torch.no_grad()
    def _distilled(self, chains: list[Chain], hood: CellState, st: torch.Tensor, s0: torch.Tensor,
                   free: torch.Tensor | None, target: torch.Tensor) -> tuple[torch.Tensor, float]:
        """(the target with cut inputs' cells moved `distill` of the way to the teacher's probability, the share
        of the step's cells so moved).

        Why: every fine-tune on synthetic cuts learnt to grow more above a cut than the weights it started from,
        and on real scans more of that growth lands where the rays saw empty: synthetic streets reward growth
        there that real ones do not hold. On cut inputs the teacher's (the starting weights') restraint is kept
        instead, while whole inputs train on the ground truth."""
        teacher, nbhd = self._teacher[0], hood.coords
        if next(teacher.parameters()).device != nbhd.device:
            teacher.to(nbhd.device)
        # each chain's lowest distilled layer: every cell of a cut chain, none of an uncut chain's
        none = 1 << 30
        lowest = torch.tensor([-1 if "cut" in c.extra else none for c in chains], device=nbhd.device)
        cut = nbhd[:, 3] >= lowest[nbhd[:, 0]]
        if not bool(cut.any()):
            return target, 0.0
        # the teacher runs on the cut chains alone, renumbered 0..m-1: in eval mode no chain's output depends on
        # another's, and with --cut 0.5 about half of a step's chains are whole (its pass was a quarter of a step)
        chosen = lowest < none
        renumber = torch.cumsum(chosen, 0) - 1

        def only(coords: torch.Tensor) -> torch.Tensor:
            kept = coords[chosen[coords[:, 0]]]
            return torch.cat([renumber[kept[:, :1]], kept[:, 1:]], dim=1)

        rows = chosen[nbhd[:, 0]]
        sub_s0, sub_free = only(s0), None if free is None else free[chosen]
        bev = teacher.bev(hood.with_coords(sub_s0), int(chosen.sum()), sub_free)
        p = torch.zeros_like(target)
        p[rows] = torch.sigmoid(teacher(hood.with_coords(only(nbhd)), only(st), sub_s0, bev, sub_free).float())
        mixed = (1.0 - self.distill) * target + self.distill * p
        return torch.where(cut, mixed, target), float(cut.float().mean())


@dataclass
class CoarseTask:
    """Everything the trainer needs to know about the coarse stage."""

    data_dir: str | Sequence[str]   # several: train on all their train splits, validate on the first's
    cfg: GCAConfig
    crop: int | None = 96
    val_count: int = 4      # val IoU of one 64-cell crop swings by +-0.1 between scenes: average several
    name: str = "coarse"
    focus_share: float = 0.0  # share of training crops drawn around missed cells up high (`data.focus_cells`)
    free_weight: float = 0.0  # extra weight of the loss on negatives seen empty (`CoarseLoss`; needs free_space)
    cut_share: float = 0.0    # share of training inputs cut at a random height (`height_cut`), as eval-real cuts
    cut_free_loss: bool = False  # free_weight on a cut input also weighs what the uncut input saw empty (`example`)
    turn_share: float = 0.0   # share of training inputs turned by a random yaw about the sensor (`data.turn_cells`)
    distill: float = 0.0      # on cut inputs the target moves this far to the teacher's probability (`CoarseLoss`)
    teacher: str | None = None  # coarse weights the cut inputs are distilled from (with distill > 0)
    teacher_sha256: str | None = None  # the teacher file's digest when the run started: a resume checks it

    def __post_init__(self) -> None:
        self.train_files = split_files(self.data_dir, "train")

    def recipe(self) -> dict:
        """The training settings a session records beside its steps (the model card shows them)."""
        return {"crop": self.crop, "focus_share": self.focus_share, "free_weight": self.free_weight,
                "cut_share": self.cut_share, "cut_free_loss": self.cut_free_loss, "turn_share": self.turn_share,
                "distill": self.distill, "teacher": self.teacher, "teacher_sha256": self.teacher_sha256}

    def build(self) -> CoarseLoss:
        teacher = None
        if self.distill:
            import copy

            from hgca_core.models.weights import load_coarse

            teacher = copy.deepcopy(load_coarse(self.teacher)[0])   # its own copy: the cached one may be in use
        return CoarseLoss(self.cfg, self.free_weight, self.distill, teacher)

    def new_example(self, rng: np.random.Generator) -> Chain:
        path = self.train_files[int(rng.integers(len(self.train_files)))]
        height = None   # without cuts the random stream is the one runs before `cut_share` drew
        if self.cut_share and rng.random() < self.cut_share:
            height = CUT_HEIGHTS[0] + rng.random() * (CUT_HEIGHTS[1] - CUT_HEIGHTS[0])   # its crop is drawn uniformly
        yaw = None      # likewise: runs without turns keep their random stream
        if self.turn_share and rng.random() < self.turn_share:
            yaw = float(rng.uniform(0.0, 2.0 * np.pi))
        (s0_t, gt_t), grid, extra = self.example(path, [], rng, self.focus_share if height is None else 0.0, height,
                                                 yaw)
        return Chain(s0=s0_t, gt=gt_t, state=s0_t.clone(), t=0, grid=grid, extra=extra)

    def example(self, path: str | Path, more: list[np.ndarray], rng: np.random.Generator, focus_share: float = 0.0,
                cut_height: float | None = None, yaw: float | None = None
                ) -> tuple[list[torch.Tensor], tuple[int, int, int], dict | None]:
        """([s0, gt, *more] cut by one random crop, the crop's grid, {"free": its free space} or None); with
        `focus_share` > 0 that share of crops is centred near missed cells up high (validation uses none); with
        `cut_height` (metres above the ground) the input is cut there first (`height_cut`). With `cut_free_loss`, a cut
        input's extra also holds {"free_loss": what the uncut input saw empty}: the model never sees it, but the
        loss weighs growth there as `hgca eval-real` counts it (against the whole scan's rays, not the cut's). With
        `yaw` (radians) every set is first turned by it about the region's centre, the sensor (`turn_cells`)."""
        s0, gt, full = coarse_pair(path)
        free = free_cells(path) if self.cfg.free_space else None
        if yaw is not None:
            s0, gt, *more = turn_cells([s0, gt, *more] + ([] if free is None else [free]), full, yaw)
            if free is not None:
                free = more.pop()
        frees: dict[str, np.ndarray] = {}     # the extra's free-space grids, cropped with the rest
        if cut_height is not None:
            if free is not None and self.cut_free_loss:
                frees["free_loss"] = free                        # the uncut free space, for the loss only
            s0, free = height_cut(s0, free, cut_height)
        if free is not None:
            frees["free"] = free
        sets = [s0, gt, *more]
        focus = focus_cells(s0, gt) if focus_share > 0 else None
        cut, grid = crop_flip(sets + list(frees.values()), full, self.crop, rng, focus, focus_share)
        if not self.cfg.free_space:
            return cut, grid, None
        extra = {k: fs.from_cells(c, grid)[0] for k, c in zip(frees, cut[len(sets):])}
        if cut_height is not None:
            extra["cut"] = cut_layer(cut_height)   # what `CoarseLoss` distils (crops keep z)
        return cut[: len(sets)], grid, extra

    def validate(self, loss_module: CoarseLoss, seed: int = 0) -> dict:
        """IoU (20 cm, visible cells) of full T1 sampling on the first val samples, cropped like training."""
        from hgca_core.metrics.iou import iou

        files = split_files(self.data_dir, "val")[: self.val_count]
        dev = next(loss_module.parameters()).device
        scores = []
        for k, path in enumerate(files):
            rng = np.random.default_rng(1000 + k)  # fixed crops: the curve compares like with like
            vis = visible_cells(path)
            (s0_t, gt_t, vis_t), grid, extra = self.example(path, [vis], rng)
            free = extra["free"][None].to(dev) if extra else None
            gen = torch.Generator(dev).manual_seed(seed + k)
            out = sample(loss_module.model, CellState(cs.with_batch(s0_t.to(dev)), grid), self.cfg.steps, gen,
                         free=free)
            scores.append(iou(out[:, 1:].cpu().numpy(), gt_t.numpy(), vis_t.numpy()))
        loss_module.train()
        return {"val_iou": float(np.nanmean(scores)) if np.any(np.isfinite(scores)) else float("nan")}
