"""File > Import > LiDAR Scan (hgca) on real sensor files, through the registered operator."""
from __future__ import annotations

import json
from pathlib import Path

import bpy
import numpy as np
import pytest

from bl_helpers import FIXTURES, NUSCENES, addon_module, core_arrays, prefs, require_fixture, snapshot

LAS_FILES = ["simple.las", "simple.laz", "simple1_4.las", "plane.laz", "simple.copc.laz", "autzen_trim.laz"]


def world_vertices(obj: bpy.types.Object) -> np.ndarray:
    """World coordinates as the add-on defines them: the scene's georeference origin + Blender's."""
    co = np.empty(len(obj.data.vertices) * 3, dtype=np.float32)
    obj.data.vertices.foreach_get("co", co)
    m = np.array(obj.matrix_world)
    origin = np.array(bpy.context.scene.get("hgca_origin", (0.0, 0.0, 0.0)), dtype=np.float64)
    return co.reshape(-1, 3).astype(np.float64) @ m[:3, :3].T + m[:3, 3] + origin


def new_objects(before: dict) -> list[bpy.types.Object]:
    return [o for o in bpy.data.objects if o.name not in before["objects"]]


def nuscenes_points(path: Path) -> np.ndarray:
    """(N, 4) x, y, z, intensity of the sweep as the core reads it: the file's rows less the returns off the
    nuScenes car (`hgca_core.io.sensor_bin`, tested against the raw file in tests/io)."""
    got = core_arrays(f"from hgca_core.io import read_scan; s = read_scan({str(path)!r})",
                      p="s.points", i="s.attributes['intensity']")
    return np.column_stack([got["p"], got["i"]])


def test_import_nuscenes_sweep(addon) -> None:
    path = require_fixture(NUSCENES)
    raw = nuscenes_points(path)
    before = snapshot()
    assert bpy.ops.import_scene.hgca_lidar(filepath=str(path)) == {"FINISHED"}
    (obj,) = new_objects(before)
    mesh = obj.data
    assert len(mesh.vertices) == len(raw) < 0.8 * (path.stat().st_size // 20)   # the car's own returns left out
    assert len(mesh.polygons) == 0 and obj.get("hgca_role") == "scan"
    np.testing.assert_allclose(world_vertices(obj), raw[:, :3], atol=1e-4)
    for name in ("intensity", "scan_index"):
        attr = mesh.attributes[name]
        assert attr.domain == "POINT" and len(attr.data) == len(raw)
    intensity = np.empty(len(raw), dtype=np.float32)
    mesh.attributes["intensity"].data.foreach_get("value", intensity)
    np.testing.assert_allclose(intensity, raw[:, 3], rtol=1e-6)
    assert obj.modifiers["hGCA Points"].node_group.name.startswith("hGCA Points")
    # what the import reports: the rows the reader left out, counted against the file's own rows (20 bytes each)
    ops = addon_module("operators.import_scans")
    *_, dropped = ops.read_scans(addon_module("preferences").core_python(), [path])
    left = path.stat().st_size // 20 - len(raw)
    assert left > 0 and dropped == {"returns off the recording vehicle": left}
    assert ops.dropped_text(dropped) == f"left out {left:,} returns off the recording vehicle"
    assert ops.dropped_text({}) == ""


@pytest.mark.parametrize("name", LAS_FILES)
def test_import_las_family(addon, name: str) -> None:
    import laspy

    path = require_fixture(FIXTURES / name)
    las = laspy.read(path)
    held = np.column_stack([np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)])
    before = snapshot()
    assert bpy.ops.import_scene.hgca_lidar(filepath=str(path)) == {"FINISHED"}
    (obj,) = new_objects(before)
    assert len(obj.data.vertices) == len(held)
    # georeferenced coordinates (these aerial scans lie at x ~ 600 km, y ~ 850 km) stay exact to the mm
    assert np.abs(world_vertices(obj) - held).max() < 1e-3
    if np.abs(held).max() > 1e4:  # Blender's float32 numbers stay small: the scene origin holds the rest
        assert np.abs(np.array(obj.location)).max() < 1e4
        assert np.abs(np.array([v.co for v in obj.data.vertices[:10]])).max() < 1e4
        assert np.abs(np.array(bpy.context.scene["hgca_origin"])).max() > 1e4


def test_import_several_files_accumulates_with_scan_index(addon) -> None:
    a, b = require_fixture(FIXTURES / "simple.las"), require_fixture(FIXTURES / "simple.laz")
    before = snapshot()
    result = bpy.ops.import_scene.hgca_lidar(directory=str(a.parent), files=[{"name": a.name}, {"name": b.name}])
    assert result == {"FINISHED"}
    (obj,) = new_objects(before)
    assert obj.name == "simple +1"
    idx = np.empty(len(obj.data.vertices), dtype=np.int32)
    obj.data.attributes["scan_index"].data.foreach_get("value", idx)
    assert len(idx) == 2 * 1065 and np.bincount(idx).tolist() == [1065, 1065]


