"""Unsigned distance -> mesh: analytic fields through the decoder interface, level, seams, cleanup, frames."""
import numpy as np
import pytest
import torch
import trimesh
from scipy.spatial import cKDTree

from hgca_core.meshing import (LEVEL_FRACTION, drop_small_components, udf_grid, udf_grid_points, udf_mesh,
                               udf_surface_points, weld)

pytestmark = pytest.mark.usefixtures("one_thread")


CENTRE = np.array([1.03, 0.97, 1.01])
RADIUS = 0.62


def sphere_udf(q: torch.Tensor) -> torch.Tensor:
    """Exact unsigned distance to a sphere, clamped at one 10 cm cell like the decoder."""
    return ((q - torch.as_tensor(CENTRE, dtype=q.dtype)).norm(dim=1) - RADIUS).abs().clamp(max=0.1)


def band_cells(dist_fn, lo: int = 0, hi: int = 22, width: float = 0.05 * np.sqrt(3)) -> np.ndarray:
    """10 cm cells (centre c * 0.1) with centre distance <= width (default: the cells the surface can cross)."""
    g = np.stack(np.meshgrid(*[np.arange(lo, hi)] * 3, indexing="ij"), -1).reshape(-1, 3)
    d = dist_fn(torch.from_numpy(g * 0.1)).numpy()
    return g[d <= width + 1e-9]


def sphere_dist(p: np.ndarray) -> np.ndarray:
    return np.abs(np.linalg.norm(p - CENTRE, axis=1) - RADIUS)


def test_grid_points_cover_each_cell_box():
    g = udf_grid_points(np.array([[0, 0, 0], [1, 0, 0]]))
    # two face-sharing cells: 3 x 3 x 3 points each, sharing the 3 x 3 face plane
    assert len(g) == 2 * 27 - 9
    assert g[:, 0].min() == -1 and g[:, 0].max() == 3 and np.abs(g[:, 1:]).max() == 1
    with pytest.raises(ValueError):
        udf_grid_points(np.zeros((1, 3)), voxel=0.1, res=0.03)


def test_sphere_shell_lies_on_the_level_set_and_closes():
    cells = band_cells(sphere_udf)
    m = udf_mesh(sphere_udf, cells)
    level = LEVEL_FRACTION * 0.05
    err = np.abs(sphere_dist(m.vertices) - level)
    assert len(m.faces) > 1000
    assert err.mean() < 0.002 and err.max() < 0.008  # linear interpolation of a curved field on a 5 cm grid
    assert m.is_watertight                             # two closed shells, inside and outside the sphere
    assert m.body_count == 2
    r = np.linalg.norm(m.vertices - CENTRE, axis=1)
    assert np.isclose(np.sort(r)[:10].mean(), RADIUS - level, atol=0.01)
    assert np.isclose(np.sort(r)[-10:].mean(), RADIUS + level, atol=0.01)


def test_projection_puts_vertices_on_the_surface():
    cells = band_cells(sphere_udf)
    m = udf_mesh(sphere_udf, cells, project=1)
    assert sphere_dist(m.vertices).max() < 1e-3
    p = udf_surface_points(sphere_udf, cells, project=1)
    assert len(p) > 1000 and sphere_dist(p).max() < 1e-3


def test_no_seams_tile_and_chunk_sizes_give_the_same_mesh():
    cells = band_cells(sphere_udf)
    a = udf_mesh(sphere_udf, cells, tile=64)
    b = udf_mesh(sphere_udf, cells, tile=5, chunk=777)   # many tiles, shells cross every tile face
    assert b.is_watertight and len(a.faces) == len(b.faces) and len(a.vertices) == len(b.vertices)
    for x, y in ((a, b), (b, a)):  # every triangle of one mesh is a triangle of the other
        d, _ = cKDTree(y.triangles.reshape(len(y.faces), 9)).query(x.triangles.reshape(len(x.faces), 9))
        assert d.max() < 1e-6  # float32 marching-cubes coordinates: the same crossings to ~0.1 um


