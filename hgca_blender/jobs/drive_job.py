"""Drive jobs: `hgca drive` on a whole drive, its tiles shown as boxes and turned into one collection, one object per
tile per sample, as they finish.

The core plans the tiles (`hgca drive --plan-only --json`, and the `plan` record of a run: the same planner),
so the add-on only draws the regions it gets. It writes every tile's own part (cut at the overlap midlines) to
DIR/tiles/<i>_s<k>.npz and says so in a `tile` record (`state` done, or cached for a tile an earlier run
finished): the add-on queues that tile's objects, added in slices while the drive runs on (`drive_results`), so
the objects tile the drive without doubled geometry and a cancelled job keeps what it finished. DIR is the user's: cancelling stops the core (drive.json says
"interrupted"), the finished tiles stay there, and the same job started again resumes.

Inputs are scan files (batch: `--drive`) or the panel's source objects: each object goes to the core as one
.npz in world coordinates (float64: the scene's georeference origin + Blender coordinates) with its sensor
origins and, for an imported sequence, `scan_index` / `origin_index`, so the core splits it into its scans.
"""
from __future__ import annotations

import json
import math
import shutil
import tempfile
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from typing import Any

import bpy
import numpy as np

from .. import settings
from ..scene import georef, mesh_build, region, sources
from . import completion, messages
from .core import CoreError, Job, check_python, core_command, run_core_json
from .drive_results import DriveResults

# Share of the progress bar: reading the scans, the tiles, merging the samples.
WEIGHTS = {"read": 0.05, "tile": 0.9, "merge": 0.05}
CHAIN_SHARE = {"planner": (0.0, 0.02), "coarse": (0.02, 0.5), "fine": (0.5, 0.9), "mesh": (0.9, 1.0)}   # of a tile
PLAN_ROLE = "drive_plan"         # ROLE_KEY of the collection holding the planned tiles' boxes
PLAN_TIMEOUT_S = 1800
RAY_ATTRIBUTES = ("scan_index", "origin_index")   # point attributes the core uses to split scans and cast rays


@dataclass
class DriveParams:
    """One drive: the scans (in trajectory order) with their poses, the folder it lives in, and the model."""

    python: str
    scans: list[str]
    out_dir: str
    poses: str | None = None
    samples: int = settings.default("samples")     # defaults: the core's (settings)
    seed: int = settings.default("seed")
    stage: str = settings.default("stage")
    quality: str = settings.default("quality")     # `hgca drive --quality`: fast (the few-step students) or best
    device: str = settings.default("device")
    t1: int = 0                  # 0: from the weights
    t2: int = 0                  # 0: from the weights
    max_faces: int = 0           # per tile; 0: no limit
    workers: int = settings.default("drive_workers")
    tile_size: float = settings.default("drive_tile_size")
    overlap: float = settings.default("drive_overlap")
    scene_name: str = ""
    run_name: str = ""
    extra_args: list[str] = field(default_factory=list)


def drive_args(params: DriveParams) -> list[str]:
    """The `hgca drive` command line (docs/CONTRACTS.md, "Drive CLI"), meshes as .npz for the add-on."""
    values = {**completion.setting_values(params), "drive_workers": int(params.workers)}
    if not int(params.max_faces):
        values.pop("max_faces")          # a drive's tiles keep every triangle by default
    args = ["drive", *params.scans, "--out", params.out_dir, *settings.core_args(values), *_plan_args(params),
            "--mesh-format", "npz", "--progress", "jsonl"]
    return args + list(params.extra_args)


def _plan_args(params: DriveParams) -> list[str]:
    """The plan's settings (tile size and overlap, through `settings.core_args`) and the poses."""
    args = settings.core_args({"drive_tile_size": float(params.tile_size), "drive_overlap": float(params.overlap)})
    return args + (["--poses", params.poses] if params.poses else [])


# -- inputs from the scene ---------------------------------------------------------------------------

