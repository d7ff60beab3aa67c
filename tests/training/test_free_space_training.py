"""Training with observed free space: the per-sample cache, crops that carry it, `hgca train --free-space
--init-from` (warm start from weights without it) that trains and resumes, and the fine stage."""
import os

import numpy as np
import pytest
import torch
from scipy.spatial import cKDTree

from hgca_testdata import tiny_sample
from hgca_core.cli import main
from hgca_core.geometry import freespace
from hgca_core.geometry.voxel import COARSE, grid_shape
from hgca_core.io.digest import file_digest
from hgca_core.models.autoencoder import Autoencoder, AutoencoderConfig
from hgca_core.models.cgca import CGCAConfig
from hgca_core.models.gca import GCAConfig, GCAKernel
from hgca_core.models.weights import WEIGHTS_DIR, load_coarse, load_file
from hgca_core.training.export import save_weights
from hgca_core.training import data
from hgca_core.training.coarse import CoarseTask
from hgca_core.training.data import free_cells, free_path
from hgca_core.training.fine import FineTask
from hgca_core.training.trainer import train

pytestmark = pytest.mark.usefixtures("one_thread")
SMALL = dict(channels=(8, 8, 16, 16, 16))


def test_free_cells_are_cached_beside_the_sample(dataset, monkeypatch):
    path = sorted((dataset / "train").glob("sample_*.npz"))[0]
    s = np.load(path)
    grid = grid_shape(s["region"][3:6], COARSE)
    want = np.argwhere(freespace.observed_empty(s["input_points"], s["input_origins"], s["input_scan_index"], grid))
    assert len(want) > 100
    got = free_cells(path)
    assert np.array_equal(got, want) and free_path(path).exists()
    monkeypatch.setattr(data, "observed_empty", lambda *a: pytest.fail("recomputed although the sidecar is good"))
    assert np.array_equal(free_cells(path), want)
    monkeypatch.undo()
    free_path(path).write_bytes(b"not a numpy file")                   # corrupt: recomputed and rewritten
    assert np.array_equal(free_cells(path), want)
    os.utime(path, ns=(free_path(path).stat().st_mtime_ns + 10**9,) * 2)   # a sample rebuilt after its sidecar
    calls = []
    real = data.observed_empty
    monkeypatch.setattr(data, "observed_empty", lambda *a: calls.append(1) or real(*a))
    assert np.array_equal(free_cells(path), want) and calls == [1]


def test_coarse_chains_carry_their_crops_free_space(dataset):
    task = CoarseTask(str(dataset), GCAConfig(**SMALL, steps=3, free_space=True), crop=16)
    plain = CoarseTask(str(dataset), GCAConfig(**SMALL, steps=3), crop=16)
    for seed in range(3):
        ch, ref = task.new_example(np.random.default_rng(seed)), plain.new_example(np.random.default_rng(seed))
        assert torch.equal(ch.s0, ref.s0) and torch.equal(ch.gt, ref.gt) and ref.extra is None   # the same crop
        free = ch.extra["free"]
        assert free.dtype == torch.bool and free.shape == ch.grid
        assert not free[ch.s0[:, 0], ch.s0[:, 1], ch.s0[:, 2]].any()    # input cells are never seen empty
    # the crop of the free set is the crop of the cells: one crop cut from the whole sample by CropSpec
    path = task.train_files[0]
    rng = np.random.default_rng(5)
    (s0, gt), grid, extra = task.example(path, [], rng)
    spec = data.draw_crop(data.grids(path)[1], 16, np.random.default_rng(5))
    want = torch.zeros(grid, dtype=torch.bool)
    c = spec.cells(free_cells(path))
    want[c[:, 0], c[:, 1], c[:, 2]] = True
    assert torch.equal(extra["free"], want) and want.sum() > 10


