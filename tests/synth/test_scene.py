"""Procedural scenes: seeded, four styles, the content the brief asks for, ground that is not flat,
streets that bend and cross at angles, objects standing on the ground, clean solids."""
from __future__ import annotations

import numpy as np
import pytest

from hgca_core.geometry.raycast import make_intersector
from hgca_core.synth import vehicles as V
from hgca_core.synth.assets import BUILDING, CAR, FENCE, PERSON, POLE, ROAD, SIDEWALK, TREE
from hgca_core.synth.materials import BARK, DARK, FOLIAGE, GLASS, RETRO, WINDOW
from hgca_core.synth.primitives import MeshBuilder
from hgca_core.synth.scene import EXTENT, STYLES, make_scene
from hgca_core.synth.terrain import StreetCurve, Terrain


@pytest.fixture(scope="module")
def scenes():
    return {(s, st): make_scene(s, st) for s in (11, 12) for st in STYLES}


@pytest.fixture(scope="module")
def many():
    """One scene per seed 0..11, each in its own style: enough to see every kind of ground and street."""
    return [make_scene(s) for s in range(12)]


def test_same_seed_same_scene():
    a, b = make_scene(4), make_scene(4)
    assert np.array_equal(a.mesh.vertices, b.mesh.vertices) and np.array_equal(a.mesh.faces, b.mesh.faces)
    assert np.array_equal(a.face_labels, b.face_labels) and np.array_equal(a.drive, b.drive)
    assert np.array_equal(a.face_materials, b.face_materials)
    c = make_scene(5)
    assert len(c.mesh.vertices) != len(a.mesh.vertices) or not np.array_equal(c.mesh.vertices, a.mesh.vertices)


def test_styles_differ(scenes):
    for seed in (11, 12):
        city, sub = scenes[seed, "city"], scenes[seed, "suburb"]
        assert city.style == "city" and sub.style == "suburb" and scenes[seed, "town"].style == "town"
        height = lambda s: np.ptp(s.mesh.vertices[s.mesh.faces[s.face_labels == BUILDING]][..., 2])  # noqa: E731
        assert height(city) > 15.0 and height(city) > height(sub)
        ratio = lambda s, lab: np.sum(s.face_labels == lab) / np.sum(s.face_labels == BUILDING)  # noqa: E731
        assert ratio(sub, FENCE) > ratio(city, FENCE)


def test_strip_streets_end_low(scenes):
    """The low-rise style holds what most real streets hold (single-storey shops, parking lots, open lots,
    low halls): no building stands much above 10 m over its ground, where every city street has walls over
    15 m, so a wall cut at 2 m does not always go on to a tower."""
    def tops(sc):
        v = sc.mesh.vertices[np.unique(sc.mesh.faces[sc.face_labels == BUILDING])]
        return v[:, 2] - sc.terrain.height(v[:, :2])

    for seed in (11, 12):
        strip, city = scenes[seed, "strip"], scenes[seed, "city"]
        assert strip.style == "strip" and tops(strip).max() < 11.0 < 15.0 < tops(city).max()
        lay = strip.layout
        assert lay["low_shops"] + lay["open_lots"] > 0 and np.any(strip.face_labels == CAR)


def test_content(scenes, many):
    for sc in scenes.values():
        assert sc.mesh.faces.shape[0] < 300_000
        for lab in (ROAD, SIDEWALK, BUILDING, CAR, POLE):
            assert np.any(sc.face_labels == lab), (sc.style, lab)
        assert sc.face_labels.shape == sc.face_materials.shape == (len(sc.mesh.faces),)
        assert sc.face_labels.dtype == np.uint8 and sc.face_materials.dtype == np.uint8
    everything = set()
    for sc in many:
        everything |= {c["shape"] for c in sc.layout["parked_cars"]}
    assert {"van", "truck", "bus", "motorbike"} <= everything
    labels = np.concatenate([sc.face_labels for sc in many])
    mats = np.concatenate([sc.face_materials for sc in many])
    assert np.any(labels == PERSON) and np.any(labels == TREE) and np.any(labels == FENCE)
    assert {GLASS, WINDOW, DARK, FOLIAGE, RETRO, BARK} <= set(np.unique(mats))
    # walls over 25 m in the city, crowns are porous foliage, trunks are not
    tall = max(np.ptp(sc.mesh.vertices[sc.mesh.faces[sc.face_labels == BUILDING]][..., 2]) for sc in many
               if sc.style == "city")
    assert tall > 25.0
    tree = np.concatenate([sc.face_materials[sc.face_labels == TREE] for sc in many])
    assert set(np.unique(tree)) == {FOLIAGE, BARK}


