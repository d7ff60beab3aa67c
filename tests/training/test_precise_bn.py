"""Precise BatchNorm: the running statistics become the plain average of the passes' batch statistics, whatever
they held before, and the model comes back in eval mode with its momenta."""
import torch
from torch import nn

from hgca_core.models.gca import GCAConfig, GCAKernel
from hgca_core.training.coarse import CoarseTask
from hgca_core.training.precise_bn import recompute_bn, recompute_bn_training

GRID = (24, 24, 20)


def _plane(z):
    xy = torch.stack(torch.meshgrid(torch.arange(4, 20), torch.arange(4, 20), indexing="ij"), -1).reshape(-1, 2)
    return torch.cat([xy, torch.full((len(xy), 1), z)], 1)


def test_running_stats_become_the_average_of_the_passes_batch_stats():
    torch.manual_seed(0)
    m = GCAKernel(GCAConfig(channels=(8, 8, 16, 16, 16), use_planner=False, grid=GRID))
    stem = m.unet.stem[1].bn
    stem.running_mean.fill_(7.0)                        # stale statistics from somewhere else
    seen = []
    stem.register_forward_hook(lambda mod, inp, out: seen.append(inp[0].detach().clone()))
    passes = recompute_bn(m, [(_plane(5), None), (_plane(9), None)], GRID, steps=2, seed=3)
    assert passes == len(seen) == 4 and not m.training
    assert all(bn.momentum == 0.1 for bn in m.modules() if isinstance(bn, nn.BatchNorm1d))
    want = torch.stack([x.mean(0) for x in seen]).mean(0)   # cumulative average of the per-pass batch means
    assert torch.allclose(stem.running_mean, want, atol=1e-5)
    assert int(stem.num_batches_tracked) == 4
    again = GCAKernel(GCAConfig(channels=(8, 8, 16, 16, 16), use_planner=False, grid=GRID))
    again.load_state_dict(m.state_dict())
    assert recompute_bn(again, [(_plane(5), None), (_plane(9), None)], GRID, steps=2, seed=3) == 4
    assert torch.allclose(again.unet.stem[1].bn.running_mean, stem.running_mean, atol=1e-6)   # seeded: repeatable


def test_training_batches_set_the_statistics_and_leave_the_weights(tiny_dataset):
    """The averaged-weights case: statistics from `batches` batches drawn as the trainer draws them; the
    parameters are untouched and the same seed gives the same statistics."""
    cfg = GCAConfig(channels=(8, 8, 16, 16, 16), steps=3, free_space=True)
    task = CoarseTask(str(tiny_dataset), cfg, crop=16, cut_share=0.5)
    torch.manual_seed(0)
    m = GCAKernel(cfg)
    params = {k: v.clone() for k, v in m.named_parameters()}
    stem = m.unet.stem[1].bn
    stem.running_var.fill_(50.0)
    seen = []
    stem.register_forward_hook(lambda mod, inp, out: seen.append(inp[0].detach().clone()))
    assert recompute_bn_training(m, task, batches=5, seed=1) == 5
    assert len(seen) == 5 and not m.training and int(stem.num_batches_tracked) == 5
    want = torch.stack([x.var(0) for x in seen]).mean(0)     # unbiased batch variances, averaged
    assert torch.allclose(stem.running_var, want, rtol=1e-4, atol=1e-6)
    assert all(torch.equal(v, params[k]) for k, v in m.named_parameters())
    first = stem.running_mean.clone()
    assert recompute_bn_training(m, task, batches=5, seed=1) == 5
    assert torch.allclose(stem.running_mean, first, atol=1e-6)
