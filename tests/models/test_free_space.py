"""Observed free space as a model input (issue 13, item 3): the inputs are exactly the free set, old weights are
unchanged, warm start keeps the old model until the new inputs are trained, and the mask forbids seen-empty cells."""
import dataclasses
from pathlib import Path

import numpy as np
import pytest
import torch

from hgca_core.errors import InputError
from hgca_core.geometry import coords as cs
from hgca_core.geometry.freespace import observed_empty
from hgca_core.models import free as fs
from hgca_core.models.cgca import CGCAConfig, CGCAKernel, _gather, _table
from hgca_core.models.gca import GCAConfig, GCAKernel
from hgca_core.models.planner import PILLAR, Planner
from hgca_core.models.weights import load_coarse, load_file, load_fine, save_file, shipped
from hgca_core.training.export import load_into, save_weights
from hgca_core.nn.encoding import sinusoidal
from hgca_core.nn.sparse import CellState

pytestmark = pytest.mark.usefixtures("one_thread")
SMALL = dict(channels=(8, 8, 16, 16, 16), steps=3)


def ray_scene():
    """One sensor at (0.5, 0.5, 0.5) m and one hit 4.5 m away along x: by hand, the ray proves the 20 cm cells
    x = 2..23 of row y = z = 2 empty (cell c spans [0.2 c - 0.05, 0.2 c + 0.15); the walk stops 0.4 m short of
    the hit, at x = 4.6 m, cell 23; the hit's cell 25 and its neighbours 24..26 are not free)."""
    origin = np.array([[0.5, 0.5, 0.5]])
    hit = np.array([[5.0, 0.5, 0.5]])
    expected = np.zeros((30, 6, 6), bool)
    expected[2:24, 2, 2] = True
    return hit, origin, expected


def test_free_set_of_a_hand_made_ray():
    hit, origin, expected = ray_scene()
    np.testing.assert_array_equal(observed_empty(hit, origin, None, expected.shape), expected)


def test_free_set_is_the_same_on_any_number_of_threads(monkeypatch):
    """The ray walk marks chunks of rays on `workers` threads; the grid is the same on 1, 2 or 3 (many chunks:
    a small chunk size forces them, and the rays cross each other's cells)."""
    from hgca_core.geometry import freespace

    rng = np.random.default_rng(0)
    origins = np.array([[3.0, 3.0, 1.5], [4.0, 2.0, 1.8]])
    hits = rng.uniform([0, 0, 0], [8, 6, 0.1], (600, 3))       # on the ground: the rays cross the air above
    index = rng.integers(0, 2, len(hits))
    monkeypatch.setattr(freespace, "CHUNK_EVENTS", 4000)
    grids = [observed_empty(hits, origins, index, (40, 30, 20), workers=w) for w in (1, 2, 3)]
    assert grids[0].sum() > 1000
    for g in grids[1:]:
        np.testing.assert_array_equal(g, grids[0])


def _stem_input(model, *args):
    """The feature matrix the coarse kernel's U-Net receives."""
    seen = {}
    hook = model.unet.stem.register_forward_pre_hook(lambda m, inp: seen.update(x=inp[0]))
    with torch.no_grad():
        model(*args)
    hook.remove()
    return seen["x"]


def test_coarse_kernel_feature_is_exactly_the_free_set():
    hit, origin, expected = ray_scene()
    grid = expected.shape
    free = fs.from_numpy(observed_empty(hit, origin, None, grid))
    model = GCAKernel(GCAConfig(**SMALL, use_planner=False, free_space=True)).eval()
    s0 = cs.with_batch(torch.tensor([[25, 2, 2], [1, 2, 2], [12, 2, 3]]))
    state = cs.dilate(s0, 2, bounds=grid)                 # a neighbourhood that covers the ray and its sides
    hood = model.neighbourhood(CellState(state, grid))
    x = _stem_input(model, hood, state, s0, None, free)
    nbhd = hood.coords
    want = torch.from_numpy(expected)[nbhd[:, 1], nbhd[:, 2], nbhd[:, 3]]
    assert want.sum() > 10 and (~want).sum() > 10
    assert torch.equal(x.feats[:, 2], want.float())
    assert torch.equal(x.feats[:, 0], cs.isin(nbhd, state).float()) and torch.equal(x.feats[:, 1], cs.isin(nbhd, s0).float())
    assert torch.equal(_stem_input(model, hood, state, s0, None, None).feats[:, 2], torch.zeros(len(nbhd)))