def test_import_with_poses_moves_the_scan(addon, tmp_path: Path) -> None:
    path = require_fixture(NUSCENES)
    pose = np.eye(4)
    pose[:3, 3] = (100.0, -20.0, 3.0)
    poses = tmp_path / "poses.json"
    poses.write_text(json.dumps({"scans": [{"file": path.name, "pose": pose.tolist()}]}))
    before = snapshot()
    assert bpy.ops.import_scene.hgca_lidar(filepath=str(path), poses_path=str(poses)) == {"FINISHED"}
    (obj,) = new_objects(before)
    np.testing.assert_allclose(world_vertices(obj), nuscenes_points(path)[:, :3] + pose[:3, 3], atol=1e-4)


def test_bad_file_reports_error_and_adds_nothing(addon, tmp_path: Path) -> None:
    bad = tmp_path / "broken.las"
    bad.write_bytes(b"LASF" + b"\x00" * 50)
    before = snapshot()
    with pytest.raises(RuntimeError, match="broken.las"):
        bpy.ops.import_scene.hgca_lidar(filepath=str(bad))
    assert snapshot() == before


def test_missing_file_reports_error_and_adds_nothing(addon, tmp_path: Path) -> None:
    before = snapshot()
    with pytest.raises(RuntimeError, match="file not found"):
        bpy.ops.import_scene.hgca_lidar(filepath=str(tmp_path / "nope.ply"))
    assert snapshot() == before


def test_interpreter_without_core_reports_error(addon, tmp_path: Path) -> None:
    path = require_fixture(NUSCENES)
    fake = tmp_path / "python"
    fake.symlink_to("/usr/bin/python3")  # a real interpreter that has no hgca_core
    prefs().python_path = str(fake)
    before = snapshot()
    with pytest.raises(RuntimeError, match="hgca_core"):
        bpy.ops.import_scene.hgca_lidar(filepath=str(path))
    assert snapshot() == before


def test_attribute_conversion_keeps_types(addon) -> None:
    mesh_build = addon_module("scene.mesh_build")
    coll = bpy.context.scene.collection
    pts = np.random.default_rng(0).normal(size=(100, 3))
    attrs = {"intensity": np.linspace(0, 1, 100), "scan_index": np.arange(100, dtype=np.uint8) % 3,
             "position": np.ones(100), "flag": np.arange(100) % 2 == 0, "origins": np.zeros((2, 3))}
    obj, skipped = mesh_build.build_point_object("pts", pts, attrs, coll, show_points=False)
    attributes = obj.data.attributes
    assert skipped == ["origins"]
    assert attributes["intensity"].data_type == "FLOAT" and attributes["scan_index"].data_type == "INT"
    assert attributes["flag"].data_type == "BOOLEAN" and attributes["hgca_position"].data_type == "FLOAT"
    values = np.empty(100, dtype=np.int32)
    attributes["scan_index"].data.foreach_get("value", values)
    assert values.tolist() == (np.arange(100) % 3).tolist()


AV2_LOG = FIXTURES / "av2" / "7fab2350-7eaf-3b7e-a39d-6937a4c1bede"


def test_import_av2_sequence_folder(addon) -> None:
    """A sequence folder goes through `hgca read FOLDER --frames`: both sweeps, placed with the log's poses."""
    if not AV2_LOG.is_dir():
        pytest.skip(f"real AV2 log missing: {AV2_LOG}")
    # the core's own reading, in the core's interpreter (the LTS venvs have no pyarrow)
    want = core_arrays(f"from hgca_core.io.sequence import read_sequence; s = read_sequence({str(AV2_LOG)!r}, '0:2')",
                       points="s.points", scan_index="s.attributes['scan_index']")
    before = snapshot()
    assert bpy.ops.import_scene.hgca_lidar(directory=str(AV2_LOG) + "/", frames="0:2") == {"FINISHED"}
    (obj,) = new_objects(before)
    assert obj.name == f"{AV2_LOG.name} [0:2]"
    assert len(obj.data.vertices) == len(want["points"]) == 99229 + 99466
    # city coordinates (km): the scene's georeference origin takes them, float32 vertices stay good to a few mm
    assert np.abs(np.array(bpy.context.scene["hgca_origin"])).max() > 1e3
    np.testing.assert_allclose(world_vertices(obj), want["points"], atol=0.01)
    idx = np.empty(len(want["points"]), dtype=np.int32)
    obj.data.attributes["scan_index"].data.foreach_get("value", idx)
    assert np.bincount(idx).tolist() == np.bincount(want["scan_index"]).tolist() == [99229, 99466]


def test_import_sequence_errors_add_nothing(addon, tmp_path: Path) -> None:
    if not AV2_LOG.is_dir():
        pytest.skip(f"real AV2 log missing: {AV2_LOG}")
    before = snapshot()
    with pytest.raises(RuntimeError, match="selects no frame"):
        bpy.ops.import_scene.hgca_lidar(directory=str(AV2_LOG) + "/", frames="5:9")
    with pytest.raises(RuntimeError, match="not a known sequence layout"):
        bpy.ops.import_scene.hgca_lidar(directory=str(tmp_path) + "/")
    path = require_fixture(NUSCENES)
    with pytest.raises(RuntimeError, match="frames apply to a sequence folder"):
        bpy.ops.import_scene.hgca_lidar(filepath=str(path), frames="0:1")
    assert snapshot() == before
