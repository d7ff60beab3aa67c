import numpy as np
import pytest

from hgca_core.errors import InputError
from hgca_core.geometry.region import Region, estimate_ground


def test_local_world_roundtrip_with_yaw():
    r = Region(center=[10.0, -5.0, 2.0], size=[38.4, 20.0, 8.0], yaw=np.radians(30))
    pts = np.random.default_rng(0).normal(size=(100, 3)) * 10
    np.testing.assert_allclose(r.to_world(r.to_local(pts)), pts, atol=1e-9)
    # the centre maps to the middle of the box, the min corner to the origin
    np.testing.assert_allclose(r.to_local(r.center[None])[0], r.size / 2, atol=1e-9)
    np.testing.assert_allclose(r.to_local(r.min_corner[None])[0], 0, atol=1e-9)


def test_local_matrix_matches_to_local():
    r = Region(center=[1.0, 2.0, 3.0], size=[4.0, 5.0, 6.0], yaw=0.7)
    p = np.array([[3.0, -1.0, 2.0]])
    m = r.local_matrix()
    np.testing.assert_allclose((m[:3, :3] @ p.T).T + m[:3, 3], r.to_local(p), atol=1e-12)


def test_parse_and_errors():
    r = Region.parse("1,2,3,38.4,38.4,8,90")
    assert r.yaw == pytest.approx(np.pi / 2)
    assert r.grid_shape(0.2) == (192, 192, 40)
    assert r.grid_shape(0.1) == (384, 384, 80)
    with pytest.raises(InputError, match="6 or 7"):
        Region.parse("1,2,3")
    with pytest.raises(InputError, match="numbers"):
        Region.parse("a,b,c,d,e,f")
    with pytest.raises(InputError, match="positive"):
        Region(center=[0, 0, 0], size=[0, 1, 1])


def test_around_puts_ground_one_metre_above_bottom():
    rng = np.random.default_rng(1)
    ground = np.c_[rng.uniform(-20, 20, (5000, 2)), np.full(5000, -1.8) + rng.normal(0, 0.01, 5000)]
    walls = np.c_[rng.uniform(-20, 20, 3000), np.full(3000, 8.0), rng.uniform(-1.8, 10, 3000)]
    cars = np.c_[rng.uniform(-3, 3, (2000, 2)), rng.uniform(-1.8, -0.3, 2000)]
    pts = np.concatenate([ground, walls, cars])
    assert estimate_ground(pts, np.zeros(2)) == pytest.approx(-1.8, abs=0.05)
    r = Region.around(pts, sensor=np.array([0.0, 0.0, 0.0]))
    local = r.to_local(np.array([[0.0, 0.0, -1.8]]))
    assert local[0, 2] == pytest.approx(1.0, abs=0.05)
    assert local[0, 0] == pytest.approx(19.2)
    with pytest.raises(InputError):
        Region.around(np.zeros((0, 3)))


def test_default_region_centres_on_the_first_sensor_else_the_median():
    """The one default region (`hgca complete` without --region, `hgca region`, the add-on's Add Region Box)."""
    from hgca_core.geometry.region import default_region, ground_height

    rng = np.random.default_rng(2)
    pts = np.c_[rng.uniform(0, 30, (4000, 2)), np.full(4000, 2.5) + rng.normal(0, 0.01, 4000)]
    r = default_region(pts, np.array([[5.0, 6.0, 4.3], [20.0, 20.0, 4.3]]))
    np.testing.assert_allclose(r.center[:2], (5.0, 6.0))
    assert ground_height(r) == pytest.approx(2.5, abs=0.05) and r.center[2] - r.size[2] / 2 == pytest.approx(1.5, abs=0.05)
    for none in (None, np.zeros((0, 3))):
        m = default_region(pts, none, size=(10.0, 10.0, 6.0))
        np.testing.assert_allclose(m.center[:2], np.median(pts[:, :2], axis=0))
        np.testing.assert_allclose(m.size, (10.0, 10.0, 6.0))
        assert ground_height(m) == pytest.approx(2.5, abs=0.05)
