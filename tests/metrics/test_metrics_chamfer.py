"""Known-answer tests for Chamfer distance, IoU and TMD."""
from __future__ import annotations

import numpy as np
import pytest

from hgca_core.errors import InputError
from hgca_core.metrics.chamfer import chamfer, chamfer_or_penalty, directed_chamfer
from hgca_core.geometry.keys import unpack
from hgca_core.metrics.iou import iou, pack_cells
from hgca_core.metrics.tmd import tmd


def _grid(n: int = 20, spacing: float = 1.0) -> np.ndarray:
    g = np.arange(n) * spacing
    return np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)


def _plane(n: int, size: float, z: float, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.column_stack([rng.uniform(0, size, (n, 2)), np.full(n, z)])


def test_identical_sets_have_zero_chamfer() -> None:
    a = np.random.default_rng(0).normal(size=(500, 3))
    assert chamfer(a, a) == 0.0
    assert directed_chamfer(a, a.copy()) == 0.0


def test_translated_grid_chamfer_is_translation_length() -> None:
    a = _grid(8)
    t = np.array([0.2, 0.1, 0.0])                   # smaller than half the 1 m spacing: a+t is each point's NN
    assert chamfer(a, a + t) == pytest.approx(np.linalg.norm(t), abs=1e-12)


def test_single_points_far_apart() -> None:
    assert chamfer(np.zeros((1, 3)), np.array([[3.0, 4.0, 0.0]])) == pytest.approx(5.0)


def test_parallel_planes_distance() -> None:
    d = 0.5
    cd = chamfer(_plane(40_000, 10.0, 0.0, 1), _plane(40_000, 10.0, d, 2))
    assert cd == pytest.approx(d, abs=0.01)
    assert cd >= d                                   # no NN can be closer than the plane gap


def test_directed_chamfer_is_asymmetric() -> None:
    a = np.zeros((1, 3))
    b = np.array([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0]])
    assert directed_chamfer(a, b) == 0.0
    assert directed_chamfer(b, a) == pytest.approx(5.0)
    assert chamfer(a, b) == pytest.approx(2.5)


def test_empty_input_is_a_clear_error() -> None:
    with pytest.raises(InputError, match="empty"):
        chamfer(np.zeros((0, 3)), np.zeros((3, 3)))
    with pytest.raises(InputError, match="empty"):
        directed_chamfer(np.zeros((3, 3)), np.zeros((0, 3)))
    with pytest.raises(InputError, match=r"\(N, 3\)"):
        chamfer(np.zeros((3, 2)), np.zeros((3, 3)))


def test_chamfer_or_penalty() -> None:
    e, a = np.zeros((0, 3)), np.ones((4, 3))
    assert chamfer_or_penalty(e, e, 75.0) == 0.0
    assert chamfer_or_penalty(e, a, 75.0) == 75.0
    assert chamfer_or_penalty(a, e, 75.0) == 75.0
    assert chamfer_or_penalty(a, a + [0, 0, 1], 75.0) == pytest.approx(1.0)


def test_iou_equal_disjoint_half_overlap() -> None:
    a = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0]])
    assert iou(a, a) == 1.0
    assert iou(a, a + [0, 0, 5]) == 0.0
    # half of each set overlaps: |P∩G| = 2, |P∪G| = 6 -> 1/3
    assert iou(a, a + [2, 0, 0]) == pytest.approx(1 / 3)
    assert iou(a.astype(np.int16), np.concatenate([a, a])) == 1.0   # duplicates and dtypes do not matter


def test_iou_visibility_mask_excludes_cells() -> None:
    pred = np.array([[0, 0, 0], [1, 0, 0], [5, 5, 5]])
    gt = np.array([[0, 0, 0], [1, 0, 0], [9, 9, 9]])
    assert iou(pred, gt) == pytest.approx(2 / 4)
    visible = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0]])           # hides both mismatching cells
    assert iou(pred, gt, visible) == 1.0
    visible2 = np.array([[0, 0, 0], [9, 9, 9]])                     # P∩V={0}, G∩V={0, 9}
    assert iou(pred, gt, visible2) == pytest.approx(1 / 2)
    assert np.isnan(iou(pred, gt, np.array([[7, 7, 7]])))           # nothing visible: undefined


def test_pack_cells_is_unique_sorted_keys_and_checks_its_input() -> None:
    c = np.array([[-5, 3, 0], [100000, -100000, 7], [0, 0, 0], [-5, 3, 0]])
    assert np.array_equal(unpack(pack_cells(c), batched=False), np.unique(c, axis=0))
    with pytest.raises(InputError, match="pred has cell coordinates outside"):
        pack_cells(np.array([[1 << 17, 0, 0]]), "pred")
    with pytest.raises(InputError, match="integer"):
        pack_cells(np.array([[0.5, 0, 0]]))


def test_chamfer_or_penalty_matches_brute_force() -> None:
    """The one Chamfer (the fine stage's validation uses it too): mean of the two directed mean NN distances."""
    rng = np.random.default_rng(4)
    a, b = rng.normal(size=(300, 3)), rng.normal(size=(200, 3)) + 0.3
    d = np.linalg.norm(a[:, None] - b[None], axis=2)
    assert chamfer_or_penalty(a, b, 1.0) == pytest.approx(0.5 * (d.min(1).mean() + d.min(0).mean()), rel=1e-12)


def test_tmd_identical_and_shifted_samples() -> None:
    g = np.arange(0, 5, 0.25)
    plane = np.stack(np.meshgrid(g, g, [0.0], indexing="ij"), -1).reshape(-1, 3)
    assert tmd([plane, plane, plane]) == 0.0
    # pairwise CDs of z shifts 0, 0.1, 0.3 are exactly 0.1, 0.3, 0.2 (each point's NN is its own copy)
    shifted = [plane, plane + [0, 0, 0.1], plane + [0, 0, 0.3]]
    assert tmd(shifted) == pytest.approx(0.2, abs=1e-12)
    assert tmd(shifted[:2]) == pytest.approx(0.1, abs=1e-12)


def test_tmd_needs_two_samples_and_handles_empty_with_penalty() -> None:
    p = np.zeros((3, 3))
    with pytest.raises(InputError, match="at least 2"):
        tmd([p])
    with pytest.raises(InputError, match="empty"):
        tmd([p, np.zeros((0, 3))])
    assert tmd([p, np.zeros((0, 3)), np.zeros((0, 3))], empty_penalty=9.0) == pytest.approx((9 + 9 + 0) / 3)