def write_object_scans(scene: bpy.types.Scene, objects: list[bpy.types.Object], folder: Path) -> list[str]:
    """Each source object as `folder/scan_NNN.npz` for the core, objects in name order (a sequence import is one
    object whose `scan_index` keeps its frames' order): world points (float64), world sensor origins, and the
    point attributes the core splits and casts rays by. An object without sensor origins is refused: a drive
    follows them."""
    paths = []
    for i, obj in enumerate(sorted(objects, key=lambda o: o.name)):
        origins = sources.world_origins([obj])
        if origins is None:
            raise CoreError(f"{obj.name!r} has no sensor origins: a drive follows the sensor, so import the scans "
                            "with their poses (or a sequence folder) through File > Import > LiDAR Scan (hgca)")
        arrays = {"points": georef.to_world(scene, sources.world_points([obj])),
                  "origins": georef.to_world(scene, origins)}
        if obj.type == "MESH":
            for name in RAY_ATTRIBUTES:
                attr = obj.data.attributes.get(name)
                if attr is not None and attr.domain == "POINT" and attr.data_type == "INT":
                    values = np.empty(len(obj.data.vertices), dtype=np.int32)
                    attr.data.foreach_get("value", values)
                    arrays[name] = values
        path = folder / f"scan_{i:03d}.npz"
        np.savez(path, **arrays)
        paths.append(str(path))
    return paths


# -- the plan: boxes along the trajectory ---------------------------------------------------------------

def plan_drive(params: DriveParams) -> dict[str, Any]:
    """The core's tiles for these scans: `hgca drive SCANS --plan-only --json` (nothing is written)."""
    check_python(params.python)
    plan = run_core_json(params.python, ["drive", *params.scans, *_plan_args(params), "--plan-only", "--json"],
                         timeout=PLAN_TIMEOUT_S)
    if not isinstance(plan.get("tiles"), list):
        raise CoreError(f"hgca drive --plan-only answered without tiles: {str(plan)[:200]}")
    return plan


def show_plan(scene: bpy.types.Scene, plan: dict[str, Any]) -> bpy.types.Collection:
    """The planned tiles as wireframe boxes (never rendered, never a source) in a collection of their own, in
    Blender coordinates; replaces the boxes an earlier plan of this scene drew (only those: the add-on's own)."""
    remove_plan(scene)
    created = mesh_build.Created()
    try:
        collection = bpy.data.collections.new("hGCA tile boxes")
        created.collections.append(collection)
        collection[mesh_build.ROLE_KEY] = PLAN_ROLE
        for tile in plan["tiles"]:
            values = tuple(float(v) for v in tile["region"])
            if len(values) != 7 or not all(math.isfinite(v) for v in values):
                raise CoreError(f"the core planned a tile with a bad region: {tile['region']!r}")
            box = region.create_region_box(collection, georef.region_to_scene(scene, values),
                                           name=f"hGCA tile {int(tile['index'])}")
            created.objects.append(box)
            created.meshes.append(box.data)
            box["hgca_tile"] = int(tile["index"])
        scene.collection.children.link(collection)
    except Exception:
        created.rollback()
        raise
    return collection


def remove_plan(scene: bpy.types.Scene) -> None:
    """Remove the tile boxes the add-on drew in `scene` (collections marked PLAN_ROLE, their boxes, meshes)."""
    for coll in list(scene.collection.children):
        if coll.get(mesh_build.ROLE_KEY) != PLAN_ROLE:
            continue
        for obj in list(coll.objects):
            mesh = obj.data if obj.get(mesh_build.ROLE_KEY) == "region" else None
            bpy.data.objects.remove(obj, do_unlink=True)
            if mesh is not None and mesh.users == 0:
                bpy.data.meshes.remove(mesh)
        bpy.data.collections.remove(coll)


def finished_tiles(folder: Path) -> list[int]:
    """The tiles drive.json lists as done (their files are written before drive.json says so)."""
    try:
        doc = json.loads((folder / "drive.json").read_text())
        return [int(t["index"]) for t in doc["tiles"] if t.get("status") == "done"]
    except (OSError, ValueError, KeyError, TypeError):
        return []


