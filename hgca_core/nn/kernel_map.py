"""Kernel maps: for every kernel offset, the (input row, output row) pairs a sparse convolution touches.

Coordinates are (N, 4) int64 [b, x, y, z] rows in units of the finest cell (a tensor at stride s has
x, y, z that are multiples of s), unique and sorted by `hgca_core.geometry.coords.pack`. Because `pack`
is linear in each field, the key of c + d is key(c) + delta(d): the neighbour queries of a kernel are
one broadcast add and one `searchsorted` into the sorted key table, with no per-offset Python work
(and only one query per neighbour *column*, see `_neighbours_half`).

Offset order (= first axis of every conv weight, shape (K, cin, cout)): lexicographic over (x, y, z),
the order of `itertools.product` and of `coords.offsets`. For a submanifold kernel of size k the offset
index of d in [-r, r]^3 (r = k // 2) is (dx + r) k^2 + (dy + r) k + (dz + r), i.e. dense weight
w[cout, cin, dx + r, dy + r, dz + r]; for a strided / transposed kernel of size f it is ox f^2 + oy f + oz
with the child's position o in [0, f)^3 inside its parent cell.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import torch

from hgca_core.geometry.coords import offsets, pack, unpack
from hgca_core.geometry.keys import OFFSET, delta
from hgca_core.nn.row_grid import RowGrid, all_offsets, half_offsets, parents_dense

# Coordinates (finest units) must stay this far inside pack's [-OFFSET, OFFSET) field so that neighbour
# keys (c + d) never borrow from the next field and alias a different cell.
COORD_LIMIT = OFFSET - 4096
# Maps with at least this share of filled (output, offset) slots run output-stationary (`conv.table_gemm`);
# measured per layer on a coarse step: the table wins at level 0 (density 0.78), pairs win at 0.5 and below.
TABLE_MIN_DENSITY = 0.6


@dataclass(frozen=True)
class KernelMap:
    """Pairs of one convolution, concatenated over kernel offsets.

    Pairs of offset k are rows splits[k]:splits[k+1] of in_idx / out_idx (output row out_idx[p] receives
    feats[in_idx[p]] @ W[k]). `identity` names an offset whose pairs are the identity (the centre of a
    submanifold kernel); its segment is empty and the convolution handles it with one plain GEMM.

    Every map built here has at most one pair per (output, offset), so it can also be read as a
    neighbour `table` (n_out, K). `symmetric` marks submanifold maps, whose adjoint is the same map with
    the offsets reversed (the pairs of -d are those of d swapped).
    """

    in_idx: torch.Tensor
    out_idx: torch.Tensor
    splits: tuple[int, ...]
    n_in: int
    n_out: int
    identity: int | None = None
    symmetric: bool = False

    @property
    def volume(self) -> int:
        return len(self.splits) - 1

    @property
    def num_pairs(self) -> int:
        """Pairs including the implicit identity ones."""
        return int(self.splits[-1]) + (self.n_in if self.identity is not None else 0)

    @property
    def density(self) -> float:
        """Share of (output, offset) slots that hold a pair: how much of a dense table would be real work."""
        return self.num_pairs / max(1, self.n_out * self.volume)

    @cached_property
    def table(self) -> torch.Tensor:
        """(n_out, K) int64: the input row of each (output, offset), n_in where there is none (built once)."""
        t = torch.full((self.n_out, self.volume), self.n_in, dtype=torch.long, device=self.in_idx.device)
        for k in range(self.volume):
            a, b = self.splits[k], self.splits[k + 1]
            t[self.out_idx[a:b], k] = self.in_idx[a:b]
        if self.identity is not None:
            t[:, self.identity] = torch.arange(self.n_in, device=t.device)
        return t

    def transposed(self) -> "KernelMap":
        """The map with inputs and outputs swapped (the adjoint: down map <-> up map, grad_in pass)."""
        return KernelMap(self.out_idx, self.in_idx, self.splits, self.n_out, self.n_in, self.identity, self.symmetric)

    def to(self, device: torch.device | str) -> "KernelMap":
        return KernelMap(self.in_idx.to(device), self.out_idx.to(device), self.splits, self.n_in,
                         self.n_out, self.identity, self.symmetric)

    def chunks(self, rows: int) -> list[tuple[int, int, list[tuple[int, int, int]]]]:
        """Cut the pair list into row ranges of at most `rows` pairs.

        Returns (r0, r1, pieces) with pieces (k, a, b): rows a:b of the chunk (chunk-relative) belong to
        offset k. One gather and one scatter per chunk, one GEMM per piece.
        """
        out: list[tuple[int, int, list[tuple[int, int, int]]]] = []
        total = self.splits[-1]
        r0 = 0
        while r0 < total:
            r1 = min(total, r0 + rows)
            pieces = []
            for k in range(self.volume):
                a, b = max(self.splits[k], r0), min(self.splits[k + 1], r1)
                if b > a:
                    pieces.append((k, a - r0, b - r0))
            out.append((r0, r1, pieces))
            r0 = r1
        return out


def _splits(counts: torch.Tensor) -> tuple[int, ...]:
    c = [0]
    for n in counts.tolist():
        c.append(c[-1] + int(n))
    return tuple(c)


def _neighbours_half(keys: torch.Tensor, r: int, stride: int) -> tuple[torch.Tensor, torch.Tensor]:
    """For the offsets before the centre (lexicographic order), whether c + d is active and its row.

    Cells of one (b, x, y) column are contiguous in key order and sorted by z, so one `searchsorted`
    per neighbour column (for z - r s) finds all k = 2r + 1 z-offsets within the next k rows: (k^2 - 1)/2
    searches of N queries instead of (k^3 - 1)/2. Returns found (centre, N) bool and rows (centre, N).
    """
    n, dev, k = keys.numel(), keys.device, 2 * r + 1
    cols = [(dx, dy) for dx in range(-r, 1) for dy in range(-r, r + 1) if dx < 0 or dy < 0]
    m = len(cols)
    d = torch.tensor([[dx * stride, dy * stride, -r * stride] for dx, dy in cols], device=dev)
    base = keys[None, :] + delta(d)[:, None]                              # (m, N): z - r s
    p = torch.searchsorted(keys, base.reshape(-1)).view(m, n)
    steps = torch.arange(k, device=dev)
    cand_rows = (p[:, None, :] + steps[None, :, None]).clamp_(max=n - 1)      # (m, j, N)
    cand = keys[cand_rows]
    target = base[:, None, :] + (steps * stride)[None, :, None]               # (m, dz, N)
    hit = torch.zeros((m, k, n), dtype=torch.bool, device=dev)
    rows = torch.zeros((m, k, n), dtype=torch.long, device=dev)
    for j in range(k):                      # keys are unique: each target matches at most one j
        e = cand[:, j:j + 1, :] == target
        hit |= e
        rows = torch.where(e, cand_rows[:, j:j + 1, :], rows)
    # own column, dz = -r .. -1: the candidates are the r rows just before the cell
    own = torch.arange(n, device=dev)
    own_rows = (own[None, :] - torch.arange(1, r + 1, device=dev)[:, None]).clamp_(min=0)   # (j, N)
    own_cand = keys[own_rows]
    own_target = keys[None, :] + (torch.arange(-r, 0, device=dev) * stride)[:, None]       # (dz, N)
    own_hit = torch.zeros((r, n), dtype=torch.bool, device=dev)
    own_idx = torch.zeros((r, n), dtype=torch.long, device=dev)
    for j in range(r):
        e = own_cand[j:j + 1] == own_target
        own_hit |= e
        own_idx = torch.where(e, own_rows[j:j + 1], own_idx)
    return torch.cat([hit.view(m * k, n), own_hit]), torch.cat([rows.view(m * k, n), own_idx])


def submanifold_map(keys: torch.Tensor, kernel_size: int, stride: int,
                    coords: torch.Tensor | None = None) -> KernelMap:
    """Map of a submanifold conv (outputs = inputs) from the sorted keys of the active set (and its coords,
    when the caller has them: `unpack(keys)`).

    Only the offsets before the centre are searched: the pairs of -d are those of d swapped, and the
    centre is the identity. A set whose box is small enough (`row_grid.DENSE_MAP_LIMIT`) is searched in a dense
    grid of row numbers, which also gives the neighbour `table` at once when the map is dense enough to run by
    table; the map is the same either way.
    """
    if kernel_size % 2 != 1:
        raise ValueError(f"submanifold kernel_size must be odd, got {kernel_size}")
    n = keys.numel()
    dev = keys.device
    kvol = kernel_size ** 3
    centre = kvol // 2
    if kvol == 1 or n == 0:
        e = torch.empty(0, dtype=torch.long, device=dev)
        return KernelMap(e, e, (0,) * (kvol + 1), n, n, centre, True)
    r = kernel_size // 2
    grid = RowGrid(unpack(keys) if coords is None else coords, stride, r)
    if grid.fits:
        grid.fill()
        rows = [grid.at(d) for d in half_offsets(r)]
        found = [q >= 0 for q in rows]
        half_out = [f.nonzero().squeeze(1) for f in found]
        half_in = [q[o].long() for q, o in zip(rows, half_out)]
        counts = torch.tensor([len(o) for o in half_out])
    else:
        found_all, idx = _neighbours_half(keys, r, stride)
        counts = found_all.sum(1)
        seg = _splits(counts)
        nz = found_all.reshape(-1).nonzero().squeeze(1)
        out_all, in_all = nz % n, idx.reshape(-1)[nz]
        half_out = [out_all[seg[k]:seg[k + 1]] for k in range(centre)]
        half_in = [in_all[seg[k]:seg[k + 1]] for k in range(centre)]
    ins = half_in + half_out[::-1]                              # offset K-1-k = -d_k: swapped pairs
    outs = half_out + half_in[::-1]
    all_counts = counts.tolist() + [0] + counts.flip(0).tolist()
    kmap = KernelMap(torch.cat(ins), torch.cat(outs), _splits(torch.tensor(all_counts)), n, n, centre, True)
    if grid.fits and kmap.density >= TABLE_MIN_DENSITY:
        # the table `KernelMap.table` would build from the pairs, one gather per offset
        cols = [torch.arange(n, dtype=torch.int32, device=dev) if k == centre else
                (rows[k] if k < centre else grid.at(d)) for k, d in enumerate(all_offsets(r))]
        t = torch.stack(cols, dim=1)                                 # (n, K) int32, -1 where none
        kmap.__dict__["table"] = torch.where(t >= 0, t, n).long()   # the cached_property's slot
    return kmap


def submanifold_map_reference(keys: torch.Tensor, kernel_size: int, stride: int) -> KernelMap:
    """Straightforward version (one searchsorted over all half offsets), kept to test the fast one."""
    n, dev = keys.numel(), keys.device
    offs = offsets(kernel_size // 2, device=dev) * stride
    kvol = len(offs)
    centre = kvol // 2
    if kvol == 1 or n == 0:
        e = torch.empty(0, dtype=torch.long, device=dev)
        return KernelMap(e, e, (0,) * (kvol + 1), n, n, centre, True)
    q = keys[None, :] + delta(offs[:centre])[:, None]
    idx = torch.searchsorted(keys, q.reshape(-1)).clamp_(max=n - 1)
    found = (keys[idx] == q.reshape(-1)).view(centre, n)
    pairs_in, pairs_out, counts = [], [], []
    for k in range(kvol):
        if k == centre:
            counts.append(0)
            continue
        kk = k if k < centre else kvol - 1 - k
        rows = found[kk].nonzero().squeeze(1)
        other = idx.view(centre, n)[kk][rows]
        pairs_in.append(other if k < centre else rows)
        pairs_out.append(rows if k < centre else other)
        counts.append(len(rows))
    return KernelMap(torch.cat(pairs_in), torch.cat(pairs_out), _splits(torch.tensor(counts)), n, n, centre, True)


def identity_map(n: int, device: torch.device | str = "cpu") -> KernelMap:
    """Map of a 1x1x1 conv: only the identity offset."""
    e = torch.empty(0, dtype=torch.long, device=device)
    return KernelMap(e, e, (0, 0), n, n, 0, True)


def _child_offset_index(child: torch.Tensor, parent: torch.Tensor, child_stride: int, factor: int) -> torch.Tensor:
    o = torch.div(child[:, 1:] - parent[:, 1:], child_stride, rounding_mode="floor")
    return (o[:, 0] * factor + o[:, 1]) * factor + o[:, 2]


def _grouped(k: torch.Tensor, in_idx: torch.Tensor, out_idx: torch.Tensor, kvol: int, n_in: int,
             n_out: int) -> KernelMap:
    order = torch.sort(k, stable=True).indices
    counts = torch.bincount(k, minlength=kvol)
    return KernelMap(in_idx[order], out_idx[order], _splits(counts), n_in, n_out, None)


def parent_coords(coords: torch.Tensor, parent_stride: int) -> torch.Tensor:
    """Each cell's parent at `parent_stride` (floor), in finest units."""
    p = coords.clone()
    p[:, 1:] = torch.div(p[:, 1:], parent_stride, rounding_mode="floor") * parent_stride
    return p


