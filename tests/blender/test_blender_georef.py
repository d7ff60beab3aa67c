"""Georeferenced scans in Blender: imported, shown, sent to the core and completed to the mm (issue 11, item 3).

Blender keeps vertices and locations in float32 (1 m spacing at y ~ 1e7 m); the add-on keeps a float64 scene
origin (`scene["hgca_origin"]`) and everything relative to it. World = origin + Blender coordinates.
"""
from __future__ import annotations

import time
from pathlib import Path

import bpy
import numpy as np
import pytest

from bl_helpers import addon_module, core_arrays, prefs
from hgca_testdata import UTM_OFFSETS, write_las

MM = 1e-3


def scene_world(obj: bpy.types.Object) -> np.ndarray:
    """What the user sees (Blender coordinates, float32 data under matrix_world) plus the scene origin."""
    co = np.empty(len(obj.data.vertices) * 3, dtype=np.float32)
    obj.data.vertices.foreach_get("co", co)
    m = np.array(obj.matrix_world)
    return co.reshape(-1, 3).astype(np.float64) @ m[:3, :3].T + m[:3, 3] + origin()


def origin() -> np.ndarray:
    return np.array(bpy.context.scene.get("hgca_origin", (0.0, 0.0, 0.0)), dtype=np.float64)


def import_las(path: Path) -> bpy.types.Object:
    before = set(bpy.data.objects.keys())
    assert bpy.ops.import_scene.hgca_lidar(filepath=str(path)) == {"FINISHED"}
    (name,) = set(bpy.data.objects.keys()) - before
    return bpy.data.objects[name]


@pytest.mark.parametrize("place", sorted(UTM_OFFSETS))
def test_import_of_utm_las_is_exact_and_small_in_blender(addon, tmp_path: Path, place: str) -> None:
    base = np.array(UTM_OFFSETS[place])
    rng = np.random.default_rng(0)
    held_a = write_las(tmp_path / "a.las", rng.uniform([-30, -30, 0], [30, 30, 10], (5000, 3)) + base)
    held_b = write_las(tmp_path / "b.las", rng.uniform([-30, -30, 0], [30, 30, 10], (5000, 3)) + base + [2500, -40, 0])
    a = import_las(tmp_path / "a.las")
    assert np.abs(scene_world(a) - held_a).max() < MM
    first_origin = origin()
    assert np.array_equal(first_origin, np.round(first_origin)) and np.abs(first_origin - base).max() < 40
    b = import_las(tmp_path / "b.las")
    assert np.array_equal(origin(), first_origin)  # one origin per scene: later imports reuse it
    for obj, held in ((a, held_a), (b, held_b)):
        assert np.abs(scene_world(obj) - held).max() < MM
        co = np.empty(len(obj.data.vertices) * 3, dtype=np.float32)
        obj.data.vertices.foreach_get("co", co)
        assert np.abs(co).max() < 100 and np.abs(np.array(obj.location)).max() < 5000
    assert tuple(b.location) == pytest.approx((2500, -40, 0), abs=1)


