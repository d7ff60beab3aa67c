"""Packed coarse training samples: the 20 cm cell sets the coarse stage trains on (the input s^0, the ground truth,
the observed free space) and, in val and test splits, the visible cells its validation scores, as bit grids.

Why: a GPU machine often cannot build scenes itself (no Embree there, and its time is better spent training).
A full sample is ~6 MB (points, surfaces, distance pairs, evaluation scans); packed, a scene is ~60 kB, so several
hundred fit in a few tens of MB that are quick to copy to it. The full samples stay the one source: a packed file is
derived from one by `training.pack.pack_sample` and gives the coarse stage the very cells its source gives
(`training.data` reads both); the fine stage and `hgca eval` need the full files.
"""
from __future__ import annotations

from collections.abc import Sequence
from functools import lru_cache
from pathlib import Path

import numpy as np

from hgca_core.dataset.samples import SPLITS as SAMPLE_SPLITS
from hgca_core.errors import InputError
from hgca_core.geometry.freespace import dense

MARK = "packed_coarse"   # key present in every packed file; its value is the format version
VERSION = 1
SPLITS = tuple(SAMPLE_SPLITS)   # a packed dataset has the full one's splits


@lru_cache(maxsize=4096)
def _packed(path: str) -> bool:
    try:
        with np.load(path, allow_pickle=False) as z:
            return MARK in z.files
    except (OSError, ValueError) as e:
        raise InputError(f"cannot read the sample: {e}", path) from None


def is_packed(path: str | Path) -> bool:
    """Whether a sample file is a packed coarse sample (looked up once per path)."""
    return _packed(str(path))


def refuse_packed(files: Sequence[str | Path], what: str) -> None:
    """A clear error where a consumer needs the full samples (points, surfaces) but was given packed ones."""
    for f in {files[0], files[-1]} if files else ():
        if is_packed(f):
            raise InputError(f"{what} needs the full samples (`hgca synth --split`); this is a packed coarse sample "
                             "(`hgca synth --pack`), which holds only the coarse stage's 20 cm cells", f)


def pack_bits(cells: np.ndarray, shape: tuple[int, int, int]) -> np.ndarray:
    """A cell set as the packed bit grid of `shape` (what `unpack_cells` reads back)."""
    return np.packbits(dense(cells, shape).reshape(-1))


def unpack_cells(bits: np.ndarray, shape: Sequence[int]) -> np.ndarray:
    """(N, 3) int64 cells of a packed bit grid, in row-major (sorted) order."""
    n = int(np.prod(shape))
    return np.argwhere(np.unpackbits(bits, count=n).astype(bool).reshape(tuple(int(s) for s in shape))).astype(np.int64)
