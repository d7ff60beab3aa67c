"""The default completion region, from the core: `hgca region --json` around the source objects.

The add-on does not estimate regions itself: it hands the core the scan files (or world points with their sensor
origins) and asks the estimator `hgca complete` uses, so the CLI and the add-on put the same box around the same
scans. Reading the scene (`region_request`) happens on the main thread, the core's answer (`ask_core`) on any.
"""
from __future__ import annotations

import shutil
import tempfile
from pathlib import Path

import bpy
import numpy as np

from ..scene import georef, sources
from .. import settings
from ..scene.region import Region, RegionError, clean
from . import job_inputs
from .core import CoreError, run_core_json

REGION_TIMEOUT_S = 600


def region_request(scene: bpy.types.Scene, objects: list[bpy.types.Object], size: tuple[float, float, float],
                   folder: Path) -> list[str]:
    """The `hgca region` arguments for the default region around source objects (main thread: reads Blender
    data): the scan files themselves when the objects are one unchanged import (float64, so the box is the one
    `hgca complete FILE` uses, bit for bit), else their world points and sensor origins written to `folder`."""
    size = clean(tuple(size))   # the panel's float32 size as the user typed it
    if min(size) <= 0:
        raise RegionError(f"region size must be positive, got {tuple(size)}")
    size_arg = "--size=" + ",".join(repr(float(v)) for v in size)
    files = job_inputs.unchanged_files(scene, objects)
    if files is not None:
        return ["region", *files.args(), size_arg, "--json"]
    pts = np.concatenate([job_inputs.object_world_points(scene, o) for o in objects])
    if len(pts) == 0:
        raise RegionError("cannot place a region: the source objects have no points")
    arrays = {"points": pts}
    origins = sources.world_origins(objects)
    if origins is not None and len(origins):
        arrays["origins"] = georef.to_world(scene, origins)
    np.savez(folder / "points.npz", **arrays)
    return ["region", str(folder / "points.npz"), size_arg, "--json"]


def ask_core(python: str, args: list[str], folder: Path) -> Region:
    """`hgca region ... --json` answered (any thread: no Blender data): the world region. CoreError when the core
    cannot be run or refuses the points."""
    answer = run_core_json(python, args, timeout=REGION_TIMEOUT_S, cwd=folder)
    values = answer.get("region")
    if not isinstance(values, list) or len(values) != 7:
        raise CoreError(f"hgca region answered without a 7-number region: {answer!r}")
    return tuple(float(v) for v in values)  # type: ignore[return-value]


def default_world_region(python: str, scene: bpy.types.Scene, objects: list[bpy.types.Object],
                         size: tuple[float, float, float] = settings.REGION_SIZE) -> Region:
    """The core's default region around source objects, in world coordinates (`region_request` + `ask_core`, in
    this thread: batch runs and scripts)."""
    folder = Path(tempfile.mkdtemp(prefix="hgca_region_"))
    try:
        return ask_core(python, region_request(scene, objects, size, folder), folder)
    finally:
        shutil.rmtree(folder, ignore_errors=True)
