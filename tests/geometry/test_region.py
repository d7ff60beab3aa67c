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


def _street(rng, slope=(0.0, 0.0), n=6000):
    """A road sloping by `slope` (dz/dx, dz/dy) through z = -1.8 at the origin, a raised sidewalk on one
    side only (an asymmetric view, as a sensor in the right lane has), cars and a wall."""
    xy = rng.uniform(-15, 15, (n, 2))
    z = -1.8 + xy @ np.asarray(slope) + rng.normal(0, 0.01, n)
    z[xy[:, 1] > 6] += 0.13                                   # sidewalk
    walls = np.c_[rng.uniform(-15, 15, 2000), np.full(2000, 9.0), rng.uniform(-2, 8, 2000)]
    cars = np.c_[rng.uniform(2, 6, 1500), rng.uniform(-5, -3, 1500), rng.uniform(-1.5, -0.3, 1500)]
    return np.concatenate([np.c_[xy, z], walls, cars])


@pytest.mark.parametrize("slope", [(0.0, 0.0), (0.08, 0.0), (-0.06, 0.03)])
def test_ground_under_the_sensor_on_slopes(slope):
    """The ground right under the sensor, not the median over what it sees: on an 8 % grade the old median
    of cell lows was off by the slope times the offset of the seen area (tens of centimetres)."""
    rng = np.random.default_rng(2)
    pts = _street(rng, slope)
    keep = (pts[:, 0] > -4) | (np.abs(pts[:, 1]) > 3)        # the sensor sees more ahead than behind
    keep &= ~((pts[:, 0] < -2) & (pts[:, 1] > 0))
    assert estimate_ground(pts[keep], np.zeros(2)) == pytest.approx(-1.8, abs=0.03)


def test_ground_of_real_sweeps():
    """The nuScenes and AV2 sweeps: the ground under the sensor as the points right around the car show it
    (nuScenes: the road 3-8 m ahead at z = -1.86; AV2: the lowest upper beam meets the road 4.3 m out at
    z = -0.355), within 3 cm (the median of cell lows was 5-9 cm off)."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "synth"))
    from real_sweeps import av2_sweeps, nuscenes_sweep

    nus = nuscenes_sweep()
    ahead = (nus.points[:, 0] > 3) & (nus.points[:, 0] < 8) & (np.abs(nus.points[:, 1]) < 1.5)
    road = np.median(nus.points[ahead, 2])
    assert estimate_ground(nus.points, np.zeros(2)) == pytest.approx(road, abs=0.03)
    for sw in av2_sweeps():
        low = sw.points[sw.ring == 31]                      # the upper head's -25 deg beam: a ring on the road
        road = np.median(low[:, 2])
        assert estimate_ground(sw.points, sw.origin[:2]) == pytest.approx(road, abs=0.03), sw.name


def test_height_layer_names_the_layer_holding_a_height():
    from hgca_core.geometry.region import BELOW_GROUND, height_layer

    # 20 cm cells, the box starting 1 m under the ground: the ground is the bottom of layer 5
    assert BELOW_GROUND == 1.0
    assert height_layer(0.0, 0.2) == 5 and height_layer(-0.01, 0.2) == 4
    assert height_layer(2.0, 0.2) == 15 and height_layer(1.99, 0.2) == 14 and height_layer(2.0, 0.1) == 30
