"""The semantics benchmark's results page (benchmarks/results/semantics.md) from its JSON record, so the page can be
rewritten from the record alone (`python benchmarks/semantics.py --markdown-only`)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

# the label-free checks' tolerances (benchmarks/semantics.py applies them, the page states them)
GROUND_TOL = 0.5      # m: road and sidewalk cells within this of the fitted ground
VERTICAL_NZ = 0.5     # |n_z| of a building cell's local surface normal at most this (60 degrees or steeper)
CAR_TOP = 3.0         # m above the fitted ground
POLE_WIDTH = 0.8      # m across (x and y) at most


def shares(timing: list[dict]) -> dict[str, float]:
    """The head's seconds as a % of the completion's, per stage: wall ("coarse") and CPU ("coarse_cpu"). Both over
    the inputs whose completion has CPU seconds (timed the way the head is; wall over every input where none has)."""
    out = {}
    for stage in ("coarse", "full"):
        rows = [t for t in timing if t.get("stage", "coarse") == stage]
        timed = [t for t in rows if t.get("completion_cpu_s") is not None]
        for key, sem, comp, sel in (("", "semantics_s", "completion_s", timed or rows),
                                    ("_cpu", "semantics_cpu_s", "completion_cpu_s", timed)):
            if sel:
                out[stage + key] = round(sum(t[sem] for t in sel) / max(sum(t[comp] for t in sel), 1e-9) * 100, 1)
    return out


def share_text(r: dict) -> str:
    """The head's time as a share of the completion's, per stage, wall and CPU."""
    sh = shares(r["timing"]) if r.get("semantics_share") else {"coarse": r.get("semantics_share_of_coarse_completion")}
    parts = []
    for stage in ("full", "coarse"):
        if sh.get(stage) is None:
            continue
        cpu = f", {sh[stage + '_cpu']:.1f} % of its CPU time" if sh.get(stage + "_cpu") is not None else ""
        parts.append(f"{sh[stage]:.1f} % of the {stage} stage's completion wall time{cpu}")
    return ("The head and the faces' labels (what `--semantics` adds) took " + "; ".join(parts)
            + " on the same inputs (over the completions timed in CPU seconds too):")


def head_text(r: dict) -> str:
    """What the head was trained on and how it was selected, from its weights' record."""
    text = (f"The head: {r.get('head_steps'):,} training steps (`hgca train --recipe semantics`, train split only) "
            f"on {r.get('head_train_scenes')} train scenes of `{r.get('head_data')}`")
    sel, val = r.get("head_selected"), r.get("head_val")
    if sel:
        text += (f"; selected on val: the weight average at the step of the best val mIoU "
                 f"({sel['value'] * 100:.1f} % on {r.get('head_val_scenes', 6)} perturbed val scenes")
        if val:
            text += ", " + ", ".join(f"{n} {val[f'val_iou_{n}'] * 100:.1f}" for n in ("road", "building", "tree")
                                     if f"val_iou_{n}" in val)
        text += ")"
    return text + "."