def test_tilted_plane_in_a_sparse_block():
    n = np.array([0.3, -0.2, 1.0]) / np.linalg.norm([0.3, -0.2, 1.0])
    off = 0.537

    def plane(q: torch.Tensor) -> torch.Tensor:
        return (q.double() @ torch.from_numpy(n) - off).abs().clamp(max=0.1).to(q.dtype)

    cells = band_cells(plane, 0, 12, width=0.099)  # thick enough that the shells stay inside the cells
    m = udf_mesh(plane, cells, min_faces=1)
    inner = np.all((m.vertices[:, :2] > 0.1) & (m.vertices[:, :2] < 1.0), axis=1)  # away from the block's rim,
    d = np.abs(m.vertices[inner] @ n - off)                                         # where the shell closes
    err = np.abs(d - LEVEL_FRACTION * 0.05)
    # the field is linear on every grid edge that does not cross the plane itself: there the crossing is exact;
    # edges over the kink of |.| interpolate across it and land a few mm off (inherent to unsigned fields)
    assert inner.sum() > 100 and np.mean(err < 1e-5) > 0.6 and err.max() < 0.008
    mp = udf_mesh(plane, cells, min_faces=1, project=1)
    assert np.abs(mp.vertices @ n - off).max() < 1e-5
    # surface points: every point is within the threshold, and the band covers the plane (no holes)
    p = udf_surface_points(plane, cells)
    assert np.abs(p @ n - off).max() < 0.05
    xy = np.unique(np.round(p[:, :2] / 0.05).astype(int), axis=0)
    lo, hi = cells[:, :2].min(0) * 2 + 4, cells[:, :2].max(0) * 2 - 4
    want = {(i, j) for i in range(lo[0], hi[0]) for j in range(lo[1], hi[1])}
    assert want <= set(map(tuple, xy))


def test_frame_shift_and_grid_values():
    cells = band_cells(sphere_udf)
    g, vals = udf_grid(sphere_udf, cells)
    assert vals.dtype == np.float32 and len(g) == len(vals)
    np.testing.assert_allclose(vals, sphere_udf(torch.from_numpy(g * 0.05)).numpy(), atol=1e-6)
    a = udf_mesh(sphere_udf, cells)
    b = udf_mesh(sphere_udf, cells, lower_corner=np.array([10.0, 20.0, 30.0]) - 0.05)
    np.testing.assert_allclose(np.sort(b.vertices, axis=0), np.sort(a.vertices + [10.0, 20.0, 30.0], axis=0))


def test_cleanup_drops_specks_and_welds_duplicates():
    small_c = np.array([0.35, 0.35, 0.35])

    def two_spheres(q: torch.Tensor) -> torch.Tensor:
        big = sphere_udf(q)
        small = ((q - torch.as_tensor(small_c, dtype=q.dtype)).norm(dim=1) - 0.01).abs()
        return torch.minimum(big, small).clamp(max=0.1)

    cells = band_cells(two_spheres)
    kept = udf_mesh(two_spheres, cells, min_faces=1)
    cleaned = udf_mesh(two_spheres, cells, min_faces=200)
    assert kept.body_count == 3 and cleaned.body_count == 2   # the speck is one small closed blob
    assert np.linalg.norm(cleaned.vertices - small_c, axis=1).min() > 0.3
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1e-9, 0, 0], [1, 0, 0]], float)
    f = np.array([[0, 1, 2], [3, 4, 2], [0, 0, 1]])
    wv, wf = weld(v, f)
    assert len(wv) == 3 and len(wf) == 1                      # duplicate and degenerate faces gone
    cv, cf = weld(v, f, candidates=np.array([True, True, False, True, True]))
    np.testing.assert_array_equal(cv, wv)
    np.testing.assert_array_equal(cf, wf)                     # the same when the twins are candidates
    nv, nf = weld(v, f, candidates=np.zeros(5, bool))
    assert len(nv) == 5 and len(nf) == 2                      # no candidates: no merge, degenerate face still gone
    dv, df = drop_small_components(wv, wf, min_faces=2)
    assert len(dv) == 0 and len(df) == 0


def test_empty_and_bad_level():
    assert len(udf_mesh(sphere_udf, np.zeros((0, 3), int)).faces) == 0
    assert len(udf_surface_points(sphere_udf, np.zeros((0, 3), int))) == 0
    with pytest.raises(ValueError):
        udf_mesh(sphere_udf, band_cells(sphere_udf), level=0.2)


def test_decimate_keeps_the_surface_with_fewer_faces():
    from hgca_core.meshing import decimate

    mesh = udf_mesh(sphere_udf, band_cells(sphere_udf))
    n = len(mesh.faces)
    small = decimate(mesh, n // 5)
    assert len(small.faces) <= n // 5 and len(small.faces) > n // 10
    # every simplified vertex stays on the original surface (within a millimetre-scale tolerance)
    _, dist, _ = trimesh.proximity.closest_point(mesh, small.vertices)
    assert dist.max() < 0.01, dist.max()
    assert decimate(mesh, n) is mesh                       # nothing to do
    with pytest.raises(ValueError):
        decimate(mesh, 0)
