"""A drive folder is never trusted blindly on resume: each finished tile records what it was made from and the
sha256 of its files; a tile mesh cut short, a tile of another drive copied over a cache entry, a cache entry
whose faces index past its vertices, an earlier plan's meshes (another --size) and a hand-edited drive.json are
each caught, said in one warning, and made again, so that the resumed drive is byte for byte the drive an
uninterrupted run writes."""
from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

import hgca_core
from drive_data import write_drive
from hgca_core.errors import HgcaWarning
from hgca_core.tiling.store import DriveStore

SMALL = {"size": 12.8, "overlap": 3.2, "stage": "coarse", "t1": 3, "threads": 1}
CLI_SMALL = ["--size", "12.8", "--overlap", "3.2", "--stage", "coarse", "--t1", "3", "--threads", "1"]


def sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def meshes(out: Path) -> dict[str, bytes]:
    """Every mesh a drive folder shows people: the merged ones and the tiles'."""
    return {p.relative_to(out).as_posix(): p.read_bytes() for p in [*out.glob("drive_s*"), *out.glob("tiles/*")]}


@pytest.fixture(scope="module")
def street(tmp_path_factory):
    """16 m of street: two 12.8 m tiles (the second conditioned on the first)."""
    return write_drive(tmp_path_factory.mktemp("street"), length=16.0)


@pytest.fixture(scope="module")
def finished(street, drive_weights, tmp_path_factory):
    scans, poses = street
    out = tmp_path_factory.mktemp("finished") / "drive"
    doc = hgca_core.drive(scans, out, poses=poses, weights=str(drive_weights), **SMALL)
    assert len(doc["tiles"]) == 2
    return out, doc, meshes(out)


@pytest.fixture
def copy(finished, tmp_path):
    out = tmp_path / "drive"
    shutil.copytree(finished[0], out, copy_function=shutil.copy2)   # the shared drive stays as it was
    return out


def rerun(street, weights, out, capsys, *extra) -> tuple[dict, list[str]]:
    """`hgca drive` again on `out` (in process, as a user would run it); drive.json and the warning lines."""
    from hgca_core.cli import main

    scans, poses = street
    code = main(["drive", *map(str, scans), "--poses", str(poses), "--weights", str(weights), *CLI_SMALL, *extra,
                 "--out", str(out), "--progress", "none"])
    err = capsys.readouterr().err
    assert code == 0 and "Traceback" not in err and "error:" not in err, err
    return json.loads((out / "drive.json").read_text()), [line for line in err.splitlines() if "warning:" in line]


def test_each_finished_tile_records_what_it_was_made_from_and_its_checksums(finished, street, drive_weights, copy,
                                                                          capsys):
    out, doc, _ = finished
    for t in doc["tiles"]:
        entry = out / "cache" / f"{t['key']}.npz"
        assert t["sha256"] == {f"cache/{entry.name}": sha256(entry), **{o: sha256(out / o) for o in t["outputs"]}}
        made = t["made_from"]
        assert DriveStore(out).load(t["key"])["made_from"] == made, "the cache entry carries it too"
        assert made["region"] == t["region"] and made["scans"] == t["scans"] and made["seed"] == t["seeds"][0]
        assert made["scans_sha256"] == [doc["scans"][i]["sha256"] for i in t["scans"]]
        assert made["weights_sha256"] == doc["settings"]["weights_sha256"]
        assert made["conditioned_on"] == [doc["tiles"][j]["key"] for j in t["conditioned_on"]]
    # a folder whose files all check out is reused as it is, without a word
    mtimes = {p.name: p.stat().st_mtime_ns for p in (copy / "cache").iterdir()}
    again, warned = rerun(street, drive_weights, copy, capsys)
    assert warned == [] and again["timings"]["tiles_computed"] == 0
    assert {p.name: p.stat().st_mtime_ns for p in (copy / "cache").iterdir()} == mtimes
    assert [t["sha256"] for t in again["tiles"]] == [t["sha256"] for t in doc["tiles"]]


