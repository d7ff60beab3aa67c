"""Cleanup of extracted surfaces, vectorised: consistent orientation, fragments, pinholes, normals, decimation.

All functions take and return plain (vertices (V, 3) float64, faces (F, 3) int64) arrays, so they serve any mesh
(the fine stage's surface, tests' analytic meshes). Edges are keyed as min * V + max; a *manifold* edge has
exactly two faces.
"""
from __future__ import annotations

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import breadth_first_order, connected_components, minimum_spanning_tree


def face_normals(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(unit normals (F, 3), areas (F,)) by the right-hand rule."""
    if len(faces) == 0:
        return np.zeros((0, 3)), np.zeros(0)
    a, b, c = vertices[faces[:, 0]], vertices[faces[:, 1]], vertices[faces[:, 2]]
    e1, e2 = b - a, c - a
    n = np.empty_like(e1)       # the cross product by components: np.cross is several times slower
    n[:, 0] = e1[:, 1] * e2[:, 2] - e1[:, 2] * e2[:, 1]
    n[:, 1] = e1[:, 2] * e2[:, 0] - e1[:, 0] * e2[:, 2]
    n[:, 2] = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
    area2 = np.sqrt(np.einsum("ij,ij->i", n, n))
    n /= np.maximum(area2, 1e-300)[:, None]
    return n, 0.5 * area2


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted mean of the adjacent faces' normals, unit length (V, 3) float32; (0, 0, 1) where undefined."""
    n, area = face_normals(vertices, faces)
    out = np.zeros((len(vertices), 3))
    w = n * area[:, None]
    for k in range(3):
        for a in range(3):
            out[:, a] += np.bincount(faces[:, k], weights=w[:, a], minlength=len(vertices))
    norm = np.linalg.norm(out, axis=1)
    out = np.where(norm[:, None] > 0, out / np.maximum(norm, 1e-300)[:, None], np.array([0.0, 0.0, 1.0]))
    return out.astype(np.float32)


def edge_faces(faces: np.ndarray, n_vertices: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Half-edges grouped by undirected edge: (edge key per half-edge sorted (3F,), face per half-edge, count of
    half-edges of each half-edge's edge). Half-edge k of face f runs faces[f, k] -> faces[f, (k + 1) % 3]."""
    a = faces.reshape(-1)
    b = faces[:, [1, 2, 0]].reshape(-1)
    key = np.minimum(a, b).astype(np.int64) * n_vertices + np.maximum(a, b)
    order = np.argsort(key, kind="stable")
    ks = key[order]
    start = np.r_[True, ks[1:] != ks[:-1]]
    group = np.cumsum(start) - 1
    count = np.bincount(group)[group]
    return order, ks, count


def edge_stats(faces: np.ndarray, n_vertices: int) -> dict[str, int]:
    """Counts of boundary (1 face), manifold (2) and non-manifold (> 2) edges."""
    if len(faces) == 0:
        return {"boundary": 0, "manifold": 0, "nonmanifold": 0}
    _, ks, _ = edge_faces(faces, n_vertices)
    _, c = np.unique(ks, return_counts=True)
    return {"boundary": int((c == 1).sum()), "manifold": int((c == 2).sum()), "nonmanifold": int((c > 2).sum())}


def boundary_length(vertices: np.ndarray, faces: np.ndarray) -> float:
    """Total length of the edges that have one face (metres when the vertices are)."""
    if len(faces) == 0:
        return 0.0
    order, ks, count = edge_faces(faces, len(vertices))
    one = ks[count == 1]
    a, b = one // len(vertices), one % len(vertices)
    return float(np.linalg.norm(vertices[a] - vertices[b], axis=1).sum())


def _manifold_pairs(faces: np.ndarray, n_vertices: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(face a, face b, same_direction) for every manifold edge; same_direction: both faces run the edge the same
    way, i.e. one of them must flip for a consistent winding."""
    order, ks, count = edge_faces(faces, n_vertices)
    first = np.flatnonzero((count == 2) & np.r_[True, ks[1:] != ks[:-1]])
    h1, h2 = order[first], order[first + 1]
    start = faces.reshape(-1)
    return h1 // 3, h2 // 3, start[h1] == start[h2]


def orient(vertices: np.ndarray, faces: np.ndarray, prior: np.ndarray | None = None,
           seed: np.ndarray | None = None) -> np.ndarray:
    """Faces turned so that their normals follow `prior` where it is trusted (`seed`) and are consistent with their
    neighbours elsewhere.

    prior: (F, 3) wanted normal directions (e.g. towards the sensor that saw the face); seed: (F,) bool, the faces
    whose prior is trusted (default: none). A spanning forest of the face graph (manifold edges only), rooted at
    the seeds and otherwise preferring edges between faces whose normals are parallel (Hoppe et al. 1992: carry
    orientation across smooth parts, not across folds), gives every face the winding of the seed it hangs from;
    flips are accumulated by pointer doubling (O(F log depth), no Python loop over faces). A connected piece
    without seeds gets a consistent winding, turned as a whole to agree with the area-weighted `prior`.
    """
    faces = np.asarray(faces, dtype=np.int64)
    nf = len(faces)
    if nf == 0:
        return faces
    prior = np.zeros((nf, 3)) if prior is None else np.asarray(prior, dtype=np.float64)
    seed = np.zeros(nf, dtype=bool) if seed is None else np.asarray(seed, dtype=bool)
    fa, fb, same = _manifold_pairs(faces, len(vertices))
    n, area = face_normals(vertices, faces)
    agree = (n * prior).sum(1) >= 0
    n_comp, label = connected_components(coo_matrix((np.ones(len(fa)), (fa, fb)), shape=(nf, nf)), directed=False)
    # roots: every seed, and the first face of each piece without one (it keeps its winding)
    has_seed = np.bincount(label, weights=seed, minlength=n_comp) > 0
    first = np.unique(label, return_index=True)[1]
    roots = np.r_[np.flatnonzero(seed), first[~has_seed]]
    # cost 1 - |n_a . n_b| + a floor (explicit zeros would not be edges); root edges are cheaper than any
    cost = 1.0 - np.abs(np.einsum("ij,ij->i", n[fa], n[fb])) + 1e-6
    rows = np.r_[fa, np.full(len(roots), nf)]
    cols = np.r_[fb, roots]
    data = np.r_[cost, np.full(len(roots), 1e-9)]
    tree = minimum_spanning_tree(coo_matrix((data, (rows, cols)), shape=(nf + 1, nf + 1)).tocsr())
    _, pred = breadth_first_order(tree + tree.T, nf, directed=False, return_predecessors=True)
    pred = pred[:nf]
    # flip relative to the parent (index nf: the virtual root, flip 0): a seed turns to its prior, any other
    # face to its parent's winding
    flip = np.zeros(nf + 1, dtype=np.int8)
    up = np.full(nf + 1, nf, dtype=np.int64)
    at_root = pred == nf
    flip[:nf][at_root] = (seed[at_root] & ~agree[at_root]).astype(np.int8)
    pk = np.minimum(fa, fb) * nf + np.maximum(fa, fb)
    pk_order = np.argsort(pk, kind="stable")
    child = np.flatnonzero((pred >= 0) & (pred < nf))
    ck = np.minimum(child, pred[child]) * nf + np.maximum(child, pred[child])
    flip[child] = same[pk_order[np.searchsorted(pk[pk_order], ck)]]
    up[child] = pred[child]
    while True:  # pointer doubling: flip = xor of the relative flips from a face up to (excluding) `up`
        if np.all(up == nf):
            break
        flip ^= flip[up]
        up = up[up]
    flip = flip[:nf]
    # pieces without seeds: turn as a whole to the area-weighted prior
    sgn = np.where(flip == 1, -1.0, 1.0)
    vote = np.bincount(label, weights=sgn * (n * prior).sum(1) * area, minlength=n_comp)
    turn = ~has_seed & (vote < 0)
    flip ^= turn[label].astype(np.int8)
    out = faces.copy()
    out[flip == 1] = out[flip == 1][:, ::-1]
    return out


def components(faces: np.ndarray, n_vertices: int) -> tuple[int, np.ndarray]:
    """(count, label per face) of the pieces connected through shared vertices."""
    if len(faces) == 0:
        return 0, np.zeros(0, dtype=np.int64)
    rows = np.r_[faces[:, 0], faces[:, 1]]
    cols = np.r_[faces[:, 1], faces[:, 2]]
    graph = coo_matrix((np.ones(len(rows), dtype=np.int8), (rows, cols)), shape=(n_vertices, n_vertices))
    n, label = connected_components(graph, directed=False)
    used, face_label = np.unique(label[faces[:, 0]], return_inverse=True)
    return len(used), face_label.reshape(-1)


def compact(vertices: np.ndarray, faces: np.ndarray, keep_faces: np.ndarray | None = None
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Keep the selected faces and the vertices they use: (vertices, faces, old index of each kept vertex)."""
    f = faces if keep_faces is None else faces[keep_faces]
    used = np.unique(f)
    remap = np.full(len(vertices), -1, dtype=np.int64)
    remap[used] = np.arange(len(used))
    return vertices[used], remap[f], used


def drop_fragments(vertices: np.ndarray, faces: np.ndarray, min_area: float) -> tuple[np.ndarray, np.ndarray]:
    """Remove connected pieces whose total area is below `min_area` (floating specks), then unused vertices."""
    if len(faces) == 0:
        return np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64)
    n, label = components(faces, len(vertices))
    _, area = face_normals(vertices, faces)
    keep = np.bincount(label, weights=area, minlength=n)[label] >= min_area
    v, f, _ = compact(vertices, faces, keep)
    return v, f


def fill_pinholes(vertices: np.ndarray, faces: np.ndarray, max_edges: int = 12) -> np.ndarray:
    """Faces plus fans closing every boundary loop of at most `max_edges` edges (the winding must be consistent:
    run after `orient`). Loops through a vertex with more than one boundary edge out are left open."""
    if len(faces) == 0:
        return faces
    nv = len(vertices)
    order, ks, count = edge_faces(faces, nv)
    half = order[count == 1]                              # boundary half-edges
    a = faces.reshape(-1)[half]
    b = faces[:, [1, 2, 0]].reshape(-1)[half]
    out_deg = np.bincount(a, minlength=nv)
    in_deg = np.bincount(b, minlength=nv)
    simple = (out_deg[a] == 1) & (in_deg[a] == 1) & (out_deg[b] == 1) & (in_deg[b] == 1)
    a, b = a[simple], b[simple]
    if len(a) == 0:
        return faces
    nxt = np.full(nv, -1, dtype=np.int64)
    nxt[a] = b
    graph = coo_matrix((np.ones(len(a), dtype=np.int8), (a, b)), shape=(nv, nv))
    _, label = connected_components(graph, directed=False)
    loop_len = np.bincount(label[a], minlength=label.max() + 1)
    # a loop: every member vertex has its successor (closed cycle); take those short enough, from their min vertex
    closed = np.ones(label.max() + 1, dtype=bool)
    lone = np.setdiff1d(np.r_[a, b], a)                  # vertices with no successor: an open chain
    closed[label[lone]] = False
    first = np.full(label.max() + 1, nv, dtype=np.int64)
    np.minimum.at(first, label[a], a)
    sel = np.flatnonzero(closed & (loop_len >= 3) & (loop_len <= max_edges) & (first < nv))
    if len(sel) == 0:
        return faces
    L = loop_len[sel]
    seq = np.empty((len(sel), max_edges), dtype=np.int64)
    seq[:, 0] = first[sel]
    for k in range(1, max_edges):
        seq[:, k] = nxt[seq[:, k - 1]]
    tris = []
    for i in range(1, max_edges - 1):                     # fan (v0, v_{i+1}, v_i), reversed to the boundary
        ok = i + 1 < L
        tris.append(np.stack([seq[ok, 0], seq[ok, i + 1], seq[ok, i]], 1))
    return np.concatenate([faces, *tris])


def smooth_flat(vertices: np.ndarray, faces: np.ndarray, sigma: float = 0.4, tol: float = 0.04,
                max_tilt_deg: float = 25.0, cell: float = 0.15) -> np.ndarray:
    """Vertices with the height of near-horizontal parts replaced by a robust local plane fit (a bilateral
    filter of the height field): the ground stays flat where the world is flat.

    Each vertex whose normal is within `max_tilt_deg` of vertical takes the height, at its x/y, of a weighted
    least-squares plane z = a + b x + c y over the near-horizontal surface around it: Gaussian weights of width
    `sigma` in x/y and `tol` in height, so a kerb or step higher than ~2 `tol` is a different surface, while
    slopes, camber and ramps are kept (a plane through them). For speed the planes are fitted per `cell`-sized
    cluster of vertices (in x, y and height / tol * sigma) and blended between the 4 nearest clusters.
    No vertex moves by more than `tol`.
    """
    from scipy.spatial import cKDTree

    v = np.asarray(vertices, dtype=np.float64).copy()
    if len(faces) == 0:
        return v
    n = vertex_normals(v, faces)
    flat = np.flatnonzero(np.abs(n[:, 2]) > np.cos(np.radians(max_tilt_deg)))
    if len(flat) < 3:
        return v
    scale = np.array([1.0, 1.0, sigma / tol])
    q = v[flat] * scale
    key = np.floor(q / cell).astype(np.int64)
    _, inv, cnt = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    inv = inv.reshape(-1)
    nc = len(cnt)
    c = np.stack([np.bincount(inv, weights=q[:, a], minlength=nc) for a in range(3)], 1) / cnt[:, None]
    pairs = cKDTree(c).query_pairs(2.0 * sigma, output_type="ndarray")
    i = np.r_[pairs[:, 0], pairs[:, 1], np.arange(nc)]
    j = np.r_[pairs[:, 1], pairs[:, 0], np.arange(nc)]
    d2 = ((c[i] - c[j]) ** 2).sum(1)
    w = np.exp(-0.5 * d2 / sigma ** 2) * cnt[j]
    x, y, z = c[j, 0] - c[i, 0], c[j, 1] - c[i, 1], c[j, 2] / scale[2]

    def s(val: np.ndarray) -> np.ndarray:
        return np.bincount(i, weights=w * val, minlength=nc)

    A = np.empty((nc, 3, 3))
    A[:, 0, 0], A[:, 0, 1], A[:, 0, 2] = s(np.ones_like(x)), s(x), s(y)
    A[:, 1, 1], A[:, 1, 2], A[:, 2, 2] = s(x * x), s(x * y), s(y * y)
    A[:, 1, 0], A[:, 2, 0], A[:, 2, 1] = A[:, 0, 1], A[:, 0, 2], A[:, 1, 2]
    rhs = np.stack([s(z), s(x * z), s(y * z)], 1)
    # a plane where the neighbourhood spans two directions, else the weighted mean height
    det = np.linalg.det(A[:, 1:, 1:] - A[:, 1:, :1] * A[:, :1, 1:] / A[:, :1, :1])
    good = det > 1e-3 * A[:, 0, 0] ** 2 * sigma ** 4
    coef = np.zeros((nc, 3))
    coef[:, 0] = rhs[:, 0] / A[:, 0, 0]
    if good.any():
        coef[good] = np.linalg.solve(A[good], rhs[good][:, :, None])[:, :, 0]
    # blend the planes of the (up to) 4 nearest clusters at each vertex
    k = min(4, nc)
    dist, idx = cKDTree(c).query(q, k=k)
    dist, idx = dist.reshape(len(q), k), idx.reshape(len(q), k)
    wv = np.exp(-0.5 * (dist / cell) ** 2) + 1e-12
    dx, dy = q[:, None, 0] - c[idx, 0], q[:, None, 1] - c[idx, 1]
    zp = coef[idx, 0] + coef[idx, 1] * dx + coef[idx, 2] * dy
    znew = (wv * zp).sum(1) / wv.sum(1)
    v[flat, 2] += np.clip(znew - v[flat, 2], -tol, tol)
    return v
