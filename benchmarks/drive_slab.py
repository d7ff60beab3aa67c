"""The 1 km drive's worst slab without tiles (run by hand): is a weak slab the tiling's or the model's?

    .venv/bin/python benchmarks/drive_slab.py [--x 182] [--seeds 7,0,1,2] [--length 400]

Builds the start of `benchmarks/drive.py`'s long drive (the same street, scanner and seed: its first scans are
the long drive's), completes one 38.4 m region centred on the slab at `--x` from the 5 scans nearest it (`--scans-per-tile`), no
neighbours, no ownership cut (stage coarse, T1 = the drive page's), once per seed (seed 7 is the one tile 7 of
the long drive had there), and scores every 4 m slab it covers as `drive_scores.seam_scores` does (recall of the
20 cm ground-truth cells, the long drive's slab grid). Results: benchmarks/results/drive_slab.{json,png}; the
drive page (`drive.py --page-only`) shows them beside the tiled figures of the same slabs.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from hgca_core.config import DriveConfig
from hgca_core.io.digest import file_digest
from hgca_core.tiling.inputs import read_drive_inputs
from hgca_core.tiling.plan import HEADING_SPAN, TilePlan, Trajectory, tile_region
from hgca_core.tiling.tile import Settings, TileJob, complete_tile, weight_files

sys.path.insert(0, str(Path(__file__).resolve().parent))
from drive import SCENE, build_drive, ground_truth, scenes  # noqa: E402
from drive_scores import SLAB, scored_cells  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
TILE = 38.4


def slab_recall(pred: np.ndarray, gt: np.ndarray, region, edges: np.ndarray) -> np.ndarray:
    """Recall of the ground-truth cells per slab of world x (`edges`), as the drive's seam table counts it."""
    w, in_p, in_g = scored_cells(pred, gt, region)
    x = w[:, 0]
    return np.histogram(x[in_p & in_g], edges)[0] / np.maximum(np.histogram(x[in_g], edges)[0], 1)


def plot(r: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(9, 3.6))
    x = np.array(r["slab_x"])
    for run in r["untiled"]:
        ax.plot(x, run["slab_recall"], ".-", lw=0.8, alpha=0.7, label=f"one region, seed {run['seed']}")
    ax.plot(x, r["tiled_recall"], "ks-", lw=1.2, label="the 1 km drive's tiles (seed 7 there)")
    ax.axhline(r["drive_median"], color="0.5", ls=":", label="drive's median slab")
    ax.axhline(0.8 * r["drive_median"], color="C3", ls="--", lw=0.8, label="0.8 x median")
    ax.axvspan(r["x"] - SLAB / 2, r["x"] + SLAB / 2, color="C3", alpha=0.1)
    ax.set_xlabel("x along the drive (m)")
    ax.set_ylabel("recall per 4 m slab")
    ax.set_ylim(0, 1)
    ax.set_title(f"a {TILE} m region centred on x = {r['x']:g} m, completed alone, against the drive's tiles")
    ax.legend(fontsize=7, ncol=2, loc="lower left")
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--x", type=float, default=None, help="slab centre (m; default: the drive page's worst)")
    ap.add_argument("--seeds", default="7,0,1,2")
    ap.add_argument("--length", type=float, default=400.0, help="metres of the long drive to build")
    ap.add_argument("--scans-per-tile", type=int, default=5, help="scans nearest the region's centre it takes")
    ap.add_argument("--name", default="drive_slab", help="results file name (.json, .png)")
    ap.add_argument("--work", type=Path, default=Path("/tmp/hgca_drive_memory"))
    ap.add_argument("--results", type=Path, default=REPO / "benchmarks" / "results")
    args = ap.parse_args()
    page = json.loads((args.results / "drive.json").read_text())
    seams, long_m = page["seams"], page["drives"]["long"]["length_m"]
    x_at = args.x if args.x is not None else seams["slabs"]["recall"]["at_x"]
    folder = args.work / f"scans_{args.length:g}"
    if not (folder / "poses.json").is_file():
        build_drive(folder, args.length, page["spacing_m"])
    scans = read_drive_inputs(sorted(folder.glob("scan_*.npz")), folder / "poses.json")
    pos = np.array([s.position for s in scans])
    path = Trajectory(pos)
    arc = float(np.interp(x_at, pos[:, 0], path.s))
    centre = path.position(arc)
    near = tuple(int(j) for j in np.sort(np.argsort(np.linalg.norm(pos[:, :2] - centre[:2], axis=1),
                                                     kind="stable")[:args.scans_per_tile]))
    region = tile_region(TilePlan(0, arc, centre[:2], path.heading(arc, TILE * HEADING_SPAN), near),
                         np.concatenate([scans[i].points for i in near]), (TILE, TILE, 8.0))
    gt = ground_truth(region, scenes(int(np.ceil((long_m + 4.0 - 116.0) / SCENE)) + 1))
    grid = np.array(seams["slab_x"])
    keep = np.abs(grid - region.center[0]) < TILE / 2 - SLAB / 2
    x = grid[keep]
    edges = np.r_[x - SLAB / 2, x[-1] + SLAB / 2]
    cfg = DriveConfig().with_(stage="coarse", t1=page["t1"], threads=1)
    digests = tuple(file_digest(p) for p in weight_files("coarse", None, None))
    out = {"x": x_at, "region": list(region.as_tuple()), "scans": list(near), "t1": page["t1"],
           "scans_per_tile": args.scans_per_tile,
           "slab_x": x.tolist(), "tiled_recall": np.array(seams["slab_recall"])[keep].tolist(),
           "drive_median": seams["slabs"]["recall"]["median"], "untiled": []}
    for seed in (int(s) for s in args.seeds.split(",")):
        t = time.perf_counter()
        c = cfg.completion.with_(seed=seed)
        job = TileJob(0, region.as_tuple(), near, tuple(scans[i].digest() for i in near), seed, Settings.of(c, 1),
                      digests, ())
        cells = complete_tile(job, [scans[i] for i in near], [])["samples"][0]["cells"].astype(np.int64)
        out["untiled"].append({"seed": seed, "slab_recall": slab_recall(cells, gt, region, edges).round(4).tolist(),
                               "s": round(time.perf_counter() - t, 1)})
        print(json.dumps(out["untiled"][-1]), flush=True)
    at = int(np.argmin(np.abs(x - x_at)))
    vals = [r["slab_recall"][at] for r in out["untiled"]]
    out["at_slab"] = {"tiled": out["tiled_recall"][at], "untiled_median": round(float(np.median(vals)), 4),
                      "untiled_min": min(vals), "untiled_max": max(vals),
                      "untiled_median_over_drive_median": round(float(np.median(vals)) / out["drive_median"], 3)}
    (args.results / f"{args.name}.json").write_text(json.dumps(out, indent=1))
    plot(out, args.results / f"{args.name}.png")
    print(json.dumps(out["at_slab"]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
