"""Sparse coordinate sets on int64 torch tensors, vectorised (no Python loops over cells).

A coordinate set is an (N, 4) int64 tensor of [batch, x, y, z] rows. Sets are kept unique and sorted by
their packed key (`hgca_core.geometry.keys.pack`), which makes membership a `searchsorted` and union a
concatenate + unique.
"""
from __future__ import annotations

import itertools

import torch

from hgca_core.geometry import keys as _keys
from hgca_core.geometry.keys import pack

__all__ = ["pack", "unpack", "unique", "union", "lookup", "isin", "offsets", "dilate", "upsample2", "downsample2",
           "with_batch"]


def unpack(keys: torch.Tensor) -> torch.Tensor:
    """Keys -> (N, 4) [b, x, y, z] rows (`keys.unpack` of batched keys)."""
    return _keys.unpack(keys, batched=True)


def unique(coords: torch.Tensor) -> torch.Tensor:
    """Unique rows, sorted by key."""
    return unpack(torch.unique(pack(coords)))


def union(*sets: torch.Tensor) -> torch.Tensor:
    return unique(torch.cat([s.long() for s in sets], dim=0))


def lookup(query: torch.Tensor, table_keys: torch.Tensor) -> torch.Tensor:
    """Index of each query row in a *sorted* key table, or -1 where absent."""
    q = pack(query) if query.dim() == 2 else query
    if table_keys.numel() == 0:
        return torch.full(q.shape, -1, dtype=torch.long, device=q.device)
    idx = torch.searchsorted(table_keys, q).clamp_(max=table_keys.numel() - 1)
    return torch.where(table_keys[idx] == q, idx, torch.full_like(idx, -1))


def isin(query: torch.Tensor, table: torch.Tensor) -> torch.Tensor:
    """Boolean membership of query rows in a coordinate set."""
    return lookup(query, torch.sort(pack(table)).values) >= 0


def offsets(radius: int, metric: str = "chebyshev", device: torch.device | str = "cpu") -> torch.Tensor:
    """Integer offsets (K, 3) within `radius` under `metric` ('chebyshev' cube, 'l1' octahedron, 'l2' ball)."""
    r = range(-radius, radius + 1)
    offs = torch.tensor(list(itertools.product(r, r, r)), dtype=torch.long, device=device)
    if metric == "l1":
        offs = offs[offs.abs().sum(1) <= radius]
    elif metric == "l2":
        offs = offs[(offs * offs).sum(1) <= radius * radius]
    elif metric != "chebyshev":
        raise ValueError(f"unknown metric {metric!r}")
    return offs


# Bounded dilations of grids up to this many cells (x batch) run on a dense boolean grid (256 MB at most).
DENSE_LIMIT = 1 << 28


def dilate(coords: torch.Tensor, radius: int, metric: str = "chebyshev",
           bounds: tuple[int, int, int] | None = None, dense_limit: int = DENSE_LIMIT) -> torch.Tensor:
    """The neighbourhood N(s): all cells within `radius` of a cell in the set (the set included), sorted by key.

    With `bounds`, cells outside [0, bounds) on any axis are dropped, so growth stays inside the region, and
    (when the grid has at most `dense_limit` cells and every cell lies inside) the dilation runs on a dense
    boolean grid: an L1 ball grown as `radius` passes of the 7-cell cross, a Chebyshev cube as one
    (2r + 1)-segment per axis, an L2 ball offset by offset; `nonzero` returns the cells already in key order.
    On the 10 cm default region that takes ~0.1 s where sorting the ~5 M candidate keys takes 2-9 s.
    """
    coords = coords.long()
    if len(coords) == 0 or radius == 0:
        return unique(coords)
    if bounds is not None:
        b = torch.tensor(bounds, device=coords.device)
        nb = int(coords[:, 0].max()) + 1
        inside = bool(((coords[:, 1:] >= 0) & (coords[:, 1:] < b)).all()) and int(coords[:, 0].min()) >= 0
        if inside and nb * bounds[0] * bounds[1] * bounds[2] <= dense_limit:
            return _dilate_dense(coords, radius, metric, (nb, *bounds))
    offs = offsets(radius, metric, coords.device)
    full = torch.zeros((len(offs), 4), dtype=torch.long, device=coords.device)
    full[:, 1:] = offs
    grown = (coords[:, None, :] + full[None]).reshape(-1, 4)
    if bounds is not None:
        grown = grown[((grown[:, 1:] >= 0) & (grown[:, 1:] < b)).all(1)]
    return unique(grown)


def _dilate_dense(coords: torch.Tensor, radius: int, metric: str, shape: tuple[int, ...]) -> torch.Tensor:
    occ = torch.zeros(shape, dtype=torch.bool, device=coords.device)
    occ[coords[:, 0], coords[:, 1], coords[:, 2], coords[:, 3]] = True
    if metric == "l1":
        unit = [d for d in offsets(1, "l1").tolist() if any(d)]
        for _ in range(radius):
            grown = occ.clone()
            for d in unit:
                _or_shifted(grown, occ, tuple(d))
            occ = grown
    elif metric == "chebyshev":
        for axis in range(3):
            grown = occ.clone()
            for k in range(-radius, radius + 1):
                if k:
                    d = [0, 0, 0]
                    d[axis] = k
                    _or_shifted(grown, occ, tuple(d))
            occ = grown
    else:
        grown = occ.clone()
        for d in offsets(radius, metric).tolist():
            if any(d):
                _or_shifted(grown, occ, tuple(d))
        occ = grown
    return torch.nonzero(occ)


def _or_shifted(out: torch.Tensor, src: torch.Tensor, d: tuple[int, int, int]) -> None:
    """out[:, x + dx, y + dy, z + dz] |= src[:, x, y, z] where both are inside the grid."""
    dst_sl, src_sl = [slice(None)], [slice(None)]
    for k, n in zip(d, src.shape[1:]):
        dst_sl.append(slice(max(k, 0), n + min(k, 0)))
        src_sl.append(slice(max(-k, 0), n - max(k, 0)))
    out[tuple(dst_sl)] |= src[tuple(src_sl)]


def upsample2(coords: torch.Tensor) -> torch.Tensor:
    """Each coarse cell -> its 8 fine children (20 cm -> 10 cm)."""
    kids = torch.tensor(list(itertools.product((0, 1), repeat=3)), dtype=torch.long, device=coords.device)
    full = torch.zeros((8, 4), dtype=torch.long, device=coords.device)
    full[:, 1:] = kids
    c = coords.long().clone()
    c[:, 1:] *= 2
    return unique((c[:, None, :] + full[None]).reshape(-1, 4))


def downsample2(coords: torch.Tensor) -> torch.Tensor:
    """Each fine cell -> its parent by flooring (10 cm -> 20 cm)."""
    c = coords.long().clone()
    c[:, 1:] = torch.div(c[:, 1:], 2, rounding_mode="floor")
    return unique(c)


def with_batch(coords3: torch.Tensor, b: int = 0) -> torch.Tensor:
    """(N, 3) -> (N, 4) with a constant batch index."""
    out = torch.empty((len(coords3), 4), dtype=torch.long, device=coords3.device)
    out[:, 0] = b
    out[:, 1:] = coords3.long()
    return out
