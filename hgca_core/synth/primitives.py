"""A mesh builder for procedural scenes: primitives are appended as raw arrays and concatenated once.

Building thousands of small `trimesh` objects and concatenating them is slow; here every primitive is a
few numpy ops on a template. The builder also records *solids* (convex polytopes and ellipsoids) so the
ground truth can drop surface that lies strictly inside another object (the ground under a house, the
wall of a bay window inside the facade): what a complete scan of the scene could ever see.
"""
from __future__ import annotations

import contextlib
from dataclasses import dataclass, field
from typing import Iterator

import numpy as np
import trimesh

# box corners in (x, y, z) bit order: corner i has x = i & 1, y = i >> 1 & 1, z = i >> 2 & 1
_CORNERS = np.array([[i & 1, (i >> 1) & 1, (i >> 2) & 1] for i in range(8)], dtype=np.float64)
# two outward-facing triangles per side: -x, +x, -y, +y, -z, +z
_BOX_SIDES = {
    "-x": [[0, 4, 6], [0, 6, 2]],
    "+x": [[1, 3, 7], [1, 7, 5]],
    "-y": [[0, 1, 5], [0, 5, 4]],
    "+y": [[2, 6, 7], [2, 7, 3]],
    "-z": [[0, 2, 3], [0, 3, 1]],
    "+z": [[4, 5, 7], [4, 7, 6]],
}
MAX_PLANES = 16
SUPPORT_DEPTH = 0.1  # a solid without a bottom face extends this far into what it stands on
_PAD_PLANE = np.array([0.0, 0.0, 0.0, -1.0])  # n.p + d = -1 < 0 everywhere: a no-op half-space
DEFAULT_MATERIAL = 255  # "the default of the face's label" (resolved by synth.materials)