class DriveJob(Job):
    """A drive whose planned tiles appear as boxes and whose finished tiles become objects in one collection."""

    def __init__(self, params: DriveParams, workdir: Path, cmd: list[str]) -> None:
        self.params = params
        self.scene_name = params.scene_name
        self.run_name = params.run_name or f"hGCA drive {datetime.now():%Y-%m-%d %H:%M:%S}"
        self.tiles, self.tiles_done = 0, 0
        self.tile_states: dict[int, str] = {}
        self.plan_collection = ""
        scene = bpy.data.scenes[params.scene_name]
        self.results = DriveResults(scene, self.run_name)
        super().__init__(cmd, workdir)

    @property
    def collection_name(self) -> str:
        return self.results.collection_name

    def tile_paths(self, index: int) -> list[Path]:
        return [Path(self.params.out_dir) / "tiles" / f"{index}_s{k}.npz" for k in range(int(self.params.samples))]

    def on_progress(self, stage: str, event: dict[str, Any]) -> None:
        try:
            self._on_record(stage, event)
        except Exception as exc:  # a tile that cannot be loaded ends the job; the tiles loaded so far stay
            if self._stop():
                self._fail(f"could not load the results: {exc}")

    def _on_record(self, stage: str, event: dict[str, Any]) -> None:
        if stage == "plan" and isinstance(event.get("plan"), dict):
            scene = bpy.data.scenes.get(self.scene_name)
            if scene is not None:
                self.plan_collection = show_plan(scene, event["plan"]).name
            return
        tile = event.get("tile")
        if stage == "tile-step":
            self._on_step(event)
            return
        if stage == "tile" and isinstance(tile, int) and tile >= 0:
            state = str(event.get("state") or "")
            self.tile_states[tile] = state
            if state in ("done", "cached"):
                self.results.add(tile, self.tile_paths(tile))
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
            self.tiles, self.tiles_done = int(total), int(step)
            self.status = f"Tiles {step}/{total} done" + (f": {event['message']}" if event.get("message") else "")
        else:
            self.status = f"{stage.capitalize()} {step}/{total}" + (f": {event['message']}" if event.get("message")
                                                                      else "")

    def _on_step(self, event: dict[str, Any]) -> None:
        """A chain step of the tile the core runs now: the bar moves within the tile (its coarse chain the first
        half, the fine chain to 90 %, the mesh the rest), and the status names the tile and step."""
        step, total, chain = event.get("step"), event.get("total"), str(event.get("chain") or "")
        if not (isinstance(step, (int, float)) and isinstance(total, (int, float)) and total > 0 and self.tiles):
            return
        lo, hi = CHAIN_SHARE.get(chain, (0.0, 0.0))
        within = lo + (hi - lo) * min(max(step / total, 0.0), 1.0)
        value = WEIGHTS["read"] + WEIGHTS["tile"] * (self.tiles_done + within) / self.tiles
        if math.isfinite(value):
            self.progress = max(self.progress, min(value, WEIGHTS["read"] + WEIGHTS["tile"]))
        self.status = f"Tiles {self.tiles_done}/{self.tiles} done: tile {event.get('tile')} {chain} {step}/{total}"

    def _collect_finished(self) -> None:
        """Queue every tile drive.json lists as done that has no objects yet (finished since the last record)."""
        for index in finished_tiles(Path(self.params.out_dir)):
            self.results.add(index, self.tile_paths(index))

    def poll_once(self) -> bool:
        """As `core.Job.poll_once`, and first a slice of the finished tiles going in while the core runs on."""
        if self.running and self.finishing is None and self.results.pending:
            self.results.step()
            if self.results.error and self._stop():
                self._fail(f"could not load the results: {self.results.error}")
                self.publish()
                self._ended = True
                self.on_end()
                return False
            if self.results.status:
                self.status = self.results.status
        return super().poll_once()

    @property
    def inserting(self) -> bool:
        """Finished tiles are going in (the timer polls again soon)."""
        return self.results.pending

    def on_success(self, outputs: list[Path]) -> DriveResults:
        """The tiles still waiting go in over the next polls (`on_inserted` then)."""
        self._collect_finished()
        return self.results

    def on_inserted(self, results: DriveResults) -> None:
        if not self.results.collection_name:
            raise CoreError("the drive finished without tiles")
        completion.undo_push(f"hGCA: {self.run_name}")

    def success_status(self) -> str:
        return f"Done: {self.tiles} tiles x {self.params.samples} sample(s) in '{self.collection_name}'"

    def cancel(self) -> None:
        """Stop the core (its drive.json then says "interrupted"); the tiles it finished stay, as objects here
        and in DIR, where the same job started again resumes."""
        self.finishing = None      # the tiles going in are kept, not removed (core.Job._stop)
        if not self._stop():
            return
        self.state = "cancelled"
        self._collect_finished()
        self.results.run()         # the tiles the core finished, at once
        if self.results.error:     # what was loaded stays; say why the rest is missing
            self.status = f"Cancelled; some finished tiles could not be loaded: {self.results.error}"
        else:
            kept = len(self.results.tiles)
            self.status = (f"Cancelled: {kept} finished tile(s) kept" +
                           (f" in '{self.collection_name}'" if kept else "") + f"; they stay in {self.params.out_dir}")
        self.publish()

    def publish(self) -> None:
        completion.publish_state(self)

    def on_end(self) -> None:
        messages.report_job(self)


