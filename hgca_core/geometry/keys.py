"""Cell keys: one int64 per integer cell, the project's only packer, for numpy arrays and torch tensors alike.

A row [x, y, z] or [b, x, y, z] (b = batch index, >= 0) packs into
    key = b << 54 | (x + 2**17) << 36 | (y + 2**17) << 18 | (z + 2**17),
so keys sort in the lexicographic order of the rows (sets become 1-D sorts, `searchsorted`, `isin`), an
unbatched row has the key of the same cell in batch 0, and the layout is linear in each field (the key of
c + d is key(c) + delta(d) while no field overflows; `nn.kernel_map` relies on it).
Each spatial axis holds [-2**17, 2**17) cells: +-13 km at 10 cm, far beyond any region.
"""
from __future__ import annotations

from typing import TypeVar

import numpy as np
import torch

from hgca_core.errors import InputError

AXIS_BITS = 18
OFFSET = 1 << (AXIS_BITS - 1)       # spatial coordinates lie in [-OFFSET, OFFSET)
MASK = (1 << AXIS_BITS) - 1

Array = TypeVar("Array", np.ndarray, torch.Tensor)


def _int64(a: Array) -> Array:
    return a.long() if isinstance(a, torch.Tensor) else np.asarray(a).astype(np.int64, copy=False)


def pack(cells: Array) -> Array:
    """(N, 3) [x, y, z] or (N, 4) [b, x, y, z] integer rows -> (N,) int64 keys (numpy in, numpy out; torch
    in, torch out). No range check: see `check_range` for untrusted input."""
    c = _int64(cells)
    key = c[:, -3] + OFFSET
    key = (key << AXIS_BITS) | (c[:, -2] + OFFSET)
    key = (key << AXIS_BITS) | (c[:, -1] + OFFSET)
    if c.shape[1] == 4:
        key = key | (c[:, 0] << (3 * AXIS_BITS))
    return key


def unpack(keys: Array, batched: bool) -> Array:
    """Inverse of `pack`: (N,) keys -> (N, 4) [b, x, y, z] rows when `batched`, else (N, 3) [x, y, z]."""
    k = _int64(keys)
    cols = [((k >> (2 * AXIS_BITS)) & MASK) - OFFSET, ((k >> AXIS_BITS) & MASK) - OFFSET, (k & MASK) - OFFSET]
    if batched:
        cols.insert(0, k >> (3 * AXIS_BITS))
    return torch.stack(cols, dim=1) if isinstance(k, torch.Tensor) else np.stack(cols, axis=1)


def delta(offsets: Array) -> Array:
    """(K, 3) spatial offsets -> (K,) int64 amounts to add to a key: pack(c + d) = pack(c) + delta(d)."""
    o = _int64(offsets)
    return (o[:, 0] << (2 * AXIS_BITS)) + (o[:, 1] << AXIS_BITS) + o[:, 2]


def check_range(cells: np.ndarray, name: str = "cells") -> None:
    """Raise InputError when a spatial coordinate lies outside what a key holds (it would alias another cell)."""
    c = np.asarray(cells)
    if c.size and (c[:, -3:].min() < -OFFSET or c[:, -3:].max() >= OFFSET):
        raise InputError(f"{name} has cell coordinates outside [-{OFFSET}, {OFFSET}) (points too far from the "
                         "region)")


def unique_rows(cells: np.ndarray) -> np.ndarray:
    """Row-unique (N, 3) int64 cells, sorted lexicographically, via 1-D keys (np.unique(axis=0) is many times
    slower on millions of rows). Coordinates out of range raise InputError."""
    c = np.asarray(cells, dtype=np.int64).reshape(-1, 3)
    if len(c) == 0:
        return np.zeros((0, 3), dtype=np.int64)
    check_range(c)
    return unpack(np.unique(pack(c)), batched=False)
