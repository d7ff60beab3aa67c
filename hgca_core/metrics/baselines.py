"""The two simple baselines printed beside hGCA: the input itself (voxelised, as the paper's "input" row)
and Open3D's screened Poisson reconstruction of the input (a classical surface-completion reference)."""
from __future__ import annotations

import os
from typing import Sequence

import numpy as np
import trimesh
from hgca_core.geometry.nearest import PointIndex

from hgca_core.errors import HgcaError, InputError
from hgca_core.geometry.voxel import COARSE, voxelize
from hgca_core.meshing.voxel_mesh import voxel_mesh
from hgca_core.metrics.chamfer import as_points


class MissingDependencyError(HgcaError, ImportError):
    """An optional dependency (here Open3D, from the "eval" extra) is not importable."""


def input_baseline(points: np.ndarray, region_size: Sequence[float] | np.ndarray | None = None,
                   voxel: float = COARSE) -> tuple[np.ndarray, trimesh.Trimesh]:
    """The "input" row: the accumulated scans voxelised (20 cm by default) as the pipeline voxelises its input
    (s^0 when `region_size` is the region's), and those cells meshed as the pipeline meshes its output.

    Returns (cells (N, 3) int64, `voxel_mesh` in the region frame) so the same ReSim and IoU code scores it as
    any voxel completion.
    """
    cells = voxelize(as_points(points, "points"), voxel, region_size)
    return cells, voxel_mesh(cells, voxel)


def _open3d():
    try:
        import open3d as o3d
    except (ImportError, OSError) as exc:          # OSError: a missing system library (libusb, libGL)
        raise MissingDependencyError(
            "the Poisson baseline needs Open3D, which is in the 'eval' extra: pip install 'hgca[eval]' "
            f"(import failed: {exc})") from exc
    return o3d


def available_cores() -> int:
    """CPU cores this process may run on (the container's quota, not the host's core count)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:                          # not on Linux
        return max(1, os.cpu_count() or 1)


def orient_towards(points: np.ndarray, normals: np.ndarray, origins: np.ndarray) -> np.ndarray:
    """Flip each normal to face the nearest sensor origin: a LiDAR only sees a surface's outward side."""
    idx = PointIndex(origins).nearest(points)[1]
    flip = np.einsum("ij,ij->i", normals, origins[idx] - points) < 0
    out = np.array(normals, dtype=np.float64, copy=True)
    out[flip] *= -1
    return out


def poisson_baseline(points: np.ndarray, origins: np.ndarray, depth: int = 9, density_quantile: float = 0.1,
                     knn: int = 30, margin: float = 0.5, n_threads: int | None = None) -> trimesh.Trimesh:
    """Screened Poisson surface of the input points (region frame), trimmed to where the input supports it.

    Normals: PCA over `knn` neighbours (Open3D), oriented towards the nearest origin in `origins` (S, 3).
    Vertices whose Poisson density is below the `density_quantile` quantile are dropped (Poisson closes
    every surface, inventing sheets far from data), then the mesh is cropped to the points' bounding box
    grown by `margin` metres. Open3D is limited to `n_threads` (default: the cores this process may use)
    for the call, so it behaves on a 2-core machine; the previous limit is restored afterwards.
    """
    o3d = _open3d()
    pts = as_points(points, "points")
    orig = as_points(np.asarray(origins, dtype=np.float64).reshape(-1, 3), "origins")
    if len(pts) < 10:
        raise InputError(f"Poisson reconstruction needs at least 10 points, got {len(pts)}")
    if not 0.0 <= density_quantile < 1.0:
        raise InputError(f"density_quantile must be in [0, 1), got {density_quantile}")
    threads = max(1, min(int(n_threads or available_cores()), available_cores()))
    limit = getattr(o3d.utility, "set_max_threads", None)
    previous = o3d.utility.get_max_threads() if limit is not None else None
    try:
        if limit is not None:
            limit(threads)
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
        pcd.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(knn=int(min(knn, len(pts)))))
        pcd.normals = o3d.utility.Vector3dVector(orient_towards(pts, np.asarray(pcd.normals), orig))
        mesh, density = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(
            pcd, depth=int(depth), n_threads=threads)
    finally:
        if limit is not None:
            limit(previous)
    verts = np.asarray(mesh.vertices, dtype=np.float64)
    faces = np.asarray(mesh.triangles, dtype=np.int64).reshape(-1, 3)
    dens = np.asarray(density, dtype=np.float64)
    keep = dens >= np.quantile(dens, density_quantile) if len(dens) else np.zeros(0, bool)
    keep &= np.all((verts >= pts.min(0) - margin) & (verts <= pts.max(0) + margin), axis=1)
    out = trimesh.Trimesh(verts, faces[keep[faces].all(axis=1)], process=False)
    out.remove_unreferenced_vertices()
    return out
