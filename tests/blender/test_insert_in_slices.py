"""Results go into the scene in time-bounded slices: the same mesh data as the one-go build, every slice within its
budget, progress that only rises, and cancel during insertion leaves the file exactly as it was."""
from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import bpy
import numpy as np
import pytest

from bl_helpers import addon_module, snapshot

CLASSES = np.array(["road", "sidewalk", "building", "car"])


def grid_result(path: Path, faces: int, seed: int, labels: bool = False) -> Path:
    """A wavy height field of about `faces` triangles (two per grid square) as a core result file, 1 km out."""
    n = int(np.sqrt(faces / 2)) + 1
    rng = np.random.default_rng(seed)
    xs, ys = np.meshgrid(np.arange(n) * 0.1, np.arange(n) * 0.1)
    verts = np.c_[xs.ravel(), ys.ravel(), np.sin(xs.ravel() + seed)] + rng.normal(0, 0.01, (n * n, 3))
    i = np.arange(n * n).reshape(n, n)
    a, b, c, d = i[:-1, :-1].ravel(), i[:-1, 1:].ravel(), i[1:, :-1].ravel(), i[1:, 1:].ravel()
    tris = np.r_[np.c_[a, b, d], np.c_[a, d, c]]
    tris = tris[rng.permutation(len(tris))].astype(np.int32)
    arrays = {"vertices": verts.astype(np.float32), "faces": tris, "offset": np.array([1200.5, -800.25, 3.0]),
              "observed_distance": rng.uniform(0.0, 0.5, n * n).astype(np.float32)}
    if labels:
        arrays |= {"face_label": rng.integers(0, len(CLASSES), len(tris)), "label_names": CLASSES,
                   "face_label_agreement": rng.random(len(tris)).astype(np.float32)}
    np.savez(path, **arrays)
    return path


@pytest.fixture(scope="module")
def results(tmp_path_factory: pytest.TempPathFactory) -> list[Path]:
    """Three labelled samples of ~30k triangles each."""
    folder = tmp_path_factory.mktemp("results")
    return [grid_result(folder / f"out_s{i}.npz", 30_000, i, labels=True) for i in range(3)]


def slices(insertion, budget: float = 0.02) -> list[tuple[float, str]]:
    """Drive `insertion` as the job's timer does; (progress, status) after each slice."""
    seen = []
    deadline = time.monotonic() + 120
    while insertion.step(budget):
        seen.append((insertion.progress, insertion.status))
        assert time.monotonic() < deadline, insertion.status
        time.sleep(0.002)
    seen.append((insertion.progress, insertion.status))
    return seen


def _values(attr) -> bytes:
    width = {"FLOAT_VECTOR": 3, "FLOAT2": 2, "FLOAT_COLOR": 4, "INT32_2D": 2}.get(attr.data_type, 1)
    key = {"FLOAT_VECTOR": "vector", "FLOAT2": "vector", "FLOAT_COLOR": "color"}.get(attr.data_type, "value")
    dtype = {"INT": np.int32, "INT32_2D": np.int32, "BOOLEAN": np.bool_, "INT8": np.int8}.get(attr.data_type,
                                                                                                np.float32)
    out = np.empty(len(attr.data) * width, dtype=dtype)
    attr.data.foreach_get(key, out)
    return out.tobytes()


def mesh_data(mesh: bpy.types.Mesh, run: str) -> dict:
    """Every array of `mesh` as bytes: positions, corners, face starts, each attribute (by name, domain and
    type). Edges as the set of vertex pairs with each corner's pair: Blender orders the edges it computes by
    hash tables whose number follows the thread count, so their order is no property of the result. Edge
    selection (edit-mode state) is left out: bpy 5.0's edge calculation stores `.select_edge` as two ints per edge
    it never sets, so the one-go meshes carry noise there; the sliced ones select every edge, as every vertex and
    face in both."""
    data = {(a.name, a.domain, a.data_type): _values(a) for a in mesh.attributes
            if a.domain != "EDGE" and a.name != ".corner_edge"}
    starts = np.empty(len(mesh.polygons), np.int32)
    mesh.polygons.foreach_get("loop_start", starts)
    edges = np.empty(len(mesh.edges) * 2, np.int32)
    mesh.edges.foreach_get("vertices", edges)
    edges = np.sort(edges.reshape(-1, 2), axis=1)
    corner_edge = np.empty(len(mesh.loops), np.int32)
    mesh.loops.foreach_get("edge_index", corner_edge)
    order = np.lexsort(edges.T[::-1])
    data |= {"loop_start": starts.tobytes(), "edges": edges[order].tobytes(),
             "corner_edges": edges[corner_edge].tobytes(),
             "materials": [m.name.replace(run, "RUN") for m in mesh.materials],
             "active_color": getattr(mesh.color_attributes.active_color, "name", None)}
    return data


