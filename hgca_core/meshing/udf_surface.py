"""One open surface from samples of an unsigned distance field on a regular grid.

Marching cubes needs a sign change, which an unsigned distance never has: cutting it at a level above zero gives a
closed shell of two sheets around every surface (the old fine-stage meshes: two layers 5.8 cm apart on the road).
Here the zero level itself is extracted, as one sheet:

1. Gradient directions at grid points near the surface (MeshUDF, Guillard et al., ECCV 2022: the gradients at two
   points on opposite sides of a surface point in opposite directions). Taken from the grid samples themselves by
   *upwind* differences: along each axis the larger of the two neighbours lies on the far side of the surface,
   so (max(d+, d-) - d) / h is |n_a| exactly for a plane (a central difference across the surface is not), with
   the sign of (d+ - d-). No decoder gradients are needed, so this costs no network evaluation.
2. An axis edge (i, j) crosses the surface where the two gradient directions disagree (cosine < MAX_DOT) and the
   distances are small enough for the surface to lie between them (d_i + d_j <= `max_sum` h; a plane crossing
   gives h |n_a|; up to WIDE_SUM h where the directions are clearly opposed, for the decoder's shallow valleys).
   The crossing point interpolates the pseudo-signed values d_i and -d_j (exact for a plane).
   MeshUDF assigns pseudo-signs per cube and runs marching cubes on each; two cubes sharing a face can then
   disagree about its edges (cracks, which MeshUDF later patches). Deciding per *edge* makes the decision one
   for all the cubes around it.
3. A dual surface (surface nets): one vertex per cube with a crossing edge, at the mean of its crossing points,
   and one quad per crossing edge joining the four cubes around it. Every crossing edge gives exactly one quad
   and every cube one vertex, so neighbouring pieces share their vertices: no cracks, no double layers, and no
   case tables (which would need consistent signs per cube, the thing a UDF lacks).

The quads' winding is arbitrary at this point (an unsigned field has no front side); `mesh_clean.orient` makes it
consistent and picks the side the sensor saw. The same family as DualMesh-UDF (Zhang et al., ICCV 2023: dual
contouring of UDFs), without its octree and QEF vertices: sharp corners are cut by up to ~1 cm at 5 cm.

DCUDF (Hou et al., 2023) gets one layer differently: marching cubes at a small level r gives the double cover (the
boundary of the r-offset volume), an optimisation with decoder gradients pulls it onto the zero level, and a
min-cut separates the two layers. It avoids non-manifold spots, but the optimisation runs many decoder passes over
all vertices; the per-edge test here needs none beyond the grid samples. Known limits, measured on the synthetic
test scenes (benchmarks/results/mesh_quality.md): where the decoded field misses a surface (a kerb face, a car's
underside) the mesh has a slit; where the zero level grazes a grid plane (flat facades), it switches between two
cube layers, leaving mm-scale facets and a few non-manifold edges.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hgca_core.geometry.keys import pack
from hgca_core.meshing.parallel import map_slices

# Crossing test thresholds, in grid steps h. A plane crossing an edge has d_i + d_j = h |n_a| <= h; the learned
# decoder's distances bottom out at ~1.5 mm rather than 0 and its slope is not exactly 1, so allow some slack.
MAX_SUM = 1.2
# Gradient directions count as opposed below this cosine: 0 would do for a plane, but at a concave corner (road
# meeting a kerb face or a car's side) the two ends of a crossing edge see different surfaces, 90 degrees apart.
MAX_DOT = 0.3
# Where the decoder is unsure (generated ground far between scan rings) its zero valley is shallow and wide: both
# ends of the edge the surface crosses sit 2-5 cm off it, d_i + d_j > MAX_SUM h, and the surface had a hole there
# (up to 7 % of a test scene's road rays). An edge whose gradients are clearly opposed (cosine below WIDE_DOT, as
# across a plane) may therefore span up to WIDE_SUM h. Corner pairs (gradients ~90 degrees apart) keep MAX_SUM:
# there the wider test accepts pairs across the medial axis outside a convex corner (non-manifold spots).
WIDE_SUM = 2.0
WIDE_DOT = -0.7

# Corner offsets (subtracted from an edge's start) of the four cubes around an edge along each axis a, in the
# order (0, 0), (1, 0), (1, 1), (0, 1) over the axes (a + 1, a + 2): counter-clockwise seen from +a
_CUBES = np.zeros((3, 4, 3), dtype=np.int64)
for _a in range(3):
    for _k, (_u, _v) in enumerate(((0, 0), (1, 0), (1, 1), (0, 1))):
        _CUBES[_a, _k, (_a + 1) % 3], _CUBES[_a, _k, (_a + 2) % 3] = _u, _v
# The two triangles of a quad (0 1 2 3) split along 0-2 (row 0) or along 1-3 (row 1)
_SPLITS = np.array([[0, 1, 2, 0, 2, 3], [0, 1, 3, 1, 2, 3]], dtype=np.int64)


@dataclass
class DualSurface:
    """A surface-nets mesh in grid units: vertices (V, 3) float64, faces (F, 3) int64 (winding arbitrary)."""

    vertices: np.ndarray
    faces: np.ndarray


class GridIndex:
    """O(1) lookup of integer grid points: per (x, y) column a dense run over its z range.

    Street scenes are thin shells, so the runs are short (a few cells on the ground, a few metres on facades);
    the table is a few times the number of points, and a lookup is three gathers instead of a binary search.
    The column grid has one empty column on every side of the points, so the x and y neighbours of an indexed
    point need no bounds test; indices are int32 where they fit (half the memory traffic of int64).
    """

    def __init__(self, g: np.ndarray) -> None:
        g = np.asarray(g, dtype=np.int64).reshape(-1, 3)
        self.lo = g.min(0) - [1, 1, 0] if len(g) else np.zeros(3, dtype=np.int64)
        d = g - self.lo
        self.nx, self.ny = (int(d[:, 0].max()) + 2, int(d[:, 1].max()) + 2) if len(g) else (1, 1)
        col = d[:, 0] * self.ny + d[:, 1]
        zlo = np.full(self.nx * self.ny, np.iinfo(np.int64).max, dtype=np.int64)
        zhi = np.full(self.nx * self.ny, -1, dtype=np.int64)
        step = col[1:] - col[:-1]
        self.sorted = bool(len(g)) and bool(np.all(step >= 0) and np.all((step > 0) | (d[1:, 2] > d[:-1, 2])))
        if self.sorted:
            first = np.flatnonzero(np.r_[True, step > 0])         # sorted (x, y, z), as the decoder returns them
            last = np.r_[first[1:], len(g)] - 1
            zlo[col[first]], zhi[col[first]] = d[first, 2], d[last, 2]
        elif len(g):                                               # any order: per-column extremes by one sort
            order = np.argsort(col, kind="stable")
            cs, zs = col[order], d[order, 2]
            first = np.flatnonzero(np.r_[True, cs[1:] != cs[:-1]])
            zlo[cs[first]], zhi[cs[first]] = np.minimum.reduceat(zs, first), np.maximum.reduceat(zs, first)
        span = np.where(zhi >= 0, zhi - np.minimum(zlo, zhi) + 1, 0)
        total = int(span.sum())
        z_top = int(d[:, 2].max()) + 2 if len(g) else 0
        small = max(total + 1 + z_top, len(g) + 1, self.nx * self.ny + self.ny) < (1 << 31) - 1
        self.itype = np.int32 if small else np.int64
        self.base = (np.cumsum(span) - span).astype(self.itype)
        self.zlo, self.span = np.where(zhi >= 0, zlo, 0).astype(self.itype), span.astype(self.itype)
        self.table = np.full(total + 1, -1, dtype=self.itype)     # the last entry: "absent"
        self.table[self.base[col] + d[:, 2] - self.zlo[col]] = np.arange(len(g), dtype=self.itype)
        if self.sorted:
            self._col, self._z = col.astype(self.itype), d[:, 2].astype(self.itype)

    def find(self, q: np.ndarray) -> np.ndarray:
        """Index of each query point (n, 3) among the indexed points, -1 where absent."""
        d = np.asarray(q, dtype=np.int64) - self.lo
        ok = (d[:, 0] >= 0) & (d[:, 0] < self.nx) & (d[:, 1] >= 0) & (d[:, 1] < self.ny)
        return self._at(np.where(ok, d[:, 0] * self.ny + d[:, 1], 0), d[:, 2], ok).astype(np.int64)

    def _at(self, c: np.ndarray, dz: np.ndarray, ok: np.ndarray) -> np.ndarray:
        z = dz - self.zlo[c]
        ok = ok & (z >= 0) & (z < self.span[c])
        return np.where(ok, self.table[np.where(ok, self.base[c] + z, 0)], -1)

    def _in_column(self, c: np.ndarray, z: np.ndarray) -> np.ndarray:
        """`_at` for columns c that exist in the column grid (no bounds test on c), int32 / int64 as the table."""
        rel = z - self.zlo[c]
        ok = rel.view(np.uint32 if self.itype is np.int32 else np.uint64) < self.span[c]   # 0 <= rel < span
        pos = self.base[c] + rel
        pos[~ok] = len(self.table) - 1
        return self.table[pos]

    def neighbours(self, g: np.ndarray, signs: tuple[int, ...] = (1, -1), first: int | None = None) -> np.ndarray:
        """(n, 3, len(signs)) indices of the neighbours g + s e_axis of grid points g (n, 3) for each s in `signs`
        (default: the +1 and the -1 neighbour), -1 where absent.

        first: when g is the indexed points' own slice [first, first + n) of sorted points, the z neighbours
        (+-1 along z) are the next and previous points where those are one step away: no table lookup; the
        result is then int32 where the indices fit."""
        if first is not None and self.sorted and len(g) and all(abs(s) == 1 for s in signs):
            return self._own_neighbours(first, first + len(g), signs).transpose(1, 2, 0)
        d = np.asarray(g, dtype=np.int64) - self.lo
        col = d[:, 0] * self.ny + d[:, 1]
        out = np.empty((len(d), 3, len(signs)), dtype=np.int64)
        yes = np.ones(len(d), dtype=bool)
        for k, s in enumerate(signs):
            x_ok = (d[:, 0] + s >= 0) & (d[:, 0] + s < self.nx)
            y_ok = (d[:, 1] + s >= 0) & (d[:, 1] + s < self.ny)
            out[:, 0, k] = self._at(np.where(x_ok, col + s * self.ny, 0), d[:, 2], x_ok)
            out[:, 1, k] = self._at(np.where(y_ok, col + s, 0), d[:, 2], y_ok)
            out[:, 2, k] = self._at(col, d[:, 2] + s, yes)
        return out

    def _own_neighbours(self, lo: int, hi: int, signs: tuple[int, ...]) -> np.ndarray:
        """(len(signs), n, 3) neighbours of the indexed points lo..hi-1 (sorted), -1 where absent: x and y by the
        padded column grid, z by their order."""
        col, z = self._col[lo:hi], self._z[lo:hi]
        out = np.empty((len(signs), hi - lo, 3), dtype=self.itype)
        for k, s in enumerate(signs):
            out[k, :, 0] = self._in_column(col + self.itype(s * self.ny), z)
            out[k, :, 1] = self._in_column(col + self.itype(s), z)
            out[k, :, 2] = self._in_order(col, z + self.itype(s), lo + s)
        return out

    def _in_order(self, col: np.ndarray, z: np.ndarray, start: int) -> np.ndarray:
        """Index start + i where the indexed point there is (col[i], z[i]), else -1: the next / previous point in
        (x, y, z) order is the one just above / below, when there is one."""
        n = len(self._col)
        j = np.arange(start, start + len(col), dtype=self.itype)
        a, b = max(start, 0), min(start + len(col), n)              # the part of j inside [0, n)
        hit = np.zeros(len(col), dtype=bool)
        if b > a:
            hit[a - start:b - start] = (self._col[a:b] == col[a - start:b - start]) & \
                (self._z[a:b] == z[a - start:b - start])
        j[~hit] = -1
        return j


def upwind_gradients(padded: np.ndarray, at: np.ndarray, nb: np.ndarray, h: float) -> np.ndarray:
    """(n, 3) gradient estimates of the distance at n grid points whose own values are `at`, from the +1 and -1
    neighbours `nb` (2, n, 3) (`GridIndex.neighbours` transposed; module docstring, step 1). `padded`: the
    distances with the fill value appended, so that an absent neighbour (-1) reads the fill."""
    vp, vm = padded[nb[0]], padded[nb[1]]
    return np.sign(vp - vm) * (np.maximum(vp, vm) - at[:, None]) / np.float32(h)


def crossing_edges(g: np.ndarray, vals: np.ndarray, h: float, fill: float, max_sum: float = MAX_SUM,
                   max_dot: float = MAX_DOT, index: GridIndex | None = None, workers: int = 1,
                   minus: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Axis edges of the grid that the zero level crosses.

    g (G, 3) int grid indices, vals (G,) distances (same unit as h). Returns (start point index into g (E,),
    axis (E,), crossing parameter t in [0, 1] from the start (E,)), ordered by axis, then start.

    An edge crosses where its ends' gradient directions are opposed (cosine < max_dot) and d_i + d_j <= max_sum h,
    or clearly opposed (cosine < WIDE_DOT) and d_i + d_j <= WIDE_SUM h (the decoder's wide valleys, see WIDE_SUM).
    Both passes (gradients per point, then the test per edge) work on slices of the points, in `workers` threads.
    index: `GridIndex(g)`, if known; minus: an (G, 3) integer array to fill with the index of g - e_a (-1 where
    absent), which the gradients look up anyway (`dual_surface` finds the cubes around an edge with it).
    """
    index = GridIndex(g) if index is None else index
    lim = np.float32(max_sum * h)
    wide = np.float32(max(max_sum, WIDE_SUM) * h)
    n = len(g)
    plus = np.empty((n, 3), dtype=index.itype)           # index of g + e_a, -1 where absent
    unit = np.empty((n, 3), dtype=np.float32)            # gradient directions
    good = np.empty(n, dtype=bool)                       # ... where there is a gradient
    padded = np.r_[vals, np.float32(fill)]               # index -1 (absent) reads the fill value

    def gradients(lo: int, hi: int) -> None:
        nb = index.neighbours(g[lo:hi], first=lo).transpose(2, 0, 1)      # (2, n, 3): the +1 and -1 neighbours
        plus[lo:hi] = nb[0]
        if minus is not None:
            minus[lo:hi] = nb[1]
        grad = upwind_gradients(padded, vals[lo:hi], nb, h)
        norm = np.sqrt(np.einsum("ij,ij->i", grad, grad))
        unit[lo:hi] = grad / np.maximum(norm, 1e-12)[:, None]
        good[lo:hi] = norm > 0

    def crossings(lo: int, hi: int) -> list[tuple[np.ndarray, np.ndarray]]:
        out = []
        for a in range(3):
            j = plus[lo:hi, a]
            # the distance test first: it is the cheap one
            i = lo + np.flatnonzero((j >= 0) & (vals[lo:hi] + padded[j] <= wide))
            j = plus[i, a]
            di, dj = vals[i], vals[j]
            cos = np.einsum("ij,ij->i", unit[i], unit[j])
            cross = ((cos < max_dot) & (di + dj <= lim) | (cos < WIDE_DOT)) & good[i] & good[j]
            out.append((i[cross], di[cross] / np.maximum(di[cross] + dj[cross], 1e-12)))
        return out

    map_slices(gradients, n, workers)
    parts = map_slices(crossings, n, workers)
    starts = [p[a][0] for a in range(3) for p in parts]
    axes = [np.full(len(p[a][0]), a, dtype=np.int8) for a in range(3) for p in parts]
    ts = [p[a][1] for a in range(3) for p in parts]
    return np.concatenate(starts), np.concatenate(axes), np.concatenate(ts).astype(np.float64)


