"""Our sparse conv against spconv 2.x (CPU build) on the same cells and weights, one thread.

    pip install spconv        # CPU wheel; not a dependency of hgca
    python benchmarks/spconv_compare.py [--sizes 60000 200000] [--channels 32 64]

Two cell sets: 'surface' (thin street-like surface, ~9 of 27 neighbours active; benchmarks/sparse_conv.py)
and 'shell' (the same surface dilated by one cell, like a GCA neighbourhood N(s^t), ~21 of 27 active).
For each: forward time of a 3x3x3 submanifold conv with cached maps on our pair path, our table path and
spconv; the largest difference between our output and spconv's; and whether spconv gives the same bits with
1 and 2 threads (it runs in subprocesses with OMP_NUM_THREADS set, since spconv reads it at start-up).
Writes benchmarks/results/spconv_compare.{json,md}.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from sparse_conv import GRID, RESULTS, cpu_model, surface_cells, timeit  # noqa: E402


def cells(kind: str, n: int) -> torch.Tensor:
    from hgca_core.geometry import coords as cs

    if kind == "surface":
        return surface_cells(n)
    base = surface_cells(max(n // 3, 1000))
    return cs.dilate(base, 1, bounds=GRID)[:n]


def spconv_run(kind: str, n: int, c: int, repeats: int, threads: int, out_npy: str) -> None:
    """In a subprocess: spconv forward time (process CPU time) and its output, written to out_npy."""
    import spconv.pytorch as spconv

    torch.set_num_threads(threads)
    torch.manual_seed(0)
    coords = cells(kind, n)
    feats = torch.randn(len(coords), c)
    weight = torch.randn(27, c, c) / np.sqrt(27 * c)
    conv = spconv.SubMConv3d(c, c, 3, bias=False, indice_key="k")
    with torch.no_grad():
        # spconv's weight is (cout, kx, ky, kz, cin); ours (K, cin, cout) with K lexicographic over (x, y, z)
        conv.weight.copy_(weight.reshape(3, 3, 3, c, c).permute(4, 0, 1, 2, 3))
        x = spconv.SparseConvTensor(feats, coords.int(), list(GRID), 1)
        y = conv(x)                                     # builds and caches the index pairs in x.indice_dict
        t = timeit(lambda: conv(x), repeats, clock=time.process_time if threads == 1 else time.perf_counter)
    np.save(out_npy, y.features.numpy())
    print(json.dumps(t))


def ours(coords: torch.Tensor, c: int, repeats: int) -> tuple[dict, dict, np.ndarray]:
    from hgca_core.nn import conv as cm
    from hgca_core.nn.sparse import SparseTensor, SubMConv3d

    torch.manual_seed(0)
    feats = torch.randn(len(coords), c)
    weight = torch.randn(27, c, c) / np.sqrt(27 * c)
    conv = SubMConv3d(c, c, 3)
    with torch.no_grad():
        conv.weight.copy_(weight)
        x = SparseTensor(coords, feats)
        conv(x)
        kmap = x.cache[("subm", 1, 3)][1]
        kmap.table
        saved = cm.TABLE_MIN_DENSITY
        try:
            cm.TABLE_MIN_DENSITY = 2.0
            pairs = timeit(lambda: conv(x), repeats, clock=time.process_time)
            cm.TABLE_MIN_DENSITY = 0.0
            table = timeit(lambda: conv(x), repeats, clock=time.process_time)
            out = conv(x).feats.numpy()
        finally:
            cm.TABLE_MIN_DENSITY = saved
    return {**pairs, "density": kmap.density}, table, out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[60_000, 200_000])
    ap.add_argument("--channels", type=int, nargs="+", default=[32, 64])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--out", type=Path, default=RESULTS / "spconv_compare")
    ap.add_argument("--worker", nargs=5, metavar=("KIND", "N", "C", "THREADS", "NPY"), help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.worker:
        kind, n, c, threads, npy = args.worker
        spconv_run(kind, int(n), int(c), args.repeats, int(threads), npy)
        return
    torch.set_num_threads(1)
    import importlib.util
    has_spconv = importlib.util.find_spec("spconv") is not None
    rows = []
    tmp = args.out.parent / "_spconv_tmp"
    tmp.mkdir(parents=True, exist_ok=True)
    for kind in ("surface", "shell"):
        for n in args.sizes:
            coords = cells(kind, n)
            for c in args.channels:
                pairs, table, out = ours(coords, c, args.repeats)
                row = {"cells": kind, "n": n, "c": c, "density": round(pairs.pop("density"), 3),
                       "ours_pairs_ms": pairs, "ours_table_ms": table}
                if has_spconv:
                    res = {}
                    for threads in (1, 2):
                        npy = tmp / f"sp_{threads}.npy"
                        env = {**os.environ, "OMP_NUM_THREADS": str(threads)}
                        p = subprocess.run([sys.executable, __file__, "--repeats", str(args.repeats), "--worker", kind,
                                            str(n), str(c), str(threads), str(npy)],
                                           capture_output=True, text=True, env=env)
                        if p.returncode != 0:
                            raise SystemExit(p.stderr[-2000:])
                        res[threads] = (json.loads(p.stdout.strip().splitlines()[-1]), np.load(npy))
                    row["spconv_1thread_ms"] = res[1][0]
                    row["spconv_2thread_wall_ms"] = res[2][0]
                    row["max_abs_diff_vs_spconv"] = float(np.abs(out - res[1][1]).max())
                    row["spconv_1_vs_2_threads_max_diff"] = float(np.abs(res[1][1] - res[2][1]).max())
                rows.append(row)
                print(json.dumps(row), flush=True)
    meta = {"cpu": cpu_model(), "cores": os.cpu_count(), "torch": torch.__version__, "date": time.strftime("%Y-%m-%d"),
            "repeats": args.repeats, "load_avg_after": os.getloadavg()[0]}
    if has_spconv:
        import spconv
        meta["spconv"] = getattr(spconv, "__version__", "?")
    args.out.with_suffix(".json").write_text(json.dumps({"meta": meta, "results": rows}, indent=2) + "\n")
    f = lambda v: f"{v['median']:.0f} ({v['min']:.0f})"  # noqa: E731
    lines = ["# Sparse conv vs spconv (CPU, one thread)", "",
             f"{meta['cpu']}, torch {meta['torch']}, spconv {meta.get('spconv', 'not installed')}, {meta['date']}. "
             f"3x3x3 submanifold conv, C in = C out, maps cached; CPU time of one thread in ms, median (min) of "
             f"{args.repeats}. 'density' = filled share of the (cell, offset) slots. Load average after: "
             f"{meta['load_avg_after']:.2f} (a shared machine: CPU time, not wall time, is the robust measure).", "",
             "| cells | N | C | density | ours: pairs | ours: table | spconv 1 thread | max abs diff vs spconv "
             "| spconv 1 vs 2 threads max diff |", "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        sp = (f"{f(r['spconv_1thread_ms'])} | {r['max_abs_diff_vs_spconv']:.2e} | "
              f"{r['spconv_1_vs_2_threads_max_diff']:.2e}") if "spconv_1thread_ms" in r else "n/a | n/a | n/a"
        lines.append(f"| {r['cells']} | {r['n']} | {r['c']} | {r['density']} | {f(r['ours_pairs_ms'])} | "
                     f"{f(r['ours_table_ms'])} | {sp} |")
    args.out.with_suffix(".md").write_text("\n".join(lines) + "\n")
    for p in tmp.glob("*.npy"):
        p.unlink()
    tmp.rmdir()
    print("\n".join(lines))


if __name__ == "__main__":
    main()
