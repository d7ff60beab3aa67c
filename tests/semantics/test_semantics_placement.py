"""Where the semantic head sits: its input read from the frozen coarse kernel (`coarse_features`) or from the
fine stage's latents (`fine_features`), the recipes that train each, and the frozen stages left as they were."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from hgca_testdata import tiny_sample, with_distance_pairs
from hgca_core.cli import main
from hgca_core.geometry import coords as cs
from hgca_core.models.gca import GCAConfig, GCAKernel
from hgca_core.models.semantics import (SemanticHead, SemanticsConfig, coarse_features, fine_features, head_input,
                                        observed_mask, predict)
from hgca_core.models.weights import load_file, load_semantics
from hgca_core.nn.sparse import CellState

pytestmark = pytest.mark.usefixtures("one_thread")


def _state(seed: int = 0) -> tuple[np.ndarray, np.ndarray, tuple[int, int, int]]:
    s = tiny_sample(seed)
    cells = s["gt_occ20"].astype(np.int64)
    return cells, cells[cells[:, 2] < 7], (30, 30, 20)


def test_coarse_features_are_the_kernels_last_layer_and_leave_it_unchanged():
    torch.manual_seed(0)
    kernel = GCAKernel(GCAConfig(channels=(16, 8, 16, 16, 16), free_space=True)).eval()
    cells, s0, grid = _state()
    state, x0 = cs.with_batch(torch.from_numpy(cells)), cs.with_batch(torch.from_numpy(s0))
    before = {k: v.clone() for k, v in kernel.state_dict().items()}

    def logits() -> tuple[torch.Tensor, torch.Tensor]:
        with torch.no_grad():
            nbhd = kernel.neighbourhood(CellState(state, grid))
            return nbhd.coords, kernel(nbhd, state, x0, kernel.bev(CellState(x0, grid), 1, None), None)

    nbhd, first = logits()
    feats = coarse_features(kernel, cells, s0, grid)
    _, again = logits()
    assert feats.shape == (len(cells), 16) and feats.dtype == np.float32 and np.isfinite(feats).all()
    assert torch.equal(first, again)                               # the kernel's output is bit for bit the same
    assert all(torch.equal(before[k], v) for k, v in kernel.state_dict().items())
    # the features are exactly what the occupancy logit reads: its linear map gives the kernel's logits back
    head = kernel.unet.head
    w = head.weight.reshape(16, 1)
    rows = cs.lookup(state, cs.pack(nbhd))
    assert torch.allclose(torch.from_numpy(feats) @ w + head.bias, first[rows][:, None], atol=1e-5)
    assert feats.std(0).max() > 0                                  # not a constant


def test_fine_features_pool_the_children_latents():
    cells = np.array([[0, 0, 0], [3, 1, 2], [5, 5, 5]])
    kids = np.array([[0, 0, 0], [1, 1, 1], [7, 3, 4]])              # two children of cell 0, one of cell 1
    z = np.array([[1.0, 2.0], [3.0, 6.0], [-1.0, 0.5]], np.float32)
    f = fine_features(cells, kids, z)
    assert f.shape == (3, 3)
    np.testing.assert_array_equal(f[0], [2.0, 4.0, 0.25])
    np.testing.assert_array_equal(f[1], [-1.0, 0.5, 0.125])
    np.testing.assert_array_equal(f[2], [0.0, 0.0, 0.0])            # no child: no code, share 0


def test_each_placement_reads_its_own_width_and_refuses_a_wrong_one():
    cells, s0, _ = _state()
    obs = observed_mask(cells, s0)
    for placement, width in (("geometry", 9), ("coarse-features", 17), ("fine-latents", 34)):
        cfg = SemanticsConfig(channels=(8, 8, 16), placement=placement)
        assert cfg.in_channels() == width
        extra = None if placement == "geometry" else np.zeros((len(cells), width - 1), np.float32)
        head = SemanticHead(cfg)
        assert predict(head, cells, obs, extra)[1].shape == (len(cells), cfg.classes)
        if placement != "geometry":
            with pytest.raises(ValueError, match="needs its features"):
                head_input(cfg, cells, obs)
            with pytest.raises(ValueError, match="features a cell"):
                head_input(cfg, cells, obs, np.zeros((len(cells), 3), np.float32))
    with pytest.raises(ValueError, match="placement must be"):
        SemanticsConfig(placement="decoder").in_channels()


@pytest.fixture(scope="module")
def labelled_dataset(tmp_path_factory):
    """Two tiny labelled samples a split, with the distance pairs the fine stage's autoencoder encodes."""
    root = tmp_path_factory.mktemp("sem_data")
    for split, seeds in (("train", (0, 1)), ("val", (100,))):
        (root / split).mkdir()
        for s in seeds:
            a = with_distance_pairs(tiny_sample(s))
            label = np.repeat(np.array([0, 2, 3], np.uint8), [6000, 6000, 3000])   # ground, wall, box (road ...)
            np.savez(root / split / f"sample_{s:07d}.npz", **a, gt_surface_label=label)
    return root


@pytest.mark.parametrize("recipe", ["semantics-coarse-features", "semantics-fine-latents"])
def test_each_placement_recipe_trains_two_steps_into_a_loadable_head(labelled_dataset, recipe, tmp_path):
    out = tmp_path / "run"
    assert main(["train", "--recipe", recipe, "--data", str(labelled_dataset), "--out", str(out), "--max-steps", "2",
                 "--minutes", "5", "--threads", "1", "--no-progress", "--set", "crop=16", "--set",
                 "val_every=1000", "--export", str(tmp_path / "head.pt")]) == 0
    ck = load_file(out / "ckpt.pt")
    placement = recipe.removeprefix("semantics-")
    assert ck["state"]["step"] == 2 and ck["config"]["placement"] == placement
    assert ck["recipe"]["fields"]["placement"] == placement
    head = load_semantics(tmp_path / "head.pt")
    assert head.cfg.placement == placement and head.unet.in_channels == head.cfg.in_channels()
    assert any(h["kind"] == "val" and np.isfinite(h["val_iou"]) for h in ck["state"]["history"])


def test_placement_is_a_semantics_recipe_field_checked_before_any_work():
    from hgca_core.errors import InputError
    from hgca_core.training.recipes import RECIPES, parse_sets, resolve

    assert RECIPES["semantics"].placement is None   # the shipped head's recipe reads the geometry features
    assert resolve("semantics", parse_sets(["placement=fine-latents"])).placement == "fine-latents"
    with pytest.raises(InputError, match="placement is the semantic head's input.*decoder"):
        resolve("semantics", parse_sets(["placement=decoder"]))
    with pytest.raises(InputError, match="not for coarse"):
        resolve("coarse", parse_sets(["placement=geometry"]))
