"""A drive's finished tiles as objects in one collection, added in slices while the drive runs on.

The core says a tile is done (or cached) and its files are on disk; the tile waits in a queue here, and each poll of
the job adds a slice of it (`result_insert`: its files read on a worker thread, the Blender part in steps of at most
`SLICE_S`), so a drive of many large tiles never freezes Blender. One object per tile per sample ("<run> tile i
sample k", custom properties hgca_tile / hgca_sample); only sample 0 shows. A tile that fails to load is removed
again whole, and the error ends the job; tiles already added stay.
"""
from __future__ import annotations

from collections import deque
from pathlib import Path

import bpy

from ..scene import georef, mesh_build, result_insert
from ..scene.result_prepare import SampleArrays, prepare_tile
from .core import CoreError


class DriveResults:
    """The drive's collection in its scene (made at the first finished tile) and the tiles waiting to go in. Also
    the job's `finishing` once the core is done: `step()` is True while tiles wait."""

    def __init__(self, scene: bpy.types.Scene, run_name: str) -> None:
        self.scene_name = scene.name
        self.run_name = run_name
        self.collection_name = ""
        self.material_name = ""
        self.tiles: set[int] = set()
        self.queue: deque[tuple[int, list[Path]]] = deque()
        self.current: result_insert.Insertion | None = None
        self.current_index = -1
        self.status, self.error = "", ""

    @property
    def pending(self) -> bool:
        return self.current is not None or bool(self.queue)

    def add(self, index: int, paths: list[Path]) -> None:
        """Queue tile `index` (its sample files); a tile added or queued already is left alone."""
        if index in self.tiles or index == self.current_index or any(i == index for i, _ in self.queue):
            return
        self.queue.append((index, [Path(p) for p in paths]))

    def step(self, budget_s: float | None = None) -> bool:
        """One slice of the tile going in (the next one started when none is); True while tiles wait. A tile that
        cannot be loaded is removed again, `error` says why and nothing more is added."""
        if self.error:
            return False
        try:
            if self.current is None:
                if not self.queue:
                    return False
                self._start(*self.queue.popleft())
        except Exception as exc:  # noqa: BLE001  (a scene gone, a broken origin)
            self.error = str(exc)
            self.cancel()
            return False
        insertion = self.current
        if insertion.step(budget_s):
            self.status = insertion.status if insertion.state == "adding" else f"Reading tile {self.current_index}"
            return True
        self.current, index, self.current_index = None, self.current_index, -1
        if insertion.state != "done":
            self.error = f"tile {index}: {insertion.error or insertion.state}"
            self.cancel()
            return False
        self.collection_name, self.material_name = insertion.result
        self.tiles.add(index)
        return self.pending

    def run(self) -> None:
        """Every queued tile at once (cancelling keeps the tiles the core finished)."""
        while self.pending and not self.error:
            if self.current is not None:
                self.current.run()
            self.step(float("inf"))

    def cancel(self) -> None:
        """Stop adding: the tile half added is removed, the queue dropped; finished tiles stay."""
        if self.current is not None:
            self.current.cancel()
        self.current, self.current_index = None, -1
        self.queue.clear()

    def _start(self, index: int, paths: list[Path]) -> None:
        scene = bpy.data.scenes.get(self.scene_name)
        if scene is None:
            raise CoreError(f"scene {self.scene_name!r} no longer exists")
        origin, run_name = georef.scene_origin(scene), self.run_name
        self.current_index = index
        self.current = result_insert.Insertion(lambda note: prepare_tile(paths, origin, run_name, index),
                                               lambda samples, created: self._plan(index, samples, created))

    def _plan(self, index: int, samples: list[SampleArrays], created: mesh_build.Created) -> list:
        """`mesh_build.result_object` per sample in the run's collection (made and linked at the first tile)."""
        shared: dict = {"run_name": self.run_name, "objects": []}
        label = f"Adding tile {index}"

        def begin() -> None:
            scene = bpy.data.scenes[self.scene_name]
            collection = bpy.data.collections.get(self.collection_name) if self.collection_name else None
            if collection is None:
                collection = bpy.data.collections.new(self.run_name)
                created.collections.append(collection)
                scene.collection.children.link(collection)
            material = bpy.data.materials.get(self.material_name) if self.material_name else None
            if material is None:
                material = mesh_build.observed_material(f"{self.run_name} observed/generated")
                created.materials.append(material)
            shared["collection"], shared["material"] = collection, material

        def end() -> tuple[str, str]:
            mesh_build.hide_in_scene(bpy.data.scenes[self.scene_name], shared["objects"][1:])
            return shared["collection"].name, shared["material"].name

        steps = [(1, label, begin)]
        for k, sample in enumerate(samples):
            steps += result_insert.sample_steps(sample, label, shared, created, {"hgca_tile": index, "hgca_sample": k})
        return steps + [(1, label, end)]
