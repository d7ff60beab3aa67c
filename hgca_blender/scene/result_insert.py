"""Results put into the scene in slices, so Blender never freezes while a completion's meshes go in.

A full completion is several meshes of hundreds of thousands of faces; built in one call it held Blender's main
thread for seconds. An `Insertion` splits the work: `result_prepare` reads and computes every array on a worker
thread (numpy only), then the Blender part runs as a list of small steps (a mesh's vertices, its edges, its corners,
an attribute, the object), and each `step()` call from the job's timer runs steps only until its time budget
(`SLICE_S`) is spent. A step that would overrun what is left of the budget (by its kind's rate, measured as it
goes) waits for the next slice, so a call lasts about the budget or one large step alone (storing the face starts,
which Blender copies face by face: benchmarks/results/blender_insert.md), never the whole insertion.

Each step copies whole arrays with `foreach_set` on the mesh's attributes (position, .edge_verts, .corner_vert,
.corner_edge, material_index), the fast path: the `vertices` / `loops` / `polygons` collections copy element by
element (1.1 s for 6M corners). The mesh data is the same as `mesh_build.build_results` makes in one go; only the
edges' order differs, which in Blender's own edge calculation depends on the number of threads.

Everything made is recorded in a `mesh_build.Created`: cancel (or an error) removes it, so the file is as before.
"""
from __future__ import annotations

import threading
import time
from typing import Any, Callable

import bpy
import numpy as np

from . import mesh_build, semantics
from .result_prepare import MeshArrays, SampleArrays

SLICE_S = 0.2          # main-thread time one step() may take before it returns (plus at most one step)
# Seconds per unit of each kind of step (by its function's name), measured as the steps run in this Blender
# process: a step that would not fit what is left of a slice's budget waits for the next slice.
RATES: dict[str, float] = {}
# (units of work, what the status line says, the Blender call; what it returns, if anything, becomes `result`)
Step = tuple[int, str, Callable[[], Any]]


class Insertion:
    """Arrays made by `prepare(note)` on a worker thread (`note(text)` says what it reads), then Blender data made by `plan(arrays, created)`'s steps in
    slices of `SLICE_S` (main thread). `status` says how far ("Adding sample 2 of 3: 45 %"), `progress` is the
    share of all steps' units done (never decreasing), `result` what the last step set."""

    def __init__(self, prepare: Callable[[Callable[[str], None]], Any],
                 plan: Callable[[Any, mesh_build.Created], list[Step]]) -> None:
        self.created = mesh_build.Created()
        self.state = "reading"      # -> "adding" -> "done" | "error" | "cancelled"
        self.status, self.error, self.progress = "Reading the results", "", 0.0
        self.result: Any = None
        self.slices: list[float] = []     # seconds of each step() that made Blender data
        self.longest_step, self.longest_name = 0.0, ""    # the longest single step (seconds, its function)
        self._plan, self._steps, self._next, self._done, self._total = plan, [], 0, 0, 1
        self._label_total: dict[str, int] = {}   # units per status label ("Adding sample 2 of 3") and done
        self._label_done: dict[str, int] = {}
        self._prepared: dict[str, Any] = {}
        self._thread = threading.Thread(target=self._read, args=(prepare,), name="hgca-results", daemon=True)
        self._thread.start()

    def _read(self, prepare: Callable[[], Any]) -> None:
        try:
            self._prepared["arrays"] = prepare(self._note)
        except Exception as exc:  # noqa: BLE001  (reported on the main thread)
            self._prepared["error"] = exc

    def _note(self, text: str) -> None:
        """What the worker is reading now, for the status line (the worker's only write)."""
        if self.state == "reading":
            self.status = text

    @property
    def running(self) -> bool:
        return self.state in ("reading", "adding")

    def step(self, budget_s: float | None = None) -> bool:
        """Run steps until `budget_s` (default `SLICE_S`) is spent, measured after each step, or until the next one
        would overrun it by its kind's measured rate (never before the slice's first step); True while there is
        more to do."""
        budget_s = SLICE_S if budget_s is None else budget_s
        if self.state == "reading" and not self._begin():
            return self.running
        if self.state != "adding":
            return False
        start, ran = time.perf_counter(), False
        try:
            while self._next < len(self._steps):
                units, label, call = self._steps[self._next]
                began = time.perf_counter()
                if ran and began - start + units * RATES.get(call.__name__, 0.0) > budget_s:
                    break            # this step would overrun the budget: it starts the next slice
                ran = True
                value = call()
                took = time.perf_counter() - began
                RATES[call.__name__] = took / max(units, 1)
                if value is not None:
                    self.result = value
                if took > self.longest_step:
                    self.longest_step, self.longest_name = took, call.__name__
                self._next += 1
                self._done += units
                self._label_done[label] = self._label_done.get(label, 0) + units
                self._say(label)
                if time.perf_counter() - start >= budget_s:
                    break
        except Exception as exc:  # noqa: BLE001  (whatever failed, the file goes back to how it was)
            self._fail(exc)
            return False
        finally:
            self.slices.append(time.perf_counter() - start)
        if self._next >= len(self._steps):
            self.state, self.progress = "done", 1.0
        return self.running

    def _begin(self) -> bool:
        """Once the worker is done: its error, or the steps planned; False while it still reads."""
        if self._thread.is_alive():
            return False
        if "error" in self._prepared:
            self._fail(self._prepared["error"])
            return False
        try:
            self._steps = self._plan(self._prepared.pop("arrays"), self.created)
        except Exception as exc:  # noqa: BLE001
            self._fail(exc)
            return False
        for units, label, _ in self._steps:
            self._label_total[label] = self._label_total.get(label, 0) + units
        self._total = max(sum(u for u, _, _ in self._steps), 1)
        self.state = "adding"
        if self._steps:
            self._say(self._steps[0][1])
        return True

    def _say(self, label: str) -> None:
        self.progress = min(self._done / self._total, 1.0)
        share = self._label_done.get(label, 0) / max(self._label_total.get(label, 0), 1)
        self.status = f"{label}: {share * 100:.0f} %"

    def run(self) -> None:
        """All of it at once (no budget): cancelling a drive, which keeps its finished tiles, and scripts."""
        self._thread.join()
        while self.step(budget_s=float("inf")):
            pass

    def cancel(self) -> None:
        """Remove everything made so far; the worker's arrays are dropped when it ends."""
        if self.running:
            self.created.rollback()
            self.state, self.status = "cancelled", "Cancelled"

    def _fail(self, exc: Exception) -> None:
        self.created.rollback()
        self.error = str(exc) or type(exc).__name__      # never empty: the job tells failure by it
        self.state, self.status = "error", f"Error: {self.error}"


