"""Recipe field `distill` (MU): on cut training inputs the coarse kernel's target moves MU of the way from the ground
truth to the probability of the `init_from` weights (cells the rays saw empty stay empty); whole inputs keep the
ground truth."""
import numpy as np
import pytest
import torch

from hgca_core.cli import main
from hgca_core.io.digest import file_digest
from hgca_core.models.gca import GCAConfig, GCAKernel
from hgca_core.models.weights import load_file
from hgca_core.training.export import save_weights
from hgca_core.nn.sparse import CellState
from hgca_core.training import coarse
from hgca_core.training.card import write_model_card
from hgca_core.training.coarse import CoarseLoss, CoarseTask

pytestmark = pytest.mark.usefixtures("one_thread")
SMALL = dict(channels=(8, 8, 16, 16, 16))
BASE = ["train", "--set", "crop=16", "--threads", "1", "--no-progress", "--set", "val_every=1000"]
NEW = ["--set", "channels=8,8,16,16,16"]   # a run started from weights takes their widths


def _chains(dataset, monkeypatch, cfg):
    """Two chains of the same scene: the first cut 0.5-0.9 m up, the second whole."""
    monkeypatch.setattr(coarse, "CUT_HEIGHTS", (0.5, 0.9))
    cut = CoarseTask(str(dataset), cfg, crop=16, cut_share=1.0, free_weight=5.0, cut_free_loss=True)
    whole = CoarseTask(str(dataset), cfg, crop=16, free_weight=5.0)
    chains = [cut.new_example(np.random.default_rng(0)), whole.new_example(np.random.default_rng(1))]
    layer = chains[0].extra["cut"]      # the cut's first cell layer: 0.5-0.9 m above the ground
    assert coarse.cut_layer(0.5) <= layer <= coarse.cut_layer(0.9) and "cut" not in chains[1].extra
    for ch in chains:   # states that grew into what the (uncut) rays saw empty
        seen = ch.extra.get("free_loss", ch.extra["free"])
        ch.state = torch.cat([ch.state, torch.nonzero(seen)[::5]])
    return chains


def _record_forwards(monkeypatch) -> list:
    """Every GCAKernel forward from now on, as (module, nbhd, logits), in call order."""
    calls = []
    real_forward = GCAKernel.forward

    def recording(self, nbhd, *a, **k):
        out = real_forward(self, nbhd, *a, **k)
        calls.append((self, nbhd.coords, out.detach()))
        return out

    monkeypatch.setattr(GCAKernel, "forward", recording)
    return calls


@pytest.mark.parametrize("mu", [1.0, 0.5])
def test_cut_inputs_learn_the_teachers_probability_and_whole_ones_the_ground_truth(dataset, monkeypatch, mu):
    cfg = GCAConfig(**SMALL, steps=3, free_space=True)
    chains = _chains(dataset, monkeypatch, cfg)
    torch.manual_seed(0)
    teacher = GCAKernel(cfg).eval()
    torch.manual_seed(1)
    loss = CoarseLoss(cfg, free_weight=5.0, distill=mu, teacher=teacher)
    assert not any(k.startswith("_teacher") or "teacher" in k for k in loss.state_dict())  # never checkpointed
    calls = _record_forwards(monkeypatch)
    _, stats, _ = loss(chains)
    monkeypatch.undo()
    (s_mod, nbhd, logits), (t_mod, t_nbhd, t_logits) = calls
    assert s_mod is loss.model and t_mod is teacher and torch.equal(nbhd[nbhd[:, 0] == 0], t_nbhd)  # the cut chain
    gts = [{tuple(c) for c in ch.gt.tolist()} for ch in chains]
    rows = nbhd.tolist()
    hard = torch.tensor([tuple(r[1:]) in gts[r[0]] for r in rows], dtype=torch.float64)
    frees = [ch.extra.get("free_loss", ch.extra["free"]) for ch in chains]
    seen = torch.tensor([bool(frees[r[0]][r[1], r[2], r[3]]) for r in rows]) & (hard == 0)
    cut = nbhd[:, 0] == 0
    assert cut.any() and (~cut).any() and (seen & cut).any()
    teach = torch.zeros(len(nbhd), dtype=torch.float64)
    teach[nbhd[:, 0] == 0] = torch.sigmoid(t_logits.double())
    target = torch.where(cut, (1 - mu) * hard + mu * teach, hard) * (~seen)
    p = torch.sigmoid(logits.double())
    bce = -(target * torch.log(p) + (1 - target) * torch.log(1 - p))
    expected = float(((1 + 5.0 * seen) * bce).mean())
    assert stats["loss_gca"] == pytest.approx(expected, rel=1e-5)
    assert stats["distilled"] == pytest.approx(float(cut.double().mean()))
    plain = CoarseLoss(cfg, free_weight=5.0)
    plain.load_state_dict(loss.state_dict())
    torch.manual_seed(0)
    _, plain_stats, _ = plain(chains)
    assert plain_stats["loss_gca"] != pytest.approx(stats["loss_gca"], rel=1e-4)   # the teacher changed it


