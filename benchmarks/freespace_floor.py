"""Ground truth against the observed free space (run by hand): `python benchmarks/freespace_floor.py [options]`.

The real-scan benchmark counts a generated cell in space the input's rays crossed as a certain error. This measures
what that count says of a perfect completion: per synthetic val scene, the share of the ground-truth 20 cm cells the
input does not hold (what a perfect model would generate) that lie in the observed free space
(`geometry.freespace.observed_empty`) and in its core (`geometry.freespace.confident`, the free space less its
one-cell rim), for the scene's own scans and for its first sweep alone (the real benchmark's single sweeps).
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

from hgca_core.geometry.freespace import confident, dense, observed_empty  # noqa: E402
from hgca_core.geometry.region import GROUND_STEP, Region  # noqa: E402
from hgca_core.geometry.voxel import COARSE, cell_centers, voxelize  # noqa: E402
from hgca_core.synth.dataset import draw_recipe, load_sample  # noqa: E402

OUT = REPO / "benchmarks" / "results" / "freespace_floor"


def ground_at(sample: dict, xy: np.ndarray) -> np.ndarray:
    """Region-frame ground height at region x, y (the sample's ground grid, nearest node)."""
    g = np.asarray(sample["ground_height"], np.float64)
    ij = np.clip(np.round(np.asarray(xy) / GROUND_STEP).astype(int), 0, np.array(g.shape) - 1)
    return g[ij[:, 0], ij[:, 1]]


def floor(sample: dict, single: bool, cut: float | None = None) -> dict:
    """Shares of the ground truth's unseen cells in the free space and its core, for all scans or the first.
    With `cut`: the input cut `cut` m above the ground and the unseen truth above the cut, against the free space
    of the whole input (as the real benchmark's height cuts)."""
    region = Region.from_tuple(sample["region"])
    shape = region.grid_shape(COARSE)
    pts = np.asarray(sample["input_points"], np.float64)
    idx = np.asarray(sample["input_scan_index"], np.int64)
    if single:
        pts, idx = pts[idx == 0], idx[idx == 0]
    free = observed_empty(pts, np.asarray(sample["input_origins"], np.float64), idx, shape)
    core = confident(free)
    truth = dense(np.asarray(sample["gt_occ20"], np.int64), shape)
    if cut is not None:
        pts = pts[pts[:, 2] < ground_at(sample, pts[:, :2]) + cut]
    unseen = truth & ~dense(voxelize(pts, COARSE, region.size), shape)
    if cut is not None:
        c = np.argwhere(unseen)
        centre = cell_centers(c, COARSE)
        low = c[centre[:, 2] < ground_at(sample, centre[:, :2]) + cut]
        unseen[low[:, 0], low[:, 1], low[:, 2]] = False
    n = int(unseen.sum())
    return {"unseen_truth": n, "free_cells": int(free.sum()), "core_cells": int(core.sum()),
            "in_free": int((unseen & free).sum()), "in_core": int((unseen & core).sum()),
            "in_free_pct": 100 * float((unseen & free).sum()) / max(n, 1),
            "in_core_pct": 100 * float((unseen & core).sum()) / max(n, 1)}


def section(sample: dict, png: Path) -> None:
    """x-z section through the first sweep's sensor: free space, its core, the ground truth, and truth in free."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    region = Region.from_tuple(sample["region"])
    shape = region.grid_shape(COARSE)
    idx = np.asarray(sample["input_scan_index"], np.int64)
    pts = np.asarray(sample["input_points"], np.float64)[idx == 0]
    org = np.asarray(sample["input_origins"], np.float64)
    free = observed_empty(pts, org, idx[idx == 0], shape)
    core = confident(free)
    truth = dense(np.asarray(sample["gt_occ20"], np.int64), shape)
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
    p.add_argument("--data", default="data/synth2", help="dataset folder with a val split (hgca synth)")
    p.add_argument("--count", type=int, default=16, help="val scenes")
    p.add_argument("--out", default=str(OUT))
    args = p.parse_args()
    files = sorted((Path(args.data) / "val").glob("sample_*.npz"))[: args.count]
    if not files:
        print(f"no val samples under {args.data}/val (make them with `hgca synth --split val`)", file=sys.stderr)
        return 2
    t0 = time.time()
    rows = []
    for f in files:
        seed = int(f.stem.split("_")[1])
        s = load_sample(f)
        profile, scans = draw_recipe(seed)
        rows.append({"scene": f.name, "profile": profile, "scans": int(len(s["input_origins"])),
                     "all": floor(s, False), "first": floor(s, True), "first_cut2": floor(s, True, 2.0)})
        print(f.name, profile, rows[-1]["first"]["in_free_pct"], rows[-1]["first"]["in_core_pct"], flush=True)
    out = Path(args.out)
    section(load_sample(files[0]), out.with_suffix(".png"))
    lines = ["# Ground truth in the observed free space", "",
             f"Synthetic val scenes of `{args.data}` ({len(files)}): the ground-truth 20 cm cells that the input does "
             "not hold (what a perfect completion would generate), and the share of them that the real-scan "
             "benchmark would count as errors: in the observed free space (rays walked to 0.4 m short of their "
             "hit, the 26 cells around every hit excluded), and in its core (free cells whose six face neighbours "
             "are free too). First sweep: the scene's first scan alone, as the real benchmark's single sweeps. Above a 2 m "
             "cut: the first sweep cut 2 m above the ground, the truth it misses above the cut, against the whole "
             "sweep's free space (as the real benchmark's height cuts).", "",
             "| scene | profile | scans | unseen truth cells | in free, all scans (%) | in core, all scans (%) "
             "| in free, first sweep (%) | in core, first sweep (%) | above a 2 m cut: in free (%) | in core (%) |",
             "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        a, b, c = r["all"], r["first"], r["first_cut2"]
        lines.append(f"| {r['scene']} | {r['profile']} | {r['scans']} | {a['unseen_truth']:,} | {a['in_free_pct']:.2f} "
                     f"| {a['in_core_pct']:.2f} | {b['in_free_pct']:.2f} | {b['in_core_pct']:.2f} "
                     f"| {c['in_free_pct']:.2f} | {c['in_core_pct']:.2f} |")
    lines += ["", "Per profile, first sweep (mean [min-max] over its scenes):", "",
              "| profile | scenes | in free (%) | in core (%) | above a 2 m cut: in free (%) | in core (%) |",
              "|---|---:|---:|---:|---:|---:|"]

    def spread(group: list[dict], case: str, key: str) -> str:
        v = np.array([r[case][key] for r in group])
        return f"{v.mean():.2f} [{v.min():.2f}-{v.max():.2f}]"

    groups = [(prof, [r for r in rows if r["profile"] == prof]) for prof in sorted({r["profile"] for r in rows})]
    for prof, group in groups + [("all", rows)]:
        lines.append(f"| {prof} | {len(group)} | {spread(group, 'first', 'in_free_pct')} | "
                     f"{spread(group, 'first', 'in_core_pct')} | {spread(group, 'first_cut2', 'in_free_pct')} | "
                     f"{spread(group, 'first_cut2', 'in_core_pct')} |")
    lines += ["", f"Section: `{out.with_suffix('.png').name}` ({files[0].name}). Run time {time.time() - t0:.0f} s."]
    out.with_suffix(".md").write_text("\n".join(lines) + "\n")
    out.with_suffix(".json").write_text(json.dumps({"data": args.data, "rows": rows}, indent=1))
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
