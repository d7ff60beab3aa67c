"""Training throughput of one coarse run on this machine's cores (should one run take every core?):
one process with 1 thread, one process with N threads, and N gloo ranks of 1 thread each (torchrun), at the same
recipe and the same chains a step in all (the ranks split them), interleaved A B C C B A (run by hand):

    python benchmarks/train_scaling.py --data data/tiny [--steps 30] [--batch 2] [--procs 2] [--repeats 2] \
        [--out benchmarks/results/train_scaling.json]

Each run is `hgca train --recipe coarse-shipped` itself in a fresh process (the recipe that made the shipped
coarse.pt, starting from it: free space, free weight 8, cut 0.5, focus 0.5, bf16 GEMMs); its seconds are
the trainer's own summed step wall time (the run record in the run's checkpoint), so start-up and the first
chains' set-up are out, and the free-space sidecars are computed before the first run. Why: on a CPU the choice is
one run on all cores or several one-thread runs side by side, and only a measurement on the machine says which.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RECIPE = ["--recipe", "coarse-shipped", "--set", "val_every=100000", "--no-progress", "--device", "cpu"]


def command(kind: str, data: str, out: Path, steps: int, batch: int, procs: int, port: int) -> tuple[list[str], dict]:
    """The `hgca train` command line and environment of one configuration."""
    env = {**os.environ, "OMP_NUM_THREADS": "1" if kind != "threads" else str(procs)}
    train = ["train", "--data", data, "--out", str(out), "--max-steps", str(steps), "--minutes", "60", *RECIPE]
    if kind == "ranks":
        if batch % procs:
            raise ValueError(f"--batch {batch} does not split over {procs} ranks")
        return ([sys.executable, "-m", "torch.distributed.run", "--nproc_per_node", str(procs), "--master_port",
                 str(port), "-m", "hgca_core.cli", *train, "--set", f"batch={batch // procs}", "--threads", "1"], env)
    threads = procs if kind == "threads" else 1
    return [sys.executable, "-m", "hgca_core.cli", *train, "--set", f"batch={batch}", "--threads", str(threads)], env


def session(out: Path) -> dict:
    """The run's session record: steps, summed step wall time, threads, world size."""
    from hgca_core.models.weights import load_file

    return load_file(out / "ckpt.pt")["state"]["sessions"][-1]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", required=True, help="a dataset folder with a train split (hgca synth --split train)")
    p.add_argument("--steps", type=int, default=30)
    p.add_argument("--batch", type=int, default=2, help="chains a step in all (the ranks split them)")
    p.add_argument("--procs", type=int, default=os.cpu_count() or 2, help="threads, or ranks, of the wide runs")
    p.add_argument("--repeats", type=int, default=2)
    p.add_argument("--out", default=str(ROOT / "benchmarks/results/train_scaling.json"))
    p.add_argument("--print-commands", action="store_true",
                   help="print each configuration's command line and OMP_NUM_THREADS as JSON, run nothing")
    args = p.parse_args(argv)
    if args.print_commands:   # what would run, so a check (tests/metrics/test_train_scaling.py) needs no training
        try:
            shown = {k: command(k, args.data, Path(args.out).parent / k, args.steps, args.batch, args.procs, 29600)
                     for k in ("one", "threads", "ranks")}
        except ValueError as exc:
            p.error(str(exc))
        print(json.dumps({k: {"cmd": cmd, "omp": env["OMP_NUM_THREADS"]} for k, (cmd, env) in shown.items()}))
        return 0
    from hgca_core.training.data import free_cells

    for sample in sorted(Path(args.data, "train").glob("sample_*.npz")):
        free_cells(sample)   # the sidecars, once, before any timed run
    load0 = os.getloadavg()[0]
    kinds = ["one", "threads", "ranks"]
    order = [k for r in range(args.repeats) for k in (kinds if r % 2 == 0 else kinds[::-1])]
    runs = []
    with tempfile.TemporaryDirectory() as tmp:
        for i, kind in enumerate(order):
            out = Path(tmp) / f"{kind}_{i}"
            cmd, env = command(kind, args.data, out, args.steps, args.batch, args.procs, 29600 + i)
            t0 = time.perf_counter()
            res = subprocess.run(cmd, env=env, capture_output=True, text=True)
            if res.returncode != 0:
                print(res.stderr[-3000:], file=sys.stderr)
                return 1
            s = session(out)
            runs.append({"kind": kind, "steps": s["steps"], "step_wall_s": s["wall_s"], "threads": s["threads"],
                         "world_size": s["world_size"], "process_wall_s": time.perf_counter() - t0})
            print(f"{kind}: {s['steps']} steps in {s['wall_s']:.1f} s", flush=True)
    from hgca_core.hardware import machine

    info = machine()
    label = {"one": "1 process x 1 thread", "threads": f"1 process x {args.procs} threads",
             "ranks": f"{args.procs} ranks x 1 thread (gloo)"}
    summary = {}
    for kind in kinds:
        per_step = [r["step_wall_s"] / r["steps"] for r in runs if r["kind"] == kind]
        summary[kind] = {"label": label[kind], "s_per_step": statistics.median(per_step),
                         "chains_per_s": args.batch / statistics.median(per_step), "runs": len(per_step)}
    base = summary["one"]["s_per_step"]
    lines = ["# One coarse training run on 1 and on all cores", "",
             f"`benchmarks/train_scaling.py --data {args.data} --steps {args.steps} --batch {args.batch} --procs "
             f"{args.procs} --repeats {args.repeats}` ({info['date']}), {info['cpu']}, {info['cores']} cores, torch "
             f"{info['torch']}. {args.batch} chains a step in all; "
             "seconds are the trainer's summed step wall time; runs interleaved in the order below. Load average "
             f"(1 min) {load0:.1f} before the first run, {os.getloadavg()[0]:.1f} after the last.", "",
             "| configuration | runs | s / step (median) | chains / s | speed-up |", "|---|---:|---:|---:|---:|"]
    for s in summary.values():
        lines.append(f"| {s['label']} | {s['runs']} | {s['s_per_step']:.3f} | {s['chains_per_s']:.2f} | "
                     f"{base / s['s_per_step']:.2f}x |")
    each = ", ".join(f"{r['kind']} {r['step_wall_s'] / r['steps']:.3f} s/step" for r in runs)
    lines += ["", f"Runs in order: {each}", ""]
    out = Path(args.out)
    out.write_text(json.dumps({"config": vars(args), "machine": info, "runs": runs, "summary": summary}, indent=1))
    out.with_suffix(".md").write_text("\n".join(lines))
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
