"""Kernel maps found in a dense grid of row numbers are those of the key search, pair for pair."""
from __future__ import annotations

import pytest
import torch

from hgca_core.geometry.coords import pack, unique, unpack
from hgca_core.nn import row_grid
from hgca_core.nn.kernel_map import KernelMap, downsample_map, submanifold_map, submanifold_map_reference


@pytest.fixture
def gen() -> torch.Generator:
    return torch.Generator().manual_seed(0)


def _cells(gen: torch.Generator, batch: int, size: int, p: float, stride: int) -> torch.Tensor:
    occ = torch.rand((batch, size, size, size), generator=gen) < p
    c = occ.nonzero()
    c[:, 1:] = (c[:, 1:] - size // 2) * stride              # negative coordinates too
    return unique(c)


def _table_from_pairs(m: KernelMap) -> torch.Tensor:
    return KernelMap(m.in_idx, m.out_idx, m.splits, m.n_in, m.n_out, m.identity, m.symmetric).table


@pytest.mark.parametrize("kernel,stride", [(3, 1), (3, 2), (5, 1), (3, 8)])
def test_dense_submanifold_map_is_the_searched_one(gen: torch.Generator, kernel: int, stride: int,
                                                  monkeypatch: pytest.MonkeyPatch) -> None:
    for p in (0.05, 0.5, 0.97):          # sparse maps (pairs) and dense ones (the table comes with the map)
        c = _cells(gen, 2, 9, p, stride)
        keys = pack(c)
        dense = submanifold_map(keys, kernel, stride, c)
        assert row_grid.RowGrid(c, stride, kernel // 2).fits
        monkeypatch.setattr(row_grid, "DENSE_MAP_LIMIT", 0)
        searched = submanifold_map(keys, kernel, stride)
        monkeypatch.undo()
        ref = submanifold_map_reference(keys, kernel, stride)
        for other in (searched, ref):
            assert dense.splits == other.splits and dense.identity == other.identity
            assert torch.equal(dense.in_idx, other.in_idx) and torch.equal(dense.out_idx, other.out_idx)
        if p > 0.9:
            assert "table" in dense.__dict__                 # built with the map, not from the pairs
        assert torch.equal(dense.table, _table_from_pairs(ref))


@pytest.mark.parametrize("stride,factor", [(1, 2), (2, 2), (4, 2), (1, 3)])
def test_dense_parents_are_the_unique_ones(gen: torch.Generator, stride: int, factor: int,
                                           monkeypatch: pytest.MonkeyPatch) -> None:
    c = _cells(gen, 3, 10, 0.3, stride)
    out, kmap = downsample_map(c, stride, factor)
    monkeypatch.setattr(row_grid, "DENSE_MAP_LIMIT", 0)
    out_s, kmap_s = downsample_map(c, stride, factor)
    assert torch.equal(out, out_s) and torch.equal(out, unpack(torch.unique(pack(out))))
    assert kmap.splits == kmap_s.splits
    assert torch.equal(kmap.in_idx, kmap_s.in_idx) and torch.equal(kmap.out_idx, kmap_s.out_idx)


def test_a_box_too_large_for_a_grid_is_searched(gen: torch.Generator) -> None:
    """Two cells 2**13 apart on every axis span a 5e11-cell box: no grid, the search answers."""
    c = unique(torch.tensor([[0, 0, 0, 0], [0, 8192, 8192, 8192], [0, 1, 0, 0]]))
    assert not row_grid.RowGrid(c, 1, 1).fits
    m = submanifold_map(pack(c), 3, 1, c)
    ref = submanifold_map_reference(pack(c), 3, 1)
    assert torch.equal(m.in_idx, ref.in_idx) and m.splits == ref.splits and m.num_pairs == 3 + 2


def test_member_rows_are_the_sorted_search(gen: torch.Generator) -> None:
    """Rows of query cells in a set (-1 where absent), queries outside the set's box included: what a search in
    the sorted keys gives, for the set in its sorted order."""
    from hgca_core.geometry.coords import lookup
    from hgca_core.nn.row_grid import member_rows

    cells = _cells(gen, 2, 8, 0.3, 1)
    query = _cells(gen, 3, 12, 0.5, 1)                      # a larger box and a batch the set lacks
    rows = member_rows(query, cells)
    assert torch.equal(rows, lookup(query, pack(cells)))
    assert (rows >= 0).sum() > 10 and (rows < 0).sum() > 10
    assert torch.equal(member_rows(query[:0], cells), torch.zeros(0, dtype=torch.long))
