"""Which weights of a run `hgca train --export` ships: the run's selection on val, not its last step.

The trainer keeps `best.pt` beside `ckpt.pt`: the weight average at the run's best validation score (IoU, or CD
where a task has no IoU). Every stage's exporter reads the run through `selected_run`, so every stage ships the
average it was selected at on the val split, and its record says which step and score that was. A run from before
best.pt was kept (no best.pt, or one without a recorded score) ships its checkpoint's average, as it always did.
Why: a run's val score can peak mid-session and fall (74.3 % at 40 min, 72.7 % at 80 in one fine-tune).
"""
from __future__ import annotations

from pathlib import Path
from typing import NamedTuple

from hgca_core.models.weights import load_file
from hgca_core.training.trainer import BEST, run_record


class SelectedRun(NamedTuple):
    """The file an export reads (`ck`, as loaded), the run record to ship with it, and where it was read from."""
    ck: dict
    record: dict
    path: Path


def selected_run(ckpt_path: str | Path) -> SelectedRun:
    """The run of `ckpt_path` as an export ships it: best.pt beside it when that holds a val selection, with
    `record["selected"]` ({key, value, step, file}) and a note when the run trained on past it; else the checkpoint
    itself with its own record."""
    ckpt_path = Path(ckpt_path)
    best = ckpt_path.with_name(BEST)
    ck = load_file(best if best.is_file() else ckpt_path)
    chosen = ck["state"].get("best_val") if best.is_file() else None
    if not chosen:
        if best.is_file():
            ck = load_file(ckpt_path)
        return SelectedRun(ck, run_record(ck), ckpt_path)
    record = {**run_record(ck), "selected": {**chosen, "file": BEST}}
    last = load_file(ckpt_path)["state"] if ckpt_path.is_file() else {}
    if last.get("step", chosen["step"]) > chosen["step"]:
        value = f"{chosen['value'] * 100:.1f} %" if chosen["key"] == "val_iou" else f"{chosen['value']:.4g}"
        record["notes"] = [*record["notes"], f"the run trained {last['step']:,} steps; these are its weight "
                           f"average at step {chosen['step']:,}, its best validation {chosen['key']} ({value})"]
    return SelectedRun(ck, record, best)
