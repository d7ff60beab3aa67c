"""How often is a free-space "violation" really wrong? (run by hand): `python benchmarks/freespace_calibration.py`.

The real-scan benchmark scores a completion without ground truth: generated cells where the input's rays passed
count as errors. `freespace_floor.py` measures what this says of the truth itself; this measures what it says of a
model's completion, on synthetic val sweeps where the truth is known: the coarse stage completes each scene's first
sweep (the real benchmark's single sweeps), whole and cut 2 m above the ground, and every generated cell each
measure flags (in the free space, its rim, its core, its swept cells) is checked against the ground truth. A measure
whose flagged cells are mostly true geometry (porous crowns, grazed ground, thin poles) reads its floor, not the
model's errors.
Writes <out>.md and <out>.json (default benchmarks/results/freespace_calibration).
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "benchmarks"))

from freespace_floor import clear_below, grids, under_cut  # noqa: E402
from hgca_core.geometry.freespace import dense  # noqa: E402
from hgca_core.geometry.voxel import COARSE, voxelize  # noqa: E402
from hgca_core.synth.dataset import draw_recipe, sample_seed  # noqa: E402

OUT = REPO / "benchmarks" / "results" / "freespace_calibration"
MEASURES = ("free", "rim", "core", "swept")
CUT = 2.0  # m above the ground, as the real benchmark's height cut


def measures(g: dict) -> dict[str, np.ndarray]:
    """The flagging grids of one input (`freespace_floor.grids`): the free space, its rim, its core, its swept cells."""
    return {"free": g["free"], "rim": g["free"] & ~g["core"], "core": g["core"], "swept": g["swept"]}


def near_truth(truth: np.ndarray) -> np.ndarray:
    """The cells within one cell (26-neighbourhood) of a true cell."""
    return dense(np.argwhere(truth), truth.shape, dilate=1)


def classify(generated: np.ndarray, truth: np.ndarray, flags: dict[str, np.ndarray],
             near: np.ndarray | None = None) -> dict[str, dict[str, int]]:
    """Per measure (and "all"): generated cells flagged, those not in the truth, and those farther than one cell
    from it (`near`: `near_truth(truth)`, computed here when None). `generated`, `truth` and every flag grid are
    dense bool grids of one shape."""
    near = near_truth(truth) if near is None else near
    out = {}
    for name, grid in {"all": np.ones_like(generated), **flags}.items():
        m = generated & grid
        out[name] = {"cells": int(m.sum()), "wrong": int((m & ~truth).sum()), "far": int((m & ~near).sum())}
    return out


def accumulate(into: dict, rows: dict[str, dict[str, int]]) -> None:
    """Add `classify`'s counts `rows` into `into` (same layout), measure by measure."""
    for name, v in rows.items():
        acc = into.setdefault(name, {"cells": 0, "wrong": 0, "far": 0})
        for k in acc:
            acc[k] += v[k]


def scene(path: Path, models, samples: int, png: Path | None = None) -> dict:
    """Counts of one val scene's first sweep, whole and cut, summed over `samples` completions; with `png`, the
    first completion of the cut drawn there (`draw`)."""
    from hgca_core.pipeline import complete_local
    from hgca_core.synth.dataset import load_sample
    from hgca_core.synth.rays import input_rays

    s = load_sample(path)
    g = grids(s, True)
    region, shape = g["region"], g["free"].shape
    rays, _ = input_rays(s, 0)
    origin = np.asarray(s["input_origins"], np.float64)[:1]
    flags, near = measures(g), near_truth(g["truth"])
    out: dict[str, dict] = {}
    for case in ("whole", "cut"):
        pts = rays
        if case == "cut":
            pts = rays[under_cut(rays, s["ground_height"], CUT)]
        inside = np.all((pts >= 0) & (pts < region.size), axis=1)
        given = dense(voxelize(pts[inside], COARSE, region.size), shape)
        res = complete_local(pts, region, models, samples=samples, seed=0, origins=origin,
                             origin_index=np.zeros(len(pts), np.int64))
        for r in res:
            gen = dense(r.coarse_cells, shape) & ~given
            if case == "cut":
                clear_below(gen, s["ground_height"], CUT)
                if png is not None and r is res[0]:
                    draw(png, gen, g["truth"], near, g["free"], given, path.name)
            accumulate(out.setdefault(case, {}), classify(gen, g["truth"], flags, near))
    return out


