"""What a completion hands the core besides the region: the scan files themselves, or points with their rays.

`hgca complete FILE` reads the file in float64 and derives the sensor origins, each point's origin and the
frames from it; Blender keeps float32 vertices, so points sent back through an .npz can differ from the file's
by a fraction of a millimetre, which moves a few voxels on georeferenced logs. So an imported scan remembers
where it came from (`hgca_source`: files, frames, poses, and a digest of its world points at import); while the
object still holds exactly those points and the files are unchanged, the job gives the core the files and the
panel's mesh is the CLI's. Anything else (edited, moved, several objects, meshes from elsewhere) goes as world
points with the sensor origins and each point's origin index, so the observed free space is still used.
"""
from __future__ import annotations

import hashlib
import json
import os
from dataclasses import dataclass

import bpy
import numpy as np

from ..scene import georef, sources

SOURCE_KEY = "hgca_source"  # custom property of an imported scan: JSON of `ScanFiles` plus its digests
INDEX_ATTRIBUTES = ("origin_index", "scan_index")


@dataclass
class ScanFiles:
    """The core's own inputs for an imported scan: `hgca complete PATHS [--frames F] [--poses P] [--topic T]`
    (the topic picks a ROS bag's point cloud stream)."""

    paths: list[str]
    frames: str = ""
    poses: str = ""
    topic: str = ""

    def args(self) -> list[str]:
        return [*self.paths, *(["--frames", self.frames] if self.frames else []),
                *(["--poses", self.poses] if self.poses else []),
                *(["--topic", self.topic] if self.topic else [])]


def _stat(path: str) -> list[int]:
    """Size and modification time: a file edited since the import no longer matches the object."""
    try:
        st = os.stat(path)
    except OSError:
        return [-1, -1]
    return [int(st.st_size), int(st.st_mtime_ns)]


def points_digest(points: np.ndarray) -> str:
    """sha256 of world points as float64: equal only for exactly the same points in the same order."""
    return hashlib.sha256(np.ascontiguousarray(points, dtype=np.float64).tobytes()).hexdigest()


def object_world_points(scene: bpy.types.Scene, obj: bpy.types.Object) -> np.ndarray:
    """(N, 3) float64 world points of one object (scene origin + Blender coordinates)."""
    sources.update_transforms()
    return georef.to_world(scene, sources.object_points(obj))


def remember_files(scene: bpy.types.Scene, obj: bpy.types.Object, files: ScanFiles) -> None:
    """Store on a freshly imported object the files it was read from and a digest of its world points."""
    record = {"paths": files.paths, "frames": files.frames, "poses": files.poses, "topic": files.topic,
              "stats": [_stat(p) for p in [*files.paths, *([files.poses] if files.poses else [])]],
              "digest": points_digest(object_world_points(scene, obj))}
    obj[SOURCE_KEY] = json.dumps(record)


def unchanged_files(scene: bpy.types.Scene, objects: list[bpy.types.Object]) -> ScanFiles | None:
    """The files of a single imported object that still holds exactly what they give, else None."""
    if len(objects) != 1 or objects[0].type != "MESH":
        return None
    raw = objects[0].get(SOURCE_KEY)
    try:
        record = json.loads(raw) if isinstance(raw, str) else None
        files = ScanFiles([str(p) for p in record["paths"]], str(record["frames"]), str(record["poses"]),
                          str(record.get("topic", "")))   # records of older versions name no topic
        stats, digest = record["stats"], str(record["digest"])
    except (TypeError, KeyError, ValueError):
        return None
    now = [_stat(p) for p in [*files.paths, *([files.poses] if files.poses else [])]]
    if now != stats or any(s == [-1, -1] for s in now):
        return None
    if points_digest(object_world_points(scene, objects[0])) != digest:
        return None
    return files


def _int_attribute(obj: bpy.types.Object, name: str) -> np.ndarray | None:
    if obj.type != "MESH":
        return None
    attr = obj.data.attributes.get(name)
    if attr is None or attr.domain != "POINT" or attr.data_type != "INT":
        return None
    values = np.empty(len(obj.data.vertices), dtype=np.int32)
    attr.data.foreach_get("value", values)
    return values.astype(np.int64)


def _nearest(points: np.ndarray, origins: np.ndarray) -> np.ndarray:
    """Index of the nearest origin for every point (few origins: a direct comparison, in chunks)."""
    out = np.empty(len(points), dtype=np.int64)
    for start in range(0, len(points), 65536):
        chunk = points[start:start + 65536]
        d = ((chunk[:, None, :] - origins[None, :, :]) ** 2).sum(axis=2)
        out[start:start + len(chunk)] = d.argmin(axis=1)
    return out


def object_origin_index(obj: bpy.types.Object, points: np.ndarray, origins: np.ndarray) -> np.ndarray:
    """Each point's row in the object's own origins, chosen as the core's `ray_origins` chooses it."""
    index = _int_attribute(obj, "origin_index")
    if index is not None and len(index) == len(points) and index.min() >= 0 and index.max() < len(origins):
        return index
    if len(origins) == 1:
        return np.zeros(len(points), dtype=np.int64)
    scans = _int_attribute(obj, "scan_index")
    if scans is not None and len(scans) == len(points) and scans.min() >= 0 and scans.max() + 1 == len(origins):
        return scans
    return _nearest(points, origins)


def ray_inputs(scene: bpy.types.Scene, objects: list[bpy.types.Object],
               points: list[np.ndarray]) -> tuple[np.ndarray | None, np.ndarray | None]:
    """World sensor origins (S, 3) and each point's row in them (N,), objects stacked in order; (None, None)
    unless every object knows where its sensor stood (points without a ray would get an invented one)."""
    all_origins, all_index, first = [], [], 0
    for obj, pts in zip(objects, points):
        origins = sources.world_origins([obj])
        if origins is None:
            return None, None
        origins = georef.to_world(scene, origins)
        all_origins.append(origins)
        all_index.append(object_origin_index(obj, pts, origins) + first)
        first += len(origins)
    if not all_origins:
        return None, None
    return np.concatenate(all_origins), np.concatenate(all_index)



def source_inputs(scene: bpy.types.Scene, objects: list[bpy.types.Object]) -> dict:
    """`CompletionParams` fields for these source objects: world points, their rays, and the files when the
    objects are one unchanged import (the panel and batch runs alike)."""
    per_object = [object_world_points(scene, obj) for obj in objects]
    origins, origin_index = ray_inputs(scene, objects, per_object)
    return {"points": np.concatenate(per_object), "origins": origins, "origin_index": origin_index,
            "files": unchanged_files(scene, objects)}
