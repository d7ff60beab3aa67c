"""The semantic head: its features, output shape, determinism, training targets and the labelling of meshes."""
from __future__ import annotations

import subprocess
import sys

import numpy as np
import torch
import trimesh

from hgca_core.io.classes import CLASS_NAMES
from hgca_core.models.semantics import (SemanticHead, SemanticsConfig, agreement, cell_features, face_labels,
                                        fitted_ground, label_completions, observed_mask, predict)
from hgca_core.synth.assets import LABEL_NAMES
from hgca_core.training.semantics import cell_labels, class_iou, confusion, perturb


def street_cells(slope: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """A toy street of 20 cm cells: ground (label 0) on a slope, a wall (2) and a pole (5)."""
    x, y = np.meshgrid(np.arange(60), np.arange(40), indexing="ij")
    gz = np.floor(5 + slope * x).astype(np.int64)
    ground = np.c_[x.ravel(), y.ravel(), gz.ravel()]
    wall = np.array([(50, j, k) for j in range(40) for k in range(int(5 + slope * 50) + 1, 35)])
    pole = np.array([(20, 20, k) for k in range(int(5 + slope * 20) + 1, 25)])
    cells = np.r_[ground, wall, pole]
    _, first = np.unique(cells, axis=0, return_index=True)
    labels = np.r_[np.zeros(len(ground)), np.full(len(wall), 2), np.full(len(pole), 5)].astype(np.uint8)
    return cells[np.sort(first)], labels[np.sort(first)]


def head(seed: int = 0) -> SemanticHead:
    torch.manual_seed(seed)
    return SemanticHead(SemanticsConfig()).eval()


def test_class_names_are_the_synthetic_labels():
    assert CLASS_NAMES == tuple(LABEL_NAMES)


def test_fitted_ground_follows_a_slope_and_ignores_walls():
    cells, labels = street_cells(slope=0.1)
    g = fitted_ground(cells)
    want = (np.floor(5 + 0.1 * cells[:, 0]) + 0.5) * 0.2
    road = labels == 0
    # the lowest cell within a 6 m window is at most 0.6 m of slope below (3 tiles of 2 m at 10 %)
    assert np.all(g[road] <= want[road] + 1e-9) and np.all(want[road] - g[road] <= 0.61)
    hag = (cells[:, 2] + 0.5) * 0.2 - g
    assert hag[labels == 2].max() > 4.0 and np.abs(hag[road]).max() < 0.61


def test_features_and_output_shape():
    cells, _ = street_cells()
    obs = cells[:, 0] < 30
    f = cell_features(cells, obs)
    assert f.shape == (len(cells), 3 + 2 * SemanticsConfig().pe_freq) and f.dtype == np.float32
    np.testing.assert_array_equal(f[:, 0], obs.astype(np.float32))
    labels, prob = predict(head(), cells, obs)
    assert labels.shape == (len(cells),) and labels.dtype == np.uint8 and labels.max() < len(CLASS_NAMES)
    assert prob.shape == (len(cells), len(CLASS_NAMES))
    np.testing.assert_allclose(prob.sum(1), 1.0, atol=1e-5)
    empty = predict(head(), np.zeros((0, 3), np.int64), np.zeros(0, bool))
    assert empty[0].shape == (0,) and empty[1].shape == (0, len(CLASS_NAMES))


def test_prediction_does_not_depend_on_cell_order():
    cells, _ = street_cells()
    obs = cells[:, 1] < 10
    perm = np.random.default_rng(3).permutation(len(cells))
    a = predict(head(), cells, obs)[1]
    b = predict(head(), cells[perm], obs[perm])[1]
    np.testing.assert_allclose(b, a[perm], atol=1e-6)


CHILD = """
import sys, numpy as np, torch
torch.set_num_threads(int(sys.argv[1]))
sys.path.insert(0, sys.argv[2])
from test_semantics_head import head, street_cells
from hgca_core.models.semantics import predict
cells, _ = street_cells()
labels, prob = predict(head(), cells, cells[:, 0] < 30)
sys.stdout.write(labels.tobytes().hex())
"""


def test_labels_are_the_same_on_one_and_two_threads():
    import os

    here = os.path.dirname(__file__)
    out = [subprocess.run([sys.executable, "-c", CHILD, str(n), here], capture_output=True, text=True, check=True,
                          timeout=300).stdout for n in (1, 2)]
    assert out[0] and out[0] == out[1]


def test_cell_labels_take_the_majority_and_else_the_nearest():
    cells = np.array([[0, 0, 0], [1, 0, 0], [5, 5, 5]])
    pts = np.array([[0.05, 0.05, 0.05], [0.1, 0.1, 0.1], [0.15, 0.1, 0.1], [0.3, 0.1, 0.1], [1.05, 1.05, 1.0]])
    lab = np.array([3, 4, 4, 7, 6])
    np.testing.assert_array_equal(cell_labels(cells, pts, lab), [4, 7, 6])


def test_perturb_keeps_labels_with_their_cells_and_cuts_the_observed_flag():
    cells, labels = street_cells()
    obs = np.ones(len(cells), bool)
    seen_cut = False
    for seed in range(8):
        c, lab, o = perturb(cells, labels, obs, np.random.default_rng(seed), crop=32)
        assert len(c) == len(lab) == len(o) > 0
        assert len(np.unique(c, axis=0)) == len(c) and c.min() >= 0
        assert set(np.unique(lab)) <= {0, 2, 5}
        hag = (c[:, 2] + 0.5) * 0.2 - fitted_ground(c)
        assert np.all(np.abs(hag[lab == 0]) < 0.5)     # ground stays ground after any turn
        seen_cut |= not o.all()
    assert seen_cut


def test_iou_from_confusion():
    conf = confusion(np.array([0, 0, 1, 1, 2]), np.array([0, 1, 1, 1, 2]), 4)
    iou = class_iou(conf)
    np.testing.assert_allclose(iou[:3], [0.5, 2 / 3, 1.0])
    assert np.isnan(iou[3])


def test_faces_take_the_nearest_cell_and_samples_vote():
    cells = np.array([[0, 0, 0], [10, 0, 0]])
    pts = np.array([[0.1, 0.1, 0.1], [1.9, 0.1, 0.1], [2.2, 0.0, 0.0]])
    np.testing.assert_array_equal(face_labels(pts, cells, np.array([1, 2])), [1, 2, 2])
    own = np.array([1, 2, 2], np.uint8)
    others = [(cells, np.array([1, 2])), (cells, np.array([1, 3])), (cells, np.array([0, 2]))]
    np.testing.assert_allclose(agreement(pts, own, others), [2 / 3, 2 / 3, 2 / 3])
    np.testing.assert_array_equal(agreement(pts, own, []), [1, 1, 1])


def test_label_completions_adds_face_attributes_and_leaves_geometry():
    class C:
        def __init__(self, mesh, cells):
            self.mesh, self.coarse_cells = mesh, cells

    cells, _ = street_cells()
    mesh = trimesh.creation.box(extents=(4, 4, 2))
    mesh.apply_translation((6, 4, 2))
    before_v, before_f = mesh.vertices.copy(), mesh.faces.copy()
    comps = [C(mesh, cells), C(mesh.copy(), cells[: len(cells) // 2])]
    label_completions(head(), comps, cells[:100], lambda v: v)
    for c in comps:
        assert c.mesh.face_attributes["label"].shape == (len(mesh.faces),)
        a = c.mesh.face_attributes["label_agreement"]
        assert a.dtype == np.float32 and np.all((a >= 0.5) & (a <= 1.0))
    np.testing.assert_array_equal(comps[0].mesh.vertices, before_v)
    np.testing.assert_array_equal(comps[0].mesh.faces, before_f)
    assert observed_mask(cells[:5], cells[:3]).tolist() == [True, True, True, False, False]


def test_cells_and_faces_use_the_projects_20cm_cells():
    """A point belongs to the 20 cm cell `voxelize` puts it in (cell c holds 10 cm cells 2c and 2c + 1, centre
    (c + 0.25) * 0.2 m): training targets take a surface point's label into that cell and a face takes that cell's
    label, never the neighbour a centre 5 cm off would pick."""
    from hgca_core.geometry.voxel import point_cells, voxelize

    rng = np.random.default_rng(4)
    points = rng.uniform(0.0, 3.0, (4000, 3))
    cells = voxelize(points)
    own = point_cells(points)
    cell_label = rng.integers(0, 9, len(cells)).astype(np.uint8)
    row = {tuple(c): i for i, c in enumerate(cells)}
    point_label = cell_label[[row[tuple(c)] for c in own]]
    assert np.array_equal(face_labels(points, cells, cell_label), point_label)
    assert np.array_equal(cell_labels(cells, points, point_label), cell_label)
