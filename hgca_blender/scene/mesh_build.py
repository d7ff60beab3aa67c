"""Building Blender data from arrays: point objects for scans, meshes and a material for completions.

Everything goes through `vertices.add / loops.add / polygons.add` + `foreach_set` on contiguous numpy
arrays (about 3x faster than `from_pydata`; 1M triangles in well under a second). Result building is
transactional: if anything fails, every datablock created so far is removed again, so a failed job
leaves the file exactly as it was.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import bpy
import numpy as np

from . import colors, confidence, georef
from .point_display import (DEFAULT_RADIUS, POINT_NODE_GROUP, RADIUS_INPUT, RENDER_POINTS_INPUT,  # noqa: F401
                            ROLE_KEY, point_display_group, point_radius, set_point_radius, set_render_points)

OBSERVED_ATTRIBUTE = "observed_distance"
# Vertices closer than this to an input point count as observed, farther ones as generated (metres).
OBSERVED_NEAR = confidence.OBSERVED_NEAR
OBSERVED_FAR = confidence.OBSERVED_FAR
POINT_MATERIAL = "hGCA point colours"
OBSERVED_COLOR = "hgca_observed_color"     # colour attributes of results: observed (grey) / generated (orange)
AGREEMENT_ATTRIBUTE = "hgca_agreement"     # share of the k samples with surface at the vertex
AGREEMENT_COLOR = "hgca_agreement_color"
DECIMATE_MODIFIER = "hGCA Max Faces"


class Created:
    """Datablocks created during one operation, removed again by `rollback()` if it fails."""

    def __init__(self) -> None:
        self.objects: list[bpy.types.Object] = []
        self.meshes: list[bpy.types.Mesh] = []
        self.materials: list[bpy.types.Material] = []
        self.collections: list[bpy.types.Collection] = []
        self.node_groups: list[bpy.types.NodeTree] = []

    def rollback(self) -> None:
        """Remove every recorded datablock; one the user already deleted (results go in over many timer ticks,
        while the interface answers) is skipped."""
        for items, data in ((self.objects, bpy.data.objects), (self.meshes, bpy.data.meshes),
                            (self.materials, bpy.data.materials), (self.collections, bpy.data.collections),
                            (self.node_groups, bpy.data.node_groups)):
            for item in items:
                try:
                    data.remove(item, do_unlink=True)
                except ReferenceError:
                    pass
        self.__init__()


# -------------------------------------------------------------------------------------------------
# Point objects

def _attribute_type(values: np.ndarray) -> tuple[str, np.ndarray] | None:
    """Blender attribute type and the array converted for foreach_set, or None if unsupported."""
    if values.ndim == 1:
        if values.dtype == np.bool_:
            return "BOOLEAN", values.astype(np.bool_)
        if np.issubdtype(values.dtype, np.integer):
            info = np.iinfo(np.int32)
            if values.size == 0 or (values.min() >= info.min and values.max() <= info.max):
                return "INT", values.astype(np.int32)
            return "FLOAT", values.astype(np.float32)
        if np.issubdtype(values.dtype, np.floating):
            return "FLOAT", values.astype(np.float32)
        return None
    if values.ndim == 2 and np.issubdtype(values.dtype, np.number):
        if values.shape[1] == 2:
            return "FLOAT2", values.astype(np.float32)
        if values.shape[1] == 3:
            return "FLOAT_VECTOR", values.astype(np.float32)
    return None


def _attribute_name(mesh: bpy.types.Mesh, name: str) -> str:
    """Avoid Blender's built-in and internal names ("position", ".select_vert", ...)."""
    clean = name.strip().lstrip(".") or "attribute"
    if clean in mesh.attributes or clean in {"position", "normal", "id", "radius", "material_index"}:
        clean = f"hgca_{clean}"
    return clean[:63]