def test_ground_is_not_flat_and_streets_bend_and_cross_at_angles(many):
    kinds = {sc.layout["ground"]["kind"] for sc in many}
    assert {"flat", "grade", "hills"} <= kinds
    assert any(abs(sc.curve.k) > 1 / 1000 for sc in many) and any(sc.curve.k == 0 for sc in many)
    angles = [sc.layout["crossroad_angle_deg"] for sc in many if sc.layout["crossroad_angle_deg"] is not None]
    assert any(abs(a - 90.0) > 10.0 for a in angles)
    for sc in many:
        z = sc.drive[:, 2]
        grade = np.abs(np.diff(z)) / np.linalg.norm(np.diff(sc.drive[:, :2], axis=0), axis=1)
        assert grade.max() < 0.16                                          # drivable
        if sc.layout["ground"]["kind"] != "flat":
            assert np.ptp(z) > 1.0                                         # a real climb over 116 m
        # the road is crowned: its centre line lies above the curbs
        u = np.linspace(-40, 40, 9)
        hw = sc.layout["road_half_width"]
        centre = sc.terrain.height(sc.curve.to_world(u, 0.0))
        curbs = (sc.terrain.height(sc.curve.to_world(u, hw - 0.01)) + sc.terrain.height(sc.curve.to_world(u, 0.01 - hw)))
        assert np.mean(centre - curbs / 2) > 0.03


def test_drive_rides_the_road_in_its_lane(many):
    for sc in many:
        assert np.allclose(sc.drive[:, 2], sc.terrain.height(sc.drive[:, :2]), atol=1e-9)  # on the road surface
        uv = sc.curve.to_street(sc.drive[:, :2])
        assert np.all(np.abs(uv[:, 1]) < sc.layout["road_half_width"]) and np.ptp(uv[:, 0]) > 100
        assert np.all(sc.drive_up[:, 2] > 0.98) and np.allclose(np.linalg.norm(sc.drive_up, axis=1), 1.0)


def test_objects_stand_on_the_ground(many):
    """Parked vehicles sit on the road under them (tilted with it), buildings reach down to the ground."""
    for sc in many:
        c = sc.mesh.triangles_center
        car_v = np.unique(sc.mesh.faces[sc.face_labels == CAR])
        cv = sc.mesh.vertices[car_v]
        cv = cv[np.abs(sc.curve.to_street(cv[:, :2])[:, 1]) < sc.layout["road_half_width"]]   # parked on the road
        for car in sc.layout["parked_cars"]:
            xy = sc.curve.to_world(car["x"], car["y"])
            near = np.linalg.norm(cv[:, :2] - xy, axis=1) < V.LENGTH_MAX.get(car["shape"], 2.2) / 2 + 0.2
            # wheels on the road, neither sunk nor floating (height over the ground under each vertex: on a grade
            # the lowest vertex can be a bus's downhill bumper, not a wheel)
            clear = cv[near, 2] - sc.terrain.height(cv[near, :2])
            assert -0.03 < clear.min() < 0.05, car   # 3 cm: a tilted plane under a wheel on a cambered road


def test_a_footprint_stands_on_its_lowest_ground():
    """Buildings, fences and furniture stand on the lowest ground under their footprint (so no side floats
    on a slope; the ground truth drops what the slope buries), and a tilted placement follows the ground."""
    from hgca_core.synth.scene import Street
    from hgca_core.synth.terrain import make_terrain

    curve = StreetCurve(1 / 400)
    terrain, _ = make_terrain(np.random.default_rng(3), 78.0, curve, 6.0)
    S = Street(6.0, 3.0, 0.12, True, 5.0, 5.0, np.radians(70.0), curve, terrain)
    for u, v, foot in ((-20.0, 12.0, (0, 0, 15, 12)), (30.0, -15.0, (0, 0, 8, 10)), (0.0, 8.0, (-0.3, -0.3, 0.3, 0.3))):
        yaw, offset, tilt = S.place(u, v, 0.0, foot)
        assert tilt is None and yaw == pytest.approx(float(curve.heading(u)))
        c, s_ = np.cos(yaw), np.sin(yaw)
        x0, y0, x1, y1 = foot
        corners = offset[:2] + np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]]) @ np.array([[c, s_], [-s_, c]])
        assert offset[2] == pytest.approx(terrain.height(corners).min(), abs=1e-9) or offset[2] < terrain.height(corners).min()
        assert np.all(offset[2] <= terrain.height(corners) + 1e-9)
    _, offset, tilt = S.place(10.0, -3.0, 0.0, (-2.5, -1.0, 2.5, 1.0), tilt=True)
    assert abs(offset[2] - terrain.height(offset[:2])[0]) < 0.05 and tilt[2, 2] < 1.0     # on the ground, tilted
    # the cross street's centre line meets the main one at xc and runs at theta
    assert S.cross_u(0.0) == pytest.approx(5.0) and S.cross_u(10.0) - S.cross_u(0.0) == pytest.approx(10 / np.tan(S.theta))
    assert not S.x_free(5.0, 0.0) and S.x_free(40.0, 0.0)


