"""Time and peak memory of one completion per stage, for the default region and 40 x w m strips.

Each configuration runs in its own process (`python -m hgca_core.bench --worker JSON`), so its peak RSS
(and `torch.cuda.max_memory_allocated` on a GPU) belongs to that run alone. It runs the product's own
`pipeline.complete` (the world-frame wrapper around the region-frame core), so the times are what a user
waits for. Stage times come from the pipeline's own progress events (`progress.StageClock`). The weights are the
shipped ones unless given; the result names them by path and sha256 (`models.weights.weights_record`), so two
files are timed on one machine without swapping the shipped file.
"""
from __future__ import annotations

import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from hgca_core.hardware import machine, peak_rss_bytes
from hgca_core.nn.precision import DEFAULT_PRECISION



def scene_inputs(width: float, seed: int = 4_000_000,
                 depth: float = 40.0) -> tuple[np.ndarray, np.ndarray, np.ndarray, "object"]:
    """Input points (world) of scans every ~8 m along a synthetic drive, the scans' sensor origins, each point's
    origin index, and a width x depth x 8 m region centred on the drive, aligned with it (the paper's 40 x w m
    strips; depth 38.4 for the default)."""
    from hgca_core.geometry.region import Region
    from hgca_core.geometry.raycast import make_intersector
    from hgca_core.synth.dataset import Drive
    from hgca_core.synth.lidar import PAPER_EFFECTS, PROFILES, Unit, scan
    from hgca_core.synth.scene import make_scene

    scene = make_scene(seed, "city")
    drive = Drive(scene.drive, scene.drive_up)
    mid = drive.length / 2
    n = max(5, int(round(width / 8)))
    half = min(width / 2 - 2.0, mid - 1.0)
    inter = make_intersector(scene.mesh)
    rng = np.random.default_rng(seed)
    unit = Unit.draw(PROFILES["waymo"], rng, PAPER_EFFECTS)
    scans = [scan(inter, scene.face_materials, drive.pose(s), unit, rng, PAPER_EFFECTS)
             for s in mid + np.linspace(-half, half, n)]
    pts = np.concatenate([sc.points for sc in scans])
    index = np.concatenate([np.full(len(sc.points), i, dtype=np.int64) for i, sc in enumerate(scans)])
    poses = [sc.pose for sc in scans]
    ego = drive.pose(mid) @ unit.mount
    region = Region.around(ego[None, :3, 3], sensor=ego[:3, 3], ground_z=float(scene.terrain.height(ego[:2, 3])[0]),
                           size=(width, depth, 8.0), yaw=float(np.arctan2(ego[1, 0], ego[0, 0])))
    return pts, np.array([p[:3, 3] for p in poses]), index, region


def run_one(width: float, depth: float, stage: str, device: str, t1: int | None, seed: int,
            precision: str = DEFAULT_PRECISION, weights: str | None = None, fine_weights: str | None = None) -> dict:
    """One completion with per-stage wall times (s) and peak memory (bytes)."""
    import torch

    from hgca_core.pipeline import complete
    from hgca_core.progress import StageClock

    pts, origins, index, region = scene_inputs(width, depth=depth)
    t_start = time.perf_counter()
    clock = StageClock()
    res = complete(pts, region=region, origins=origins, samples=1, seed=seed, stage=stage, device=device, t1=t1,
                   progress=clock, precision=precision, origin_index=index, weights=weights,
                   fine_weights=fine_weights)[0]
    t_mesh = time.perf_counter()
    from hgca_core.io import write_mesh

    out = Path(os.environ.get("TMPDIR", "/tmp")) / f"hgca_bench_{os.getpid()}.ply"
    write_mesh(out, res.mesh)
    out.unlink()
    total = time.perf_counter() - t_start
    stages = dict(clock.seconds)
    stages["write"] = time.perf_counter() - t_mesh
    usage = resource.getrusage(resource.RUSAGE_SELF)   # page faults
    gpu = torch.cuda.max_memory_allocated() if device.startswith("cuda") else None
    from hgca_core.nn.conv import precision_name, resolve_precision

    gemm = precision_name(resolve_precision(precision, device))
    return {"width": width, "depth": depth, "stage": stage, "device": device, "precision": gemm, "points": int(len(pts)),
            "coarse_cells": int(len(res.coarse_cells)), "triangles": int(len(res.mesh.faces)),
            "seconds": round(total, 2), "stages_s": {k: round(v, 3) for k, v in stages.items()},
            "steps": {k: clock.totals[k] for k in ("coarse", "fine") if k in clock.totals},
            "peak_rss_gib": round(peak_rss_bytes() / 2**30, 3), "minor_faults": usage.ru_minflt,
            "gpu_peak_gib": None if gpu is None else round(gpu / 2**30, 3)}


def worker(job: dict, timeout: int | None = None, env: dict | None = None, cwd: Path | None = None) -> dict:
    """One configuration in a fresh worker process (`python -m hgca_core.bench --worker JOB`, from `cwd`, with
    `env`): its result row, or {"error": the last line of its stderr}."""
    proc = subprocess.run([sys.executable, "-m", "hgca_core.bench", "--worker", json.dumps(job)], capture_output=True,
                          text=True, timeout=timeout, env=env, cwd=cwd)
    if proc.returncode != 0:
        return {"error": proc.stderr.strip().splitlines()[-1:]}
    return json.loads(proc.stdout.strip().splitlines()[-1])


