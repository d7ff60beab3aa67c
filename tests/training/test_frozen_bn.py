"""`--frozen-bn`: the coarse model trains under the running BatchNorm statistics of the weights it starts from, the
ones sampling normalises by, instead of each batch's own."""

import pytest
import torch

from hgca_core.cli import main
from hgca_core.models.gca import GCAConfig
from hgca_core.models.weights import load_file
from hgca_core.training.coarse import CoarseLoss, CoarseTask
from hgca_core.training.trainer import train

pytestmark = pytest.mark.usefixtures("one_thread")
BASE = ["train", "coarse", "--channels", "8,8,16,16,16", "--crop", "16", "--threads", "1", "--no-progress",
        "--val-every", "1000"]


def _bn(state: dict) -> dict:
    return {k: v for k, v in state.items() if k.endswith(("running_mean", "running_var"))}


def _params(state: dict) -> dict:
    return {k: v for k, v in state.items() if k.endswith("conv.weight") or k.endswith(".weight")}


def test_frozen_batchnorm_stays_in_eval_mode_through_train_calls() -> None:
    loss = CoarseLoss(GCAConfig(channels=(8, 8, 16, 16, 16)), frozen_bn=True)
    bns = [m for m in loss.modules() if isinstance(m, torch.nn.modules.batchnorm._BatchNorm)]
    assert bns and loss.train().training
    assert not any(m.training for m in bns)
    convs = [m for m in loss.modules() if not isinstance(m, torch.nn.modules.batchnorm._BatchNorm)]
    assert all(m.training for m in convs)
    free = CoarseLoss(GCAConfig(channels=(8, 8, 16, 16, 16))).train()
    assert all(m.training for m in free.modules())


@pytest.mark.parametrize("frozen", [True, False])
def test_training_keeps_the_initial_statistics_only_when_frozen(dataset, tmp_path, frozen) -> None:
    init = tmp_path / "init.pt"
    base = BASE + ["--data", str(dataset)]
    assert main(base + ["--out", str(tmp_path / "a"), "--max-steps", "2", "--export", str(init)]) == 0
    start = load_file(init)["state_dict"]
    out = tmp_path / "b"
    assert main(base + ["--out", str(out), "--init-from", str(init), "--max-steps", "3", "--lr", "1e-2"]
                + (["--frozen-bn"] if frozen else [])) == 0
    ck = load_file(out / "ckpt.pt")
    for state in (ck["model"], ck["ema"]["model"]):
        stats = {k.removeprefix("model."): v for k, v in _bn(state).items()}
        assert stats.keys() == _bn(start).keys() and stats
        same = all(torch.equal(stats[k].to(start[k].dtype), start[k]) for k in stats)
        assert same == frozen
    moved = [k for k, v in _params(ck["model"]).items()
             if not torch.equal(v.to(start[k.removeprefix("model.")].dtype), start[k.removeprefix("model.")])]
    assert moved, "the parameters train either way"
    assert ck["state"]["sessions"][-1]["recipe"]["frozen_bn"] is frozen


def test_frozen_bn_is_kept_on_resume_and_needs_weights_to_start_from(dataset, tmp_path, capsys) -> None:
    base = BASE + ["--data", str(dataset)]
    assert main(base + ["--out", str(tmp_path / "x"), "--frozen-bn", "--max-steps", "1"]) == 2
    assert "--frozen-bn" in capsys.readouterr().err and not (tmp_path / "x" / "ckpt.pt").exists()
    # --resume of a folder without a checkpoint starts a new run: no statistics to keep either
    assert main(base + ["--out", str(tmp_path / "x"), "--resume", "--frozen-bn", "--max-steps", "1"]) == 2
    assert "--frozen-bn" in capsys.readouterr().err and not (tmp_path / "x" / "ckpt.pt").exists()
    init = tmp_path / "init.pt"
    assert main(base + ["--out", str(tmp_path / "a"), "--max-steps", "1", "--export", str(init)]) == 0
    out = tmp_path / "b"
    assert main(base + ["--out", str(out), "--init-from", str(init), "--frozen-bn", "--max-steps", "1"]) == 0
    assert main(base + ["--out", str(out), "--resume", "--max-steps", "1"]) == 0
    sessions = load_file(out / "ckpt.pt")["state"]["sessions"]
    assert [s["recipe"]["frozen_bn"] for s in sessions] == [True, True]
    task = CoarseTask(str(dataset), GCAConfig(channels=(8, 8, 16, 16, 16)), frozen_bn=True)
    assert task.build().frozen_bn and task.recipe()["frozen_bn"] is True
