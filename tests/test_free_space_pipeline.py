"""Observed free space in the pipeline (`--free-space`): computed once per completion from every ray and handed to
both stages, old weights unchanged by default, the mask never outputs a cell of the free space's core, clear
errors."""
import dataclasses

import numpy as np
import pytest
import torch

from hgca_testdata import tiny_sample
from hgca_core.errors import InputError
from hgca_core.geometry import freespace
from hgca_core.geometry.region import Region
from hgca_core.geometry.voxel import COARSE
from hgca_core.meshing.fine import udf_mesh
from hgca_core.models import cgca, gca
from hgca_core.models.autoencoder import Autoencoder, AutoencoderConfig
from hgca_core.models.cgca import CGCAConfig, CGCAKernel
from hgca_core.models.gca import GCAConfig, GCAKernel
from hgca_core.models.weights import shipped
from hgca_core.training.export import save_weights
from hgca_core.pipeline import Models, complete_local, load_models, takes_free_space

pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture(scope="module")
def scene():
    """The tiny sample's input (seen from (3, 3, 3)) plus a fan of horizontal rays from (-1, 3, 1.7) to hits 2 m
    beyond the far side of the box at 0.2-3.4 m: they cross the whole box (hits outside it still prove the cells
    before them empty), below the ground too, where the shipped model grows on this scene. Not a physical
    scan (the rays pass through the ground and the wall), a test of what is done with the free cells."""
    s = tiny_sample(3)
    pts = s["input_points"].astype(np.float64)
    y, z = np.meshgrid(np.linspace(0.0, 6.0, 80), np.linspace(0.2, 3.4, 33))
    fan = np.c_[np.full(y.size, 8.0), y.ravel(), z.ravel()]
    local = np.concatenate([pts, fan])
    origins = np.array([[3.0, 3.0, 3.0], [-1.0, 3.0, 1.7]])
    index = np.r_[np.zeros(len(pts), np.int64), np.ones(len(fan), np.int64)]
    region = Region.from_tuple(s["region"])
    return local, origins, index, region


def _free_models():
    torch.manual_seed(0)
    coarse = GCAKernel(GCAConfig(channels=(8, 8, 16, 16, 16), steps=3, free_space=True)).eval()
    fine = CGCAKernel(CGCAConfig(latent=4, channels=(8, 8, 8), in_proj=8, pe_freq=1, steps=2, free_space=True)).eval()
    ae = Autoencoder(AutoencoderConfig(latent=4, enc_hidden=8, mlp_hidden=8, dec_channels=8)).eval()
    return Models(coarse, fine, ae)


@pytest.mark.filterwarnings("ignore:.*empty mesh")      # untrained small models
def test_free_space_is_computed_once_from_every_ray_and_reaches_both_stages(scene, monkeypatch):
    local, origins, index, region = scene
    want = freespace.observed_empty(local, origins, index, region.grid_shape(COARSE))
    inside_only = freespace.observed_empty(local[region.contains_local(local)], origins,
                                           index[region.contains_local(local)], region.grid_shape(COARSE))
    assert want.sum() > inside_only.sum()      # the rays to hits outside the box count
    calls, seen = [], {"coarse": [], "fine": []}
    real_walk, real_gca, real_up = freespace.observed_empty, gca.sample, cgca.upsample
    monkeypatch.setattr(freespace, "observed_empty", lambda *a, **k: calls.append(1) or real_walk(*a, **k))

    def spy_gca(*a, **k):
        seen["coarse"].append(a[5])                                  # free
        return real_gca(*a, **k)

    def spy_up(*a, **k):
        seen["fine"].append(a[8])                                    # free20
        return real_up(*a, **k)

    monkeypatch.setattr(gca, "sample", spy_gca)
    monkeypatch.setattr(cgca, "upsample", spy_up)
    res = complete_local(local, region, _free_models(), stage="full", samples=2, origins=origins, origin_index=index,
                         precision="fp32")
    assert len(res) == 2 and len(calls) == 1
    for free in seen["coarse"] + seen["fine"]:
        assert free.shape == (1, *want.shape) and np.array_equal(free[0].numpy(), want)
    assert len(seen["coarse"]) == len(seen["fine"]) == 2


