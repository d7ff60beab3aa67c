"""cGCA upsampler: neighbourhoods, kernel shapes and gradients, infusion, seeded sampling, x^0, overfitting, and
the functions the pipeline calls (upsample, shipped weights, the mesh of its output)."""

import numpy as np
import pytest
import torch
from scipy.spatial import cKDTree

from hgca_core.geometry import coords as cs
from hgca_core.geometry.voxel import downsample, voxelize
from hgca_core.models.autoencoder import Autoencoder, AutoencoderConfig
from hgca_core.meshing.fine import udf_mesh
from hgca_core.models.cgca import CGCAConfig, CGCAKernel, initial_state, sample, upsample
from hgca_core.models.weights import load_file, load_fine
from hgca_core.training.export import save_weights
from hgca_core.nn.sparse import CellState
from hgca_core.training.buffer import Chain, ChainBuffer
from hgca_core.training.fine import FineLoss, FineTask, export_fine
from hgca_core.training.trainer import train

K = 4
TINY = CGCAConfig(latent=K, channels=(8, 16), in_proj=8, pe_freq=1, crop=None)


pytestmark = pytest.mark.usefixtures("one_thread")


def _random_cells(n: int, grid: tuple[int, int, int], batches: int = 2, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    c = torch.stack([torch.randint(0, batches, (n,), generator=g)] +
                    [torch.randint(0, s, (n,), generator=g) for s in grid], 1)
    return cs.unique(c)


@pytest.mark.parametrize("metric", ["l1", "l2", "chebyshev"])
@pytest.mark.parametrize("radius", [1, 2])
def test_dense_neighbourhood_equals_sparse_dilation(metric, radius):
    grid = (10, 12, 6)
    cells = _random_cells(40, grid)
    got = cs.dilate(cells, radius, metric, grid)                              # dense grid path
    assert torch.equal(cs.dilate(cells, radius, metric, grid, dense_limit=0), got)  # the sparse path
    assert torch.equal(cs.pack(got), torch.sort(cs.pack(got)).values)


def _state(grid=(8, 8, 6), seed=0):
    g = torch.Generator().manual_seed(seed)
    x0 = _random_cells(30, grid, seed=seed)
    st = _random_cells(30, grid, seed=seed + 1)
    return x0, torch.randn(len(x0), K, generator=g), st, torch.randn(len(st), K, generator=g), grid


@pytest.mark.parametrize("layout", [dict(), dict(unet_stride=1, pe_axes="xyz")])
def test_kernel_shapes_and_gradients(layout):
    torch.manual_seed(0)
    model = CGCAKernel(CGCAConfig(**{**TINY.to_dict(), **layout}))
    x0, z0, st, zt, grid = _state()
    nbhd = model.neighbourhood(CellState(st, grid))
    logits, mu = model(nbhd, st, zt, x0, z0)
    assert logits.shape == (len(nbhd),) and mu.shape == (len(nbhd), K)
    (logits.sum() + mu.square().sum()).backward()
    for name, p in model.named_parameters():
        assert p.grad is not None and torch.isfinite(p.grad).all(), name
    head = model.unet.head if model.cfg.unet_stride == 1 else model.head[-1]
    assert model.proj[0].weight.grad.abs().sum() > 0 and head.weight.grad.abs().sum() > 0
    # the latent inputs matter: changing z^t changes the output
    with torch.no_grad():
        _, mu2 = model.eval()(nbhd, st, zt + 1.0, x0, z0)
        _, mu1 = model(nbhd, st, zt, x0, z0)
    assert (mu2 - mu1).abs().max() > 1e-4


def _chain(x0, z0, gt, zgt, grid, t=0):
    return Chain(s0=x0, gt=gt, state=x0.clone(), t=t, grid=grid, extra={"z0": z0, "zt": z0.clone(), "zgt": zgt})


def test_one_infusion_step_and_full_infusion_copies_the_truth():
    torch.manual_seed(0)
    grid = (8, 8, 6)
    x0 = _random_cells(40, grid, batches=1)[:, 1:]
    gt = _random_cells(40, grid, batches=1, seed=5)[:, 1:]
    chains = [_chain(x0, torch.randn(len(x0), K), gt, torch.randn(len(gt), K), grid, t) for t in (0, 7)]
    module = FineLoss(TINY)
    loss, stats, new = module(chains)
    assert torch.isfinite(loss) and loss > 0 and set(stats) >= {"loss_occ", "loss_lat", "cells"}
    loss.backward()
    for ch, s in zip(chains, new):
        assert s.shape[1] == 3 and len(ch.extra["zt"]) == len(s)      # latents row-aligned with the new cells
    # alpha = 1: the next state is exactly GT within N(x~^t), with the GT latents
    full = FineLoss(CGCAConfig(**{**TINY.to_dict(), "alpha0": 1.0}))
    ch = _chain(x0, torch.zeros(len(x0), K), gt, torch.randn(len(gt), K), grid)
    _, _, (s,) = full([ch])
    reach = cs.dilate(cs.with_batch(x0), 2, "l1", grid)
    want = gt[cs.isin(cs.with_batch(gt), reach)]
    assert torch.equal(s, want)
    torch.testing.assert_close(ch.extra["zt"], ch.extra["zgt"][cs.isin(cs.with_batch(gt), reach)])


def test_sampling_is_seeded():
    torch.manual_seed(0)
    model = CGCAKernel(TINY)
    x0, z0, _, _, grid = _state()
    runs = [sample(model, CellState(x0, grid), z0, 4, torch.Generator().manual_seed(s)) for s in (3, 3, 4)]
    assert torch.equal(runs[0][0], runs[1][0]) and torch.equal(runs[0][1], runs[1][1])
    assert not (torch.equal(runs[0][0], runs[2][0]) and torch.equal(runs[0][1], runs[2][1]))
    assert runs[0][1].shape == (len(runs[0][0]), K)


def test_initial_state_holds_input_cells_with_latents_and_upsampled_coarse_cells():
    torch.manual_seed(0)
    ae = Autoencoder(AutoencoderConfig(latent=K, enc_hidden=8, mlp_hidden=8, dec_channels=8)).eval()
    pts = np.array([[0.31, 0.42, 0.18], [0.29, 0.38, 0.22], [1.02, 0.5, 0.5], [-0.4, 0.2, 0.2]])  # last: outside
    coarse = np.array([[0, 0, 0], [3, 3, 1]])
    grid = (10, 10, 4)
    state, z0 = initial_state(ae, pts, coarse, grid)
    x0 = state.coords
    assert state.grid == grid                                                  # the state knows its grid
    inp = torch.tensor([[0, 3, 4, 2], [0, 10, 5, 5]])
    kids = cs.upsample2(cs.with_batch(torch.from_numpy(coarse)))
    kids = kids[(kids[:, 1:] < torch.tensor(grid)).all(1)]                     # children above z = 4 dropped
    assert torch.equal(x0, cs.union(inp[:1], kids))                            # (10, 5, 5) is outside the grid
    with torch.no_grad():
        _, z_ref = ae.encode(torch.tensor(pts[:2], dtype=torch.float32), torch.zeros(2))
    at_input = cs.isin(x0, inp[:1])
    torch.testing.assert_close(z0[at_input], z_ref)
    assert torch.all(z0[~at_input] == 0) and int(at_input.sum()) == 1 and len(x0) == 1 + len(kids)


@pytest.mark.parametrize("unet_stride", [2, 1])
def test_tiny_cgca_learns_to_fill_an_upsampled_block(unet_stride):
    """x^0 = a 2-cell-thick upsampled layer (what the coarse stage hands over) plus a few input cells with
    latents; the GT is one layer of it, with latents that vary across it. After a short infusion training the
    maximum-likelihood sample recovers the GT cells and their latents."""
    torch.manual_seed(0)
    grid = (10, 10, 6)
    xy = torch.stack(torch.meshgrid(torch.arange(1, 9), torch.arange(1, 9), indexing="ij"), -1).reshape(-1, 2)
    gt = torch.cat([xy, torch.full((len(xy), 1), 3)], 1)
    zgt = torch.stack([torch.sin(gt[:, 0] * 0.7), torch.cos(gt[:, 1] * 0.5), gt[:, 0] * 0.1, -gt[:, 1] * 0.1], 1)
    coarse = cs.upsample2(cs.downsample2(cs.with_batch(gt)))[:, 1:]                # z = 2 and 3, 8 x 8 x 2
    inputs = gt[::7]
    x0 = cs.union(cs.with_batch(coarse), cs.with_batch(inputs))[:, 1:]
    z0 = torch.zeros(len(x0), K)
    z0[cs.isin(cs.with_batch(x0), cs.with_batch(inputs))] = zgt[::7]
    cfg = CGCAConfig(**{**TINY.to_dict(), "channels": (16, 16), "in_proj": 16, "unet_stride": unet_stride})
    module = FineLoss(cfg)
    buf = ChainBuffer(2, lambda rng: _chain(x0, z0, gt, zgt, grid), cfg.steps, np.random.default_rng(0))
    opt = torch.optim.Adam(module.parameters(), lr=1e-2)
    losses = []
    for _ in range(120):
        idx = buf.take(2)
        loss, _, new = module([buf.chains[i] for i in idx])
        opt.zero_grad()
        loss.backward()
        torch.nn.utils.clip_grad_norm_(module.parameters(), 0.5)
        opt.step()
        for i, s in zip(idx, new):
            buf.advance(i, s)
        losses.append(float(loss.detach()))
    assert np.mean(losses[-10:]) < 0.3 * np.mean(losses[:10])
    cells, z = sample(module.model, CellState(cs.with_batch(x0), grid), z0, cfg.steps,
                      torch.Generator().manual_seed(0))
    hit = cs.isin(cells, cs.with_batch(gt))
    iou = int(hit.sum()) / (len(cells) + len(gt) - int(hit.sum()))
    assert iou > 0.9, iou
    zt = zgt[cs.lookup(cells[hit], cs.pack(cs.with_batch(gt)))]
    assert ((z[hit] - zt) ** 2).mean() < 0.05 * zgt.var(0).mean()   # 0.007 (stride 2), 0.0004 (1) vs 0.28


# -- the task with the shared trainer, shipped weights, and the pipeline's calls -------------------------------------
def _scene(seed: int, size: float = 3.2, height: float = 2.0) -> dict:
    """Ground + wall; distances to dense surface samples stand in for exact ones (a smoke-test dataset)."""
    rng = np.random.default_rng(seed)
    n = 20000
    wall_x = rng.uniform(1.0, size - 1.0)
    ground = np.c_[rng.uniform(0, size, (n, 2)), np.full(n, 0.5)]
    wall = np.c_[np.full(n // 2, wall_x), rng.uniform(0, size, n // 2), rng.uniform(0.5, 1.8, n // 2)]
    dense = np.concatenate([ground, wall])
    surf = dense[::4]
    pairs = surf + rng.normal(0, 0.05, surf.shape)
    pairs = pairs[np.all((pairs >= 0) & (pairs < [size, size, height]), axis=1)]
    occ10 = voxelize(dense, 0.1, (size, size, height))
    inp = surf[(surf[:, 2] < 1.2) & (rng.random(len(surf)) < 0.2)]
    return {"region": np.array([size / 2, size / 2, height / 2, size, size, height, 0.0]),
            "input_points": inp.astype(np.float32), "gt_occ10": occ10.astype(np.int16),
            "gt_occ20": downsample(occ10).astype(np.int16), "gt_surface": surf.astype(np.float32),
            "udf_points": pairs.astype(np.float32),
            "udf_dist": cKDTree(dense).query(pairs)[0].astype(np.float32)}


def test_fine_task_trains_exports_and_runs_the_pipeline_calls(tmp_path):
    torch.manual_seed(0)
    root = tmp_path / "data"
    for split, seeds in (("train", (0, 1)), ("val", (9,))):
        (root / split).mkdir(parents=True)
        for s in seeds:
            np.savez(root / split / f"sample_{s:07d}.npz", **_scene(s))
    ae = Autoencoder(AutoencoderConfig(latent=K, enc_hidden=8, mlp_hidden=8, dec_channels=8))
    save_weights(tmp_path / "ae.pt", ae, {"note": "untrained"})
    cfg = CGCAConfig(**{**TINY.to_dict(), "crop": 16, "steps": 3})
    task = FineTask(str(root), cfg, str(tmp_path / "ae.pt"), val_count=1)
    state = train(task, tmp_path / "run", minutes=5, max_steps=3, batch=2, buffer_size=2, progress=False)
    val = state["history"][-1]
    assert val["kind"] == "val" and 0.0 <= val["val_iou"] <= 1.0 and val["val_cd"] > 0
    ck = load_file(tmp_path / "run" / "ckpt.pt")
    assert all(len(c["extra"]["zt"]) == len(c["state"]) for c in ck["ranks"][0]["buffer"]["chains"])
    dest = export_fine(tmp_path / "run" / "ckpt.pt", tmp_path / "ae.pt", tmp_path / "fine.pt")
    model, ae2, meta = load_fine(dest)
    assert meta["kind"] == "fine" and meta["steps"] == 3 and model.cfg.steps == 3
    s = np.load(root / "val" / "sample_0000009.npz")
    grid10 = (32, 32, 20)
    calls = []
    out = [upsample(model, ae2, s["input_points"], s["gt_occ20"], grid10, None, torch.Generator().manual_seed(7),
                    lambda t, n: calls.append((t, n))) for _ in range(2)]
    cells, z = out[0]
    assert calls[-1] == (3, 3) and cells.shape[1] == 3 and z.shape == (len(cells), K)
    assert torch.equal(out[0][0], out[1][0]) and torch.equal(out[0][1], out[1][1])   # same seed, same result
    assert ((cells >= 0) & (cells < torch.tensor(grid10))).all()
    mesh = udf_mesh(ae2, cells, z, voxel=ae2.cfg.voxel)
    if len(mesh.vertices):                       # untrained decoder: whatever surface it has lies near the cells
        assert cKDTree(cells.numpy() * 0.1).query(mesh.vertices)[0].max() < 0.1


def _reference_forward(model, nbhd, state, z_state, x0, z0, grid):
    """The kernel as the paper writes it: concatenate [in x^t, in x^0, z^t, z^0, PE], project, U-Net, head."""
    from hgca_core.models.cgca import _gather, _table
    from hgca_core.nn.encoding import sinusoidal
    from hgca_core.nn.sparse import SparseTensor

    nk = cs.pack(nbhd)
    in_t, zt = _gather(nk, *_table(state, z_state))
    in_0, zz = _gather(nk, *_table(x0, z0))
    g = torch.tensor(grid, dtype=torch.float32)[model.pe_axes]
    pe = sinusoidal((nbhd[:, 1:][:, model.pe_axes].float() + 0.5) / g, model.cfg.pe_freq)
    feats = model.proj(torch.cat([in_t, in_0, zt, zz, pe], dim=1))
    x = SparseTensor(nbhd, feats, check=False)
    p = model.down(x)
    pc = p.coords.clone()
    pc[:, 1:] = torch.div(pc[:, 1:], 2, rounding_mode="floor")
    h = model.unet(SparseTensor(pc, p.feats, check=False)).feats
    u = model.up(SparseTensor(p.coords, h, 2, p.cache, check=False), x)
    out = model.head(torch.cat([feats, torch.relu(u.feats)], dim=1))
    return out[:, 0], out[:, 1:]


@pytest.mark.parametrize("pe_axes", ["z", "xyz"])
def test_blockwise_projection_equals_concatenation(pe_axes):
    torch.manual_seed(0)
    model = CGCAKernel(CGCAConfig(latent=K, channels=(8, 8, 8, 8, 8), pe_axes=pe_axes)).eval()
    x0, z0, st, zs, grid = _state()
    nbhd = model.neighbourhood(CellState(st, grid))
    for grad in (False, True):
        with torch.set_grad_enabled(grad):
            got = model(nbhd, st, zs, x0, z0)
            ref = _reference_forward(model, nbhd.coords, st, zs, x0, z0, grid)
        for a, b in zip(got, ref):
            torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-5)
    (got[0].sum() + got[1].square().sum()).backward()           # gradients flow through the block form
    assert model.proj[0].weight.grad is not None and model.proj[0].weight.grad.abs().sum() > 0
