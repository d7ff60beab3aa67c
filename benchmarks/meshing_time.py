"""Wall time of the fine stage's mesh, step by step, on the default region of `hgca bench` (the budget:
meshing, i.e. decode + extraction + cleanup, <= 5 s on 2 cores).

    python benchmarks/meshing_time.py [--reps 5] [--workers 1 2] [--cache DIR] [--out NAME]
    python benchmarks/meshing_time.py --reps 1 --workers 2 --cache DIR --jsonl runs.jsonl --label new
    python benchmarks/meshing_time.py --reps 1 --workers 2 --cache DIR --no-warmup --jsonl rss.jsonl --label new
    python benchmarks/meshing_time.py --compare old.jsonl new.jsonl [--rss rss_old.jsonl rss_new.jsonl] --out meshing_time

Side by side with older code: run the second form once per process, alternating the old tree
(PYTHONPATH=<old checkout>) and this one, each appending its steps' wall and CPU seconds, the sha256 of its
meshes and its peak RSS to its own JSON-lines file; the third form (no warm-up: the process's one mesh stage is
the timed one) gives the peak RSS of one mesh stage; the last writes the old-vs-new page (median and min per
step, wall and CPU, whether every run made the same meshes, peak RSS) and a bar chart.

The fine-stage result (10 cm cells and latents) of the bench's default region (38.4 x 38.4 x 8 m, synthetic
drive, 5 scans) is made once by the product's `pipeline.complete_local` (cached with --cache); then the product's
mesh stage (`meshing.fine.udf_mesh` with the fairing, `decimate` to the default 1 M faces, the vertices' observed
distances) runs `--reps` times for each thread count, interleaved, so a change in the machine's speed during the
run touches every configuration alike. Reported: min and median of each step, and the load average. This VM's
speed drifts by up to ~35 % within an hour, so compare rows of one run, not runs of different days.
"""
from __future__ import annotations

import argparse
import hashlib
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
from hgca_core.meshing.decimation import DEFAULT_MAX_FACES, decimate  # noqa: E402
from hgca_core.meshing.fine import udf_mesh  # noqa: E402
from hgca_core.pipeline import load_models  # noqa: E402

STEPS = ("decode", "extract", "clean", "meshing", "fair", "decimate", "distances", "total")

# What the side-by-side page says about the code it measures (the figures above it are the runs' own)
NOTES = """
## What the mesh stage does differently

Every change keeps the mesh byte for byte (the digests above); each has a test against the plain version it
replaces (tests/test_meshing_udf.py, tests/meshing/test_fairing.py).

- Extraction (`meshing/udf_surface.py`): the grid index keeps its column table, run starts and neighbour
  indices in int32 (half the memory traffic of int64), with one empty column on every side of the points, so the
  x and y neighbours of a grid point are found without bounds tests (one unsigned comparison tells whether a z
  lies in a column's run); an absent neighbour is -1, which reads the fill value appended to the distances, so
  the upwind gradients need no masking pass; the crossing test reads the distance sum before compacting the
  edges; the quad split writes the two triangles' columns instead of gathering through an index table.
- Cleanup (`meshing/mesh_clean.py`): run lengths of sorted keys from the run starts (no cumulative sum and
  bincount over the 4.9 M half-edges), the edge keys built in place, the compaction's renumbering by a scatter
  of the kept vertices' ranks, the per-vertex sums with one contiguous copy per face corner instead of one per
  channel and corner.
- Fairing (`meshing/fairing.py`): the anchors' nearest input points are looked up for the ground-like
  vertices only (the only ones that read them; about half); the membrane's matrix and the ground regions come
  from the adjacency by relabelling the selected rows' columns instead of scipy's column indexing; the
  adjacency itself is the upper triangle read off the sorted edge keys plus its transpose (scipy's linear-time
  CSR -> CSC and row merge) instead of two scatters through computed ranks; the
  conjugate gradients are scipy's `cg` step for step (the same floats in the same order) without its operator
  wrappers and per-step temporaries.
- Not changed: the decoder (`models/autoencoder.py`: the MLP on 27 points per cell, the grid keys' unique and
  the sparse convolutions), the decimation (fast-simplification, one thread) and the k-d tree queries; together
  they are over half of the stage's CPU and cannot shrink without changing the mesh.
"""


