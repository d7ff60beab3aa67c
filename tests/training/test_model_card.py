"""The model card is rendered from the weights files and the eval results beside them, never typed."""
import json

import torch

from hgca_core.models.gca import GCAConfig, GCAKernel
from hgca_core.training.export import save_weights
from hgca_core.training.card import write_model_card


def test_card_renders_weights_metadata_and_eval_provenance(tmp_path):
    torch.manual_seed(0)
    session = {"ended": "2026-11-23 10:45:24", "steps": 77, "wall_s": 12.5, "device": "cpu", "device_name": "EPYC",
               "threads": 1, "world_size": 1, "precision": "bf16", "recipe": {"crop": 64, "focus_share": 0.5}}
    gpu = {**session, "device": "cuda", "device_name": "NVIDIA H200", "threads": 5, "lr": 1.5e-4, "batch": 6,
           "ema_decay": 0.9998}
    meta = {"stage": "coarse", "data": "data/synth2", "crop": 64, "steps": 77, "train_wall_s": 12.5,
            "sessions": [session, gpu], "notes": ["selected on validation"], "train_samples": ["sample_0000003.npz"],
            "history_tail": [{"step": 77, "kind": "val", "val_iou": 0.5}]}
    save_weights(tmp_path / "coarse.pt", GCAKernel(GCAConfig(channels=(8, 8, 16, 16, 16), free_space=True)), meta)
    (tmp_path / "eval_test.md").write_text("| Method |\n|---|\n| hGCA |\n")
    rows = {"hGCA coarse (planner)": {"k": 3, "seconds_per_completion": 12.5}}
    (tmp_path / "eval_test.json").write_text(json.dumps({
        "data": "data/synth2", "split": "test", "files": ["sample_2000000.npz"], "samples": 3, "t1": None,
        "free_space": "off", "rows": rows, "notes": ["The GCA row is not like-for-like."]}))
    card = write_model_card(tmp_path).read_text()
    assert '"free_space": true' in card                                  # the file's own config
    assert "training data: data/synth2 (train split): 1 samples, seeds 3-3" in card
    assert "77 steps in 12.5 s, device cpu (EPYC), 1 thread(s), world size 1, bf16 GEMMs, crop 64, focus share 0.5" in card
    assert ("device cuda (NVIDIA H200), 5 thread(s), world size 1, bf16 GEMMs, learning rate 0.00015, 6 chains a step, "
            "weight average decay 0.9998, crop 64") in card           # the batch and the decay the run recorded
    assert "- note: selected on validation" in card and "step 77: val_iou 0.5000" in card
    assert "Scenes (data/synth2, test split): sample_2000000.npz; k = 3 samples; T1 = default; free space off." in card
    assert "- hGCA coarse (planner): 12.5 s per completion" in card
    assert "The GCA row is not like-for-like." in card
    assert "eval_test.png" not in card                                   # no rendering beside the table: no link
    (tmp_path / "eval_test.png").write_bytes(b"\x89PNG")
    assert "![eval_test: the first scene](eval_test.png)" in write_model_card(tmp_path).read_text()
    assert "fine.pt" not in card.split("Card written")[1].split("## Evaluation")[0]   # only the files present
    # the intro's dataset lists come from the files' metadata, not from typed text
    assert "Trained on it last: `coarse.pt` (each warm-started" in card
    assert "one Waymo-like" in card and "5 scans per sample. Trained on it last: none of the files here." in card
    assert "a further input: `coarse.pt`." in card
    assert "low halls). Validation stays on synth2's val split. Trained on it last: none of the files here." in card


def test_card_lists_weights_trained_on_synth2_and_synth3_under_both(tmp_path):
    meta = {"stage": "coarse", "data": "/work/data/synth2 + /work/data/synth3", "steps": 1, "sessions": []}
    save_weights(tmp_path / "coarse.pt", GCAKernel(GCAConfig(channels=(8, 8, 16, 16, 16))), meta)
    card = write_model_card(tmp_path).read_text()
    assert "Validation stays on synth2's val split. Trained on it last: `coarse.pt`." in card
    assert "Trained on it last: none of the files here (each warm-started" in card     # not under synth2 alone


