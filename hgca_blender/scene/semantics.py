"""Semantic classes of a labelled completion (`hgca complete --semantics`) as Blender materials and collections.

Each class is one material, shared by every result in the file and named "hGCA <class>" (road, sidewalk,
building, ...): its colour is the palette. Change a class's colour once (the material's Base Color, or
`set_palette`) and every labelled result follows; a material the user already has under that name is reused as it
is, so an edited palette survives new runs. A labelled mesh gets the class materials as its slots and each face the
slot of its class, plus the face attributes `hgca_label` (class index) and, when given, `hgca_label_agreement`
(the share of the k samples that agree). Optionally each class also becomes an object of its own in a child
collection per class ("<run> road", ...), for simulators and scene layouts that assign physics per class.

Nothing here touches objects, meshes or materials the add-on did not make, except reading a same-named material.
"""
from __future__ import annotations

from pathlib import Path

import bpy
import numpy as np

# the core's vocabulary (hgca_core.io.classes), repeated here: the add-on never imports the core
CLASS_NAMES = ("road", "sidewalk", "building", "car", "tree", "pole", "fence", "shelter", "person")
CLASS_COLORS = ((90, 90, 96), (190, 170, 150), (200, 90, 60), (40, 110, 230), (60, 170, 60), (240, 220, 40),
                (160, 110, 200), (40, 200, 200), (250, 60, 160))
MATERIAL_PREFIX = "hGCA "
LABEL_ATTRIBUTE = "hgca_label"
AGREEMENT_ATTRIBUTE = "hgca_label_agreement"
ROLE_KEY = "hgca_role"


def _linear(c: float) -> float:
    return c / 12.92 if c <= 0.04045 else ((c + 0.055) / 1.055) ** 2.4


def default_palette() -> dict[str, tuple[float, float, float, float]]:
    """{class: linear RGBA}: the colours of the core's renderings and GLB materials."""
    return {n: (*(_linear(v / 255.0) for v in rgb), 1.0) for n, rgb in zip(CLASS_NAMES, CLASS_COLORS)}


def read_labels(path: Path) -> tuple[np.ndarray, np.ndarray | None, tuple[str, ...]] | None:
    """(face labels (F,), agreement (F,) or None, class names) of a result file, or None when it has no labels.
    Labels outside the names given are refused (a damaged file), never silently drawn as another class."""
    with np.load(path, allow_pickle=False) as data:
        if "face_label" not in data.files:
            return None
        labels = np.asarray(data["face_label"]).astype(np.int64)
        names = tuple(str(n) for n in data["label_names"]) if "label_names" in data.files else CLASS_NAMES
        agree = np.asarray(data["face_label_agreement"], dtype=np.float32) \
            if "face_label_agreement" in data.files else None
        n_faces = len(data["faces"]) if "faces" in data.files else len(labels)
    if labels.shape != (n_faces,) or (agree is not None and agree.shape != (n_faces,)):
        raise ValueError(f"{path.name}: face_label must have one entry per face ({n_faces})")
    if labels.size and (labels.min() < 0 or labels.max() >= len(names)):
        raise ValueError(f"{path.name}: face_label holds {labels.max()}, but only {len(names)} classes are named")
    return labels, agree, names


def class_material(name: str, created: "object | None" = None,
                   palette: dict[str, tuple[float, float, float, float]] | None = None) -> bpy.types.Material:
    """The file's material of class `name` ("hGCA <name>"), made with the palette colour when it does not exist."""
    full = MATERIAL_PREFIX + name
    mat = bpy.data.materials.get(full)
    if mat is not None:
        return mat
    rgba = (palette or default_palette()).get(name, (0.8, 0.8, 0.8, 1.0))
    mat = bpy.data.materials.new(full)
    if created is not None:
        created.materials.append(mat)
    if mat.node_tree is None:    # Blender 4.x; in 5.x materials always have a node tree
        mat.use_nodes = True
    bsdf = next((n for n in mat.node_tree.nodes if n.bl_idname == "ShaderNodeBsdfPrincipled"), None)
    if bsdf is None:
        bsdf = mat.node_tree.nodes.new("ShaderNodeBsdfPrincipled")
        output = next((n for n in mat.node_tree.nodes if n.bl_idname == "ShaderNodeOutputMaterial"), None) \
            or mat.node_tree.nodes.new("ShaderNodeOutputMaterial")
        mat.node_tree.links.new(bsdf.outputs["BSDF"], output.inputs["Surface"])
    bsdf.inputs["Base Color"].default_value = rgba
    bsdf.inputs["Roughness"].default_value = 0.9
    mat.diffuse_color = rgba      # Solid view
    mat[ROLE_KEY] = "class"
    mat["hgca_class"] = name
    return mat


