"""Dense grids of row numbers: neighbour and parent queries of a sparse set by one gather each.

A kernel map asks, for every active cell c and kernel offset d, which row holds c + d. With sorted keys that is
a binary search per query (`kernel_map._neighbours_half`); when the set's bounding box is small (a region is a
192 x 192 x 40 box of 20 cm cells: 1.5 M cells, 6 MB of int32), a dense grid holding each active cell's row
(-1 elsewhere) answers it with one gather per offset, several times faster on a CPU. The box is padded by the
kernel's reach on every spatial axis, so c + d never wraps into another row of the grid. The rows found are
the very rows a search finds, so the maps, and every result computed with them, are the same bit for bit.

Flat grid order is (b, x, y, z) lexicographic, the order of `geometry.keys.pack`: a `nonzero` over the grid
lists cells already sorted by key.
"""
from __future__ import annotations

import torch

# Boxes (cells of the set's stride, padded, x batch) of at most this many cells use a dense grid (int32: 64 MB).
DENSE_MAP_LIMIT = 1 << 24


class RowGrid:
    """The active cells `coords` ((N, 4) [b, x, y, z], finest units, multiples of `stride`) in a dense box of
    their stride's cells, padded by `pad` cells on each spatial side. `fits` says whether the box is within
    DENSE_MAP_LIMIT; `fill()` then builds the grid of row numbers (rows in the order of `coords`)."""

    def __init__(self, coords: torch.Tensor, stride: int, pad: int) -> None:
        c = coords if stride == 1 else torch.cat([coords[:, :1], torch.div(coords[:, 1:], stride,
                                                                            rounding_mode="floor")], 1)
        lo, hi = c.amin(0), c.amax(0)
        lo[0] = 0
        lo[1:] -= pad
        ext = hi - lo + 1
        ext[1:] += pad
        self.shape = tuple(int(v) for v in ext.tolist())
        self.size = self.shape[0] * self.shape[1] * self.shape[2] * self.shape[3]
        self.fits = self.size <= DENSE_MAP_LIMIT
        self.strides = (self.shape[1] * self.shape[2] * self.shape[3], self.shape[2] * self.shape[3],
                        self.shape[3], 1)
        self.stride, self.lo, self.cells = stride, lo, c

    def flat_of(self, cells: torch.Tensor) -> torch.Tensor:
        """(N,) int64 flat grid index of cells in the grid's units ((N, 4), inside the box)."""
        f = (cells[:, 0] - self.lo[0]) * self.strides[0]
        for a in (1, 2, 3):
            f += (cells[:, a] - self.lo[a]) * self.strides[a]
        return f

    def fill(self) -> "RowGrid":
        n, dev = len(self.cells), self.cells.device
        self.flat = self.flat_of(self.cells)
        self.rows = torch.full((self.size,), -1, dtype=torch.int32, device=dev)
        self.rows[self.flat] = torch.arange(n, dtype=torch.int32, device=dev)
        return self

    def at(self, d: tuple[int, int, int]) -> torch.Tensor:
        """(N,) int32: the row of each cell's neighbour at spatial offset d (cells of the stride, |d| <= pad), -1
        where none is active."""
        shift = d[0] * self.strides[1] + d[1] * self.strides[2] + d[2]
        return torch.index_select(self.rows, 0, self.flat + shift)


def half_offsets(r: int) -> list[tuple[int, int, int]]:
    """The offsets of [-r, r]^3 before the centre, lexicographic (x, y, z): the submanifold maps' searched half."""
    every = [(dx, dy, dz) for dx in range(-r, r + 1) for dy in range(-r, r + 1) for dz in range(-r, r + 1)]
    return every[: len(every) // 2]


def all_offsets(r: int) -> list[tuple[int, int, int]]:
    return [(dx, dy, dz) for dx in range(-r, r + 1) for dy in range(-r, r + 1) for dz in range(-r, r + 1)]


def parents_dense(coords: torch.Tensor, stride: int, factor: int) -> tuple[torch.Tensor, torch.Tensor] | None:
    """(unique parents (M, 4) at stride * factor sorted by key, each cell's parent row (N,)), what `torch.unique`
    of the parents' keys with `return_inverse` gives, from a dense occupancy grid of the parents; None when their
    box is too large for one."""
    s = stride * factor
    par = torch.cat([coords[:, :1], torch.div(coords[:, 1:], s, rounding_mode="floor")], 1)
    grid = RowGrid(par, 1, 0)
    if not grid.fits:
        return None
    flat = grid.flat_of(par)
    occ = torch.zeros(grid.size, dtype=torch.bool, device=coords.device)
    occ[flat] = True
    out_flat = occ.nonzero().squeeze(1)
    rank = torch.empty(grid.size, dtype=torch.long, device=coords.device)
    rank[out_flat] = torch.arange(len(out_flat), device=coords.device)
    inv = rank[flat]
    out = torch.empty((len(out_flat), 4), dtype=torch.long, device=coords.device)
    rest = out_flat
    for a in (0, 1, 2, 3):
        q = torch.div(rest, grid.strides[a], rounding_mode="floor")
        out[:, a] = q + grid.lo[a]
        rest = rest - q * grid.strides[a]
    out[:, 1:] *= s
    return out, inv


def member_rows(query: torch.Tensor, cells: torch.Tensor) -> torch.Tensor | None:
    """(M,) int64: the row of each query cell ((M, 4) [b, x, y, z]) in `cells` ((N, 4), unique), -1 where it is
    not one of them; what a `searchsorted` in the cells' sorted keys says, by one gather from a dense grid of
    the cells' rows. None when their box is too large for one."""
    if len(cells) == 0 or len(query) == 0:
        return torch.full((len(query),), -1, dtype=torch.long, device=query.device)
    grid = RowGrid(cells, 1, 0)
    if not grid.fits:
        return None
    grid.fill()
    hi = grid.lo + torch.tensor(grid.shape, device=cells.device) - 1
    inside = ((query >= grid.lo) & (query <= hi)).all(1)
    out = torch.full((len(query),), -1, dtype=torch.long, device=query.device)
    if bool(inside.all()):
        return torch.index_select(grid.rows, 0, grid.flat_of(query)).long()
    out[inside] = torch.index_select(grid.rows, 0, grid.flat_of(query[inside])).long()
    return out
