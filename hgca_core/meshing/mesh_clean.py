"""Cleanup of extracted surfaces, vectorised: consistent orientation, fragments, pinholes, normals, decimation.

All functions take and return plain (vertices (V, 3) float64, faces (F, 3) int64) arrays, so they serve any mesh
(the fine stage's surface, tests' analytic meshes). Edges are keyed as min * V + max; a *manifold* edge has
exactly two faces.
"""
from __future__ import annotations

import numpy as np
from scipy.sparse import coo_matrix, csr_matrix
from scipy.sparse.csgraph import breadth_first_order, connected_components

from hgca_core.meshing.parallel import map_slices, run_all


def face_normals(vertices: np.ndarray, faces: np.ndarray, workers: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """(unit normals (F, 3), areas (F,)) by the right-hand rule, in the vertices' float type; slices of the faces
    in `workers` threads."""
    if len(faces) == 0:
        return np.zeros((0, 3)), np.zeros(0)
    n = np.empty((len(faces), 3), dtype=np.result_type(vertices.dtype, np.float32))
    area = np.empty(len(faces), dtype=n.dtype)

    def part(lo: int, hi: int) -> None:
        f = faces[lo:hi]
        a = vertices[f[:, 0]]
        e1, e2 = vertices[f[:, 1]] - a, vertices[f[:, 2]] - a
        m = n[lo:hi]            # the cross product by components: np.cross is several times slower
        m[:, 0] = e1[:, 1] * e2[:, 2] - e1[:, 2] * e2[:, 1]
        m[:, 1] = e1[:, 2] * e2[:, 0] - e1[:, 0] * e2[:, 2]
        m[:, 2] = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
        area2 = np.sqrt(np.einsum("ij,ij->i", m, m))
        m /= np.maximum(area2, np.finfo(n.dtype).tiny)[:, None]
        area[lo:hi] = 0.5 * area2

    map_slices(part, len(faces), workers)
    return n, area


def vertex_sums(faces: np.ndarray, n_vertices: int, values: np.ndarray) -> np.ndarray:
    """Per-vertex sums (V, C) of per-face values (F, C) over each vertex's faces."""
    corner = [np.ascontiguousarray(faces[:, k]) for k in range(3)]        # one copy per corner, not per channel
    out = np.empty((n_vertices, values.shape[1]))
    for c in range(values.shape[1]):
        w = np.ascontiguousarray(values[:, c])
        out[:, c] = sum(np.bincount(corner[k], weights=w, minlength=n_vertices) for k in range(3))
    return out


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted mean of the adjacent faces' normals, unit length (V, 3) float32; (0, 0, 1) where undefined."""
    n, area = face_normals(vertices, faces)
    out = vertex_sums(faces, len(vertices), n * area[:, None])
    norm = np.linalg.norm(out, axis=1)
    out = np.where(norm[:, None] > 0, out / np.maximum(norm, 1e-300)[:, None], np.array([0.0, 0.0, 1.0]))
    return out.astype(np.float32)


def edge_faces(faces: np.ndarray, n_vertices: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Half-edges grouped by undirected edge: (half-edge ids sorted by edge key (3F,), their edge keys, the number
    of half-edges of each one's edge). Half-edge 3 f + k runs faces[f, k] -> faces[f, (k + 1) % 3]."""
    a = faces.reshape(-1)
    b = faces[:, [1, 2, 0]].reshape(-1)
    key = np.minimum(a, b).astype(np.int64, copy=False)
    key *= n_vertices                          # in place: each temporary of 3F keys is a fresh 40 MB to fault in
    key += np.maximum(a, b)
    order = np.argsort(key, kind="stable")     # faces come in runs of near vertex ids: ~1.7x faster than quicksort
    ks = key[order]
    return order, ks, run_lengths(ks)


def run_lengths(sorted_keys: np.ndarray) -> np.ndarray:
    """For each element of a sorted key array, how many elements share its key (empty in, empty out)."""
    k = np.asarray(sorted_keys)
    if len(k) == 0:
        return np.zeros(0, dtype=np.int64)
    new = np.empty(len(k), dtype=bool)
    new[0] = True
    np.not_equal(k[1:], k[:-1], out=new[1:])
    length = np.diff(np.append(np.flatnonzero(new), len(k)))    # runs, then each element its run's length
    return np.repeat(length, length)


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


def _manifold_pairs(faces: np.ndarray, n_vertices: int, edges: tuple | None = None
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(face a, face b, same_direction) for every manifold edge; same_direction: both faces run the edge the same
    way, i.e. one of them must flip for a consistent winding. `edges`: `edge_faces` of these faces, if known."""
    order, ks, count = edge_faces(faces, n_vertices) if edges is None else edges
    first = np.flatnonzero((count == 2) & np.r_[True, ks[1:] != ks[:-1]])
    h1, h2 = order[first], order[first + 1]
    start = faces.reshape(-1)
    return h1 // 3, h2 // 3, start[h1] == start[h2]


def orient(vertices: np.ndarray, faces: np.ndarray, prior: np.ndarray | None = None,
           seed: np.ndarray | None = None, normals: np.ndarray | None = None, edges: tuple | None = None,
           pieces: tuple[int, np.ndarray] | None = None, pairs: tuple | None = None,
           graph: csr_matrix | None = None, workers: int = 1) -> np.ndarray:
    """Faces turned so that their normals follow `prior` where it is trusted (`seed`) and are consistent with their
    neighbours elsewhere.

    prior: (F, 3) wanted normal directions (e.g. towards the sensor that saw the face); seed: (F,) bool, the faces
    whose prior is trusted (default: none). A breadth-first forest of the face graph (manifold edges only), grown
    from all seeds at once, gives every face the winding of the seed nearest to it (in steps); flips are
    accumulated by pointer doubling (O(F log depth), no Python loop over faces). A connected piece without seeds
    gets a consistent winding, turned as a whole to agree with `prior` (face-count weighted).
    normals / edges / pieces / pairs / graph: `face_normals(...)[0]`, `edge_faces(...)`, `face_pieces(...)`, the
    manifold face pairs (fa, fb) of these faces and their `face_graph`, if already known.
    """
    faces = np.asarray(faces, dtype=np.int64)
    nf = len(faces)
    if nf == 0:
        return faces
    prior = np.zeros((nf, 3)) if prior is None else np.asarray(prior, dtype=np.float64)
    seed = np.zeros(nf, dtype=bool) if seed is None else np.asarray(seed, dtype=bool)
    if graph is None:
        fa, fb = _manifold_pairs(faces, len(vertices), edges)[:2] if pairs is None else pairs
        graph = face_graph(nf, fa, fb)
    n = face_normals(vertices, faces, workers)[0] if normals is None else normals
    dot = np.concatenate(map_slices(lambda lo, hi: np.einsum("ij,ij->i", n[lo:hi], prior[lo:hi]), nf, workers))
    n_comp, label = face_pieces(graph) if pieces is None else pieces
    # roots: every seed, and the first face of each piece without one (it keeps its winding)
    has_seed = np.bincount(label, weights=seed, minlength=n_comp) > 0
    first = np.empty(n_comp, dtype=np.int64)
    first[label[::-1]] = np.arange(nf - 1, -1, -1)
    roots = np.r_[np.flatnonzero(seed), first[~has_seed]].astype(graph.indices.dtype)
    # one breadth-first forest from a virtual root (index nf): the graph with one more row, listing the roots
    rooted = csr_matrix((np.r_[graph.data, np.ones(len(roots), dtype=graph.data.dtype)],
                         np.r_[graph.indices, roots], np.r_[graph.indptr, graph.indptr[-1] + len(roots)]),
                        shape=(nf + 1, nf + 1))
    _, pred = breadth_first_order(rooted, nf, directed=True, return_predecessors=True)
    pred = pred[:nf].astype(np.int64)
    # flip relative to the parent (index nf: the virtual root, flip 0): a seed turns to its prior, any other
    # face to its parent's winding (it must flip when both run their shared edge the same way)
    flip = np.zeros(nf + 1, dtype=np.int8)
    up = np.full(nf + 1, nf, dtype=np.int64)
    at_root = pred == nf
    flip[:nf][at_root] = seed[at_root] & (dot[at_root] < 0)
    child = np.flatnonzero((pred >= 0) & (pred < nf))

    def same_way(lo: int, hi: int) -> np.ndarray:
        fc, fp = faces[child[lo:hi]], faces[pred[child[lo:hi]]]
        same = np.zeros(len(fc), dtype=bool)
        for i in range(3):
            for j in range(3):
                same |= (fc[:, i] == fp[:, j]) & (fc[:, (i + 1) % 3] == fp[:, (j + 1) % 3])
        return same

    flip[child] = np.concatenate(map_slices(same_way, len(child), workers))
    up[child] = pred[child]
    active = child
    while len(active):  # pointer doubling: flip = xor of the relative flips from a face up to (excluding) `up`
        flip[active] ^= flip[up[active]]
        up[active] = up[up[active]]
        active = active[up[active] != nf]
    flip = flip[:nf]
    # pieces without seeds: turn as a whole to the area-weighted prior
    if not has_seed.all():
        vote = np.bincount(label, weights=np.where(flip == 1, -dot, dot), minlength=n_comp)
        flip ^= (~has_seed & (vote < 0))[label].astype(np.int8)
    out = faces.copy()
    out[flip == 1] = out[flip == 1][:, ::-1]
    return out


def face_graph(n_faces: int, fa: np.ndarray, fb: np.ndarray) -> csr_matrix:
    """(F, F) symmetric 0/1 matrix of face adjacency from face pairs (both directions stored, so traversals need
    no transpose)."""
    return csr_matrix((np.ones(2 * len(fa), dtype=np.int8), (np.r_[fa, fb], np.r_[fb, fa])),
                      shape=(n_faces, n_faces))


def face_pieces(graph: csr_matrix) -> tuple[int, np.ndarray]:
    """(count, label per face) of the pieces of a `face_graph` (faces connected through manifold edges)."""
    return connected_components(graph, directed=False)


def adjacency(faces: np.ndarray, n_vertices: int) -> csr_matrix:
    """(V, V) 0/1 symmetric matrix of the mesh's edges, indices sorted within rows (scipy's canonical form).

    Built from the sorted unique edge keys min * V + max, without scipy's COO -> CSR conversion and duplicate
    summing of all 6 F directed entries: in key order the edges (i, j), i <= j, are already the upper triangle in
    CSR order; the lower one is its transpose (scipy's linear-time CSR -> CSC), and their sum merges each row's
    two sorted runs. A face (i, i, j) gives an entry (i, i), once.
    """
    f = np.asarray(faces, dtype=np.int64)
    nv = int(n_vertices)
    a, b = f.reshape(-1), f[:, [1, 2, 0]].reshape(-1)
    key = np.minimum(a, b)
    key *= nv
    key += np.maximum(a, b)
    lo, hi = np.divmod(np.unique(key), nv)
    index_dtype = np.int32 if max(nv, 2 * len(lo)) < np.iinfo(np.int32).max else np.int64

    def upper(rows: np.ndarray, cols: np.ndarray) -> csr_matrix:
        indptr = np.zeros(nv + 1, dtype=index_dtype)
        np.cumsum(np.bincount(rows, minlength=nv), out=indptr[1:])
        out = csr_matrix((np.ones(len(cols), dtype=np.float32), cols.astype(index_dtype), indptr), shape=(nv, nv))
        out.has_sorted_indices = True
        return out

    strict = lo < hi
    up = upper(lo, hi)
    low = (up if strict.all() else upper(lo[strict], hi[strict])).T.tocsr()
    out = up + low
    out.has_sorted_indices = True
    return out


def components(faces: np.ndarray, n_vertices: int) -> tuple[int, np.ndarray]:
    """(count, label per face) of the pieces connected through shared vertices."""
    if len(faces) == 0:
        return 0, np.zeros(0, dtype=np.int64)
    n, label = connected_components(adjacency(faces, n_vertices), directed=False)
    used, face_label = np.unique(label[faces[:, 0]], return_inverse=True)
    return len(used), face_label.reshape(-1)


def compact(vertices: np.ndarray, faces: np.ndarray, keep_faces: np.ndarray | None = None
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Keep the selected faces and the vertices they use: (vertices, faces, old index of each kept vertex)."""
    f = faces if keep_faces is None else faces[keep_faces]
    mask = np.zeros(len(vertices), dtype=bool)
    mask[f] = True
    used = np.flatnonzero(mask)
    remap = np.empty(len(vertices), dtype=np.int64)          # new index of each used vertex (others unread)
    remap[used] = np.arange(len(used))
    return vertices[used], remap[f], used


def fill_pinholes(vertices: np.ndarray, faces: np.ndarray, max_edges: int = 12, edges: tuple | None = None
                  ) -> np.ndarray:
    """Faces plus fans closing every boundary loop of at most `max_edges` edges (the winding must be consistent:
    run after `orient`). Loops through a vertex with more than one boundary edge out are left open.
    `edges`: `edge_faces` of these faces, if known."""
    if len(faces) == 0:
        return faces
    nv = len(vertices)
    order, ks, count = edge_faces(faces, nv) if edges is None else edges
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


def reversed_edges(edges: tuple, flipped: np.ndarray) -> tuple:
    """`edge_faces` of the same faces after reversing (a, b, c) -> (c, b, a) those in `flipped` (F,) bool: the
    edges are the same, only the half-edge ids within each reversed face move (ab: 0 -> 1, bc: 1 -> 0)."""
    order, ks, count = edges
    f, k = order // 3, order % 3
    return np.where(flipped[f], 3 * f + np.array([1, 0, 2])[k], order), ks, count


def clean_surface(vertices: np.ndarray, faces: np.ndarray, min_area: float = 0.0,
                  observed: np.ndarray | None = None, sensors: np.ndarray | None = None,
                  pinhole_edges: int = 12, workers: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Fragments (and faces of zero area) -> orientation -> pinholes, sharing normals, components and edges
    between the steps.

    min_area: connected pieces (through manifold edges) with less area are dropped.
    observed: (V,) bool, vertices near an input point; sensors: (S, 3) sensor positions. A face with all three
    vertices observed, not seen edge-on (|cos| > 0.1), is a seed of `orient` and faces its nearest sensor; pieces
    without seeds face away from their own centre (outwards from what they enclose), ties broken upwards.
    pinhole_edges: boundary loops of at most this many edges are closed (< 3: none).
    workers: threads for the per-face steps (the seeds are found while the pieces are labelled).

    Everything runs on all faces and the fragments go at the end, in one compaction. A face of zero area joins
    the face graph as a leaf (through one neighbour of non-zero area), so it never bridges two pieces (a speck
    hanging on a large piece by a collapsed face is still a speck); it goes, and the pinhole step closes the
    hole it leaves, consistently wound.
    """
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    if len(f) == 0:
        return np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64)
    v32 = v.astype(np.float32)                                 # normals and centres: float32 is plenty, and faster
    edges, (fn, area) = run_all(lambda: edge_faces(f, len(v)), lambda: face_normals(v32, f, workers),
                                workers=workers)
    fa, fb, _ = _manifold_pairs(f, len(v), edges)
    flat_a, flat_b = area[fa] > 0, area[fb] > 0
    leaf = flat_a ^ flat_b                                     # a zero-area face and a neighbour with area
    z = np.where(flat_a, fb, fa)[leaf]
    _, once = np.unique(z, return_index=True)                  # one neighbour per zero-area face
    joined = np.flatnonzero(flat_a & flat_b)
    joined = np.r_[joined, np.flatnonzero(leaf)[once]]
    fa, fb = fa[joined], fb[joined]

    def centre(sel: np.ndarray) -> np.ndarray:
        return (v32[f[sel, 0]] + v32[f[sel, 1]] + v32[f[sel, 2]]) / np.float32(3.0)

    def unit(x: np.ndarray) -> np.ndarray:
        return x / np.maximum(np.sqrt(np.einsum("ij,ij->i", x, x)), 1e-9)[:, None]

    def seeds() -> tuple[np.ndarray, np.ndarray]:
        """(prior (F, 3), seed (F,)): observed faces look at their nearest sensor."""
        prior = np.zeros((len(f), 3), dtype=np.float32)
        seed = np.zeros(len(f), dtype=bool)
        if observed is None or sensors is None or not len(sensors):
            return prior, seed
        obs = np.asarray(observed, dtype=bool)
        s = np.asarray(sensors, dtype=np.float32).reshape(-1, 3)

        def part(lo: int, hi: int) -> None:
            seen = lo + np.flatnonzero(obs[f[lo:hi]].all(1) & (area[lo:hi] > 0))
            c = centre(seen)
            best = np.zeros(len(c), dtype=np.int64)
            if len(s) > 1:
                dist = np.full(len(c), np.inf, dtype=np.float32)
                for k in range(len(s)):
                    dk = ((c - s[k]) ** 2).sum(1)
                    best[dk < dist] = k
                    dist = np.minimum(dist, dk)
            look = unit(s[best] - c)
            prior[seen] = look
            seed[seen] = np.abs(np.einsum("ij,ij->i", fn[seen], look)) > 0.1

        map_slices(part, len(f), workers)
        return prior, seed

    def pieces() -> tuple[csr_matrix, int, np.ndarray]:
        graph = face_graph(len(f), fa, fb)
        return (graph, *face_pieces(graph))

    (graph, n_comp, label), (prior, seed) = run_all(pieces, seeds, workers=workers)
    keep = (np.bincount(label, weights=area, minlength=n_comp)[label] >= min_area) & (area > 0)
    # pieces without seeds (only they use it): away from the piece's centre, ties broken upwards
    rest = np.flatnonzero(~(np.bincount(label, weights=seed, minlength=n_comp) > 0)[label] & keep)
    if len(rest):
        c = centre(rest)
        count = np.maximum(np.bincount(label[rest], minlength=n_comp), 1)[:, None]
        mid = np.stack([np.bincount(label[rest], weights=c[:, a], minlength=n_comp) for a in range(3)], 1) / count
        prior[rest] = unit(c - mid[label[rest]])
        prior[rest, 2] += 1e-3
    def rim() -> tuple[tuple, np.ndarray]:
        """The boundary half-edges of the kept faces (all `fill_pinholes` reads), and which vertices stay."""
        order, ks, _ = edges
        he = keep[order // 3]
        order, ks = order[he], ks[he]
        one = run_lengths(ks) == 1
        kept_vertex = np.zeros(len(v), dtype=bool)
        kept_vertex[f[keep]] = True
        return (order[one], ks[one], np.ones(int(one.sum()), dtype=np.int64)), kept_vertex

    jobs = [lambda: orient(v, f, prior, seed, normals=fn, pieces=(n_comp, label), graph=graph, workers=workers)]
    out, *more = run_all(*jobs, *([rim] if pinhole_edges >= 3 else []), workers=workers)
    if more:                                                   # the holes of what stays
        (boundary, kept_vertex), = more
        out = fill_pinholes(v, out, pinhole_edges, reversed_edges(boundary, out[:, 0] != f[:, 0]))
        keep = np.r_[keep, kept_vertex[out[len(f):]].all(1)]  # a fan stays when its rim's faces stay
    if keep.all():
        return v, out
    v, out, _ = compact(v, out, keep)
    return v, out
