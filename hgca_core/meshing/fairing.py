"""Ground fairing: near-horizontal surfaces made as flat as the input points say, between the points.

Why: the fine stage puts the ground where the input's scan rings are to a few millimetres, but the ground it
generates between the rings sits on terraces up to ~5-10 cm above or below them (a generated 10 cm cell does not
know its sub-cell height; benchmarks/results/mesh_quality.md), which is what "scan-ring ripples" are on a road.
The fairing treats the heights of near-horizontal vertices as a membrane anchored where input points are:

    minimise  sum over edges (i, j) of (z_i - z_j - s . (p_i - p_j))^2  +  sum_i w_i (z_i - t_i)^2,
    w_i = anchor_weight * exp(-(d_i / anchor_scale)^2) + free_weight,

over the heights z_i of "ground-like" vertices only: normals, averaged over `rings` rings of neighbours, within
`tilt` degrees of vertical, not on a steep part at least `step` tall, in a connected region of at least
`min_region` (a car roof, a bonnet keep their shape). Every other vertex (facades, kerb sides, car bodies) is
fixed and bounds the membrane, so kerbs stay while the terraces' few-centimetre risers are smoothed away. d_i is
the vertex's distance to the nearest input point. t_i is where the anchor pulls: the vertex's own height plus the
local bias of the decoded ground, the anchor-weighted mean of (nearest point's height - vertex height) over
`offset_tile` squares, blended bilinearly (`point_heights`; without them t_i is the vertex's own height). The decoded
surface at the rings is off by a few millimetres (on the AV2 log 7fab 1-6 mm below the points' plane), and holding
it there carried that error between the rings; pulling each vertex to its own nearest point instead fixes the bias
but draws every ring as a stripe (its one noisy point per vertex), so the pull is the local mean. On 10 val scenes
the road then lies closer to the true plane (benchmarks/results/fairing_sweep.md, in git at 7f06b18). Far from every point a vertex
follows the evidence around it. Without input (`distances` None) it is a plain low-pass.

s is the local slope (`slopes`: planes per region and 8 m square, fitted mostly to the vertices at input points).
A membrane on raw heights prefers level ground: where the neighbours lie on one side (the region's edge, holes) it
would bend a sloped road by 10 cm on a 5 % slope; against the local slope, every plane is a fixed point and a
crest of 200 m radius scanned every metre moves by < 5 mm (tests/meshing/test_fairing.py). No vertex moves
more than `max_move` (one fine cell; on the AV2 log 7fab 0.2 % of the vertices reach it, on hole rims far from
any point).

Only heights move (the surfaces concerned are within `tilt` of horizontal), so no triangle flips. The system is
the graph Laplacian plus a positive diagonal: symmetric positive definite, solved by Jacobi-preconditioned CG for
the height change (relative tolerance 1e-3: 0.4 mm RMS from the converged solution on a default region).

Defaults selected on three synth2 val scenes by the height error against the ground-truth road plane, with the
AV2 log 7fab's flatness as a check (the mesh_quality.md of commit 01d23f9); the anchor weight with both kinds of
targets re-measured on 10 generator-7 val scenes (benchmarks/results/fairing_sweep.md, in git at 7f06b18).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse import csr_matrix, diags
from scipy.sparse.csgraph import connected_components

from hgca_core.geometry.keys import pack
from hgca_core.meshing.mesh_clean import adjacency, face_normals, vertex_sums
from hgca_core.geometry.nearest import PointIndex
from hgca_core.meshing.parallel import map_slices, run_all
from hgca_core.geometry.planes import fit_planes

TILT = 30.0            # degrees: surfaces flatter than this are ground-like
NORMAL_RINGS = 3       # rings of neighbours the normals are averaged over before the tilt test (~15 cm at 5 cm)
ANCHOR_SCALE = 0.02    # m: an input point holds a vertex within about this distance
ANCHOR_WEIGHT = 10.0
FREE_WEIGHT = 3e-4     # keeps vertices far from every point near their own height over ~60 edges (~2 m)
TILE = 8.0             # m: the squares whose local planes give the slope the membrane keeps (see slopes)
MAX_MOVE = 0.1         # m: no vertex moves farther than one fine cell (a rim or a lip far from every point)
STEP = 0.08            # m: steep parts at least this tall (kerbs, walls, car sides) bound the membrane
STEEP = 45.0           # degrees: faces steeper than this make up steps
OFFSET_TILE = 0.5      # m: squares over which the anchors' offset to the points is averaged (0.25 m: stripes)
MIN_REGION = 8.0       # m^2: connected ground-like regions smaller than this (a car roof, a bonnet) keep their shape


@dataclass
class FairingReport:
    """What the fairing did: vertices moved (ground-like), largest and RMS height change (m), CG iterations."""

    ground: int
    max_move: float
    rms_move: float
    iterations: int


def ground_like(normals: np.ndarray, adj: csr_matrix, tilt: float = TILT, rings: int = NORMAL_RINGS) -> np.ndarray:
    """(V,) bool: the vertex normal (area-weighted, unnormalised is fine), averaged over `rings` rings of
    neighbours, is within `tilt` of vertical (either way up: orientation does not matter for a height)."""
    n = normals
    for _ in range(rings):
        n = n + adj @ n
    return np.abs(n[:, 2]) > np.cos(np.radians(tilt)) * np.maximum(np.linalg.norm(n, axis=1), 1e-12)


def _components(adj: csr_matrix, idx: np.ndarray) -> tuple[int, np.ndarray, csr_matrix]:
    """(count, label of each vertex in `idx`, the edges among them) of the connected parts of a vertex subset."""
    sub = _subgraph(adj, idx)
    n, label = connected_components(sub, directed=False)
    return n, label, sub


def tall_steps(face_normals: np.ndarray, faces: np.ndarray, z: np.ndarray, adj: csr_matrix,
               steep: float = STEEP, step: float = STEP) -> np.ndarray:
    """(V,) bool: vertices of steep faces (more than `steep` degrees from horizontal) whose connected steep part
    rises at least `step`: a kerb, a wall, a car's side; not the few-centimetre risers between terraces."""
    v_steep = np.zeros(len(z), dtype=bool)
    v_steep[faces[np.abs(face_normals[:, 2]) < np.cos(np.radians(steep))].reshape(-1)] = True
    idx = np.flatnonzero(v_steep)
    if len(idx) == 0:
        return v_steep
    n, label, _ = _components(adj, idx)
    lo = np.full(n, np.inf)
    hi = np.full(n, -np.inf)
    np.minimum.at(lo, label, z[idx])
    np.maximum.at(hi, label, z[idx])
    v_steep[idx] = (hi - lo)[label] >= step
    return v_steep


