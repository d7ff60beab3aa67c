"""The project's only cells -> mesh conversion: the blocky surface of the union of occupied cells.

It meshes the coarse stage's output for the user (`hgca complete --stage coarse`), and every voxel row of
`hgca eval` (the input, GCA, hGCA 20 cm and 10 cm) before ReSim, so what is scored is what is shipped and all
voxel methods are meshed alike. Faces lie exactly on the cell boundaries (no bevelled edges as marching
cubes at 0.5 would give), so the mesh holds exactly the occupied volume.
"""
from __future__ import annotations

import numpy as np
import trimesh

from hgca_core.errors import InputError
from hgca_core.geometry.keys import pack
from hgca_core.geometry.voxel import COARSE, FINE, lower_corner as default_corner

# For each face direction: the neighbour offset and the 4 corners (unit cube, counter-clockwise seen from outside).
_FACES = [
    ((1, 0, 0), [(1, 0, 0), (1, 1, 0), (1, 1, 1), (1, 0, 1)]),
    ((-1, 0, 0), [(0, 0, 0), (0, 0, 1), (0, 1, 1), (0, 1, 0)]),
    ((0, 1, 0), [(0, 1, 0), (0, 1, 1), (1, 1, 1), (1, 1, 0)]),
    ((0, -1, 0), [(0, 0, 0), (1, 0, 0), (1, 0, 1), (0, 0, 1)]),
    ((0, 0, 1), [(0, 0, 1), (1, 0, 1), (1, 1, 1), (0, 1, 1)]),
    ((0, 0, -1), [(0, 0, 0), (0, 1, 0), (1, 1, 0), (1, 0, 0)]),
]


def voxel_mesh(coords: np.ndarray, voxel: float, lower_corner: np.ndarray | float | None = None) -> trimesh.Trimesh:
    """Watertight blocky surface of occupied cells (region frame): only faces between an occupied and an empty
    cell, outward normals, vertices shared, so the result is a 2-manifold wherever cells meet by faces.

    Cell c spans [lower_corner + c * voxel, lower_corner + (c + 1) * voxel). The default is the project's
    convention for 10 and 20 cm cells (`hgca_core.geometry.voxel.lower_corner`: -5 cm); other sizes must pass
    it. No cells -> an empty mesh (ReSim scores it with its empty-scan penalty).
    """
    c = np.asarray(coords)
    if c.ndim != 2 or c.shape[1] != 3:
        raise InputError(f"voxel coordinates must be (N, 3), got shape {c.shape}")
    if not voxel > 0:
        raise InputError(f"voxel size must be positive, got {voxel}")
    if lower_corner is None:
        if not (np.isclose(voxel, FINE) or np.isclose(voxel, COARSE)):
            raise InputError(f"no default cell convention for {voxel} m voxels; pass lower_corner")
        lower_corner = default_corner(voxel)
    if len(c) == 0:
        return trimesh.Trimesh(vertices=np.zeros((0, 3)), faces=np.zeros((0, 3), dtype=np.int64), process=False)
    c = c.astype(np.int64)
    occupied = np.sort(pack(c))
    quads = []
    for normal, corners in _FACES:
        nb = pack(c + np.array(normal))
        pos = np.searchsorted(occupied, nb).clip(max=len(occupied) - 1)
        exposed = c[occupied[pos] != nb]
        quads.append(exposed[:, None, :] + np.array(corners)[None])  # (n, 4, 3) integer corner coordinates
    flat = np.concatenate(quads).reshape(-1, 3)
    uniq, inv = np.unique(pack(flat), return_inverse=True)
    verts_int = np.empty((len(uniq), 3), dtype=np.int64)
    verts_int[inv.reshape(-1)] = flat
    q = inv.reshape(-1, 4)
    faces = np.concatenate([q[:, [0, 1, 2]], q[:, [0, 2, 3]]])
    vertices = verts_int * voxel + np.asarray(lower_corner, dtype=np.float64)
    return trimesh.Trimesh(vertices=vertices, faces=faces, process=False)


def smooth_cells_mesh(coords: np.ndarray, voxel: float, grid: tuple[int, int, int], sigma: float = 0.75,
                      level: float = 0.3) -> trimesh.Trimesh:
    """A smooth surface around occupied cells (region frame): their occupancy blurred by a Gaussian of `sigma`
    cells and cut at `level` by scikit-image's marching cubes. What the preview stage shows instead of cubes: a
    street's shape from the coarse chain alone, without the fine stage's cost. `level` 0.3 keeps walls one cell
    thick (their blurred peak is about 0.5) and drops lone cells (about 0.2). Cell centres follow the project's
    convention (`geometry.voxel.lower_corner`)."""
    from skimage.filters import gaussian
    from skimage.measure import marching_cubes

    c = np.asarray(coords, dtype=np.int64).reshape(-1, 3)
    shape = np.asarray(grid, dtype=np.int64) + 4      # two empty cells around the grid: closed at its sides
    occ = np.zeros(tuple(shape), dtype=np.float32)
    inside = c[np.all((c >= 0) & (c < np.asarray(grid)), axis=1)]
    occ[tuple((inside + 2).T)] = 1.0
    blurred = gaussian(occ, sigma=sigma, mode="constant", preserve_range=True)
    if len(inside) == 0 or blurred.max() <= level:
        return trimesh.Trimesh(np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64), process=False)
    verts, faces, _normals, _ = marching_cubes(blurred, level=level, spacing=(voxel,) * 3)
    corner = np.asarray(default_corner(voxel), dtype=np.float64)
    verts = verts.astype(np.float64) + corner + (0.5 - 2.0) * voxel   # index i's centre: corner + (i + 0.5) voxel
    return trimesh.Trimesh(verts, faces[:, ::-1].astype(np.int64), process=False)
