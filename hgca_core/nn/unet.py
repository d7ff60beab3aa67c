"""Sparse residual U-Net shared by both GCA stages (in the spirit of GCA's Mink16UNet34C).

Level l (0 = finest) runs at tensor stride 2**l with channels[l]. Encoder: stem SubMConv -> blocks at
level 0, then per level a stride-2 SparseConv3d down + blocks. Decoder, level 3 (coarsest) .. 0:
SparseConvTranspose3d onto the encoder's cells of that level -> norm -> `modulate(level, x)` (SPADE
de-normalisation hook) -> ReLU -> concat skip -> blocks. Head: per-cell linear at stride 1, so the output
cells are exactly the input cells. No dense tensor is created anywhere.
"""
from __future__ import annotations

from typing import Callable, Sequence

from torch import nn

from hgca_core.nn.sparse import (SparseBatchNorm, SparseConv3d, SparseConvTranspose3d, SparseLinear, SparseReLU,
                                 SparseTensor, SubMConv3d, sparse_cat)

Modulate = Callable[[int, SparseTensor], SparseTensor]


class ResBlock(nn.Module):
    """SubMConv-BN-ReLU-SubMConv-BN + skip (linear projection when channels change), ReLU. Each norm, the sum and
    the ReLUs work on the block's own maps in place (see SparseBatchNorm), never on its input."""

    def __init__(self, cin: int, cout: int) -> None:
        super().__init__()
        self.conv1 = SubMConv3d(cin, cout, 3)
        self.norm1 = SparseBatchNorm(cout, inplace=True)
        self.conv2 = SubMConv3d(cout, cout, 3)
        self.norm2 = SparseBatchNorm(cout, inplace=True)
        self.proj = None if cin == cout else nn.Sequential(SparseLinear(cin, cout, bias=False),
                                                           SparseBatchNorm(cout, inplace=True))
        self.relu = SparseReLU(inplace=True)

    def forward(self, x: SparseTensor) -> SparseTensor:
        h = self.relu(self.norm1(self.conv1(x)))
        h = self.norm2(self.conv2(h))
        skip = x if self.proj is None else self.proj(x)
        return self.relu(h.replace_feats(h.feats.add_(skip.feats)))


def _blocks(cin: int, cout: int, n: int) -> nn.Sequential:
    return nn.Sequential(*[ResBlock(cin if i == 0 else cout, cout) for i in range(max(1, n))])


class SparseUNet(nn.Module):
    """Sparse U-Net with len(channels) - 1 stride-2 levels (4 by default).

    forward(x, modulate=None): x at stride 1 with `in_channels` features -> SparseTensor on the same
    cells with `out_channels` features. `modulate(level, x)` is called once per decoder level
    (level = len(channels) - 2 first, down to 0) right after that level's normalisation and must return
    a tensor on the same cells with the same channels (e.g. x * (1 + gamma) + beta per BEV pillar). x is a map of
    the U-Net's own, which `modulate` may change in place; the U-Net rectifies the result in place, so return x
    or a new map, never a tensor someone else reads.
    """

    def __init__(self, in_channels: int, out_channels: int, channels: Sequence[int] = (32, 48, 64, 96, 128),
                 blocks: int = 1) -> None:
        super().__init__()
        ch = list(channels)
        if len(ch) < 2:
            raise ValueError("SparseUNet needs at least two channel entries (one stride-2 level)")
        self.channels = tuple(ch)
        self.num_levels = len(ch) - 1
        self.in_channels, self.out_channels = in_channels, out_channels
        self.stem = nn.Sequential(SubMConv3d(in_channels, ch[0], 3), SparseBatchNorm(ch[0], inplace=True),
                                  SparseReLU(inplace=True))
        self.enc = nn.ModuleList([_blocks(ch[0], ch[0], blocks)])
        self.down = nn.ModuleList()
        for lvl in range(1, len(ch)):
            self.down.append(nn.Sequential(SparseConv3d(ch[lvl - 1], ch[lvl], 2, 2),
                                           SparseBatchNorm(ch[lvl], inplace=True), SparseReLU(inplace=True)))
            self.enc.append(_blocks(ch[lvl], ch[lvl], blocks))
        # decoder modules indexed by level 0 .. num_levels - 1 (run from the coarsest)
        self.up = nn.ModuleList([SparseConvTranspose3d(ch[lvl + 1], ch[lvl], 2, 2) for lvl in range(self.num_levels)])
        self.up_norm = nn.ModuleList([SparseBatchNorm(ch[lvl], inplace=True) for lvl in range(self.num_levels)])
        self.dec = nn.ModuleList([_blocks(2 * ch[lvl], ch[lvl], blocks) for lvl in range(self.num_levels)])
        self.relu = SparseReLU(inplace=True)  # on the up-convolution's (normalised, modulated) output only
        self.head = SparseLinear(ch[0], out_channels, bias=True)

    def forward(self, x: SparseTensor, modulate: Modulate | None = None) -> SparseTensor:
        if x.stride != 1:
            raise ValueError(f"SparseUNet expects a stride-1 input, got stride {x.stride}")
        h = self.enc[0](self.stem(x))
        skips = [h]
        for lvl in range(1, self.num_levels + 1):
            h = self.enc[lvl](self.down[lvl - 1](h))
            skips.append(h)
        for lvl in range(self.num_levels - 1, -1, -1):
            skip = skips[lvl]
            h = self.up_norm[lvl](self.up[lvl](h, skip))
            if modulate is not None:
                m = modulate(lvl, h)
                if len(m) != len(h) or m.num_channels != h.num_channels:
                    raise ValueError(f"modulate({lvl}) changed the shape: {tuple(h.feats.shape)} -> "
                                     f"{tuple(m.feats.shape)}")
                h = m
            h = self.dec[lvl](sparse_cat(self.relu(h), skip))
        return self.head(h)
