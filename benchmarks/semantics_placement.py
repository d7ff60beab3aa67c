"""Where the semantic head sits, compared on the val split: the same head (sparse U-Net 16-24-32-48) on the
geometry features, on the frozen coarse kernel's last decoder features, or on the fine stage's pooled latents.

    python benchmarks/semantics_placement.py [--complete 3]   # cache full-stage completions of val scenes first
    python benchmarks/semantics_placement.py                  # the page, from the run folders and that cache

Each placement is a training run (`hgca train --recipe semantics[-coarse-features|-fine-latents]`, 1 thread,
seed 0, validated at the same steps). From its history: the training's own validation (fixed, perturbed ground-
truth val scenes: the same cells for every placement) at matching steps; a second seed of the geometry head, where
its run folder exists, gives the seed-to-seed spread. From the cached completions (the shipped full stage, seed 0,
on the first val scenes): each head's val-best weights label the completion's 20 cm cells (scored where the
completion and the truth both hold a cell, observed apart from generated), and the CPU each head adds to the
completion (its features and its forward pass; the completion's own latents for the fine placement).
Writes benchmarks/results/semantics_placement.{md,json,png}.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
RUNS = (  # placement, run folder (relative to the repository), label
    ("geometry", "runs/semantics_geometry", "A. geometry features (shipped)"),
    ("coarse-features", "runs/semantics_coarse_features", "B. coarse U-Net features"),
    ("fine-latents", "runs/semantics_fine_latents", "C. fine latents"),
)
SECOND_SEED = "runs/semantics_geometry_s1"
KEY_CLASSES = ("road", "building", "tree")


def val_history(folder: Path) -> list[dict]:
    from hgca_core.models.weights import load_file

    f = folder / "ckpt.pt"
    return [h for h in load_file(f)["state"]["history"] if h["kind"] == "val"] if f.exists() else []


def cpu_per_step(folder: Path) -> float | None:
    """Training CPU seconds (user + sys, every session, validation included) per step, from `<run>.time`."""
    f = folder.with_name(folder.name + ".time")
    if not f.exists():
        return None
    cpu = sum(float(p[1]) + float(p[3]) for p in (line.split() for line in f.read_text().splitlines())
              if len(p) >= 4 and p[0] == "cpu_user")
    hist = val_history(folder)
    return cpu / hist[-1]["step"] if hist else None


def completions(data: Path, cache: Path, n: int) -> list[Path]:
    """Cached full-stage completions (seed 0) of the first `n` val scenes: coarse cells, the input's cells, fine
    cells and latents, the completion's CPU seconds."""
    from hgca_core.dataset.samples import load_sample, split_files
    from hgca_core.geometry.region import Region
    from hgca_core.geometry.voxel import COARSE, voxelize
    from hgca_core.pipeline import complete_local, load_models
    from hgca_core.synth.rays import input_rays

    cache.mkdir(parents=True, exist_ok=True)
    out = []
    for path in split_files(data, "val")[:n]:
        f = cache / f"{path.stem}.npz"
        if not f.exists():
            models = load_models("full")
            sample = load_sample(path)
            rays, ray_scan = input_rays(sample)
            region = Region.from_tuple(sample["region"])
            t0, c0 = time.perf_counter(), time.process_time()
            comp = complete_local(rays, region, models, stage="full", samples=1, seed=0, max_faces=0,
                                  origins=sample["input_origins"], origin_index=ray_scan)[0]
            secs, cpu = time.perf_counter() - t0, time.process_time() - c0
            np.savez(f, cells=comp.coarse_cells, s0=voxelize(rays[region.contains_local(rays)], COARSE, region.size),
                     fine_cells=comp.fine_cells, fine_latents=comp.fine_latents, grid=region.grid_shape(COARSE),
                     completion_s=secs, completion_cpu_s=cpu)
            print(f"completed {path.stem}: {cpu:.0f} s CPU", flush=True)
        out.append(f)
    return out


