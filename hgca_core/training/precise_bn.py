"""Precise BatchNorm statistics for the coarse kernel: averaged over many batches instead of the last few.

Why: the trainer exports the EMA of the parameters but copies BatchNorm's running mean and variance from the live
model, where they are a momentum-0.1 average over its last ~10 batches of two crops: a noisy estimate, and one made
for other (the live) weights. The coarse chain compounds any shift over its 30 steps: swapping only these buffers
between the shipped weights and a checkpoint 388 steps later moved the growth above a 2 m cut on a real AV2 log
from 16,848 to 27,228 cells (session 14). `recompute_bn_training` averages them over many training batches drawn
as the trainer draws them (what `torch.optim.swa_utils.update_bn` does for averaged weights; Wu & Johnson,
"Rethinking 'Batch' in BatchNorm", 2021: precise BN); `recompute_bn` over chains the model samples itself from
whole regions or from one input (as inference sees them; AdaBN when that input is the one to complete).
"""
from __future__ import annotations

from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch
from torch import nn

from hgca_core.geometry import coords as cs
from hgca_core.models import free as fs
from hgca_core.models.gca import GCAKernel, transition

if TYPE_CHECKING:
    from hgca_core.training.coarse import CoarseTask


@contextmanager
def _cumulative_bn(model: nn.Module) -> Iterator[None]:
    """Inside: every BatchNorm starts from reset statistics and averages the batch statistics of each forward pass
    in train mode (momentum None: a plain cumulative average, not an exponential one), without gradients. After:
    momenta restored, model in eval mode."""
    bns = [m for m in model.modules() if isinstance(m, nn.modules.batchnorm._BatchNorm)]
    momenta = [bn.momentum for bn in bns]
    for bn in bns:
        bn.reset_running_stats()
        bn.momentum = None
    model.train()
    try:
        with torch.no_grad():
            yield
    finally:
        for bn, m in zip(bns, momenta):
            bn.momentum = m
        model.eval()


def recompute_bn(model: GCAKernel, inputs: Sequence[tuple[torch.Tensor, torch.Tensor | None]],
                 grid: tuple[int, int, int], steps: int, seed: int = 0) -> int:
    """Replace every BatchNorm's running statistics by their average over the forward passes of chains run from
    `inputs` ((N, 3) cells of s0, (*grid) bool seen-empty or None), each pass normalised by its own batch
    statistics as in training; returns the number of passes. The model is left in eval mode."""
    gen = torch.Generator().manual_seed(seed)
    passes = 0
    with _cumulative_bn(model):
        for cells, free in inputs:
            s0 = cs.with_batch(cells.long())
            free_b = None if free is None else free[None]
            bev = model.bev(s0, 1, grid, free_b)
            state = s0
            for _ in range(steps):
                nbhd, prob = transition(model, state, s0, grid, bev, free_b)
                passes += 1
                state = nbhd[torch.rand(prob.shape, generator=gen) < prob]
                if len(state) == 0:
                    break
    return passes


def recompute_bn_training(model: GCAKernel, task: "CoarseTask", batches: int, batch: int = 2, buffer_size: int = 8,
                          seed: int = 0) -> int:
    """Replace every BatchNorm's running statistics by their average over `batches` training batches of `task`,
    drawn and advanced exactly as the trainer does (crops, infusion chains) but without a weight update; returns
    `batches`. For weights that are an average (the trainer's EMA), whose copied statistics belong to the last
    few batches of the live weights: what `torch.optim.swa_utils.update_bn` does for averaged weights."""
    from hgca_core.training.buffer import ChainBuffer
    from hgca_core.training.coarse import CoarseLoss

    loss_module = CoarseLoss(model.cfg, task.free_weight)
    loss_module.model = model
    torch.manual_seed(seed)        # the infusion draws
    buffer = ChainBuffer(buffer_size, task.new_example, model.cfg.steps, np.random.default_rng(seed))
    with _cumulative_bn(model):
        for _ in range(batches):
            idx = buffer.take(batch)
            _, _, states = loss_module([buffer.chains[i] for i in idx])
            for i, st in zip(idx, states):
                buffer.advance(i, st)
    return batches


def train_inputs(files: Sequence[str | Path], cfg_free: bool, cut_share: float = 0.5,
                 seed: int = 0) -> list[tuple[torch.Tensor, torch.Tensor | None]]:
    """Whole-region inputs of train samples as the trainer sees them before cropping: a `cut_share` of them cut
    1.5-3 m above the ground (with the free space above the cut unknown), the rest uncut."""
    from hgca_core.training.coarse import CUT_HEIGHTS, height_cut
    from hgca_core.training.data import coarse_pair, free_cells

    rng = np.random.default_rng(seed)
    out = []
    for path in files:
        s0, _, grid = coarse_pair(path)
        free = free_cells(path) if cfg_free else None
        if rng.random() < cut_share:
            s0, free = height_cut(s0, free, CUT_HEIGHTS[0] + rng.random() * (CUT_HEIGHTS[1] - CUT_HEIGHTS[0]))
        dense = fs.from_cells(torch.as_tensor(free), grid)[0] if free is not None else None
        out.append((torch.as_tensor(s0), dense))
    return out
