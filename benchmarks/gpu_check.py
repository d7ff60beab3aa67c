"""GPU check: completion and training on a CUDA GPU, timed, and the GPU's mesh checked against the CPU's.

    .venv/bin/python benchmarks/gpu_check.py --prepare gpu_data      # here, once: inputs the GPU machine can't build
    scripts/gpu_check.sh                                             # on the GPU machine: under 5 minutes
    .venv/bin/python benchmarks/gpu_check.py --device cpu --quick --out DIR   # the same code on a CPU (a test)

On `--device`: the default region (38.4 x 38.4 x 8 m) of the synthetic drive `hgca bench` times (its
`scene_inputs`, 786 k points, with each point's sensor origin), completed with the shipped weights, coarse and
full: one warm-up run (CUDA start, kernel loading), then `--repeats` timed runs each (median; stage times from the
pipeline's own progress events, the GPU synchronised at each). Then the same full completion on the CPU with the
same seed: the sampler draws its random numbers on the CPU on any device, so the two differ only by floating-point
rounding (GEMM order, fused kernels), which can flip a cell whose probability sits at a draw. The check: the share
of 20 cm cells the two have in common (IoU) and the distances between their meshes (each vertex to the other
mesh's nearest vertex, both ways) must be closer than two CPU samples of different seeds are (the same run
measures those): the tolerance is the spread between samples, measured, not a number typed in. Last, `--steps`
coarse training steps on the device on a small packed dataset (per step: the time of a longer run less a shorter
one's, over the extra steps; start-up and validation cancel). Writes gpu.md, gpu.json and gpu.png in `--out`
(default benchmarks/results).
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
import traceback
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "benchmarks" / "results"
DATA = REPO / "gpu_data"
SEED = 0


def prepare(folder: Path, scenes: int = 3) -> None:
    """The default region's inputs (inputs.npz) and a small packed coarse dataset (train_data/: train/, val/):
    what the GPU machine cannot build itself (its image has no ray-casting library)."""
    from hgca_core.bench import scene_inputs

    folder.mkdir(parents=True, exist_ok=True)
    pts, origins, index, region = scene_inputs(38.4, depth=38.4)
    # float32 points (as a LiDAR file holds them) and uint8 origin rows: 8 MB, so it travels with the tree
    np.savez_compressed(folder / "inputs.npz", points=pts.astype(np.float32), origins=origins,
                        origin_index=index.astype(np.uint8), region=np.array(region.as_tuple()))
    raw = folder / "synth"
    hgca = [sys.executable, "-m", "hgca_core.cli", "synth"]
    for split, count in (("train", scenes), ("val", 1)):
        subprocess.run([*hgca, "--split", split, "--count", str(count), "--out", str(raw), "--no-preview",
                        "--workers", "1"], check=True)
    subprocess.run([*hgca, "--pack", str(raw), "--out", str(folder / "train_data")], check=True)


def load_inputs(folder: Path):
    from hgca_core.geometry.region import Region

    with np.load(folder / "inputs.npz") as z:
        return (z["points"].astype(np.float64), z["origins"], z["origin_index"].astype(np.int64),
                Region.from_tuple(tuple(z["region"])))


def sync(device: str) -> None:
    import torch

    if device.startswith("cuda"):
        torch.cuda.synchronize()


def complete_once(inputs, stage: str, device: str, seed: int = SEED, t1: int | None = None,
                  t2: int | None = None) -> tuple[dict, object]:
    """One completion: wall and stage seconds (the device synchronised at every progress event) and the result."""
    from hgca_core.pipeline import complete
    from hgca_core.progress import StageClock

    pts, origins, index, region = inputs
    clock = StageClock()

    def timed(*a) -> None:
        sync(device)
        clock(*a)

    sync(device)
    t = time.perf_counter()
    res = complete(pts, region=region, origins=origins, origin_index=index, samples=1, seed=seed, stage=stage,
                   device=device, t1=t1, t2=t2, progress=timed)[0]
    sync(device)
    return {"wall_s": time.perf_counter() - t, "stages_s": {k: round(v, 3) for k, v in clock.seconds.items()}}, res


def time_completion(inputs, stage: str, device: str, repeats: int, **kw) -> tuple[dict, list]:
    """A warm-up run, then `repeats` timed runs; returns the timings and the timed runs' results."""
    import torch

    warm, _ = complete_once(inputs, stage, device, **kw)
    if device.startswith("cuda"):
        torch.cuda.reset_peak_memory_stats()
    runs, results = [], []
    for _ in range(repeats):
        r, res = complete_once(inputs, stage, device, **kw)
        runs.append(r)
        results.append(res)
    walls = [r["wall_s"] for r in runs]
    out = {"warmup_s": round(warm["wall_s"], 3), "wall_s": [round(w, 3) for w in walls],
           "median_s": round(float(np.median(walls)), 3), "stages_s": runs[int(np.argsort(walls)[len(walls) // 2])]
           ["stages_s"]}
    if device.startswith("cuda"):
        out["peak_gpu_gib"] = round(torch.cuda.max_memory_allocated() / 2**30, 2)
    return out, results


def cell_iou(a: np.ndarray, b: np.ndarray) -> float:
    ka = {tuple(c) for c in np.asarray(a, dtype=np.int64)}
    kb = {tuple(c) for c in np.asarray(b, dtype=np.int64)}
    return len(ka & kb) / max(1, len(ka | kb))


def mesh_distance(a, b) -> dict:
    """Each vertex of either mesh to the other's nearest vertex (metres): median, 95th percentile, max."""
    from scipy.spatial import cKDTree

    va, vb = np.asarray(a.vertices), np.asarray(b.vertices)
    if not len(va) or not len(vb):
        return {"median": None, "p95": None, "max": None, "vertices": [len(va), len(vb)]}
    d = np.concatenate([cKDTree(vb).query(va)[0], cKDTree(va).query(vb)[0]])
    return {"median": round(float(np.median(d)), 4), "p95": round(float(np.percentile(d, 95)), 4),
            "max": round(float(d.max()), 4), "vertices": [len(va), len(vb)]}


def compare(device_res, cpu_res, cpu_other) -> dict:
    """The device's mesh against the CPU's (same seed), judged by the spread between two CPU samples."""
    same = {"cell_iou": round(cell_iou(device_res.coarse_cells, cpu_res.coarse_cells), 4),
            "distance_m": mesh_distance(device_res.mesh, cpu_res.mesh)}
    spread = {"cell_iou": round(cell_iou(cpu_other.coarse_cells, cpu_res.coarse_cells), 4),
              "distance_m": mesh_distance(cpu_other.mesh, cpu_res.mesh)}
    p95, p95_spread = same["distance_m"]["p95"], spread["distance_m"]["p95"]
    ok = same["cell_iou"] > spread["cell_iou"] and (p95 is not None and p95_spread is not None and p95 < p95_spread)
    return {"device_vs_cpu": same, "cpu_seed_vs_seed_plus_1": spread, "within_tolerance": bool(ok)}


def time_training(folder: Path, device: str, steps: int, work: Path, small: bool = False) -> dict:
    """Seconds per coarse training step on `device`, from one run of 10 + `steps` steps: the trainer's own mean
    step time over the steps after the tenth (it logs means of 10 steps; the first ten hold the kernels' loading),
    the first ten's with fewer steps; the default model and crop, or with `small` a small model on small crops."""
    from hgca_core.models.gca import GCAConfig
    from hgca_core.training.coarse import CoarseTask
    from hgca_core.training.trainer import train

    cfg, crop = (GCAConfig(channels=(8, 8, 16, 16, 16), steps=3), 24) if small else (GCAConfig(), 96)
    task = CoarseTask(str(folder), cfg, crop=crop, val_count=1)
    t = time.perf_counter()
    state = train(task, work / "train", minutes=10, max_steps=10 + steps, batch=2, buffer_size=4, progress=False,
                  device=device)
    logged = [h for h in state["history"] if h["kind"] == "train"]
    return {"steps": 10 + steps, "batch": 2, "crop": crop, "small_model": small,
            "run_s": round(time.perf_counter() - t, 1), "step_s": round(float(logged[-1]["step_s"]), 3),
            "first_ten_step_s": round(float(logged[0]["step_s"]), 3),
            "steps_averaged": f"{10 * len(logged) - 9}-{10 * len(logged)}"}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--data", type=Path, default=DATA, help="what --prepare wrote")
    ap.add_argument("--prepare", type=Path, default=None, help="build the inputs into this folder and stop")
    ap.add_argument("--out", type=Path, default=RESULTS)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--steps", type=int, default=10, help="training steps timed after the first ten")
    ap.add_argument("--quick", action="store_true",
                    help="a few steps of everything (the test's CPU run): 1 repeat, T1 = T2 = 2, 10 training steps")
    args = ap.parse_args()
    if args.prepare:
        prepare(args.prepare)
        return 0
    import torch

    from hgca_core.hardware import machine
    from hgca_core.pipeline import check_device

    try:
        check_device(args.device)
    except ValueError as exc:
        print(f"gpu_check: error: {exc}", file=sys.stderr)
        return 2
    if not (args.data / "inputs.npz").is_file():
        print(f"gpu_check: error: {args.data}/inputs.npz is missing: run with --prepare {args.data} first (on a "
              "machine that has the project's dependencies)", file=sys.stderr)
        return 2
    steps = {"t1": 2, "t2": 2} if args.quick else {}
    repeats, train_steps = (1, 0) if args.quick else (args.repeats, args.steps)
    inputs = load_inputs(args.data)
    result: dict = {"machine": machine(), "device": args.device, "quick": args.quick, "points": int(len(inputs[0])),
                    "region": list(inputs[3].as_tuple()), "seed": SEED, "parts": {}, "errors": {}}
    if args.device.startswith("cuda"):
        result["gpu"] = torch.cuda.get_device_name(torch.device(args.device))
    work = Path(tempfile.mkdtemp(prefix="hgca_gpu_check_"))     # training runs: not beside the page
    t0 = time.perf_counter()

    def part(name: str, fn) -> object:
        try:
            return fn()
        except Exception as exc:          # one failing part must not lose what the others measured
            result["errors"][name] = f"{type(exc).__name__}: {exc}"
            traceback.print_exc()
            return None
        finally:
            print(f"{name}: {time.perf_counter() - t0:.0f} s", flush=True)

    timed: dict = {}
    for stage in ("coarse", "full"):
        got = part(f"complete {stage}", lambda: time_completion(inputs, stage, args.device, repeats, **steps))
        if got:
            result["parts"][f"complete_{stage}"], timed[stage] = got
    if "full" in timed:
        got = part("cpu reference", lambda: (complete_once(inputs, "full", "cpu", **steps),
                                             complete_once(inputs, "full", "cpu", seed=SEED + 1, **steps)))
        if got:
            (cpu_t, cpu_res), (_, cpu_other) = got
            result["parts"]["cpu_full_s"] = round(cpu_t["wall_s"], 3)
            result["parts"]["mesh_check"] = compare(timed["full"][0], cpu_res, cpu_other)
            if len(timed["full"]) > 1:
                result["parts"]["mesh_check"]["device_run_vs_run_cell_iou"] = round(
                    cell_iou(timed["full"][0].coarse_cells, timed["full"][1].coarse_cells), 4)
            part("plot", lambda: plot(result, timed["full"][0], cpu_res, args.out / "gpu.png"))
    packed = args.data / "train_data"
    if packed.is_dir():
        got = part("training", lambda: time_training(packed, args.device, train_steps, work, small=args.quick))
        if got:
            result["parts"]["train_coarse"] = got
    else:
        result["errors"]["training"] = f"{packed} is missing (--prepare builds it)"
    result["total_s"] = round(time.perf_counter() - t0, 1)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "gpu.json").write_text(json.dumps(result, indent=1))
    (args.out / "gpu.md").write_text(table(result))
    print(table(result))
    return 0 if not result["errors"] else 1


def plot(result: dict, dev, cpu, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(13, 5.2), gridspec_kw={"width_ratios": [1, 1.3]})
    parts = result["parts"]
    names = [k for k in ("complete_coarse", "complete_full") if k in parts]
    stages = sorted({s for k in names for s in parts[k]["stages_s"]})
    bottom = np.zeros(len(names))
    for s in stages:
        v = np.array([parts[k]["stages_s"].get(s, 0.0) for k in names])
        ax[0].bar([n.replace("complete_", "") for n in names], v, bottom=bottom, label=s)
        bottom += v
    ax[0].set_ylabel("seconds (median run)")
    ax[0].set_title(f"{result['device']}: completion of the default region")
    ax[0].legend(fontsize=8)
    a = {tuple(c) for c in dev.coarse_cells.astype(np.int64)}
    b = {tuple(c) for c in cpu.coarse_cells.astype(np.int64)}
    for cells, colour, label in ((a & b, "0.6", "both"), (a - b, "C3", f"{result['device']} only"),
                                 (b - a, "C0", "CPU only")):
        c = np.array(sorted(cells)).reshape(-1, 3)
        ax[1].scatter(c[:, 0], c[:, 1], s=0.3 if label == "both" else 2, color=colour, label=f"{label} ({len(c)})",
                      rasterized=True)
    ax[1].set_aspect("equal")
    ax[1].set_title("20 cm cells, top view (region frame): the device's against the CPU's, same seed")
    ax[1].legend(fontsize=8, markerscale=6)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=80)
    plt.close(fig)


def table(r: dict) -> str:
    m, p = r["machine"], r["parts"]
    size = " x ".join(f"{v:g}" for v in r["region"][3:6])
    what = (f"The default region ({size} m) of the synthetic drive `hgca bench` times" if r["region"][3:6] == [
        38.4, 38.4, 8.0] else f"A {size} m region")
    lines = [f"# GPU check: `{r['device']}`{' (quick: T1 = T2 = 2, one run each)' if r['quick'] else ''}", "",
             f"Machine: {r.get('gpu', 'no GPU')}, {m['cpu']} ({m['cores']} cores), torch {m['torch']}, "
             f"{m['date']}. {what}, {r['points']:,} input points, shipped weights, seed {r['seed']}. "
             f"Whole check: {r['total_s']} s.", "",
             "| completion | warm-up (s) | median of timed runs (s) | runs (s) | stages (s) | peak GPU memory (GiB) |",
             "|---|---:|---:|---|---|---:|"]
    for stage in ("coarse", "full"):
        v = p.get(f"complete_{stage}")
        if v:
            st = ", ".join(f"{k} {s:.2f}" for k, s in v["stages_s"].items())
            lines.append(f"| {stage} | {v['warmup_s']} | {v['median_s']} | {', '.join(map(str, v['wall_s']))} | "
                         f"{st} | {v.get('peak_gpu_gib', '-')} |")
    full = p.get("complete_full")
    if full and r["device"].startswith("cuda") and not r["quick"]:
        lines += ["", f"Target: the full default region in at most 2 s on an H100-class GPU; here {full['median_s']} s "
                  f"({'met' if full['median_s'] <= 2.0 else 'not met'})."]
    if "cpu_full_s" in p:
        lines += ["", f"The same full completion on this machine's CPU: {p['cpu_full_s']} s."]
    c = p.get("mesh_check")
    if c:
        lines += ["", "| mesh check (full stage) | 20 cm cells in common (IoU) | distance median (m) | p95 (m) | "
                  "max (m) | vertices |", "|---|---:|---:|---:|---:|---|"]
        for key, label in (("device_vs_cpu", f"{r['device']} vs CPU, same seed"),
                           ("cpu_seed_vs_seed_plus_1", "CPU seed vs seed + 1 (the tolerance)")):
            d = c[key]["distance_m"]
            lines.append(f"| {label} | {c[key]['cell_iou']} | {d['median']} | {d['p95']} | {d['max']} | "
                         f"{', '.join(map(str, d['vertices']))} |")
        if "device_run_vs_run_cell_iou" in c:
            lines.append(f"| {r['device']} run vs run, same seed | {c['device_run_vs_run_cell_iou']} | | | | |")
        lines += ["", f"Within tolerance (more cells in common and a smaller p95 distance than two samples): "
                  f"**{c['within_tolerance']}**. The sampler draws on the CPU on every device, so the same seed "
                  "gives the same draws; what remains is floating-point rounding."]
    t = p.get("train_coarse")
    if t:
        model = "a small model" if t["small_model"] else "the default model"
        lines += ["", f"Coarse training ({model}, {t['crop']}-cell crops, batch {t['batch']}): {t['step_s']} s a step "
                  f"(the mean of steps {t['steps_averaged']}; steps 1-10: {t['first_ten_step_s']} s; the whole run of "
                  f"{t['steps']} steps with its validation {t['run_s']} s)."]
    for name, err in r["errors"].items():
        lines += ["", f"Failed: {name}: `{err}`"]
    if (RESULTS / "gpu.png").exists() or c:
        lines += ["", "![gpu check](gpu.png)"]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    sys.exit(main())