def label_completion(head, done: dict) -> tuple[np.ndarray, np.ndarray, float]:
    """(labels, observed flags, CPU seconds) of one head on one cached completion: its features and forward."""
    from hgca_core.models.semantics import coarse_features, fine_features, observed_mask, predict
    from hgca_core.models.weights import load_coarse

    kernel = load_coarse()[0] if head.cfg.placement == "coarse-features" else None
    c0 = time.process_time()
    obs = observed_mask(done["cells"], done["s0"])
    extra = None
    if head.cfg.placement == "coarse-features":
        extra = coarse_features(kernel, done["cells"], done["s0"], tuple(int(v) for v in done["grid"]))
    elif head.cfg.placement == "fine-latents":
        extra = fine_features(done["cells"], done["fine_cells"], done["fine_latents"])
    labels = predict(head, done["cells"], obs, extra)[0]
    return labels, obs, time.process_time() - c0


def added_cpu(args: argparse.Namespace, heads: dict) -> dict:
    """CPU seconds each head adds to one default-region completion (the test scene cached by
    `benchmarks/semantics.py`, full stage, its CPU seconds recorded when it was made): its features and forward
    pass, median of 3 runs. The fine placement pools latents of the scene's ground-truth 10 cm cells (random
    codes: the cost does not depend on their values; the completion's own latents are not in that cache)."""
    from hgca_core.dataset.samples import load_arrays

    f = Path(args.timing_scene)
    if not f.exists():
        return {}
    with np.load(f) as z:
        done = {k: z[k] for k in z.files}
    stem = f.stem.removesuffix("_full")
    a = load_arrays(str(Path(args.timing_data) / "test" / f"{stem}.npz"), ("gt_occ10", "region"))
    done["fine_cells"] = a["gt_occ10"].astype(np.int64)
    done["fine_latents"] = np.random.default_rng(0).standard_normal((len(done["fine_cells"]), 32)).astype(np.float32)
    done["grid"] = np.array([int(round(v / 0.2)) for v in a["region"][3:6]])
    out = {"scene": f.stem, "cells": int(len(done["cells"])), "fine_cells": int(len(done["fine_cells"])),
           "completion_cpu_s": round(float(done["completion_cpu_s"]), 1), "heads": {}}
    for placement, head in heads.items():
        secs = sorted(label_completion(head, done)[2] for _ in range(3))
        out["heads"][placement] = {"cpu_s": round(secs[1], 2),
                                   "share": round(secs[1] / float(done["completion_cpu_s"]) * 100, 2)}
    return out


