"""Where a sampling step's time goes: torch.profiler over GCA (coarse) or cGCA (fine) steps on the bundled example.

    python benchmarks/profile_steps.py --stage coarse|fine [--steps 4] [--threads 1] [--precision fp32|bf16]
                                       [--fine-weights hgca_core/weights/fine.pt] [--out FILE]

Runs the shipped models on the default region of the example scans (hgca_core/examples). The chain is first run
to the middle of its steps (coarse: 10 of 30; fine: a full coarse completion, then 7 of 15 fine steps), where
states are typical of most steps; then `--steps` transitions are profiled. Writes the operator table, sorted by
self CPU time, to benchmarks/results/profile_<stage>_<precision>.txt.
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import torch


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--stage", choices=("coarse", "fine"), default="coarse")
    ap.add_argument("--steps", type=int, default=4)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--precision", choices=("fp32", "bf16"), default="fp32", help="GEMM precision of the convs")
    ap.add_argument("--fine-weights", default=None)
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)

    from torch.profiler import ProfilerActivity, profile, record_function

    from hgca_core.geometry import coords as cs
    from hgca_core.geometry.region import Region
    from hgca_core.geometry.voxel import COARSE, FINE, voxelize
    from hgca_core.io.read import read_scans
    from hgca_core.models.weights import load_coarse, load_fine
    from hgca_core.models.gca import sample as gca_sample
    from hgca_core.nn.conv import gemm_precision

    ex = Path(__file__).resolve().parents[1] / "hgca_core" / "examples"
    scans = read_scans(sorted(ex.glob("*.laz")), poses=ex / "poses.json")
    region = Region.around(scans.points, sensor=scans.origins[0])
    local = region.to_local(scans.points)
    local = local[region.contains_local(local)]
    s0 = cs.with_batch(torch.from_numpy(voxelize(local, COARSE, region.size)))
    grid = region.grid_shape(COARSE)
    model, _ = load_coarse()
    gen = torch.Generator().manual_seed(0)
    dtype = torch.bfloat16 if args.precision == "bf16" else None
    with torch.no_grad(), gemm_precision(dtype):
        if args.stage == "coarse":
            bev = model.bev(s0, 1, grid)
            state = s0
            for _ in range(10):
                nbhd = model.neighbourhood(state, grid)
                state = nbhd[torch.rand(len(nbhd), generator=gen) < torch.sigmoid(model(nbhd, state, s0, grid, bev))]

            def step():
                nonlocal state
                with record_function("neighbourhood"):
                    nbhd = model.neighbourhood(state, grid)
                with record_function("kernel"):
                    logits = model(nbhd, state, s0, grid, bev)
                state = nbhd[torch.rand(len(nbhd), generator=gen) < torch.sigmoid(logits)]
                return len(state), len(nbhd)
        else:
            from hgca_core.models.cgca import initial_state

            fine, ae, _ = load_fine(args.fine_weights)
            cells = gca_sample(model, s0, grid, model.cfg.steps, gen)[:, 1:]
            grid10 = region.grid_shape(FINE)
            x0, z0 = initial_state(ae, local, cells, grid10)
            state, z = x0, z0

            def step():
                nonlocal state, z
                with record_function("neighbourhood"):
                    nbhd = fine.neighbourhood(state, grid10)
                with record_function("kernel"):
                    logits, mu = fine(nbhd, state, z, x0, z0, grid10)
                keep = torch.rand(len(nbhd), generator=gen) < torch.sigmoid(logits)   # as cgca.sample does
                state, z = nbhd[keep], mu[keep]
                z = z + fine.cfg.sigma * torch.randn(z.shape, generator=gen)
                return len(state), len(nbhd)

            for _ in range(7):
                step()
        t0 = time.perf_counter()
        with profile(activities=[ProfilerActivity.CPU], record_shapes=False) as prof:
            for _ in range(args.steps):
                n_state, n_nbhd = step()
        wall = (time.perf_counter() - t0) / args.steps
    table = prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=30)
    head = (f"{args.stage} step on the example's default region: {n_state} occupied, {n_nbhd} neighbourhood cells, "
            f"{wall:.2f} s/step (profiled, {args.threads} thread(s), {args.precision} GEMMs)\n")
    out = Path(args.out or f"benchmarks/results/profile_{args.stage}_{args.precision}.txt")
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(head + table)
    print(head + table)


if __name__ == "__main__":
    main()
