"""The scene's georeference origin: float64 world coordinates in, float32 Blender coordinates near zero.

Blender stores vertex positions and object locations in float32, whose spacing is 1 m at a UTM northing of
1e7 m: a scan placed there in world coordinates is drawn, measured and sent back on a 1 m grid. As the
BlenderGIS / georeferencing add-ons do, the scene keeps one origin in a custom property (`scene["hgca_origin"]`,
three float64 numbers; ID properties hold doubles) and everything the add-on adds lies relative to it:

    world (float64) = origin (scene, float64) + Blender coordinates (object location + vertex, float32)

Imports set the origin (whole metres near the first georeferenced scan) when the scene has none; later imports
and completion results reuse it, each object placed at a whole-metre location with vertices within about its
own extent of zero, so float32 keeps sub-millimetre detail. Points and regions go back to the core as
`origin + Blender coordinates` computed in float64. Nothing here changes an existing object.
"""
from __future__ import annotations

from decimal import Decimal

import bpy
import numpy as np

ORIGIN_KEY = "hgca_origin"
# BlenderGIS keeps a scene's georeferencing in these keys (x/y offset of Blender's 0 in the CRS, and the CRS
# itself): the add-on writes the x/y of its origin there too, and takes them as the origin of a scene that
# BlenderGIS georeferenced first (z 0: BlenderGIS has no vertical offset).
GIS_X, GIS_Y, GIS_CRS = "crs x", "crs y", "crs"
# Objects whose data centre lies farther than this from the scene origin get a whole-metre location (the data
# then stays near zero); nearer ones keep location 0, as an import of local scans always did.
RECENTER_ABOVE = 1000.0


def scene_origin(scene: bpy.types.Scene) -> np.ndarray:
    """(3,) float64 world position of Blender's (0, 0, 0) in `scene`; zeros when the scene has no origin."""
    value = scene.get(ORIGIN_KEY)
    if value is None and scene.get(GIS_X) is not None and scene.get(GIS_Y) is not None:
        value = (scene[GIS_X], scene[GIS_Y], 0.0)
    if value is None:
        return np.zeros(3)
    try:
        origin = np.array([float(v) for v in value], dtype=np.float64)
    except (TypeError, ValueError):
        origin = np.full(1, np.nan)
    if origin.shape != (3,) or not np.all(np.isfinite(origin)):
        raise ValueError(f"scene {scene.name!r} has a broken {ORIGIN_KEY!r} property: {list(value)}")
    return origin


def ensure_origin(scene: bpy.types.Scene, centre_world: np.ndarray, placed: list | None = None) -> np.ndarray:
    """The scene's origin, first set to `centre_world` rounded to whole metres when the scene has none and
    the data is far from zero (a georeferenced scan); local data leaves the scene without one.

    `placed`: objects already in the scene in its local frame (earlier imports, results, region boxes). Setting an
    origin now would move every one of them into the georeferenced frame, kilometres from where they are meant to
    be, so that is refused with the reason instead: georeferencing never moves an earlier import."""
    if (not has_origin(scene)) and float(np.abs(centre_world).max()) > RECENTER_ABOVE:
        if placed:
            names = ", ".join(f"'{o.name}'" for o in placed[:3]) + (" ..." if len(placed) > 3 else "")
            distance = float(np.linalg.norm(np.asarray(centre_world, dtype=np.float64)))
            raise ValueError(f"this scan lies in a georeferenced frame ({distance / 1000:.1f} km from the scene's "
                             f"zero), but the scene already holds {names} in its local frame: importing it here "
                             "would move them there too. Import it into a new scene (Scene > New), or remove "
                             "those objects first")
        origin = [float(v) for v in np.round(centre_world)]
        scene[ORIGIN_KEY] = origin
        scene[GIS_X], scene[GIS_Y] = origin[0], origin[1]
    return scene_origin(scene)


def has_origin(scene: bpy.types.Scene) -> bool:
    """Whether the scene is georeferenced (by the add-on or by BlenderGIS)."""
    return scene.get(ORIGIN_KEY) is not None or (scene.get(GIS_X) is not None and scene.get(GIS_Y) is not None)


def check_crs(scene: bpy.types.Scene, crs: str | None) -> None:
    """Refuse data in a CRS other than the scene's (its coordinates would mean other places); None passes."""
    have = scene.get(GIS_CRS)
    if crs and have and str(have) != crs:
        raise ValueError(f"the scan's CRS is {short_crs(crs)} but the scene's is {short_crs(str(have))}: reproject "
                         "the scan (for example with PDAL) or import it into another scene")


def set_crs(scene: bpy.types.Scene, crs: str | None) -> None:
    """Keep a file's CRS ("EPSG:n" or WKT) in the scene key BlenderGIS reads, when the scene has none yet."""
    check_crs(scene, crs)
    if crs and not scene.get(GIS_CRS):
        scene[GIS_CRS] = crs


def short_crs(crs: str) -> str:
    """A CRS for a label: "EPSG:n" as it is, a WKT by its name (the first quoted string)."""
    if len(crs) <= 24:
        return crs
    name = crs.split('"')[1] if crs.count('"') >= 2 else crs[:24]
    return name if len(name) <= 40 else name[:39] + "\u2026"


def origin_keys(scene: bpy.types.Scene) -> dict:
    """The georeferencing keys the scene holds now (to put back if an import fails)."""
    return {k: scene[k] for k in (ORIGIN_KEY, GIS_X, GIS_Y, GIS_CRS) if k in scene}


def restore_keys(scene: bpy.types.Scene, keys: dict) -> None:
    for k in (ORIGIN_KEY, GIS_X, GIS_Y, GIS_CRS):
        if k in keys:
            scene[k] = keys[k]
        elif k in scene:
            del scene[k]


def place(local: np.ndarray, offset: np.ndarray, origin: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Float32 vertices and a whole-metre object location for points `local + offset` (world, computed in
    float64) in a scene whose origin is `origin`."""
    pts = np.asarray(local, dtype=np.float64)
    rel_offset = np.asarray(offset, dtype=np.float64) - origin
    centre = (pts.min(axis=0) + pts.max(axis=0)) / 2 + rel_offset if len(pts) else rel_offset
    location = np.round(centre) if float(np.abs(centre).max()) > RECENTER_ABOVE else np.zeros(3)
    vertices = (pts + (rel_offset - location)).astype(np.float32)
    return vertices, location


def to_world(scene: bpy.types.Scene, points: np.ndarray) -> np.ndarray:
    """Blender coordinates (float64 from float32 data) -> world coordinates for the core."""
    return np.asarray(points, dtype=np.float64) + scene_origin(scene)


def region_to_world(scene: bpy.types.Scene, region: tuple[float, ...]) -> tuple[float, ...]:
    """A (cx, cy, cz, sx, sy, sz, yaw) region in Blender coordinates -> the same region in world coordinates.

    The centre is added in decimal: -0.11 in a scene whose origin is 5225 is the 5224.89 a user gives the CLI,
    where float64 addition would give 5224.889999999999."""
    origin = scene_origin(scene)
    centre = [float(Decimal(repr(float(c))) + Decimal(repr(float(o)))) for c, o in zip(region[:3], origin)]
    return (*centre, *map(float, region[3:]))


def region_to_scene(scene: bpy.types.Scene, region: tuple[float, ...]) -> tuple[float, ...]:
    """A world region (the CLI's --region) -> Blender coordinates of `scene`."""
    centre = np.asarray(region[:3], dtype=np.float64) - scene_origin(scene)
    return (*map(float, centre), *map(float, region[3:]))
