"""Meshes from the fine stage's output: unsigned distance -> marching cubes (the coarse stage's blocky mesh
is `hgca_core.geometry.voxel_mesh`)."""
from __future__ import annotations

from typing import Callable

import numpy as np
import torch
import trimesh

from hgca_core.geometry.keys import pack, unpack

# ---------------------------------------------------------------------------------------------------------------
# Unsigned distance -> mesh (the fine stage, paper App. "Other Implementation Details")
#
# Frames: the decoder works in the *cell frame*, where 10 cm cell c has its centre at c * voxel (the region frame,
# since 10 cm cells are made by rounding). The 5 cm evaluation grid has point g at g * res, so with voxel = 2 res a
# cell owns the grid points 2c - 1, 2c, 2c + 1 per axis (its centre, faces, edges and corners). Grid points outside
# every occupied cell are never evaluated: they take the clamp value (one cell), which is what the decoder returns
# there anyway (no occupied cell among their 8 nearest cell centres).
# ---------------------------------------------------------------------------------------------------------------
UdfFn = Callable[[torch.Tensor], torch.Tensor]

# Marching cubes level as a fraction of the grid spacing. An unsigned distance has no sign change, so the
# surface is the boundary of the thin band {d < level}: a closed, double-sided shell around every sheet (the
# paper's "thick meshes for thin structures"). For a plane, the grid points of one grid column have distances
# spaced res * |n_i| >= res / sqrt(3) apart, so the closest one is at most res / 2 away: any level above res / 2
# finds every surface; at exactly res / 2 a plane midway between grid planes is missed. 0.6 res (3 cm at 5 cm)
# leaves a margin for decoder error while keeping the shell within 3 cm of the surface.
LEVEL_FRACTION = 0.6


def _as_field(decoder: object, cells: torch.Tensor, latents: torch.Tensor | None) -> UdfFn:
    """The query function: `decoder.field(cells, latents)` for an autoencoder, or `decoder` itself when it is
    already a function of region-frame points (metres) -> unsigned distance (metres), e.g. an analytic one."""
    if hasattr(decoder, "field"):
        return decoder.field(cells, latents)  # type: ignore[attr-defined]
    if callable(decoder):
        return decoder  # type: ignore[return-value]
    raise TypeError(f"decoder must have .field(cells, latents) or be callable, got {type(decoder).__name__}")


def _cells_tensor(cells: np.ndarray | torch.Tensor) -> torch.Tensor:
    t = cells.cpu() if isinstance(cells, torch.Tensor) else torch.from_numpy(np.asarray(cells))
    return t.long().reshape(-1, 3)


def _ratio(voxel: float, res: float) -> int:
    r = voxel / res
    if res <= 0 or abs(r - round(r)) > 1e-6 or round(r) < 1:
        raise ValueError(f"voxel ({voxel}) must be a whole multiple of res ({res})")
    return int(round(r))


def udf_grid_points(cells: np.ndarray | torch.Tensor, voxel: float = 0.1, res: float = 0.05) -> np.ndarray:
    """Integer indices (G, 3) of the res-grid points inside or on the boundary of occupied cells, unique, sorted.

    Point g lies at g * res in the cell frame; cell c (centre c * voxel, r = voxel / res) owns the points with
    |g - r c| <= r / 2 on every axis.
    """
    c = (cells.cpu().numpy() if isinstance(cells, torch.Tensor) else np.asarray(cells)).astype(np.int64).reshape(-1, 3)
    if len(c) == 0:
        return np.zeros((0, 3), dtype=np.int64)
    r = _ratio(voxel, res)
    h = r // 2
    o = np.arange(-h, h + 1)
    offs = np.stack(np.meshgrid(o, o, o, indexing="ij"), -1).reshape(-1, 3)
    g = (c[:, None, :] * r + offs[None]).reshape(-1, 3)
    return unpack(np.unique(pack(g)), batched=False)


