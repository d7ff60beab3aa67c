"""`hgca train --export` ships every stage's selection on val: the weight average kept at the run's best validation
score (best.pt), not the last step's, with the step and score in the record; a run without best.pt (from before it
was kept) ships its checkpoint, and a new run refuses a folder holding another run's best.pt."""
from __future__ import annotations

import pytest
import torch

from hgca_core.cli import main
from hgca_core.models.gca import GCAConfig
from hgca_core.models.weights import load_file, save_file
from hgca_core.training.coarse import CoarseTask
from hgca_core.training.recipes import parse_sets, resolve
from hgca_core.training.trainer import train

SETS = ["channels=8,8,16,16,16", "crop=24", "batch=1", "buffer=1"]


@pytest.fixture(scope="module")
def selected_run(tiny_dataset, tmp_path_factory):
    """A 3-step coarse-noplanner run validated after every step, scoring 0.5, 0.7, 0.6: best.pt is step 2's
    average, ckpt.pt step 3's (the scores are set so that best and last differ; the weights are trained)."""
    recipe = resolve("coarse-noplanner", parse_sets(SETS))
    task = CoarseTask(str(tiny_dataset), GCAConfig(use_planner=False, steps=4, channels=recipe.channels),
                      crop=recipe.crop, val_count=1)
    scores = iter([0.5, 0.7, 0.6])
    task.validate = lambda model: {"val_iou": next(scores)}
    out = tmp_path_factory.mktemp("sel") / "run"
    train(task, out, minutes=5, max_steps=3, batch=1, buffer_size=1, progress=False, val_every_min=0,
          recipe={"name": "coarse-noplanner", "fields": recipe.to_dict()})
    return out


def _export(tiny_dataset, run, dest) -> dict:
    code = main(["train", "--data", str(tiny_dataset), "--out", str(run), "--minutes", "0", "--export", str(dest),
                 "--no-progress"])
    assert code == 0
    return load_file(dest)


def _model_weights(ck: dict) -> dict:
    return {k[len("model."):]: v for k, v in ck["ema"]["model"].items()}


def _same(exported: dict, weights: dict) -> bool:
    """Exported (fp16 where floating) tensors equal to a run's fp32 average as saving rounds it."""
    sd = exported["state_dict"]
    return sd.keys() == weights.keys() and all(
        torch.equal(sd[k], weights[k].to(sd[k].dtype)) for k in sd)


def test_export_ships_the_val_selected_average_and_names_its_step(selected_run, tiny_dataset, tmp_path):
    best, last = load_file(selected_run / "best.pt"), load_file(selected_run / "ckpt.pt")
    assert (best["state"]["step"], last["state"]["step"]) == (2, 3)
    blob = _export(tiny_dataset, selected_run, tmp_path / "w.pt")
    assert _same(blob, _model_weights(best)) and not _same(blob, _model_weights(last))
    meta = blob["meta"]
    assert meta["selected"] == {"key": "val_iou", "value": 0.7, "step": 2, "file": "best.pt"}
    assert meta["steps"] == 2 and meta["stage"] == "coarse-noplanner"
    assert any("trained 3 steps" in n and "step 2" in n and "70.0 %" in n for n in meta["notes"])


def test_a_run_without_best_pt_ships_its_checkpoint(selected_run, tiny_dataset, tmp_path):
    import shutil

    old = tmp_path / "old"
    old.mkdir()
    shutil.copy(selected_run / "ckpt.pt", old / "ckpt.pt")    # a run from before best.pt was kept
    blob = _export(tiny_dataset, old, tmp_path / "w.pt")
    assert _same(blob, _model_weights(load_file(old / "ckpt.pt")))
    assert "selected" not in blob["meta"] and blob["meta"]["steps"] == 3


def test_a_new_run_refuses_a_folder_holding_another_runs_best_pt(selected_run, tiny_dataset, tmp_path, capsys):
    import shutil

    stale = tmp_path / "stale"
    stale.mkdir()
    shutil.copy(selected_run / "best.pt", stale / "best.pt")
    for resume in ([], ["--resume"]):
        code = main(["train", "--data", str(tiny_dataset), "--out", str(stale), "--max-steps", "1", "--no-progress",
                     *[a for s in SETS for a in ("--set", s)], *resume])
        err = capsys.readouterr().err
        assert code == 2 and "best.pt of an earlier run" in err and str(stale / "best.pt") in err, err
    assert sorted(p.name for p in stale.iterdir()) == ["best.pt"]     # nothing trained, nothing written


@pytest.mark.parametrize("stage", ["autoencoder", "fine"])
def test_the_other_stages_exporters_take_best_pt(stage, tmp_path):
    """The autoencoder's and the fine stage's exporters read the run the same way (checkpoints as the trainer
    writes them, their averages drawn from two seeds)."""
    from hgca_core.models.autoencoder import AutoencoderConfig
    from hgca_core.models.cgca import CGCAConfig
    from hgca_core.models.weights import shipped
    from hgca_core.training.fine import AutoencoderLoss, FineLoss, export_autoencoder, export_fine

    def checkpoint(name: str, seed: int, step: int, best: dict | None) -> dict:
        torch.manual_seed(seed)
        module = AutoencoderLoss(AutoencoderConfig()) if stage == "autoencoder" else FineLoss(CGCAConfig())
        state = {"step": step, "elapsed_s": 1.0, "history": [], "sessions": [], "seed": 0,
                 **({"best_val": best} if best else {})}
        save_file({"model": module.state_dict(), "ema": {"model": module.state_dict()}, "state": state,
                   "config": module.cfg.to_dict(), "task": stage}, tmp_path / name)
        return {k: v.clone() for k, v in module.model.state_dict().items()}

    def export(dest: str) -> dict:
        if stage == "autoencoder":
            return load_file(export_autoencoder(tmp_path / "ckpt.pt", tmp_path / dest))
        return load_file(export_fine(tmp_path / "ckpt.pt", shipped("autoencoder"), tmp_path / dest))

    last = checkpoint("ckpt.pt", seed=1, step=90, best={"key": "val_cd", "value": 0.05, "step": 90})
    without = export("last.pt")
    best = checkpoint("best.pt", seed=2, step=60, best={"key": "val_cd", "value": 0.04, "step": 60})
    chosen = export("best_w.pt")

    def same(blob: dict, weights: dict) -> bool:
        sd = blob["state_dict"]
        return all(torch.equal(sd[k], v.to(sd[k].dtype)) for k, v in weights.items())

    assert same(without, last) and "selected" not in without["meta"]
    assert same(chosen, best) and not same(chosen, last)
    assert chosen["meta"]["selected"]["step"] == 60 and chosen["meta"]["steps"] == 60
    assert any("trained 90 steps" in n and "val_cd (0.04)" in n for n in chosen["meta"]["notes"])