def run(widths: list[float], default: bool, stage: str, device: str, t1: int | None, out_dir: Path,
        name: str, timeout: int = 3600, precision: str = DEFAULT_PRECISION, weights: str | None = None,
        fine_weights: str | None = None) -> dict:
    """Each configuration in its own worker process, with the weights of `weights_files` (given or shipped),
    which the caller has checked to load, and writes `out_dir`/`name`.{json,md,png} into the folder the caller has
    made and checked (`hgca bench`: `check_outputs`)."""
    from hgca_core.models.weights import weights_record

    record = weights_record(["hgca-full" if stage == "full" else "hgca"], weights, fine_weights)
    files = record["weights"]
    configs = ([(38.4, 38.4)] if default else []) + [(w, 40.0) for w in widths]
    rows = []
    for width, depth in configs:
        row = worker({"width": width, "depth": depth, "stage": stage, "device": device, "t1": t1, "seed": 0,
                      "precision": precision, "weights": files["coarse"], "fine_weights": files.get("fine")}, timeout)
        rows.append({"width": width, "depth": depth, **row} if "error" in row else row)
        print(json.dumps(rows[-1]), flush=True)
    result = {"machine": machine(), "stage": stage, "device": device, "t1": t1, "precision": precision, **record,
              "rows": rows}
    (out_dir / f"{name}.json").write_text(json.dumps(result, indent=1))
    (out_dir / f"{name}.md").write_text(table(result))
    plot(result, out_dir / f"{name}.png")
    return result


def table(result: dict) -> str:
    m = result["machine"]
    stage_names = sorted({k for r in result["rows"] for k in r.get("stages_s", {})})
    head = ["region (m)", "input points", "coarse cells", "total (s)", *[f"{s} (s)" for s in stage_names],
            "peak RSS (GiB)", "GPU peak (GiB)"]
    gemm = sorted({r["precision"] for r in result["rows"] if "precision" in r})
    lines = [f"Completion benchmark, stage {result['stage']}, device {result['device']}, T1 = {result['t1'] or 'default'}"
             + (f", sparse-conv GEMMs in {'/'.join(gemm)}" if gemm else ""),
             f"Machine: {m['cpu']}, {m['cores']} cores, torch {m['torch']} ({m['threads']} threads), {m['date']}"
             + (f", GPU {m['gpu']}" if "gpu" in m else ""),
             *(["Weights: " + ", ".join(f"{r} {Path(f).name} (sha256 {result['weights_sha256'][r][:8]})"
                                       for r, f in result["weights"].items())] if "weights" in result else []), "",
             "| " + " | ".join(head) + " |", "|" + "|".join(["---:"] * len(head)) + "|"]
    for r in result["rows"]:
        if "error" in r:
            lines.append(f"| {r['depth']} x {r['width']} | error: {' '.join(r['error'])} |")
            continue
        cells = [f"{r['depth']} x {r['width']}", str(r["points"]), str(r["coarse_cells"]), f"{r['seconds']:.1f}",
                 *[f"{r['stages_s'].get(s, 0.0):.2f}" for s in stage_names], f"{r['peak_rss_gib']:.2f}",
                 "-" if r["gpu_peak_gib"] is None else f"{r['gpu_peak_gib']:.2f}"]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def plot(result: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = [r for r in result["rows"] if "error" not in r and r["depth"] == 40.0]
    if not rows:
        return
    w = [r["width"] for r in rows]
    fig, ax = plt.subplots(1, 2, figsize=(10, 4))
    ax[0].plot(w, [r["seconds"] for r in rows], "o-")
    ax[0].set(xlabel="region width w (m), 40 x w", ylabel="seconds", title="completion time")
    ax[1].plot(w, [r["peak_rss_gib"] for r in rows], "o-", label="peak RSS")
    if rows[0]["gpu_peak_gib"] is not None:
        ax[1].plot(w, [r["gpu_peak_gib"] for r in rows], "s-", label="GPU peak")
    ax[1].set(xlabel="region width w (m), 40 x w", ylabel="GiB", title="peak memory")
    ax[1].legend()
    fig.suptitle(f"{result['machine']['cpu']} ({result['machine']['cores']} cores), {result['device']}")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def _worker(job: str) -> int:
    """One configuration, in a process set up as the CLI's (`tune_allocator`), so its times are a user's."""
    from hgca_core.hardware import tune_allocator

    tune_allocator()
    args = json.loads(job)
    print(json.dumps(run_one(args["width"], args["depth"], args["stage"], args["device"], args["t1"], args["seed"],
                             args.get("precision", DEFAULT_PRECISION), args.get("weights"), args.get("fine_weights"))))
    return 0


if __name__ == "__main__":
    if len(sys.argv) == 3 and sys.argv[1] == "--worker":
        sys.exit(_worker(sys.argv[2]))
    sys.exit("usage: python -m hgca_core.bench --worker JSON (use `hgca bench`)")