def test_card_says_a_blend_is_one_and_lists_both_trainings(tmp_path):
    from hgca_core.models.weights import save_file
    from hgca_core.training.export import blend_files

    ses = {"ended": "2026-11-23 11:00:00", "steps": 9, "wall_s": 3.0, "device": "cpu", "threads": 2,
           "world_size": 1, "precision": "fp32"}
    cfg = GCAConfig(channels=(8, 8, 16, 16, 16))
    a = save_weights(tmp_path / "a.pt", GCAKernel(cfg), {"stage": "coarse", "data": "d/synth2", "steps": 5,
                                                          "sessions": [{**ses, "steps": 5}]})
    b = save_weights(tmp_path / "b.pt", GCAKernel(cfg), {"stage": "coarse", "data": "d/synth7", "steps": 9,
                                                          "train_wall_s": 3.0, "sessions": [ses]})
    cards = tmp_path / "card"
    cards.mkdir()
    save_file(blend_files(a, b, 0.25), cards / "coarse.pt")
    card = write_model_card(cards).read_text()
    assert "- steps: 5," in card and "  - session ended 2026-11-23 11:00:00: 5 steps in 3.0 s" in card
    assert "t = 0.25 (`hgca_core.training.export.blend_files`, WiSE-FT), a = `a.pt` (sha256 " in card
    assert ", the training above, b = `b.pt` (sha256 " in card
    assert "9 steps, 3.0 s of step wall time on d/synth7 over 1 session(s)" in card
    assert "  - session ended 2026-11-23 11:00:00: 9 steps in 3.0 s" in card


def test_card_names_every_session_of_a_blend_of_a_blend_and_of_a_warm_start(tmp_path):
    """Blend a blend with a run started from it: the card lists the sessions and devices of all four trainings
    (the inner blend's second source and the run's start included)."""
    from hgca_core.models.weights import load_file, save_file
    from hgca_core.training.export import blend_files, lineage

    def ses(day, steps, device="cpu", name=None):
        return {"ended": f"2026-11-{day} 11:00:00", "steps": steps, "wall_s": 1.0, "device": device,
                "threads": 2, "world_size": 1, "precision": "bf16", **({"device_name": name} if name else {})}

    cfg = GCAConfig(channels=(8, 8, 16, 16, 16))
    x = save_weights(tmp_path / "x.pt", GCAKernel(cfg), {"stage": "coarse", "data": "d/x", "steps": 11,
                                                          "sessions": [ses(10, 11)]})
    y = save_weights(tmp_path / "y.pt", GCAKernel(cfg), {"stage": "coarse", "data": "d/y", "steps": 12,
                                                          "sessions": [ses(11, 12)]})
    save_file(blend_files(x, y, 0.5), tmp_path / "we.pt")
    z = save_weights(tmp_path / "z.pt", GCAKernel(cfg), {   # a run started from the blend, on a GPU
        "stage": "coarse", "data": "d/z", "steps": 13, "sessions": [ses(12, 13, "cuda", "NVIDIA H200")],
        "init": lineage(tmp_path / "we.pt", load_file(tmp_path / "we.pt")["meta"])})
    cards = tmp_path / "card"
    cards.mkdir()
    save_file(blend_files(tmp_path / "we.pt", z, 0.3), cards / "coarse.pt")
    card = write_model_card(cards).read_text()
    for steps, day in ((11, 10), (12, 11), (13, 12)):
        assert f"session ended 2026-11-{day} 11:00:00: {steps} steps" in card, steps
    assert "device cuda (NVIDIA H200)" in card
    assert "a = `we.pt`" in card and "b = `z.pt`" in card and "b = `y.pt`" in card and "started from `we.pt`" in card


def test_a_results_page_that_is_not_an_eval_record_goes_on_the_card_as_it_is(tmp_path):
    # benchmarks/sim_to_real.py writes eval_sim_to_real.{md,json,png} beside the weights: its JSON holds no scenes
    # or rows, so the card shows the page and its rendering and reads nothing else from it
    (tmp_path / "eval_sim_to_real.md").write_text("# Sim-to-real\n\n| target | measured | met |\n")
    (tmp_path / "eval_sim_to_real.json").write_text(json.dumps({"targets": [["IoU >= 75 %", "64.02 %", False]]}))
    (tmp_path / "eval_sim_to_real.png").write_bytes(b"\x89PNG")
    card = write_model_card(tmp_path).read_text()
    assert "## Evaluation: `eval_sim_to_real`" in card and "| target | measured | met |" in card
    assert "![eval_sim_to_real](eval_sim_to_real.png)" in card and "Scenes (" not in card