def test_completion_of_a_utm_scan_round_trips_to_the_mm(addon, tmp_path: Path) -> None:
    """Points and region reach the core in world coordinates to the mm, and the result is placed back under
    the scene origin with its vertices on the region's 20 cm grid (coarse stage: cell corners) to the mm."""
    jobs = addon_module("jobs.completion")
    operators = addon_module("operators.complete")
    prefs().weights_path = ""  # the shipped weights
    base = np.array(UTM_OFFSETS["utm_1e7"])
    points = core_arrays("from hgca_testdata import tiny_sample", p='tiny_sample(3)["input_points"]')["p"]
    held = write_las(tmp_path / "scan.las", points.astype(np.float64) + base)
    scan = import_las(tmp_path / "scan.las")
    scan.select_set(True)
    bpy.context.view_layer.objects.active = scan
    props = bpy.context.scene.hgca
    world_region = (base[0] + 3, base[1] + 3, base[2] + 1, 6.0, 6.0, 4.0)
    props.region_mode = "NUMBERS"
    props.region_center = tuple(np.array(world_region[:3]) - origin())  # the panel shows scene coordinates
    props.region_size = world_region[3:6]
    props.region_yaw = 0.0
    props.samples, props.seed, props.stage, props.device, props.t1 = 1, 3, "coarse", "cpu", 2

    params = operators.gather_params(bpy.context)
    assert np.abs(params.points - held).max() < MM
    np.testing.assert_allclose(params.region[:3], world_region[:3], rtol=0, atol=MM)

    assert bpy.ops.hgca.complete() == {"FINISHED"}
    job = jobs.active_job(bpy.context.scene.name)
    deadline = time.monotonic() + 240
    while job.poll_once():
        assert time.monotonic() < deadline, job.status
        time.sleep(0.05)
    assert job.state == "done", job.error
    coll = bpy.data.collections[job.collection_name]
    (result,) = coll.objects
    world = scene_world(result)
    assert len(world) > 50
    corner = np.array(world_region[:3]) - np.array(world_region[3:6]) / 2
    cells = (world - corner + 0.05) / 0.2  # coarse vertices: k * 0.2 - 0.05 in the region frame
    assert np.abs(cells - np.round(cells)).max() * 0.2 < MM
    co = np.empty(len(result.data.vertices) * 3, dtype=np.float32)
    result.data.vertices.foreach_get("co", co)
    assert np.abs(co).max() < 100  # float32 data near zero, the offset is in the location and the origin


def test_origin_is_kept_where_blendergis_reads_it(addon, tmp_path: Path) -> None:
    """The first far import writes its origin's x/y also as BlenderGIS's `crs x` / `crs y`."""
    base = np.array(UTM_OFFSETS["utm"])
    rng = np.random.default_rng(1)
    write_las(tmp_path / "a.las", rng.uniform([-30, -30, 0], [30, 30, 10], (2000, 3)) + base)
    import_las(tmp_path / "a.las")
    scene = bpy.context.scene
    assert (scene["crs x"], scene["crs y"]) == tuple(origin()[:2])


def test_scene_georeferenced_by_blendergis_places_the_scan_under_its_origin(addon, tmp_path: Path) -> None:
    """A scene BlenderGIS set up (`crs`, `crs x`, `crs y`, no hgca origin) keeps its origin: the scan lies
    relative to it, to the mm, and the add-on adds no origin of its own."""
    base = np.array(UTM_OFFSETS["utm"])
    scene = bpy.context.scene
    scene["crs"], scene["crs x"], scene["crs y"] = "EPSG:32632", base[0] + 100.0, base[1] - 50.0
    rng = np.random.default_rng(2)
    held = write_las(tmp_path / "a.las", rng.uniform([-30, -30, 0], [30, 30, 10], (2000, 3)) + base)
    obj = import_las(tmp_path / "a.las")
    assert "hgca_origin" not in scene
    gis = np.array([scene["crs x"], scene["crs y"], 0.0])
    co = np.empty(len(obj.data.vertices) * 3, dtype=np.float32)
    obj.data.vertices.foreach_get("co", co)
    world = co.reshape(-1, 3).astype(np.float64) + np.array(obj.location) + gis
    assert np.abs(world - held).max() < MM
    assert np.abs(np.array(obj.location)).max() < 1000  # near Blender's 0, not 5,000 km away


def write_las_crs(path: Path, points: np.ndarray, epsg: int) -> Path:
    """A LAS whose GeoTIFF keys name `epsg` as its projected CRS (ProjectedCSTypeGeoKey 3072)."""
    import laspy
    from laspy.vlrs.known import GeoKeyDirectoryVlr, GeoKeyEntryStruct

    header = laspy.LasHeader(point_format=1, version="1.2")
    header.scales, header.offsets = [0.001] * 3, np.floor(points.min(axis=0))
    vlr = GeoKeyDirectoryVlr()
    vlr.geo_keys_header.key_directory_version, vlr.geo_keys_header.number_of_keys = 1, 1
    key = GeoKeyEntryStruct()
    key.id, key.tiff_tag_location, key.count, key.value_offset = 3072, 0, 1, epsg
    vlr.geo_keys = [key]
    las = laspy.LasData(header)
    las.x, las.y, las.z = points[:, 0], points[:, 1], points[:, 2]
    las.vlrs.append(vlr)
    las.write(str(path))
    return path


