"""Do the samples agree on what they grow where the rays saw empty? (run by hand)
`python benchmarks/sample_consensus.py [--samples 6] [--cut 2.0] [--threads 1]`.

The real-scan benchmark's height cut (`hgca eval-real`): each real input is cut `--cut` m above the ground and the
coarse stage completes it k times (seeds 0..k-1); scored as there (`metrics.realscan.cut_scores`: recall of the
cut-away real cells, and the share of the cells grown above the cut that lie where the uncut scans' rays passed).
Beside the mean over single samples, the consensus of m of the k samples (the cells at least m samples hold) is
scored for every m: if the cells grown in seen-empty space were each sample's own noise, consensus would remove
them faster than it loses recall; if the model is sure of them, every sample holds them and the share stays.
Writes benchmarks/results/sample_consensus.{md,json,png}.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]

from hgca_core.commands.eval_real import DEFAULT_REAL, default_items  # noqa: E402
from hgca_core.geometry.freespace import confident, observed_empty  # noqa: E402
from hgca_core.geometry.keys import pack, unpack  # noqa: E402
from hgca_core.geometry.region import BELOW_GROUND, Region  # noqa: E402
from hgca_core.geometry.voxel import COARSE  # noqa: E402
from hgca_core.metrics.realscan import cut_scores  # noqa: E402
from hgca_core.real_eval import height_cut, input_rays  # noqa: E402

OUT = REPO / "benchmarks" / "results" / "sample_consensus"


def consensus(cell_sets: list[np.ndarray], m: int) -> np.ndarray:
    """The cells that at least `m` of the sets hold (each set row-unique, as a completion's cells are), sorted."""
    keys, count = np.unique(pack(np.concatenate(cell_sets)), return_counts=True)
    return unpack(keys[count >= m], batched=False)


def run_input(item: dict, k: int, cut: float, weights: str | None) -> dict:
    """Single-sample and consensus scores of one real input cut `cut` m above the ground."""
    import hgca_core

    pts, origins, index = input_rays(item)
    region = Region.around(pts, sensor=origins[0])
    local = region.to_local(pts)
    inside = region.contains_local(local)
    shape = region.grid_shape(COARSE)
    empty = observed_empty(local, region.to_local(origins), index, shape)
    core = confident(empty)
    keep, cut_cells, away = height_cut(local, inside, region, cut)
    t = time.time()
    done = hgca_core.complete(pts[keep], region=region, origins=origins, samples=k, seed=0, stage="coarse",
                              origin_index=index[keep], weights=weights)
    seconds = time.time() - t
    sets = [r.coarse_cells for r in done]
    score = lambda cells: cut_scores(cells, cut_cells, away, BELOW_GROUND + cut, empty, core)  # noqa: E731
    single = [score(c) for c in sets]
    return {"k": k, "cut": cut, "cut_away_cells": len(away), "seconds": seconds,
            "single": {key: float(np.mean([s[key] for s in single])) for key in single[0]},
            "single_per_sample": single,
            "consensus": {str(m): score(consensus(sets, m)) for m in range(1, k + 1)}}


def table(result: dict) -> str:
    lines = ["| input | cells | recall (%) | grown above the cut | of them in seen-empty space (%) | in its core (%) |",
             "|---|---|---:|---:|---:|---:|"]
    for name, r in result["inputs"].items():
        rows = [("one sample (mean of k)", r["single"])] + [
            (f"in >= {m} of {r['k']} samples", s) for m, s in r["consensus"].items()]
        for label, s in rows:
            lines.append(f"| {name} | {label} | {100 * s['recall']:.1f} | {s['generated_above']:,.0f} | "
                         f"{100 * s['above_empty_share']:.1f} | {100 * s['above_core_share']:.2f} |")
    return "\n".join(lines)


def plot(result: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.5), dpi=110)
    for i, (name, r) in enumerate(result["inputs"].items()):
        colour = f"C{i}"
        ms = sorted(r["consensus"], key=int)
        x = [100 * r["consensus"][m]["recall"] for m in ms]
        y = [100 * r["consensus"][m]["above_empty_share"] for m in ms]
        ax.plot(x, y, "o-", color=colour, label=f"{name}: in >= m of {r['k']}")
        for m, xi, yi in zip(ms, x, y):
            ax.annotate(m, (xi, yi), textcoords="offset points", xytext=(4, 3), fontsize=7, color=colour)
        ax.plot(100 * r["single"]["recall"], 100 * r["single"]["above_empty_share"], "*", ms=13, color=colour,
                mec="k", label=f"{name}: one sample")
    ax.axhline(8.0, ls="--", color="0.5", lw=1)
    ax.text(ax.get_xlim()[0], 8.1, " target 8 %", fontsize=7, color="0.4", va="bottom")
    ax.set_xlabel(f"recall of the real cells cut away {result['cut']:g} m above the ground (%)")
    ax.set_ylabel("grown above the cut in seen-empty space (%)")
    ax.set_title("coarse stage on real scans: single samples and their consensus", fontsize=10)
    ax.legend(fontsize=6.5, ncol=2)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    import torch

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--samples", type=int, default=6, help="completions k per input")
    p.add_argument("--cut", type=float, default=2.0, help="cut height above the ground (m)")
    p.add_argument("--weights", default=None, help="coarse weights (default: the shipped coarse.pt)")
    p.add_argument("--real-dir", default=str(REPO / DEFAULT_REAL))
    p.add_argument("--threads", type=int, default=1, help="torch CPU threads")
    p.add_argument("--out", default=str(OUT), help="output path without suffix")
    args = p.parse_args(argv)
    if args.samples < 2:
        p.error("--samples must be 2 or more (consensus needs several samples)")
    torch.set_num_threads(args.threads)
    t0 = time.time()
    result = {"samples": args.samples, "cut": args.cut, "weights": args.weights or "shipped", "inputs": {}}
    for item in default_items(args.real_dir):
        result["inputs"][item["name"]] = run_input(item, args.samples, args.cut, args.weights)
        print(item["name"], f"{result['inputs'][item['name']]['seconds']:.0f} s", file=sys.stderr)
    result["seconds"] = time.time() - t0
    out = Path(args.out)
    out.with_suffix(".json").write_text(json.dumps(result, indent=1))
    plot(result, out.with_suffix(".png"))
    md = table(result)
    out.with_suffix(".md").write_text(md + "\n")
    print(md)
    return 0


if __name__ == "__main__":
    sys.exit(main())
