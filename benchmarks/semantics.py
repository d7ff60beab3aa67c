"""The semantic head on completed streets: per-class IoU at 20 cm on the synthetic test split, label-free checks
on the real logs, renderings coloured by class, and the head's time beside the completion's.

    python benchmarks/semantics.py [--data data/synth2f] [--weights hgca_core/weights/semantics.pt] [--threads 1]

Synthetic test split (labels known): each scene is completed by the shipped coarse stage (`pipeline.complete_local`,
seed 0, as `hgca eval` runs it); the head labels the completion's 20 cm cells. A cell is scored where the completion
and the ground truth both hold it (the geometry's own errors are `hgca eval`'s), observed cells (the input holds
them) apart from generated ones. The "ground-truth cells" rows label the ground-truth state itself (with the input's
observed flags): the head without the completion's errors.

Real logs (no labels), label-free checks that a wrong labelling fails, each the share of cells of that class that
passes: road and sidewalk within GROUND_TOL of the ground fitted to the cells; building cells on vertical surfaces
(the normal of the building cells around them, within 0.6 m, at most VERTICAL_NZ from horizontal); car cells at
most CAR_TOP above the ground; pole cells in thin vertical pieces (connected pole cells at most POLE_WIDTH across
and taller than twice their width). The same checks on the synthetic ground truth show what a right labelling
scores. Writes benchmarks/results/semantics.{md,json,png}.
"""
from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

import numpy as np

from hgca_core.geometry.voxel import COARSE, cell_centers
from semantics_page import CAR_TOP, GROUND_TOL, POLE_WIDTH, VERTICAL_NZ, markdown, shares

ROOT = Path(__file__).resolve().parents[1]
REAL = (  # name, path under --real-dir, frames, calibration (as hgca eval-real reads them)
    ("av2_7fab2350", "av2/7fab2350-7eaf-3b7e-a39d-6937a4c1bede", "0:2", None),
    ("av2_adcf7d18", "av2/adcf7d18-0510-35b0-a2fa-b4cea13a6d76", None,
     "av2/7fab2350-7eaf-3b7e-a39d-6937a4c1bede/calibration/egovehicle_SE3_sensor.feather"),
    ("nuscenes", "nuscenes_lidar_top_1532402927647951.pcd.bin", None, None),
)
MIN_SHARE = 0.01      # classes with fewer cells than this share of a scene's are left out of its IoU means


def hag(cells: np.ndarray) -> np.ndarray:
    from hgca_core.models.semantics import fitted_ground

    return cell_centers(cells, COARSE)[:, 2] - fitted_ground(cells)


def checks(cells: np.ndarray, labels: np.ndarray) -> dict[str, tuple[int, int]]:
    """{check: (cells passing, cells checked)} of the label-free checks (module docstring)."""
    from scipy import ndimage
    from scipy.spatial import cKDTree

    from hgca_core.io.classes import CLASS_NAMES

    idx = {n: i for i, n in enumerate(CLASS_NAMES)}
    h = hag(cells)
    out = {}
    flat = np.isin(labels, [idx["road"], idx["sidewalk"]])
    out["road and sidewalk within 0.5 m of the ground"] = (int((np.abs(h[flat]) <= GROUND_TOL).sum()), int(flat.sum()))
    car = labels == idx["car"]
    out["car cells at most 3 m above the ground"] = (int((h[car] <= CAR_TOP).sum()), int(car.sum()))
    b = np.flatnonzero(labels == idx["building"])
    ok = 0
    if len(b):
        from scipy.sparse import coo_matrix, identity

        p = cell_centers(cells[b], COARSE)
        pairs = cKDTree(p).query_pairs(0.6, output_type="ndarray")
        adj = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(p), len(p))).tocsr()
        adj = adj + adj.T + identity(len(p), format="csr")
        n = np.asarray(adj.sum(1)).ravel()
        mean = (adj @ p) / n[:, None]
        outer = (adj @ (p[:, :, None] * p[:, None, :]).reshape(-1, 9)).reshape(-1, 3, 3) / n[:, None, None]
        cov = outer - mean[:, :, None] * mean[:, None, :]
        normal = np.linalg.eigh(cov)[1][:, :, 0]          # the direction of least spread
        ok = int(((np.abs(normal[:, 2]) <= VERTICAL_NZ) & (n >= 4)).sum())
    out["building cells on vertical surfaces"] = (int(ok), int(len(b)))
    pole = labels == idx["pole"]
    passing = 0
    if pole.any():
        c = cells[pole]
        lo = c.min(0)
        grid = np.zeros(tuple(c.max(0) - lo + 1), bool)
        grid[tuple((c - lo).T)] = True
        comp, n = ndimage.label(grid, structure=np.ones((3, 3, 3)))
        ids = comp[tuple((c - lo).T)]
        for k in range(1, n + 1):
            m = c[ids == k]
            width = (m[:, :2].max(0) - m[:, :2].min(0) + 1).max() * 0.2
            height = (m[:, 2].max() - m[:, 2].min() + 1) * 0.2
            if width <= POLE_WIDTH and height >= 2 * width:
                passing += len(m)
    out["pole cells in thin vertical pieces"] = (int(passing), int(pole.sum()))
    return out


