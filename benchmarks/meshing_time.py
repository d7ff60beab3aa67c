"""Wall time of the fine stage's mesh, step by step, on the default region of `hgca bench` (the budget:
meshing, i.e. decode + extraction + cleanup, <= 5 s on 2 cores).

    python benchmarks/meshing_time.py [--reps 5] [--workers 1 2] [--cache DIR] [--out NAME]
    python benchmarks/meshing_time.py --reps 1 --workers 2 --cache DIR --jsonl runs.jsonl --label new
    python benchmarks/meshing_time.py --compare old.jsonl new.jsonl --out meshing_time

Side by side with older code: run the second form once per process, alternating the old tree
(PYTHONPATH=<old checkout>) and this one, each appending its steps' wall and CPU seconds to its own JSON-lines
file; the third form writes the old-vs-new table (median and min per step, wall and CPU) and a bar chart.

The fine-stage result (10 cm cells and latents) of the bench's default region (38.4 x 38.4 x 8 m, synthetic
drive, 5 scans) is made once by the product's `pipeline.complete_local` (cached with --cache); then the product's
mesh stage (`meshing.udf_mesh` with the fairing, `decimate` to the default 1 M faces, the vertices' observed
distances) runs `--reps` times for each thread count, interleaved, so a change in the machine's speed during the
run touches every configuration alike. Reported: min and median of each step, and the load average. This VM's
speed drifts by up to ~35 % within an hour, so compare rows of one run, not runs of different days.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import time
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")    # as the CLI sets it (hgca_core/cli.py)

import numpy as np  # noqa: E402
import torch  # noqa: E402

REPO = Path(__file__).resolve().parents[1]

from mesh_quality import fine_state  # noqa: E402

from hgca_core.bench import scene_inputs  # noqa: E402
from hgca_core.geometry.nearest import PointIndex  # noqa: E402
from hgca_core.hardware import machine  # noqa: E402
from hgca_core.meshing import DEFAULT_MAX_FACES, decimate, udf_mesh  # noqa: E402
from hgca_core.pipeline import load_models  # noqa: E402

STEPS = ("decode", "extract", "clean", "meshing", "fair", "decimate", "distances", "total")


def time_once(ae, cells, z, local: np.ndarray, sensors: np.ndarray, workers: int) -> tuple[dict, int, int]:
    """Seconds of each step of one mesh stage, and the triangles before / after decimation."""
    t = {}
    t0, c0 = time.perf_counter(), time.process_time()
    tree = PointIndex(local)
    with torch.no_grad():
        mesh = udf_mesh(ae, cells, z, voxel=ae.cfg.voxel, points=local, sensors=sensors, tree=tree, timings=t,
                        workers=workers)
    a, ac = time.perf_counter(), time.process_time()
    light = decimate(mesh, DEFAULT_MAX_FACES)
    b, bc = time.perf_counter(), time.process_time()
    tree.distances(np.asarray(light.vertices))
    c, cc = time.perf_counter(), time.process_time()
    out = {k: t[k] for k in ("decode", "extract", "clean", "fair")}
    out.update(meshing=t["decode"] + t["extract"] + t["clean"], decimate=b - a, distances=c - b, total=c - t0)
    out.update({f"{k}_cpu": t[f"{k}_cpu"] for k in ("decode", "extract", "clean", "fair")})
    out.update(meshing_cpu=t["decode_cpu"] + t["extract_cpu"] + t["clean_cpu"], decimate_cpu=bc - ac,
               distances_cpu=cc - bc, total_cpu=cc - c0)
    return out, len(mesh.faces), len(light.faces)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--reps", type=int, default=5)
    ap.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--threads", type=int, default=2, help="torch threads (the decoder)")
    ap.add_argument("--cache", type=Path, default=None)
    ap.add_argument("--out", default="meshing_time")
    ap.add_argument("--jsonl", type=Path, default=None, help="append each run's seconds here (no results page)")
    ap.add_argument("--label", default="", help="with --jsonl: the code's name in the side-by-side table")
    ap.add_argument("--compare", type=Path, nargs=2, metavar=("OLD", "NEW"), default=None,
                    help="write the side-by-side page of two --jsonl files")
    args = ap.parse_args()
    if args.compare:
        side_by_side(*args.compare, args.out)
        return
    torch.set_num_threads(args.threads)
    models = load_models("full")
    ae = models.autoencoder
    pts, origins, index, region = scene_inputs(38.4, depth=38.4)
    local, sensors = region.to_local(pts), region.to_local(origins)
    cells, z = fine_state(models, local, region, 0, args.cache, "bench_default", origins=sensors, origin_index=index)
    time_once(ae, cells, z, local, sensors, max(args.workers))                  # warm-up (imports, allocator)
    runs: dict[int, list[dict]] = {w: [] for w in args.workers}
    loads = []
    for rep in range(args.reps):
        for w in args.workers:
            t, faces, light = time_once(ae, cells, z, local, sensors, w)
            runs[w].append(t)
            loads.append(os.getloadavg()[0])
            print(f"rep {rep} workers {w}: " + " ".join(f"{k} {v:.2f}" for k, v in t.items()), flush=True)
            if args.jsonl is not None:
                import hgca_core
                with open(args.jsonl, "a") as fh:
                    fh.write(json.dumps({"label": args.label, "workers": w, "torch_threads": args.threads,
                                         "load": os.getloadavg()[0], "faces": faces, "decimated": light,
                                         "code": str(Path(hgca_core.__file__).parents[1]), **t}) + "\n")
    if args.jsonl is not None:
        return
    result = {"machine": machine(), "cells": int(len(cells)), "triangles": faces, "decimated": light,
              "reps": args.reps, "load_min_max": [round(min(loads), 2), round(max(loads), 2)],
              "rows": {str(w): {k: {"min": round(min(r[k] for r in rs), 3),
                                    "median": round(statistics.median(r[k] for r in rs), 3)} for k in STEPS}
                       for w, rs in runs.items()},
              "runs": {str(w): rs for w, rs in runs.items()}}
    out = REPO / "benchmarks" / "results"
    (out / f"{args.out}.json").write_text(json.dumps(result, indent=1))
    (out / f"{args.out}.md").write_text(table(result))
    print(table(result))


def side_by_side(old: Path, new: Path, name: str) -> None:
    """benchmarks/results/<name>.md/.json/.png: median and min of each step, wall and CPU, old vs new."""
    runs = {}
    for path in (old, new):
        rows = [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
        runs[rows[0]["label"] or path.stem] = rows
    stat = {lab: {k: {"median": round(statistics.median(r[k] for r in rs), 3), "min": round(min(r[k] for r in rs), 3)}
                  for k in STEPS + tuple(f"{s}_cpu" for s in STEPS)} for lab, rs in runs.items()}
    loads = [r["load"] for rs in runs.values() for r in rs]
    (lo, hi) = (min(loads), max(loads))
    first = next(iter(runs.values()))[0]
    result = {"machine": machine(), "runs": runs, "stats": stat, "load_min_max": [round(lo, 2), round(hi, 2)],
              "faces": first["faces"], "decimated": first["decimated"]}
    out = REPO / "benchmarks" / "results"
    (out / f"{name}.json").write_text(json.dumps(result, indent=1))
    m = result["machine"]
    (a, b) = list(stat)
    lines = [f"Mesh stage of the default region ({first['faces']:,} triangles decimated to {first['decimated']:,}), "
             f"{a} against {b}, the same cached fine-stage result, alternating fresh processes "
             f"({len(runs[a])} + {len(runs[b])} runs), 2 torch threads, 2 numpy workers.",
             f"Machine: {m['cpu']}, {m['cores']} cores, torch {m['torch']}, {m['date']}; load average (1 min) "
             f"{lo:.1f}-{hi:.1f} during the runs.", "",
             "| step | " + " | ".join(f"{lab} wall | {lab} CPU" for lab in stat) + " | CPU new / old |",
             "|---|" + "---:|" * (2 * len(stat) + 1)]
    for k in STEPS:
        cells = " | ".join(f"{stat[lab][k]['median']:.2f} ({stat[lab][k]['min']:.2f}) | "
                           f"{stat[lab][k + '_cpu']['median']:.2f} ({stat[lab][k + '_cpu']['min']:.2f})" for lab in stat)
        ratio = stat[b][k + "_cpu"]["median"] / max(stat[a][k + "_cpu"]["median"], 1e-9)
        lines.append(f"| {k} | {cells} | {ratio:.2f} |")
    lines += ["", "Seconds, median (min) over the runs. CPU: user + system seconds of the process, all its threads "
              "(on a busy machine the fairer measure of the work). meshing = decode + extract + clean."]
    (out / f"{name}.md").write_text("\n".join(lines) + "\n")
    chart(stat, out / f"{name}.png", f"{m['cpu']}, load {lo:.0f}-{hi:.0f}")
    print("\n".join(lines))


def chart(stat: dict, path: Path, note: str) -> None:
    """Bar chart of the steps' median CPU and wall seconds, one bar per code."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    steps = ("decode", "extract", "clean", "fair", "decimate", "distances")
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    for ax, suffix, title in ((axes[0], "_cpu", "CPU seconds (user + system)"), (axes[1], "", "wall seconds")):
        x = np.arange(len(steps))
        for i, lab in enumerate(stat):
            ax.bar(x + (i - 0.5) * 0.4, [stat[lab][s + suffix]["median"] for s in steps], 0.4, label=lab)
        ax.set_xticks(x, steps)
        ax.set_title(f"{title}, median")
        ax.legend()
    fig.suptitle(f"Mesh stage of the default region, step by step ({note})", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def table(r: dict) -> str:
    m = r["machine"]
    lines = [f"Mesh stage of the default region ({r['cells']:,} fine cells -> {r['triangles']:,} triangles, "
             f"decimated to {r['decimated']:,}), {r['reps']} interleaved runs per thread count.",
             f"Machine: {m['cpu']}, {m['cores']} cores, torch {m['torch']}, {m['date']}; load average (1 min) "
             f"{r['load_min_max'][0]}-{r['load_min_max'][1]} during the runs.", "",
             "| numpy threads | " + " | ".join(STEPS) + " |", "|---|" + "---:|" * len(STEPS)]
    for w, row in r["rows"].items():
        lines.append(f"| {w} | " + " | ".join(f"{row[k]['median']:.2f} ({row[k]['min']:.2f})" for k in STEPS) + " |")
    lines += ["", "Seconds, median (min). meshing = decode + extract + clean (the budgeted measure: <= 5 s on 2 cores); clean includes "
              "finding the observed vertices; fair, decimate and the observed distances complete the stage. The "
              "decoder runs on torch's threads (2) in every row; the thread count is that of the numpy steps."]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