def slopes(vertices: np.ndarray, label: np.ndarray, weight: np.ndarray, tile: float = TILE,
           workers: int = 1) -> np.ndarray:
    """(N, 2) slope (dz/dx, dz/dy) at each of N labelled vertices (`label` >= 0: its ground region): weighted
    least-squares planes per region and `tile` x `tile` square, their slopes blended bilinearly between square
    centres within the region. Exact for any plane; a kerb between two regions does not tilt either's planes.
    `weight`: how much each vertex is trusted (the fairing gives vertices at input points ~1000 times the weight
    of the others, so where the rings are, they alone set the slope and the terraces between them do not).
    `workers`: threads for the blend (slices of the vertices)."""
    p = np.asarray(vertices, dtype=np.float64)
    region = np.unique(label, return_inverse=True)[1].reshape(-1)       # 0..R-1: fits in a key's z field
    t = np.floor(p[:, :2] / tile).astype(np.int64)                     # squares

    key, inv = np.unique(pack(np.c_[t[:, 0], t[:, 1], region]), return_inverse=True)
    inv = inv.reshape(-1)
    m = len(key)
    fit = fit_planes(p, inv, m, weight)
    cnt, grad = fit.weight, fit.slope
    # trusted squares: not degenerate, and spread (standard deviation) at least 1/16 of a square both ways: a
    # sliver along the region's edge would tilt its neighbours
    spread = np.minimum(fit.sxx, fit.syy) >= (tile / 16) ** 2 * cnt
    ok = (fit.det > 1e-6 * np.maximum(fit.sxx * fit.syy, 1e-30)) & spread
    # bilinear blend over the (up to) four squares of the same region nearest to each vertex, each also weighted
    # by its total weight
    out = np.empty((len(p), 2))

    def blend(lo: int, hi: int) -> None:
        u = p[lo:hi, :2] / tile - 0.5
        base = np.floor(u).astype(np.int64)
        frac = u - base
        num = np.zeros((hi - lo, 2))
        den = np.zeros(hi - lo)
        for dx in (0, 1):
            for dy in (0, 1):
                k = pack(np.c_[base[:, 0] + dx, base[:, 1] + dy, region[lo:hi]])
                j = np.searchsorted(key, k).clip(max=m - 1)
                wt = np.where((key[j] == k) & ok[j],
                              np.abs(1 - dx - frac[:, 0]) * np.abs(1 - dy - frac[:, 1]) * cnt[j], 0.0)
                num += wt[:, None] * grad[j]
                den += wt
        out[lo:hi] = np.where(den[:, None] > 0, num / np.maximum(den, 1e-300)[:, None], 0.0)  # none trusted: level

    map_slices(blend, len(p), workers)
    return out


