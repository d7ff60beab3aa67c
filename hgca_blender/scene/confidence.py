"""How sure a completion is, per vertex: how many of the k samples put a surface there, and how far each vertex
lies from what the sensor saw, both as colours Solid view can draw.

The model samples k completions from one scan; where they agree the surface is well determined by the input,
where only some place it the model is guessing. Agreement of a vertex = the share of the k samples (itself
included) with a vertex in the same 20 cm cell or a neighbouring one.
"""
from __future__ import annotations

import numpy as np

CELL = 0.2  # metres: the coarse stage's voxel
OBSERVED_NEAR, OBSERVED_FAR = 0.05, 0.3  # metres: observed below, generated above (as the result material)
OBSERVED_RGB = np.array([0.55, 0.57, 0.6], dtype=np.float32)   # grey: near the input
GENERATED_RGB = np.array([0.95, 0.45, 0.1], dtype=np.float32)  # orange: made by the model
_NEIGHBOURS = np.array([(x, y, z) for x in (-1, 0, 1) for y in (-1, 0, 1) for z in (-1, 0, 1)], dtype=np.int64)
_BITS = 21


def _keys(cells: np.ndarray) -> np.ndarray:
    c = cells + (1 << (_BITS - 1))
    return (c[:, 0] << (2 * _BITS)) | (c[:, 1] << _BITS) | c[:, 2]


def agreement(world_vertices: list[np.ndarray], cell: float = CELL) -> list[np.ndarray]:
    """Per sample, each vertex's share (1/k .. 1) of the k samples with surface within one cell of it."""
    if not world_vertices:
        return []
    anchor = np.floor(np.concatenate([v[:1] for v in world_vertices if len(v)] or [np.zeros((1, 3))])[0] / cell)
    cells = [np.floor(np.asarray(v, dtype=np.float64) / cell).astype(np.int64) - anchor.astype(np.int64)
             for v in world_vertices]
    near = []
    for c in cells:
        own = np.unique(c, axis=0) if len(c) else np.zeros((0, 3), dtype=np.int64)
        near.append(np.unique(_keys((own[:, None, :] + _NEIGHBOURS[None]).reshape(-1, 3))))
    k = len(cells)
    out = []
    for c in cells:
        keys = _keys(c)
        count = sum(np.isin(keys, n, assume_unique=False).astype(np.int32) for n in near)
        out.append((count / k).astype(np.float32))
    return out


def observed_colors(observed_distance: np.ndarray) -> np.ndarray:
    """(V, 4) grey where a vertex is near the input, orange where it was generated (linear between)."""
    t = np.clip((np.asarray(observed_distance, dtype=np.float32) - OBSERVED_NEAR) / (OBSERVED_FAR - OBSERVED_NEAR),
                0.0, 1.0)[:, None]
    rgba = np.ones((len(t), 4), dtype=np.float32)
    rgba[:, :3] = OBSERVED_RGB * (1 - t) + GENERATED_RGB * t
    return rgba


def agreement_colors(share: np.ndarray, stops: np.ndarray) -> np.ndarray:
    """(V, 4) colours of agreement shares along `stops` (low: few samples agree, high: all do)."""
    from .colors import ramp

    rgba = np.ones((len(share), 4), dtype=np.float32)
    rgba[:, :3] = ramp(share, stops)
    return rgba