def markdown(r: dict) -> str:
    from hgca_core.io.classes import CLASS_NAMES

    def row(name: str, t: dict) -> str:
        vals = [("-" if t["per_class"][n] is None else f"{t['per_class'][n]:.1f}") for n in CLASS_NAMES]
        miou = "-" if not np.isfinite(t["miou"]) else f"{t['miou']:.1f}"
        return f"| {name} | **{miou}** | {' | '.join(vals)} | {t['cells']:,} |"

    head = f"| cells | mIoU | {' | '.join(CLASS_NAMES)} | scored cells |"
    lines = ["# Semantic head: classes of completed streets", "",
             "Per-class IoU (%) at 20 cm on the synthetic test split "
             f"({len(r['files'])} scenes of `{r['data']}`: {', '.join(r['files'])}). Completion rows: the shipped "
             f"coarse stage's completion (seed 0) of {len(r['completed_files'])} of them "
             f"({', '.join(r['completed_files']) or 'none'}) labelled by the head (`hgca complete --semantics`); "
             "cells are scored where the completion and the ground truth both hold them. Ground-truth rows: the head "
             "on every scene's true 20 cm state (the completion's geometry errors removed). Observed cells (the input "
             "holds them) apart from generated ones. mIoU is over the classes holding at least 1 % of the scored "
             f"cells ({', '.join(r['iou_all']['gt']['classes'])}). Measured by `python benchmarks/semantics.py` "
             f"({r['threads']} thread, {r['cpu']}, torch {r['torch']}); weights `{Path(r['weights']).name}`.", "",
             head, "|" + " --- |" * (len(CLASS_NAMES) + 3)]
    for src, label in (("completion", "completion"), ("gt", "ground-truth cells")):
        for part in ("observed", "generated"):
            lines.append(row(f"{label}, {part}", r["iou"][src][part]))
        lines.append(row(f"{label}, all", r["iou_all"][src]))
    lines += ["", "Per scene, completion mIoU (%): " + "; ".join(
        f"{s['scene']} observed {s['miou_observed']:.1f}, generated {s['miou_generated']:.1f}" for s in r["per_scene"]),
              "", "## Label-free checks on the real logs", "",
              f"Share of a class's cells that passes (cells checked). Ground fitted to the completion's own cells; "
              f"tolerances: road/sidewalk within {GROUND_TOL} m of it, building normals |n_z| <= {VERTICAL_NZ}, car "
              f"cells at most {CAR_TOP} m up, pole pieces at most {POLE_WIDTH} m across and twice as tall. The last "
              "column is the same check on the synthetic test split's ground truth (a right labelling).", ""]
    names = list(r["gt_checks"])
    lines.append("| check | " + " | ".join(x["input"] for x in r["real"]) + " | synthetic ground truth |")
    lines.append("|" + " --- |" * (len(r["real"]) + 2))
    for n in names:
        cells = []
        for x in r["real"]:
            ok, tot = x["checks"][n]
            cells.append(f"{ok / tot * 100:.0f} % ({tot:,})" if tot else "no cells")
        ok, tot = r["gt_checks"][n]
        cells.append(f"{ok / tot * 100:.0f} % ({tot:,})" if tot else "no cells")
        lines.append(f"| {n} | " + " | ".join(cells) + " |")
    lines += ["", "Class shares of the real completions' cells (%): " + "; ".join(
        f"{x['input']}: " + ", ".join(f"{k} {v:.1f}" for k, v in x["class_share"].items() if v >= 0.5)
        for x in r["real"]), "", "## Time", "",
              share_text(r), "",
              "| input | stage | cells | faces | completion wall (s) | completion CPU (s) | semantics wall (s) | "
              "semantics CPU (s) |", "|" + " --- |" * 8]
    cpu = lambda v: "-" if v is None else f"{v:.1f}"   # noqa: E731  (completions cached before CPU was recorded)
    lines += [f"| {t['scene']} | {t.get('stage', 'coarse')} | {t['cells']:,} | {t['faces']:,} | "
              f"{t['completion_s']:.1f} | {cpu(t.get('completion_cpu_s'))} | {t['semantics_s']:.2f} | "
              f"{cpu(t.get('semantics_cpu_s'))} |" for t in r["timing"]]
    weak = [n for n, v in r["iou_all"]["gt"]["per_class"].items() if v is not None and v < 50]
    lines += ["", "Wall seconds depend on what else the shared machine runs at the time; CPU seconds (user + sys of "
              "the one-thread process) less so. Each completion was timed once, when it was made and cached "
              "(`--cache`); the head is timed each time the page is scored.", "",
              head_text(r) + (f" Classes under 50 % IoU on the true cells: {', '.join(weak)}." if weak else ""), "",
              *[x for note in r.get("notes", []) for x in (note, "")],
              "![Completions coloured by class](semantics.png)", ""]
    return "\n".join(lines + placement_lines())


PLACEMENT = Path(__file__).resolve().parent / "results" / "semantics_placement.json"


def placement_lines() -> list[str]:
    """The placement comparison's section (`benchmarks/semantics_placement.py`), where its record exists."""
    import json

    if not PLACEMENT.exists():
        return []
    from semantics_placement_page import section

    return [*section(json.loads(PLACEMENT.read_text())), ""]