def downsample_map(coords: torch.Tensor, stride: int, factor: int) -> tuple[torch.Tensor, KernelMap]:
    """Output coords (unique parents at stride * factor) and the map of a kernel=stride=factor conv."""
    par = parent_coords(coords, stride * factor)
    dense = parents_dense(coords, stride, factor) if len(coords) else None
    if dense is None:
        out_keys, inv = torch.unique(pack(par), return_inverse=True)
        out = unpack(out_keys)
    else:
        out, inv = dense
    k = _child_offset_index(coords, par, stride, factor)
    n = coords.shape[0]
    kmap = _grouped(k, torch.arange(n, device=coords.device), inv, factor ** 3, n, len(out))
    return out, kmap


def upsample_map(in_keys: torch.Tensor, target: torch.Tensor, target_stride: int, factor: int) -> KernelMap:
    """Map of a kernel=stride=factor transposed conv from a coarse set (sorted keys) onto `target`.

    Target cells whose parent is not active receive nothing (zero before bias).
    """
    par = parent_coords(target, target_stride * factor)
    src = torch.searchsorted(in_keys, pack(par)).clamp_(max=max(in_keys.numel() - 1, 0))
    ok = in_keys[src] == pack(par) if in_keys.numel() else torch.zeros_like(src, dtype=torch.bool)
    rows = ok.nonzero().squeeze(1)
    k = _child_offset_index(target[rows], par[rows], target_stride, factor)
    return _grouped(k, src[rows], rows, factor ** 3, in_keys.numel(), target.shape[0])
