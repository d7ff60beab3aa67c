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


_PLY_TYPES = {"i1": "char", "u1": "uchar", "i2": "short", "u2": "ushort", "i4": "int", "u4": "uint",
              "f4": "float", "f8": "double"}


def _vertex_array(vertices: np.ndarray, attrs: Mapping[str, np.ndarray]) -> np.ndarray:
    """float32 x, y, z and the attribute columns as one little-endian structured array (a PLY vertex row)."""
    columns = {name: _ply_compatible(v) for name, v in attrs.items()}
    dtype = [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), *[(n, c.dtype.str) for n, c in columns.items()]]
    data = np.empty(len(vertices), dtype=dtype)
    for i, c in enumerate("xyz"):
        data[c] = vertices[:, i]
    for name, values in columns.items():
        data[name] = values
    return data


def _write_ply(out: BinaryIO, vertex: np.ndarray, faces: np.ndarray | None = None) -> None:
    """Binary little-endian PLY from whole arrays: header, then the rows as raw bytes (plyfile writes list
    properties one face at a time, 20 s for the 7 M faces of a default-region mesh; this takes ~1 s)."""
    lines = ["ply", "format binary_little_endian 1.0", "comment written by hgca", f"element vertex {len(vertex)}"]
    lines += [f"property {_PLY_TYPES[vertex.dtype[n].str[1:]]} {n}" for n in vertex.dtype.names]
    if faces is not None:
        lines += [f"element face {len(faces)}", "property list uchar int vertex_indices"]
    out.write(("\n".join(lines + ["end_header"]) + "\n").encode("ascii"))
    out.write(vertex.tobytes())
    if faces is not None:
        rows = np.empty(len(faces), dtype=[("n", "u1"), ("v", "<i4", (3,))])   # packed: 13 bytes a face
        rows["n"] = 3
        rows["v"] = faces
        out.write(rows.tobytes())


def write_points(path: str | os.PathLike, points: np.ndarray, attributes: Mapping[str, np.ndarray] | None = None,
                 origins: np.ndarray | None = None) -> str:
    """Write a point cloud to `.ply` (float32 xyz + attributes) or `.npz` (`points` f32, attributes,
    `origins` when given; the layout `hgca read` promises)."""
    path = os.fspath(path)
    ext = _extension(path, (".ply", ".npz"))
    pts, attrs = _check_points(points, attributes, ("x", "y", "z") if ext == ".ply" else NPZ_RESERVED)
    if ext == ".ply":
        vertex = _vertex_array(pts, attrs)
        return atomic_write(path, lambda f: _write_ply(f, vertex))
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
    _write_ply(out, _vertex_array(vertices, attrs), np.asarray(mesh.faces, dtype=np.int32))


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
