"""The one voxel mesher: cube faces on the cell boundaries, the project's cell convention by default."""
import numpy as np
import pytest

from hgca_core.errors import InputError
from hgca_core.geometry.voxel import cell_centers
from hgca_core.meshing.voxel_mesh import voxel_mesh


def test_single_cell_is_a_closed_cube():
    m = voxel_mesh(np.array([[0, 0, 0]]), 0.2, lower_corner=-0.05)
    assert len(m.faces) == 12 and len(m.vertices) == 8
    assert m.is_watertight
    np.testing.assert_allclose(m.bounds, [[-0.05] * 3, [0.15] * 3])
    assert np.isclose(m.volume, 0.2 ** 3)                 # positive: outward normals


def test_block_hides_inner_faces_and_keeps_its_volume():
    cells = np.stack(np.meshgrid(range(3), range(3), range(3), indexing="ij"), -1).reshape(-1, 3)
    m = voxel_mesh(cells - [1, 2, 3], 1.0, lower_corner=0.0)   # negative cells too
    assert len(m.faces) == 6 * 9 * 2  # only the outer 54 unit squares
    assert m.is_watertight and np.isclose(m.volume, 27.0)
    np.testing.assert_allclose(m.bounds, [[-1, -2, -3], [2, 1, 0]])


def test_default_corner_follows_the_cell_centre_convention():
    c = np.array([[3, 4, 5]])
    for voxel in (0.1, 0.2):
        centre = cell_centers(c, voxel)[0]
        np.testing.assert_allclose(voxel_mesh(c, voxel).bounds, [centre - voxel / 2, centre + voxel / 2], atol=1e-12)
    np.testing.assert_allclose(voxel_mesh(c, 0.2).bounds.mean(0), [0.65, 0.85, 1.05])  # (c + 0.25) * 0.2


def test_empty_and_bad_input():
    assert len(voxel_mesh(np.zeros((0, 3)), 0.1).faces) == 0
    with pytest.raises(InputError, match="lower_corner"):
        voxel_mesh(np.zeros((1, 3), int), 0.3)
    assert len(voxel_mesh(np.zeros((1, 3), int), 0.3, lower_corner=0.0).faces) == 12
    with pytest.raises(InputError, match=r"\(N, 3\)"):
        voxel_mesh(np.zeros((2, 2), int), 0.2)