def test_the_teacher_runs_on_the_cut_chains_alone_and_gives_them_what_it_gives_in_the_whole_batch(dataset, monkeypatch):
    """A step's whole chains need no teacher: it runs on the cut ones, renumbered, and (eval mode: no chain's
    output depends on another's) gives their cells the logits it gives them in the whole batch."""
    cfg = GCAConfig(**SMALL, steps=3, free_space=True)
    cut, whole = _chains(dataset, monkeypatch, cfg)
    chains = [whole, cut, whole]            # the cut chain is renumbered 1 -> 0
    torch.manual_seed(0)
    teacher = GCAKernel(cfg).eval()
    loss = CoarseLoss(cfg, free_weight=5.0, distill=1.0, teacher=teacher)
    calls = _record_forwards(monkeypatch)
    loss(chains)
    monkeypatch.undo()
    [(t_nbhd, t_logits)] = [(n, out) for m, n, out in calls if m is teacher]
    grid = chains[0].grid
    s0, st = (coarse.batched([getattr(c, k) for c in chains]) for k in ("s0", "state"))
    free = torch.stack([c.extra["free"] for c in chains])
    hood = teacher.neighbourhood(CellState(st, grid))
    with torch.no_grad():
        ref = teacher(hood, st, s0, teacher.bev(CellState(s0, grid), 3, free), free)
    nbhd = hood.coords
    mine = nbhd[:, 0] == 1
    assert len(t_nbhd) == int(mine.sum()) < len(nbhd) and (t_nbhd[:, 0] == 0).all()
    assert torch.equal(t_nbhd[:, 1:], nbhd[mine, 1:])
    torch.testing.assert_close(t_logits, ref[mine], rtol=1e-5, atol=1e-5)   # GEMMs of fewer rows round apart


def test_a_teacher_equal_to_the_student_leaves_cut_inputs_nothing_to_learn(dataset, monkeypatch):
    """With the student's own weights as teacher and no free-space weight, the cut chain's cells give no
    gradient (the target is the prediction), the whole chain's do (no planner: its loss would train either way)."""
    cfg = GCAConfig(**SMALL, steps=3, free_space=True, use_planner=False)
    chains = _chains(dataset, monkeypatch, cfg)
    loss = CoarseLoss(cfg, distill=1.0)
    teacher = GCAKernel(cfg)
    teacher.load_state_dict(loss.model.state_dict())
    loss._teacher = [teacher.eval()]
    loss.eval()     # both normalise by the same running statistics
    grads = []
    for keep in ([0], [1]):
        loss.zero_grad()
        total, _, _ = loss([chains[i] for i in keep])
        total.backward()
        head = [p.grad for p in loss.model.parameters() if p.grad is not None]
        grads.append(max(float(g.abs().max()) for g in head))
    cut_grad, whole_grad = grads
    assert whole_grad > 1e-4 and cut_grad < 1e-3 * whole_grad