def local_offsets(p: np.ndarray, offset: np.ndarray, weight: np.ndarray, tile: float) -> np.ndarray:
    """(N,) the `weight`-ed mean of the finite `offset`s over `tile` squares, splatted to and gathered from the
    square centres bilinearly (so it varies smoothly); NaN where the offset itself is not finite (no point near)."""
    if len(p) == 0:
        return np.zeros(0)
    ok = np.isfinite(offset)
    u = p[:, :2] / tile - 0.5
    base = np.floor(u).astype(np.int64)
    frac = u - base
    lo = base.min(0)
    ny = int(base[:, 1].max() - lo[1]) + 2
    n = (int(base[:, 0].max() - lo[0]) + 2) * ny
    key = (base[:, 0] - lo[0]) * ny + (base[:, 1] - lo[1])
    corners = [(dx * ny + dy, np.abs(1 - dx - frac[:, 0]) * np.abs(1 - dy - frac[:, 1]))
               for dx in (0, 1) for dy in (0, 1)]
    wo = np.where(ok, weight, 0.0)
    num, den = np.zeros(n), np.zeros(n)
    for shift, b in corners:
        num += np.bincount(key + shift, weights=b * wo * np.where(ok, offset, 0.0), minlength=n)
        den += np.bincount(key + shift, weights=b * wo, minlength=n)
    has = den > 1e-3                       # squares with at least a vertex at a point's worth of evidence
    mean = np.where(has, num / np.maximum(den, 1e-12), 0.0)
    out, norm = np.zeros(len(p)), np.zeros(len(p))
    for shift, b in corners:
        k = key + shift
        out += np.where(has[k], b * mean[k], 0.0)
        norm += np.where(has[k], b, 0.0)
    return np.where(ok & (norm > 0), out / np.maximum(norm, 1e-12), np.nan)


def fair_ground(vertices: np.ndarray, faces: np.ndarray, distances: np.ndarray | None = None,
                tilt: float = TILT, rings: int = NORMAL_RINGS, anchor_scale: float = ANCHOR_SCALE,
                anchor_weight: float = ANCHOR_WEIGHT, free_weight: float = FREE_WEIGHT,
                min_region: float = MIN_REGION, step: float = STEP, tile: float = TILE, max_move: float = MAX_MOVE,
                tol: float = 1e-3, max_iter: int = 500, point_heights: np.ndarray | None = None,
                offset_tile: float = OFFSET_TILE, workers: int = 1, points: PointIndex | None = None
                ) -> tuple[np.ndarray, FairingReport]:
    """(vertices with the heights of ground-like vertices faired, report); see the module docstring.

    distances: (V,) each vertex's distance to the nearest input point (m), or None for no evidence.
    point_heights: (V,) the height of that nearest point (NaN where none is near): the anchors pull by the local
      mean offset to them over `offset_tile` squares (0: to each vertex's own point); None: the anchors hold.
    workers: threads (the adjacency is built while the normals are summed).
    points: instead of `distances` and `point_heights`, the input points' index: only the ground-like vertices
      (those the two are read for, about half) are looked up, within 3 `anchor_scale` (beyond, the anchor's
      weight is below a tenth of `free_weight`): the same values as a lookup of every vertex.
    """
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    out = v.copy()
    if len(f) == 0:
        return out, FairingReport(0, 0.0, 0.0, 0)
    if free_weight <= 0:
        raise ValueError(f"free_weight must be positive (it keeps the system definite), got {free_weight}")
    def normals() -> tuple[np.ndarray, np.ndarray]:
        fn, area = face_normals(v.astype(np.float32), f, workers)
        return fn, vertex_sums(f, len(v), np.c_[fn * area[:, None], area / 3])  # area-weighted normals, areas

    adj, (fn, sums) = run_all(lambda: adjacency(f, len(v)), normals, workers=workers)
    g = ground_like(sums[:, :3], adj, tilt, rings) & ~tall_steps(fn, f, v[:, 2], adj, step=step)
    idx = np.flatnonzero(g)
    n_regions, label, sub = _components(adj, idx)                       # connected ground regions
    big = np.bincount(label, weights=sums[idx, 3], minlength=n_regions)[label] >= min_region
    g[idx[~big]] = False
    n = int(g.sum())
    if n == 0:
        return out, FairingReport(0, 0.0, 0.0, 0)
    # Solved for the height change dz: A dz = r with A = diag(deg + w) - L_gg and r the neighbours' pull
    # sum_j (z_j - z_i - s_i . (p_j - p_i)) against the local slope s_i (fixed neighbours included: they bound
    # the membrane). The data terms vanish at dz = 0, so a relative tolerance means "this much of the initial
    # imbalance left", whatever the heights' magnitude.
    deg = np.diff(adj.indptr).astype(np.float64)[g]
    pull = (adj @ v)[g] - deg[:, None] * v[g]                          # sum_j (p_j - p_i), x y z
    if points is not None and distances is None:
        dist, which = points.nearest(v[g], upper=3 * anchor_scale)
        heights = np.where(which >= 0, points.points[which, 2], np.nan)
    else:
        dist = None if distances is None else np.asarray(distances, dtype=np.float64)[g]
        heights = None if point_heights is None else np.asarray(point_heights, dtype=np.float64)[g]
    anchor = anchor_weight * np.exp(-np.square(dist / anchor_scale)) if dist is not None else np.zeros(n)
    w = free_weight + anchor
    r = pull[:, 2] - np.einsum("ij,ij->i", slopes(v[g], label[big], w, tile, workers), pull[:, :2])
    if heights is not None:                # the anchors pull by t_i - z_i instead of holding (module docstring)
        offset = heights - v[g, 2]
        if offset_tile > 0:
            offset = local_offsets(v[g], offset, anchor, offset_tile)
        r += np.where(np.isfinite(offset), anchor * offset, 0.0)
    diag = (deg + w).astype(np.float32)
    system = (diags(diag) - _subgraph(sub, np.flatnonzero(big))).tocsr()   # float32: half the memory traffic
    dz, iterations = _cg(system, r.astype(np.float32), 1.0 / diag, tol, max_iter)
    dz = np.clip(dz, -max_move, max_move)
    out[g, 2] += dz
    return out, FairingReport(n, float(np.abs(dz).max()), float(np.sqrt(np.mean(dz ** 2))), iterations)