def add_point_attributes(mesh: bpy.types.Mesh, attributes: dict[str, np.ndarray]) -> list[str]:
    """Add per-point arrays as point-domain attributes; returns the names that were skipped."""
    n = len(mesh.vertices)
    skipped = []
    for name, raw in attributes.items():
        values = np.asarray(raw)
        converted = _attribute_type(values) if values.shape[:1] == (n,) else None
        if converted is None:
            skipped.append(name)
            continue
        kind, data = converted
        attr = mesh.attributes.new(_attribute_name(mesh, name), kind, "POINT")
        key = "vector" if kind in ("FLOAT2", "FLOAT_VECTOR") else "value"
        attr.data.foreach_set(key, np.ascontiguousarray(data).ravel())
    return skipped


def points_mesh(name: str, points: np.ndarray) -> bpy.types.Mesh:
    """A vertex-only mesh holding `points` (float32 inside Blender: keep them near zero, see georef.place)."""
    mesh = bpy.data.meshes.new(name)
    mesh.vertices.add(len(points))
    mesh.vertices.foreach_set("co", np.ascontiguousarray(points, dtype=np.float32).ravel())
    mesh.update()
    return mesh


def add_point_colors(mesh: bpy.types.Mesh, rgba: np.ndarray) -> None:
    """The scan's colours as its active colour attribute (what Solid view draws with colour = Attribute)."""
    add_color(mesh, colors.COLOR_ATTRIBUTE, rgba, active=True)


def attribute_material(mat: bpy.types.Material, attribute: str) -> tuple:
    """(nodes, links, Principled BSDF, Attribute node reading `attribute`) of `mat`, made to have them."""
    if mat.node_tree is None:  # Blender 4.x; in 5.x materials always have a node tree
        mat.use_nodes = True
    nodes, links = mat.node_tree.nodes, mat.node_tree.links
    bsdf = next((n for n in nodes if n.bl_idname == "ShaderNodeBsdfPrincipled"), None)
    if bsdf is None:
        bsdf = nodes.new("ShaderNodeBsdfPrincipled")
        output = next((n for n in nodes if n.bl_idname == "ShaderNodeOutputMaterial"), None) \
            or nodes.new("ShaderNodeOutputMaterial")
        links.new(bsdf.outputs["BSDF"], output.inputs["Surface"])
    attr = nodes.new("ShaderNodeAttribute")
    attr.attribute_type = "GEOMETRY"
    attr.attribute_name = attribute
    return nodes, links, bsdf, attr


def point_color_material(created: Created) -> bpy.types.Material:
    """One material drawing the scan colour attribute, for Material Preview and renders."""
    existing = bpy.data.materials.get(POINT_MATERIAL)
    if existing is not None and existing.get(ROLE_KEY) == "points":
        return existing
    mat = bpy.data.materials.new(POINT_MATERIAL)
    created.materials.append(mat)
    mat[ROLE_KEY] = "points"
    nodes, links, bsdf, attr = attribute_material(mat, colors.COLOR_ATTRIBUTE)
    attr.location = (-400, 200)
    links.new(attr.outputs["Color"], bsdf.inputs["Base Color"])
    return mat


def build_point_object(name: str, points: np.ndarray, attributes: dict[str, np.ndarray],
                       collection: bpy.types.Collection, show_points: bool = True,
                       location: np.ndarray | None = None, radius: float = DEFAULT_RADIUS,
                       rgba: np.ndarray | None = None) -> tuple[bpy.types.Object, list[str]]:
    """A new point object in `collection` holding `points` at `location` (Blender coordinates, from
    `georef.place`), drawn as points of `radius` coloured by `rgba` (N, 4) when given; returns it and the
    attribute names that could not be stored."""
    created = Created()
    try:
        mesh = points_mesh(name, points)
        created.meshes.append(mesh)
        skipped = add_point_attributes(mesh, attributes)
        if rgba is not None:
            add_point_colors(mesh, rgba)
            mesh.materials.append(point_color_material(created))
        obj = bpy.data.objects.new(name, mesh)
        created.objects.append(obj)
        obj.location = (0.0, 0.0, 0.0) if location is None else [float(v) for v in location]
        obj[ROLE_KEY] = "scan"
        if show_points:
            mod = obj.modifiers.new("hGCA Points", "NODES")
            mod.node_group = point_display_group(created)
            set_point_radius(obj, radius)
        collection.objects.link(obj)
    except Exception:
        created.rollback()
        raise
    return obj, skipped


