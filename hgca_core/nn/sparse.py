"""Sparse tensors and sparse 3D convolution layers in pure PyTorch.

Conventions (see also `hgca_core.nn.kernel_map`):
- `SparseTensor.coords`: (N, 4) int64 [b, x, y, z], unique, sorted by `coords.pack` key, in units of the
  finest cell; at tensor stride s, x, y, z are multiples of s (MinkowskiEngine's convention, so a cell
  maps to a BEV pillar or a parent by plain integer division whatever its level).
- Conv weights have shape (K, cin, cout) with K kernel offsets in lexicographic (x, y, z) order.
- `cache` is one dict shared by every tensor derived from the same input (feature replacement,
  strided conv outputs, decoder outputs), so each level's kernel maps are built once per forward.
  Entries remember the coords objects they were built from and are rebuilt if those differ.
- `grid`: the (x, y, z) shape, in finest cells, of the box the cells live in (spconv's `spatial_shape`), or
  None where nothing reads it. Set where a tensor is made and kept by every op that derives one from another,
  so what depends on the box (the planner's BEV map under SPADE, the height encoding) reads it from the
  tensor instead of a `grid` argument passed beside it.
- `CellState`: a chain's state (N, 4) cells without features and its grid, what the GCA / cGCA chains pass.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Callable

import torch
from torch import nn

from hgca_core.geometry.coords import pack, unpack
from hgca_core.nn.conv import conv_gemm
from hgca_core.nn.kernel_map import (COORD_LIMIT, KernelMap, downsample_map, identity_map, submanifold_map,
                                     upsample_map)

__all__ = [
    "CellState", "SparseTensor", "sparse_cat", "KernelMap", "SubMConv3d", "SparseConv3d", "SparseConvTranspose3d",
    "SparseLinear", "SparseBatchNorm", "SparseReLU", "conv_gemm",
]


def _cached(cache: dict, key: tuple, refs: tuple[torch.Tensor, ...], build: Callable[[], Any]) -> Any:
    """cache[key] if it was built from the very same coords objects `refs`, else build and store."""
    hit = cache.get(key)
    if hit is not None and len(hit[0]) == len(refs) and all(a is b for a, b in zip(hit[0], refs)):
        return hit[1]
    value = build()
    cache[key] = (refs, value)
    return value


Grid = tuple[int, int, int]


@dataclass(frozen=True, eq=False)
class CellState:
    """(N, 4) int64 cells [b, x, y, z] of a GCA / cGCA chain and the grid (x, y, z cells) they live in.

    Why a type and not a `SparseTensor`: a chain's state has no features, and every step masks it (`state[keep]`),
    renumbers its batches and hands its coords to the `geometry.coords` set operations; a plain tensor there plus
    a `grid` argument beside it went through every signature of both chains (neighbourhood, forward, planner,
    transition, sample). The state that knows its box lets those read it, while the set operations take
    `.coords` as before. Where only membership is read (the kernels' `state` / `s0` inputs) plain tensors stay."""

    coords: torch.Tensor
    grid: Grid

    def __post_init__(self) -> None:
        object.__setattr__(self, "grid", tuple(int(v) for v in self.grid))
        if len(self.grid) != 3:
            raise ValueError(f"grid must be (x, y, z) cells, got {self.grid!r}")

    def __len__(self) -> int:
        return self.coords.shape[0]

    def __getitem__(self, rows: torch.Tensor) -> "CellState":
        """The cells selected by a mask or index, in the same grid."""
        return CellState(self.coords[rows], self.grid)

    def with_coords(self, coords: torch.Tensor) -> "CellState":
        """Other cells (a neighbourhood, a renumbered subset) in the same grid."""
        return CellState(coords, self.grid)

    @property
    def device(self) -> torch.device:
        return self.coords.device


class SparseTensor:
    """Active cells (coords) with features; see the module docstring for the conventions.

    With check=True (the default) the constructor verifies shapes, dtype, order/uniqueness, stride
    alignment and the coordinate range; layers build their outputs with check=False.
    """

    __slots__ = ("coords", "feats", "stride", "cache", "grid")

    def __init__(self, coords: torch.Tensor, feats: torch.Tensor, stride: int = 1,
                 cache: dict | None = None, check: bool = True, grid: Grid | None = None) -> None:
        self.coords = coords
        self.feats = feats
        self.stride = int(stride)
        self.cache = {} if cache is None else cache
        self.grid = None if grid is None else tuple(int(v) for v in grid)
        if check:
            self._check()

    def _check(self) -> None:
        c, f = self.coords, self.feats
        if c.dim() != 2 or c.shape[1] != 4 or c.dtype != torch.int64:
            raise ValueError(f"coords must be (N, 4) int64, got {tuple(c.shape)} {c.dtype}")
        if f.dim() != 2 or f.shape[0] != c.shape[0]:
            raise ValueError(f"feats must be (N, C) with N = {c.shape[0]}, got {tuple(f.shape)}")
        if c.device != f.device:
            raise ValueError(f"coords on {c.device} but feats on {f.device}")
        if self.stride < 1:
            raise ValueError(f"stride must be >= 1, got {self.stride}")
        if self.grid is not None and (len(self.grid) != 3 or min(self.grid) < 1):
            raise ValueError(f"grid must be three positive cell counts, got {self.grid!r}")
        if c.shape[0]:
            if int(c[:, 1:].abs().max()) >= COORD_LIMIT or int(c[:, 0].min()) < 0:
                raise ValueError(f"coords out of range: |x|,|y|,|z| must be < {COORD_LIMIT}, batch >= 0")
            if self.stride > 1 and bool((c[:, 1:] % self.stride != 0).any()):
                raise ValueError(f"coords must be multiples of the tensor stride {self.stride}")
            k = pack(c)
            if k.numel() > 1 and not bool((k[1:] > k[:-1]).all()):
                raise ValueError("coords must be unique and sorted by pack key (use SparseTensor.from_points)")

    @classmethod
    def from_points(cls, coords: torch.Tensor, feats: torch.Tensor, stride: int = 1,
                    reduce: str = "mean", grid: Grid | None = None) -> "SparseTensor":
        """Sort and deduplicate arbitrary cell rows; features of duplicates are averaged or summed."""
        keys, inv = torch.unique(pack(coords.long()), return_inverse=True)
        out = feats.new_zeros((keys.numel(), feats.shape[1])).index_add_(0, inv, feats)
        if reduce == "mean":
            cnt = torch.bincount(inv, minlength=keys.numel()).to(feats.dtype).clamp_(min=1)
            out = out / cnt[:, None]
        elif reduce != "sum":
            raise ValueError(f"reduce must be 'mean' or 'sum', got {reduce!r}")
        return cls(unpack(keys), out, stride, grid=grid)

    # -- basic properties -------------------------------------------------------------------------
    def __len__(self) -> int:
        return self.coords.shape[0]

    def __repr__(self) -> str:
        return (f"SparseTensor(N={len(self)}, C={self.num_channels}, stride={self.stride}, grid={self.grid}, "
                f"dtype={self.feats.dtype}, device={self.device})")

    @property
    def num_channels(self) -> int:
        return self.feats.shape[1]

    @property
    def device(self) -> torch.device:
        return self.feats.device

    @property
    def dtype(self) -> torch.dtype:
        return self.feats.dtype

    @property
    def keys(self) -> torch.Tensor:
        """Sorted packed keys of coords (cached)."""
        return _cached(self.cache, ("keys", self.stride), (self.coords,), lambda: pack(self.coords))

    @property
    def batch(self) -> torch.Tensor:
        return self.coords[:, 0]

    # -- derived tensors --------------------------------------------------------------------------
    def replace_feats(self, feats: torch.Tensor) -> "SparseTensor":
        """Same coords, stride and map cache, new features (what every pointwise op returns)."""
        if feats.shape[0] != self.coords.shape[0]:
            raise ValueError(f"replace_feats: expected {self.coords.shape[0]} rows, got {feats.shape[0]}")
        return SparseTensor(self.coords, feats, self.stride, self.cache, check=False, grid=self.grid)

    def to(self, *args: Any, **kwargs: Any) -> "SparseTensor":
        """Move / cast features (dtype casts keep coords int64); a device move starts a new cache."""
        feats = self.feats.to(*args, **kwargs)
        if feats.device == self.coords.device:
            return SparseTensor(self.coords, feats, self.stride, self.cache, check=False, grid=self.grid)
        return SparseTensor(self.coords.to(feats.device), feats, self.stride, None, check=False, grid=self.grid)

    def cpu(self) -> "SparseTensor":
        return self.to("cpu")

    def cuda(self) -> "SparseTensor":
        return self.to("cuda")

    def detach(self) -> "SparseTensor":
        return self.replace_feats(self.feats.detach())


def sparse_cat(*tensors: SparseTensor) -> SparseTensor:
    """Concatenate features of tensors on the same coords (the U-Net skip connection)."""
    if not tensors:
        raise ValueError("sparse_cat needs at least one tensor")
    first = tensors[0]
    for t in tensors[1:]:
        if t.stride != first.stride or (t.coords is not first.coords and not torch.equal(t.coords, first.coords)):
            raise ValueError("sparse_cat: tensors must share coords and stride")
    return first.replace_feats(torch.cat([t.feats for t in tensors], dim=1))


# -- convolution layers ---------------------------------------------------------------------------
def _init_weight(weight: torch.Tensor, fan_in: int) -> None:
    # Kaiming-uniform for ReLU nets (gain sqrt 2): keeps activations O(1) through the U-Net.
    bound = math.sqrt(6.0 / max(1, fan_in))
    nn.init.uniform_(weight, -bound, bound)


class _ConvBase(nn.Module):
    def __init__(self, cin: int, cout: int, kvol: int, bias: bool) -> None:
        super().__init__()
        self.in_channels, self.out_channels = cin, cout
        self.weight = nn.Parameter(torch.empty(kvol, cin, cout))
        self.bias = nn.Parameter(torch.zeros(cout)) if bias else None
        _init_weight(self.weight.data, kvol * cin)

    def _apply_conv(self, feats: torch.Tensor, kmap: KernelMap) -> torch.Tensor:
        if feats.shape[1] != self.in_channels:
            raise ValueError(f"{type(self).__name__}: expected {self.in_channels} channels, got {feats.shape[1]}")
        out = conv_gemm(feats, self.weight, kmap)
        return out + self.bias if self.bias is not None else out


class SubMConv3d(_ConvBase):
    """Submanifold conv: outputs on the input cells; offsets d in [-k//2, k//2]^3 scaled by the stride.

    weight[k] = dense `conv3d` weight[:, :, dx + r, dy + r, dz + r].T (cross-correlation, padding k//2).
    """

    def __init__(self, in_channels: int, out_channels: int, kernel_size: int = 3, bias: bool = False) -> None:
        if kernel_size % 2 != 1:
            raise ValueError(f"SubMConv3d kernel_size must be odd, got {kernel_size}")
        super().__init__(in_channels, out_channels, kernel_size ** 3, bias)
        self.kernel_size = kernel_size

    def forward(self, x: SparseTensor) -> SparseTensor:
        if self.kernel_size == 1:
            return x.replace_feats(self._apply_conv(x.feats, identity_map(len(x), x.device)))
        kmap = _cached(x.cache, ("subm", x.stride, self.kernel_size), (x.coords,),
                       lambda: submanifold_map(x.keys, self.kernel_size, x.stride, x.coords))
        return x.replace_feats(self._apply_conv(x.feats, kmap))

    def extra_repr(self) -> str:
        return f"{self.in_channels}, {self.out_channels}, kernel_size={self.kernel_size}, bias={self.bias is not None}"


class SparseConv3d(_ConvBase):
    """Strided conv with kernel_size == stride (non-overlapping): outputs on the unique parents
    floor(c / (s f)) * s f of the active cells, tensor stride s -> s f.

    weight[k] = dense `conv3d(kernel=f, stride=f)` weight[:, :, ox, oy, oz].T, o = child position in parent.
    """

    def __init__(self, in_channels: int, out_channels: int, kernel_size: int = 2, stride: int = 2,
                 bias: bool = False) -> None:
        if kernel_size != stride or stride < 2:
            raise ValueError(f"SparseConv3d supports kernel_size == stride >= 2, got {kernel_size}, {stride}")
        super().__init__(in_channels, out_channels, stride ** 3, bias)
        self.factor = stride

    def forward(self, x: SparseTensor) -> SparseTensor:
        coords, kmap = _cached(x.cache, ("down", x.stride, self.factor), (x.coords,),
                               lambda: downsample_map(x.coords, x.stride, self.factor))
        feats = self._apply_conv(x.feats, kmap)
        return SparseTensor(coords, feats, x.stride * self.factor, x.cache, check=False, grid=x.grid)

    def extra_repr(self) -> str:
        return f"{self.in_channels}, {self.out_channels}, kernel_size={self.factor}, stride={self.factor}"


class SparseConvTranspose3d(_ConvBase):
    """Transposed conv with kernel_size == stride onto given finer cells (`target`, e.g. the encoder
    skip), so decoder outputs land exactly on them; a target cell with no active parent gets zeros
    (+ bias).

    weight[k] = dense `conv_transpose3d` weight[:, :, ox, oy, oz] (shape cin x cout).
    """

    def __init__(self, in_channels: int, out_channels: int, kernel_size: int = 2, stride: int = 2,
                 bias: bool = False) -> None:
        if kernel_size != stride or stride < 2:
            raise ValueError(f"SparseConvTranspose3d supports kernel_size == stride >= 2, got {kernel_size}, {stride}")
        super().__init__(in_channels, out_channels, stride ** 3, bias)
        self.factor = stride
        _init_weight(self.weight.data, in_channels)     # each output cell receives exactly one tap

    def forward(self, x: SparseTensor, target: SparseTensor) -> SparseTensor:
        f = self.factor
        if target.stride * f != x.stride:
            raise ValueError(f"target stride {target.stride} x {f} != input stride {x.stride}")

        def build() -> KernelMap:
            # The decoder's target is usually the very set x was downsampled from: reuse that map.
            for cache in (target.cache, x.cache):
                hit = cache.get(("down", target.stride, f))
                if hit is not None and hit[0][0] is target.coords and hit[1][0] is x.coords:
                    return hit[1][1].transposed()
            return upsample_map(x.keys, target.coords, target.stride, f)

        kmap = _cached(x.cache, ("up", x.stride, f), (x.coords, target.coords), build)
        feats = self._apply_conv(x.feats, kmap)
        return SparseTensor(target.coords, feats, target.stride, target.cache, check=False,
                            grid=target.grid if target.grid is not None else x.grid)

    def extra_repr(self) -> str:
        return f"{self.in_channels}, {self.out_channels}, kernel_size={self.factor}, stride={self.factor}"


class SparseLinear(_ConvBase):
    """Per-cell linear map of features (a 1x1x1 conv, weight (1, cin, cout)); runs through the conv
    backend so it is thread-count deterministic like the other layers."""

    def __init__(self, in_channels: int, out_channels: int, bias: bool = True) -> None:
        super().__init__(in_channels, out_channels, 1, bias)
        if bias:
            bound = 1.0 / math.sqrt(max(1, in_channels))
            nn.init.uniform_(self.bias, -bound, bound)

    def forward(self, x: SparseTensor) -> SparseTensor:
        return x.replace_feats(self._apply_conv(x.feats, identity_map(len(x), x.device)))

    def extra_repr(self) -> str:
        return f"{self.in_channels}, {self.out_channels}, bias={self.bias is not None}"


# -- normalisation and activation -----------------------------------------------------------------
class SparseBatchNorm(nn.Module):
    """BatchNorm1d over the features of all active cells of the batch.

    `inplace`: the input's features are a fresh map that nothing else reads (a convolution's output). Then, at
    inference on the CPU (running statistics, no autograd), they are normalised where they lie, bit for bit as
    BatchNorm1d would: each fresh map costs a page fault per 4 KiB. With the U-Nets' sums and ReLUs also in place,
    a default-region full completion took 3.0 M faults instead of 4.5 M and 43.3 s instead of 46.7 s
    (`benchmarks/results/inplace_full.md`, in git at 7f06b18). CUDA's caching allocator reuses its blocks, so CUDA keeps torch's
    path, as does training (BN's backward needs its input)."""

    def __init__(self, channels: int, eps: float = 1e-5, momentum: float = 0.1, affine: bool = True,
                 inplace: bool = False) -> None:
        super().__init__()
        self.bn = nn.BatchNorm1d(channels, eps=eps, momentum=momentum, affine=affine)
        self.inplace = inplace

    def forward(self, x: SparseTensor) -> SparseTensor:
        bn, f = self.bn, x.feats
        if (self.inplace and not bn.training and bn.running_mean is not None and f.is_cpu
                and not torch.is_grad_enabled()):
            spare = f.new_empty(0)
            torch.ops.aten.native_batch_norm.out(f, bn.weight, bn.bias, bn.running_mean, bn.running_var, False, 0.0,
                                                 bn.eps, out=f, save_mean=spare, save_invstd=spare.clone())
            return x
        return x.replace_feats(bn(f))


class SparseReLU(nn.Module):
    def __init__(self, inplace: bool = False) -> None:
        super().__init__()
        self.inplace = inplace

    def forward(self, x: SparseTensor) -> SparseTensor:
        return x.replace_feats(torch.relu_(x.feats) if self.inplace else torch.relu(x.feats))
