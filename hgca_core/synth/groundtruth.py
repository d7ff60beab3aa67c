"""Ground truth of a region: dense surface samples, occupancy, unsigned distances and LiDAR visibility.

Everything here works in the region frame. Surface is sampled only from faces near the region (large
faces are first split so cropping wastes little), and samples hidden inside solids (the ground under a
house, a wheel inside a car body) or below the ground (a wall's foot on a slope) are dropped: the ground
truth is what a complete scan could see.
"""
from __future__ import annotations

import numpy as np
import trimesh

from hgca_core.geometry.nearest import PointIndex
from hgca_core.geometry.raycast import Sensor
from hgca_core.geometry.region import BELOW_GROUND, Region
from hgca_core.geometry.voxel import COARSE, FINE, cell_centers, downsample, point_cells, voxelize
from hgca_core.synth.primitives import Solids
from hgca_core.synth.terrain import Terrain

MAX_EDGE = 1.5  # metres: faces near the region are split to this size before sampling


class RegionSurface:
    """The scene's surface near a region: split triangles (region frame) with labels, and dense samples."""

    def __init__(self, mesh: trimesh.Trimesh, labels: np.ndarray, solids: Solids, region: Region,
                 rng: np.random.Generator, density: float, pad: float = 0.4, terrain: Terrain | None = None,
                 ground_faces: int = 0) -> None:
        self.region = region
        lo, hi = -pad, region.size + pad
        local = region.to_local(mesh.vertices)
        faces = np.asarray(mesh.faces)
        keep = _tri_box_overlap(local[faces], lo, hi)
        v, f, idx = trimesh.remesh.subdivide_to_size(local, faces[keep], MAX_EDGE, max_iter=12, return_index=True)
        tri = v[f]
        near = _tri_box_overlap(tri, lo, hi)
        tri, lab = tri[near], labels[keep][idx[near]]
        on_ground = np.flatnonzero(keep)[idx[near]] < ground_faces   # the first `ground_faces` faces are the terrain
        self.solids = solids.transformed(region.local_matrix())
        # a triangle whose corners lie inside one convex solid is hidden whole: skip it before sampling
        inside = self.solids.which(tri.reshape(-1, 3)).reshape(-1, 3)
        buried = (inside[:, 0] >= 0) & (inside[:, 0] == inside[:, 1]) & (inside[:, 0] == inside[:, 2])
        self.triangles, self.labels, on_ground = tri[~buried], lab[~buried], on_ground[~buried]
        # dense samples; keep those not hidden inside a solid and not under the ground
        pts, face = sample_triangles(self.triangles, density, rng)
        inside = np.all((pts >= lo) & (pts < hi), axis=1)
        pts, face = pts[inside], face[inside]
        hidden = self.solids.contains(pts)
        hidden[~on_ground[face]] |= self._below_ground(pts[~on_ground[face]], terrain)
        self.points, self.face = pts[~hidden], face[~hidden]
        self.in_region = region.contains_local(self.points)
        self._tree: PointIndex | None = None
        self._tree_face: np.ndarray | None = None

    def _below_ground(self, pts: np.ndarray, terrain: Terrain | None, eps: float = 0.02) -> np.ndarray:
        """Samples more than `eps` under the ground (the terrain, or a flat ground at the region's ground_z)."""
        if terrain is None:
            return pts[:, 2] < BELOW_GROUND - eps
        # only samples lower than the highest ground in the region can be under it
        g = np.stack(np.meshgrid(*(np.arange(-1.0, s + 1.5, 1.0) for s in self.region.size[:2]), indexing="ij"), -1)
        world_xy = self.region.to_world(np.c_[g.reshape(-1, 2), np.zeros(g.size // 2)])[:, :2]
        z_top = float(terrain.height(world_xy).max()) - (self.region.center[2] - self.region.size[2] / 2) + 0.3
        out = np.zeros(len(pts), dtype=bool)
        low = np.flatnonzero(pts[:, 2] < z_top)
        world = self.region.to_world(pts[low])
        out[low] = world[:, 2] < terrain.height(world[:, :2]) - eps
        return out

    def occupancy(self) -> tuple[np.ndarray, np.ndarray]:
        """(10 cm cells, 20 cm cells) of the surface inside the region, by the project's voxeliser."""
        occ10 = voxelize(self.points[self.in_region], FINE, self.region.size)
        return occ10.astype(np.int32), downsample(occ10).astype(np.int32)

    def distance(self, query: np.ndarray, k: int = 4, tree_points: int = 250_000) -> np.ndarray:
        """Unsigned distance from query points to the visible surface.

        A k-d tree over a subset of the samples proposes candidate triangles (those of the k nearest
        samples); the answer is the exact point-triangle distance to the nearest candidate, so it does not
        depend on the sample spacing.
        """
        if self._tree is None:
            step = max(1, len(self.points) // tree_points)
            self._tree = PointIndex(self.points[::step])
            self._tree_face = self.face[::step]
        q = np.asarray(query, dtype=np.float64)
        cand = self._tree_face[self._tree.k_nearest(q, k)]
        best = np.full(len(q), np.inf)
        for j in range(k):
            d = point_triangle_distance(q, self.triangles[cand[:, j]])
            best = np.minimum(best, d)
        return best


def _tri_box_overlap(tri: np.ndarray, lo, hi) -> np.ndarray:
    """Triangles whose bounding box meets the box [lo, hi] (conservative)."""
    return np.all((tri.max(axis=1) >= lo) & (tri.min(axis=1) <= hi), axis=1)


def sample_triangles(tri: np.ndarray, density: float, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Uniform random surface samples, `density` per square metre on average; returns (points, face index)."""
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    area = 0.5 * np.linalg.norm(np.cross(e1, e2), axis=1)
    counts = rng.poisson(area * density)
    face = np.repeat(np.arange(len(tri), dtype=np.int32), counts)
    u, v = rng.random((2, len(face)), dtype=np.float32)
    flip = u + v > 1
    u[flip], v[flip] = 1 - u[flip], 1 - v[flip]
    pts = tri[:, 0].astype(np.float32)[face]
    pts += u[:, None] * e1.astype(np.float32)[face]
    pts += v[:, None] * e2.astype(np.float32)[face]
    return pts, face


def point_triangle_distance(p: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """Exact Euclidean distance from each point to its triangle (Ericson, Real-Time Collision Detection 5.1.5)."""
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    ab, ac, ap = b - a, c - a, p - a
    dot = lambda x, y: np.einsum("ij,ij->i", x, y)  # noqa: E731
    d1, d2 = dot(ab, ap), dot(ac, ap)
    bp = p - b
    d3, d4 = dot(ab, bp), dot(ac, bp)
    cp = p - c
    d5, d6 = dot(ab, cp), dot(ac, cp)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        denom = va + vb + vc
        v = vb / denom
        w = vc / denom
        closest = a + v[:, None] * ab + w[:, None] * ac                    # interior
        # edges (checked so the last assignment is the right Voronoi region)
        t_bc = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        m = (va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0)
        closest[m] = (b + t_bc[:, None] * (c - b))[m]
        t_ac = d2 / (d2 - d6)
        m = (vb <= 0) & (d2 >= 0) & (d6 <= 0)
        closest[m] = (a + t_ac[:, None] * ac)[m]
        t_ab = d1 / (d1 - d3)
        m = (vc <= 0) & (d1 >= 0) & (d3 <= 0)
        closest[m] = (a + t_ab[:, None] * ab)[m]
    # vertices
    m = (d6 >= 0) & (d5 <= d6)
    closest[m] = c[m]
    m = (d3 >= 0) & (d4 <= d3)
    closest[m] = b[m]
    m = (d1 <= 0) & (d2 <= 0)
    closest[m] = a[m]
    bad = ~np.all(np.isfinite(closest), axis=1)  # degenerate triangles: nearest vertex
    if np.any(bad):
        closest[bad] = tri[bad][np.arange(bad.sum()), np.argmin(np.linalg.norm(tri[bad] - p[bad, None], axis=2), axis=1)]
    return np.linalg.norm(p - closest, axis=1)


def visible_cells(region: Region, scans: list[tuple[np.ndarray, np.ndarray]], sensor: Sensor,
                  behind: float = 0.3, extra_points: list[np.ndarray] | None = None) -> np.ndarray:
    """20 cm cells visible to the LiDAR: in front of the first return or at most `behind` metres past it.

    `scans` holds (pose sensor->region (4, 4), range image (E, A) with inf for no return) per pose. Like
    the paper's TSDF > -0.3 mask, done projectively: every cell centre is looked up in each range image
    (nearest beam) and compared with that beam's range; no return means free space up to max range. The
    cells of the returns themselves and of the 0.3 m behind them are added, so surface cells at
    silhouettes (where the nearest beam hit something else) are never missed; so are the cells of
    `extra_points` (the stored evaluation scans, after rounding).
    """
    grid = region.grid_shape(COARSE)
    idx = np.indices(grid, dtype=np.int32).reshape(3, -1).T
    centers = cell_centers(idx, COARSE).astype(np.float32)
    visible = np.zeros(len(idx), dtype=bool)
    todo = np.arange(len(idx))                       # cells no pose has seen yet: only these are looked up
    el = np.radians(np.asarray(sensor.elevations_deg, dtype=np.float64))
    el_edges = np.concatenate([[el[0] - (el[1] - el[0]) / 2], (el[1:] + el[:-1]) / 2, [el[-1] + (el[-1] - el[-2]) / 2]])
    extra = list(extra_points or [])
    for pose, rng_img in scans:
        n_az = rng_img.shape[1]
        rel = (centers[todo] - pose[:3, 3].astype(np.float32)) @ pose[:3, :3].astype(np.float32)  # sensor frame
        r = np.linalg.norm(rel, axis=1)
        row = np.searchsorted(el_edges, np.arcsin(np.clip(rel[:, 2] / np.maximum(r, 1e-9), -1, 1))) - 1
        col = np.round(np.arctan2(rel[:, 1], rel[:, 0]) * (n_az / (2 * np.pi))).astype(np.int64) % n_az
        ok = (row >= 0) & (row < len(el)) & (r <= sensor.max_range)
        depth = np.full(len(r), -np.inf, dtype=np.float32)
        depth[ok] = rng_img[row[ok], col[ok]]
        depth[ok & ~np.isfinite(depth)] = sensor.max_range
        seen = ok & (r < depth + behind)
        visible[todo[seen]] = True
        todo = todo[~seen]
        # returns inside the region, and the slab behind them
        hit = np.isfinite(rng_img)
        dirs = _directions(sensor, n_az, pose)[hit]
        rr = rng_img[hit]
        inside = region.contains_local(pose[:3, 3] + rr[:, None] * dirs)
        dirs, rr = dirs[inside], rr[inside]
        for extra_d in (0.0, 0.1, 0.2, behind):
            extra.append(pose[:3, 3] + (rr + extra_d)[:, None] * dirs)
    dense = visible.reshape(grid)
    if extra:
        pts = np.concatenate(extra)
        c = point_cells(pts, COARSE)
        c = c[np.all((c >= 0) & (c < grid), axis=1)]
        dense[c[:, 0], c[:, 1], c[:, 2]] = True
    return np.argwhere(dense).astype(np.int16)


def _directions(sensor: Sensor, n_az: int, pose: np.ndarray) -> np.ndarray:
    return sensor.with_azimuth(n_az).directions() @ pose[:3, :3].T