def _rot_z(yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


@dataclass
class Frame:
    """A placement in the scene: a rotation (about z, optionally tilted onto sloped ground), then a translation."""

    rotation: np.ndarray = field(default_factory=lambda: np.eye(3))
    offset: np.ndarray = field(default_factory=lambda: np.zeros(3))

    @property
    def yaw(self) -> float:
        return float(np.arctan2(self.rotation[1, 0], self.rotation[0, 0]))

    def apply(self, p: np.ndarray) -> np.ndarray:
        return np.asarray(p, dtype=np.float64) @ self.rotation.T + self.offset

    def then(self, inner: "Frame") -> "Frame":
        """The frame `inner` expressed in this frame's parent (self o inner)."""
        return Frame(self.rotation @ inner.rotation, self.apply(inner.offset))


class MeshBuilder:
    """Accumulates triangles with a semantic label per face and the solids they bound."""

    def __init__(self) -> None:
        self._verts: list[np.ndarray] = []
        self._faces: list[np.ndarray] = []
        self._labels: list[np.ndarray] = []
        self._materials: list[np.ndarray] = []
        self._count = 0
        self._planes: list[np.ndarray] = []      # (MAX_PLANES, 4) per convex solid, world n.p + d <= 0 inside
        self._bounds: list[np.ndarray] = []      # (2, 3) lo/hi corner per convex solid
        self._ellipsoids: list[np.ndarray] = []  # (cx, cy, cz, r_xy, r_z, yaw, subdivisions) icosphere blobs
        self.frame = Frame()
        self._material: int | None = None

    @contextlib.contextmanager
    def placed(self, yaw: float, offset, tilt: np.ndarray | None = None) -> Iterator[None]:
        """Build an object in its own frame (rotated by yaw, then by the 3x3 `tilt` that sets it on sloped
        ground, then moved to offset in the current frame)."""
        outer = self.frame
        rot = _rot_z(yaw) if tilt is None else np.asarray(tilt, dtype=np.float64) @ _rot_z(yaw)
        self.frame = outer.then(Frame(rot, np.asarray(offset, dtype=np.float64).reshape(3)))
        try:
            yield
        finally:
            self.frame = outer

    @contextlib.contextmanager
    def material(self, material: int) -> Iterator[None]:
        """Faces added inside get this LiDAR material (see `synth.materials`); outside, their label's default."""
        outer = self._material
        self._material = int(material)
        try:
            yield
        finally:
            self._material = outer

    # ------------------------------------------------------------------ raw
    def add(self, vertices: np.ndarray, faces: np.ndarray, label: int) -> None:
        """Append local-frame triangles, transformed by the current frame."""
        v = self.frame.apply(vertices)
        f = np.asarray(faces, dtype=np.int64) + self._count
        self._verts.append(v)
        self._faces.append(f)
        self._labels.append(np.full(len(f), label, dtype=np.uint8))
        self._materials.append(np.full(len(f), DEFAULT_MATERIAL if self._material is None else self._material,
                                       dtype=np.uint8))
        self._count += len(v)

    def add_solid_planes(self, local_vertices: np.ndarray, faces: np.ndarray) -> None:
        """Record a convex solid by the planes of its (closed, outward) faces."""
        v = self.frame.apply(local_vertices)
        tri = v[np.asarray(faces)]
        n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        norm = np.linalg.norm(n, axis=1)
        ok = norm > 1e-12
        n = n[ok] / norm[ok, None]
        d = -np.einsum("ij,ij->i", n, tri[ok, 0])
        planes = np.unique(np.round(np.c_[n, d], 9), axis=0)
        if len(planes) > MAX_PLANES:
            return  # too many facets to be worth a solid test; its interior faces stay
        pad = np.tile(_PAD_PLANE, (MAX_PLANES - len(planes), 1))
        self._planes.append(np.vstack([planes, pad]))
        self._bounds.append(np.stack([v.min(axis=0), v.max(axis=0)]))

    # ------------------------------------------------------------ primitives
    def hexahedron(self, corners: np.ndarray, label: int, skip: tuple[str, ...] = ("-z",), solid: bool = True) -> None:
        """Eight corners in box bit order (a box, or a tapered box like a car cabin); `skip` omits hidden sides."""
        faces = np.array([t for side, tris in _BOX_SIDES.items() if side not in skip for t in tris])
        self.add(corners, faces, label)
        if solid:
            allf = np.array([t for tris in _BOX_SIDES.values() for t in tris])
            c = np.array(corners, dtype=np.float64)
            if "-z" in skip:  # it stands on something: the surface under it is hidden, so reach below it
                c[:4, 2] -= SUPPORT_DEPTH
            self.add_solid_planes(c, allf)

    def box(self, lo, hi, label: int, skip: tuple[str, ...] = ("-z",), solid: bool = True) -> None:
        """Axis-aligned (in the current frame) box from corner lo to corner hi."""
        lo, hi = np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)
        self.hexahedron(lo + _CORNERS * (hi - lo), label, skip, solid)

    def gable(self, lo, hi, ridge_height: float, label: int, ridge_axis: int = 0, solid: bool = True) -> None:
        """Gabled roof over the rectangle lo..hi (lo[2] = eave height), ridge along x (0) or y (1), open below."""
        x0, y0, z0 = lo
        x1, y1 = hi[0], hi[1]
        zr = z0 + ridge_height
        if ridge_axis == 0:
            ym = (y0 + y1) / 2
            v = np.array([[x0, y0, z0], [x1, y0, z0], [x1, y1, z0], [x0, y1, z0], [x0, ym, zr], [x1, ym, zr]])
        else:
            xm = (x0 + x1) / 2
            # the x-ridge layout with x and y swapped (a mirror, hence the flipped winding below)
            v = np.array([[x0, y0, z0], [x0, y1, z0], [x1, y1, z0], [x1, y0, z0], [xm, y0, zr], [xm, y1, zr]])
        # slopes (2 quads) and gable ends (2 triangles); bottom open so overhangs look like eaves
        faces = np.array([[0, 1, 5], [0, 5, 4], [2, 3, 4], [2, 4, 5], [0, 4, 3], [1, 2, 5]])
        if ridge_axis == 1:
            faces = faces[:, ::-1]
        self.add(v, faces, label)
        if solid:
            bottom = np.array([[0, 3, 2], [0, 2, 1]])
            closed = np.vstack([faces, bottom if ridge_axis == 0 else bottom[:, ::-1]])
            self.add_solid_planes(v, closed)

    def cylinder(self, p0, p1, radius: float, label: int, segments: int = 10, solid: bool = True,
                 radius_top: float | None = None) -> None:
        """Closed cylinder (or cone frustum with `radius_top`) from p0 to p1, any axis."""
        p0, p1 = np.asarray(p0, dtype=np.float64), np.asarray(p1, dtype=np.float64)
        axis = p1 - p0
        length = np.linalg.norm(axis)
        a = axis / length
        helper = np.array([1.0, 0.0, 0.0]) if abs(a[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
        u = np.cross(a, helper)
        u /= np.linalg.norm(u)
        w = np.cross(a, u)
        ang = np.linspace(0, 2 * np.pi, segments, endpoint=False)
        ring = np.cos(ang)[:, None] * u + np.sin(ang)[:, None] * w
        top = radius if radius_top is None else max(radius_top, 1e-3)
        v = np.vstack([p0 + radius * ring, p1 + top * ring, p0, p1])
        i = np.arange(segments)
        j = (i + 1) % segments
        c0, c1 = 2 * segments, 2 * segments + 1
        side = np.vstack([np.c_[i, j, j + segments], np.c_[i, j + segments, i + segments]])
        caps = np.vstack([np.c_[np.full(segments, c0), j, i], np.c_[np.full(segments, c1), i + segments, j + segments]])
        faces = np.vstack([side, caps])
        self.add(v, faces, label)
        if solid:
            self.add_solid_planes(v, faces)

    def ellipsoid(self, center, radius_xy: float, radius_z: float, label: int, subdivisions: int = 1) -> None:
        """Icosphere blob (tree canopy), also recorded as a solid (the exact convex polyhedron)."""
        ico = _icosphere(subdivisions)
        scale = np.array([radius_xy, radius_xy, radius_z])
        self.add(ico.vertices * scale + np.asarray(center, dtype=np.float64), ico.faces, label)
        c = self.frame.apply(np.asarray(center, dtype=np.float64)[None])[0]
        self._ellipsoids.append(np.array([*c, radius_xy, radius_z, self.frame.yaw, subdivisions]))

    # ---------------------------------------------------------------- output
    def quad(self, corners, label: int) -> None:
        """A double-sided rectangle (a glass pane) from 4 corners in order; bounds no solid."""
        self.add(np.asarray(corners, dtype=np.float64), np.array([[0, 1, 2], [0, 2, 3]]), label)

    def build(self) -> tuple[trimesh.Trimesh, np.ndarray, "Solids"]:
        """(mesh, face labels, solids); `materials` holds the per-face LiDAR materials."""
        mesh = trimesh.Trimesh(np.vstack(self._verts), np.vstack(self._faces), process=False)
        solids = Solids(np.array(self._planes).reshape(-1, MAX_PLANES, 4),
                        np.array(self._bounds).reshape(-1, 2, 3),
                        np.array(self._ellipsoids).reshape(-1, 7))
        self.materials = np.concatenate(self._materials)
        return mesh, np.concatenate(self._labels), solids


_ICO: dict[int, trimesh.Trimesh] = {}


def _icosphere(subdivisions: int) -> trimesh.Trimesh:
    if subdivisions not in _ICO:
        _ICO[subdivisions] = trimesh.creation.icosphere(subdivisions=subdivisions)
    return _ICO[subdivisions]


def _ico_planes(subdivisions: int) -> tuple[np.ndarray, np.ndarray]:
    """Face normals and plane offsets of the unit icosphere (inside: n.p < d)."""
    ico = _icosphere(subdivisions)
    n = np.asarray(ico.face_normals)
    return n, np.einsum("ij,ij->i", n, ico.triangles[:, 0])


@dataclass
class Solids:
    """Convex polytopes (planes n.p + d < 0 inside, padded to MAX_PLANES; bounds lo/hi) and icosphere
    blobs (cx, cy, cz, r_xy, r_z, yaw, subdivisions), used to drop surface hidden inside other objects."""

    planes: np.ndarray
    bounds: np.ndarray
    ellipsoids: np.ndarray

    def transformed(self, matrix: np.ndarray) -> "Solids":
        """Move by a rigid transform that rotates about z only (the scene's global placement)."""
        r, t = matrix[:3, :3], matrix[:3, 3]
        n = self.planes[..., :3] @ r.T
        d = self.planes[..., 3] - np.einsum("...i,i->...", n, t)
        planes = np.concatenate([n, d[..., None]], axis=-1)
        planes[~np.any(self.planes[..., :3] != 0, axis=-1)] = _PAD_PLANE
        corners = self.bounds[:, None, 0, :] + _CORNERS[None] * (self.bounds[:, 1] - self.bounds[:, 0])[:, None, :]
        moved = corners @ r.T + t
        bounds = np.stack([moved.min(axis=1), moved.max(axis=1)], axis=1)
        ell = self.ellipsoids.copy()
        if len(ell):
            ell[:, :3] = self.ellipsoids[:, :3] @ r.T + t
            ell[:, 5] += np.arctan2(r[1, 0], r[0, 0])
        return Solids(planes, bounds, ell)

    def contains(self, points: np.ndarray, eps: float = 0.01, cell: float = 1.0) -> np.ndarray:
        """Which points lie deeper than `eps` inside any solid (boolean mask)."""
        return self.which(points, eps, cell) >= 0

    def which(self, points: np.ndarray, eps: float = 0.01, cell: float = 1.0) -> np.ndarray:
        """Index of a solid each point lies deeper than `eps` inside (polytopes first, then ellipsoids), or -1.

        Points are sorted into 1 m buckets in x/y once; a solid then tests only the contiguous runs of
        the buckets its bounds cover, instead of every point against every solid.
        """
        pts = np.asarray(points)
        out = np.full(len(pts), -1, dtype=np.int64)
        if len(pts) == 0:
            return out
        origin = pts[:, :2].min(axis=0).astype(np.float64)
        b = np.floor((pts[:, :2] - origin) / cell).astype(np.int64)
        nx, ny = int(b[:, 0].max()) + 1, int(b[:, 1].max()) + 1
        key = b[:, 0] * ny + b[:, 1]
        order = np.argsort(key, kind="stable")
        skey, sp = key[order], pts[order]
        hidden = np.full(len(pts), -1, dtype=np.int64)

        def runs(lo_xy: np.ndarray, hi_xy: np.ndarray):
            i0 = np.floor((lo_xy - origin) / cell).astype(np.int64)
            i1 = np.floor((hi_xy - origin) / cell).astype(np.int64)
            if i1[0] < 0 or i1[1] < 0 or i0[0] >= nx or i0[1] >= ny:
                return
            i0, i1 = np.maximum(i0, 0), np.minimum(i1, [nx - 1, ny - 1])
            rows = np.arange(i0[0], i1[0] + 1)
            starts = np.searchsorted(skey, rows * ny + i0[1], side="left")
            stops = np.searchsorted(skey, rows * ny + i1[1], side="right")
            for a, z in zip(starts, stops):
                if z > a:
                    yield a, z

        for k, (pl, (lo, hi)) in enumerate(zip(self.planes, self.bounds)):
            pl = pl[np.any(pl[:, :3] != 0, axis=1)].astype(pts.dtype)
            lo32, hi32 = lo.astype(pts.dtype), hi.astype(pts.dtype)
            for a, z in runs(lo[:2], hi[:2]):
                p = sp[a:z]
                sel = np.flatnonzero(np.all((p > lo32) & (p < hi32), axis=1))
                for n in pl:                                   # keep the points inside every half-space
                    if len(sel) == 0:
                        break
                    sel = sel[p[sel] @ n[:3] + n[3] < -eps]
                hidden[a + sel] = k
        for k, (cx, cy, cz, rxy, rz, yaw, sub) in enumerate(self.ellipsoids, start=len(self.planes)):
            c = np.array([cx, cy])
            normals, offsets = _ico_planes(int(sub))
            rot = np.array([[np.cos(yaw), np.sin(yaw), 0.0], [-np.sin(yaw), np.cos(yaw), 0.0], [0.0, 0.0, 1.0]])
            margin = eps / max(rxy, rz)
            inner = offsets.min() - margin                      # inside this sphere: inside the blob
            for a, z in runs(c - rxy, c + rxy):
                p = sp[a:z]
                near = np.flatnonzero(np.abs(p[:, 2] - cz) < rz)
                q = ((p[near].astype(np.float64) - [cx, cy, cz]) @ rot.T) / [rxy, rxy, rz]  # unit-blob frame
                r2 = np.einsum("ij,ij->i", q, q)
                inside = r2 < inner * inner
                band = np.flatnonzero(~inside & (r2 < 1.0))
                if len(band):
                    inside[band] = np.all(q[band] @ normals.T < offsets - margin, axis=1)
                hidden[a + near[inside]] = k
        out[order] = hidden
        return out
