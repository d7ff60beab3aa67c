"""Where the coarse stage's IoU is lost: recall and false cells per object class and per height band.

    python benchmarks/coarse_errors.py [--data data/synth] [--split test] [--weights W ...] [--samples 1]

For each scene of the split and each weights file, one completion per seed (as `hgca eval` samples them) is
compared with the ground truth's 20 cm cells inside the visible mask (the IoU of `hgca eval`). Every visible
ground-truth cell gets the class of the surface samples in it; a false cell gets the class of the nearest
ground-truth cell. For each class and each height band the table gives the recall, the false cells, and the IoU the
completion would reach if that part alone were perfect (its missed cells found, its false cells removed): the
share of the gap each part accounts for. Writes benchmarks/results/coarse_errors.{json,md}.
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

BANDS = ((-1.0, 0.5, "ground, < 0.5 m"), (0.5, 3.0, "0.5-3 m (the scanner's reach)"), (3.0, 5.0, "3-5 m"),
         (5.0, 99.0, "> 5 m"))


def cell_labels(sample: dict, cells: np.ndarray) -> np.ndarray:
    """Class of each 20 cm cell: of the stored surface samples in it, else of the nearest sample."""
    from scipy.spatial import cKDTree

    from hgca_core.geometry.voxel import COARSE, point_cells

    pts = np.asarray(sample["gt_surface"], dtype=np.float64)
    lab = np.asarray(sample["gt_surface_label"])
    centres = point_cells(pts, COARSE) + 0.5
    return lab[cKDTree(centres).query(cells + 0.5, workers=-1)[1]]


def part_stats(hit_gt: np.ndarray, true_pred: np.ndarray, groups_gt: np.ndarray, groups_pred: np.ndarray,
               names: list[str]) -> list[dict]:
    """Counts per group of ground-truth cells (`groups_gt`) and of predicted cells (`groups_pred`), given which
    ground-truth cells the completion found (`hit_gt`) and which of its cells are true (`true_pred`)."""
    tp, fp, fn = int(hit_gt.sum()), int((~true_pred).sum()), int((~hit_gt).sum())
    rows = []
    for g, name in enumerate(names):
        n_gt = int((groups_gt == g).sum())
        fn_g = int(((groups_gt == g) & ~hit_gt).sum())
        fp_g = int(((groups_pred == g) & ~true_pred).sum())
        rows.append({"part": name, "gt_cells": n_gt, "found": n_gt - fn_g, "false_cells": fp_g,
                     "iou_if_perfect": (tp + fn_g) / max(tp + fn_g + fp - fp_g + fn - fn_g, 1)})
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default="data/synth")
    ap.add_argument("--split", default="test", choices=("val", "test"))
    ap.add_argument("--weights", nargs="+", default=None, help="coarse weights (default: both shipped models)")
    ap.add_argument("--samples", type=int, default=1, help="completions per scene (seeds 0..k-1)")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--out", default="benchmarks/results/coarse_errors")
    args = ap.parse_args()

    import torch
    from scipy.spatial import cKDTree

    from hgca_core.geometry import coords as cs
    from hgca_core.geometry.voxel import COARSE, cell_centers
    from hgca_core.metrics.iou import iou, pack_cells
    from hgca_core.models.weights import load_coarse, shipped
    from hgca_core.models.gca import sample as gca_sample
    from hgca_core.nn.conv import gemm_precision, resolve_precision
    from hgca_core.synth.dataset import load_sample
    from hgca_core.training.data import coarse_pair, split_files

    torch.set_num_threads(args.threads)
    weights = args.weights or [str(shipped("coarse")), str(shipped("coarse-noplanner"))]
    files = split_files(args.data, args.split)
    stems = [Path(w).stem for w in weights]
    names = stems if len(set(stems)) == len(stems) else weights   # two files of one name: tell them by path
    methods = {"input": None, **{n: load_coarse(w)[0] for n, w in zip(names, weights)}}
    acc: dict[str, dict[str, dict]] = {m: {} for m in methods}
    ious: dict[str, list[float]] = {m: [] for m in methods}
    labels: list[str] = []
    edges = [b[1] for b in BANDS[:-1]]
    for path in files:
        sample = load_sample(path)
        labels = json.loads(str(sample["meta"]))["labels"]
        s0, gt, grid = coarse_pair(path)
        vis = pack_cells(np.asarray(sample["visible20"], dtype=np.int64))
        gt = gt[np.isin(pack_cells(gt), vis)]
        gt_class = cell_labels(sample, gt)
        ground = float(sample["ground_z"])
        band = np.digitize(cell_centers(gt, COARSE)[:, 2] - ground, edges)
        tree = cKDTree(gt)
        for name, model in methods.items():
            seeds = [None] if model is None else range(args.samples)
            for seed in seeds:
                if model is None:
                    pred = s0
                else:
                    t0 = time.time()
                    with gemm_precision(resolve_precision("auto")):
                        pred = gca_sample(model, cs.with_batch(torch.from_numpy(s0)), grid, model.cfg.steps,
                                          torch.Generator().manual_seed(seed))[:, 1:].numpy()
                    print(f"{path.name} {name} seed {seed}: {time.time() - t0:.1f} s", flush=True)
                pred = pred[np.isin(pack_cells(pred), vis)]
                ious[name].append(iou(pred, gt))
                near = tree.query(pred, workers=-1)[1]
                pred_band = np.digitize(cell_centers(pred, COARSE)[:, 2] - ground, edges)
                hit_gt = np.isin(pack_cells(gt), pack_cells(pred))
                true_pred = np.isin(pack_cells(pred), pack_cells(gt))
                parts = (part_stats(hit_gt, true_pred, gt_class, gt_class[near], labels)
                         + part_stats(hit_gt, true_pred, band, pred_band, [b[2] for b in BANDS]))
                for r in parts:
                    a = acc[name].setdefault(r["part"], {"gt_cells": 0, "found": 0, "false_cells": 0, "gain": []})
                    a["gt_cells"] += r["gt_cells"]
                    a["found"] += r["found"]
                    a["false_cells"] += r["false_cells"]
                    a["gain"].append(r["iou_if_perfect"] - ious[name][-1])
    per = {m: len(ious[m]) / len(files) for m in methods}    # completions per scene: counts are per completion
    rows = {m: {"iou": float(np.mean(ious[m])),
                "parts": {p: {"gt_cells": round(a["gt_cells"] / per[m]), "recall": a["found"] / max(a["gt_cells"], 1),
                              "false_cells": round(a["false_cells"] / per[m]),
                              "iou_gain_if_perfect": float(np.mean(a["gain"]))}
                          for p, a in acc[m].items() if a["gt_cells"] or a["false_cells"]}}
            for m in methods}
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".json").write_text(json.dumps({"split": args.split, "files": [p.name for p in files],
                                                    "samples": args.samples, "rows": rows}, indent=1))
    lines = [f"# Where the coarse IoU is lost ({args.split} split, {len(files)} scenes, "
             f"{args.samples} completion(s) each)", ""]
    for m, r in rows.items():
        lines += [f"## {m}: IoU {100 * r['iou']:.2f} %", "",
                  "| part | visible GT cells | recall (%) | false cells (per completion) | IoU gain if perfect (points) |",
                  "|---|---:|---:|---:|---:|"]
        lines += [f"| {p} | {a['gt_cells']} | {100 * a['recall']:.1f} | {a['false_cells']} | "
                  f"{100 * a['iou_gain_if_perfect']:.2f} |" for p, a in r["parts"].items()]
        lines.append("")
    out.with_suffix(".md").write_text("\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