def test_distill_needs_a_cut_the_free_space_and_init_weights_and_is_kept_on_resume(dataset, tmp_path, capsys):
    base = BASE + ["--data", str(dataset)]
    init = tmp_path / "init.pt"
    assert main(base + NEW + ["--out", str(tmp_path / "a"), "--set", "free_space=true", "--max-steps", "1",
                        "--export", str(init)]) == 0
    capsys.readouterr()
    for extra, says in ((["--set", "distill=0.5", "--set", f"init_from={init}"], "needs cut"),
                        (["--set", "distill=0.5", "--set", "cut=0.5"], "init_from"),
                        (["--set", "distill=1.5", "--set", "cut=0.5", "--set", f"init_from={init}"], "[0, 1]")):
        out = tmp_path / "bad"
        assert main(base + ["--out", str(out), "--set", "free_space=true", "--max-steps", "1"] + extra) == 2
        assert says in capsys.readouterr().err and not out.exists()
    no_planner = tmp_path / "np.pt"
    save_weights(no_planner, GCAKernel(GCAConfig(**SMALL, use_planner=False, free_space=True)))
    assert main(base + ["--out", str(tmp_path / "bad"), "--set", "free_space=true", "--max-steps", "1",
                               "--set", "cut=0.5", "--set", f"init_from={no_planner}", "--set", "distill=1"]) == 2
    assert "planner" in capsys.readouterr().err
    out = tmp_path / "b"
    assert main(base + ["--out", str(out), "--set", f"init_from={init}", "--set", "cut=1", "--set",
                               "free_space=true", "--set", "distill=0.5", "--max-steps", "2"]) == 0
    assert main(base + ["--out", str(out), "--resume", "--max-steps", "3"]) == 0
    ck = load_file(out / "ckpt.pt")
    recipes = [s["recipe"] for s in ck["state"]["sessions"]]
    assert [r["distill"] for r in recipes] == [0.5, 0.5]
    assert all(r["teacher"] == str(init.resolve()) for r in recipes)
    assert not any("teacher" in k for k in ck["model"])


def test_a_resume_refuses_a_teacher_overwritten_since_the_run_started(dataset, tmp_path, capsys):
    """Shipping a fine-tune overwrites the weights it distilled from: a resume must notice (exit 2, checkpoint
    untouched) rather than distil from the student."""
    base = BASE + ["--data", str(dataset)]
    teacher = tmp_path / "teacher.pt"
    assert main(base + NEW + ["--out", str(tmp_path / "a"), "--set", "free_space=true", "--max-steps", "1", "--export",
                        str(teacher)]) == 0
    first = file_digest(teacher)
    out = tmp_path / "b"
    assert main(base + ["--out", str(out), "--set", f"init_from={teacher}", "--set", "cut=1", "--set",
                               "free_space=true", "--set", "distill=1", "--max-steps", "1"]) == 0
    assert load_file(out / "ckpt.pt")["state"]["sessions"][0]["recipe"]["teacher_sha256"] == first
    shipped = tmp_path / "weights"                     # the card names each session's teacher by its digest
    shipped.mkdir()
    assert main(base + ["--out", str(out), "--minutes", "0", "--export", str(shipped / "coarse.pt")]) == 0
    assert f"teacher sha256 {first}" in write_model_card(shipped).read_text()
    assert main(base + ["--out", str(out), "--minutes", "0", "--export", str(teacher)]) == 0   # the student shipped
    assert file_digest(teacher) != first
    before = (out / "ckpt.pt").read_bytes()
    capsys.readouterr()
    assert main(base + ["--out", str(out), "--resume", "--max-steps", "2"]) == 2
    err = capsys.readouterr().err
    assert str(teacher) in err and first[:12] in err
    assert (out / "ckpt.pt").read_bytes() == before
