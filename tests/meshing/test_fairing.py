"""Ground fairing: terraces between scan rings flattened onto the rings, while planes (sloped too), kerbs, small
domes and steep surfaces keep their shape."""
import numpy as np
import pytest

from hgca_core.meshing.fairing import fair_ground
from hgca_core.meshing.mesh_clean import adjacency

H = 0.05   # grid spacing of the test meshes, like the 5 cm extraction grid


def grid_mesh(n: int, height, xs: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """An n x n height-field mesh z = height(x, y) on a 5 cm grid (or columns at `xs`), two triangles per
    square."""
    xs = np.arange(n) * H if xs is None else np.asarray(xs)
    x, y = np.meshgrid(xs, np.arange(n) * H, indexing="ij")
    v = np.c_[x.ravel(), y.ravel(), height(x.ravel(), y.ravel())]
    i = (np.arange(n - 1)[:, None] * n + np.arange(n - 1)[None]).ravel()
    f = np.r_[np.c_[i, i + n, i + 1], np.c_[i + 1, i + n, i + n + 1]]
    return v, f


def ring_distances(v: np.ndarray, rings_y: tuple[float, ...]) -> np.ndarray:
    """Distance of each vertex to the nearest 'scan ring' (a line of input points at y = r, z = 0)."""
    return np.min(np.stack([np.hypot(v[:, 1] - r, v[:, 2]) for r in rings_y]), axis=0)


def plane_rms(v: np.ndarray) -> float:
    a = np.c_[v[:, :2], np.ones(len(v))]
    coef = np.linalg.lstsq(a, v[:, 2], rcond=None)[0]
    return float(np.sqrt(np.mean((v[:, 2] - a @ coef) ** 2)))


def test_adjacency_of_a_grid():
    v, f = grid_mesh(4, lambda x, y: 0 * x)
    adj = adjacency(f, len(v))
    assert (adj != adj.T).nnz == 0 and adj.diagonal().sum() == 0 and set(adj.data) == {1.0}
    assert adj.nnz == 2 * (2 * 4 * 3 + 3 * 3)          # grid edges + one diagonal per square, both directions
    assert adj[5, 6] == 1 and adj[5, 8] == 1 and adj[5, 10] == 0   # a grid neighbour, its diagonal, not the other


def test_terraces_between_rings_flatten_onto_the_rings():
    """The fine stage's defect in miniature: ground exact at the rings (y = 0.5, 2.5, 4.5 m), generated between
    them on terraces 3 cm above or below. After fairing the road is flat and where the rings say it is."""
    rings = (0.5, 2.5, 4.5)

    def terraces(x, y):
        far = np.min(np.abs(np.subtract.outer(y, rings)), axis=1) > 0.3
        return np.where(far, np.where(x < 2.5, 0.03, -0.03), 0.0)

    v, f = grid_mesh(100, terraces)
    d = ring_distances(v * [1, 1, 0], rings)             # the rings' points lie at z = 0
    before = plane_rms(v)
    out, rep = fair_ground(v, f, d)
    assert before > 0.015
    assert plane_rms(out) < 0.25 * before
    assert np.abs(out[:, 2]).mean() < 0.005                 # flat at the rings' height, not at the terraces' mean
    on_ring = d < 0.01
    assert np.abs(out[on_ring, 2] - v[on_ring, 2]).max() < 0.003
    assert rep.ground == len(v) and rep.max_move <= 0.1


def test_anchors_pull_to_the_points_heights_when_given():
    """The decoded ground sits 8 mm below the rings' points (as on the AV2 log, where it is 1-6 mm low): with the
    points' heights as targets the faired road goes to the rings' height, at the rings and between them; without,
    the anchors hold the decoded height and the road stays low."""
    rings = (0.5, 1.5, 2.5, 3.5, 4.5)
    v, f = grid_mesh(100, lambda x, y: 0 * x - 0.008)
    d = ring_distances(v * [1, 1, 0], rings)
    heights = np.where(d < 0.06, 0.0, np.nan)               # the nearest point's height (0) where one is near
    held = fair_ground(v, f, d)[0]
    pulled = fair_ground(v, f, d, point_heights=heights)[0]
    assert np.abs(held[:, 2] + 0.008).max() < 1e-4
    on_ring, between = d < 0.01, d > 0.3
    assert np.abs(pulled[on_ring, 2]).max() < 0.002 and np.abs(pulled[between, 2]).max() < 0.003
    assert np.abs(fair_ground(v, f, d, point_heights=np.full(len(v), np.nan))[0] - held).max() < 1e-6


def test_the_pull_is_the_local_mean_offset_not_each_points_noise():
    """Ring points with 1 cm of noise each, 8 mm above the decoded ground on average: pulled to the local mean
    offset the road rises 8 mm and stays smooth along the rings; pulled to each vertex's own point
    (offset_tile 0) it takes on the points' noise."""
    rings = (0.5, 1.5, 2.5, 3.5, 4.5)
    v, f = grid_mesh(100, lambda x, y: 0 * x - 0.008)
    d = ring_distances(v * [1, 1, 0], rings)
    noise = np.random.default_rng(0).normal(0, 0.01, len(v))
    heights = np.where(d < 0.06, noise, np.nan)
    mean = fair_ground(v, f, d, point_heights=heights)[0]
    each = fair_ground(v, f, d, point_heights=heights, offset_tile=0)[0]
    on_ring = d < 0.01
    assert abs(mean[on_ring, 2].mean()) < 0.002 and mean[on_ring, 2].std() < 0.003
    assert each[on_ring, 2].std() > 2.5 * mean[on_ring, 2].std()


@pytest.mark.parametrize("slope", [0.0, 0.05, 0.15])
def test_planes_are_fixed_points_with_or_without_evidence(slope):
    """Also at the border: a membrane on the raw heights would bend a 5 % slope by 10 cm there (away from any
    point); relative to the local planes it leaves every plane where it is."""
    v, f = grid_mesh(80, lambda x, y: slope * x + 0.02 * y + 1.0)
    for d in (None, ring_distances(v, (1.0,)) + 0.5):        # no points at all / points far away
        out, _ = fair_ground(v, f, d)
        assert np.abs(out[:, 2] - v[:, 2]).max() < 1e-4


def test_a_crest_scanned_by_rings_keeps_its_shape_and_noise_does_not_drift():
    def crest(x, y):
        return 0.05 * x - 0.0025 * (x - 2) ** 2     # a vertical curve of radius 200 m

    v, f = grid_mesh(80, crest)                    # a road over a crest, scan rings across it every metre
    rings = np.array([0.5, 1.5, 2.5, 3.5])
    d = np.min(np.hypot(np.subtract.outer(v[:, 0], rings), np.subtract.outer(v[:, 2], crest(rings, 0))), axis=1)
    out, _ = fair_ground(v, f, d)
    assert np.abs(out[:, 2] - v[:, 2]).max() < 0.005
    noise = np.random.default_rng(1).normal(0, 0.01, 80 * 80)
    v, f = grid_mesh(80, lambda x, y: noise)
    out, _ = fair_ground(v, f, None)
    assert abs(out[:, 2].mean()) < 1e-3 and out[:, 2].std() < 0.2 * v[:, 2].std()


def test_a_kerb_keeps_its_height():
    """A 12 cm kerb (a near-vertical face through columns at x = 1.99, 2.0, 2.01 m) between noisy road and
    sidewalk: a steep part that tall bounds the membrane; road and sidewalk flatten, each at its own height."""
    rng = np.random.default_rng(0)
    xs = np.sort(np.r_[np.arange(80) * H, 1.99, 2.01])
    noise = rng.normal(0, 0.01, 82 * 82)

    def kerb(x, y):
        return np.where(x > 2.005, 0.12, np.where(x > 1.995, 0.06, 0.0)) + noise

    v, f = grid_mesh(82, kerb, xs)
    out, _ = fair_ground(v, f, None)
    road, walk = v[:, 0] < 1.7, v[:, 0] > 2.3
    assert abs(out[road, 2].mean() - 0.0) < 0.003 and abs(out[walk, 2].mean() - 0.12) < 0.003
    assert out[road, 2].std() < 0.5 * v[road, 2].std() and out[walk, 2].std() < 0.5 * v[walk, 2].std()


def test_small_regions_and_steep_surfaces_are_untouched():
    # a 1.5 x 1.5 m dome (a car roof: under min_region) and a wall-like steep ramp
    dome_v, dome_f = grid_mesh(30, lambda x, y: 0.1 - 0.2 * ((x - 0.75) ** 2 + (y - 0.75) ** 2))
    out, rep = fair_ground(dome_v, dome_f, None)
    assert rep.ground == 0 and np.array_equal(out, dome_v)
    ramp_v, ramp_f = grid_mesh(80, lambda x, y: 1.2 * x + 0.01 * np.sin(7 * y))
    out, rep = fair_ground(ramp_v, ramp_f, None)
    assert rep.ground == 0 and np.array_equal(out, ramp_v)


def test_moves_are_bounded_and_empty_meshes_pass():
    v, f = grid_mesh(60, lambda x, y: np.where((x > 1.0) & (x < 2.0), 0.4, 0.0) * 0 + np.where(x > 1.5, 0.09, 0.0))
    out, rep = fair_ground(v, f, None, max_move=0.02)
    assert np.abs(out[:, 2] - v[:, 2]).max() <= 0.02 + 1e-12
    out, rep = fair_ground(np.zeros((0, 3)), np.zeros((0, 3), np.int64))
    assert out.shape == (0, 3) and rep.ground == 0
    with pytest.raises(ValueError, match="free_weight"):
        fair_ground(v, f, None, free_weight=0.0)


def _membrane(n: int, seed: int):
    """A fairing-like system (diag(deg + w) - L of a random grid mesh's subgraph, float32) and a right side."""
    from scipy.sparse import diags

    rng = np.random.default_rng(seed)
    v, f = grid_mesh(n, lambda x, y: 0 * x)
    adj = adjacency(f, len(v))
    w = rng.uniform(3e-4, 10.0, len(v)) * (rng.random(len(v)) < 0.3) + 3e-4
    diag = (np.diff(adj.indptr) + w).astype(np.float32)
    return (diags(diag) - adj).tocsr(), rng.normal(size=len(v)).astype(np.float32), diag


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_own_cg_is_scipys_cg_bit_for_bit(seed):
    """The fairing's CG replays scipy's Jacobi-preconditioned `cg` step for step: the same solution to the last
    bit and the same iteration count, converged or stopped by max_iter."""
    from scipy.sparse import diags
    from scipy.sparse.linalg import cg

    from hgca_core.meshing.fairing import _cg

    a, b, diag = _membrane(30, seed)
    for tol, max_iter in ((1e-3, 500), (1e-6, 7)):
        steps = []
        want, _ = cg(a, b, rtol=tol, maxiter=max_iter, M=diags(1.0 / diag), callback=lambda x: steps.append(1))
        got, iterations = _cg(a, b, 1.0 / diag, tol, max_iter)
        assert got.dtype == want.dtype and got.tobytes() == want.tobytes()
        assert iterations == len(steps) > 0
    zero, iterations = _cg(a, np.zeros_like(b), 1.0 / diag, 1e-3, 500)
    assert iterations == 0 and not zero.any()


def test_subgraph_is_scipys_fancy_index():
    """`_subgraph(adj, idx)` is `adj[idx][:, idx]`: the same rows, columns (sorted) and values."""
    from hgca_core.meshing.fairing import _subgraph

    rng = np.random.default_rng(4)
    v, f = grid_mesh(25, lambda x, y: 0 * x)
    adj = adjacency(f, len(v))
    for keep in (0.5, 0.95, 0.0, 1.0):
        idx = np.flatnonzero(rng.random(len(v)) < keep)
        want, got = adj[idx][:, idx], _subgraph(adj, idx)
        assert got.shape == want.shape and (got != want).nnz == 0
        want.sort_indices()
        np.testing.assert_array_equal(got.indptr, want.indptr)
        np.testing.assert_array_equal(got.indices, want.indices)
        assert got.data.dtype == want.data.dtype


def test_anchors_from_the_point_index_equal_given_distances():
    """fair_ground(points=index) looks up only the ground-like vertices: the same heights, bit for bit, as
    passing every vertex's nearest distance and height."""
    from hgca_core.meshing.fairing import ANCHOR_SCALE
    from hgca_core.geometry.nearest import PointIndex

    rng = np.random.default_rng(6)
    v, f = grid_mesh(60, lambda x, y: 0.02 * np.sin(3 * x) + np.where(y > 1.5, 0.3, 0.0))   # ground and a step
    pts = np.c_[rng.uniform(0, 3, (4000, 2)), rng.normal(0, 0.005, 4000)]
    index = PointIndex(pts)
    near, which = index.nearest(v, upper=3 * ANCHOR_SCALE)
    heights = np.where(which >= 0, index.points[which, 2], np.nan)
    want = fair_ground(v, f, near, point_heights=heights, min_region=1.0)
    got = fair_ground(v, f, points=index, min_region=1.0)
    assert got[0].tobytes() == want[0].tobytes() and got[1] == want[1] and got[1].ground > 0
