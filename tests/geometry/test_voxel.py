import numpy as np

from hgca_core.geometry.voxel import cell_centers, downsample, voxelize_coarse, voxelize_fine


def test_fine_rounds_and_coarse_floors_the_fine_cells():
    pts = np.array([[0.04, 0.06, 0.149], [0.26, 0.0, 0.0], [0.36, 0.0, 0.0]])
    fine = voxelize_fine(pts, (10, 10, 10))
    assert fine.tolist() == [[0, 1, 1], [3, 0, 0], [4, 0, 0]]
    coarse = voxelize_coarse(pts, (10, 10, 10))
    assert coarse.tolist() == downsample(fine).tolist()


def test_points_outside_grid_dropped_and_centres_inside_cells():
    pts = np.array([[-0.2, 0, 0], [0.5, 0.5, 0.5], [10.0, 0, 0]])
    fine = voxelize_fine(pts, (20, 20, 20))
    assert fine.tolist() == [[5, 5, 5]]
    c20 = downsample(fine)
    centre = cell_centers(c20, 0.2)[0]
    # the 20 cm cell spans [0.2 c - 0.05, 0.2 c + 0.15): the point must lie inside it
    assert np.all(np.abs(pts[1] - centre) <= 0.1)
