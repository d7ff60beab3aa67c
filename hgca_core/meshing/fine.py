"""The fine stage's mesh: one open surface at the zero level of the decoded unsigned distance.

Unsigned distance decoded on a 5 cm grid (`hgca_core.meshing.field.udf_grid`) -> one open surface at its zero
level (`hgca_core.meshing.udf_surface`) -> cleanup (`hgca_core.meshing.mesh_clean`): floating fragments, consistent
orientation towards the sensors, pinholes -> near-horizontal surfaces faired between the input points
(`hgca_core.meshing.fairing`).
"""
from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import torch
import trimesh

from hgca_core.geometry.keys import pack
from hgca_core.meshing.field import udf_grid

if TYPE_CHECKING:
    from hgca_core.geometry.nearest import PointIndex

# Defaults of the fine stage's cleanup (see `udf_mesh`)
MIN_AREA = 0.05          # m^2: connected pieces smaller than a 22 x 22 cm square are specks, not objects
PINHOLE_EDGES = 12       # boundary loops of at most this many edges (~0.5 m around at 5 cm) are closed


def udf_mesh(decoder: object, cells: np.ndarray | torch.Tensor, latents: torch.Tensor | None = None,
             lower_corner: float | np.ndarray | None = None, voxel: float = 0.1, res: float = 0.05,
             chunk: int = 1 << 15, min_area: float = MIN_AREA, pinhole_edges: int = PINHOLE_EDGES,
             points: np.ndarray | None = None, sensors: np.ndarray | None = None, fair: bool = True,
             timings: dict | None = None, tree: PointIndex | None = None, workers: int | None = None
             ) -> trimesh.Trimesh:
    """One open surface at the zero level of the unsigned distance around occupied 10 cm cells (5 cm grid).

    decoder: an autoencoder (anything with `.field(cells, latents)`) or a function of (Q, 3) cell-frame points
      (metres) -> (Q,) unsigned distances (metres), clamped at `voxel`.
    cells: (N, 3) int occupied cells; latents: (N, K) their codes (ignored by a plain function).
    lower_corner: where cell c's box starts, lower_corner + c * voxel, as in `meshing.voxel_mesh`; the default
      -voxel / 2 is the region frame of 10 cm cells made by rounding, so vertices come back in that frame.
    chunk: decoder queries per call (memory bound; results do not depend on it).
    min_area: connected pieces with less area (m^2) are dropped; pinhole_edges: boundary loops with at most
      this many edges are closed (0: none).
    points / sensors: input points and sensor positions (output frame): observed faces (`observed_vertices`)
      face the nearest sensor, and each connected piece follows its observed faces; pieces nobody saw face
      away from their own centre (outwards from what they enclose), or up. Without points: the latter.
    fair: near-horizontal surfaces are faired between the input points (`hgca_core.meshing.fairing`: the
      generated ground between scan rings is flattened onto what the rings say, and the decoder's local bias at
      the rings taken out); needs `points`.
    tree: a `geometry.nearest.PointIndex` of `points` when the caller has one (`pipeline.complete_local` builds
      one per completion for the fairing's anchors and the vertices' observed_distance); None: built here if needed.
    workers: threads for the numpy steps (default: torch's thread count, the decoder's).
    timings: if given, filled with the wall seconds of each step (decode, extract, clean, fair) and the CPU seconds
      (`*_cpu`, all threads of this process: on a busy machine a fairer measure of the work).
    """
    import time

    from hgca_core.meshing import mesh_clean as mc
    from hgca_core.meshing.udf_surface import dual_surface

    workers = torch.get_num_threads() if workers is None else max(1, int(workers))
    t0, c0 = time.perf_counter(), time.process_time()
    shift = np.asarray(-voxel / 2 if lower_corner is None else lower_corner, dtype=np.float64) + voxel / 2
    g, vals = udf_grid(decoder, cells, latents, voxel, res, chunk)
    t1, c1 = time.perf_counter(), time.process_time()
    surf = dual_surface(g, vals, res, voxel, workers=workers)
    v, f = surf.vertices * res + shift, surf.faces
    t2, c2 = time.perf_counter(), time.process_time()
    observed = None
    if points is not None and sensors is not None and len(points) and len(v):
        observed = observed_vertices(v, points, voxel)
    v, f = mc.clean_surface(v, f, min_area, observed, sensors, pinhole_edges, workers)
    t3, c3 = time.perf_counter(), time.process_time()
    if fair and points is not None and len(points) and len(f):
        from hgca_core.meshing.fairing import fair_ground
        from hgca_core.geometry.nearest import PointIndex

        tree = PointIndex(points) if tree is None else tree
        v = fair_ground(v, f, workers=workers, points=tree)[0]   # anchors: the ground vertices' nearest points
    if timings is not None:   # wall seconds, and CPU seconds of this process (all its threads)
        t4, c4 = time.perf_counter(), time.process_time()
        timings.update(decode=t1 - t0, extract=t2 - t1, clean=t3 - t2, fair=t4 - t3,
                       decode_cpu=c1 - c0, extract_cpu=c2 - c1, clean_cpu=c3 - c2, fair_cpu=c4 - c3)
    return trimesh.Trimesh(vertices=v, faces=f, process=False)


def observed_vertices(vertices: np.ndarray, points: np.ndarray, voxel: float) -> np.ndarray:
    """(V,) bool: the vertex lies in a `voxel` cell (by rounding, like the 10 cm input cells) that holds an input
    point, i.e. within ~0.9 voxel of one; a search among the points' sorted cell keys, several times cheaper than a
    nearest-neighbour query."""
    if len(points) == 0 or len(vertices) == 0:
        return np.zeros(len(vertices), dtype=bool)
    keys = np.unique(pack(np.round(np.asarray(points, dtype=np.float64) / voxel).astype(np.int64)))
    q = pack(np.round(np.asarray(vertices, dtype=np.float64) / voxel).astype(np.int64))
    return keys[np.minimum(np.searchsorted(keys, q), len(keys) - 1)] == q
