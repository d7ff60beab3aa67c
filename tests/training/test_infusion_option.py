"""`hgca train --infusion A0,A1`: a new run trains with that schedule (kept in its checkpoint and weights), the
chains' next states follow it, and a resumed run or a bad schedule is refused."""
import shutil

import numpy as np
import pytest
import torch

from hgca_core.cli import main
from hgca_core.models.gca import GCAConfig
from hgca_core.models.weights import load_file
from hgca_core.training.coarse import CoarseTask

pytestmark = pytest.mark.usefixtures("one_thread")


def test_infusion_sets_a_new_runs_schedule_and_a_resume_keeps_its_own(tiny_dataset, tmp_path, capsys):
    data = tmp_path / "data"
    shutil.copytree(tiny_dataset, data)
    run = tmp_path / "run"
    base = ["train", "coarse", "--data", str(data), "--out", str(run), "--channels", "8,8,16,16,16",
            "--no-progress", "--val-every", "1000"]
    assert main([*base, "--max-steps", "1", "--infusion", "0.05,0.01"]) == 0
    cfg = load_file(run / "ckpt.pt")["config"]
    assert (cfg["alpha0"], cfg["alpha1"]) == (0.05, 0.01)
    capsys.readouterr()
    assert main([*base, "--max-steps", "1", "--resume", "--infusion", "0.1,0.0"]) == 2
    assert "keeps its own" in capsys.readouterr().err
    for bad in ("2,0", "0.1", "a,b"):
        with pytest.raises(SystemExit) as e:
            main([*base, "--max-steps", "1", "--infusion", bad])
        assert e.value.code == 2


def test_the_chains_next_states_follow_the_infusion_weight(tiny_dataset):
    """alpha = 1: the next state is exactly the ground-truth cells of the neighbourhood, whatever the model says;
    alpha = 0: the model's own draw (an untrained model's is far from it)."""
    from hgca_core.geometry import coords as cs

    def step(alpha: float) -> set:
        task = CoarseTask(str(tiny_dataset), GCAConfig(channels=(8, 8, 16, 16, 16), steps=3, alpha0=alpha,
                                                       alpha1=0.0), crop=16)
        chain = task.new_example(np.random.default_rng(0))
        torch.manual_seed(0)
        with torch.no_grad():
            _, _, (nxt,) = task.build().eval()([chain])   # eval: BatchNorm of a 16-cell crop
        nbhd = cs.dilate(cs.with_batch(chain.state), 1, bounds=chain.grid)
        want = {tuple(c) for c in nbhd[cs.isin(nbhd, cs.with_batch(chain.gt))][:, 1:].tolist()}
        return {tuple(c) for c in nxt.tolist()}, want

    got, want = step(1.0)
    assert got == want and len(want) > 20
    got, want = step(0.0)
    assert len(got ^ want) > len(want) // 4