# -------------------------------------------------------------------------------------------------
# Completion results

@dataclass
class ResultArrays:
    vertices: np.ndarray  # (V, 3) float32, relative to offset
    faces: np.ndarray  # (F, 3) int32
    observed_distance: np.ndarray  # (V,) float32
    offset: np.ndarray  # (3,) float64: world = vertices + offset


def read_result(path: Path) -> ResultArrays:
    """Load and check one `out_s{i}.npz` (CONTRACTS.md) before any Blender data is made from it."""
    with np.load(path, allow_pickle=False) as data:
        missing = [k for k in ("vertices", "faces") if k not in data.files]
        if missing:
            raise ValueError(f"{path.name}: missing arrays {missing}")
        vertices = np.asarray(data["vertices"], dtype=np.float32)
        faces = np.asarray(data["faces"])
        if "observed_distance" in data.files:
            observed = np.asarray(data["observed_distance"], dtype=np.float32)
        else:
            observed = np.zeros(len(vertices), dtype=np.float32)
        offset = np.asarray(data["offset"]) if "offset" in data.files else np.zeros(3)
    if vertices.ndim != 2 or vertices.shape[1] != 3:
        raise ValueError(f"{path.name}: vertices must be (V, 3), got {vertices.shape}")
    if faces.size == 0:
        faces = faces.reshape(0, 3)
    if faces.ndim != 2 or faces.shape[1] != 3 or not np.issubdtype(faces.dtype, np.integer):
        raise ValueError(f"{path.name}: faces must be (F, 3) integers, got {faces.shape} {faces.dtype}")
    if faces.size and (faces.min() < 0 or faces.max() >= len(vertices)):
        raise ValueError(f"{path.name}: face indices out of range 0..{len(vertices) - 1}")
    if observed.shape != (len(vertices),):
        raise ValueError(f"{path.name}: observed_distance must be ({len(vertices)},), got {observed.shape}")
    if not np.all(np.isfinite(vertices)):
        raise ValueError(f"{path.name}: vertices contain NaN or infinite values")
    if offset.shape != (3,) or offset.dtype.kind not in "iuf" or not np.all(np.isfinite(offset)):
        raise ValueError(f"{path.name}: offset must be 3 finite numbers, got {offset.shape} {offset.dtype}")
    return ResultArrays(vertices, faces.astype(np.int32), observed, offset.astype(np.float64))


def triangle_mesh(name: str, vertices: np.ndarray, faces: np.ndarray) -> bpy.types.Mesh:
    """A triangle mesh from (V,3) vertices and (F,3) faces, built with foreach_set."""
    mesh = bpy.data.meshes.new(name)
    n_faces = len(faces)
    mesh.vertices.add(len(vertices))
    mesh.vertices.foreach_set("co", np.ascontiguousarray(vertices, dtype=np.float32).ravel())
    mesh.loops.add(3 * n_faces)
    mesh.loops.foreach_set("vertex_index", np.ascontiguousarray(faces, dtype=np.int32).ravel())
    mesh.polygons.add(n_faces)
    mesh.polygons.foreach_set("loop_start", np.arange(0, 3 * n_faces, 3, dtype=np.int32))
    mesh.update(calc_edges=True)
    return mesh


