"""Drive jobs: `hgca drive` on scan files, its tiles turned into one collection, one object per tile per sample.

The core writes every tile's own part (cut at the overlap midlines) to DIR/tiles/<i>_s<k>.npz, so the objects
tile the drive without doubled geometry. DIR is the user's: cancelling a job stops the core, and the tiles
it finished stay there, so the same job started again resumes (`hgca drive` skips finished tiles).
"""
from __future__ import annotations

import json
import math
import tempfile
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from typing import Any

import bpy

from . import georef, mesh_build
from .core import CoreError, Job, check_python, core_command

# Share of the progress bar: reading the scans, the tiles, merging the samples.
WEIGHTS = {"read": 0.05, "tile": 0.9, "merge": 0.05}


@dataclass
class DriveParams:
    """One drive: the scans (in trajectory order) with their poses, the folder it lives in, and the model."""

    python: str
    scans: list[str]
    out_dir: str
    poses: str | None = None
    samples: int = 1
    seed: int = 0
    stage: str = "full"
    device: str = "cpu"
    t1: int = 0                  # 0: from the weights
    max_faces: int = 0           # per tile; 0: no limit
    workers: int = 1
    tile_size: float = 38.4
    overlap: float = 6.4
    scene_name: str = ""
    run_name: str = ""
    extra_args: list[str] = field(default_factory=list)


def drive_args(params: DriveParams) -> list[str]:
    """The `hgca drive` command line (docs/CONTRACTS.md, "Drive CLI"), meshes as .npz for the add-on."""
    args = ["drive", *params.scans, "--out", params.out_dir, "--samples", str(int(params.samples)),
            "--seed", str(int(params.seed)), "--stage", params.stage, "--device", params.device,
            "--workers", str(int(params.workers)), "--size", repr(float(params.tile_size)),
            "--overlap", repr(float(params.overlap)), "--mesh-format", "npz", "--progress", "jsonl"]
    if params.poses:
        args += ["--poses", params.poses]
    if int(params.t1):
        args += ["--t1", str(int(params.t1))]
    if int(params.max_faces):
        args += ["--max-faces", str(int(params.max_faces))]
    return args + list(params.extra_args)


class DriveJob(Job):
    """A drive whose tiles become one collection in its scene."""

    def __init__(self, params: DriveParams, workdir: Path, cmd: list[str]) -> None:
        self.params = params
        self.scene_name = params.scene_name
        self.run_name = params.run_name or f"hGCA drive {datetime.now():%Y-%m-%d %H:%M:%S}"
        self.collection_name = ""
        self.tiles = 0
        super().__init__(cmd, workdir)

    def on_progress(self, stage: str, event: dict[str, Any]) -> None:
        if stage not in WEIGHTS:
            return
        step, total = event.get("step"), event.get("total")
        if not (isinstance(step, (int, float)) and isinstance(total, (int, float)) and total > 0):
            return
        names = list(WEIGHTS)
        before = sum(WEIGHTS[s] for s in names[:names.index(stage)])
        value = before + WEIGHTS[stage] * min(max(step / total, 0.0), 1.0)
        if math.isfinite(value):
            self.progress = max(self.progress, min(value, 1.0))
        if stage == "tile":
            self.tiles = int(total)
        self.status = f"{stage.capitalize()} {step}/{total}" + (f": {event['message']}" if event.get("message") else "")

    def on_success(self, outputs: list[Path]) -> None:
        scene = bpy.data.scenes.get(self.scene_name)
        if scene is None:
            raise CoreError(f"scene {self.scene_name!r} no longer exists")
        folder = Path(self.params.out_dir)
        doc = json.loads((folder / "drive.json").read_text())
        tiles = [[folder / o for o in t["outputs"]] for t in doc["tiles"]]
        self.collection_name = build_drive_results(scene, tiles, self.run_name).name

    def success_status(self) -> str:
        return f"Done: {self.tiles} tiles x {self.params.samples} sample(s) in '{self.collection_name}'"


def build_drive_results(scene: bpy.types.Scene, tiles: list[list[Path]], run_name: str) -> bpy.types.Collection:
    """A collection `run_name` with one mesh object per tile per sample ("<run> tile i sample k"); only sample 0
    visible. Every file is read and checked first; on any failure everything made here is removed."""
    arrays = [[mesh_build.read_result(p) for p in paths] for paths in tiles]
    origin = georef.scene_origin(scene)
    created = mesh_build.Created()
    try:
        collection = bpy.data.collections.new(run_name)
        created.collections.append(collection)
        material = mesh_build.observed_material(f"{run_name} observed/generated")
        created.materials.append(material)
        hidden = []
        for i, samples in enumerate(arrays):
            for k, arr in enumerate(samples):
                obj = mesh_build.result_object(f"{run_name} tile {i} sample {k}", arr, material, created, origin)
                obj["hgca_tile"], obj["hgca_sample"] = i, k
                collection.objects.link(obj)
                if k:
                    hidden.append(obj)
        scene.collection.children.link(collection)
        mesh_build.hide_in_scene(scene, hidden)
    except Exception:
        created.rollback()
        raise
    return collection


def start_drive_job(params: DriveParams) -> DriveJob:
    """Launch `hgca drive`; CoreError (nothing started) for bad parameters or a missing interpreter."""
    if not params.scene_name:
        scene = bpy.context.scene
        params.scene_name = scene.name if scene is not None else ""
    if bpy.data.scenes.get(params.scene_name) is None:
        raise CoreError(f"no scene named {params.scene_name!r}")
    check_python(params.python)
    if not params.scans:
        raise CoreError("a drive needs scan files")
    if not 1 <= int(params.samples) <= 8:
        raise CoreError(f"sample count must be 1..8, got {params.samples}")
    # the core runs in a temporary folder: every path it gets is absolute
    params.out_dir = str(Path(params.out_dir).resolve())
    params.scans = [str(Path(s).resolve()) for s in params.scans]
    params.poses = str(Path(params.poses).resolve()) if params.poses else None
    workdir = Path(tempfile.mkdtemp(prefix="hgca_drive_job_"))
    return DriveJob(params, workdir, core_command(params.python, drive_args(params)))