def _without_free_space(path):
    """The shipped no-planner weights with their free-space input column cut out: trained weights of a model
    without the feature, as every file written before it existed."""
    model = load_models("coarse", weights=shipped("coarse-noplanner")).coarse
    sd = model.state_dict()
    for name, (dim, cols) in model.free_columns().items():
        keep = torch.tensor([i for i in range(sd[name].shape[dim]) if i not in cols])
        sd[name] = sd[name].index_select(dim, keep)
    old = GCAKernel(dataclasses.replace(model.cfg, free_space=False))
    old.load_state_dict(sd)
    return save_weights(path, old)


def test_old_weights_give_the_old_result_unless_the_mask_is_asked_for(scene, tmp_path, monkeypatch):
    """Weights without a free-space input: auto (the default) with or without origins and off are the same
    chains, and nothing is computed for them; feature is refused, mask changes the result (here with a core that
    is the whole free space: this model grows only in its rim)."""
    local, origins, index, region = scene
    monkeypatch.setattr(freespace, "confident", lambda free: free)
    models = load_models("coarse", weights=_without_free_space(tmp_path / "old.pt"))
    assert not takes_free_space(models)
    runs = {name: complete_local(local, region, models, stage="coarse", samples=1, seed=3, precision="fp32",
                                 **kw)[0].coarse_cells
            for name, kw in {"plain": {}, "auto": dict(origins=origins, origin_index=index),
                             "off": dict(origins=origins, origin_index=index, free_space="off"),
                             "mask": dict(origins=origins, origin_index=index, free_space="mask")}.items()}
    assert np.array_equal(runs["plain"], runs["auto"]) and np.array_equal(runs["plain"], runs["off"])
    assert not np.array_equal(runs["plain"], runs["mask"])
    with pytest.raises(InputError, match="trained without observed free space"):
        complete_local(local, region, models, stage="coarse", origins=origins, free_space="feature")
    with pytest.raises(InputError, match="needs the sensor origins"):
        complete_local(local, region, models, stage="coarse", free_space="mask")
    with pytest.raises(InputError, match="free_space must be one of"):
        complete_local(local, region, models, stage="coarse", origins=origins, free_space="maybe")


def test_shipped_coarse_weights_read_the_free_space_by_default(scene, monkeypatch):
    """The shipped coarse.pt was trained with observed free space: auto uses it when the scans have origins (the
    chain differs from off) and masks its core (the chain is mask's; with a core as large as the free space, no
    seen-empty cell is output), and without origins it is all unknown (the chain equals off)."""
    local, origins, index, region = scene
    models = load_models("coarse")
    assert takes_free_space(models)
    kw = dict(stage="coarse", samples=1, seed=3, precision="fp32")
    auto = complete_local(local, region, models, origins=origins, origin_index=index, **kw)[0]
    off = complete_local(local, region, models, origins=origins, origin_index=index, free_space="off", **kw)[0]
    mask = complete_local(local, region, models, origins=origins, origin_index=index, free_space="mask", **kw)[0]
    assert auto.free_cells and auto.free_cells > 0 and off.free_cells is None
    assert not np.array_equal(auto.coarse_cells, off.coarse_cells)
    assert np.array_equal(auto.coarse_cells, mask.coarse_cells)
    free = freespace.observed_empty(local, origins, index, region.grid_shape(COARSE))
    monkeypatch.setattr(freespace, "confident", lambda grid: grid)
    strict = complete_local(local, region, models, origins=origins, origin_index=index, **kw)[0]
    assert free[tuple(auto.coarse_cells.T)].sum() > 0 and free[tuple(strict.coarse_cells.T)].sum() == 0
    with pytest.warns(UserWarning, match="no sensor origins"):
        bare = complete_local(local, region, models, **kw)[0]
    assert np.array_equal(bare.coarse_cells, off.coarse_cells)


