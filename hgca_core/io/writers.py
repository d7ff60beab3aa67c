"""Writers for accumulated points and completed meshes (PLY, NPZ, OBJ, GLB), all atomic.

PLY is always binary little endian: compact, and what Blender, CloudCompare and MeshLab read natively.
The mesh's per-vertex `observed_distance` travels as a PLY vertex property (and as the
`_observed_distance` glTF attribute in GLB), so observed vs generated survives export.

Georeferenced coordinates stay exact (`hgca_core.io.georef`): PLY x, y, z are float32 near the origin and
float64 (`property double x`) beyond 8192 m: world coordinates, standard PLY, read exactly by trimesh and
plyfile (Blender's own PLY importer reads them but keeps float32: 0.5 m steps at y = 1e7; the add-on's
import keeps a float64 scene origin instead, see hgca_blender/scene/georef.py); OBJ writes 8 decimals of the float64 values; NPZ stores float32 relative to a float64
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
from hgca_core.io.classes import CLASS_COLORS, CLASS_NAMES

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


def _write_ply(out: BinaryIO, vertex: np.ndarray, faces: np.ndarray | None = None,
               face_attrs: Mapping[str, np.ndarray] | None = None) -> None:
    """Binary little-endian PLY from whole arrays: header, then the rows as raw bytes (plyfile writes list
    properties one face at a time, 20 s for the 7 M faces of a default-region mesh; this takes ~1 s).
    `face_attrs`: scalar face properties after `vertex_indices` (e.g. the observed / generated `material`)."""
    lines = ["ply", "format binary_little_endian 1.0", "comment written by hgca", f"element vertex {len(vertex)}"]
    lines += [f"property {_PLY_TYPES[vertex.dtype[n].str[1:]]} {n}" for n in vertex.dtype.names]
    columns = {n: _ply_compatible(v) for n, v in (face_attrs or {}).items()}
    if faces is not None:
        lines += [f"element face {len(faces)}", "property list uchar int vertex_indices"]
        lines += [f"property {_PLY_TYPES[c.dtype.str[1:]]} {n}" for n, c in columns.items()]
    out.write(("\n".join(lines + ["end_header"]) + "\n").encode("ascii"))
    out.write(vertex.tobytes())
    if faces is not None:
        rows = np.empty(len(faces), dtype=[("n", "u1"), ("v", "<i4", (3,)),     # packed: 13 bytes a face + attrs
                                           *[(n, c.dtype.str) for n, c in columns.items()]])
        rows["n"] = 3
        rows["v"] = faces
        for n, c in columns.items():
            rows[n] = c
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
                   observed_distance: np.ndarray, batch: AtomicBatch | None = None,
                   normals: np.ndarray | None = None, face_material: np.ndarray | None = None,
                   face_label: np.ndarray | None = None, face_label_agreement: np.ndarray | None = None) -> str:
    """The mesh layout of CONTRACTS.md: `vertices` (V,3) f32 relative to `offset` (3,) f64, `faces` (F,3) i32,
    `observed_distance` (V,) f32, and when given `normals` (V,3) f32 (unit per-vertex normals),
    `face_material` (F,) u8 (0 observed, 1 generated), `face_label` (F,) u8 (the class, an index into the
    `label_names` array written with it) and `face_label_agreement` (F,) f32 (the share of the k samples that
    agree on it). World coordinates are `vertices + offset`, in float64."""
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
    if normals is not None:
        n = np.asarray(normals, dtype=np.float32)
        if n.shape != v.shape:
            raise ValueError(f"normals must be ({len(v)}, 3), got {n.shape}")
        arrays["normals"] = n
    if face_material is not None:
        m = np.asarray(face_material)
        if m.shape != (len(f),):
            raise ValueError(f"face_material must be ({len(f)},), got {m.shape}")
        arrays["face_material"] = m.astype(np.uint8)
    for name, values, dtype in (("face_label", face_label, np.uint8),
                                ("face_label_agreement", face_label_agreement, np.float32)):
        if values is not None:
            a = np.asarray(values)
            if a.shape != (len(f),):
                raise ValueError(f"{name} must be ({len(f)},), got {a.shape}")
            arrays[name] = a.astype(dtype)
    if face_label is not None:
        arrays["label_names"] = np.array(CLASS_NAMES)
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
    faces = np.asarray(mesh.faces, dtype=np.int32)
    face_attrs = {n: np.asarray(v) for n, v in mesh.face_attributes.items()
                  if np.asarray(v).shape == (len(faces),) and np.asarray(v).dtype.kind in "biuf"}
    _write_ply(out, _vertex_array(vertices, attrs), faces, face_attrs)


# glTF base colours of the observed / generated faces (linear RGBA), the add-on's material colours
MATERIALS = {"observed": (0.55, 0.57, 0.6, 1.0), "generated": (0.95, 0.45, 0.1, 1.0)}


def _srgb_to_linear(c: float) -> float:
    return c / 12.92 if c <= 0.04045 else ((c + 0.055) / 1.055) ** 2.4


# glTF base colours of the semantic classes (linear RGBA) from their display colours
CLASS_MATERIALS = {n: (*(round(_srgb_to_linear(v / 255.0), 4) for v in rgb), 1.0)
                   for n, rgb in zip(CLASS_NAMES, CLASS_COLORS)}


def mesh_parts(mesh: "trimesh.Trimesh") -> list[tuple[str, "trimesh.Trimesh"]]:
    """(name, part) per material for glTF: with the face attribute `label` (a semantic completion) the faces of
    each class with a PBR material named for it (`CLASS_MATERIALS`); otherwise the faces of each value of the face
    attribute `material` (0 observed, 1 generated) with a PBR material of that name; each part with its vertices'
    normals and scalar attributes (a face's `label_agreement` as the vertex attribute `label_agreement`, the
    lowest of its faces'). One part "mesh" when the mesh has neither."""
    import trimesh
    from trimesh.visual.material import PBRMaterial

    faces = np.asarray(mesh.faces)
    label = mesh.face_attributes.get("label")
    material = mesh.face_attributes.get("material")
    if label is not None and np.asarray(label).shape == (len(faces),):
        groups, colours = np.asarray(label), CLASS_MATERIALS
    elif material is not None and np.asarray(material).shape == (len(faces),):
        groups, colours = np.asarray(material), MATERIALS
    else:
        return [("mesh", mesh)]
    agree = mesh.face_attributes.get("label_agreement")
    normals = np.asarray(mesh.vertex_normals)
    parts = []
    for value, name in enumerate(colours):
        sel = groups == value
        if not sel.any():
            continue
        used, f = np.unique(faces[sel], return_inverse=True)
        part = trimesh.Trimesh(np.asarray(mesh.vertices)[used], f.reshape(-1, 3), vertex_normals=normals[used],
                               process=False)
        for key, values in mesh.vertex_attributes.items():
            if np.asarray(values).shape == (len(mesh.vertices),) and key not in ("nx", "ny", "nz"):
                part.vertex_attributes[key] = np.asarray(values)[used]
        if agree is not None and np.asarray(agree).shape == (len(faces),):
            low = np.ones(len(used), np.float32)
            np.minimum.at(low, f, np.repeat(np.asarray(agree, np.float32)[sel], 3))
            part.vertex_attributes["label_agreement"] = low
        part.visual = trimesh.visual.TextureVisuals(material=PBRMaterial(name=name, baseColorFactor=colours[name],
                                                                         metallicFactor=0.0, roughnessFactor=0.9))
        parts.append((name, part))
    return parts


def _glb(mesh: "trimesh.Trimesh") -> bytes:
    """GLB bytes: one primitive per material (`mesh_parts`) with normals; georeferenced meshes become float32
    vertices near the origin under nodes whose matrix translates them by the float64 offset (glTF stores node
    matrices as JSON numbers, so they stay exact)."""
    import trimesh

    offset = local_offset(np.asarray(mesh.vertices, dtype=np.float64))
    transform = np.eye(4)
    transform[:3, 3] = offset
    scene = trimesh.Scene()
    for name, part in mesh_parts(mesh):
        if offset.any():
            part = part.copy()
            part.vertices = np.asarray(part.vertices, dtype=np.float64) - offset
        scene.add_geometry(part, geom_name=name, node_name=name if name != "mesh" else "hgca_mesh",
                           transform=transform)
    return bytes(scene.export(file_type="glb", include_normals=True))


def write_mesh(path: str | os.PathLike, mesh: "trimesh.Trimesh", batch: AtomicBatch | None = None) -> str:
    """Write a trimesh to `.ply` (with `observed_distance`, normals `nx ny nz` and other scalar vertex
    attributes, and scalar face attributes such as `material`), `.obj` (geometry, and for a labelled mesh one group
    and material per class; OBJ has no per-vertex scalars) or `.glb` (one primitive per material, see `mesh_parts`, with normals; custom vertex attributes
    as `_name`)."""
    path = os.fspath(path)
    ext = _extension(path, (".ply", ".obj", ".glb"))
    if ext == ".ply":
        return _save(path, lambda f: _mesh_ply(mesh, f), batch)
    if ext == ".glb":
        payload = _glb(mesh)
    elif "label" in mesh.face_attributes:
        payload = _obj_by_class(mesh)
    else:
        data = mesh.export(file_type="obj")
        payload = data.encode("utf-8") if isinstance(data, str) else bytes(data)
    return _save(path, lambda f: f.write(payload), batch)


def _obj_by_class(mesh: "trimesh.Trimesh") -> bytes:
    """A labelled mesh as OBJ text with one group and one material name per class (`g road` / `usemtl road`, the
    names of `io.classes.CLASS_NAMES`): what OBJ readers, Blender's among them, split into parts and materials."""
    import io

    from hgca_core.io.classes import CLASS_NAMES

    labels = np.asarray(mesh.face_attributes["label"]).astype(np.int64).reshape(-1)
    faces = np.asarray(mesh.faces, dtype=np.int64) + 1
    out = io.StringIO()
    out.write(f"# hgca completion: {len(faces)} faces, one group and material per class\n")
    np.savetxt(out, np.asarray(mesh.vertices, dtype=np.float64), fmt="v %.8f %.8f %.8f")
    for k in np.unique(labels):
        name = CLASS_NAMES[k] if 0 <= k < len(CLASS_NAMES) else f"class_{k}"
        out.write(f"g {name}\nusemtl {name}\n")
        np.savetxt(out, faces[labels == k], fmt="f %d %d %d")
    return out.getvalue().encode("utf-8")


__all__ = ["AtomicBatch", "write_points", "write_mesh", "write_mesh_npz", "atomic_write"]
