"""The one voxeliser: 10 cm cells by rounding, 20 cm cells by flooring those, the region's 10 cm grid crop."""
import numpy as np
import pytest

from hgca_core.errors import InputError
from hgca_core.geometry.voxel import cell_centers, downsample, grid_shape, lower_corner, point_cells, voxelize


def _naive(points, voxel, size=None):
    """Reference: per point, round to 10 cm, floor by 2 for 20 cm; np.unique over rows."""
    c = np.round(np.asarray(points, np.float64) / 0.1).astype(np.int64)
    if size is not None:
        c = c[np.all((c >= 0) & (c < np.round(np.asarray(size) / 0.1)), axis=1)]
    if voxel == 0.2:
        c = np.floor_divide(c, 2)
    return np.unique(c, axis=0).reshape(-1, 3)


def test_fine_rounds_and_coarse_floors_the_fine_cells():
    pts = np.array([[0.04, 0.06, 0.149], [0.26, 0.0, 0.0], [0.36, 0.0, 0.0]])
    assert voxelize(pts, 0.1).tolist() == [[0, 1, 1], [3, 0, 0], [4, 0, 0]]
    # 0.149 rounds to 10 cm cell 1 -> 20 cm cell 0; a direct floor of 0.149 / 0.2 would agree, but
    # x = 0.16 rounds to cell 2 -> 20 cm cell 1, where floor(0.16 / 0.2) = 0
    assert voxelize(np.array([[0.16, 0.0, 0.0]]), 0.2).tolist() == [[1, 0, 0]]
    assert voxelize(pts, 0.2).tolist() == downsample(voxelize(pts, 0.1)).tolist() == [[0, 0, 0], [1, 0, 0], [2, 0, 0]]


def test_negative_points_round_then_floor():
    pts = np.array([[-0.04, 0.0, 0.0], [-0.06, 0.0, 0.0], [-0.16, 0.0, 0.0], [-0.26, 0.0, 0.0]])
    assert point_cells(pts, 0.1)[:, 0].tolist() == [0, -1, -2, -3]
    assert point_cells(pts, 0.2)[:, 0].tolist() == [0, -1, -1, -2]   # floor, not truncation towards 0


def test_region_crop_is_on_the_10cm_grid():
    size = np.array([1.3, 1.0, 1.0])             # 13 x 10 x 10 cells of 10 cm: an odd x grid
    assert grid_shape(size, 0.1) == (13, 10, 10) and grid_shape(size, 0.2) == (6, 5, 5)
    pts = np.array([[-0.2, 0.5, 0.5], [-0.04, 0.5, 0.5], [1.24, 0.5, 0.5], [1.26, 0.5, 0.5], [0.5, 0.5, 1.2]])
    assert voxelize(pts, 0.1, size).tolist() == [[0, 5, 5], [12, 5, 5]]
    # the last, half-filled 20 cm layer (10 cm cell 12 -> 20 cm cell 6) is kept
    assert voxelize(pts, 0.2, size).tolist() == [[0, 2, 2], [6, 2, 2]]


@pytest.mark.parametrize("voxel", [0.1, 0.2])
def test_dense_and_sparse_paths_match_a_naive_reference(voxel, monkeypatch):
    rng = np.random.default_rng(3)
    pts = rng.uniform(-1.0, 9.0, (20_000, 3))
    size = np.array([8.0, 7.9, 4.0])
    ref = _naive(pts, voxel, size)
    assert np.array_equal(voxelize(pts, voxel, size), ref)                   # dense grid
    monkeypatch.setattr("hgca_core.geometry.voxel.DENSE_CELLS", 0)
    assert np.array_equal(voxelize(pts, voxel, size), ref)                   # sorted keys
    assert np.array_equal(voxelize(pts, voxel), _naive(pts, voxel))          # no region: nothing dropped


def test_other_voxel_sizes_are_refused():
    with pytest.raises(InputError, match="0.1 or 0.2"):
        voxelize(np.zeros((1, 3)), 0.3)


def test_centres_and_corners_follow_the_rule():
    pts = np.array([[0.5, 0.5, 0.5], [0.149, 0.0, 0.0]])
    for voxel in (0.1, 0.2):
        c = point_cells(pts, voxel)
        lo = lower_corner(voxel) + c * voxel
        assert np.all((pts >= lo - 1e-12) & (pts < lo + voxel))              # each point lies in its cell
        assert np.allclose(cell_centers(c, voxel), lo + voxel / 2)
    assert lower_corner(0.1) == pytest.approx(-0.05) and lower_corner(0.2) == pytest.approx(-0.05)


def test_column_tops_is_the_highest_occupied_cell_or_minus_one():
    from hgca_core.geometry.voxel import column_tops

    occ = np.zeros((3, 2, 6), dtype=bool)
    occ[0, 0, [1, 4]] = True       # a gap below the top does not matter
    occ[1, 1, 0] = True
    occ[2, 0, 5] = True
    np.testing.assert_array_equal(column_tops(occ), [[4, -1], [-1, 0], [5, -1]])