def start_drive_job(params: DriveParams, objects: list[bpy.types.Object] | None = None) -> DriveJob:
    """Launch `hgca drive` on `params.scans`, or on `objects` (the panel's sources, written to the job's temporary
    folder), and register it for its scene; CoreError (nothing started) for bad parameters, a missing
    interpreter, sources without sensor origins, or a job already running there."""
    if not params.scene_name:
        scene = bpy.context.scene
        params.scene_name = scene.name if scene is not None else ""
    scene = bpy.data.scenes.get(params.scene_name)
    if scene is None:
        raise CoreError(f"no scene named {params.scene_name!r}")
    if completion.active_job(params.scene_name) is not None:
        raise CoreError(f"a job is already running in scene {params.scene_name!r}")
    check_python(params.python)
    if not 1 <= int(params.samples) <= 8:
        raise CoreError(f"sample count must be 1..8, got {params.samples}")
    if not params.out_dir:
        raise CoreError("a drive needs a folder for its tiles")
    workdir = Path(tempfile.mkdtemp(prefix="hgca_drive_job_"))
    try:
        if objects is not None:
            params.scans = write_object_scans(scene, objects, workdir)
        if not params.scans:
            raise CoreError("a drive needs scans")
        # the core runs in the temporary folder: every path it gets is absolute
        params.out_dir = str(Path(params.out_dir).resolve())
        params.scans = [str(Path(s).resolve()) for s in params.scans]
        params.poses = str(Path(params.poses).resolve()) if params.poses else None
        job = DriveJob(params, workdir, core_command(params.python, drive_args(params)))
    except Exception:
        shutil.rmtree(workdir, ignore_errors=True)
        raise
    completion.ACTIVE[params.scene_name] = job
    job.publish()
    return job


def plan_objects(scene: bpy.types.Scene, params: DriveParams, objects: list[bpy.types.Object]) -> bpy.types.Collection:
    """Ask the core where the tiles of a drive through `objects` go and show them as boxes (writes nothing else;
    in this thread: batch runs and scripts)."""
    folder = Path(tempfile.mkdtemp(prefix="hgca_drive_plan_"))
    try:
        params.scans = write_object_scans(scene, objects, folder)
        return show_plan(scene, plan_drive(params))
    finally:
        shutil.rmtree(folder, ignore_errors=True)


def start_plan(scene: bpy.types.Scene, params: DriveParams, objects: list[bpy.types.Object]) -> None:
    """*Show Tiles* in the interface (returns at once): the scans are written here, the core plans on a thread
    (`background`), and the boxes are drawn on the main thread (`background.poll("drive_plan")` elsewhere)."""
    from . import background

    if background.busy("drive_plan"):
        raise RuntimeError("Show Tiles is still running")
    check_python(params.python)
    folder = Path(tempfile.mkdtemp(prefix="hgca_drive_plan_"))
    try:
        params.scans = write_object_scans(scene, objects, folder)
    except Exception:
        shutil.rmtree(folder, ignore_errors=True)
        raise
    scene_name = scene.name

    def work() -> dict[str, Any]:
        try:
            return plan_drive(params)
        finally:
            shutil.rmtree(folder, ignore_errors=True)

    def finish(plan: dict[str, Any]) -> str:
        collection = show_plan(bpy.data.scenes[scene_name], plan)
        return f"{len(collection.objects)} tiles in '{collection.name}'"

    background.start("drive_plan", "Show Tiles", work, finish)
