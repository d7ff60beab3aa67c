"""Ground truth against the observed free space (run by hand): `python benchmarks/freespace_floor.py [options]`.

The real-scan benchmark counts a generated cell in space the input's rays crossed as a certain error. This measures
what that count says of a perfect completion: per synthetic val scene, the share of the ground-truth 20 cm cells the
input does not hold (what a perfect model would generate) that lie in the observed free space
(`geometry.freespace.observed_empty`), in its core (`geometry.freespace.confident`, the free space less its
one-cell rim) and in its swept cells (`geometry.freespace.swept`: rays crossed at least half of the cell's 5 cm
sub-cells), for the scene's own scans and for its first sweep alone (the real benchmark's single sweeps).
Writes benchmarks/results/freespace_floor.{md,json} and a section through one scene (.png).
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]

from hgca_core.geometry.freespace import HALF, confident, dense, observed_empty, swept  # noqa: E402
from hgca_core.geometry.region import Region, ground_at  # noqa: E402
from hgca_core.geometry.voxel import COARSE, cell_centers, voxelize  # noqa: E402
from hgca_core.synth.dataset import draw_recipe, load_sample, sample_seed  # noqa: E402
from hgca_core.synth.rays import input_rays  # noqa: E402

OUT = REPO / "benchmarks" / "results" / "freespace_floor"


def grids(sample: dict, single: bool) -> dict:
    """The scene's region, its input (all scans or the first) inside the region, the free space of that input's rays
    (from format 3 also those to hits beyond the region, as `hgca complete` walks a real scan) and its core, and the
    truth."""
    region = Region.from_tuple(sample["region"])
    shape = region.grid_shape(COARSE)
    pts = np.asarray(sample["input_points"], np.float64)
    idx = np.asarray(sample["input_scan_index"], np.int64)
    if single:
        pts = pts[idx == 0]
    rays, ray_scan = input_rays(sample, 0 if single else None)
    origins = np.asarray(sample["input_origins"], np.float64)
    free = observed_empty(rays, origins, ray_scan, shape)
    return {"region": region, "points": pts, "free": free, "core": confident(free),
            "swept": swept(rays, origins, ray_scan, shape) >= HALF,
            "truth": dense(np.asarray(sample["gt_occ20"], np.int64), shape)}


def under_cut(p: np.ndarray, ground_height, cut: float) -> np.ndarray:
    """Per region-frame point (a hit, a cell centre): below `cut` m above the scene's ground (`ground_height`, a
    sample's ground), as the real benchmark cuts its inputs."""
    return p[:, 2] < ground_at(ground_height, p[:, :2]) + cut


def clear_below(grid: np.ndarray, ground_height, cut: float) -> None:
    """Unset, in a dense 20 cm grid, the cells whose centre lies under the cut (`under_cut`): what is left lies
    above it."""
    c = np.argwhere(grid)
    low = c[under_cut(cell_centers(c, COARSE), ground_height, cut)]
    grid[low[:, 0], low[:, 1], low[:, 2]] = False


def floor(sample: dict, g: dict, cut: float | None = None) -> dict:
    """Shares of the truth's cells that the input `g` misses in its free space and its core. With `cut`: the input
    cut `cut` m above the ground and the truth it misses above the cut, against the free space of the whole input
    `g` (as the real benchmark's height cuts)."""
    region, pts, free, core, half = g["region"], g["points"], g["free"], g["core"], g["swept"]
    shape = free.shape
    if cut is not None:
        pts = pts[under_cut(pts, sample["ground_height"], cut)]
    unseen = g["truth"] & ~dense(voxelize(pts, COARSE, region.size), shape)
    if cut is not None:
        clear_below(unseen, sample["ground_height"], cut)
    n = int(unseen.sum())
    out = {"unseen_truth": n, "free_cells": int(free.sum()), "core_cells": int(core.sum()),
           "swept_cells": int(half.sum())}
    for name, grid in (("free", free), ("core", core), ("swept", half)):
        out[f"in_{name}"] = int((unseen & grid).sum())
        out[f"in_{name}_pct"] = 100 * out[f"in_{name}"] / max(n, 1)
    return out