def udf_grid(decoder: object, cells: np.ndarray | torch.Tensor, latents: torch.Tensor | None = None,
             voxel: float = 0.1, res: float = 0.05, chunk: int = 1 << 15) -> tuple[np.ndarray, np.ndarray]:
    """(grid indices (G, 3) int64, unsigned distances (G,) float32 metres) on the res-grid around occupied cells.

    A decoder with `grid_udf(cells, latents, res, chunk)` (the autoencoder: the same values, evaluated per cell
    without neighbour search) is asked directly; otherwise its query function sees at most `chunk` points at a
    time. Either way memory stays bounded whatever the scene size.
    """
    cells_t = _cells_tensor(cells)
    _ratio(voxel, res)
    if len(cells_t) == 0:
        return np.zeros((0, 3), dtype=np.int64), np.zeros(0, dtype=np.float32)
    if hasattr(decoder, "grid_udf") and latents is not None:
        with torch.no_grad():
            g_t, vals_t = decoder.grid_udf(cells_t, latents, res, chunk)  # type: ignore[attr-defined]
        return g_t.cpu().numpy(), vals_t.float().cpu().numpy()
    g = udf_grid_points(cells_t, voxel, res)
    field = _as_field(decoder, cells_t, latents)
    vals = np.empty(len(g), dtype=np.float32)
    with torch.no_grad():
        for a in range(0, len(g), chunk):
            q = torch.from_numpy(g[a:a + chunk].astype(np.float32) * np.float32(res))
            vals[a:a + chunk] = field(q).float().cpu().numpy()
    return g, vals


def _tile_members(g: np.ndarray, tile: int) -> tuple[np.ndarray, np.ndarray]:
    """For each grid point, every tile whose closed index box [k T, (k + 1) T] holds it (points on a tile face
    belong to both tiles), as (point index, tile (3,)) rows sorted by tile. Sharing the boundary planes is what
    makes adjacent tiles' marching cubes meet without a gap: each cube belongs to exactly one tile."""
    home = np.floor_divide(g, tile)
    on_face = (g % tile) == 0
    idx, tiles = [], []
    for o in np.stack(np.meshgrid((0, 1), (0, 1), (0, 1), indexing="ij"), -1).reshape(-1, 3):
        ok = np.all(on_face | (o == 0), axis=1)
        idx.append(np.nonzero(ok)[0])
        tiles.append(home[ok] - o)
    idx_a, tiles_a = np.concatenate(idx), np.concatenate(tiles)
    order = np.argsort(pack(tiles_a), kind="stable")
    return idx_a[order], tiles_a[order]


def marching_tiles(g: np.ndarray, vals: np.ndarray, level: float, fill: float,
                   tile: int = 32) -> tuple[np.ndarray, np.ndarray]:
    """Marching cubes over sparse grid samples, one dense (tile + 1)^3 block at a time.

    Returns vertices in grid-index units (float64) and faces; vertices on shared tile faces appear once per tile
    at bit-identical positions (the same two samples are interpolated, then an integer tile origin is added).
    """
    from skimage.measure import marching_cubes

    if tile < 2:
        raise ValueError(f"tile must be at least 2 grid steps, got {tile}")
    if len(g) == 0:
        return np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64)
    idx, tiles = _tile_members(g, tile)
    tk = pack(tiles)
    starts = np.r_[0, np.nonzero(tk[1:] != tk[:-1])[0] + 1, len(tk)]
    verts, faces, nv = [], [], 0
    for a, b in zip(starts[:-1], starts[1:]):
        v_t = vals[idx[a:b]]
        if not (v_t < level).any():
            continue
        origin = tiles[a] * tile
        loc = g[idx[a:b]] - origin
        vol = np.full((tile + 1,) * 3, fill, dtype=np.float32)
        vol[loc[:, 0], loc[:, 1], loc[:, 2]] = v_t
        if not (vol.min() < level < vol.max()):
            continue
        v, f, _, _ = marching_cubes(vol, level, allow_degenerate=False)
        verts.append(v.astype(np.float64) + origin)
        faces.append(f.astype(np.int64) + nv)
        nv += len(v)
    if not verts:
        return np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64)
    return np.concatenate(verts), np.concatenate(faces)