# -- the steps: one mesh -------------------------------------------------------------------------------------

def mesh_steps(name: str | Callable[[], str], arrays: MeshArrays, label: str, out: dict,
               created: mesh_build.Created) -> list[Step]:
    """Steps making mesh `name` (or the name it returns then) from `arrays` into `out["mesh"]`: the data
    `mesh_build.triangle_mesh` makes."""
    v, f = arrays.vertices, arrays.faces
    n_faces = len(f)

    def new() -> None:
        mesh = bpy.data.meshes.new(name if isinstance(name, str) else name())
        created.meshes.append(mesh)
        out["mesh"] = mesh
        mesh.vertices.add(len(v))

    def positions() -> None:
        out["mesh"].attributes["position"].data.foreach_set("vector", v.ravel())

    def edges() -> None:
        mesh = out["mesh"]
        mesh.edges.add(len(arrays.edges))
        if len(arrays.edges):
            mesh.attributes[".edge_verts"].data.foreach_set("value", arrays.edges.ravel())

    def corners() -> None:
        mesh = out["mesh"]
        mesh.loops.add(3 * n_faces)
        if n_faces:
            mesh.attributes[".corner_vert"].data.foreach_set("value", f.ravel())
            if arrays.corner_edge is not None:
                mesh.attributes[".corner_edge"].data.foreach_set("value", arrays.corner_edge)

    def faces() -> None:
        mesh = out["mesh"]
        mesh.polygons.add(n_faces)
        mesh.polygons.foreach_set("loop_start", np.arange(0, 3 * n_faces, 3, dtype=np.int32))
        mesh.update(calc_edges=arrays.edges is None)

    steps = [(1, label, new), (len(v), label, positions)]
    if arrays.edges is not None:
        steps.append((len(arrays.edges), label, edges))
    return steps + [(3 * n_faces, label, corners), (n_faces, label, faces)]


def attribute_steps(sample: SampleArrays, label: str, out: dict) -> list[Step]:
    """The observed/generated and agreement attributes and colours of `mesh_build.result_object`."""
    n = len(sample.mesh.vertices)

    def observed() -> None:
        mesh = out["mesh"]
        mesh.attributes.new(mesh_build.OBSERVED_ATTRIBUTE, "FLOAT", "POINT").data.foreach_set("value", sample.observed)
        mesh_build.add_color(mesh, mesh_build.OBSERVED_COLOR, sample.observed_rgba)

    def agreement() -> None:
        mesh = out["mesh"]
        mesh.attributes.new(mesh_build.AGREEMENT_ATTRIBUTE, "FLOAT", "POINT").data.foreach_set(
            "value", sample.agreement)
        mesh_build.add_color(mesh, mesh_build.AGREEMENT_COLOR, sample.agreement_rgba)

    steps = [(n, label, observed)]
    if sample.agreement is not None:
        steps.append((n, label, agreement))
    return steps


def label_steps(sample: SampleArrays, label: str, out: dict, created: mesh_build.Created) -> list[Step]:
    """`semantics.apply_labels` as steps: the class materials as slots, each face its class's slot."""
    labels, agree, names = sample.labels

    def apply() -> None:
        mesh = out["mesh"]
        present = [int(v) for v in np.unique(labels)]
        index = np.zeros(len(labels), np.int32)
        for v in present:
            mesh.materials.append(semantics.class_material(names[v], created))
            index[labels == v] = len(mesh.materials) - 1
        mesh.attributes.new("material_index", "INT", "FACE").data.foreach_set("value", index)
        mesh.attributes.new(semantics.LABEL_ATTRIBUTE, "INT", "FACE").data.foreach_set("value",
                                                                                       labels.astype(np.int32))
        if agree is not None:
            mesh.attributes.new(semantics.AGREEMENT_ATTRIBUTE, "FLOAT", "FACE").data.foreach_set(
                "value", np.ascontiguousarray(agree, dtype=np.float32))
        mesh.update()

    return [(2 * len(labels), label, apply)]


