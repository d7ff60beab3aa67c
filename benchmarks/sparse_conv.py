"""Sparse conv speed on CPU: SubMConv3d / strided SparseConv3d vs dense nn.Conv3d on the bounding grid.

Active cells are surface-like (a wavy ground plane plus building facades in a 384 x 384 x 80 grid, the
default 10 cm region), cut to exactly N cells as a spatially contiguous slab. Writes
benchmarks/results/sparse_conv.json and .md. Run: .venv/bin/python benchmarks/sparse_conv.py
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import time
from pathlib import Path
from typing import Callable

import torch

from hgca_core.geometry.coords import pack, unique
from hgca_core.nn.kernel_map import downsample_map, submanifold_map
from hgca_core.nn.sparse import SparseConv3d, SparseTensor, SubMConv3d
from hgca_core.nn.unet import SparseUNet

GRID = (384, 384, 80)
RESULTS = Path(__file__).resolve().parent / "results"


def surface_cells(n: int) -> torch.Tensor:
    """Exactly n cells of a street-like surface set (ground + facades), sorted, batch 0."""
    sx, sy, sz = GRID
    xs, ys = torch.meshgrid(torch.arange(sx), torch.arange(sy), indexing="ij")
    gz = (10 + 3 * torch.sin(xs / 40.0) * torch.cos(ys / 55.0)).round().long()
    parts = [torch.stack([xs, ys, gz], -1).reshape(-1, 3)]
    fy, fz = torch.meshgrid(torch.arange(sy), torch.arange(12, 64), indexing="ij")
    for x0 in (60, 150, 250, 330):            # facades along y
        parts.append(torch.stack([torch.full_like(fy, x0), fy, fz], -1).reshape(-1, 3))
    fx, fz = torch.meshgrid(torch.arange(sx), torch.arange(12, 50), indexing="ij")
    for y0 in (100, 290):                     # facades along x
        parts.append(torch.stack([fx, torch.full_like(fx, y0), fz], -1).reshape(-1, 3))
    c = torch.cat(parts)
    c = torch.cat([torch.zeros(len(c), 1, dtype=torch.long), c], 1)
    c = unique(c)                             # x-major order: the first n cells form a slab
    if n > len(c):
        raise ValueError(f"scene has only {len(c)} cells")
    return c[:n]


def timeit(fn: Callable[[], object], repeats: int, warmup: int = 1,
           clock: Callable[[], float] = time.perf_counter) -> dict[str, float]:
    """Median and minimum time in ms (wall clock by default); the minimum shows the quiet-machine cost."""
    for _ in range(warmup):
        fn()
    ts = []
    for _ in range(repeats):
        t0 = clock()
        fn()
        ts.append(clock() - t0)
    return {"median": statistics.median(ts) * 1e3, "min": min(ts) * 1e3}


def _cpu_idle_fraction(seconds: float) -> float:
    """Share of CPU time idle over the next `seconds` (Linux /proc/stat; 1.0 where unavailable)."""
    def read() -> tuple[int, int]:
        vals = [int(v) for v in Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:]]
        return vals[3] + vals[4], sum(vals)
    try:
        i0, t0 = read()
        time.sleep(seconds)
        i1, t1 = read()
    except (OSError, ValueError, IndexError):
        return 1.0
    return (i1 - i0) / max(1, t1 - t0)


def wait_idle(max_wait_s: float, threshold: float = 0.8) -> float:
    """On a shared machine, wait (at most max_wait_s) until other jobs leave the CPU mostly idle."""
    deadline = time.monotonic() + max_wait_s
    idle = _cpu_idle_fraction(2.0)
    while idle < threshold and time.monotonic() < deadline:
        idle = _cpu_idle_fraction(5.0)
    return idle


def cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def bench_sparse(coords: torch.Tensor, c: int, repeats: int) -> dict[str, object]:
    feats = torch.randn(len(coords), c)
    conv = SubMConv3d(c, c, 3)
    down = SparseConv3d(c, c, 2, 2)
    keys = pack(coords)
    res: dict[str, object] = {}
    res["map_build_subm_ms"] = timeit(lambda: submanifold_map(keys, 3, 1), repeats)
    res["map_build_down_ms"] = timeit(lambda: downsample_map(coords, 1, 2), repeats)
    x = SparseTensor(coords, feats)
    conv(x)                                   # build and cache the maps (shared by all layers of a level)
    down(x)
    kmap = x.cache[("subm", 1, 3)][1]
    res["pairs_per_cell"] = kmap.num_pairs / len(coords)
    with torch.no_grad():
        res["subm_fwd_ms"] = timeit(lambda: conv(x), repeats)
        res["down_fwd_ms"] = timeit(lambda: down(x), repeats)
    xg = x.replace_feats(feats.clone().requires_grad_(True))

    def fwd_bwd(layer: torch.nn.Module) -> None:
        layer.zero_grad(set_to_none=True)
        layer(xg).feats.sum().backward()

    res["subm_fwd_bwd_ms"] = timeit(lambda: fwd_bwd(conv), repeats)
    res["down_fwd_bwd_ms"] = timeit(lambda: fwd_bwd(down), repeats)
    # CPU time of one thread: nearly insensitive to other jobs on a shared machine
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        with torch.no_grad():
            res["subm_fwd_cpu1_ms"] = timeit(lambda: conv(x), repeats, clock=time.process_time)
        res["subm_fwd_bwd_cpu1_ms"] = timeit(lambda: fwd_bwd(conv), repeats, clock=time.process_time)
    finally:
        torch.set_num_threads(threads)
    return res


def bench_unet(coords: torch.Tensor, repeats: int) -> dict[str, object]:
    """Default SparseUNet (channels 32..128, 4 levels), 4 input features, fresh coords every call
    (maps rebuilt, as in a GCA step) vs. reused coords (maps cached)."""
    net = SparseUNet(4, 2)
    feats = torch.randn(len(coords), 4)
    res: dict[str, object] = {}
    with torch.no_grad():
        res["unet_fwd_new_coords_ms"] = timeit(lambda: net(SparseTensor(coords, feats, check=False)), repeats)
        x = SparseTensor(coords, feats)
        res["unet_fwd_cached_ms"] = timeit(lambda: net(x), repeats)

    def fwd_bwd() -> None:
        net.zero_grad(set_to_none=True)
        net(SparseTensor(coords, feats, check=False)).feats.square().mean().backward()

    res["unet_fwd_bwd_new_coords_ms"] = timeit(fwd_bwd, repeats)
    return res


def bench_dense(coords: torch.Tensor, c: int, repeats: int, mem_cap_gb: float) -> dict[str, object]:
    lo = coords[:, 1:].min(0).values
    hi = coords[:, 1:].max(0).values
    shape = [int(v) for v in (hi - lo + 1)]
    vox = shape[0] * shape[1] * shape[2]
    # forward+backward holds input, output and both their gradients (+ oneDNN workspace ~ 1 more)
    need_gb = 5 * vox * c * 4 / 1e9
    out: dict[str, object] = {"dense_grid": shape, "dense_need_gb": round(need_gb, 2)}
    if need_gb > mem_cap_gb:
        out["dense_fwd_ms"] = out["dense_fwd_bwd_ms"] = f"n/a: would need {need_gb:.1f} GB"
        return out
    dense = torch.nn.Conv3d(c, c, 3, padding=1, bias=False)
    grid = torch.zeros(1, c, *shape)
    rel = coords[:, 1:] - lo
    grid[0, :, rel[:, 0], rel[:, 1], rel[:, 2]] = torch.randn(c, len(coords))
    with torch.no_grad():
        out["dense_fwd_ms"] = timeit(lambda: dense(grid), repeats)
    g = grid.requires_grad_(True)

    def fwd_bwd() -> None:
        dense.zero_grad(set_to_none=True)
        g.grad = None
        dense(g).sum().backward()

    out["dense_fwd_bwd_ms"] = timeit(fwd_bwd, repeats)
    return out


def to_markdown(meta: dict, rows: list[dict], unet_rows: list[dict]) -> str:
    def f(v: object) -> str:
        if isinstance(v, dict):
            return f"{v['median']:.0f} ({v['min']:.0f})"
        return f"{v:.0f}" if isinstance(v, float) else str(v)

    lines = [
        "# Sparse conv benchmark (CPU)",
        "",
        f"{meta['cpu']}, {meta['threads']} threads ({meta['cores']} cores visible), torch {meta['torch']}, "
        f"{meta['date']}, OMP_WAIT_POLICY={meta['omp_wait_policy']}. Times in ms: median (minimum) of "
        f"{meta['repeats']} runs (dense: {meta['dense_repeats']}, U-Net: {meta['unet_repeats']}).",
        "Surface-like cells (wavy ground + facades in a 384x384x80 grid), 3x3x3 submanifold and 2x2x2 "
        "stride-2 convs, C in = C out. Map build = kernel-map construction for new coordinates "
        "(cached afterwards, shared by every layer of a level).",
        "",
        "| N | C | pairs/cell | map subm | map down | SubM fwd | SubM fwd+bwd | down fwd | down fwd+bwd "
        "| dense 3x3x3 fwd | dense fwd+bwd | dense grid | SubM fwd, 1-thread CPU | SubM fwd+bwd, 1-thread CPU |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['n']} | {r['c']} | {r['pairs_per_cell']:.1f} | {f(r['map_build_subm_ms'])} | "
            f"{f(r['map_build_down_ms'])} | {f(r['subm_fwd_ms'])} | {f(r['subm_fwd_bwd_ms'])} | "
            f"{f(r['down_fwd_ms'])} | {f(r['down_fwd_bwd_ms'])} | {f(r['dense_fwd_ms'])} | "
            f"{f(r['dense_fwd_bwd_ms'])} | {'x'.join(map(str, r['dense_grid']))} | "
            f"{f(r['subm_fwd_cpu1_ms'])} | {f(r['subm_fwd_bwd_cpu1_ms'])} |")
    lines += [
        "",
        "Default `SparseUNet(4, 2)` (channels 32-48-64-96-128, 4 stride-2 levels, batch norm) on the same "
        "cells; 'new coords' rebuilds every kernel map (a GCA step), 'cached' reuses them.",
        "",
        "| N | U-Net fwd (new coords) | U-Net fwd (cached maps) | U-Net fwd+bwd (new coords) |",
        "|---|---|---|---|",
    ]
    for u in unet_rows:
        lines.append(f"| {u['n']} | {f(u['unet_fwd_new_coords_ms'])} | {f(u['unet_fwd_cached_ms'])} | "
                     f"{f(u['unet_fwd_bwd_new_coords_ms'])} |")
    idles = [f"{r['n']}/{r.get('c', 'U-Net')}: {r['cpu_idle_before']:.0%}" for r in rows + unet_rows
             if r.get("cpu_idle_before") is not None]
    if idles:
        lines += ["", "CPU idle just before each configuration (others' jobs): " + ", ".join(idles) + "."]
    lines += ["", f"Load average (1 min) before / after the run: {meta['load_before']:.2f} / "
              f"{meta['load_after']:.2f}. The machine is shared with other jobs, which inflate wall-clock medians "
              "(2 threads); the 1-thread CPU-time columns are the contention-robust measure.", ""]
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[60_000, 200_000])
    ap.add_argument("--channels", type=int, nargs="+", default=[32, 64])
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--dense-repeats", type=int, default=3)
    ap.add_argument("--dense-mem-gb", type=float, default=6.0, help="skip dense convs needing more")
    ap.add_argument("--threads", type=int, default=torch.get_num_threads())
    ap.add_argument("--wait-idle", type=float, default=0.0,
                    help="before each configuration wait up to this many seconds for an idle CPU")
    ap.add_argument("--out", type=Path, default=RESULTS / "sparse_conv")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    meta = {
        "cpu": cpu_model(), "cores": os.cpu_count(), "threads": torch.get_num_threads(),
        "torch": torch.__version__, "date": time.strftime("%Y-%m-%d"), "repeats": args.repeats,
        "dense_repeats": args.dense_repeats, "grid": list(GRID), "load_before": os.getloadavg()[0],
        "omp_wait_policy": os.environ.get("OMP_WAIT_POLICY", "default"),
        "unet_repeats": max(3, args.repeats // 2),
    }
    rows, unet_rows = [], []
    for n in args.sizes:
        coords = surface_cells(n)
        for c in args.channels:
            idle = wait_idle(args.wait_idle) if args.wait_idle > 0 else None
            r = {"n": n, "c": c, "cpu_idle_before": idle, **bench_sparse(coords, c, args.repeats)}
            r.update(bench_dense(coords, c, args.dense_repeats, args.dense_mem_gb))
            rows.append(r)
            print(json.dumps(r), flush=True)
        idle = wait_idle(args.wait_idle) if args.wait_idle > 0 else None
        u = {"n": n, "cpu_idle_before": idle, **bench_unet(coords, meta["unet_repeats"])}
        unet_rows.append(u)
        print(json.dumps(u), flush=True)
    meta["load_after"] = os.getloadavg()[0]
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.with_suffix(".json").write_text(json.dumps({"meta": meta, "results": rows, "unet": unet_rows}, indent=2) + "\n")
    args.out.with_suffix(".md").write_text(to_markdown(meta, rows, unet_rows))
    print(to_markdown(meta, rows, unet_rows))


if __name__ == "__main__":
    main()
