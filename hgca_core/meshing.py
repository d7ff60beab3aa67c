"""Meshes from the model's outputs.

`voxel_mesh` turns occupied cells into the blocky surface of their union (the coarse stage's output and
the voxel baselines); the fine stage's unsigned distance -> marching cubes path lives here too.
"""
from __future__ import annotations

import numpy as np
import trimesh

# For each face direction: the neighbour offset and the 4 corners (unit cube, counter-clockwise seen from outside).
_FACES = [
    ((1, 0, 0), [(1, 0, 0), (1, 1, 0), (1, 1, 1), (1, 0, 1)]),
    ((-1, 0, 0), [(0, 0, 0), (0, 0, 1), (0, 1, 1), (0, 1, 0)]),
    ((0, 1, 0), [(0, 1, 0), (0, 1, 1), (1, 1, 1), (1, 1, 0)]),
    ((0, -1, 0), [(0, 0, 0), (1, 0, 0), (1, 0, 1), (0, 0, 1)]),
    ((0, 0, 1), [(0, 0, 1), (1, 0, 1), (1, 1, 1), (0, 1, 1)]),
    ((0, 0, -1), [(0, 0, 0), (0, 1, 0), (1, 1, 0), (1, 0, 0)]),
]


def _keys(c: np.ndarray) -> np.ndarray:
    c = c.astype(np.int64) + (1 << 20)
    return (c[:, 0] << 42) | (c[:, 1] << 21) | c[:, 2]


def voxel_mesh(coords: np.ndarray, voxel: float, lower_corner: np.ndarray | float = 0.0) -> trimesh.Trimesh:
    """Watertight blocky surface of occupied cells: only faces between an occupied and an empty cell.

    A cell c spans [lower_corner + c * voxel, lower_corner + (c + 1) * voxel); vertices are shared, so the
    result is a proper 2-manifold wherever cells meet by faces.
    """
    c = np.asarray(coords, dtype=np.int64).reshape(-1, 3)
    if len(c) == 0:
        return trimesh.Trimesh(vertices=np.zeros((0, 3)), faces=np.zeros((0, 3), dtype=np.int64), process=False)
    occupied = np.sort(_keys(c))
    quads = []
    for normal, corners in _FACES:
        nb = _keys(c + np.array(normal))
        pos = np.searchsorted(occupied, nb).clip(max=len(occupied) - 1)
        exposed = c[occupied[pos] != nb]
        quads.append(exposed[:, None, :] + np.array(corners)[None])  # (n, 4, 3) integer corner coordinates
    corners = np.concatenate(quads)
    flat = corners.reshape(-1, 3)
    uniq, inv = np.unique(_keys(flat), return_inverse=True)
    verts_int = np.empty((len(uniq), 3), dtype=np.int64)
    verts_int[inv] = flat
    q = inv.reshape(-1, 4)
    faces = np.concatenate([q[:, [0, 1, 2]], q[:, [0, 2, 3]]])
    vertices = verts_int * voxel + np.asarray(lower_corner, dtype=np.float64)
    return trimesh.Trimesh(vertices=vertices, faces=faces, process=False)
