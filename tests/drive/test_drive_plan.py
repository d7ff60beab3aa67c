"""Tile plans: tiles cover the trajectory, consecutive tiles overlap by at least the asked overlap, each is
oriented with the path and placed on its own ground, and ownership splits every overlap exactly once."""
import numpy as np
import pytest

from hgca_core.errors import InputError
from hgca_core.geometry.region import Region
from hgca_core.tiling.plan import Trajectory, footprint_contains, owned, plan_tiles, tile_region


def regions_of(tiles, size=38.4):
    return [Region(np.array([*t.center_xy, 3.0]), np.array([size, size, 8.0]), t.yaw) for t in tiles]


def path_overlap(path: Trajectory, a: Region, b: Region, step: float = 0.05) -> float:
    """Length of the trajectory (sampled every `step` m) inside both footprints."""
    s = np.arange(0.0, path.length + step, step)
    xy = np.array([path.position(v)[:2] for v in s])
    both = footprint_contains(a, xy) & footprint_contains(b, xy)
    return float(both.sum() * step)


def check_plan(positions, size=38.4, overlap=6.4):
    tiles = plan_tiles(positions, size, overlap)
    regions = regions_of(tiles, size)
    path = Trajectory(positions)
    inside = np.zeros(len(positions), int)
    for r in regions:
        inside += footprint_contains(r, positions[:, :2])
    assert np.all(inside >= 1), "every scan position lies in a tile"
    for a, b in zip(regions, regions[1:]):
        assert path_overlap(path, a, b) >= overlap - 0.1
    for t in tiles:                                     # oriented with the path: yaw = local chord heading
        s = min(max(t.arc, 0.0), path.length)
        d = path.position(min(s + 1, path.length)) - path.position(max(s - 1, 0))
        diff = np.angle(np.exp(1j * (t.yaw - np.arctan2(d[1], d[0]))))
        assert abs(diff) < np.radians(8)
    return tiles, regions


def test_straight_drive_tiles_every_stride_with_exact_overlap():
    positions = np.c_[np.arange(0, 201, 8.0), np.zeros(26), np.full(26, 2.0)]
    tiles, regions = check_plan(positions)
    assert len(tiles) == 7                              # 200 + 6.4 m to cover at a 32 m stride from 38.4 m
    centres = np.array([r.center[0] for r in regions])
    assert np.allclose(np.diff(centres), 32.0) and np.isclose(centres.mean(), 100.0)
    assert np.allclose([t.yaw for t in tiles], 0.0)
    assert [t.phase for t in tiles] == [1, 2, 1, 2, 1, 2, 1]


def test_curved_and_reversed_drives_are_covered_and_oriented():
    a = np.radians(np.arange(0, 151, 3))
    arc = np.c_[60 * np.cos(a), 60 * np.sin(a), np.zeros(len(a))]
    check_plan(arc)
    reverse = np.c_[np.arange(300, 99, -10.0), np.full(21, 5.0), np.zeros(21)]
    tiles, _ = check_plan(reverse)
    assert all(abs(abs(t.yaw) - np.pi) < 1e-6 for t in tiles)


def test_each_tile_takes_its_nearest_scans():
    positions = np.c_[np.arange(0, 101, 5.0), np.zeros(21), np.zeros(21)]
    for t in plan_tiles(positions, scans_per_tile=5):
        d = np.abs(positions[:, 0] - t.center_xy[0])
        assert sorted(d[list(t.scans)]) == sorted(d)[:5]


def test_ownership_is_the_overlap_midline_and_a_partition():
    positions = np.c_[np.arange(0, 121, 8.0), np.zeros(16), np.zeros(16)]
    tiles, regions = check_plan(positions)
    rng = np.random.default_rng(0)
    xy = np.c_[rng.uniform(-30, 150, 20000), rng.uniform(-19, 19, 20000)]
    counts = sum(owned(xy, i, regions).astype(int) for i in range(len(regions)))
    covered = np.any([footprint_contains(r, xy) for r in regions], axis=0)
    assert np.array_equal(counts, covered.astype(int)), "each covered point has exactly one owner"
    mid = (regions[0].center[0] + regions[1].center[0]) / 2
    probe = np.array([[mid - 0.01, 3.0], [mid + 0.01, 3.0]])
    assert owned(probe, 0, regions).tolist() == [True, False]
    assert owned(probe, 1, regions).tolist() == [False, True]


def test_georeferenced_positions_plan_the_same_tiles():
    positions = np.c_[np.arange(0, 101, 8.0), 0.1 * np.arange(13), np.full(13, 2.0)]
    offset = np.array([512_345.0, 5_612_345.0, 120.0])
    near = plan_tiles(positions)
    far = plan_tiles(positions + offset)
    for a, b in zip(near, far):
        assert np.allclose(b.center_xy - offset[:2], a.center_xy, atol=1e-6) and np.isclose(a.yaw, b.yaw)


def test_each_tile_sits_on_its_own_ground():
    rng = np.random.default_rng(1)
    xy = rng.uniform([-20, -15], [220, 15], (200_000, 2))
    ground = np.c_[xy, 0.08 * xy[:, 0]]                # an 8 % hill
    positions = np.c_[np.arange(0, 201, 10.0), np.zeros(21), 0.08 * np.arange(0, 201, 10.0) + 2]
    for t in plan_tiles(positions):
        r = tile_region(t, ground, (38.4, 38.4, 8.0))
        expect = 0.08 * t.center_xy[0] - 1.0 + 4.0
        assert abs(r.center[2] - expect) < 0.5


@pytest.mark.parametrize("kw, message", [({"overlap": 40.0}, "overlap"), ({"size": -1.0}, "size"),
                                         ({"scans_per_tile": 0}, "scans per tile")])
def test_bad_plan_settings_are_input_errors(kw, message):
    with pytest.raises(InputError, match=message):
        plan_tiles(np.zeros((3, 3)), **kw)