def test_train_coarse_free_space_warm_starts_from_old_weights_and_resumes(dataset, tmp_path, capsys):
    torch.manual_seed(0)
    old = GCAKernel(GCAConfig(**SMALL, steps=3))
    save_weights(tmp_path / "old.pt", old, {"steps": 123})
    out = tmp_path / "run"
    base = ["train", "--data", str(dataset), "--out", str(out), "--threads", "1", "--no-progress"]
    recipe = ["--set", "crop=16", "--set", "batch=2", "--set", "buffer=2", "--set", "val_every=100"]
    assert main(base + recipe + ["--set", "free_space=true", "--set", f"init_from={tmp_path / 'old.pt'}",
                                 "--max-steps", "3"]) == 0
    ck = load_file(out / "ckpt.pt")
    assert ck["config"]["free_space"] is True and ck["config"]["steps"] == 3 and ck["state"]["step"] == 3
    assert any("initialised from" in n and "123 steps" in n and "zero-initialised" in n for n in ck["state"]["notes"])
    w = ck["model"]["model.unet.stem.0.weight"]
    assert w[:, 2].abs().sum() > 0                                     # the free column started at 0 and trained
    first = old.state_dict()["unet.stem.0.weight"].half().float()
    assert (w[:, [0, 1, 3]] - first[:, [0, 1, 2]]).abs().max() < 0.01  # the rest started from the old weights
    assert all(c["extra"]["free"].dtype == torch.bool for c in ck["ranks"][0]["buffer"]["chains"])
    assert main(base + ["--resume", "--max-steps", "2"]) == 0          # the checkpoint's architecture, no init
    ck2 = load_file(out / "ckpt.pt")
    assert ck2["state"]["step"] == 5 and ck2["config"]["free_space"] is True and len(ck2["state"]["sessions"]) == 2
    assert sum("initialised from" in n for n in ck2["state"]["notes"]) == 1
    card = WEIGHTS_DIR / "MODEL_CARD.md"
    card_before = card.read_bytes()
    assert main(base + ["--minutes", "0", "--export", str(tmp_path / "exported.pt")]) == 0   # export only, elsewhere
    model, meta = load_coarse(tmp_path / "exported.pt")
    assert model.cfg.free_space is True and meta["steps"] == 5 and len(meta["sessions"]) == 2
    assert meta["data"] == str(dataset) and card.read_bytes() == card_before             # the card is untouched
    assert meta["init"]["sha256"] == file_digest(tmp_path / "old.pt") and meta["init"]["steps"] == 123   # lineage
    capsys.readouterr()
    assert main(["train", "--data", str(dataset), "--out", str(tmp_path / "bad"), "--set", "free_space=true",
                 "--set", f"init_from={tmp_path / 'missing.pt'}", "--max-steps", "1"]) == 2
    assert "missing.pt" in capsys.readouterr().err
    assert main(["train", "--recipe", "coarse-noplanner", "--data", str(dataset), "--out", str(tmp_path / "np"),
                 "--set", f"init_from={tmp_path / 'old.pt'}", "--max-steps", "1"]) == 2     # no planner ablation
    assert "with the planner" in capsys.readouterr().err


def test_fine_stage_trains_with_free_space(dataset, tmp_path):
    for split in ("train", "val"):                                     # the fine stage also needs distance pairs
        for path in (dataset / split).glob("sample_*.npz"):
            s = dict(np.load(path))
            rng = np.random.default_rng(0)
            q = s["gt_surface"][::5] + rng.normal(0, 0.05, (len(s["gt_surface"][::5]), 3)).astype(np.float32)
            q = q[np.all((q >= 0) & (q < [6.0, 6.0, 4.0]), axis=1)]
            s["udf_points"], s["udf_dist"] = q, cKDTree(s["gt_surface"]).query(q)[0].astype(np.float32)
            np.savez(path, **s)
    torch.manual_seed(0)
    ae = Autoencoder(AutoencoderConfig(latent=4, enc_hidden=8, mlp_hidden=8, dec_channels=8))
    save_weights(tmp_path / "ae.pt", ae)
    cfg = CGCAConfig(latent=4, channels=(8, 8, 8), in_proj=8, pe_freq=1, crop=15, steps=2, free_space=True)
    task = FineTask(str(dataset), cfg, str(tmp_path / "ae.pt"), val_count=1)
    ch = task.new_example(np.random.default_rng(3))
    free = ch.extra["free"]
    assert free.shape == ch.grid == (15, 15, 40) and free.sum() > 10
    state = train(task, tmp_path / "fine", minutes=5, max_steps=2, batch=2, buffer_size=2, progress=False)
    assert state["step"] == 2 and 0.0 <= state["history"][-1]["val_iou"] <= 1.0
    ck = load_file(tmp_path / "fine" / "ckpt.pt")
    assert ck["model"]["model.proj.0.weight"].shape[1] == 2 + 8 + 2 + 1


