"""Completion regions in the scene: boxes read from objects, drawn and parsed.

A region is the CLI's 7-tuple (cx, cy, cz, sx, sy, sz, yaw_deg) in world metres (CONTRACTS.md). The add-on
does not estimate regions itself: "Add Region Box" asks the core (`jobs.default_region`) and draws its answer
here, so the CLI and the add-on put the same box around the same scans. The region box the add-on creates is
an ordinary wireframe mesh cube of unit size whose object scale is the box size, so users move, rotate (about z)
and scale it with the usual tools; any object's bounding box (or an empty's cube) works as a region too.
"""
from __future__ import annotations

import math

import bpy
import numpy as np

from . import georef
from .mesh_build import ROLE_KEY
from .sources import update_transforms

MAX_TILT_DEG = 1.0
REGION_TYPES = ("MESH", "EMPTY")  # objects whose box can be a region
EXACT_KEY = "hgca_exact_region"   # custom property of a box the add-on made: its region in float64 world metres


def decimal32(value: float) -> float:
    """The shortest decimal a float32 holds (9.6 for the float32 nearest 9.6): what the user typed into a
    Blender property, without the float32 noise (9.600000381...) that would make the core's region differ."""
    return float(str(np.float32(value)))


def clean(region: tuple[float, ...]) -> "Region":
    """A region read from float32 Blender data, each number as the user typed it (`decimal32`)."""
    return tuple(decimal32(v) for v in region)  # type: ignore[return-value]


class RegionError(ValueError):
    """The region cannot be used (no points, a tilted box, zero size); the message says why."""


Region = tuple[float, float, float, float, float, float, float]


def _local_bounds(obj: bpy.types.Object) -> tuple[np.ndarray, np.ndarray]:
    if obj.type == "EMPTY":
        s = float(obj.empty_display_size)
        return np.full(3, -s), np.full(3, s)
    corners = np.array([tuple(c) for c in obj.bound_box], dtype=np.float64)
    return corners.min(axis=0), corners.max(axis=0)


def region_from_object(obj: bpy.types.Object) -> Region:
    """The oriented box an object spans in world space (its bounds under its world matrix).

    Only rotation about z is allowed: the core's regions are upright boxes.
    """
    if obj.type not in REGION_TYPES:
        raise RegionError(f"region object {obj.name!r} is a {obj.type.lower()}: use a mesh box or an empty")
    update_transforms()
    lo, hi = _local_bounds(obj)
    m = np.array(obj.matrix_world, dtype=np.float64)
    axes = m[:3, :3]
    lengths = np.linalg.norm(axes, axis=0)
    size = (hi - lo) * lengths
    if np.any(size <= 1e-6):
        raise RegionError(f"region object {obj.name!r} has zero size")
    z_axis = axes[:, 2] / lengths[2]
    if math.degrees(math.acos(min(1.0, abs(float(z_axis[2]))))) > MAX_TILT_DEG:
        raise RegionError(f"region object {obj.name!r} is tilted: rotate it about Z only")
    centre = m @ np.append((lo + hi) / 2, 1.0)
    yaw = math.degrees(math.atan2(axes[1, 0], axes[0, 0]))
    return clean((*map(float, centre[:3]), *map(float, size), float(yaw)))


def world_region_of(scene: bpy.types.Scene, obj: bpy.types.Object) -> Region:
    """The world region (the CLI's --region) a box stands for: the exact float64 region it was made from while it
    stands where it was put, else the box as it now stands (`region_from_object`) in world coordinates."""
    seen = region_from_object(obj)
    exact = obj.get(EXACT_KEY)
    if exact is not None and len(exact) == 7:
        exact = tuple(float(v) for v in exact)
        if _same_box(seen, georef.region_to_scene(scene, exact)):
            return exact  # type: ignore[return-value]
    return georef.region_to_world(scene, seen)  # type: ignore[return-value]


def _same_box(seen: Region, exact: Region) -> bool:
    """Whether the box Blender holds (float32) is still the exact region it was made from: each number within a
    few float32 roundings of it, the yaw (read back through a float32 rotation matrix) within 1e-4 degrees. A
    moved, scaled or turned box is not, and is read as it now stands."""
    for i, (a, b) in enumerate(zip(seen, exact)):
        tol = 1e-4 if i == 6 else 4 * float(np.spacing(np.float32(max(abs(a), abs(b), 1.0))))
        if not math.isfinite(b) or abs(a - b) > tol:
            return False
    return True


def region_from_numbers(centre: tuple[float, float, float], size: tuple[float, float, float],
                        yaw_rad: float) -> Region:
    if min(size) <= 0:
        raise RegionError(f"region size must be positive, got {tuple(size)}")
    return clean((*map(float, centre), *map(float, size), math.degrees(yaw_rad)))


def _unit_cube(name: str) -> bpy.types.Mesh:
    verts = [(x, y, z) for x in (-0.5, 0.5) for y in (-0.5, 0.5) for z in (-0.5, 0.5)]
    faces = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    mesh = bpy.data.meshes.new(name)
    mesh.from_pydata(verts, [], faces)
    mesh.update()
    return mesh


def create_region_box(collection: bpy.types.Collection, region: Region, name: str = "hGCA Region",
                      world: Region | None = None) -> bpy.types.Object:
    """A new wireframe box object showing `region` (Blender coordinates); it never renders. `world`: the exact
    world region it stands for, which `world_region_of` gives back while the box is left where it is."""
    obj = bpy.data.objects.new(name, _unit_cube(name))
    obj.display_type = "WIRE"
    obj.show_in_front = True
    obj.hide_render = True
    obj.location = region[:3]
    obj.scale = region[3:6]
    obj.rotation_euler = (0.0, 0.0, math.radians(region[6]))
    obj[ROLE_KEY] = "region"
    # Blender keeps transforms in float32 (z 1.160985 for 1.1609850125...); the exact numbers travel with the
    # box, so an untouched box gives the core the very region `hgca region` gave, and the CLI's mesh
    if world is not None:
        obj[EXACT_KEY] = [float(v) for v in world]
    collection.objects.link(obj)
    return obj


def format_region(region: Region) -> str:
    """The CLI's --region text."""
    return ",".join(repr(float(v)) for v in region)


def parse_region(text: str) -> Region:
    """Parse 'cx,cy,cz,sx,sy,sz[,yaw_deg]' (batch command line)."""
    try:
        vals = [float(v) for v in text.split(",")]
    except ValueError as exc:
        raise RegionError(f"region must be numbers 'cx,cy,cz,sx,sy,sz[,yaw]', got {text!r}") from exc
    if len(vals) not in (6, 7):
        raise RegionError(f"region needs 6 or 7 numbers, got {len(vals)}")
    if len(vals) == 6:
        vals.append(0.0)
    if min(vals[3:6]) <= 0 or not all(math.isfinite(v) for v in vals):
        raise RegionError(f"region size must be positive and finite, got {text!r}")
    return tuple(vals)  # type: ignore[return-value]
