"""Writers for accumulated points and completed meshes (PLY, NPZ, OBJ, GLB), all atomic.

PLY is always binary little endian: compact, and what Blender, CloudCompare and MeshLab read natively.
The mesh's per-vertex `observed_distance` travels as a PLY vertex property (and as the
`_observed_distance` glTF attribute in GLB), so observed vs generated survives export.

Georeferenced coordinates stay exact (`hgca_core.io.georef`): PLY x, y, z are float32 near the origin and
float64 (`property double x`) beyond 8192 m: world coordinates, standard PLY, read exactly by trimesh and
plyfile (Blender's own PLY importer reads them but keeps float32: 0.5 m steps at y = 1e7; the add-on's
import keeps a float64 scene origin instead, see hgca_blender/georef.py); OBJ writes 8 decimals of the float64 values; NPZ stores float32 relative to a float64
`offset` array (always present, zeros near the origin); GLB stores float32 vertices under a node whose matrix
translation (a JSON number) is the offset. Every writer takes an optional `hgca_core.io.atomic.AtomicBatch`,
so the k samples of a completion appear together or not at all.
"""
from __future__ import annotations

import os
from typing import TYPE_CHECKING, BinaryIO, Callable, Mapping

import numpy as np

from hgca_core.errors import InputError
from hgca_core.io.atomic import AtomicBatch, atomic_write
from hgca_core.io.georef import local_offset, needs_offset, to_local32

if TYPE_CHECKING:
    import trimesh

NPZ_RESERVED = ("points", "origins", "offset")  # keys of the `hgca read` layout that are not attributes


def _save(path: str, write: Callable[[BinaryIO], None], batch: AtomicBatch | None) -> str:
    return batch.add(path, write) if batch is not None else atomic_write(path, write)


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
    """x, y, z (float32, or float64 for georeferenced coordinates) and the attribute columns as one
    little-endian structured array (a PLY vertex row)."""
    columns = {name: _ply_compatible(v) for name, v in attrs.items()}
    xyz = "<f8" if needs_offset(vertices) else "<f4"
    dtype = [("x", xyz), ("y", xyz), ("z", xyz), *[(n, c.dtype.str) for n, c in columns.items()]]
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
                 origins: np.ndarray | None = None, batch: AtomicBatch | None = None) -> str:
    """Write a point cloud to `.ply` (xyz + attributes) or `.npz` (`points` f32 relative to `offset` f64,
    attributes, `origins` f64 when given; the layout `hgca read` promises)."""
    path = os.fspath(path)
    ext = _extension(path, (".ply", ".npz"))
    pts, attrs = _check_points(points, attributes, ("x", "y", "z") if ext == ".ply" else NPZ_RESERVED)
    if ext == ".ply":
        vertex = _vertex_array(pts, attrs)
        return _save(path, lambda f: _write_ply(f, vertex), batch)
    offset = local_offset(pts)
    arrays = {"points": to_local32(pts, offset), "offset": offset, **attrs}
    if origins is not None:
        arrays["origins"] = np.asarray(origins, dtype=np.float64).reshape(-1, 3)
    return _save(path, lambda f: np.savez(f, **arrays), batch)


def write_mesh_npz(path: str | os.PathLike, vertices: np.ndarray, faces: np.ndarray,
                   observed_distance: np.ndarray, batch: AtomicBatch | None = None) -> str:
    """The mesh layout of CONTRACTS.md: `vertices` (V,3) f32 relative to `offset` (3,) f64, `faces` (F,3) i32,
    `observed_distance` (V,) f32. World coordinates are `vertices + offset`, computed in float64."""
    path = os.fspath(path)
    _extension(path, (".npz",))
    world = np.asarray(vertices, dtype=np.float64)
    if world.ndim != 2 or world.shape[1] != 3:
        raise ValueError(f"vertices must be (V, 3), got {world.shape}")
    offset = local_offset(world)
    v = to_local32(world, offset)
    f = np.asarray(faces)
    d = np.asarray(observed_distance, dtype=np.float32)
    if f.ndim != 2 or f.shape[1] != 3:
        raise ValueError(f"faces must be (F, 3), got {f.shape}")
    if f.size and (f.min() < 0 or f.max() >= len(v)):
        raise ValueError("faces index vertices out of range")
    if d.shape != (len(v),):
        raise ValueError(f"observed_distance must be ({len(v)},), got {d.shape}")
    arrays = {"vertices": v, "offset": offset, "faces": f.astype(np.int32), "observed_distance": d}
    return _save(path, lambda fh: np.savez(fh, **arrays), batch)


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


def _glb(mesh: "trimesh.Trimesh") -> bytes:
    """GLB bytes; georeferenced meshes become float32 vertices near the origin under a node whose matrix
    translates them by the float64 offset (glTF stores node matrices as JSON numbers, so they stay exact)."""
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    offset = local_offset(vertices)
    if not offset.any():
        return bytes(mesh.export(file_type="glb"))
    import trimesh

    local = mesh.copy()
    local.vertices = vertices - offset
    transform = np.eye(4)
    transform[:3, 3] = offset
    scene = trimesh.Scene()
    scene.add_geometry(local, node_name="hgca_mesh", transform=transform)
    return bytes(scene.export(file_type="glb"))


def write_mesh(path: str | os.PathLike, mesh: "trimesh.Trimesh", batch: AtomicBatch | None = None) -> str:
    """Write a trimesh to `.ply` (with `observed_distance` and other scalar vertex attributes), `.obj`
    (geometry only: OBJ has no per-vertex scalars) or `.glb` (custom attributes as `_name`)."""
    path = os.fspath(path)
    ext = _extension(path, (".ply", ".obj", ".glb"))
    if ext == ".ply":
        return _save(path, lambda f: _mesh_ply(mesh, f), batch)
    if ext == ".glb":
        payload = _glb(mesh)
    else:
        data = mesh.export(file_type="obj")
        payload = data.encode("utf-8") if isinstance(data, str) else bytes(data)
    return _save(path, lambda f: f.write(payload), batch)


__all__ = ["AtomicBatch", "write_points", "write_mesh", "write_mesh_npz", "atomic_write"]
