"""Which objects feed a completion, and their points in world space.

Sources are only read (`foreach_get`), never written: the add-on does not change the user's objects.
"""
from __future__ import annotations

import bpy
import numpy as np

from .mesh_build import ROLE_KEY

POINT_TYPES = {"MESH", "POINTCLOUD"}
ORIGINS_KEY = "hgca_sensor_origins"  # custom property: sensor positions (x, y, z, x, y, z, ...) in the object's frame


class SourceError(ValueError):
    """No usable source points; the message tells the user what to select."""


def not_a_scan(obj: bpy.types.Object) -> str | None:
    """Why `obj` is no scan (None when it is one). Scans are point clouds and meshes of vertices only, as the
    import makes them; a mesh with faces (the startup Cube, a model) is a surface, whose 8 corners would make a
    region box around the wrong thing."""
    if obj.type not in POINT_TYPES:
        return f"'{obj.name}' is a {obj.type.lower()}, not a scan"
    if obj.get(ROLE_KEY) in ("region", "result"):
        return f"'{obj.name}' is an hGCA {obj.get(ROLE_KEY)}, not a scan"
    if obj.type == "MESH" and len(obj.data.polygons):
        return f"'{obj.name}' is a mesh with {len(obj.data.polygons):,} face(s), not a scan of points"
    return None


def is_point_source(obj: bpy.types.Object, exclude: bpy.types.Object | None = None) -> bool:
    """Point clouds and vertex-only meshes (imported scans), but not region boxes, results or surfaces."""
    return obj is not exclude and not_a_scan(obj) is None


def selected_sources(context: bpy.types.Context, exclude: bpy.types.Object | None = None) -> list[bpy.types.Object]:
    """The selected scans (else the active object when it is one). Selected objects that are no scan are left
    out; when nothing selected is a scan, the refusal names what was selected and why it is none."""
    picked = [o for o in (context.selected_objects or []) if o is not exclude]
    objs = [o for o in picked if is_point_source(o)]
    active = context.active_object
    if not objs and active is not None and active is not exclude:
        objs = [active] if is_point_source(active) else []
        picked += [] if active in picked else [active]
    if not objs and picked:
        raise SourceError("; ".join(not_a_scan(o) or "" for o in picked[:3])
                          + ": select an imported scan (File > Import > LiDAR Scan) or pick a source collection")
    return objs


def collection_sources(collection: bpy.types.Collection,
                       exclude: bpy.types.Object | None = None) -> list[bpy.types.Object]:
    return [o for o in collection.all_objects if is_point_source(o, exclude)]


def object_points(obj: bpy.types.Object) -> np.ndarray:
    """(N, 3) float64 world-space points of one object (its data's vertices/points, matrix applied)."""
    data = obj.data
    if obj.type == "MESH":
        n = len(data.vertices)
        local = np.empty(n * 3, dtype=np.float32)
        data.vertices.foreach_get("co", local)
    elif obj.type == "POINTCLOUD":
        n = len(data.points)
        local = np.empty(n * 3, dtype=np.float32)
        data.attributes["position"].data.foreach_get("vector", local)
    else:
        raise SourceError(f"{obj.name!r} is a {obj.type.lower()}, not a point object")
    m = np.array(obj.matrix_world, dtype=np.float64)
    pts = local.reshape(-1, 3).astype(np.float64)
    return pts @ m[:3, :3].T + m[:3, 3]


def update_transforms() -> None:
    """Bring `matrix_world` up to date: it lags behind location/rotation/scale set from Python until
    the depsgraph is evaluated, which never happens by itself in background mode."""
    view_layer = getattr(bpy.context, "view_layer", None)
    if view_layer is not None:
        view_layer.update()


def world_points(objects: list[bpy.types.Object]) -> np.ndarray:
    """All source points stacked, in world space."""
    if not objects:
        raise SourceError("no source objects: select imported scans (or pick a collection) first")
    update_transforms()
    arrays = [object_points(o) for o in objects]
    pts = np.concatenate(arrays) if arrays else np.zeros((0, 3))
    if len(pts) == 0:
        raise SourceError("the source objects have no points")
    return pts


def set_sensor_origins(obj: bpy.types.Object, origins: np.ndarray | None) -> None:
    """Remember where the sensor stood for an imported scan (world (S, 3), stored in the object's frame, float64)
    so the default region around it is the one `hgca region` gives for the scan files."""
    if origins is None or len(origins) == 0:
        return
    inv = np.array(obj.matrix_basis.inverted(), dtype=np.float64)
    local = np.asarray(origins, dtype=np.float64).reshape(-1, 3) @ inv[:3, :3].T + inv[:3, 3]
    obj[ORIGINS_KEY] = local.reshape(-1).tolist()


def world_origins(objects: list[bpy.types.Object]) -> np.ndarray | None:
    """Sensor origins of the source objects in world space, in object order; None when none has any."""
    update_transforms()
    found = []
    for obj in objects:
        flat = obj.get(ORIGINS_KEY)
        if flat is None or len(flat) == 0 or len(flat) % 3:
            continue
        m = np.array(obj.matrix_world, dtype=np.float64)
        found.append(np.asarray(list(flat), dtype=np.float64).reshape(-1, 3) @ m[:3, :3].T + m[:3, 3])
    return np.concatenate(found) if found else None