def scene_data(coll: bpy.types.Collection, run: str) -> dict:
    """Objects of a run's collection (and its class collections) by name, with placement, properties, modifiers,
    visibility, collections and mesh data."""
    return {o.name.replace(run, "RUN"): {
        "location": tuple(o.location), "props": dict(o.items()), "hidden": (o.hide_render, o.hide_get()),
        "modifiers": [(m.type, getattr(m, "ratio", None)) for m in o.modifiers],
        "collections": sorted(c.name.replace(run, "RUN") for c in o.users_collection),
        "mesh": mesh_data(o.data, run)} for o in coll.all_objects}


def test_sliced_insertion_is_the_one_go_mesh_byte_for_byte(addon, results: list[Path]) -> None:
    mesh_build, result_insert = addon_module("scene.mesh_build"), addon_module("scene.result_insert")
    scene = bpy.context.scene
    scene["hgca_origin"] = (1000.0, -1000.0, 0.0)
    one_go = mesh_build.build_results(scene, results, "run A", decimate_to=20_000, class_collections=True)
    insertion = result_insert.start_completion(scene, results, "run B", decimate_to=20_000, class_collections=True)
    slices(insertion)
    assert insertion.state == "done", insertion.error
    sliced = bpy.data.collections[insertion.result]
    a, b = scene_data(one_go, "run A"), scene_data(sliced, "run B")
    assert sorted(a) == sorted(b) and len(a) == 3 + len(CLASSES)   # 3 samples, sample 0's classes
    for name in a:
        for key in a[name]["mesh"].keys() | b[name]["mesh"].keys():
            assert a[name]["mesh"].get(key) == b[name]["mesh"].get(key), (name, key)
        assert a[name] == b[name], name
    assert not any(o.data.validate() for o in sliced.all_objects), "nothing for Blender to correct"
    for obj in sliced.all_objects:
        selected = np.empty(len(obj.data.edges), bool)
        obj.data.edges.foreach_get("select", selected)
        assert selected.all()
    assert [c.name for c in scene.collection.children][-2:] == ["run A", "run B"]


def test_empty_and_degenerate_results_match_the_one_go_build_too(addon, tmp_path: Path) -> None:
    """No faces at all, and a face that repeats a vertex (Blender then computes the edges itself)."""
    mesh_build, result_insert = addon_module("scene.mesh_build"), addon_module("scene.result_insert")
    verts = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], np.float32)
    empty, degenerate = tmp_path / "empty.npz", tmp_path / "degenerate.npz"
    np.savez(empty, vertices=verts, faces=np.zeros((0, 3), np.int32))
    np.savez(degenerate, vertices=verts, faces=np.array([[0, 1, 2], [1, 3, 3]], np.int32))
    for path in (empty, degenerate):
        one_go = mesh_build.build_results(bpy.context.scene, [path], "run A")
        insertion = result_insert.start_completion(bpy.context.scene, [path], "run B")
        slices(insertion)
        assert insertion.state == "done", insertion.error
        assert scene_data(one_go, "run A") == scene_data(bpy.data.collections[insertion.result], "run B"), path.name


def test_every_slice_stays_within_its_budget(addon, tmp_path: Path) -> None:
    """A slice ends after the step that spends its budget: never longer than budget + the longest step, which is
    one copy into one mesh (the face starts: ~85 ns a face), so the bound holds on any CPU."""
    result_insert = addon_module("scene.result_insert")
    paths = [grid_result(tmp_path / f"out_s{i}.npz", 60_000, i) for i in range(3)]
    insertion = result_insert.start_completion(bpy.context.scene, paths, "hGCA slices")
    budget = 0.01
    slices(insertion, budget)
    assert insertion.state == "done", insertion.error
    assert len(insertion.slices) > 3, "the work was split"
    assert max(insertion.slices) <= budget + insertion.longest_step + 0.005
    assert max(insertion.slices) < 1.0, "a generous absolute bound: 180k triangles in all"
    units = [u for u, _, _ in insertion._steps]
    assert max(units) <= 4 * 60_000, "no step copies more than one array of one mesh"


def test_cancel_mid_insertion_leaves_the_scene_as_it_was(addon, results: list[Path]) -> None:
    result_insert, semantics = addon_module("scene.result_insert"), addon_module("scene.semantics")
    bpy.ops.mesh.primitive_cube_add()                       # the user's own data, which must stay as it is
    semantics.class_material("road")["hgca_mine"] = 1       # a class material already in the file is reused
    before = snapshot()
    insertion = result_insert.start_completion(bpy.context.scene, results, "hGCA cancel", class_collections=True)
    while insertion.step(0.005) and len(insertion.created.objects) < 2:
        pass
    assert insertion.state == "adding" and len(insertion.created.objects) >= 2 and insertion.created.meshes
    insertion.cancel()
    assert insertion.state == "cancelled" and not insertion.step()
    assert snapshot() == before
    assert bpy.data.materials["hGCA road"]["hgca_mine"] == 1


