"""The placement comparison's page (benchmarks/results/semantics_placement.md and its section of semantics.md) and
its rendering, from the JSON record `benchmarks/semantics_placement.py` writes."""
from __future__ import annotations

from pathlib import Path

import numpy as np

KEY_CLASSES = ("road", "building", "tree")


def _f(v, fmt: str = "{:.1f}") -> str:
    return "-" if v is None or (isinstance(v, float) and not np.isfinite(v)) else fmt.format(v)


def verdict(r: dict) -> dict:
    """The placement with the best val mIoU at the last common step, its margin over the geometry head, and the
    noise it must exceed: twice the RMS difference between two seeds of the geometry head at matching steps (no
    band, and so no winner, without the second seed)."""
    curves = {k: {h["step"]: h["val_iou"] for h in v} for k, v in r["curves"].items() if v}
    common = set.intersection(*(set(c) for c in curves.values())) if curves else set()
    if not common:
        return {}
    step = max(common)
    scores = {k: c[step] for k, c in curves.items()}
    best = max(scores, key=scores.get)
    rms = (r.get("noise") or {}).get("rms_diff")
    band = float("nan") if rms is None else 2 * rms
    how = ("no second seed ran, so no band" if rms is None else
           f"twice the RMS difference between two seeds of the geometry head ({rms:.2f})")
    margin = scores[best] - scores["geometry"]
    return {"step": step, "scores": scores, "best": best, "margin": round(margin, 1), "band": round(band, 2),
            "how": how, "wins": bool(best != "geometry" and margin > band)}


def names_of(rows: list[dict]) -> dict[str, str]:
    return {row["placement"]: row["label"] for row in rows}


