"""Procedural scenes: seeded, two distinct styles, the content the brief asks for, clean solids."""
from __future__ import annotations

import numpy as np
import pytest

from hgca_core.synth.assets import BUILDING, CAR, FENCE, POLE, ROAD, SIDEWALK, TREE
from hgca_core.synth.primitives import MeshBuilder
from hgca_core.synth.scene import make_scene


@pytest.fixture(scope="module")
def scenes():
    return {(s, st): make_scene(s, st) for s in (11, 12) for st in ("city", "suburb")}


def test_same_seed_same_scene():
    a, b = make_scene(4), make_scene(4)
    assert np.array_equal(a.mesh.vertices, b.mesh.vertices) and np.array_equal(a.mesh.faces, b.mesh.faces)
    assert np.array_equal(a.face_labels, b.face_labels) and np.array_equal(a.drive, b.drive)
    c = make_scene(5)
    assert len(c.mesh.vertices) != len(a.mesh.vertices) or not np.array_equal(c.mesh.vertices, a.mesh.vertices)


def test_styles_differ(scenes):
    for seed in (11, 12):
        city, sub = scenes[seed, "city"], scenes[seed, "suburb"]
        assert city.style == "city" and sub.style == "suburb"
        zc = city.mesh.vertices[city.mesh.faces[city.face_labels == BUILDING]][..., 2].max()
        zs = sub.mesh.vertices[sub.mesh.faces[sub.face_labels == BUILDING]][..., 2].max()
        assert zc > 15.0 > zs                         # city blocks up to 25 m, houses stay low
        # suburbs have many more trees and fences per building face
        ratio = lambda s, lab: np.sum(s.face_labels == lab) / np.sum(s.face_labels == BUILDING)  # noqa: E731
        assert ratio(sub, FENCE) > ratio(city, FENCE)


def test_content_and_extent(scenes):
    for sc in scenes.values():
        assert sc.mesh.faces.shape[0] < 300_000
        lo, hi = sc.mesh.bounds
        assert hi[0] - lo[0] >= 119 and hi[1] - lo[1] >= 119 and abs(lo[2]) < 0.2
        for lab in (ROAD, SIDEWALK, BUILDING, CAR, POLE):
            assert np.any(sc.face_labels == lab), (sc.style, lab)
        assert sc.face_labels.shape == (len(sc.mesh.faces),) and sc.face_labels.dtype == np.uint8
        assert np.any(sc.face_labels == TREE) or sc.style == "city"
        # the road is at z = 0 and the sensor rides about 2 m above it, inside the street corridor
        assert np.allclose(sc.drive[:, 2], 2.0, atol=0.15)
        x0, y0, x1, y1 = sc.street_box
        assert np.all((sc.drive[:, 1] > y0) & (sc.drive[:, 1] < y1) & (sc.drive[:, 0] >= x0) & (sc.drive[:, 0] <= x1))
        assert np.ptp(sc.drive[:, 0]) > 100


def test_parked_cars_do_not_overlap(scenes):
    shapes = set()
    for sc in scenes.values():
        cars = sc.layout["parked_cars"]
        for side in (1, -1):
            xs = sorted(c["x"] for c in cars if np.sign(c["y"]) == side)
            assert np.all(np.diff(xs) > 3.8)           # centres further apart than the shortest car
        shapes |= {c["shape"] for c in cars}
    assert len(shapes) >= 3


def test_buildings_tower_over_the_top_beam(scenes):
    """The input LiDAR's top beam (+2.4 deg from ~2 m) reaches about 3 m at 20 m: buildings go far higher."""
    sc = scenes[11, "city"]
    near = sc.mesh.vertices[sc.mesh.faces[sc.face_labels == BUILDING]].reshape(-1, 3)
    near = near[np.abs(near[:, 1]) < 30]
    assert near[:, 2].max() > 8.0


def test_solids_hide_interior_surface_only():
    b = MeshBuilder()
    b.box([0, 0, 0], [4, 4, 3], BUILDING)
    b.ellipsoid([10, 0, 3], 2.0, 1.5, TREE)
    _, _, solids = b.build()
    pts = np.array([[2, 2, 1.5], [2, 2, 0.0], [2, 2, 3.0], [4.0, 2, 1], [5, 2, 1], [10, 0, 3], [10, 0, 4.6]])
    assert solids.contains(pts).tolist() == [True, True, False, False, False, True, False]
