"""The drive merge's weld fills its arrays one piece at a time (the merge is a drive's memory peak): its result must
be the plain concatenate-and-weld's, bit for bit, on pieces with shared seam vertices and faces that collapse."""
from __future__ import annotations

import numpy as np

from hgca_core.tiling.merge import WELD, Piece, weld


def naive_weld(pieces: list[Piece]) -> Piece:
    """The reference: concatenate everything, map seam duplicates to their first vertex, drop degenerate faces."""
    pieces = [p for p in pieces if len(p.faces)]
    offsets = np.cumsum([0] + [len(p.vertices) for p in pieces])
    v = np.concatenate([p.vertices for p in pieces])
    f = np.concatenate([p.faces + o for p, o in zip(pieces, offsets[:-1])])
    d = np.concatenate([p.observed_distance for p in pieces])
    seam = np.concatenate([p.seam for p in pieces])
    target = np.arange(len(v))
    for i in np.flatnonzero(seam):
        same = [j for j in np.flatnonzero(seam) if np.all(np.round((v[j] - v[seam].min(0)) / WELD)
                                                       == np.round((v[i] - v[seam].min(0)) / WELD))]
        target[i] = same[0]
        d[same[0]] = min(d[same[0]], d[i])
    f = target[f]
    f = f[(f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])]
    used = np.zeros(len(v), bool)
    used[f.ravel()] = True
    return Piece(v[used], (np.cumsum(used) - 1)[f], d[used], seam[used])


def pieces(seed: int) -> list[Piece]:
    rng = np.random.default_rng(seed)
    out = []
    for k in range(3):
        v = rng.uniform(0, 4, (30, 3)).round(1) + [4.0 * k, 0, 0]
        v[:6] = [[4.0 * (k + y // 3), y % 3, 0.5] for y in range(6)]     # seam lines shared with both neighbours
        f = rng.integers(0, 30, (50, 3))
        f[0] = [0, 1, 0] if k == 1 else f[0]                             # a face that is degenerate already
        seam = np.zeros(30, bool)
        seam[:6] = True
        out.append(Piece(v, f.astype(np.int64), rng.uniform(0, 1, 30).astype(np.float32), seam))
    out.insert(1, Piece.empty())
    return out


def test_weld_equals_the_plain_concatenation_and_lets_go_of_the_pieces():
    for seed in range(4):
        given = pieces(seed)
        want = naive_weld(pieces(seed))
        got = weld(given)
        assert given == []                                               # the pieces are let go of
        assert np.array_equal(got.vertices, want.vertices) and got.vertices.dtype == want.vertices.dtype
        assert np.array_equal(got.faces, want.faces) and got.faces.dtype == np.int64
        assert np.array_equal(got.observed_distance, want.observed_distance)
        assert np.array_equal(got.seam, want.seam)
        assert len(got.vertices) < sum(len(p.vertices) for p in pieces(seed))   # seam vertices were merged
