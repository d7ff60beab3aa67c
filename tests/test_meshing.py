import numpy as np

from hgca_core.meshing import voxel_mesh


def test_single_cell_is_a_closed_cube():
    m = voxel_mesh(np.array([[0, 0, 0]]), 0.2, lower_corner=-0.05)
    assert len(m.faces) == 12 and len(m.vertices) == 8
    assert m.is_watertight
    np.testing.assert_allclose(m.bounds, [[-0.05] * 3, [0.15] * 3])
    assert np.isclose(m.volume, 0.2 ** 3)


def test_block_hides_inner_faces():
    cells = np.stack(np.meshgrid(range(3), range(3), range(3), indexing="ij"), -1).reshape(-1, 3)
    m = voxel_mesh(cells, 1.0)
    assert len(m.faces) == 6 * 9 * 2  # only the outer 54 unit squares
    assert m.is_watertight and np.isclose(m.volume, 27.0)


def test_empty():
    assert len(voxel_mesh(np.zeros((0, 3)), 0.1).faces) == 0