def set_palette(colours: dict[str, tuple[float, float, float, float]]) -> int:
    """Recolour the file's class materials ({class: linear RGBA}); returns how many changed."""
    changed = 0
    for name, rgba in colours.items():
        mat = bpy.data.materials.get(MATERIAL_PREFIX + name)
        if mat is None or mat.get(ROLE_KEY) != "class":
            continue
        bsdf = next((n for n in mat.node_tree.nodes if n.bl_idname == "ShaderNodeBsdfPrincipled"), None)
        if bsdf is not None:
            bsdf.inputs["Base Color"].default_value = tuple(rgba)
        mat.diffuse_color = tuple(rgba)
        changed += 1
    return changed


def apply_labels(obj: bpy.types.Object, labels: np.ndarray, agreement: np.ndarray | None,
                 names: tuple[str, ...], created: "object | None" = None) -> list[str]:
    """Give `obj` (a result the add-on made) the class materials as slots and each face its class's slot;
    store the labels (and agreement) as face attributes. Returns the classes present, in slot order."""
    mesh = obj.data
    present = [int(v) for v in np.unique(labels)]
    slots = {}
    for v in present:
        mesh.materials.append(class_material(names[v], created))
        slots[v] = len(mesh.materials) - 1
    index = np.zeros(len(labels), np.int32)
    for v, s in slots.items():
        index[labels == v] = s
    mesh.polygons.foreach_set("material_index", index)
    attr = mesh.attributes.new(LABEL_ATTRIBUTE, "INT", "FACE")
    attr.data.foreach_set("value", labels.astype(np.int32))
    if agreement is not None:
        share = mesh.attributes.new(AGREEMENT_ATTRIBUTE, "FLOAT", "FACE")
        share.data.foreach_set("value", np.ascontiguousarray(agreement, dtype=np.float32))
    mesh.update()
    return [names[v] for v in present]


def class_collections(obj: bpy.types.Object, labels: np.ndarray, names: tuple[str, ...], parent: bpy.types.Collection,
                      run_name: str, created: "object | None" = None) -> list[bpy.types.Collection]:
    """One child collection of `parent` per class present ("<run> <class>"), each with an object holding the
    faces of that class of `obj` (same placement, the class's material)."""
    mesh = obj.data
    n = len(mesh.vertices)
    co = np.empty(n * 3, np.float32)
    mesh.vertices.foreach_get("co", co)
    co = co.reshape(-1, 3)
    loops = np.empty(len(mesh.polygons) * 3, np.int32)
    mesh.loops.foreach_get("vertex_index", loops)
    faces = loops.reshape(-1, 3)
    out = []
    for v in (int(x) for x in np.unique(labels)):
        used, f = np.unique(faces[labels == v], return_inverse=True)
        part = bpy.data.meshes.new(f"{obj.name} {names[v]}")
        if created is not None:
            created.meshes.append(part)
        part.vertices.add(len(used))
        part.vertices.foreach_set("co", np.ascontiguousarray(co[used]).ravel())
        nf = len(f) // 3
        part.loops.add(3 * nf)
        part.loops.foreach_set("vertex_index", f.astype(np.int32))
        part.polygons.add(nf)
        part.polygons.foreach_set("loop_start", np.arange(0, 3 * nf, 3, dtype=np.int32))
        part.update(calc_edges=True)
        part.materials.append(class_material(names[v], created))
        child = bpy.data.objects.new(f"{obj.name} {names[v]}", part)
        if created is not None:
            created.objects.append(child)
        child.location = obj.location
        child[ROLE_KEY] = "result"
        child["hgca_class"] = names[v]
        coll = bpy.data.collections.new(f"{run_name} {names[v]}")
        if created is not None:
            created.collections.append(coll)
        coll.objects.link(child)
        parent.children.link(coll)
        out.append(coll)
    return out


def label_results(objects: list, outputs: list[Path], collection: bpy.types.Collection, run_name: str,
                  created: "object | None" = None, per_class: bool = False) -> int:
    """The hook of `mesh_build.build_results`: label each result object whose file carries labels; with
    `per_class`, the first sample's classes also become collections. Returns how many objects were labelled."""
    done = 0
    for i, (obj, path) in enumerate(zip(objects, outputs)):
        found = read_labels(Path(path))
        if found is None:
            continue
        labels, agreement, names = found
        apply_labels(obj, labels, agreement, names, created)
        if per_class and i == 0:
            class_collections(obj, labels, names, collection, run_name, created)
        done += 1
    return done