def digest(mesh) -> str:
    """sha256 of a mesh's vertices and faces (as stored): equal digests, byte-identical meshes."""
    h = hashlib.sha256()
    h.update(np.ascontiguousarray(mesh.vertices).tobytes())
    h.update(np.ascontiguousarray(mesh.faces).tobytes())
    return h.hexdigest()


def peak_rss_mib() -> float:
    """This process's peak resident set (VmHWM), MiB."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM"):
            return int(line.split()[1]) / 1024
    return float("nan")


def time_once(ae, cells, z, local: np.ndarray, sensors: np.ndarray, workers: int,
              digests: dict | None = None) -> tuple[dict, int, int]:
    """Seconds of each step of one mesh stage, and the triangles before / after decimation; `digests` gets
    the sha256 of the mesh, the decimated mesh and its vertices' observed distances."""
    t = {}
    t0, c0 = time.perf_counter(), time.process_time()
    tree = PointIndex(local)
    with torch.no_grad():
        mesh = udf_mesh(ae, cells, z, voxel=ae.cfg.voxel, points=local, sensors=sensors, tree=tree, timings=t,
                        workers=workers)
    a, ac = time.perf_counter(), time.process_time()
    light = decimate(mesh, DEFAULT_MAX_FACES)
    b, bc = time.perf_counter(), time.process_time()
    dist = tree.distances(np.asarray(light.vertices))
    c, cc = time.perf_counter(), time.process_time()
    if digests is not None:
        digests.update(sha_mesh=digest(mesh), sha_light=digest(light),
                       sha_distances=hashlib.sha256(dist.tobytes()).hexdigest())
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
    ap.add_argument("--rss", type=Path, nargs=2, metavar=("OLD", "NEW"), default=None,
                    help="with --compare: --jsonl files of --no-warmup runs, for the peak RSS of one mesh stage")
    ap.add_argument("--no-warmup", action="store_true",
                    help="time the process's first mesh stage (its peak RSS is then that of one stage)")
    args = ap.parse_args()
    if args.compare:
        side_by_side(*args.compare, args.out, args.rss)
        return
    torch.set_num_threads(args.threads)
    models = load_models("full")
    ae = models.autoencoder
    pts, origins, index, region = scene_inputs(38.4, depth=38.4)
    local, sensors = region.to_local(pts), region.to_local(origins)
    cells, z = fine_state(models, local, region, 0, args.cache, "bench_default", origins=sensors, origin_index=index)
    if not args.no_warmup:
        time_once(ae, cells, z, local, sensors, max(args.workers))              # warm-up (imports, allocator)
    runs: dict[int, list[dict]] = {w: [] for w in args.workers}
    loads = []
    for rep in range(args.reps):
        for w in args.workers:
            sha: dict = {}
            t, faces, light = time_once(ae, cells, z, local, sensors, w, sha)
            runs[w].append(t)
            loads.append(os.getloadavg()[0])
            print(f"rep {rep} workers {w}: " + " ".join(f"{k} {v:.2f}" for k, v in t.items()), flush=True)
            if args.jsonl is not None:
                import hgca_core
                with open(args.jsonl, "a") as fh:
                    fh.write(json.dumps({"label": args.label, "workers": w, "torch_threads": args.threads,
                                         "load": os.getloadavg()[0], "faces": faces, "decimated": light,
                                         "peak_rss_mib": peak_rss_mib(), "warmup": not args.no_warmup, "end": time.time(), **sha,
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


def read_runs(*paths: Path) -> dict[str, list[dict]]:
    """The rows of --jsonl files by label (a file's name where its rows have none)."""
    runs = {}
    for path in paths:
        rows = [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
        runs[rows[0]["label"] or path.stem] = rows
    return runs


def identity(runs: dict[str, list[dict]]) -> str:
    """Whether every run of every code made the same meshes (sha256 of vertices and faces)."""
    rows = [r for rs in runs.values() for r in rs]
    if not all("sha_light" in r for r in rows):
        return "Mesh digests: not recorded by these runs."
    same = {(r["sha_mesh"], r["sha_light"], r["sha_distances"]) for r in rows}
    if len(same) == 1:
        mesh, light, _ = same.pop()
        return (f"Byte-identical: every run of both codes made the same mesh (sha256 of vertices and faces "
                f"{mesh[:12]}...), the same decimated mesh ({light[:12]}...) and the same observed distances.")
    per = {lab: len({(r["sha_mesh"], r["sha_light"]) for r in rs}) for lab, rs in runs.items()}
    return f"NOT byte-identical: {len(same)} distinct (mesh, decimated, distances) digests; per code {per}."


def rss_lines(rss: tuple[Path, Path] | None, labels: list[str]) -> list[str]:
    """Peak RSS (VmHWM) of processes whose first and only mesh stage was the timed one, per code."""
    if rss is None:
        return []
    runs = read_runs(*rss)
    parts = []
    for lab, rs in runs.items():
        each = ", ".join(f"{r['peak_rss_mib']:.0f}" for r in rs)
        parts.append(f"{lab} {statistics.median(r['peak_rss_mib'] for r in rs):.0f} MiB ({each})")
    cpu = [f"{lab} {statistics.median(r['total_cpu'] for r in rs):.2f} s" for lab, rs in runs.items()]
    return ["", f"Peak RSS of one mesh stage (fresh processes that load the models and the cached fine-stage result, "
            f"then run one mesh stage, no warm-up; VmHWM of /proc/self/status at its end), median (each run): "
            + "; ".join(parts) + f". The same processes' mesh-stage CPU (a cold first stage): {'; '.join(cpu)}."]


def side_by_side(old: Path, new: Path, name: str, rss: tuple[Path, Path] | None = None) -> None:
    """benchmarks/results/<name>.md/.json/.png: median and min of each step, wall and CPU, old vs new; whether
    the meshes are byte-identical; with `rss`, the peak RSS of one mesh stage per code."""
    runs = read_runs(old, new)
    stat = {lab: {k: {"median": round(statistics.median(r[k] for r in rs), 3), "min": round(min(r[k] for r in rs), 3)}
                  for k in STEPS + tuple(f"{s}_cpu" for s in STEPS)} for lab, rs in runs.items()}
    loads = [r["load"] for rs in runs.values() for r in rs]
    (lo, hi) = (min(loads), max(loads))
    first = next(iter(runs.values()))[0]
    result = {"machine": machine(), "runs": runs, "stats": stat, "load_min_max": [round(lo, 2), round(hi, 2)],
              "faces": first["faces"], "decimated": first["decimated"],
              "rss_runs": read_runs(*rss) if rss else None}
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
              "(on a busy machine the fairer measure of the work). meshing = decode + extract + clean.", "",
              identity(runs)]
    if all("peak_rss_mib" in r for rs in runs.values() for r in rs):
        lines += ["", "Peak RSS of these processes (model load, cached state, a warm-up stage and the timed one), "
                  "median: " + "; ".join(f"{lab} {statistics.median(r['peak_rss_mib'] for r in rs):.0f} MiB"
                                         for lab, rs in runs.items()) + "."]
    lines += rss_lines(rss, list(stat))
    lines += ["", "Load average (1 min) at the end of each run, in run order: " + ", ".join(
        f"{r['label']} {r['load']:.1f}" for r in sorted((r for rs in runs.values() for r in rs),
                                                      key=lambda r: r.get("end", 0)))]
    (out / f"{name}.md").write_text("\n".join(lines) + "\n" + NOTES)
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