def observed_material(name: str = "hGCA observed/generated") -> bpy.types.Material:
    """Colour by the "observed_distance" point attribute: grey where observed, orange where generated.

    Attribute -> Map Range (OBSERVED_NEAR..OBSERVED_FAR -> 0..1) -> Color Ramp -> Principled Base Color.
    """
    mat = bpy.data.materials.new(name)
    nodes, links, bsdf, attr = attribute_material(mat, OBSERVED_ATTRIBUTE)
    remap = nodes.new("ShaderNodeMapRange")
    remap.inputs["From Min"].default_value = OBSERVED_NEAR
    remap.inputs["From Max"].default_value = OBSERVED_FAR
    ramp = nodes.new("ShaderNodeValToRGB")
    elements = ramp.color_ramp.elements
    elements[0].position, elements[0].color = 0.0, (0.55, 0.57, 0.6, 1.0)  # observed: neutral grey
    elements[1].position, elements[1].color = 1.0, (0.95, 0.45, 0.1, 1.0)  # generated: orange
    attr.location, remap.location, ramp.location = (-900, 200), (-650, 200), (-400, 200)
    links.new(attr.outputs["Fac"], remap.inputs["Value"])
    links.new(remap.outputs["Result"], ramp.inputs["Fac"])
    links.new(ramp.outputs["Color"], bsdf.inputs["Base Color"])
    mat.diffuse_color = (0.95, 0.45, 0.1, 1.0)  # solid-mode colour
    mat[ROLE_KEY] = "result"
    return mat


def add_color(mesh: bpy.types.Mesh, name: str, rgba: np.ndarray, active: bool = False) -> None:
    """A point-domain colour attribute from (N, 4) RGBA; `active` makes it the one Solid view and renders use.
    Returns nothing: a Python reference to an attribute dangles once another attribute is added (Blender
    reallocates the layers), so callers name attributes, never keep them."""
    attr = mesh.color_attributes.new(name, "FLOAT_COLOR", "POINT")
    attr.data.foreach_set("color", np.ascontiguousarray(rgba, dtype=np.float32).ravel())
    if active:
        set_active_color(mesh, name)


def set_active_color(mesh: bpy.types.Mesh, name: str) -> None:
    """The colour attribute `name` becomes the one Solid view (colour = Attribute) and renders draw; looked up by
    name now, as a reference taken before other attributes were added no longer points at it."""
    mesh.color_attributes.active_color = mesh.color_attributes[name]
    if hasattr(mesh.color_attributes, "render_color_index"):
        mesh.color_attributes.render_color_index = mesh.color_attributes.active_color_index


def color_results_by(objects: list, name: str) -> int:
    """Show the colour attribute `name` (OBSERVED_COLOR or AGREEMENT_COLOR) on result `objects`: in Solid view
    (the active colour attribute) and in renders (their material's Base Color); returns how many have it."""
    changed, materials = 0, set()
    for obj in objects:
        if obj.data.color_attributes.get(name) is None:
            continue
        set_active_color(obj.data, name)
        materials.update(m for m in obj.data.materials if m is not None and m.get(ROLE_KEY) == "result")
        changed += 1
    for mat in materials:
        nodes, links = mat.node_tree.nodes, mat.node_tree.links
        bsdf = next((n for n in nodes if n.bl_idname == "ShaderNodeBsdfPrincipled"), None)
        if bsdf is None:
            continue
        if name == OBSERVED_COLOR:
            source = next((n for n in nodes if n.bl_idname == "ShaderNodeValToRGB"), None)
        else:
            source = next((n for n in nodes if n.bl_idname == "ShaderNodeVertexColor" and n.layer_name == name), None)
            if source is None:
                source = nodes.new("ShaderNodeVertexColor")
                source.layer_name, source.location = name, (-400, -100)
        if source is not None:
            links.new(source.outputs["Color"], bsdf.inputs["Base Color"])
    return changed


