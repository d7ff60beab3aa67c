"""What every shipped mesh carries, in its final frame: each vertex's distance to the input
(`observed_distances`), per-vertex normals and the observed / generated face split (`finish_mesh`).
"""
from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import trimesh

if TYPE_CHECKING:
    from hgca_core.geometry.nearest import PointIndex

OBSERVED_SPLIT = 0.15    # m: faces whose vertices are on average farther from the input are "generated"


def observed_distances(vertices: np.ndarray, points: PointIndex) -> np.ndarray:
    """(V,) float32: each vertex's distance (m) to the nearest input point, `points` being the completion's one
    index of them; what tells observed from generated surface (`finish_mesh`) and what a scene builder reads."""
    return points.distances(vertices).astype(np.float32)


def finish_mesh(mesh: trimesh.Trimesh, observed_distance: np.ndarray | None = None,
                split: float = OBSERVED_SPLIT) -> trimesh.Trimesh:
    """Add what a scene builder expects to a finished mesh (in its final frame): per-vertex normals as the
    vertex attributes `nx`, `ny`, `nz` (and trimesh's `vertex_normals`), `observed_distance` when given, and
    the face attribute `material` (uint8: 0 observed, 1 generated: the mean observed_distance of the face's
    vertices above `split` metres; all 0 without distances)."""
    from hgca_core.meshing.mesh_clean import vertex_normals

    v, f = np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int64)
    normals = vertex_normals(v, f) if len(v) else np.zeros((0, 3), np.float32)
    out = trimesh.Trimesh(vertices=v, faces=f, vertex_normals=normals if len(v) else None, process=False)
    if observed_distance is not None:
        d = np.asarray(observed_distance, dtype=np.float32)
        out.vertex_attributes["observed_distance"] = d
        material = (d[f].mean(1) > split).astype(np.uint8) if len(f) else np.zeros(0, np.uint8)
    else:
        material = np.zeros(len(f), np.uint8)
    for name, k in (("nx", 0), ("ny", 1), ("nz", 2)):
        out.vertex_attributes[name] = normals[:, k]
    out.face_attributes["material"] = material
    return out
