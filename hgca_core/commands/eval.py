"""`hgca eval --split test`: the paper's Table 1 for our synthetic data, baselines and models in one table."""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

METHODS = ("input", "poisson", "gca", "hgca")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--data", default="data/synth", help="dataset folder (hgca synth --split test)")
    p.add_argument("--split", default="test", choices=("val", "test"))
    p.add_argument("--stage", default="coarse", choices=("coarse",), help="which hGCA output to score")
    p.add_argument("--count", type=int, default=None, help="evaluate only the first N samples")
    p.add_argument("--samples", type=int, default=3, help="completions k per input (min/avg/TMD)")
    p.add_argument("--methods", default=",".join(METHODS), help=f"comma list of {', '.join(METHODS)}")
    p.add_argument("--t1", type=int, default=None, help="coarse steps (default from the weights)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default=None, help="write the rows as JSON and the table as .md next to it")


def run(args: argparse.Namespace) -> int:
    import numpy as np
    import torch
    from tqdm import tqdm

    from hgca_core.errors import InputError
    from hgca_core.geometry import coords as cs
    from hgca_core.geometry.voxel import COARSE, FINE
    from hgca_core.meshing import voxel_mesh
    from hgca_core.metrics.baselines import input_baseline, poisson_baseline
    from hgca_core.metrics.evaluate import aggregate, evaluate_sample, format_table
    from hgca_core.models.checkpoint import load_coarse
    from hgca_core.models.gca import sample as gca_sample
    from hgca_core.synth.dataset import load_sample
    from hgca_core.training.coarse import weights_path
    from hgca_core.training.data import coarse_pair, split_files

    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    unknown = set(methods) - set(METHODS)
    if unknown:
        raise InputError(f"unknown methods {sorted(unknown)}; choose from {', '.join(METHODS)}")
    files = split_files(args.data, args.split)[: args.count]
    models = {m: load_coarse(str(weights_path(m == "hgca")))[0] for m in methods if m in ("gca", "hgca")}
    results: dict[str, list[dict]] = {m: [] for m in methods}
    timings: dict[str, list[float]] = {m: [] for m in methods}
    for path in tqdm(files, desc=f"eval {args.split}", unit="scene"):
        sample = load_sample(path)
        pts = np.asarray(sample["input_points"], dtype=np.float64)
        s0, _, grid = coarse_pair(path)
        for m in methods:
            t0 = time.time()
            if m == "input":
                cells, mesh = input_baseline(pts)
                res = evaluate_sample(sample, [mesh], [cells])
            elif m == "poisson":
                res = evaluate_sample(sample, [poisson_baseline(pts, np.asarray(sample["input_origins"]))])
            else:
                model = models[m]
                steps = args.t1 or model.cfg.steps
                occ = [gca_sample(model, cs.with_batch(torch.from_numpy(s0)), grid, steps,
                                  torch.Generator().manual_seed(args.seed + i))[:, 1:].numpy()
                       for i in range(args.samples)]
                meshes = [voxel_mesh(o, COARSE, lower_corner=-FINE / 2) for o in occ]
                res = evaluate_sample(sample, meshes, occ)
            timings[m].append(time.time() - t0)
            results[m].append(res)
    names = {"input": ("input", "20cm^3 points"), "poisson": ("Poisson (Open3D)", "mesh"),
             "gca": ("GCA (no planner)", "20cm^3"), "hgca": ("hGCA coarse (planner)", "20cm^3")}
    rows = {names[m][0]: {**aggregate(results[m]), "representation": names[m][1],
                          "seconds_per_scene": float(np.mean(timings[m]))} for m in methods}
    table = format_table(rows)
    print(table)
    for name, r in rows.items():
        print(f"{name}: {r['seconds_per_scene']:.1f} s per scene")
    if args.out:
        out = Path(args.out)
        out.write_text(json.dumps({"split": args.split, "files": [p.name for p in files], "rows": rows,
                                   "samples": args.samples, "t1": args.t1}, indent=1))
        out.with_suffix(".md").write_text(table + "\n")
        if out.resolve().parent == weights_path(True).parent:  # results beside the weights go on the card
            from hgca_core.training.card import write_model_card

            write_model_card()
    return 0
