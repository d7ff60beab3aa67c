"""Sparse U-Net: shapes, cells, the modulate hook, gradients, a tiny overfitting sanity check, and the grid that
every derived tensor keeps."""
from __future__ import annotations

import pytest
import torch

from hgca_core.geometry.coords import unique
from hgca_core.nn.sparse import (CellState, SparseBatchNorm, SparseConv3d, SparseConvTranspose3d, SparseLinear,
                                 SparseReLU, SparseTensor, SubMConv3d, sparse_cat)
from hgca_core.nn.unet import SparseUNet


def scene(gen: torch.Generator, batch: int = 2, size: int = 24) -> torch.Tensor:
    """Surface-like cells: a wavy ground plane and a wall per sample."""
    rows = []
    for b in range(batch):
        xs, ys = torch.meshgrid(torch.arange(size), torch.arange(size), indexing="ij")
        zs = (2 + (torch.sin(xs / 3.0 + b) * 1.5).round()).long()
        ground = torch.stack([torch.full_like(xs, b), xs, ys, zs], -1).reshape(-1, 4)
        wy, wz = torch.meshgrid(torch.arange(size), torch.arange(3, 12), indexing="ij")
        wall = torch.stack([torch.full_like(wy, b), torch.full_like(wy, 5 + 7 * b), wy, wz], -1).reshape(-1, 4)
        rows += [ground, wall]
    c = unique(torch.cat(rows))
    keep = torch.rand(len(c), generator=gen) < 0.8
    return c[keep]


@pytest.fixture
def gen() -> torch.Generator:
    return torch.Generator().manual_seed(0)


def test_unet_forward_backward_and_modulate(gen: torch.Generator) -> None:
    torch.manual_seed(0)
    coords = scene(gen)
    net = SparseUNet(5, 3, channels=(8, 12, 16, 20, 24))
    x = SparseTensor(coords, torch.randn(len(coords), 5, generator=gen))
    seen: list[tuple[int, int, int]] = []

    def modulate(level: int, h: SparseTensor) -> SparseTensor:
        seen.append((level, h.stride, h.num_channels))
        return h.replace_feats(h.feats * 1.5 + 0.1)

    y = net(x, modulate=modulate)
    assert y.coords is x.coords and y.stride == 1 and y.feats.shape == (len(coords), 3)
    assert seen == [(3, 8, 20), (2, 4, 16), (1, 2, 12), (0, 1, 8)]
    y.feats.square().mean().backward()
    for name, p in net.named_parameters():
        assert p.grad is not None and torch.isfinite(p.grad).all(), name
    assert net.stem[0].weight.grad.abs().sum() > 0


def test_modulate_changes_output_and_shape_is_checked(gen: torch.Generator) -> None:
    torch.manual_seed(0)
    coords = scene(gen, batch=1)
    net = SparseUNet(2, 2, channels=(8, 8, 8, 8, 8)).eval()
    x = SparseTensor(coords, torch.randn(len(coords), 2, generator=gen))
    with torch.no_grad():
        base = net(x).feats
        same = net(x, modulate=lambda lvl, h: h).feats
        shifted = net(x, modulate=lambda lvl, h: h.replace_feats(h.feats + (lvl == 3))).feats
    torch.testing.assert_close(base, same, rtol=0, atol=0)
    assert (base - shifted).abs().max() > 1e-3
    with pytest.raises(ValueError, match="modulate"):
        net(x, modulate=lambda lvl, h: h.replace_feats(h.feats[:, :4]))


def test_unet_batches_do_not_mix(gen: torch.Generator) -> None:
    """At inference (batch norm on its running statistics), sample 0's output ignores sample 1's cells."""
    torch.manual_seed(0)
    coords = scene(gen)
    feats = torch.randn(len(coords), 2, generator=gen, dtype=torch.float64)
    net = SparseUNet(2, 2, channels=(4, 4, 4, 4, 4)).double()
    with torch.no_grad():      # running statistics that are not the identity, so they matter
        net(SparseTensor(coords, feats * 3 + 1))
    net.eval()
    m = coords[:, 0] == 0
    with torch.no_grad():
        both = net(SparseTensor(coords, feats)).feats[m]
        alone = net(SparseTensor(coords[m], feats[m])).feats
    torch.testing.assert_close(both, alone, rtol=1e-9, atol=1e-9)