def test_the_mask_never_outputs_a_cell_of_the_free_space_core(scene, monkeypatch):
    """The mask forbids the free space's core (`freespace.confident`) in both stages and leaves its rim, where
    true surface lies under grazing rays: the shipped model grows 13 cells into this scene's rim, none into its
    core; given a core that is the whole free space, nothing seen empty is output."""
    local, origins, index, region = scene
    free = freespace.observed_empty(local, origins, index, region.grid_shape(COARSE))
    core = freespace.confident(free)
    models = load_models("full")                                        # the shipped coarse and fine weights
    kw = dict(origins=origins, origin_index=index, samples=1, seed=0, precision="fp32")
    off = complete_local(local, region, models, stage="full", free_space="off", **kw)[0]
    assert free[tuple(off.coarse_cells.T)].sum() > 0                    # unmasked, the model does grow there
    rim = complete_local(local, region, models, stage="full", free_space="mask", **kw)[0]
    assert free[tuple(rim.coarse_cells.T)].sum() > 0 and core[tuple(rim.coarse_cells.T)].sum() == 0
    monkeypatch.setattr(freespace, "confident", lambda grid: grid)
    on = complete_local(local, region, models, stage="full", free_space="mask", **kw)[0]
    assert len(on.coarse_cells) and len(on.fine_cells)
    assert free[tuple(on.coarse_cells.T)].sum() == 0
    parents = on.fine_cells // 2
    parents = parents[(parents < free.shape).all(1)]
    assert free[tuple(parents.T)].sum() == 0
    # the latents come back row-aligned with the fine cells: meshing them again gives the run's own mesh
    assert on.fine_latents.shape == (len(on.fine_cells), models.autoencoder.cfg.latent)
    again = udf_mesh(models.autoencoder, torch.from_numpy(on.fine_cells), torch.from_numpy(on.fine_latents),
                     voxel=models.autoencoder.cfg.voxel, points=local[region.contains_local(local)], sensors=origins)
    np.testing.assert_array_equal(again.faces, on.mesh.faces)
    np.testing.assert_allclose(again.vertices, on.mesh.vertices, atol=1e-6)
    shuffled = np.random.default_rng(0).permutation(len(on.fine_cells))
    other = udf_mesh(models.autoencoder, torch.from_numpy(on.fine_cells), torch.from_numpy(on.fine_latents[shuffled]),
                     voxel=models.autoencoder.cfg.voxel)
    assert len(other.faces) != len(on.mesh.faces)                       # the pairing matters
    assert off.fine_latents is not None and off.coarse_cells is not None


def test_free_space_weights_without_origins_warn_that_it_is_unknown(scene):
    local, _, _, region = scene
    models = _free_models()
    with pytest.warns(UserWarning, match="no sensor origins"):
        a = complete_local(local, region, models, stage="coarse", samples=1, seed=1, precision="fp32")[0]
    b = complete_local(local, region, models, stage="coarse", samples=1, seed=1, precision="fp32", free_space="off")[0]
    assert np.array_equal(a.coarse_cells, b.coarse_cells)              # all unknown = off


def test_cli_free_space_option(tmp_path):
    from hgca_core.cli import main

    s = tiny_sample(3)
    scan = tmp_path / "scan.npz"
    np.savez(scan, points=s["input_points"].astype(np.float64), origins=s["input_origins"].astype(np.float64))
    args = ["complete", str(scan), "-o", str(tmp_path / "out.npz"), "--region", "3,3,1,6,6,4", "--progress", "none",
            "--t1", "2"]
    noplanner = str(_without_free_space(tmp_path / "old.pt"))           # trained without free space
    assert main(args + ["--free-space", "feature", "--weights", noplanner, "--stage", "coarse"]) == 2
    assert not list(tmp_path.glob("out_s*"))
    bare = tmp_path / "bare.npz"                                        # no sensor origins: nothing to walk
    np.savez(bare, points=s["input_points"].astype(np.float64))
    assert main(["complete", str(bare)] + args[2:] + ["--free-space", "feature"]) == 2
    assert not list(tmp_path.glob("out_s*"))
    assert main(args + ["--free-space", "feature"]) == 0                # the shipped coarse.pt takes it
    assert (tmp_path / "out_s0.npz").exists()
    (tmp_path / "out_s0.npz").unlink()
    assert main(args + ["--free-space", "mask"]) == 0 and (tmp_path / "out_s0.npz").exists()
