"""The fine stage's earlier mesher, kept as a naive reference for tests and the mesh-quality benchmark: marching
cubes at an iso-level above zero of the unsigned distance (0.6 grid steps), which gives a closed two-sheet shell
around every surface instead of the surface itself. Not used by the package (see hgca_core.meshing.udf_surface).
It lives in tests/ with the other shared builders (tests never import benchmarks/); tests/test_meshing_udf.py and
benchmarks/mesh_quality.py import this one copy."""
from __future__ import annotations

import numpy as np
import trimesh
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree
from skimage.measure import marching_cubes

LEVEL_FRACTION = 0.6


def shell_mesh(g: np.ndarray, vals: np.ndarray, res: float = 0.05, fill: float = 0.1, tile: int = 32,
               min_faces: int = 16) -> trimesh.Trimesh:
    """Marching cubes of {d < LEVEL_FRACTION res} over sparse grid samples g (G, 3) / vals (G,), one dense
    (tile + 1)^3 block at a time, tiles welded, pieces below `min_faces` dropped; vertices g * res (metres)."""
    level = LEVEL_FRACTION * res
    home = np.floor_divide(g, tile)
    on_face = (g % tile) == 0
    idx, tiles = [], []
    for o in np.stack(np.meshgrid((0, 1), (0, 1), (0, 1), indexing="ij"), -1).reshape(-1, 3):
        ok = np.all(on_face | (o == 0), axis=1)      # a point on a tile face belongs to both tiles
        idx.append(np.nonzero(ok)[0])
        tiles.append(home[ok] - o)
    idx_a, tiles_a = np.concatenate(idx), np.concatenate(tiles)
    tk = (tiles_a[:, 0] + (1 << 20)) * (1 << 42) + (tiles_a[:, 1] + (1 << 20)) * (1 << 21) + tiles_a[:, 2] + (1 << 20)
    order = np.argsort(tk, kind="stable")
    idx_a, tiles_a, tk = idx_a[order], tiles_a[order], tk[order]
    starts = np.r_[0, np.nonzero(tk[1:] != tk[:-1])[0] + 1, len(tk)]
    verts, faces, nv = [], [], 0
    for a, b in zip(starts[:-1], starts[1:]):
        v_t = vals[idx_a[a:b]]
        if not (v_t < level).any():
            continue
        origin = tiles_a[a] * tile
        loc = g[idx_a[a:b]] - origin
        vol = np.full((tile + 1,) * 3, fill, dtype=np.float32)
        vol[loc[:, 0], loc[:, 1], loc[:, 2]] = v_t
        if not (vol.min() < level < vol.max()):
            continue
        v, f, _, _ = marching_cubes(vol, level, allow_degenerate=False)
        verts.append(v.astype(np.float64) + origin)
        faces.append(f.astype(np.int64) + nv)
        nv += len(v)
    if not verts:
        return trimesh.Trimesh(np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64), process=False)
    v, f = np.concatenate(verts), np.concatenate(faces)
    # weld the copies of tile-face vertices and of edges meeting at a sample on the level (clustering by
    # distance, not rounding); only those can have a twin
    r, frac = v % tile, np.abs(v - np.round(v))
    cand = np.flatnonzero(np.any((r < 1e-2) | (r > tile - 1e-2), axis=1) | np.all(frac < 1e-2, axis=1))
    pairs = cand[cKDTree(v[cand]).query_pairs(1e-3, output_type="ndarray")]
    _, label = connected_components(coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])),
                                               shape=(len(v), len(v))), directed=False)
    _, first = np.unique(label, return_index=True)
    f = _drop_small(label, f, min_faces)
    used, f = np.unique(f, return_inverse=True)
    return trimesh.Trimesh(v[first][used] * res, f.reshape(-1, 3), process=False)


def _drop_small(label: np.ndarray, faces: np.ndarray, min_faces: int) -> np.ndarray:
    """Welded faces (degenerate and duplicate ones removed) of pieces with at least `min_faces` faces."""
    f = label[faces]
    f = f[(f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])]
    _, keep = np.unique(np.sort(f, axis=1), axis=0, return_index=True)
    f = f[np.sort(keep)]
    n = int(f.max()) + 1 if len(f) else 0
    _, comp = connected_components(coo_matrix((np.ones(2 * len(f)), (np.r_[f[:, 0], f[:, 1]], np.r_[f[:, 1], f[:, 2]])),
                                              shape=(n, n)), directed=False)
    fl = comp[f[:, 0]]
    return f[np.bincount(fl)[fl] >= min_faces]
