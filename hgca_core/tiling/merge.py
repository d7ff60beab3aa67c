"""One mesh per sample from a drive's tiles: each tile cut to the part it owns (the overlap midline), then the
pieces welded where they meet.

A face stays with the tile that owns its centroid (`plan.owned`), so every place of the overlap comes from
exactly one tile and nothing is doubled. Only vertices on a cut (used by a kept and by a dropped face) can
coincide with another tile's, so only those are welded (positions equal to `WELD` metres), which keeps the
weld cheap for meshes of tens of millions of faces. `observed_distance` stays per vertex (a welded vertex
keeps the smaller of its copies'). All positions are float64 world metres until the caller writes them.
"""
from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from hgca_core.geometry.region import Region
from hgca_core.tiling.plan import owned

WELD = 1e-4   # metres: tiles' meshes meet on a common grid or not at all; this only absorbs float rounding


@dataclass
class Piece:
    """Part of a mesh: float64 world vertices, int64 faces, per-vertex distance, and which vertices lie on a cut."""

    vertices: np.ndarray
    faces: np.ndarray
    observed_distance: np.ndarray
    seam: np.ndarray   # (V,) bool

    @classmethod
    def empty(cls) -> "Piece":
        return cls(np.zeros((0, 3)), np.zeros((0, 3), np.int64), np.zeros(0, np.float32), np.zeros(0, bool))


def tile_piece(sample: dict, region: Region) -> Piece:
    """A tile result's sample (region-frame mesh) as a world-frame piece, uncut."""
    v = region.to_world(np.asarray(sample["vertices"], dtype=np.float64))
    return Piece(v, np.asarray(sample["faces"], dtype=np.int64), np.asarray(sample["observed_distance"], np.float32),
                 np.zeros(len(v), bool))


def cut(piece: Piece, index: int, regions: list[Region]) -> Piece:
    """The faces of tile `index`'s piece whose centroid the tile owns, with their vertices renumbered."""
    if len(piece.faces) == 0:
        return Piece.empty()
    centroids = piece.vertices[piece.faces].mean(axis=1)
    keep = owned(centroids[:, :2], index, regions)
    used_kept = np.zeros(len(piece.vertices), bool)
    used_kept[piece.faces[keep].ravel()] = True
    used_dropped = np.zeros(len(piece.vertices), bool)
    used_dropped[piece.faces[~keep].ravel()] = True
    new_index = np.cumsum(used_kept) - 1
    return Piece(piece.vertices[used_kept], new_index[piece.faces[keep]], piece.observed_distance[used_kept],
                 (piece.seam | used_dropped)[used_kept])


def _remap(index: np.ndarray, faces: np.ndarray) -> None:
    """faces[:] = index[faces], a block at a time: a 1 km drive's faces are ~1.4 GB, and a whole-array gather
    would hold a second copy."""
    for start in range(0, len(faces), 1 << 20):
        block = faces[start:start + (1 << 20)]
        block[:] = index[block]


def weld(pieces: list[Piece]) -> Piece:
    """Concatenate pieces, merging seam vertices at the same position (to WELD metres) and dropping faces that
    the merge made degenerate. Empties `pieces` once they are concatenated, so that their memory is freed before
    the weld's own arrays grow (a drive's merge is its peak)."""
    kept = [p for p in pieces if len(p.faces)]
    pieces.clear()
    if not kept:
        return Piece.empty()
    nv, nf = sum(len(p.vertices) for p in kept), sum(len(p.faces) for p in kept)
    v, f = np.empty((nv, 3), kept[0].vertices.dtype), np.empty((nf, 3), np.int64)
    d, seam = np.empty(nv, kept[0].observed_distance.dtype), np.empty(nv, bool)
    at_v = at_f = 0
    while kept:                           # copied in, then let go of, one piece at a time
        p = kept.pop(0)
        v[at_v:at_v + len(p.vertices)] = p.vertices
        d[at_v:at_v + len(p.vertices)] = p.observed_distance
        seam[at_v:at_v + len(p.vertices)] = p.seam
        np.add(p.faces, at_v, out=f[at_f:at_f + len(p.faces)], casting="unsafe")
        at_v, at_f = at_v + len(p.vertices), at_f + len(p.faces)
        del p
    target = np.arange(len(v))
    idx = np.flatnonzero(seam)
    if len(idx):
        q = np.round((v[idx] - v[idx].min(axis=0)) / WELD).astype(np.int64)
        _, first, inverse = np.unique(q, axis=0, return_index=True, return_inverse=True)
        inverse = inverse.reshape(-1)
        rep = idx[first][inverse]                     # each seam vertex -> the first vertex at its position
        target[idx] = rep
        np.minimum.at(d, rep, d[idx])
    _remap(target, f)
    del target
    f = f[(f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])]
    used = np.zeros(len(v), bool)
    used[f.ravel()] = True
    renumber = np.cumsum(used) - 1
    _remap(renumber, f)
    return Piece(v[used], f, d[used], seam[used])


def merge_sample(tile_samples: Iterable[dict | None], regions: list[Region]) -> Piece:
    """The drive mesh of one sample: every tile's sample (None for a tile without one) cut and welded. Each
    sample is cut as it arrives, so a generator of samples (loaded one at a time from the store) never has more
    than one uncut tile in memory."""
    pieces = [cut(tile_piece(s, regions[i]), i, regions) for i, s in enumerate(tile_samples) if s is not None]
    return weld(pieces)


def write_piece(path, piece: Piece) -> str:
    """Write a world-frame piece; the writers keep georeferenced coordinates exact (float64 PLY x/y/z, an NPZ
    `offset`, a GLB node translation: `hgca_core.io.georef`)."""
    import trimesh

    from hgca_core.io import write_mesh, write_mesh_npz

    if str(path).lower().endswith(".npz"):
        return write_mesh_npz(path, piece.vertices, piece.faces, piece.observed_distance)
    mesh = trimesh.Trimesh(piece.vertices, piece.faces, process=False)
    mesh.vertex_attributes["observed_distance"] = piece.observed_distance.astype(np.float32)
    return write_mesh(path, mesh)
