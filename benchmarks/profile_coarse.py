"""Where the coarse sampling time goes: torch.profiler over a few GCA steps on the bundled example.

    python benchmarks/profile_coarse.py [--steps 5] [--threads 1] [--out benchmarks/results/profile_coarse.txt]

Runs the shipped coarse model on the default region of the example scans (hgca_core/examples), first a
warm-up step, then `--steps` profiled transitions; writes the operator table sorted by self CPU time.
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import torch


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=5)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--precision", choices=("fp32", "bf16"), default="fp32", help="GEMM precision of the convs")
    ap.add_argument("--out", default="benchmarks/results/profile_coarse.txt")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)

    from hgca_core.geometry import coords as cs
    from hgca_core.geometry.region import Region
    from hgca_core.geometry.voxel import COARSE, FINE, voxelize_coarse
    from hgca_core.io.read import read_scans
    from hgca_core.models.checkpoint import WEIGHTS_DIR, load_coarse

    ex = Path(__file__).resolve().parents[1] / "hgca_core" / "examples"
    scans = read_scans(sorted(ex.glob("*.laz")), poses=ex / "poses.json")
    region = Region.around(scans.points, sensor=scans.origins[0])
    local = region.to_local(scans.points)
    s0 = cs.with_batch(torch.from_numpy(voxelize_coarse(local[region.contains_local(local)], region.grid_shape(FINE))))
    grid = region.grid_shape(COARSE)
    model, _ = load_coarse(str(WEIGHTS_DIR / "coarse.pt"))
    gen = torch.Generator().manual_seed(0)
    with torch.no_grad():
        bev = model.bev(s0, 1, grid)
        state = s0
        # run the chain to the middle, where states are typical of most steps
        for _ in range(10):
            nbhd = model.neighbourhood(state, grid)
            state = nbhd[torch.rand(len(nbhd), generator=gen) < torch.sigmoid(model(nbhd, state, s0, grid, bev))]
        from torch.profiler import ProfilerActivity, profile, record_function

        from hgca_core.nn.conv import gemm_precision

        t0 = time.perf_counter()
        with gemm_precision(torch.bfloat16 if args.precision == "bf16" else None), \
                profile(activities=[ProfilerActivity.CPU], record_shapes=False) as prof:
            for _ in range(args.steps):
                with record_function("neighbourhood"):
                    nbhd = model.neighbourhood(state, grid)
                with record_function("kernel"):
                    logits = model(nbhd, state, s0, grid, bev)
                state = nbhd[torch.rand(len(nbhd), generator=gen) < torch.sigmoid(logits)]
        wall = (time.perf_counter() - t0) / args.steps
    table = prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=30)
    head = (f"coarse step on the example's default region: {len(state)} occupied, {len(nbhd)} neighbourhood cells, "
            f"{wall:.2f} s/step (profiled, {args.threads} thread(s), {args.precision} GEMMs)\n")
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(head + table)
    print(head + table)


if __name__ == "__main__":
    main()
