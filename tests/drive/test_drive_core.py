"""The core hook a drive needs: `complete_local(..., fixed_cells=)` puts extra cells in s0 exactly as observed
cells (so with none the run is bit-identical), and `transfer_cells` carries a neighbour's cells into a tile."""
import numpy as np
import pytest

from hgca_testdata import tiny_sample
from hgca_core.geometry.region import Region
from hgca_core.geometry.voxel import COARSE, cell_centers
from hgca_core.pipeline import complete_local, load_models
from hgca_core.tiling.tile import transfer_cells


@pytest.fixture(scope="module")
def setup(drive_weights):
    s = tiny_sample(3)
    return s["input_points"].astype(np.float64), Region.from_tuple(s["region"]), load_models("coarse", drive_weights)


def run(setup, points=None, **kw):
    pts, region, models = setup
    return complete_local(pts if points is None else points, region, models, **{"stage": "coarse", "samples": 2,
                                                                               "seed": 7, "t1": 3, **kw})


def same(a, b):
    return all(np.array_equal(x.coarse_cells, y.coarse_cells) and np.array_equal(x.mesh.vertices, y.mesh.vertices)
               and np.array_equal(x.mesh.faces, y.mesh.faces) for x, y in zip(a, b))


def test_no_fixed_cells_is_bit_identical(setup, one_thread):
    plain = run(setup)
    assert same(plain, run(setup, fixed_cells=None))
    assert same(plain, run(setup, fixed_cells=np.zeros((0, 3), np.int64)))
    assert same(plain, run(setup, fixed_cells=np.array([[-1, 0, 0], [0, 10_000, 0]])))   # outside: ignored


def test_fixed_cells_act_exactly_like_observed_cells(setup, one_thread):
    pts, region, _ = setup
    wall = np.array([[x, 25, z] for x in range(2, 28) for z in range(3, 15)])   # cells no point covers
    with_cells = run(setup, fixed_cells=wall)
    as_points = run(setup, points=np.concatenate([pts, cell_centers(wall, COARSE)]))
    assert same(with_cells, as_points)
    assert not same(with_cells, run(setup))


def test_each_sample_can_have_its_own_fixed_cells(setup, one_thread):
    """A drive tile completes its k samples in one call, sample i joining its neighbours' sample i: the same meshes
    as k calls of one sample each (seed + i), with the free space and the input's cells made once."""
    wall = np.array([[x, 25, z] for x in range(2, 28) for z in range(3, 15)])
    post = np.array([[15, 5, z] for z in range(3, 20)])
    both = run(setup, fixed_cells=[wall, post])
    one_by_one = [run(setup, fixed_cells=f, samples=1, seed=7 + i)[0] for i, f in enumerate((wall, post))]
    assert same(both, one_by_one) and len(both) == 2
    assert not same(both, run(setup, fixed_cells=wall))      # sample 1 did not get sample 0's cells
    with pytest.raises(ValueError, match="2 samples"):
        run(setup, fixed_cells=[wall])


def test_transfer_cells_between_frames():
    a = Region(np.array([10.0, 0.0, 3.0]), np.array([12.8, 12.8, 8.0]), 0.0)
    cells = np.array([[10, 10, 5], [63, 5, 5], [40, 60, 39]])
    assert np.array_equal(transfer_cells(cells, a, a), cells[np.lexsort(cells.T[::-1])])
    b = Region(a.center + [6.4, 0.0, 0.0], a.size, 0.0)       # 32 cells further along x
    assert np.array_equal(transfer_cells(cells, a, b), [[8, 60, 39], [31, 5, 5]])
    # turned a quarter about the same centre: c's x is a's y, c's y is 12.8 m - a's x; cell boxes start at -5 cm,
    # so a's cell i lies across c's cells 63 - i and 64 - i: its centre picks one, nothing is thickened
    c = Region(a.center, a.size, np.pi / 2)
    moved = transfer_cells(cells, a, c)
    assert len(moved) == 3
    for x, y, z in cells:
        assert any(m[0] == y and m[1] in (63 - x, 64 - x) and m[2] == z for m in moved.tolist())
    # grids offset by half a cell (3 mm of ground height can do that at a boundary): still one cell per cell
    d = Region(a.center + [0.1, 0.1, 0.1], a.size, 0.0)
    assert len(transfer_cells(cells, a, d)) == len(cells)
