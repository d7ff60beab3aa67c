"""Time and size of synthetic samples: one-core time per sample (wall and CPU), bytes on disk per array,
and what the files would weigh stored smaller.

    OMP_NUM_THREADS=1 python benchmarks/synth_samples.py [--seeds 10] [--start 0] [--out benchmarks/results]

Each seed is one `make_sample` at the dataset's default quality (its own profile and scan count), in this
one process. CPU time is this process's (the machine may be shared: wall time then runs longer). Sizes:
the .npz as `save_sample` writes it, per array compressed, and two smaller encodings measured on the same
arrays: (a) point coordinates as uint16 multiples of the 1/1024 m quantum they are already rounded to
(lossless) and cell coordinates as sorted int32 keys, delta-encoded; (b) only what training reads.
Writes synth_samples.md and .json.
"""
from __future__ import annotations

import argparse
import io
import json
import sys
import time
import zipfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
TRAINING = ("region", "input_points", "gt_occ20", "gt_occ10", "gt_surface", "udf_points", "udf_dist", "visible20")
POINTS = ("input_points", "gt_surface", "udf_points", "eval_scan_0", "eval_scan_1")
CELLS = ("gt_occ20", "gt_occ10", "visible20")


def npz_bytes(arrays: dict) -> int:
    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    return len(buf.getvalue())


def smaller(sample: dict, quantum: float = 1.0 / 1024) -> dict:
    """Lossless re-encoding: uint16 point coordinates, delta-coded int32 cell keys, udf_dist as uint16."""
    out = {}
    for k, v in sample.items():
        if k in POINTS:
            out[k] = np.asfortranarray(np.round(np.asarray(v, dtype=np.float64) / quantum).astype(np.uint16))
        elif k in CELLS:
            c = np.asarray(v, dtype=np.int64)
            key = np.sort((c[:, 0] * 1024 + c[:, 1]) * 1024 + c[:, 2])
            out[k] = np.diff(key, prepend=0).astype(np.int32)
        elif k == "udf_dist":
            out[k] = np.round(np.asarray(v, dtype=np.float64) / (quantum / 4)).astype(np.uint16)
        else:
            out[k] = v
    return out


def coarse_only(sample: dict) -> dict:
    """What the coarse stage's training reads, as cells: the input voxelised to 20 cm the way training does
    it, the 20 cm ground truth and the visible cells, each as delta-coded sorted int32 keys."""
    from hgca_core.geometry.voxel import COARSE, voxelize

    cells = {"s0": voxelize(sample["input_points"], COARSE, np.asarray(sample["region"])[3:6]), "gt_occ20": sample["gt_occ20"],
             "visible20": sample["visible20"]}
    return {"region": sample["region"], **{k: smaller({"gt_occ20": v})["gt_occ20"] for k, v in cells.items()}}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--start", type=int, default=0)
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "results"))
    args = ap.parse_args()
    from hgca_core.dataset.samples import save_sample
    from hgca_core.synth.dataset import make_sample

    rows = []
    tmp = Path(args.out) / ".synth_samples_tmp.npz"
    Path(args.out).mkdir(parents=True, exist_ok=True)
    for seed in range(args.start, args.start + args.seeds):
        w0, c0 = time.perf_counter(), time.process_time()
        s = make_sample(seed)
        wall, cpu = time.perf_counter() - w0, time.process_time() - c0
        save_sample(tmp, s)
        with zipfile.ZipFile(tmp) as z:
            per = {i.filename[:-4]: i.compress_size for i in z.infolist()}
        meta = json.loads(str(s["meta"]))
        rows.append({"seed": seed, "profile": meta["profile"], "n_scans": meta["n_scans"], "style": meta["style"],
                     "ground": meta["layout"]["ground"]["kind"], "wall_s": wall, "cpu_s": cpu,
                     "bytes": tmp.stat().st_size, "per_array": per,
                     "bytes_smaller": npz_bytes(smaller(s)),
                     "bytes_training": npz_bytes({k: s[k] for k in TRAINING}),
                     "bytes_training_smaller": npz_bytes({k: v for k, v in smaller(s).items() if k in TRAINING}),
                     "bytes_coarse_cells": npz_bytes(coarse_only(s)),
                     "input_points": int(len(s["input_points"]))})
        print(json.dumps({k: v for k, v in rows[-1].items() if k != "per_array"}), flush=True)
    tmp.unlink(missing_ok=True)
    cpu = np.array([r["cpu_s"] for r in rows])
    wall = np.array([r["wall_s"] for r in rows])
    size = np.array([r["bytes"] for r in rows])
    keys = list(rows[0]["per_array"])
    mean_arr = {k: float(np.mean([r["per_array"].get(k, 0) for r in rows])) for k in keys}
    mib = 2**20
    lines = ["# Synthetic samples: time and size", "",
             f"Measured by `benchmarks/synth_samples.py` ({time.strftime('%Y-%m-%d')}), seeds {args.start}-"
             f"{args.start + args.seeds - 1}, default quality, one process with OMP_NUM_THREADS=1 on a shared "
             "2-core machine (CPU time is the one-core cost; wall time includes waiting for the core).", "",
             "| seed | profile | scans | style | ground | input points | CPU (s) | wall (s) | file (MB) |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['seed']} | {r['profile']} | {r['n_scans']} | {r['style']} | {r['ground']} | "
                     f"{r['input_points']:,} | {r['cpu_s']:.1f} | {r['wall_s']:.1f} | {r['bytes'] / 1e6:.2f} |")
    lines += ["", f"CPU time per sample: median {np.median(cpu):.1f} s, max {cpu.max():.1f} s "
              f"(wall: median {np.median(wall):.1f} s, max {wall.max():.1f} s).",
              f"File size: median {np.median(size) / 1e6:.2f} MB, mean {size.mean() / 1e6:.2f} MB: "
              f"200 samples take {200 * size.mean() / mib:.0f} MiB.", "",
              "| array | mean compressed bytes | share |", "|---|---|---|"]
    for k in sorted(mean_arr, key=mean_arr.get, reverse=True):
        lines.append(f"| {k} | {mean_arr[k]:,.0f} | {mean_arr[k] / sum(mean_arr.values()):.0%} |")
    for label, key in (("all arrays, lossless smaller encoding (uint16 points, delta int32 cell keys)", "bytes_smaller"),
                       ("only the arrays training reads", "bytes_training"),
                       ("only the arrays training reads, smaller encoding", "bytes_training_smaller"),
                       ("coarse stage only: input, ground truth and visible cells at 20 cm as delta keys",
                        "bytes_coarse_cells")):
        b = np.mean([r[key] for r in rows])
        lines.append(f"\n{label}: mean {b / 1e6:.2f} MB per sample, 200 samples {200 * b / mib:.0f} MiB.")
    text = "\n".join(lines) + "\n"
    (Path(args.out) / "synth_samples.md").write_text(text)
    (Path(args.out) / "synth_samples.json").write_text(json.dumps(rows, indent=1))
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