def dual_surface(g: np.ndarray, vals: np.ndarray, h: float, fill: float, max_sum: float = MAX_SUM,
                 max_dot: float = MAX_DOT, workers: int = 1) -> DualSurface:
    """Surface nets over the crossing edges (module docstring, step 3), in grid units; the per-point and per-edge
    steps run in `workers` threads."""
    g = np.asarray(g, dtype=np.int64).reshape(-1, 3)
    vals = np.asarray(vals, dtype=np.float32).reshape(-1)
    index = GridIndex(g)
    minus = np.empty((len(g), 3), dtype=index.itype)
    start, axis, t = crossing_edges(g, vals, h, fill, max_sum, max_dot, index, workers, minus)
    if len(start) == 0:
        return DualSurface(np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64))
    p0 = g[start]
    point = p0.astype(np.float64)
    rows = np.arange(len(start))
    point[rows, axis] += t
    # the four cubes (by min corner) around each edge, counter-clockwise seen from +axis: the edge's start,
    # its -1 neighbours along the two other axes, and the diagonal one (the -1 neighbour of a -1 neighbour, else
    # looked up)
    a1, a2 = (axis + 1) % 3, (axis + 2) % 3

    def cube_ids(lo: int, hi: int) -> np.ndarray:
        i, b1, b2 = start[lo:hi], a1[lo:hi], a2[lo:hi]
        out = np.empty((hi - lo, 4), dtype=np.int64)
        out[:, 0] = i
        out[:, 1] = minus[i, b1]
        out[:, 3] = minus[i, b2]
        has = out[:, 1] >= 0
        out[:, 2] = np.where(has, minus[np.maximum(out[:, 1], 0), b2], -1)
        look = np.flatnonzero(~has)
        if len(look):
            out[look, 2] = index.find(p0[lo + look] - _CUBES[axis[lo + look], 2])
        return out.reshape(-1)

    # a cube's id: its min corner's index among the grid points, or a new one past them
    cid = np.concatenate(map_slices(cube_ids, len(start), workers))
    missing = cid < 0
    n_ids = len(g)
    if missing.any():
        rows = np.flatnonzero(missing)
        corners = p0[rows // 4] - _CUBES[axis[rows // 4], rows % 4]
        uk, extra = np.unique(pack(corners), return_inverse=True)   # keys sort like the rows
        cid[missing] = len(g) + extra.reshape(-1)
        n_ids += len(uk)
    # the cubes in use, numbered in the order of their ids (np.unique's order, by a mask instead of a sort)
    mask = np.zeros(n_ids, dtype=bool)
    mask[cid] = True
    used = np.flatnonzero(mask)
    rank = np.empty(n_ids, dtype=np.int64)              # the rank of each used id (a cumsum of the mask, cheaper)
    rank[used] = np.arange(len(used))
    inv = rank[cid]
    counts = np.bincount(inv, minlength=len(used)).astype(np.float64)
    verts = np.stack([np.bincount(inv, weights=np.repeat(point[:, a], 4), minlength=len(used))
                      for a in range(3)], 1) / counts[:, None]
    quads = inv.reshape(-1, 4)
    # split each quad along its shorter diagonal
    def split(lo: int, hi: int) -> np.ndarray:
        q = quads[lo:hi]
        d02 = ((verts[q[:, 0]] - verts[q[:, 2]]) ** 2).sum(1)
        d13 = ((verts[q[:, 1]] - verts[q[:, 3]]) ** 2).sum(1)
        other = d02 > d13                                 # the rows of _SPLITS, column by column
        out = np.empty((hi - lo, 6), dtype=q.dtype)
        out[:, 0], out[:, 1], out[:, 4], out[:, 5] = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
        out[:, 2] = np.where(other, q[:, 3], q[:, 2])
        out[:, 3] = np.where(other, q[:, 1], q[:, 0])
        return out

    tri = np.concatenate(map_slices(split, len(quads), workers)).reshape(-1, 3)
    return DualSurface(verts, tri)