def test_free_weight_weighs_the_loss_on_seen_empty_negatives(dataset, capsys, monkeypatch):
    """`--free-weight W`: a neighbourhood cell the rays saw through and the ground truth leaves empty weighs
    1 + W in the kernel's BCE; a seen-empty cell the ground truth fills, and every other cell, weigh 1."""
    from hgca_core.training.coarse import CoarseLoss

    cfg = GCAConfig(**SMALL, steps=3, free_space=True)
    task = CoarseTask(str(dataset), cfg, crop=16, free_weight=5.0)
    chains = [task.new_example(np.random.default_rng(s)) for s in (1, 2)]
    free0 = chains[0].extra["free"]
    filled = torch.nonzero(free0)[:3]
    chains[0].gt = torch.cat([chains[0].gt, filled])                    # seen empty, yet in the ground truth
    for ch in chains:                                                  # chains that grew into the free space
        ch.state = torch.cat([ch.state, torch.nonzero(ch.extra["free"])[::7]])
    torch.manual_seed(0)
    plain = CoarseLoss(cfg)
    weighted = CoarseLoss(cfg, free_weight=5.0)
    weighted.load_state_dict(plain.state_dict())
    seen_logits = []
    real_forward = GCAKernel.forward

    def recording(self, nbhd, *a, **k):
        out = real_forward(self, nbhd, *a, **k)
        seen_logits.append((nbhd.coords, out.detach()))
        return out

    monkeypatch.setattr(GCAKernel, "forward", recording)
    _, s_plain, _ = plain(chains)
    _, s_weighted, _ = weighted(chains)
    monkeypatch.undo()
    nbhd, logits = seen_logits[1]
    assert torch.equal(nbhd, seen_logits[0][0])
    gts = [{tuple(c) for c in ch.gt.tolist()} for ch in chains]
    frees = [ch.extra["free"] for ch in chains]
    target = torch.tensor([tuple(r[1:]) in gts[r[0]] for r in nbhd.tolist()], dtype=torch.float32)
    seen = torch.tensor([bool(frees[r[0]][r[1], r[2], r[3]]) and tuple(r[1:]) not in gts[r[0]]
                         for r in nbhd.tolist()])
    assert 0 < seen.sum() < len(seen)
    gt_free = [bool(frees[r[0]][r[1], r[2], r[3]]) and tuple(r[1:]) in gts[r[0]] for r in nbhd.tolist()]
    assert any(gt_free)                                                 # the filled seen-empty cells were scored
    p = torch.sigmoid(logits.double())
    bce = -(target * torch.log(p) + (1 - target) * torch.log(1 - p))
    assert s_plain["loss_gca"] == pytest.approx(float(bce.mean()), rel=1e-5)
    assert s_weighted["loss_gca"] == pytest.approx(float(((1 + 5.0 * seen) * bce).mean()), rel=1e-5)
    assert s_weighted["seen_empty"] == pytest.approx(float(seen.float().mean()))
    assert task.recipe()["free_weight"] == 5.0
    capsys.readouterr()
    run = ["--out", str(dataset.parent / "run")]
    assert main(["train", "--data", str(dataset), *run, "--set", "free_weight=2", "--max-steps", "1"]) == 2
    assert "free_space=true" in capsys.readouterr().err                 # nothing to weigh without the free space
    assert main(["train", "--data", str(dataset), *run, "--set", "free_space=true", "--set", "free_weight=-1",
                 "--max-steps", "1"]) == 2
    assert "free_weight must lie in [0" in capsys.readouterr().err