def _cg(a: csr_matrix, b: np.ndarray, inv_diag: np.ndarray, tol: float, max_iter: int) -> tuple[np.ndarray, int]:
    """Jacobi-preconditioned CG; returns (solution, iterations).

    The steps of scipy's `cg` (1.17) in its order and float types, so the same solution bit for bit
    (tests/meshing/test_fairing.py checks), without its operator wrappers and per-step temporaries; the
    preconditioner is an elementwise product where scipy multiplies by a diagonal matrix (0 + d r: the same)."""
    b = np.asarray(b)
    bnrm2 = np.linalg.norm(b)
    if bnrm2 == 0:
        return b, 0
    atol = max(0.0, float(tol) * float(bnrm2))
    x = np.zeros(len(b), dtype=np.result_type(a.dtype, b.dtype))
    r = b.astype(x.dtype)
    z, tmp = np.empty_like(r), np.empty_like(r)
    p, rho_prev = z, None
    for iteration in range(max_iter):
        if np.linalg.norm(r) < atol:
            return x, iteration
        np.multiply(inv_diag, r, out=z)
        z += 0                                          # as scipy's diagonal product: -0 becomes +0
        rho = np.dot(r, z)
        if iteration > 0:
            p *= rho / rho_prev
            p += z
        else:
            p = z.copy()
        q = a @ p
        alpha = rho / np.dot(p, q)
        np.multiply(p, alpha, out=tmp)
        x += tmp
        np.multiply(q, alpha, out=tmp)
        r -= tmp
        rho_prev = rho
    return x, max_iter


def _subgraph(adj: csr_matrix, idx: np.ndarray) -> csr_matrix:
    """`adj[idx][:, idx]` for sorted unique `idx`, the same matrix (sorted rows), by one relabelling of the
    selected rows' columns: scipy's column selection costs several times more."""
    rows = adj[idx]
    new = np.full(adj.shape[1], -1, dtype=rows.indices.dtype)
    new[idx] = np.arange(len(idx), dtype=new.dtype)
    col = new[rows.indices]
    keep = col >= 0
    seen = np.zeros(len(keep) + 1, dtype=rows.indptr.dtype)
    np.cumsum(keep, out=seen[1:])
    out = csr_matrix((rows.data[keep], col[keep], seen[rows.indptr]), shape=(len(idx), len(idx)))
    out.has_sorted_indices = rows.has_sorted_indices
    return out