def scene_confusion(pred_cells: np.ndarray, pred_labels: np.ndarray, observed: np.ndarray, gt: dict) -> dict:
    """{"observed", "generated"}: confusion matrices over the cells both the completion and the truth hold."""
    from hgca_core.geometry.keys import pack
    from hgca_core.training.semantics import confusion

    gk = pack(gt["cells"])
    order = np.argsort(gk)
    pk = pack(pred_cells)
    pos = np.clip(np.searchsorted(gk[order], pk), 0, len(gk) - 1)
    hit = gk[order][pos] == pk
    truth = gt["labels"][order][pos]
    return {name: confusion(pred_labels[hit & sel], truth[hit & sel])
            for name, sel in (("observed", observed), ("generated", ~observed))}


def render(cells: np.ndarray, labels: np.ndarray, ax, title: str) -> None:
    """Cells as an oblique view coloured by class (painter's order, far first)."""
    from hgca_core.io.classes import CLASS_COLORS

    p = cell_centers(cells, COARSE)
    view = np.array([-0.55, -0.75, 0.45])
    view /= np.linalg.norm(view)
    right = np.cross(view, [0, 0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, view)
    depth = p @ view
    order = np.argsort(depth)
    col = np.asarray(CLASS_COLORS, float)[labels] / 255.0
    shade = 0.75 + 0.25 * np.clip(hag(cells) / 6.0, 0, 1)
    ax.scatter(p[order] @ right, p[order] @ up, c=col[order] * shade[order, None], s=1.2, marker="s", linewidths=0)
    ax.set_title(title, fontsize=9)
    ax.set_aspect("equal")
    ax.axis("off")


def iou_table(conf: np.ndarray) -> dict:
    from hgca_core.io.classes import CLASS_NAMES
    from hgca_core.training.semantics import class_iou

    iou = class_iou(conf)
    present = conf.sum(1) >= MIN_SHARE * max(conf.sum(), 1)
    return {"per_class": {n: (None if not np.isfinite(v) else round(float(v) * 100, 1)) for n, v in
                          zip(CLASS_NAMES, iou)},
            "miou": round(float(np.nanmean(np.where(present, iou, np.nan))) * 100, 1),
            "cells": int(conf.sum()), "accuracy": round(float(np.trace(conf) / max(conf.sum(), 1)) * 100, 1),
            "classes": [n for n, k in zip(CLASS_NAMES, present) if k]}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", default="data/synth2f", help="dataset folder with a test split (hgca synth)")
    p.add_argument("--weights", default=None, help="semantic head weights (default: the shipped semantics.pt)")
    p.add_argument("--real-dir", default=str(ROOT / "tests" / "data" / "real"))
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--limit", type=int, default=None, help="first N test scenes only")
    p.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "semantics.json"))
    p.add_argument("--cache", default="runs/semantics_bench",
                   help="folder keeping each input's completion (cells, face centres, seconds): the completions do "
                        "not depend on the head, so a second run with other head weights reuses them")
    p.add_argument("--full", type=int, default=1,
                   help="time the head against the full stage's completion of the first N completed test scenes "
                        "(made once and cached like the coarse ones; CPU and wall seconds)")
    p.add_argument("--complete-only", action="store_true", help="make the cached completions and stop")
    p.add_argument("--inputs", choices=("all", "real", "synthetic"), default="all",
                   help="which completions to make (with --complete-only)")
    p.add_argument("--cached-only", action="store_true",
                   help="score only the inputs whose completion is cached (the ground-truth rows still cover every "
                        "test scene)")
    p.add_argument("--markdown-only", action="store_true", help="rewrite the .md page from the .json record only")
    p.add_argument("--note", action="append", default=[], help="a paragraph for the page (repeatable)")
    args = p.parse_args()
    if args.markdown_only:
        out = Path(args.out)
        out.with_suffix(".md").write_text(markdown(json.loads(out.read_text())))
        return
    import matplotlib
    import torch

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    torch.set_num_threads(args.threads)
    from hgca_core.geometry.region import Region, default_region
    from hgca_core.geometry.voxel import COARSE, voxelize
    from hgca_core.io.classes import CLASS_COLORS, CLASS_NAMES
    from hgca_core.models.semantics import label_mesh, observed_mask, predict
    from hgca_core.models.weights import load_semantics, shipped
    from hgca_core.pipeline import complete_local, load_models
    from hgca_core.metrics.real_eval import read_input
    from hgca_core.dataset.samples import load_sample, split_files
    from hgca_core.synth.rays import input_rays
    from hgca_core.training.semantics import SemanticsTask, scene

    cache = Path(args.cache)
    cache.mkdir(parents=True, exist_ok=True)
    models = {"coarse": load_models("coarse")}

    def completed(name: str, run) -> dict:
        """{cells, s0, centres, completion_s, completion_cpu_s} of one input's completion, from the cache or made
        now (completions cached before CPU seconds were recorded lack completion_cpu_s)."""
        f = cache / f"{name}.npz"
        if not f.exists():
            t0, c0 = time.perf_counter(), time.process_time()
            comp, s0 = run()
            secs, cpu = time.perf_counter() - t0, time.process_time() - c0
            np.savez(f, cells=comp.coarse_cells, s0=s0, centres=np.asarray(comp.mesh.triangles_center, np.float32),
                     completion_s=secs, completion_cpu_s=cpu)
        with np.load(f) as z:
            return {k: z[k] for k in z.files}

    def synthetic_run(path: Path, stage: str = "coarse"):
        if stage not in models:
            models[stage] = load_models(stage)
        sample = load_sample(path)
        rays, ray_scan = input_rays(sample)
        region = Region.from_tuple(sample["region"])
        comp = complete_local(rays, region, models[stage], stage=stage, samples=1, seed=0, max_faces=0,
                              origins=sample["input_origins"], origin_index=ray_scan)[0]
        return comp, voxelize(rays[region.contains_local(rays)], COARSE, region.size)

    def real_run(rel: str, frames: str | None, calib: str | None):
        from hgca_core.geometry.freespace import ray_origins

        scan = read_input({"path": str(Path(args.real_dir) / rel), "frames": frames,
                           "calibration": None if calib is None else str(Path(args.real_dir) / calib)})
        region = default_region(scan.points, scan.origins)
        index = ray_origins(scan.origins, scan.attributes, scan.points)
        local = region.to_local(scan.points)
        comp = complete_local(local, region, models["coarse"], stage="coarse", samples=1, seed=0, max_faces=0,
                              origins=region.to_local(scan.origins), origin_index=index)[0]
        return comp, voxelize(local[region.contains_local(local)], COARSE, region.size)

    files = split_files(args.data, "test")[: args.limit]
    if not args.cached_only:
        for name, rel, frames, calib in (REAL if args.inputs != "synthetic" else ()):
            completed(name, lambda: real_run(rel, frames, calib))
            print(f"completed {name}", flush=True)
        for path in (files if args.inputs != "real" else ()):
            completed(path.stem, lambda: synthetic_run(path))
            print(f"completed {path.stem}", flush=True)
    have = lambda name: (cache / f"{name}.npz").exists()   # noqa: E731
    full_files = [f for f in files if have(f.stem)][: args.full]
    for path in full_files:
        completed(f"{path.stem}_full", lambda: synthetic_run(path, "full"))
        print(f"completed {path.stem} (full stage)", flush=True)
    if args.complete_only:
        return
    head = load_semantics(args.weights)
    k = len(CLASS_NAMES)
    zero = lambda: np.zeros((k, k), np.int64)   # noqa: E731
    conf = {"completion": {"observed": zero(), "generated": zero()}, "gt": {"observed": zero(), "generated": zero()}}
    per_scene, timing, gt_checks, panels = [], [], {}, []
    from hgca_core.training.semantics import confusion

    def timed(name: str, stage: str, done: dict) -> tuple[np.ndarray, np.ndarray]:
        """The head on one cached completion (what `hgca complete --semantics` adds), its wall and CPU seconds
        recorded beside the completion's."""
        t0, c0 = time.perf_counter(), time.process_time()
        labels, faces = label_mesh(head, done["centres"], done["cells"], done["s0"])
        t1, c1 = time.perf_counter(), time.process_time()
        cpu = done.get("completion_cpu_s")
        timing.append({"scene": name, "stage": stage, "cells": int(len(done["cells"])), "faces": int(len(faces)),
                       "completion_s": round(float(done["completion_s"]), 2),
                       "completion_cpu_s": None if cpu is None else round(float(cpu), 2),
                       "semantics_s": round(t1 - t0, 2), "semantics_cpu_s": round(c1 - c0, 2)})
        return labels, faces

    for path in full_files:
        timed(path.stem, "full", completed(f"{path.stem}_full", lambda: synthetic_run(path, "full")))
    scored = []
    for path in files:
        gt = scene(path)
        gl = predict(head, gt["cells"], gt["observed"])[0]
        for part in ("observed", "generated"):
            sel = gt["observed"] if part == "observed" else ~gt["observed"]
            conf["gt"][part] += confusion(gl[sel], gt["labels"][sel])
        for name, (ok, n) in checks(gt["cells"], gt["labels"]).items():
            a = gt_checks.setdefault(name, [0, 0])
            a[0] += ok
            a[1] += n
        if not have(path.stem):
            continue
        scored.append(path.name)
        done = completed(path.stem, lambda: synthetic_run(path))
        labels, faces = timed(path.stem, "coarse", done)
        obs = observed_mask(done["cells"], done["s0"])
        c = scene_confusion(done["cells"], labels, obs, gt)
        row = {"scene": path.stem}
        for part in ("observed", "generated"):
            conf["completion"][part] += c[part]
            row[f"miou_{part}"] = iou_table(c[part])["miou"]
        per_scene.append(row)
        if len(panels) < 2:
            panels.append((f"{path.stem}: ground truth", gt["cells"], gt["labels"]))
            panels.append((f"{path.stem}: completion, labelled", done["cells"], labels))
        print(json.dumps({**row, **timing[-1]}), flush=True)
    real = []
    for name, rel, frames, calib in REAL:
        if not have(name):
            continue
        done = completed(name, lambda: real_run(rel, frames, calib))
        labels, faces = timed(name, "coarse", done)
        res = checks(done["cells"], labels)
        real.append({"input": name, "checks": res,
                     "class_share": {n: round(float((labels == i).mean()) * 100, 1)
                                     for i, n in enumerate(CLASS_NAMES)}})
        panels.append((f"{name} (real): completion, labelled", done["cells"], labels))
        print(json.dumps(real[-1]), flush=True)

    out = Path(args.out)
    tables = {src: {part: iou_table(m) for part, m in parts.items()} for src, parts in conf.items()}
    tables_all = {src: iou_table(parts["observed"] + parts["generated"]) for src, parts in conf.items()}
    share = shares(timing)
    from hgca_core.models.weights import load_file

    wmeta = load_file(args.weights or shipped("semantics"))["meta"]
    record = {"head_steps": wmeta.get("steps"), "head_train_scenes": len(wmeta.get("train_samples") or []),
              "head_data": wmeta.get("data"), "head_selected": wmeta.get("selected"),
              "head_val": next((h for h in reversed(wmeta.get("history_tail", [])) if h.get("kind") == "val"
                                and h["step"] == wmeta.get("steps")), None),
              "head_val_scenes": SemanticsTask.__dataclass_fields__["val_count"].default,
              "data": args.data, "files": [f.name for f in files], "completed_files": scored,
              "weights": str(args.weights or shipped("semantics")),
              "threads": args.threads, "cpu": platform.processor() or platform.machine(), "torch": torch.__version__,
              "iou": tables, "iou_all": tables_all, "per_scene": per_scene, "real": real,
              "gt_checks": {k2: v for k2, v in gt_checks.items()}, "timing": timing,
              "semantics_share": share, **({"notes": args.note} if args.note else {})}
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(record, indent=1))

    cols = 4
    rows = (len(panels) + cols - 1) // cols
    fig, axes = plt.subplots(rows, cols, figsize=(5.2 * cols, 4.4 * rows + 0.6), squeeze=False)
    for ax in np.ravel(axes)[len(panels):]:
        ax.axis("off")
    for ax, (title, cells, labels) in zip(np.ravel(axes), panels):
        render(cells, labels, ax, title)
    handles = [plt.Line2D([], [], marker="s", ls="", color=np.asarray(c) / 255.0, label=n)
               for n, c in zip(CLASS_NAMES, CLASS_COLORS)]
    fig.legend(handles=handles, loc="lower center", ncol=len(CLASS_NAMES), fontsize=9, frameon=False)
    fig.tight_layout(rect=(0, 0.05, 1, 1))
    fig.savefig(out.with_suffix(".png"), dpi=90)
    out.with_suffix(".md").write_text(markdown(record))
    print(f"wrote {out}, {out.with_suffix('.md')}, {out.with_suffix('.png')}")


if __name__ == "__main__":
    main()