def test_height_cut_inputs_match_eval_reals_cut(dataset, monkeypatch):
    """`--cut`: a training input cut h m above the ground holds the cells of the input points below the cut (as
    `hgca eval-real` cuts a real scan), and the layer the cut crosses whole; its free space above the cut is
    unknown."""
    from hgca_core.geometry.region import BELOW_GROUND
    from hgca_core.geometry.voxel import voxelize
    from hgca_core.training import coarse
    from hgca_core.training.coarse import height_cut

    path = sorted((dataset / "train").glob("sample_*.npz"))[0]
    s = np.load(path)
    pts, size = s["input_points"], s["region"][3:6]
    s0, free = voxelize(pts, COARSE, size), free_cells(path)
    for h in (0.65, 0.75, 0.95):                                       # the tiny samples' input ends at 2.2 m
        cut_s0, cut_free = height_cut(s0, free, h)
        layer = int((BELOW_GROUND + h) / COARSE)                        # the cell layer the cut crosses
        below = {tuple(c) for c in voxelize(pts[pts[:, 2] < BELOW_GROUND + h], COARSE, size).tolist()}
        kept = {tuple(c) for c in cut_s0.tolist()}
        assert below <= kept and all(c[2] == layer for c in kept - below)
        assert len(cut_s0) < len(s0) and cut_s0[:, 2].max() == layer
        assert np.array_equal(cut_free, free[free[:, 2] <= layer]) and len(cut_free) < len(free)
    monkeypatch.setattr(coarse, "CUT_HEIGHTS", (0.5, 0.9))
    task = CoarseTask(str(dataset), GCAConfig(**SMALL, steps=3, free_space=True), crop=16, focus_share=1.0,
                      cut_share=1.0)
    for seed in range(4):
        ch = task.new_example(np.random.default_rng(seed))
        limit = int(np.ceil((BELOW_GROUND + 0.9) / COARSE))
        assert ch.s0[:, 2].max() < limit and not ch.extra["free"][..., limit:].any()
        assert ch.gt[:, 2].max() >= limit                               # what lies above is still to be made
    assert task.recipe()["cut_share"] == 1.0


def test_cut_free_loss_weighs_what_the_uncut_scan_saw_empty(dataset, monkeypatch, capsys):
    """`--cut-free-loss`: a cut input keeps the model's view (no free space above the cut) but its loss weighs
    the cells the uncut input saw empty, above the cut too, as `hgca eval-real` counts growth there."""
    from hgca_core.geometry.region import BELOW_GROUND
    from hgca_core.training import coarse
    from hgca_core.training.coarse import CoarseLoss

    monkeypatch.setattr(coarse, "CUT_HEIGHTS", (0.5, 0.9))
    cfg = GCAConfig(**SMALL, steps=3, free_space=True)
    task = CoarseTask(str(dataset), cfg, crop=16, cut_share=1.0, free_weight=5.0, cut_free_loss=True)
    plain_task = CoarseTask(str(dataset), cfg, crop=16, cut_share=1.0, free_weight=5.0)
    limit = int(np.ceil((BELOW_GROUND + 0.9) / COARSE))
    chains = [task.new_example(np.random.default_rng(s)) for s in (0, 1)]
    same = plain_task.new_example(np.random.default_rng(0))             # same draws without the option
    assert torch.equal(same.s0, chains[0].s0) and torch.equal(same.extra["free"], chains[0].extra["free"])
    assert "free_loss" not in same.extra and task.recipe()["cut_free_loss"] is True
    for ch in chains:
        free, loss_free = ch.extra["free"], ch.extra["free_loss"]
        assert not free[..., limit:].any() and loss_free[..., limit:].any()
        assert torch.equal(free & loss_free, free)                      # below the cut the two agree
        ch.state = torch.cat([ch.state, torch.nonzero(loss_free[..., limit:])[::5] + torch.tensor([0, 0, limit])])
    model_free = []
    real_forward = GCAKernel.forward

    def recording(self, nbhd, st, s0, bev, free):
        model_free.append(free)
        return real_forward(self, nbhd, st, s0, bev, free)

    monkeypatch.setattr(GCAKernel, "forward", recording)
    torch.manual_seed(0)
    loss = CoarseLoss(cfg, free_weight=5.0)
    _, with_uncut, _ = loss(chains)
    for ch in chains:
        ch.extra.pop("free_loss")
    _, cut_only, _ = loss(chains)
    assert torch.equal(model_free[0], model_free[1])                   # the model sees the cut's view both times
    assert with_uncut["seen_empty"] > cut_only["seen_empty"]
    assert main(["train", "--data", str(dataset), "--out", str(dataset.parent / "run"), "--set", "free_space=true",
                 "--set", "free_weight=2", "--set", "cut_free_loss=true", "--max-steps", "1"]) == 2
    assert "needs cut" in capsys.readouterr().err