def test_import_keeps_the_files_crs_where_blendergis_reads_it(addon, tmp_path: Path) -> None:
    """The CRS in a LAS file's GeoTIFF keys lands in the scene key `crs`; a scan in another CRS is then refused
    and the scene stays as it was."""
    from bl_helpers import snapshot

    base = np.array(UTM_OFFSETS["utm"])
    rng = np.random.default_rng(3)
    pts = rng.uniform([-30, -30, 0], [30, 30, 10], (500, 3)) + base
    import_las(write_las_crs(tmp_path / "a.las", pts, 32617))
    scene = bpy.context.scene
    assert scene["crs"] == "EPSG:32617"
    def keys() -> dict:
        return {k: (list(scene[k]) if k == "hgca_origin" else scene[k]) for k in ("crs", "crs x", "crs y", "hgca_origin")}

    held = keys()
    before = snapshot()
    with pytest.raises(RuntimeError, match="EPSG:32618 but the scene's is EPSG:32617"):
        bpy.ops.import_scene.hgca_lidar(filepath=str(write_las_crs(tmp_path / "b.las", pts, 32618)))
    assert snapshot() == before
    assert keys() == held


def test_real_copc_brings_its_crs(addon) -> None:
    from bl_helpers import FIXTURES, require_fixture

    import_las(require_fixture(FIXTURES / "simple.copc.laz"))
    assert bpy.context.scene["crs"] == "EPSG:2991"


def test_set_origin_from_the_panel_keeps_float64_and_refuses_under_placed_objects(addon, tmp_path: Path) -> None:
    scene = bpy.context.scene
    assert bpy.ops.hgca.set_origin(x="631000.125", y="4833000.375", z="12.5", crs="EPSG:32617") == {"FINISHED"}
    assert list(scene["hgca_origin"]) == [631000.125, 4833000.375, 12.5]
    assert (scene["crs x"], scene["crs y"], scene["crs"]) == (631000.125, 4833000.375, "EPSG:32617")
    with pytest.raises(RuntimeError, match="origin y is not a number"):
        bpy.ops.hgca.set_origin(x="1", y="north", z="0")
    base = np.array(UTM_OFFSETS["utm"])
    write_las(tmp_path / "a.las", np.random.default_rng(4).uniform([-5, -5, 0], [5, 5, 2], (200, 3)) + base)
    import_las(tmp_path / "a.las")
    with pytest.raises(RuntimeError, match="placed relative to the current origin"):
        bpy.ops.hgca.set_origin(x="0", y="0", z="0", crs="")
    assert list(scene["hgca_origin"]) == [631000.125, 4833000.375, 12.5]


def test_a_far_import_never_moves_an_earlier_local_one(addon, tmp_path: Path) -> None:
    """A local scan first (no origin), then a georeferenced one: setting the origin now would move the local scan
    kilometres away, so the import is refused with the reason and the scene stays as it was."""
    rng = np.random.default_rng(1)
    write_las(tmp_path / "local.las", rng.uniform([-20, -20, 0], [20, 20, 5], (3000, 3)))
    write_las(tmp_path / "far.las", rng.uniform([-20, -20, 0], [20, 20, 5], (3000, 3)) + UTM_OFFSETS["utm"])
    local = import_las(tmp_path / "local.las")
    before = scene_world(local)
    assert "hgca_origin" not in bpy.context.scene
    with pytest.raises(RuntimeError, match=r"already holds 'local' in its local frame.*new scene"):
        bpy.ops.import_scene.hgca_lidar(filepath=str(tmp_path / "far.las"))
    assert "hgca_origin" not in bpy.context.scene and len(bpy.data.objects) == 1
    np.testing.assert_array_equal(scene_world(local), before)
