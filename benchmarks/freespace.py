"""Time of the observed-free-space ray walk (`hgca_core.geometry.freespace.observed_empty`) on real sweeps.

    python benchmarks/freespace.py [--real-dir tests/data/real] [--repeats 5] [--threads 1]

Every input ray, in the default region (38.4 x 38.4 x 8 m, 192 x 192 x 40 cells of 20 cm) that `hgca complete`
and `hgca eval-real` use. The walk will also become a model input, so it should stay around a second. On a
shared machine wall time depends on the other jobs: the process CPU time (numpy runs it on one core) is the
figure to read, the wall minimum and median show what the load did. Writes
benchmarks/results/freespace.{json,md}.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

import numpy as np

INPUTS = (  # name, path under --real-dir, frames, calibration (as hgca eval-real reads them)
    ("av2_7fab2350 (2 sweeps)", "av2/7fab2350-7eaf-3b7e-a39d-6937a4c1bede", "0:2", None),
    ("av2_adcf7d18 (1 sweep)", "av2/adcf7d18-0510-35b0-a2fa-b4cea13a6d76", None,
     "av2/7fab2350-7eaf-3b7e-a39d-6937a4c1bede/calibration/egovehicle_SE3_sensor.feather"),
    ("nuScenes (1 sweep)", "nuscenes_lidar_top_1532402927647951.pcd.bin", None, None),
)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--real-dir", default=str(Path(__file__).resolve().parents[1] / "tests" / "data" / "real"))
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--threads", type=int, default=1, help="numpy is single-threaded here; kept for the record")
    p.add_argument("--out", default="benchmarks/results/freespace.json")
    args = p.parse_args()
    from hgca_core.geometry.freespace import observed_empty, ray_origins
    from hgca_core.geometry.region import Region
    from hgca_core.geometry.voxel import COARSE
    from hgca_core.metrics.real_eval import read_input

    root = Path(args.real_dir)
    rows = []
    for name, path, frames, calib in INPUTS:
        scan = read_input({"path": str(root / path), "frames": frames,
                           "calibration": None if calib is None else str(root / calib)})
        index = ray_origins(scan.origins, scan.attributes, scan.points)
        region = Region.around(scan.points, sensor=scan.origins[0])
        local, origins = region.to_local(scan.points), region.to_local(scan.origins)
        times, cpu, cells = [], [], 0
        for _ in range(args.repeats):
            t, c = time.perf_counter(), time.process_time()
            grid = observed_empty(local, origins, index, region.grid_shape(COARSE))
            times.append(time.perf_counter() - t)
            cpu.append(time.process_time() - c)
            cells = int(grid.sum())
        rows.append({"input": name, "rays": len(local), "empty_cells": cells, "cpu_min_s": min(cpu),
                     "cpu_median_s": float(np.median(cpu)), "wall_min_s": min(times),
                     "wall_median_s": float(np.median(times)), "wall_s": times, "cpu_s": cpu})
        print(f"{name}: {len(local):,} rays, {cells:,} empty cells, CPU min {min(cpu):.2f} s, "
              f"wall min {min(times):.2f} s, median {np.median(times):.2f} s")
    doc = {"machine": {"cpus": os.cpu_count(), "processor": platform.processor() or platform.machine(),
                       "load_avg_1min": os.getloadavg()[0]}, "repeats": args.repeats, "rows": rows}
    out = Path(args.out)
    out.write_text(json.dumps(doc, indent=1))
    lines = ["# Observed free space: ray walk time (default region, 20 cm cells)", "",
             f"{args.repeats} repeats on a {os.cpu_count()}-core machine shared with other jobs "
             f"(1-min load average {os.getloadavg()[0]:.1f} at the end): read the CPU time, one core.", "",
             "| input | rays | observed-empty cells | CPU min (s) | CPU median (s) | wall min (s) | wall median (s) |",
             "|---|---:|---:|---:|---:|---:|---:|"]
    lines += [f"| {r['input']} | {r['rays']:,} | {r['empty_cells']:,} | {r['cpu_min_s']:.2f} | "
              f"{r['cpu_median_s']:.2f} | {r['wall_min_s']:.2f} | {r['wall_median_s']:.2f} |" for r in rows]
    out.with_suffix(".md").write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
