"""Ground flatness and layer counts of the mesh-quality benchmark: plane fits, patch selection, vertical rays."""
import numpy as np
import trimesh

from hgca_core.metrics.flatness import (Patches, flat_patches_from_labels, flat_patches_from_points, ground_report,
                                        plane_rms)


def test_plane_rms_is_the_residual_to_each_groups_plane():
    rng = np.random.default_rng(0)
    xy = rng.uniform(0, 2, size=(4000, 2))
    group = (xy[:, 0] > 1).astype(int)
    sigma = np.array([0.004, 0.02])
    z = 0.3 * xy[:, 0] - 0.1 * xy[:, 1] + 5.0 + rng.normal(size=len(xy)) * sigma[group]   # tilted planes + noise
    rms, n = plane_rms(np.c_[xy, z], group, 3)
    np.testing.assert_allclose(rms[:2], sigma, rtol=0.08)
    assert n.tolist()[:2] == np.bincount(group).tolist() and np.isnan(rms[2]) and n[2] == 0
    # the naive reference: least squares per group
    for g in (0, 1):
        p = np.c_[xy, z][group == g]
        A = np.c_[p[:, :2], np.ones(len(p))]
        res = p[:, 2] - A @ np.linalg.lstsq(A, p[:, 2], rcond=None)[0]
        assert np.isclose(rms[g], np.sqrt(np.mean(res ** 2)))


def test_patches_skip_kerbs_and_objects():
    rng = np.random.default_rng(1)
    road = np.c_[rng.uniform(0, 6, (6000, 2)), np.zeros(6000)]
    label = np.zeros(len(road), int)
    road[road[:, 0] > 3, 2] = 0.14                       # a sidewalk from x = 3 m: a kerb inside patch x 2-4
    label[road[:, 0] > 3] = 1
    car = np.c_[rng.uniform(0.5, 1.5, (500, 2)) + [0, 2], rng.uniform(0.2, 1.4, 500)]   # a car on patch (0, 2)
    p = flat_patches_from_labels(np.r_[road, car], np.r_[label, np.full(500, 3)], min_points=100)
    got = {tuple(c) for c in p.corners}
    assert (0.0, 0.0) in got and (4.0, 0.0) in got      # pure road, pure sidewalk
    assert (0.0, 2.0) not in got                         # the car
    assert not any(c[0] == 2.0 for c in got)             # the kerb
    assert np.isclose(p.height[np.flatnonzero((p.corners == [4.0, 0.0]).all(1))[0]], 0.14)
    q = flat_patches_from_points(np.r_[road, car], min_points=100)
    got = {tuple(c) for c in q.corners}
    assert (0.0, 0.0) in got and (4.0, 0.0) in got
    assert (0.0, 2.0) not in got                         # the car stands on flat road: not a ground patch
    assert not any(c[0] == 2.0 for c in got)             # the kerb: two planes
    every = flat_patches_from_points(np.r_[road, car], min_points=100, max_above=1.0)
    assert (0.0, 2.0) in {tuple(c) for c in every.corners}   # the flat bottom alone would take it


def test_rays_count_layers_and_measure_flatness():
    plane = trimesh.creation.box(extents=(4, 4, 0.001))                     # two sheets 1 mm apart: one surface
    patches = Patches(np.array([[-1.0, -1.0]]), np.array([0.0]))
    r = ground_report(plane, patches)
    assert r["one_layer"] == 1.0 and r["rms_mesh"] < 1e-6
    shell = trimesh.creation.box(extents=(4, 4, 0.06))                      # a 6 cm shell: two layers
    r = ground_report(shell, patches)
    assert r["two_plus"] == 1.0
    bumpy = trimesh.creation.box(extents=(4, 4, 0.001))
    v = bumpy.vertices.copy()
    bumpy = trimesh.Trimesh(*trimesh.remesh.subdivide_to_size(v, bumpy.faces, 0.05))
    bumpy.vertices[:, 2] += 0.01 * np.sin(bumpy.vertices[:, 0] * 2 * np.pi / 0.5)   # 1 cm ripples, 0.5 m apart
    r = ground_report(bumpy, patches, {"flat": np.c_[np.random.default_rng(2).uniform(-1, 1, (500, 2)), np.zeros(500)]})
    assert 0.004 < r["rms_mesh"] < 0.0075 and r["rms_flat"] < 1e-9             # sin RMS: 1 cm / sqrt(2)


def test_height_error_against_the_truth_plane():
    """Flat is not enough: a perfectly flat mesh 2 cm above the true road has RMS 0 but error 2 cm."""
    n = 41
    x, y = np.meshgrid(np.linspace(0, 4, n), np.linspace(0, 4, n), indexing="ij")
    i = (np.arange(n - 1)[:, None] * n + np.arange(n - 1)[None]).ravel()
    faces = np.r_[np.c_[i, i + n, i + 1], np.c_[i + 1, i + n, i + n + 1]]
    truth = np.c_[x.ravel(), y.ravel(), 0.01 * x.ravel()]
    patches = Patches(np.array([[0.0, 0.0], [2.0, 2.0]]), np.array([0.01, 0.03]))
    for lift in (0.0, 0.02):
        mesh = trimesh.Trimesh(truth + [0, 0, lift], faces, process=False)
        r = ground_report(mesh, patches, truth=truth)
        assert r["rms_mesh"] < 1e-6 and abs(r["rms_to_truth"] - lift) < 1e-6