def section(sample: dict, g: dict, png: Path) -> None:
    """x-z section through the first sweep's sensor (`g`: its grids): free space, its core, the ground truth, and
    truth in free."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    free, core, truth = g["free"], g["core"], g["truth"]
    shape = free.shape
    org = np.asarray(sample["input_origins"], np.float64)
    y = int(np.clip(np.floor((org[0, 1] + 0.05) / COARSE), 0, shape[1] - 1))
    img = np.ones((*free[:, y].shape, 3))
    img[free[:, y]] = (0.75, 0.85, 1.0)
    img[core[:, y]] = (0.35, 0.55, 0.95)
    img[truth[:, y]] = (0.1, 0.1, 0.1)
    img[truth[:, y] & free[:, y]] = (0.9, 0.1, 0.1)
    img[truth[:, y] & core[:, y]] = (1.0, 0.8, 0.0)
    fig, ax = plt.subplots(figsize=(12, 3.6))
    ax.imshow(img.transpose(1, 0, 2), origin="lower", extent=(0, shape[0] * COARSE, 0, shape[2] * COARSE),
              interpolation="nearest")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("z (m, region frame)")
    ax.set_title("section through the sensor (first sweep): light blue free space, dark blue its core, black ground "
                 "truth, red truth in the free space's rim, yellow truth in the core", fontsize=9)
    fig.tight_layout()
    fig.savefig(png, dpi=110)
    plt.close(fig)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", nargs="+", default=["data/synth2"],
                   help="dataset folders with a val split (hgca synth); their val scenes in the order given")
    p.add_argument("--count", type=int, default=16, help="val scenes")
    p.add_argument("--out", default=str(OUT), help="results stem (.md, .json, .png)")
    args = p.parse_args()
    files = [f for d in args.data for f in sorted((Path(d) / "val").glob("sample_*.npz"))][: args.count]
    if not files:
        print(f"no val samples under {' '.join(args.data)} (make them with `hgca synth --split val`)",
              file=sys.stderr)
        return 2
    t0 = time.time()
    rows = []
    out = Path(args.out)
    for f in files:
        seed = sample_seed(f)
        s = load_sample(f)
        profile, _ = draw_recipe(seed)
        first = grids(s, True)
        rows.append({"scene": f.name, "profile": profile, "scans": int(len(s["input_origins"])),
                     "all": floor(s, grids(s, False)), "first": floor(s, first), "first_cut2": floor(s, first, 2.0)})
        print(f.name, profile, *(round(rows[-1]["first"][f"in_{m}_pct"], 2) for m in ("free", "core", "swept")),
              flush=True)
        if f == files[0]:
            section(s, first, out.with_suffix(".png"))
    cases = (("all", "all scans"), ("first", "first sweep"), ("first_cut2", "above a 2 m cut"))
    measures = (("free", "in free"), ("core", "in core"), ("swept", "swept"))
    lines = ["# Ground truth in the observed free space", "",
             f"Synthetic val scenes of `{' '.join(args.data)}` ({len(files)}): the ground-truth 20 cm cells that the "
             "input does not hold (what a perfect completion would generate), and the share of them that the real-scan "
             "benchmark would count as errors: in the observed free space (every ray of the input, from sample "
             "format 3 also those to hits beyond the region, walked to 0.4 m short of their hit, the 26 cells around "
             "every hit excluded), in its core (free cells whose six face neighbours are free too), and swept (free "
             "cells whose volume the rays crossed at least half of, counted on 5 cm sub-cells). First sweep: "
             "the scene's first scan alone, as the real benchmark's single sweeps. Above a 2 m cut: the first sweep "
             "cut 2 m above the ground, the truth it misses above the cut, against the whole sweep's free space (as "
             "the real benchmark's height cuts).", "",
             "| scene | profile | scans | unseen truth cells | "
             + " | ".join(f"{c}: {m} (%)" for _, c in cases for _, m in measures) + " |",
             "|---|---|---:|---:|" + "---:|" * (len(cases) * len(measures))]
    for r in rows:
        lines.append(f"| {r['scene']} | {r['profile']} | {r['scans']} | {r['all']['unseen_truth']:,} | "
                     + " | ".join(f"{r[c]['in_' + m + '_pct']:.2f}" for c, _ in cases for m, _ in measures) + " |")
    lines += ["", "Per profile, first sweep and above its 2 m cut (mean [min-max] over its scenes):", "",
              "| profile | scenes | " + " | ".join(f"{c}: {m} (%)" for _, c in cases[1:] for _, m in measures) + " |",
              "|---|---:|" + "---:|" * (2 * len(measures))]

    def spread(group: list[dict], case: str, key: str) -> str:
        v = np.array([r[case][key] for r in group])
        return f"{v.mean():.2f} [{v.min():.2f}-{v.max():.2f}]"

    groups = [(prof, [r for r in rows if r["profile"] == prof]) for prof in sorted({r["profile"] for r in rows})]
    for prof, group in groups + [("all", rows)]:
        lines.append(f"| {prof} | {len(group)} | "
                     + " | ".join(spread(group, c, f"in_{m}_pct") for c, _ in cases[1:] for m, _ in measures) + " |")
    lines += ["", f"Section: `{out.with_suffix('.png').name}` ({files[0].name}). Run time {time.time() - t0:.0f} s."]
    out.with_suffix(".md").write_text("\n".join(lines) + "\n")
    out.with_suffix(".json").write_text(json.dumps({"data": args.data, "rows": rows}, indent=1))
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
