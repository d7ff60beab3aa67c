"""Per-group least-squares planes: exact planes recovered far from the origin, weights honoured, degenerate groups
flagged."""
import numpy as np

from hgca_core.geometry.planes import fit_planes


def test_planes_per_group_weights_and_degenerate_groups():
    rng = np.random.default_rng(0)
    xy = rng.uniform(0, 4, size=(600, 2)) + [5.0e5, 4.2e6]            # georeferenced magnitudes
    group = np.repeat([0, 1, 2], 200)
    truth = np.array([[0.02, -0.01, 30.0], [0.0, 0.05, 31.0], [0.1, 0.1, 29.0]])
    z = np.einsum("ij,ij->i", truth[group, :2], xy - [5.0e5, 4.2e6]) + truth[group, 2]
    pts = np.c_[xy, z]
    fit = fit_planes(pts, group, 4)
    np.testing.assert_allclose(fit.slope[:3], truth[:, :2], atol=1e-9)
    np.testing.assert_allclose(fit.height(group, xy), z, atol=1e-6)
    assert np.all(fit.rss[:3] < 1e-12) and fit.weight[3] == 0 and fit.det[3] == 0   # group 3 is empty
    # an outlier with weight ~0 does not tilt the plane; with weight 1 it does
    out = np.r_[pts, [[5.0e5 + 2, 4.2e6 + 2, 40.0]]]
    g = np.r_[group, 0]
    light = fit_planes(out, g, 3, np.r_[np.ones(600), 1e-9])
    heavy = fit_planes(out, g, 3)
    assert np.abs(light.slope[0] - truth[0, :2]).max() < 1e-6 < np.abs(heavy.slope[0] - truth[0, :2]).max()
    assert heavy.rss[0] > 1.0
    # collinear points: no plane (det ~ 0 relative to the spread)
    line = np.c_[np.linspace(0, 1, 10), np.linspace(0, 2, 10), np.zeros(10)]
    f = fit_planes(line, np.zeros(10, np.int64), 1)
    assert f.det[0] <= 1e-12 * f.sxx[0] * f.syy[0]