def test_planner_sees_the_share_of_each_pillars_cells_seen_empty_per_height_bin():
    g = torch.Generator().manual_seed(0)
    grid = (10, 8, 12)                                     # pillars at the far edges hold 1 and 2 columns
    free = torch.rand((2, *grid), generator=g) < 0.3
    got = fs.pillar_fractions(free, PILLAR, 4)
    hw = Planner.bev_shape(grid)
    assert got.shape == (2, 4, *hw)
    for b in range(2):
        for zb in range(4):
            for px in range(hw[0]):
                for py in range(hw[1]):
                    cells = [(x, y, z) for x in range(px * 3, min(px * 3 + 3, grid[0]))
                             for y in range(py * 3, min(py * 3 + 3, grid[1])) for z in range(grid[2])
                             if z * 4 // grid[2] == zb]
                    want = sum(bool(free[b, x, y, z]) for x, y, z in cells) / len(cells)
                    assert abs(float(got[b, zb, px, py]) - want) < 1e-6
    planner = Planner([8, 8], z_r=4, free_bins=4)
    seen = {}
    planner.unet.downs[0][0].register_forward_pre_hook(lambda m, inp: seen.update(x=inp[0]))
    planner(CellState(cs.with_batch(torch.tensor([[1, 1, 1]])), grid), 2, free)
    assert seen["x"].shape[1] == 32 + 4 and torch.equal(seen["x"][:, 32:], got)


def _cgca_reference(model, nbhd, state, zs, x0, z0, grid, free10):
    """relu(proj(cat([in x^t, in x^0, z^t, z^0, PE, in free]))): the projection as one concatenation."""
    nk = cs.pack(nbhd)
    in_t, zt = _gather(nk, *_table(state, zs))
    in_0, zz = _gather(nk, *_table(x0, z0))
    g = torch.tensor(grid, dtype=torch.float32)[model.pe_axes]
    pe = sinusoidal((nbhd[:, 1:][:, model.pe_axes].float() + 0.5) / g, model.cfg.pe_freq)
    in_free = free10[nbhd[:, 0], nbhd[:, 1], nbhd[:, 2], nbhd[:, 3]].float()[:, None]
    return model.proj(torch.cat([in_t, in_0, zt, zz, pe, in_free], dim=1))


def test_fine_kernel_feature_is_the_children_of_the_free_20cm_cells():
    hit, origin, expected = ray_scene()
    grid10 = (60, 12, 12)
    free20 = fs.from_numpy(observed_empty(hit, origin, None, expected.shape))
    free10 = fs.upsample(free20, grid10)
    want = torch.from_numpy(expected).repeat_interleave(2, 0).repeat_interleave(2, 1).repeat_interleave(2, 2)
    assert torch.equal(free10[0], want)
    assert fs.upsample(free20, (59, 13, 12)).shape == (1, 59, 13, 12)     # odd 10 cm grids: cut / padded
    torch.manual_seed(0)
    model = CGCAKernel(CGCAConfig(latent=4, channels=(8, 8, 8), in_proj=8, pe_freq=1, free_space=True)).eval()
    x0 = cs.with_batch(torch.tensor([[50, 4, 4], [4, 4, 4], [30, 4, 6]]))
    z0 = torch.randn(len(x0), 4)
    hood = model.neighbourhood(CellState(x0, grid10))
    nbhd = hood.coords
    with torch.no_grad():
        got = model.project(hood, x0, z0, x0, z0, free10)
        ref = torch.relu(_cgca_reference(model, nbhd, x0, z0, x0, z0, grid10, free10))
    assert free10[0][nbhd[:, 1], nbhd[:, 2], nbhd[:, 3]].sum() > 10
    torch.testing.assert_close(got, ref, rtol=1e-5, atol=1e-5)


def _old_format(path: Path, kind: str = "coarse") -> Path:
    """Weights as written before the free-space field existed (no `free_space` key in the config): the shipped
    file's architecture without the feature, seeded random weights. kind: coarse (with the planner),
    coarse-noplanner, or fine (with the shipped autoencoder)."""
    torch.manual_seed(0)
    if kind == "fine":
        kernel, ae, _ = load_fine()
        save_weights(path, CGCAKernel(dataclasses.replace(kernel.cfg, free_space=False)), autoencoder=ae)
    else:
        save_weights(path, GCAKernel(dataclasses.replace(load_coarse(shipped(kind))[0].cfg, free_space=False)))
    blob = load_file(path)
    del blob["config"]["free_space"]
    save_file(blob, path)
    return path


def test_old_weights_load_unchanged_without_the_feature(tmp_path):
    """Files written before the field existed are models without free space: same tensors, same input layout."""
    old = _old_format(tmp_path / "old_coarse.pt")
    nop = _old_format(tmp_path / "old_noplanner.pt", "coarse-noplanner")
    fine = _old_format(tmp_path / "old_fine.pt", "fine")
    for load, path in ((lambda: load_coarse(old)[0], old), (lambda: load_coarse(nop)[0], nop),
                       (lambda: load_fine(fine)[0], fine)):
        model = load()
        assert model.cfg.free_space is False and model.free_columns() == {}
        sd = load_file(path)["state_dict"]
        assert {k: tuple(v.shape) for k, v in sd.items()} == {k: tuple(v.shape) for k, v in model.state_dict().items()}
    model = load_coarse(old)[0]
    assert model.unet.stem[0].weight.shape[1] == 2 + 2 * model.cfg.pe_freq * len(model.cfg.pe_axes)
    assert model.planner.unet.downs[0][0].in_channels == 32


def test_shipped_coarse_weights_take_the_feature():
    """The shipped coarse.pt was trained with free space: one more kernel input column, z_r more planner bins."""
    model = load_coarse()[0]
    assert model.cfg.free_space is True
    assert model.unet.stem[0].weight.shape[1] == 3 + 2 * model.cfg.pe_freq * len(model.cfg.pe_axes)
    assert model.planner.unet.downs[0][0].in_channels == 32 + model.cfg.z_r
    assert set(model.free_columns()) == {"unet.stem.0.weight", "planner.unet.downs.0.0.weight"}


def _coarse_inputs(grid=(30, 27, 40), seed=0):
    g = torch.Generator().manual_seed(seed)
    s0 = cs.unique(torch.cat([torch.zeros(800, 1, dtype=torch.long), torch.randint(0, grid[0], (800, 1), generator=g),
                              torch.randint(0, grid[1], (800, 1), generator=g), torch.randint(0, 8, (800, 1), generator=g)], 1))
    free = torch.rand((1, *grid), generator=g) < 0.5
    return s0, free, grid


def test_warm_start_from_coarse_weights_without_the_feature(tmp_path):
    path = _old_format(tmp_path / "old_coarse.pt")
    old = load_coarse(path)[0]
    new = GCAKernel(dataclasses.replace(old.cfg, free_space=True))
    meta = load_into(new, path)
    assert meta["widened"] == ["planner.unet.downs.0.0.weight", "unet.stem.0.weight"]
    new.eval()
    assert torch.count_nonzero(new.unet.stem[0].weight[:, 2]) == 0
    s0, free, grid = _coarse_inputs()
    nbhd = old.neighbourhood(CellState(s0, grid))

    def logits(model, f):
        with torch.no_grad():
            return model(nbhd, s0, s0, model.bev(CellState(s0, grid), 1, f), f)

    ref = logits(old, None)
    torch.testing.assert_close(logits(new, free), ref, rtol=0, atol=1e-4)     # zero columns: the old model
    torch.testing.assert_close(logits(new, None), ref, rtol=0, atol=1e-4)
    with torch.no_grad():                                                     # as a trained model would have them
        new.unet.stem[0].weight[:, 2] = 0.5
        new.planner.unet.downs[0][0].weight[:, 32:] = 0.5
    assert (logits(new, free) - ref).abs().max() > 0.1                        # now the free cells count
    torch.testing.assert_close(logits(new, torch.zeros_like(free)), ref, rtol=0, atol=1e-4)


def test_warm_start_of_fine_weights_without_the_feature(tmp_path):
    """As the shipped fine.pt was made: fine weights written before the feature (the shipped architecture)
    warm-start a model with it, which computes the same until its new column is trained."""
    path = _old_format(tmp_path / "old_fine.pt", "fine")
    old = load_fine(path)[0]
    new = CGCAKernel(dataclasses.replace(old.cfg, free_space=True))
    assert load_into(new, path)["widened"] == ["proj.0.weight"]
    new.eval()
    grid = (40, 40, 30)
    g = torch.Generator().manual_seed(1)
    x0 = cs.unique(torch.cat([torch.zeros(400, 1, dtype=torch.long), torch.randint(0, 40, (400, 2), generator=g),
                              torch.randint(0, 10, (400, 1), generator=g)], 1))
    z0 = torch.randn(len(x0), old.cfg.latent, generator=g)
    free = torch.rand((1, *grid), generator=g) < 0.5
    nbhd = old.neighbourhood(CellState(x0, grid))
    with torch.no_grad():
        ref = old(nbhd, x0, z0, x0, z0)
        for a, b in zip(new(nbhd, x0, z0, x0, z0, free), ref):
            torch.testing.assert_close(a, b, rtol=0, atol=1e-4)
        new.proj[0].weight[:, -1] = 0.5
        assert (new(nbhd, x0, z0, x0, z0, free)[0] - ref[0]).abs().max() > 0.01


def test_warm_start_refuses_what_does_not_fit(tmp_path):
    torch.manual_seed(0)
    with_free = GCAKernel(GCAConfig(**SMALL, free_space=True))
    save_weights(tmp_path / "free.pt", with_free)
    with pytest.raises(InputError, match="do not fit"):               # dropping an input is no warm start
        load_into(GCAKernel(GCAConfig(**SMALL)), tmp_path / "free.pt")
    with pytest.raises(InputError, match="do not fit"):               # another architecture
        load_into(GCAKernel(GCAConfig(channels=(8, 8, 16, 16, 32), free_space=True)), tmp_path / "free.pt")
    with pytest.raises(InputError, match="this is a fine weights file"):   # another kind of model
        load_into(GCAKernel(GCAConfig(**SMALL)), shipped("fine"))
    same = GCAKernel(GCAConfig(**SMALL, free_space=True))
    assert load_into(same, tmp_path / "free.pt")["widened"] == []
    assert all(torch.equal(a, b.half().float() if b.is_floating_point() else b)      # files hold fp16
               for a, b in zip(same.state_dict().values(), with_free.state_dict().values()))
