"""The completion path's nearest-point index against brute force: exact distances and indices, the bound, and the
empty cases."""
import numpy as np

from hgca_core.geometry.nearest import PointIndex


def brute(points: np.ndarray, queries: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    d = np.linalg.norm(queries[:, None, :] - points[None], axis=2)
    return d.min(1), d.argmin(1)


def test_matches_brute_force_near_and_far():
    rng = np.random.default_rng(0)
    pts = np.c_[rng.uniform(0, 10, (2000, 2)), rng.normal(0, 0.01, 2000)]      # a noisy ground
    q = np.r_[pts[:200] + rng.normal(0, 0.02, (200, 3)), rng.uniform([0, 0, 1], [10, 10, 6], (300, 3))]
    d, i = PointIndex(pts).nearest(q)
    bd, bi = brute(pts, q)
    assert np.allclose(d, bd, atol=1e-12) and np.array_equal(i, bi)
    assert i.dtype == np.int64 and d.dtype == np.float64


def test_upper_bound_and_empty_sets():
    pts = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    d, i = PointIndex(pts).nearest(np.array([[0.1, 0, 0], [0.5, 3, 0]]), upper=0.5)
    assert np.isclose(d[0], 0.1) and i[0] == 0 and np.isinf(d[1]) and i[1] == -1
    d, i = PointIndex(np.zeros((0, 3))).nearest(np.ones((2, 3)))
    assert np.isinf(d).all() and (i == -1).all()
    assert PointIndex(pts).distances(np.zeros((0, 3))).shape == (0,)