def draw(png: Path, gen: np.ndarray, truth: np.ndarray, near: np.ndarray, free: np.ndarray, given: np.ndarray,
         title: str) -> None:
    """Plan view of a cut's completion, each column showing its top-most cell: the cut input black, the truth it
    misses grey, generated cells blue within one cell of the truth, yellow within one cell but in the free space,
    orange farther in space no ray saw, red farther in the free space (what the count flags). `near`:
    `near_truth(truth)`."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    layers = [(truth & ~given & ~gen, (0.8, 0.8, 0.8)), (given, (0.0, 0.0, 0.0)),
              (gen & near & ~free, (0.2, 0.45, 0.9)), (gen & near & free, (0.95, 0.8, 0.1)),
              (gen & ~near & ~free, (1.0, 0.55, 0.1)), (gen & ~near & free, (0.85, 0.05, 0.05))]
    z = np.arange(truth.shape[2])
    best = np.full(truth.shape[:2], -1)
    img = np.ones((*best.shape, 3))
    for mask, rgb in layers:   # later layers win ties: errors drawn over what they cover
        top = np.where(mask, z, -1).max(axis=2)
        win = (top >= 0) & (top >= best)
        img[win], best[win] = rgb, top[win]
    fig, ax = plt.subplots(figsize=(9, 9.6))
    ax.imshow(img.transpose(1, 0, 2), origin="lower", interpolation="nearest",
              extent=(0, best.shape[0] * COARSE, 0, best.shape[1] * COARSE))
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(f"{title}: first sweep cut {CUT:g} m up and completed, seen from above\nblack: cut input; grey: "
                 "missed truth; generated: blue within a cell of the truth, yellow the same\nin the free space, "
                 "orange farther in space no ray saw, red farther in the free space (flagged errors)", fontsize=9)
    fig.tight_layout()
    fig.savefig(png, dpi=90)
    plt.close(fig)


def table(total: dict) -> list[str]:
    lines = ["| case | measure | flagged cells | share of generated (%) | not in the truth (%) | more than one cell "
             "from the truth (%) | of the wrong cells in the free space, flagged (%) |",
             "|---|---|---:|---:|---:|---:|---:|"]
    names = {"whole": "single sweep, whole", "cut": f"single sweep, above a {CUT:g} m cut"}
    for case, rows in total.items():
        n_all, wrong_free = rows["all"]["cells"], rows["free"]["wrong"]
        for name in ("all", *MEASURES):
            r = rows[name]
            pct = lambda a, b: f"{100 * a / b:.1f}" if b else "-"  # noqa: E731
            lines.append(f"| {names[case]} | {'generated' if name == 'all' else name} | {r['cells']:,} | "
                         f"{pct(r['cells'], n_all)} | {pct(r['wrong'], r['cells'])} | {pct(r['far'], r['cells'])} | "
                         f"{'' if name == 'all' else pct(r['wrong'], wrong_free)} |")
    return lines


def by_profile(per_scene: dict[str, dict]) -> list[str]:
    """Per sensor profile (each val scene's seed draws one): the share of the growth above the cut that the free
    space flags, and the model's wrong cells in the whole sweep's free space as a share of what it generates."""
    groups: dict[str, list[dict]] = {}
    for name, rows in per_scene.items():
        groups.setdefault(draw_recipe(sample_seed(name))[0], []).append(rows)
    lines = ["| profile | scenes | above the cut: generated | flagged in the free space (%) | whole sweep: generated | "
             "wrong and in the free space (%) |", "|---|---:|---:|---:|---:|---:|"]
    for prof, group in sorted(groups.items()):
        up = sum(r["cut"]["all"]["cells"] for r in group)
        up_free = sum(r["cut"]["free"]["cells"] for r in group)
        whole = sum(r["whole"]["all"]["cells"] for r in group)
        wrong = sum(r["whole"]["free"]["wrong"] for r in group)
        lines.append(f"| {prof} | {len(group)} | {up:,} | {100 * up_free / max(up, 1):.1f} | {whole:,} | "
                     f"{100 * wrong / max(whole, 1):.2f} |")
    return lines


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", nargs="+", default=["data/synth2f"],
                   help="dataset folders with a val split (hgca synth); their val scenes in the order given")
    p.add_argument("--count", type=int, default=16, help="val scenes")
    p.add_argument("--samples", type=int, default=1, help="completions a scene (seeds 0..)")
    p.add_argument("--weights", default=None, help="coarse weights (default: the shipped coarse.pt)")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--out", default=str(OUT), help="results stem (.md, .json, .png)")
    p.add_argument("--render-profile", default="av2", help="the first scene of this sensor profile is drawn (.png)")
    args = p.parse_args(argv)
    files = [f for d in args.data for f in sorted((Path(d) / "val").glob("sample_*.npz"))][: args.count]
    if not files:
        print(f"no val samples under {' '.join(args.data)} (make them with `hgca synth --split val`)",
              file=sys.stderr)
        return 2
    import torch

    from hgca_core.pipeline import load_models

    torch.set_num_threads(args.threads)
    models = load_models("coarse", args.weights)
    t0 = time.time()
    out = Path(args.out)
    per_scene, total, drawn = {}, {}, None
    for f in files:
        png = None
        if drawn is None and draw_recipe(sample_seed(f))[0] == args.render_profile:
            png = drawn = out.with_suffix(".png")
        per_scene[f.name] = scene(f, models, args.samples, png)
        for case, rows in per_scene[f.name].items():
            accumulate(total.setdefault(case, {}), rows)
        print(f.name, flush=True)
    lines = ["# Free-space measures against the ground truth", "",
             f"`python benchmarks/freespace_calibration.py --data {' '.join(args.data)} --count {len(files)} --samples "
             f"{args.samples}{f' --weights {args.weights}' if args.weights else ''}`: the coarse stage "
             f"({args.weights or 'the shipped coarse.pt'}) completes the first sweep of {len(files)} synthetic val "
             "scenes, whole and cut, as `hgca eval-real` completes the real sweeps; each measure's flagged generated "
             "cells (generated: completion cells the input does not hold; above the cut only, for the cut) are "
             "checked against the scene's ground-truth 20 cm cells. Measures: free (the observed free space, "
             "`geometry.freespace.observed_empty`), rim (free, not core), core (free cells with six free "
             "neighbours), swept (free cells whose 5 cm sub-cells the rays crossed half or more of, "
             "`geometry.freespace.swept`). Summed over scenes and samples.", "", *table(total), "",
             "Per sensor profile:", "", *by_profile(per_scene), "",
             *([f"Drawn: `{drawn.name}` (the first {args.render_profile} scene's cut, sample 0)."] if drawn else []),
             f"Run time {time.time() - t0:.0f} s, {args.threads} thread(s)."]
    out.with_suffix(".md").write_text("\n".join(lines) + "\n")
    out.with_suffix(".json").write_text(json.dumps({"data": args.data, "weights": args.weights,
                                                    "samples": args.samples, "cut": CUT, "total": total,
                                                    "scenes": per_scene}, indent=1) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