def section(r: dict, level: str = "##") -> list[str]:
    """The comparison as Markdown lines (a section of semantics.md, or the whole placement page)."""
    rows, v = r["rows"], verdict(r)
    steps = sorted({h["step"] for c in r["curves"].values() for h in c})
    lines = [f"{level} Where the head sits (val split)", "",
             "The same head (sparse U-Net 16-24-32-48, one block a level, the observed flag in every input) on three "
             "inputs, the coarse and fine stages frozen (their weights unchanged, so the geometry is the same): "
             "**A** the geometry-only features of the completed cells (the shipped head); **B** the frozen coarse "
             "kernel run once on the final 20 cm state (the input's cells as x^0, free space unknown), its last "
             "decoder features (before the occupancy logit); **C** per 20 cm cell the mean latent of its 10 cm "
             "children and their share of the eight (in training the fine autoencoder's encoding of the "
             "ground-truth 10 cm cells, at inference the fine chain's latents). Each trained by its recipe "
             "(`hgca train --recipe semantics`, `semantics-coarse-features`, `semantics-fine-latents`) from "
             "scratch, seed 0, 1 thread, on the 52 train scenes of `data/sem`, with the same examples and "
             "perturbations in the same order; validated at the same steps on the same 6 perturbed val scenes "
             f"(the training's own validation, its weight average). Measured by `{r['command']}` from the run "
             "folders.", "",
             "| placement | input / cell | head parameters | steps | val mIoU | road | building | tree | "
             "best val mIoU (step) | train CPU s / step |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for row in rows:
        val, best = row.get("val") or {}, row.get("best") or {}
        lines.append(f"| {row['label']} | {row['in_channels']} | {row['parameters']:,} | {_f(val.get('step'), '{:,}')} | "
                     f"**{_f(val.get('val_iou'))}** | " + " | ".join(_f(val.get(c)) for c in KEY_CLASSES) +
                     f" | {_f(best.get('val_iou'))} ({_f(best.get('step'), '{:,}')}) | "
                     f"{_f(row.get('train_cpu_s_per_step'), '{:.2f}')} |")
    lines += ["", "Val mIoU (%) by step:", "", "| step | " + " | ".join(row["label"] for row in rows) + " |",
              "|---:|" + "---:|" * len(rows)]
    by = {row["placement"]: {h["step"]: h["val_iou"] for h in r["curves"][row["placement"]]} for row in rows}
    for s in steps:
        lines.append(f"| {s:,} | " + " | ".join(_f(by[row["placement"]].get(s)) for row in rows) + " |")
    noise = r.get("noise")
    if noise and noise.get("pairs"):
        lines += ["", f"Seed-to-seed spread: the geometry head again with seed 1 (`{noise['run']}`): "
                  + ", ".join(f"step {p['step']:,} {p['seed0']:.1f} vs {p['seed1']:.1f}" for p in noise["pairs"])
                  + f"; RMS difference {noise['rms_diff']:.2f} points."]
    t = r.get("timing") or {}
    if t.get("heads"):
        lines += ["", f"CPU each head adds to a completion of the default region ({t['scene']}: {t['cells']:,} cells "
                  f"at 20 cm, the full stage took {t['completion_cpu_s']:.1f} s of CPU; 1 thread, median of 3; the "
                  f"fine placement pools {t['fine_cells']:,} 10 cm cells): "
                  + ", ".join(f"{names_of(rows)[k]} {h['cpu_s']:.2f} s ({h['share']:.1f} %)"
                              for k, h in t["heads"].items()) + ". The issue's limit is +10 %."]
    done = [row for row in rows if row.get("completed")]
    if done:
        n = len(r["completed_scenes"])
        lines += ["", f"On completed val scenes ({n}: {', '.join(r['completed_scenes'])}; the shipped full stage, "
                  "seed 0; each head's val-best weights; cells scored where completion and truth both hold them) "
                  "and the CPU each head adds to that completion (its features and forward pass, 1 thread):", "",
                  "| placement | mIoU all | observed | generated | road | building | tree | added CPU (% of completion) |",
                  "|---|---:|---:|---:|---:|---:|---:|---:|"]
        for row in done:
            c = row["completed"]
            lines.append(f"| {row['label']} | **{_f(c['all']['miou'])}** | {_f(c['observed']['miou'])} | "
                         f"{_f(c['generated']['miou'])} | "
                         + " | ".join(_f(c["all"]["per_class"].get(k)) for k in KEY_CLASSES)
                         + f" | {row['added_cpu']['share']:.2f} |")
    if v:
        names = {row["placement"]: row["label"] for row in rows}
        lines += ["", f"At step {v['step']:,}: " + ", ".join(f"{names[k]} {s:.1f}" for k, s in v["scores"].items())
                  + f". The noise band is {v['how']}: {v['band']:.2f} points. "
                  + (f"{names[v['best']]} leads the geometry head by {v['margin']:.1f} points, more than the band."
                     if v["wins"] else
                     f"No placement beats the geometry head by more than the band (best: {names[v['best']]}, "
                     f"{v['margin']:+.1f}), so the shipped head stays.")]
    lines += ["", "![val mIoU by step per placement](semantics_placement.png)"]
    return lines


def markdown(r: dict) -> str:
    return "\n".join(section(r, "#")) + "\n"


def plot(r: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 4, figsize=(15, 3.6), sharex=True)
    labels = {row["placement"]: row["label"] for row in r["rows"]}
    for ax, key, title in zip(axes, ("val_iou", *KEY_CLASSES), ("val mIoU", *(f"val IoU {c}" for c in KEY_CLASSES))):
        for placement, curve in r["curves"].items():
            if curve:
                ax.plot([h["step"] for h in curve], [h[key] for h in curve], marker="o", label=labels[placement])
        noise = r.get("noise")
        if key == "val_iou" and noise and noise.get("pairs"):
            ax.plot([p["step"] for p in noise["pairs"]], [p["seed1"] for p in noise["pairs"]], "k:", marker=".",
                    label="A, seed 1")
        ax.set_title(title, fontsize=10)
        ax.set_xlabel("training step")
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("%")
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