def test_street_coordinates_round_trip():
    curve = StreetCurve(1 / 300)
    u, v = np.meshgrid(np.linspace(-EXTENT, EXTENT, 13), np.linspace(-EXTENT, EXTENT, 13))
    xy = curve.to_world(u.ravel(), v.ravel())
    assert np.allclose(curve.to_street(xy), np.c_[u.ravel(), v.ravel()], atol=1e-9)
    # v is a true distance from the centre line
    d = np.linalg.norm(curve.to_world(10.0, 5.0) - curve.to_world(10.0, 0.0))
    assert d == pytest.approx(5.0)


def test_terrain_height_is_the_ground_mesh():
    """`height` is exactly the triangulated surface the LiDAR sees (a ray straight down lands on it)."""
    import trimesh

    rng = np.random.default_rng(0)
    t = Terrain(-10.0, -10.0, 2.0, rng.normal(0, 0.5, (11, 11)))
    v, f = t.mesh_arrays()
    mesh = trimesh.Trimesh(v, f, process=False)
    xy = rng.uniform(-9.9, 9.9, (500, 2))
    dist, _ = make_intersector(mesh).first_hits(np.c_[xy, np.full(500, 50.0)], np.tile([0.0, 0.0, -1.0], (500, 1)))
    assert np.allclose(50.0 - dist, t.height(xy), atol=1e-9)
    assert np.all(mesh.face_normals[:, 2] > 0)                            # upward facing


def test_solids_hide_interior_surface_only():
    b = MeshBuilder()
    b.box([0, 0, 0], [4, 4, 3], BUILDING)
    b.ellipsoid([10, 0, 3], 2.0, 1.5, TREE)
    _, _, solids = b.build()
    pts = np.array([[2, 2, 1.5], [2, 2, 0.0], [2, 2, 3.0], [4.0, 2, 1], [5, 2, 1], [10, 0, 3], [10, 0, 4.6]])
    assert solids.contains(pts).tolist() == [True, True, False, False, False, True, False]


def test_tilted_placement_keeps_solids_outward():
    """A box set onto a 10 % slope: its solid still holds its inside and not its outside."""
    from hgca_core.synth.terrain import tilt_to

    b = MeshBuilder()
    with b.placed(0.3, [5.0, 0.0, 1.0], tilt_to([0.1, 0.0, 1.0])):
        b.box([-1, -1, 0], [1, 1, 1], CAR)
    mesh, _, solids = b.build()
    centre = mesh.vertices.mean(axis=0)
    assert solids.contains(centre[None])[0] and not solids.contains(centre[None] + [0, 0, 2.0])[0]


def test_generator_6_makes_the_synth2_scenes_again():
    """Version 7 added the strip style to the seed's draw, which changed most seeds' scenes; generator 6 draws as
    version 6 did, so synth2 (and the val / test scenes of the earlier tables) can be rebuilt. The
    styles and face counts are those of the rebuilt synth2 test scenes whose scores matched the earlier
    test table (`hgca eval --methods input`: equal ground-truth patches, equal or within 1 % scores)."""
    for seed, style, faces in ((2_000_000, "town", 30_180), (2_000_001, "city", 30_902), (2_000_003, "suburb", 41_002)):
        old = make_scene(seed, generator=6)
        assert (old.style, len(old.mesh.faces)) == (style, faces)
    styles = {s: (make_scene(s, generator=6).style, make_scene(s).style) for s in range(2_000_000, 2_000_008)}
    assert {v6 for v6, _ in styles.values()} <= {"city", "suburb", "town"}
    assert any(v6 != v7 for v6, v7 in styles.values())         # the versions really differ for some seeds
    with pytest.raises(ValueError, match="for generator version 6"):
        make_scene(1, "strip", generator=6)
    with pytest.raises(ValueError, match="unknown generator version 5"):
        make_scene(1, generator=5)