def test_progress_rises_to_100_percent_sample_by_sample(addon, results: list[Path]) -> None:
    result_insert = addon_module("scene.result_insert")
    insertion = result_insert.start_completion(bpy.context.scene, results, "hGCA progress")
    seen = slices(insertion, budget=0.002)
    values = [p for p, _ in seen]
    assert all(b >= a for a, b in zip(values, values[1:])) and values[-1] == 1.0
    assert len(set(values)) > 5, "the bar moves through the insertion"
    adding = [s for _, s in seen if s.startswith("Adding")]
    samples = [int(s.split()[2]) for s in adding]
    assert samples == sorted(samples) and set(samples) == {1, 2, 3}
    for k in (1, 2, 3):
        shares = [int(s.rsplit(": ", 1)[1].rstrip(" %")) for s in adding if s.startswith(f"Adding sample {k} of 3")]
        assert shares == sorted(shares), shares
    assert seen[-1][1] == "Adding sample 3 of 3: 100 %"


def fake_job(jobs, results: list[Path], workdir: Path, scene: bpy.types.Scene):
    """A completion job whose "core" only reports `results` done (copied into its folder, which the job owns)."""
    workdir.mkdir()
    outputs = []
    for p in results:
        (workdir / p.name).write_bytes(p.read_bytes())
        outputs.append(p.name)
    record = {"protocol": 1, "stage": "done", "outputs": outputs}
    params = jobs.CompletionParams(python=sys.executable, points=np.zeros((1, 3)), region=(0, 0, 0, 1, 1, 1, 0),
                                   samples=len(results), scene_name=scene.name, run_name="hGCA job")
    job = jobs.CompletionJob(params, workdir, [sys.executable, "-c", f"print({json.dumps(json.dumps(record))})"])
    jobs.ACTIVE[scene.name] = job
    return job


def test_a_job_runs_on_while_its_results_go_in_and_cancel_removes_them(addon, results: list[Path],
                                                                          tmp_path: Path, monkeypatch) -> None:
    jobs = addon_module("jobs.completion")
    monkeypatch.setattr(addon_module("scene.result_insert"), "SLICE_S", 0.002)   # many slices of these small meshes
    job = fake_job(jobs, results, tmp_path / "one", bpy.context.scene)
    statuses = []
    while job.poll_once():
        statuses.append(job.status)
        time.sleep(0.005)
    assert job.state == "done", job.error
    assert any(s.startswith("Adding sample 2 of 3: ") for s in statuses) and statuses.index(
        next(s for s in statuses if s.startswith("Adding"))) < len(statuses) - 1, "the status moves while adding"
    assert len(bpy.data.collections[job.collection_name].objects) == 3 and not job.workdir.exists()
    assert job.status == f"Done: 3 samples in '{job.collection_name}'"

    bpy.ops.wm.read_homefile(use_empty=True)
    before = snapshot()
    job = fake_job(jobs, results, tmp_path / "two", bpy.context.scene)
    while job.poll_once() and not (job.finishing is not None and job.finishing.created.objects):
        time.sleep(0.005)
    assert job.running and job.finishing.state == "adding", "cancelled while the results go in"
    assert bpy.ops.hgca.cancel() == {"FINISHED"}
    assert job.state == "cancelled" and jobs.active_job(bpy.context.scene.name) is None
    assert snapshot() == before and not job.workdir.exists()


def test_drive_tiles_go_in_slice_by_slice_and_cancel_removes_only_the_half_added_one(addon, tmp_path: Path) -> None:
    drive_results = addon_module("jobs.drive_results")
    tiles = {i: [grid_result(tmp_path / f"{i}_s{k}.npz", 20_000, 10 * i + k) for k in range(2)] for i in range(3)}
    before = snapshot()
    results = drive_results.DriveResults(bpy.context.scene, "hGCA drive")
    for i in (0, 1, 0):                                  # a tile reported twice goes in once
        results.add(i, tiles[i])
    statuses = []
    while results.step(0.002) and not results.tiles:
        statuses.append(results.status)
    assert results.tiles == {0} and any(s.startswith("Adding tile 0: ") for s in statuses)
    coll = bpy.data.collections[results.collection_name]
    assert sorted((o["hgca_tile"], o["hgca_sample"]) for o in coll.objects) == [(0, 0), (0, 1)]
    kept = snapshot()
    while results.current is None or not results.current.created.objects:      # tile 1 half added
        results.step(0.002)
    results.cancel()
    assert not results.pending and snapshot() == kept and kept != before

    damaged = tmp_path / "2_s1.npz"
    np.savez(damaged, vertices=np.zeros((3, 3), np.float32), faces=np.array([[0, 1, 5]]))
    results.add(2, tiles[2])
    while results.step(0.002):
        pass
    assert "tile 2" in results.error and "out of range" in results.error
    assert snapshot() == kept, "the failed tile is removed whole; tile 0 stays"


def test_a_damaged_result_fails_the_job_and_adds_nothing(addon, results: list[Path], tmp_path: Path) -> None:
    jobs = addon_module("jobs.completion")
    bad = tmp_path / "out_s2.npz"
    np.savez(bad, vertices=np.zeros((3, 3), np.float32), faces=np.array([[0, 1, 7]], np.int32))
    before = snapshot()
    job = fake_job(jobs, [*results[:2], bad], tmp_path / "job", bpy.context.scene)
    while job.poll_once():
        time.sleep(0.005)
    assert job.state == "error" and "could not load the results" in job.error and "out of range" in job.error
    assert snapshot() == before and not job.workdir.exists()