def test_a_tile_mesh_cut_short_is_written_again(finished, street, drive_weights, copy, capsys):
    mesh = copy / "tiles" / "1_s0.ply"
    whole = mesh.read_bytes()
    mesh.write_bytes(whole[: len(whole) // 2])
    doc, warned = rerun(street, drive_weights, copy, capsys)
    assert len(warned) == 1 and "tile 1: its mesh tiles/1_s0.ply does not match its checksum" in warned[0], warned
    assert doc["timings"]["tiles_computed"] == 0, "the mesh is written again from the checked finished tile"
    assert meshes(copy) == finished[2]


@pytest.fixture(scope="module")
def other_drive_entry(drive_weights, tmp_path_factory):
    """The one finished tile of another (shorter, other) drive."""
    root = tmp_path_factory.mktemp("other")
    scans, poses = write_drive(root / "scans", length=8.0, seed=5)
    doc = hgca_core.drive(scans, root / "drive", poses=poses, weights=str(drive_weights), **SMALL)
    return root / "drive" / "cache" / f"{doc['tiles'][0]['key']}.npz"


def test_a_tile_of_another_drive_copied_over_a_cache_entry_is_recomputed(finished, street, drive_weights, copy,
                                                                        capsys, other_drive_entry):
    entry = copy / "cache" / f"{finished[1]['tiles'][0]['key']}.npz"
    shutil.copy2(other_drive_entry, entry)
    doc, warned = rerun(street, drive_weights, copy, capsys)
    assert len(warned) == 1 and "tile 0: its finished result" in warned[0] and "another tile" in warned[0], warned
    assert doc["timings"]["tiles_computed"] == 1 and doc["tiles"][1]["run"] == 1, "only tile 0 ran again"
    assert meshes(copy) == finished[2]


def test_a_cache_entry_whose_faces_index_past_its_vertices_is_recomputed(finished, street, drive_weights, copy,
                                                                        capsys):
    key = finished[1]["tiles"][0]["key"]
    entry = copy / "cache" / f"{key}.npz"
    with np.load(entry) as z:
        arrays = dict(z)
    arrays["s0_faces"][0, 0] = len(arrays["s0_vertices"]) + 7
    np.savez(entry, **arrays)
    record = json.loads((copy / "drive.json").read_text())      # a record that agrees (as an older drive's would)
    record["tiles"][0].setdefault("sha256", {})[f"cache/{key}.npz"] = sha256(entry)
    (copy / "drive.json").write_text(json.dumps(record))
    doc, warned = rerun(street, drive_weights, copy, capsys)
    assert len(warned) == 1 and "tile 0: its finished result" in warned[0], warned
    assert "faces that index past its vertices" in warned[0], warned
    assert doc["timings"]["tiles_computed"] == 1
    assert meshes(copy) == finished[2]


def test_another_size_leaves_only_this_plans_tiles(finished, street, drive_weights, copy, tmp_path, monkeypatch):
    from hgca_core.tiling.runners import LocalRunner

    scans, poses = street
    bigger = {**SMALL, "size": 22.4}                                   # one tile where there were two
    def stopped(*args, **kwargs):
        raise KeyboardInterrupt
    monkeypatch.setattr(LocalRunner, "run", stopped)
    with pytest.warns(HgcaWarning, match=r"removing 3 mesh file.*2 tiles of 12\.8 m.*1 of 22\.4 m") as caught:
        with pytest.raises(KeyboardInterrupt):
            hgca_core.drive(scans, copy, poses=poses, weights=str(drive_weights), **bigger)
    assert len([w for w in caught if issubclass(w.category, HgcaWarning)]) == 1
    # stopped before its one tile was done: no mesh of the earlier plan stays under a name this drive writes
    assert list((copy / "tiles").iterdir()) == [] and not list(copy.glob("drive_s*"))
    monkeypatch.undo()
    doc = hgca_core.drive(scans, copy, poses=poses, weights=str(drive_weights), **bigger)
    assert len(doc["tiles"]) == 1 and doc["timings"]["tiles_computed"] == 1
    fresh = hgca_core.drive(scans, tmp_path / "fresh", poses=poses, weights=str(drive_weights), **bigger)
    assert [t["key"] for t in fresh["tiles"]] == [t["key"] for t in doc["tiles"]]
    assert meshes(copy) == meshes(tmp_path / "fresh") and set(meshes(copy)) == {"drive_s0.ply", "tiles/0_s0.ply"}


def _set(path: str, value):
    def edit(doc: dict) -> None:
        *parents, last = path.split(".")
        for name in parents:
            doc = doc[int(name)] if isinstance(doc, list) else doc[name]
        doc[last] = value
    return edit


def _drop(doc: dict) -> None:
    del doc["tiles"][0]["status"]


@pytest.mark.parametrize("edit, named", [
    (_set("runs", None), "runs is null"),
    (_set("tiles.0.key", ["a", "list"]), "tiles[0].key is a list"),
    (_set("runs", "1"), "runs is a string"),
    (_set("tiles.1.faces", ["100344"]), "tiles[1].faces[0] is a string"),
    (_drop, "tiles[0].status is missing"),
    ("cut", "not JSON"),
], ids=["runs-null", "key-list", "runs-string", "faces-strings", "status-missing", "cut-short"])
def test_an_edited_drive_json_is_one_warning_naming_the_key_and_the_drive_is_the_same(
        finished, street, drive_weights, copy, capsys, edit, named):
    path = copy / "drive.json"
    if edit == "cut":
        text = path.read_text()
        path.write_text(text[: len(text) // 2])
    else:
        doc = json.loads(path.read_text())
        edit(doc)
        path.write_text(json.dumps(doc))
    doc, warned = rerun(street, drive_weights, copy, capsys)
    assert len(warned) == 1 and "drive.json" in warned[0] and named in warned[0], warned
    assert doc["timings"]["tiles_computed"] == 0, "the cached tiles checked out on their own"
    from hgca_core.tiling.records import check_record

    assert check_record(doc) == "" and doc["runs"] == 1, "a new record"
    assert meshes(copy) == finished[2]
