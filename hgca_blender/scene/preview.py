"""A quick preview render of a completion: camera and sun aimed at the region, Cycles on the CPU.

Used by batch runs (`--render`); settings favour speed (few samples, small image) over beauty.
"""
from __future__ import annotations

import math
from pathlib import Path

import bpy
from mathutils import Vector

from .region import Region


def add_camera_and_sun(scene: bpy.types.Scene, region: Region) -> tuple[bpy.types.Object, bpy.types.Object]:
    """Camera looking down at the region's centre from a corner, and a sun; both new objects."""
    cx, cy, cz, sx, sy, sz, _ = region
    target = Vector((cx, cy, cz - sz / 2))
    reach = max(sx, sy)
    cam_data = bpy.data.cameras.new("hGCA Camera")
    cam_data.lens = 30
    cam_data.clip_end = reach * 10
    camera = bpy.data.objects.new("hGCA Camera", cam_data)
    camera.location = target + Vector((-0.75 * reach, -0.75 * reach, 0.6 * reach))
    camera.rotation_euler = (target - camera.location).to_track_quat("-Z", "Y").to_euler()
    sun_data = bpy.data.lights.new("hGCA Sun", type="SUN")
    sun_data.energy = 3.0
    sun = bpy.data.objects.new("hGCA Sun", sun_data)
    sun.rotation_euler = (math.radians(40), math.radians(10), math.radians(30))
    scene.collection.objects.link(camera)
    scene.collection.objects.link(sun)
    scene.camera = camera
    return camera, sun


def configure_cycles(scene: bpy.types.Scene, samples: int = 16, resolution: tuple[int, int] = (640, 480)) -> None:
    """Cycles on the CPU with few samples and no denoiser (OIDN may be missing in the bpy module)."""
    scene.render.engine = "CYCLES"
    scene.cycles.device = "CPU"
    scene.cycles.samples = samples
    scene.cycles.use_denoising = False
    scene.cycles.use_adaptive_sampling = True
    scene.render.resolution_x, scene.render.resolution_y = resolution
    scene.render.resolution_percentage = 100
    scene.render.image_settings.file_format = "PNG"
    if scene.world is None:
        scene.world = bpy.data.worlds.new("hGCA World")
    sky = (0.6, 0.65, 0.7)
    scene.world.color = sky
    tree = scene.world.node_tree
    background = tree and next((n for n in tree.nodes if n.bl_idname == "ShaderNodeBackground"), None)
    if background is not None:  # worlds that use nodes ignore `world.color` when rendering
        background.inputs["Color"].default_value = (*sky, 1.0)


def render_png(scene: bpy.types.Scene, path: Path) -> Path:
    """Render the scene's camera to `path` (PNG)."""
    path = Path(path).resolve()
    path.parent.mkdir(parents=True, exist_ok=True)
    scene.render.filepath = str(path)
    with bpy.context.temp_override(scene=scene):
        bpy.ops.render.render(write_still=True, scene=scene.name)
    if not path.is_file():
        raise RuntimeError(f"render finished but {path} was not written")
    return path
