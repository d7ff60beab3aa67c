"""Spinning LiDAR ray casting (Embree through trimesh): the one ray caster for synthetic inputs,
ground truth visibility and the High LiDAR ReSim metric.

A sensor head is a grid of beams: fixed elevations times evenly spaced azimuths, in the sensor frame
(x forward, y left, z up). Embree only finds the first triangle per ray; the hit itself is recomputed in
float64 from that triangle's plane, so ranges are exact to float64 rather than Embree's float32.
Noise and the effects of real sensors live with the simulator (`hgca_core.synth.lidar`), not here.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh


@dataclass(frozen=True, eq=False)
class Sensor:
    """Beam elevations (degrees), azimuth steps per revolution, and the range window (metres)."""

    elevations_deg: np.ndarray
    n_azimuth: int
    max_range: float
    min_range: float = 1.0

    def directions(self) -> np.ndarray:
        """(n_elevation, n_azimuth, 3) unit rays in the sensor frame; azimuth 0 is forward (+x)."""
        el = np.radians(np.asarray(self.elevations_deg, dtype=np.float64))[:, None]
        az = (2 * np.pi / self.n_azimuth) * np.arange(self.n_azimuth)[None, :]
        return np.stack(np.broadcast_arrays(np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)), axis=-1)

    def with_azimuth(self, n_azimuth: int) -> "Sensor":
        return Sensor(self.elevations_deg, n_azimuth, self.max_range, self.min_range)


WAYMO64 = Sensor(np.linspace(-17.6, 2.4, 64), 2650, 75.0)   # the paper's input LiDAR (Waymo top sensor geometry)
EVAL128 = Sensor(np.linspace(-30.0, 30.0, 128), 2650, 75.0)  # the paper's high evaluation LiDAR (ReSim)


class Intersector:
    """A mesh with its Embree BVH, built once and reused for every scan of that mesh."""

    def __init__(self, mesh: trimesh.Trimesh) -> None:
        self.mesh = mesh
        try:
            from trimesh.ray.ray_pyembree import RayMeshIntersector
        except ImportError:  # pragma: no cover - embreex is a dependency; the slow fallback keeps cast() usable
            from trimesh.ray.ray_triangle import RayMeshIntersector
        self._rays = RayMeshIntersector(mesh)
        self._v0 = np.asarray(mesh.triangles[:, 0], dtype=np.float64) if len(mesh.faces) else np.zeros((0, 3))
        self._normals = np.asarray(mesh.face_normals, dtype=np.float64) if len(mesh.faces) else np.zeros((0, 3))

    @property
    def normals(self) -> np.ndarray:
        """Unit face normals (F, 3), float64."""
        return self._normals

    def first_hits(self, origins: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(distance along each unit ray, inf where nothing is hit; index of the triangle hit, -1 for none)."""
        n = len(origins)
        dist = np.full(n, np.inf)
        if n == 0 or len(self.mesh.faces) == 0:
            return dist, np.full(n, -1, dtype=np.int64)
        tri = np.asarray(self._rays.intersects_first(origins, directions), dtype=np.int64)
        hit = np.flatnonzero(tri >= 0)
        nrm = self._normals[tri[hit]]
        denom = np.einsum("ij,ij->i", nrm, directions[hit])
        t = np.einsum("ij,ij->i", nrm, self._v0[tri[hit]] - origins[hit]) / np.where(np.abs(denom) > 1e-12, denom, np.nan)
        ok = np.isfinite(t) & (t >= 0)
        dist[hit[ok]] = t[ok]
        tri[hit[~ok]] = -1
        return dist, tri


def make_intersector(mesh: trimesh.Trimesh | Intersector) -> Intersector:
    """Embree acceleration structure for `mesh`; pass it to `cast` to scan the same mesh many times."""
    return mesh if isinstance(mesh, Intersector) else Intersector(mesh)


def column_poses(pose: np.ndarray, pose_end: np.ndarray | None, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Per-azimuth-column rotations (n, 3, 3) and origins (n, 3): the sensor moves from `pose` to `pose_end`
    during one revolution (rolling shutter); without `pose_end` every column uses `pose`."""
    p0 = np.asarray(pose, dtype=np.float64)
    if pose_end is None:
        return np.broadcast_to(p0[:3, :3], (n, 3, 3)), np.broadcast_to(p0[:3, 3], (n, 3))
    from scipy.spatial.transform import Rotation, Slerp

    p1 = np.asarray(pose_end, dtype=np.float64)
    f = np.arange(n) / n
    rots = Slerp([0.0, 1.0], Rotation.from_matrix(np.stack([p0[:3, :3], p1[:3, :3]])))(f).as_matrix()
    return rots, p0[:3, 3] + f[:, None] * (p1[:3, 3] - p0[:3, 3])


def beam_rays(pose: np.ndarray, sensor: Sensor, pose_end: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """World ray origins and unit directions (E, A, 3) of every beam of one revolution."""
    rots, origins = column_poses(pose, pose_end, sensor.n_azimuth)
    d_world = np.einsum("aij,eaj->eai", rots, sensor.directions())
    return np.broadcast_to(origins[None], d_world.shape), d_world


def range_image(target: trimesh.Trimesh | Intersector, pose: np.ndarray, sensor: Sensor,
                pose_end: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Cast every beam once. Returns (range (E, A), inf where no return in [min, max] range;
    ray origins (E, A, 3); unit world directions (E, A, 3))."""
    inter = make_intersector(target)
    o, d_world = beam_rays(pose, sensor, pose_end)
    dist, _ = inter.first_hits(np.ascontiguousarray(o.reshape(-1, 3)), np.ascontiguousarray(d_world.reshape(-1, 3)))
    dist = dist.reshape(d_world.shape[:2])
    dist[(dist < sensor.min_range) | (dist > sensor.max_range)] = np.inf
    return dist, o, d_world


def cast(target: trimesh.Trimesh | Intersector, pose: np.ndarray, sensor: Sensor,
         pose_end: np.ndarray | None = None) -> np.ndarray:
    """Noise-free scan of `target` from `pose` (4x4 sensor -> frame of the mesh): (N, 3) hits in the mesh's
    frame. With `pose_end`, columns are cast from poses interpolated over the revolution (rolling shutter)."""
    dist, o, d = range_image(target, pose, sensor, pose_end)
    hit = np.isfinite(dist)
    return o[hit] + dist[hit][:, None] * d[hit]
