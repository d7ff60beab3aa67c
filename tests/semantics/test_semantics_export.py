"""The exported head is the run's selection on val: the weight average kept at the best validation mIoU (best.pt),
not whatever the last step left, and its record says which step and score it was selected at."""
from __future__ import annotations

import torch

from hgca_core.models.weights import load_file, load_semantics, save_file
from hgca_core.training.semantics import SemanticsLoss, export_semantics
from hgca_core.models.semantics import SemanticsConfig


def _checkpoint(path, seed: int, step: int, best: dict | None) -> dict:
    """A semantics training checkpoint (as the trainer writes it) whose weight average is drawn from `seed`."""
    cfg = SemanticsConfig(channels=(8, 8, 16))
    torch.manual_seed(seed)
    module = SemanticsLoss(cfg)
    state = {"step": step, "elapsed_s": 1.0, "history": [], "sessions": [], "seed": 0,
             **({"best_val": best} if best else {})}
    save_file({"model": module.state_dict(), "ema": {"model": module.state_dict()}, "state": state,
               "config": cfg.to_dict(), "task": "semantics"}, path)
    return {k: v.clone() for k, v in module.model.state_dict().items()}


def _same(head, weights: dict) -> bool:
    got = head.state_dict()
    return all(torch.allclose(got[k].float(), v.float(), atol=1e-2) for k, v in weights.items()
               if v.is_floating_point())


def test_export_takes_the_val_selected_average_and_says_so(tmp_path):
    last = _checkpoint(tmp_path / "ckpt.pt", seed=1, step=900, best=None)
    best = _checkpoint(tmp_path / "best.pt", seed=2, step=600, best={"key": "val_iou", "value": 0.7, "step": 600})
    out = export_semantics(tmp_path / "ckpt.pt", tmp_path / "semantics.pt")
    head = load_semantics(out)
    assert _same(head, best) and not _same(head, last)
    meta = load_file(out)["meta"]
    assert meta["steps"] == 600 and meta["selected"]["step"] == 600 and meta["selected"]["value"] == 0.7
    assert any("900 steps" in n and "step 600" in n for n in meta["notes"])


def test_export_without_a_val_selection_takes_the_checkpoint(tmp_path):
    last = _checkpoint(tmp_path / "ckpt.pt", seed=1, step=900, best=None)
    head = load_semantics(export_semantics(tmp_path / "ckpt.pt", tmp_path / "semantics.pt"))
    assert _same(head, last)


def test_a_head_can_start_from_shipped_weights(tmp_path):
    """`hgca train --recipe semantics --set init_from=semantics.pt` fine-tunes a head (e.g. after its targets moved):
    the recipe takes init_from, the new head starts with the file's tensors, and free_space stays refused."""
    import pytest

    from hgca_core.errors import InputError
    from hgca_core.models.semantics import SemanticHead
    from hgca_core.training.export import load_into, save_weights
    from hgca_core.training.recipes import parse_sets, resolve

    cfg = SemanticsConfig(channels=(8, 8, 16))
    torch.manual_seed(3)
    source = save_weights(tmp_path / "head.pt", SemanticHead(cfg))
    torch.manual_seed(4)
    head = SemanticHead(cfg)
    assert not _same(head, load_semantics(source).state_dict())
    load_into(head, source)
    assert _same(head, load_semantics(source).state_dict())
    assert resolve("semantics", parse_sets([f"init_from={source}"])).init_from == str(source)
    with pytest.raises(InputError, match="free_space is not for the semantic head"):
        resolve("semantics", parse_sets(["free_space=true"]))