def class_part_steps(sample: SampleArrays, label: str, out: dict, created: mesh_build.Created) -> list[Step]:
    """`semantics.class_collections` as steps: each class of sample 0 an object in a child collection."""
    steps: list[Step] = []
    for part in sample.class_parts or []:
        part_out: dict = {}
        full = lambda part=part: f"{out['object'].name} {part.name}"   # noqa: E731  (the object's real name)
        steps += mesh_steps(full, part.mesh, label, part_out, created)

        def place(part=part, part_out=part_out) -> None:
            mesh = part_out["mesh"]
            mesh.materials.append(semantics.class_material(part.name, created))
            child = bpy.data.objects.new(full(part), mesh)
            created.objects.append(child)
            child.location = out["object"].location
            child[semantics.ROLE_KEY] = "result"
            child["hgca_class"] = part.name
            coll = bpy.data.collections.new(f"{out['shared']['run_name']} {part.name}")
            created.collections.append(coll)
            coll.objects.link(child)
            out["shared"]["collection"].children.link(coll)

        steps.append((1, label, place))
    return steps


def object_step(sample: SampleArrays, label: str, out: dict, shared: dict, created: mesh_build.Created,
                decimate_to: int = 0) -> Step:
    """The object of `mesh_build.result_object` with `shared["material"]`, placed and (with `decimate_to`) under a
    Decimate modifier."""
    def make() -> None:
        mesh = out["mesh"]
        mesh_build.set_active_color(mesh, mesh_build.OBSERVED_COLOR)   # after every attribute (see add_color)
        mesh.materials.append(shared["material"])
        obj = bpy.data.objects.new(sample.name, mesh)
        created.objects.append(obj)
        obj.location = [float(v) for v in sample.location]
        obj[mesh_build.ROLE_KEY] = "result"
        out["object"] = obj
        for key, value in out.get("properties", {}).items():
            obj[key] = value
        mesh_build.add_decimate(obj, decimate_to)
        shared["collection"].objects.link(obj)

    return (1, label, make)


def sample_steps(sample: SampleArrays, label: str, shared: dict, created: mesh_build.Created,
                 properties: dict, decimate_to: int = 0) -> list[Step]:
    """Every step of one result object: mesh, attributes, object (custom `properties`), labels, class parts."""
    out = {"properties": properties, "shared": shared}
    steps = mesh_steps(sample.name, sample.mesh, label, out, created) + attribute_steps(sample, label, out)
    steps.append(object_step(sample, label, out, shared, created, decimate_to))
    steps.append((0, label, lambda: shared["objects"].append(out["object"])))
    if sample.labels is not None:
        steps += label_steps(sample, label, out, created)
        steps += class_part_steps(sample, label, out, created)
    return steps


def completion_plan(scene_name: str, run_name: str, decimate_to: int = 0) -> Callable:
    """The plan of `mesh_build.build_results`: a collection `run_name` holding one object per sample, linked to
    the scene last, only sample 0 shown; `result` is the collection's name."""
    def plan(samples: list[SampleArrays], created: mesh_build.Created) -> list[Step]:
        k = len(samples)
        shared: dict = {"run_name": run_name, "objects": []}

        def begin() -> None:
            shared["collection"] = bpy.data.collections.new(run_name)
            created.collections.append(shared["collection"])
            shared["material"] = mesh_build.observed_material(f"{run_name} observed/generated")
            created.materials.append(shared["material"])

        def end() -> str:
            scene = bpy.data.scenes[scene_name]
            scene.collection.children.link(shared["collection"])
            mesh_build.hide_in_scene(scene, shared["objects"][1:])
            return shared["collection"].name

        steps: list[Step] = [(1, f"Adding sample 1 of {k}", begin)]
        for i, sample in enumerate(samples):
            steps += sample_steps(sample, f"Adding sample {i + 1} of {k}", shared, created, {"hgca_sample": i},
                                  decimate_to)
        steps.append((1, f"Adding sample {k} of {k}", end))
        return steps

    return plan


def start_completion(scene: bpy.types.Scene, outputs: list, run_name: str, decimate_to: int = 0,
                     class_collections: bool = False) -> Insertion:
    """Begin putting a completion's `outputs` into `scene` as `mesh_build.build_results` would (returns at once;
    drive it with `step()`); its `result` is the new collection's name."""
    from pathlib import Path

    from . import georef
    from .result_prepare import prepare_results

    origin = georef.scene_origin(scene)          # Blender data: read here, on the main thread
    paths = [Path(p) for p in outputs]
    return Insertion(lambda note: prepare_results(paths, origin, run_name, class_collections, note),
                     completion_plan(scene.name, run_name, int(decimate_to)))