def measure(args: argparse.Namespace) -> dict:
    import torch

    from hgca_core.models.semantics import SemanticHead, SemanticsConfig
    from hgca_core.models.weights import load_semantics
    from hgca_core.training.semantics import scene
    from semantics import iou_table, scene_confusion

    torch.set_num_threads(args.threads)
    files = sorted(Path(args.cache).glob("sample_*.npz"))[: args.complete] if args.complete else []
    scenes = {f.stem: scene(Path(args.data) / "val" / f"{f.stem}.npz") for f in files}
    rows, curves = [], {}
    for placement, rel, label in RUNS:
        folder = ROOT / rel
        hist = val_history(folder)
        cfg = SemanticsConfig(placement=placement)
        row = {"placement": placement, "label": label, "run": rel, "in_channels": cfg.in_channels(),
               "parameters": sum(p.numel() for p in SemanticHead(cfg).parameters()),
               "train_cpu_s_per_step": None if cpu_per_step(folder) is None else round(cpu_per_step(folder), 2)}
        curves[placement] = [{"step": h["step"], "val_iou": round(h["val_iou"] * 100, 1),
                              **{c: round(h.get(f"val_iou_{c}", float("nan")) * 100, 1) for c in KEY_CLASSES}}
                             for h in hist]
        row["val"] = curves[placement][-1] if hist else None
        row["best"] = max(curves[placement], key=lambda h: h["val_iou"]) if hist else None
        best = folder / "best.pt"
        if best.exists() and files:
            head = load_semantics(best)
            k = head.cfg.classes
            conf = {p: np.zeros((k, k), np.int64) for p in ("observed", "generated")}
            added = []
            for f in files:
                with np.load(f) as z:
                    done = {key: z[key] for key in z.files}
                labels, obs, cpu = label_completion(head, done)
                for part, m in scene_confusion(done["cells"], labels, obs, scenes[f.stem]).items():
                    conf[part] += m
                added.append({"scene": f.stem, "head_cpu_s": round(cpu, 2),
                              "completion_cpu_s": round(float(done["completion_cpu_s"]), 1)})
            row["completed"] = {"observed": iou_table(conf["observed"]),
                                "generated": iou_table(conf["generated"]),
                                "all": iou_table(conf["observed"] + conf["generated"])}
            row["added_cpu"] = {"scenes": added, "share": round(sum(a["head_cpu_s"] for a in added)
                                                               / sum(a["completion_cpu_s"] for a in added) * 100, 2)}
        rows.append(row)
    heads = {}
    for placement, rel, _ in RUNS:
        best = ROOT / rel / "best.pt"
        heads[placement] = load_semantics(best) if best.exists() else SemanticHead(SemanticsConfig(placement=placement))
    timing = added_cpu(args, heads)
    second = val_history(ROOT / SECOND_SEED)
    noise = None
    if second and curves["geometry"]:
        a = {h["step"]: h["val_iou"] for h in curves["geometry"]}
        pairs = [(s, a[s], round(h["val_iou"] * 100, 1)) for s, h in ((h["step"], h) for h in second) if s in a]
        noise = {"run": SECOND_SEED, "pairs": [{"step": s, "seed0": x, "seed1": y} for s, x, y in pairs],
                 "rms_diff": round(float(np.sqrt(np.mean([(x - y) ** 2 for _, x, y in pairs]))), 2) if pairs else None}
    return {"rows": rows, "curves": curves, "noise": noise, "completed_scenes": [f.stem for f in files],
            "timing": timing,
            "machine": {"cpu": platform.processor() or platform.machine(), "cores": os.cpu_count(),
                        "threads": args.threads},
            "command": "python benchmarks/semantics_placement.py" + (f" --complete {args.complete}"
                                                                     if args.complete else "")}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", default=str(ROOT / "data" / "sem"), help="dataset with the val split the runs used")
    p.add_argument("--cache", default=str(ROOT / "runs" / "semantics_placement_val"),
                   help="folder of the cached val completions")
    p.add_argument("--complete", type=int, default=0, help="complete (or reuse) the first N val scenes and score them")
    p.add_argument("--complete-only", action="store_true", help="make the cached completions and stop")
    p.add_argument("--timing-scene", default=str(ROOT / "runs" / "semantics_bench" / "sample_2000000_full.npz"),
                   help="a cached full-stage completion of the default region (benchmarks/semantics.py --full 1)")
    p.add_argument("--timing-data", default=str(ROOT / "data" / "synth2f"), help="the dataset of that scene")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--out", default=str(ROOT / "benchmarks" / "results"))
    args = p.parse_args()
    import torch

    torch.set_num_threads(args.threads)
    if args.complete:
        completions(Path(args.data), Path(args.cache), args.complete)
    if args.complete_only:
        return
    result = measure(args)
    from common import write_page
    from semantics_placement_page import markdown, plot

    print(write_page(Path(args.out), "semantics_placement", result, markdown, plot))
    sem = Path(args.out) / "semantics.json"
    if sem.exists():   # the semantics page carries the comparison as a section of its own
        import semantics_page

        semantics_page.PLACEMENT = Path(args.out) / "semantics_placement.json"
        sem.with_suffix(".md").write_text(semantics_page.markdown(json.loads(sem.read_text())))


if __name__ == "__main__":
    main()