def result_object(name: str, arrays: ResultArrays, material: bpy.types.Material, created: Created,
                  origin: np.ndarray | None = None, agreement: np.ndarray | None = None) -> bpy.types.Object:
    """One sample's mesh object, placed relative to the scene origin `origin` (see georef), with its
    observed/generated colours (the active colour attribute: Solid view with colour = Attribute) and, for k > 1
    samples, the share of samples that agree with each vertex (`confidence.agreement`) and its colours."""
    vertices, location = georef.place(arrays.vertices, arrays.offset, np.zeros(3) if origin is None else origin)
    mesh = triangle_mesh(name, vertices, arrays.faces)
    created.meshes.append(mesh)
    attr = mesh.attributes.new(OBSERVED_ATTRIBUTE, "FLOAT", "POINT")
    attr.data.foreach_set("value", arrays.observed_distance)
    add_color(mesh, OBSERVED_COLOR, confidence.observed_colors(arrays.observed_distance))
    if agreement is not None:
        share = mesh.attributes.new(AGREEMENT_ATTRIBUTE, "FLOAT", "POINT")
        share.data.foreach_set("value", np.ascontiguousarray(agreement, dtype=np.float32))
        add_color(mesh, AGREEMENT_COLOR, confidence.agreement_colors(agreement, colors.RAMP))
    set_active_color(mesh, OBSERVED_COLOR)   # after every attribute is added (see add_color)
    mesh.materials.append(material)
    obj = bpy.data.objects.new(name, mesh)
    created.objects.append(obj)
    obj.location = [float(v) for v in location]
    obj[ROLE_KEY] = "result"
    return obj


def add_decimate(obj: bpy.types.Object, faces: int) -> bpy.types.Modifier | None:
    """A Decimate (collapse) modifier showing at most `faces` triangles of `obj`, whose mesh keeps every one;
    None when the mesh has no more than that. Collapse keeps the colour attributes (interpolated)."""
    total = len(obj.data.polygons)
    if faces <= 0 or total <= faces:
        return None
    mod = obj.modifiers.new(DECIMATE_MODIFIER, "DECIMATE")
    mod.decimate_type = "COLLAPSE"
    mod.ratio = faces / total
    return mod


def build_results(scene: bpy.types.Scene, outputs: list[Path], run_name: str,
                  decimate_to: int = 0, class_collections: bool = False) -> bpy.types.Collection:
    """A new collection `run_name` in `scene` with one mesh object per sample; only sample 0 visible. With
    `decimate_to` > 0 each mesh keeps every triangle under a Decimate modifier showing that many.

    All files are read and checked first; on any failure everything created here is removed.
    """
    arrays = [read_result(Path(p)) for p in outputs]
    origin = georef.scene_origin(scene)
    created = Created()
    try:
        collection = bpy.data.collections.new(run_name)
        created.collections.append(collection)
        material = observed_material(f"{run_name} observed/generated")
        created.materials.append(material)
        objects = []
        shares = confidence.agreement([a.vertices.astype(np.float64) + a.offset for a in arrays]) \
            if len(arrays) > 1 else [None] * len(arrays)
        for i, arr in enumerate(arrays):
            obj = result_object(f"{run_name} sample {i}", arr, material, created, origin, shares[i])
            obj["hgca_sample"] = i
            add_decimate(obj, decimate_to)
            collection.objects.link(obj)
            objects.append(obj)
        from . import semantics   # labelled results (`--semantics`): a material per class, collections optional

        semantics.label_results(objects, outputs, collection, run_name, created, per_class=class_collections)
        scene.collection.children.link(collection)
        hide_in_scene(scene, objects[1:])
    except Exception:
        created.rollback()
        raise
    return collection


def hide_in_scene(scene: "bpy.types.Scene", objects: list) -> None:
    """Hide extra samples in the viewport and renders: sample 0 is what the user sees first."""
    for obj in objects:
        obj.hide_render = True
        for view_layer in scene.view_layers:
            obj.hide_set(True, view_layer=view_layer)
