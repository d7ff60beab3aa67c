"""Writers for accumulated points and completed meshes (PLY, NPZ, OBJ, GLB), all atomic.

PLY is always binary little endian with float32 xyz: compact, and what Blender, CloudCompare and
MeshLab read natively. The mesh's per-vertex `observed_distance` travels as a PLY vertex property
(and as the `_observed_distance` glTF attribute in GLB), so observed vs generated survives export.
"""
from __future__ import annotations

import os
from typing import TYPE_CHECKING, BinaryIO, Mapping

import numpy as np

from hgca_core.errors import InputError
from hgca_core.io.atomic import atomic_write

if TYPE_CHECKING:
    import trimesh

NPZ_RESERVED = ("points", "origins")  # keys of the `hgca read` layout that are not attributes


def _extension(path: str, allowed: tuple[str, ...]) -> str:
    ext = os.path.splitext(path)[1].lower()
    if ext not in allowed:
        raise InputError(f"unsupported output extension {ext or '(none)'!r}; use one of {', '.join(allowed)}", path)
    return ext


def _ply_compatible(values: np.ndarray) -> np.ndarray:
    """PLY has no 64-bit integers or booleans: pick the nearest type that holds the values exactly."""
    a = np.asarray(values)
    if a.dtype == bool:
        return a.astype(np.uint8)
    if a.dtype.kind in "iu" and a.dtype.itemsize == 8:
        info = np.iinfo(np.int32 if a.dtype.kind == "i" else np.uint32)
        if a.size == 0 or (a.min() >= info.min and a.max() <= info.max):
            return a.astype(np.int32 if a.dtype.kind == "i" else np.uint32)
        return a.astype(np.float64)
    if a.dtype.kind not in "iuf":
        raise ValueError(f"attribute of dtype {a.dtype} cannot be written to PLY")
    return a.astype(a.dtype.newbyteorder("<"))


def _check_points(points: np.ndarray, attributes: Mapping[str, np.ndarray] | None,
                  reserved: tuple[str, ...]) -> tuple[np.ndarray, dict]:
    pts = np.asarray(points)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"points must be (N, 3), got {pts.shape}")
    attrs = {str(k): np.asarray(v) for k, v in (attributes or {}).items()}
    for name, values in attrs.items():
        if values.shape != (len(pts),):
            raise ValueError(f"attribute {name!r} must be ({len(pts)},), got {values.shape}")
        if name in reserved:
            raise ValueError(f"attribute name {name!r} is reserved")
    return pts, attrs


def _vertex_element(vertices: np.ndarray, attrs: Mapping[str, np.ndarray]):
    from plyfile import PlyElement

    columns = {name: _ply_compatible(v) for name, v in attrs.items()}
    dtype = [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), *[(n, c.dtype.str) for n, c in columns.items()]]
    data = np.empty(len(vertices), dtype=dtype)
    for i, c in enumerate("xyz"):
        data[c] = vertices[:, i]
    for name, values in columns.items():
        data[name] = values
    return PlyElement.describe(data, "vertex")


def write_points(path: str | os.PathLike, points: np.ndarray, attributes: Mapping[str, np.ndarray] | None = None,
                 origins: np.ndarray | None = None) -> str:
    """Write a point cloud to `.ply` (float32 xyz + attributes) or `.npz` (`points` f32, attributes,
    `origins` when given; the layout `hgca read` promises)."""
    path = os.fspath(path)
    ext = _extension(path, (".ply", ".npz"))
    pts, attrs = _check_points(points, attributes, ("x", "y", "z") if ext == ".ply" else NPZ_RESERVED)
    if ext == ".ply":
        from plyfile import PlyData

        ply = PlyData([_vertex_element(pts, attrs)], text=False, byte_order="<")
        return atomic_write(path, ply.write)
    arrays = {"points": pts.astype(np.float32), **attrs}
    if origins is not None:
        arrays["origins"] = np.asarray(origins, dtype=np.float64).reshape(-1, 3)
    return atomic_write(path, lambda f: np.savez(f, **arrays))


def write_mesh_npz(path: str | os.PathLike, vertices: np.ndarray, faces: np.ndarray,
                   observed_distance: np.ndarray) -> str:
    """The mesh layout of CONTRACTS.md: `vertices` (V,3) f32, `faces` (F,3) i32, `observed_distance` (V,) f32."""
    path = os.fspath(path)
    _extension(path, (".npz",))
    v = np.asarray(vertices, dtype=np.float32)
    f = np.asarray(faces)
    d = np.asarray(observed_distance, dtype=np.float32)
    if v.ndim != 2 or v.shape[1] != 3:
        raise ValueError(f"vertices must be (V, 3), got {v.shape}")
    if f.ndim != 2 or f.shape[1] != 3:
        raise ValueError(f"faces must be (F, 3), got {f.shape}")
    if f.size and (f.min() < 0 or f.max() >= len(v)):
        raise ValueError("faces index vertices out of range")
    if d.shape != (len(v),):
        raise ValueError(f"observed_distance must be ({len(v)},), got {d.shape}")
    arrays = {"vertices": v, "faces": f.astype(np.int32), "observed_distance": d}
    return atomic_write(path, lambda fh: np.savez(fh, **arrays))


def _mesh_ply(mesh: "trimesh.Trimesh", out: BinaryIO) -> None:
    from plyfile import PlyData, PlyElement

    vertices = np.asarray(mesh.vertices)
    attrs: dict[str, np.ndarray] = {}
    for name, values in mesh.vertex_attributes.items():
        values = np.asarray(values)
        if values.shape != (len(vertices),) or name in ("x", "y", "z") or values.dtype.kind not in "biuf":
            continue
        attrs[name] = values.astype(np.float32) if values.dtype.kind == "f" else values
    if getattr(mesh.visual, "kind", None) == "vertex":
        colors = np.asarray(mesh.visual.vertex_colors, dtype=np.uint8)
        for i, c in enumerate(("red", "green", "blue", "alpha")[: colors.shape[1]]):
            attrs.setdefault(c, colors[:, i])
    faces = np.empty(len(mesh.faces), dtype=[("vertex_indices", "<i4", (3,))])
    faces["vertex_indices"] = np.asarray(mesh.faces, dtype=np.int32)
    face_el = PlyElement.describe(faces, "face", len_types={"vertex_indices": "u1"})
    PlyData([_vertex_element(vertices, attrs), face_el], text=False, byte_order="<").write(out)


def write_mesh(path: str | os.PathLike, mesh: "trimesh.Trimesh") -> str:
    """Write a trimesh to `.ply` (with `observed_distance` and other scalar vertex attributes), `.obj`
    (geometry only: OBJ has no per-vertex scalars) or `.glb` (custom attributes as `_name`)."""
    path = os.fspath(path)
    ext = _extension(path, (".ply", ".obj", ".glb"))
    if ext == ".ply":
        return atomic_write(path, lambda f: _mesh_ply(mesh, f))
    data = mesh.export(file_type=ext[1:])
    payload = data.encode("utf-8") if isinstance(data, str) else bytes(data)
    return atomic_write(path, lambda f: f.write(payload))


__all__ = ["write_points", "write_mesh", "write_mesh_npz", "atomic_write"]
