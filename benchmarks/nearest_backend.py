"""Nearest-neighbour backends side by side on a real-sized case: pykdtree (`geometry.nearest.PointIndex`) and
scipy's cKDTree, timed in one run on the same queries, with their answers compared.

Reference: the bundled example's five scans (world frame). Queries: as many points as a default region's
decimated full-stage mesh has vertices (0.5 M): half on the scanned surface (each input point jittered by up
to 10 cm), half uniform in the 38.4 x 38.4 x 8 m region around the first sensor, metres from any input point,
where a completion's generated vertices lie. Writes benchmarks/results/nearest_backend.{json,md,png}.

    python benchmarks/nearest_backend.py [--repeats 3] [--threads 2]
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

RESULTS = Path(__file__).resolve().parent / "results"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--queries", type=int, default=500_000)
    args = ap.parse_args()
    os.environ["OMP_NUM_THREADS"] = str(args.threads)

    import hgca_core
    from hgca_core.geometry.region import default_region
    from hgca_core.io import read_scans
    from hgca_core.io.poses import load_poses
    from pykdtree.kdtree import KDTree
    from scipy.spatial import cKDTree

    example = Path(hgca_core.__file__).parent / "examples"
    scans = [str(example / e.file) for e in load_poses(example / "poses.json")]
    scan = read_scans(scans, poses=str(example / "poses.json"))
    ref = np.ascontiguousarray(scan.points, dtype=np.float64)
    region = default_region(ref, scan.origins)
    rng = np.random.default_rng(0)
    half = args.queries // 2
    near = ref[rng.integers(0, len(ref), half)] + rng.uniform(-0.1, 0.1, (half, 3))
    far = region.to_world(rng.uniform(0, 1, (args.queries - half, 3)) * region.size)
    queries = np.ascontiguousarray(np.concatenate([near, far]))

    def pyk():
        return KDTree(ref).query(queries, k=1)

    def scipy():
        return cKDTree(ref).query(queries, k=1, workers=args.threads)

    times = {"pykdtree": [], "scipy cKDTree": []}
    answers = {}
    for _ in range(args.repeats):          # interleaved, so both see the same machine load
        for name, fn in (("pykdtree", pyk), ("scipy cKDTree", scipy)):
            t = time.perf_counter()
            answers[name] = fn()
            times[name].append(time.perf_counter() - t)
    (dp, ip), (ds, is_) = answers["pykdtree"], answers["scipy cKDTree"]
    exact = np.sqrt(((queries - ref[is_]) ** 2).sum(1))
    result = {
        "reference_points": int(len(ref)), "queries": int(len(queries)), "threads": args.threads,
        "seconds": {k: [round(v, 4) for v in t] for k, t in times.items()},
        "median_s": {k: round(float(np.median(t)), 4) for k, t in times.items()},
        "max_abs_distance_difference_m": float(np.abs(dp - ds).max()),
        "different_indices": int((ip.astype(np.int64) != is_).sum()),
        "different_indices_at_unequal_distance": int(((ip.astype(np.int64) != is_) & (dp != ds)).sum()),
        "max_abs_difference_to_recomputed_m": {"pykdtree": float(np.abs(dp - exact).max()),
                                               "scipy cKDTree": float(np.abs(ds - exact).max())},
    }
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "nearest_backend.json").write_text(json.dumps(result, indent=1) + "\n")
    ratio = result["median_s"]["scipy cKDTree"] / result["median_s"]["pykdtree"]
    md = ["# Nearest-neighbour backend: pykdtree vs scipy cKDTree", "",
          f"{len(ref):,} reference points (the bundled example's five scans), {len(queries):,} queries (half "
          f"within 10 cm of the scans, half uniform in the default region), k = 1, {args.threads} threads, "
          f"{args.repeats} interleaved repeats, build + query, on a machine shared with other jobs. "
          f"`python benchmarks/nearest_backend.py {' '.join(sys.argv[1:])}`.".replace(" `.", "`."), "",
          "| backend | median (s) | runs (s) |", "|---|---|---|"]
    md += [f"| {k} | {result['median_s'][k]:.3f} | {', '.join(f'{v:.3f}' for v in t)} |" for k, t in times.items()]
    md += ["", f"scipy / pykdtree time: {ratio:.2f}. Largest distance difference between the two: "
           f"{result['max_abs_distance_difference_m']:.3g} m; queries answered with another index: "
           f"{result['different_indices']} ({result['different_indices_at_unequal_distance']} of them at an "
           "unequal distance, the rest ties).", "", "![times](nearest_backend.png)", ""]
    (RESULTS / "nearest_backend.md").write_text("\n".join(md))
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5, 2.6))
    names = list(times)
    for i, n in enumerate(names):
        ax.scatter(times[n], [i] * len(times[n]), color="grey", s=12, zorder=3)
        ax.barh(i, result["median_s"][n], color=("tab:blue", "tab:orange")[i], alpha=0.7)
    ax.set_yticks(range(len(names)), names)
    ax.set_xlabel(f"build + query of {len(queries):,} points (s)")
    ax.set_title(f"{len(ref):,} reference points, {args.threads} threads", fontsize=9)
    fig.tight_layout()
    fig.savefig(RESULTS / "nearest_backend.png", dpi=110)
    print("\n".join(md))


if __name__ == "__main__":
    main()