def weld(vertices: np.ndarray, faces: np.ndarray, tol: float = 1e-4,
         candidates: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Merge vertices closer than `tol`, then drop faces that collapse and duplicate faces.

    Clustering by distance (a k-d tree), not by rounding: the same crossing computed by two tiles differs in
    the last float32 bits, and rounding would split a pair that straddles a rounding boundary (a crack).
    `candidates` (bool mask) limits the search to the vertices that can have a twin (those on tile faces, ~10 %
    of a tiled marching-cubes mesh); faces without a candidate vertex are kept as they are.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    if len(faces) == 0:
        return np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64)
    n = len(vertices)
    cand = np.arange(n) if candidates is None else np.flatnonzero(candidates)
    pairs = cand[cKDTree(vertices[cand]).query_pairs(tol, output_type="ndarray")] if len(cand) else np.zeros((0, 2), int)
    graph = coo_matrix((np.ones(len(pairs), dtype=np.int8), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    _, label = connected_components(graph, directed=False)
    _, first = np.unique(label, return_index=True)          # labels are 0..k-1: first vertex of each cluster
    f = label[faces]
    ok = (f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])
    touched = np.ones(len(f), dtype=bool) if candidates is None else candidates[faces].any(axis=1)
    check = np.flatnonzero(ok & touched)
    _, keep = np.unique(np.sort(f[check], axis=1), axis=0, return_index=True)
    dup = np.ones(len(check), dtype=bool)
    dup[keep] = False
    ok[check[dup]] = False
    return vertices[first], f[ok]


def drop_small_components(vertices: np.ndarray, faces: np.ndarray, min_faces: int) -> tuple[np.ndarray, np.ndarray]:
    """Remove connected pieces (sharing vertices) with fewer than `min_faces` faces, then unused vertices."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    if len(faces) == 0:
        return np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64)
    if min_faces > 1:
        n = len(vertices)
        rows = np.concatenate([faces[:, 0], faces[:, 1]])
        cols = np.concatenate([faces[:, 1], faces[:, 2]])
        graph = coo_matrix((np.ones(len(rows), dtype=np.int8), (rows, cols)), shape=(n, n))
        _, label = connected_components(graph, directed=False)
        face_label = label[faces[:, 0]]
        counts = np.bincount(face_label)
        faces = faces[counts[face_label] >= min_faces]
    used = np.unique(faces)
    remap = np.full(len(vertices), -1, dtype=np.int64)
    remap[used] = np.arange(len(used))
    return vertices[used], remap[faces]


def project_to_zero(field: UdfFn, points: np.ndarray, steps: int = 1, max_dist: float | None = None,
                    chunk: int = 1 << 16) -> np.ndarray:
    """Move points onto the zero level along the distance gradient: p <- p - d(p) grad d / |grad d|.

    One step is exact for a true distance function; points whose distance is at the clamp (no gradient) or
    above `max_dist` stay where they are.
    """
    p = np.asarray(points, dtype=np.float64).copy()
    for _ in range(max(0, steps)):
        for a in range(0, len(p), chunk):
            q = torch.from_numpy(p[a:a + chunk].astype(np.float32)).requires_grad_(True)
            with torch.enable_grad():
                d = field(q)
                (grad,) = torch.autograd.grad(d.sum(), q)
            n = grad.norm(dim=1, keepdim=True)
            ok = (n[:, 0] > 1e-6) & (d.detach() > 0)
            if max_dist is not None:
                ok &= d.detach() < max_dist
            step = (d.detach()[:, None] * grad / n.clamp(min=1e-6)) * ok[:, None]
            p[a:a + chunk] -= step.double().numpy()
    return p


def udf_mesh(decoder: object, cells: np.ndarray | torch.Tensor, latents: torch.Tensor | None = None,
             lower_corner: float | np.ndarray | None = None, voxel: float = 0.1, res: float = 0.05,
             level: float | None = None, chunk: int = 1 << 15, tile: int = 32, min_faces: int = 16,
             project: int = 0) -> trimesh.Trimesh:
    """Mesh of the unsigned distance field around occupied 10 cm cells (paper: 5 cm marching cubes).

    decoder: an autoencoder (anything with `.field(cells, latents)`) or a function of (Q, 3) cell-frame points
      (metres) -> (Q,) unsigned distances (metres), clamped at `voxel`.
    cells: (N, 3) int occupied cells; latents: (N, K) their codes (ignored by a plain function).
    lower_corner: where cell c's box starts, lower_corner + c * voxel, as in `geometry.voxel_mesh`; the default
      -voxel / 2 is the region frame of 10 cm cells made by rounding, so vertices come back in that frame.
    level: iso-level in metres, default LEVEL_FRACTION * res (see there; a thin double-sided shell).
    chunk: decoder queries per call (memory bound); tile: marching-cubes block edge in grid steps (memory of one
      dense block); results do not depend on either.
    min_faces: connected pieces with fewer faces are dropped (specks where the field barely dips below level).
    project: gradient steps that move vertices onto the zero level (0 = keep the shell at `level`; >= 1 collapses
      both sides of the shell onto the surface, better for metrics, but the two sheets then coincide).
    """
    level = LEVEL_FRACTION * res if level is None else float(level)
    if not 0 < level < voxel:
        raise ValueError(f"level must lie in (0, voxel = {voxel}), got {level}")
    shift = np.asarray(-voxel / 2 if lower_corner is None else lower_corner, dtype=np.float64) + voxel / 2
    g, vals = udf_grid(decoder, cells, latents, voxel, res, chunk)
    v, f = marching_tiles(g, vals, level, fill=voxel, tile=tile)
    # twins: the same crossing from two tiles (on tile faces) and the vertices of edges that meet at a sample
    # where the field equals the level (at grid points); the same result as welding all, 4x faster
    r, frac = v % tile, np.abs(v - np.round(v))
    twins = np.any((r < 1e-2) | (r > tile - 1e-2), axis=1) | np.all(frac < 1e-2, axis=1)
    v, f = weld(v, f, tol=1e-3, candidates=twins)  # grid units: 50 um at 5 cm
    v, f = drop_small_components(v, f, min_faces)
    v = v * res
    if project and len(v):
        v = project_to_zero(_as_field(decoder, _cells_tensor(cells), latents), v, steps=project, max_dist=voxel * 0.999)
    return trimesh.Trimesh(vertices=v + shift, faces=f, process=False)


def decimate(mesh: trimesh.Trimesh, max_faces: int) -> trimesh.Trimesh:
    """The mesh with at most `max_faces` triangles, by quadric edge collapse (fast-simplification).

    A 5 cm marching-cubes surface of a default region has 5-7 M triangles (two sheets around every surface,
    which an unsigned distance gives); scenes meant for a simulator or an editor rarely need a tenth of that,
    and flat facades and roads, most of a street, lose nothing. Vertex attributes are dropped: the vertices
    are new (the pipeline recomputes `observed_distance` after this).
    """
    import fast_simplification

    if max_faces < 1:
        raise ValueError(f"max_faces must be at least 1, got {max_faces}")
    n = len(mesh.faces)
    if n <= max_faces:
        return mesh
    v, f = fast_simplification.simplify(np.asarray(mesh.vertices, dtype=np.float32),
                                        np.asarray(mesh.faces, dtype=np.int32), target_reduction=1.0 - max_faces / n)
    return trimesh.Trimesh(vertices=v.astype(np.float64), faces=f.astype(np.int64), process=False)


def udf_surface_points(decoder: object, cells: np.ndarray | torch.Tensor, latents: torch.Tensor | None = None,
                       lower_corner: float | np.ndarray | None = None, voxel: float = 0.1, res: float = 0.05,
                       threshold: float | None = None, chunk: int = 1 << 15, project: int = 0) -> np.ndarray:
    """Grid points "close to the surface": res-grid points with unsigned distance below `threshold` (paper, App.:
    5 cm cells with implicit distance below 0.5, in units of the 10 cm voxel, i.e. 5 cm).

    The default threshold is voxel / 2: res / 2 would miss a plane lying midway between two grid planes (its
    nearest grid points are exactly res / 2 away). With `project` the points are moved onto the zero level,
    which gives surface samples for Chamfer distances rather than the band the paper's IoU uses.
    """
    threshold = 0.5 * voxel if threshold is None else float(threshold)
    shift = np.asarray(-voxel / 2 if lower_corner is None else lower_corner, dtype=np.float64) + voxel / 2
    g, vals = udf_grid(decoder, cells, latents, voxel, res, chunk)
    p = g[vals < threshold].astype(np.float64) * res
    if project and len(p):
        p = project_to_zero(_as_field(decoder, _cells_tensor(cells), latents), p, steps=project, max_dist=voxel * 0.999)
    return p + shift