def test_unet_overfits_tiny_occupancy(gen: torch.Generator) -> None:
    """A 3-level net learns a fixed per-cell occupancy pattern from positions in 50 Adam steps."""
    torch.manual_seed(0)
    coords = scene(gen, batch=1, size=16)
    pos = coords[:, 1:].float() / 16.0
    target = ((coords[:, 1] // 4 + coords[:, 2] // 4 + coords[:, 3]) % 2).float()
    net = SparseUNet(3, 1, channels=(16, 24, 32, 48))
    opt = torch.optim.Adam(net.parameters(), lr=1e-2)
    x = SparseTensor(coords, pos)
    losses = []
    for _ in range(50):
        opt.zero_grad()
        logits = net(x).feats[:, 0]
        loss = torch.nn.functional.binary_cross_entropy_with_logits(logits, target)
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert losses[-1] < 0.25 * losses[0], losses[::10]
    net.eval()
    with torch.no_grad():
        acc = ((net(x).feats[:, 0] > 0).float() == target).float().mean()
    assert acc > 0.9


def test_inference_in_place_matches_autograd_path_and_leaves_the_input_alone(gen: torch.Generator) -> None:
    """At inference the blocks normalise, add and rectify their own maps in place; the result is bit for bit the
    out-of-place path's (what runs when gradients are on), and the caller's features are not touched."""
    torch.manual_seed(0)
    coords = scene(gen)
    net = SparseUNet(5, 3, channels=(8, 12, 16, 20, 24), blocks=2)
    x = SparseTensor(coords, torch.randn(len(coords), 5, generator=gen) * 3 + 1)
    with torch.no_grad():
        for _ in range(3):          # running statistics away from (0, 1)
            net(x)
    net.eval()
    before = x.feats.clone()
    scale = 1 + torch.rand(20, generator=gen)

    def modulate(level: int, h: SparseTensor) -> SparseTensor:
        return h.replace_feats(h.feats * scale[:h.num_channels])

    with torch.no_grad():
        fast = net(x, modulate=modulate).feats
    slow = net(x, modulate=modulate).feats.detach()          # gradients on: torch's out-of-place modules
    assert torch.equal(x.feats, before)
    assert torch.equal(fast, slow) and fast.abs().max() > 0
    block = net.enc[0][0]                                     # a residual block alone, identity skip
    h = SparseTensor(coords, torch.randn(len(coords), 8, generator=gen))
    kept = h.feats.clone()
    with torch.no_grad():
        block(h)
    assert torch.equal(h.feats, kept)


def test_the_grid_travels_with_every_tensor_made_from_another() -> None:
    """The box a tensor lives in is set where it is made and kept by each op and every U-Net level (what SPADE
    reads), so nothing downstream is handed it beside the tensor; a tensor made without one has none."""
    gen = torch.Generator().manual_seed(0)
    coords = scene(gen, batch=1, size=16)
    x = SparseTensor.from_points(coords, torch.randn(len(coords), 4, generator=gen), grid=(16, 16, 20))
    assert x.grid == (16, 16, 20)
    down = SparseConv3d(4, 4)(x)
    made = [x.replace_feats(x.feats * 2), x.to(torch.float64), x.detach(), SubMConv3d(4, 4)(x), down,
            SparseConvTranspose3d(4, 4)(down, x), SparseLinear(4, 4)(x), SparseBatchNorm(4)(x), SparseReLU()(x),
            sparse_cat(x, x)]
    assert [t.grid for t in made] == [(16, 16, 20)] * len(made)
    seen = []

    def modulate(level: int, t: SparseTensor) -> SparseTensor:
        seen.append(t.grid)
        return t

    net = SparseUNet(4, 2, channels=(8, 8, 8))
    assert net(x, modulate=modulate).grid == (16, 16, 20) and seen == [(16, 16, 20)] * 2
    assert SparseTensor(coords, torch.zeros(len(coords), 1)).grid is None
    with pytest.raises(ValueError, match="grid"):
        SparseTensor(coords, torch.zeros(len(coords), 1), grid=(16, 0, 20))
    state = CellState(coords, (16, 16, 20))
    assert state[coords[:, 3] > 3].grid == state.with_coords(coords[:2]).grid == (16, 16, 20)
    with pytest.raises(ValueError, match="grid"):
        CellState(coords, (16, 16))
