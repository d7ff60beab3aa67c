"""bf16 against fp32 GEMMs for training (issue 13, item 4): step time and gradient agreement on real chains.

    python benchmarks/train_precision.py --data /work/data/synth2 [--weights checkpoints/coarse_fs.pt]
        [--examples 6] [--repeats 3] [--threads 1,2] [--out benchmarks/results/train_precision.json]

Builds coarse training chains from the train split as `hgca train coarse` does (crop 64, batch 2), advances each
10 infusion steps so its state is a typical mid-chain one, then times one training step's forward + backward
(the optimiser's share is the same in both) in fp32 and in bf16 (`nn.conv.training_precision`), interleaved
A/B/A/B so a shared machine's load hits both alike, and reports the relative difference of the loss and of
every gradient. Writes JSON and a markdown table beside it.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

import numpy as np
import torch


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", required=True)
    ap.add_argument("--weights", default="checkpoints/coarse_fs.pt")
    ap.add_argument("--examples", type=int, default=6)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--threads", default="1,2")
    ap.add_argument("--out", default="benchmarks/results/train_precision.json")
    args = ap.parse_args()

    from hgca_core.hardware import cpu_name
    from hgca_core.models.gca import GCAConfig
    from hgca_core.models.weights import load_file, load_into
    from hgca_core.nn.conv import training_precision
    from hgca_core.training.coarse import CoarseTask

    cfg = GCAConfig.from_dict(load_file(args.weights)["config"])
    task = CoarseTask(args.data, cfg, crop=64)
    module = task.build()
    load_into(module.model, args.weights)
    module.train()
    rng = np.random.default_rng(0)
    torch.manual_seed(0)
    batches = []
    for _ in range(args.examples):
        chains = [task.new_example(rng) for _ in range(2)]
        with torch.no_grad():
            for t in range(10):                      # a typical mid-chain state
                _, _, states = module(chains)
                for c, s in zip(chains, states):
                    c.state, c.t = s, t + 1
        batches.append(chains)

    def step(chains, dtype) -> tuple[float, float, list[torch.Tensor]]:
        module.zero_grad(set_to_none=True)
        torch.manual_seed(1)                         # the same Bernoulli draws in both precisions
        t0 = time.perf_counter()
        with training_precision(dtype):
            loss, _, _ = module(chains)
            loss.backward()
        dt = time.perf_counter() - t0
        return dt, float(loss.detach()), [p.grad.detach().clone() for p in module.parameters() if p.grad is not None]

    rows = []
    for threads in (int(t) for t in args.threads.split(",")):
        torch.set_num_threads(threads)
        times = {"fp32": [], "bf16": []}
        loss_rel, grad_rel = [], []
        for chains in batches:
            step(chains, None)                       # warm the kernel-map caches of this batch
            for _ in range(args.repeats):
                t32, l32, g32 = step(chains, None)
                t16, l16, g16 = step(chains, torch.bfloat16)
                times["fp32"].append(t32)
                times["bf16"].append(t16)
            loss_rel.append(abs(l16 - l32) / abs(l32))
            num = torch.sqrt(sum((a - b).pow(2).sum() for a, b in zip(g16, g32)))
            den = torch.sqrt(sum(b.pow(2).sum() for b in g32))
            grad_rel.append(float(num / den))
        rows.append({"threads": threads, "fp32_s": float(np.median(times["fp32"])),
                     "bf16_s": float(np.median(times["bf16"])),
                     "speedup": float(np.median(times["fp32"]) / np.median(times["bf16"])),
                     "loss_rel_diff_max": float(max(loss_rel)), "grad_rel_diff_max": float(max(grad_rel)),
                     "grad_rel_diff_mean": float(np.mean(grad_rel))})
        print(json.dumps(rows[-1]))
    info = {"rows": rows, "cpu": cpu_name(), "machine": platform.machine(), "torch": torch.__version__,
            "bf16_native": bool(torch.ops.mkldnn._is_mkldnn_bf16_supported()), "weights": args.weights,
            "data": args.data, "examples": args.examples, "repeats": args.repeats,
            "load_average": os.getloadavg()}
    out = Path(args.out)
    out.write_text(json.dumps(info, indent=1))
    lines = ["# Training GEMMs: bf16 against fp32", "",
             f"One coarse training step (forward + backward, batch 2, crop 64, chains 10 steps in) of "
             f"`{args.weights}` on {args.examples} batches from `{args.data}`, {args.repeats} interleaved repeats "
             f"each; median seconds. CPU: {info['cpu']} (native bf16: {info['bf16_native']}), torch "
             f"{info['torch']}; load average at the end {info['load_average'][0]:.1f} (shared machine).", "",
             "| threads | fp32 s/step | bf16 s/step | speedup | loss rel. diff (max) | gradient rel. diff (mean / max) |",
             "|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        lines.append(f"| {r['threads']} | {r['fp32_s']:.3f} | {r['bf16_s']:.3f} | {r['speedup']:.2f}x | "
                     f"{r['loss_rel_diff_max']:.2e} | {r['grad_rel_diff_mean']:.2e} / {r['grad_rel_diff_max']:.2e} |")
    out.with_suffix(".md").write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
