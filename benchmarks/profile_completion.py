"""Where the seconds of a completion go: the default region of `hgca demo`, coarse and full, on 1 and 2 threads.

    python benchmarks/profile_completion.py [--stages coarse full] [--threads 1 2] [--torch-threads 2]
                                            [--pyspy-stages full] [--no-pyspy] [--out profile]

Each configuration runs in a fresh process three ways:
* timers: the product's functions wrapped by exclusive wall-clock timers (a function's time minus that of the
  timed functions it calls), grouped into the parts of a completion: the free-space ray walk, the planner, the
  neighbourhoods, the kernel maps, the sparse convolutions (gathers, GEMMs and scatters together), BatchNorm, the
  kernels' input features, each meshing stage (decode, extract, clean, fair, decimate) and the rest;
* torch: `torch.profiler` op-level self CPU time, grouped by what the op does (GEMM, gather, scatter, BatchNorm,
  search / sort for maps and neighbourhoods, element-wise);
* py-spy (when installed): the sampled Python frames innermost in hgca_core, the top functions.
The timers' wrappers add a few microseconds per call (~1e4 calls a run), the profiler ~10 %.
Writes benchmarks/results/<out>.{md,json,png}.
"""
from __future__ import annotations

import argparse
import functools
import json
import os
import shutil
import subprocess
import sys
import time
from collections import Counter, defaultdict
from pathlib import Path

from common import write_page

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")    # as the CLI sets it (hgca_core/cli.py)

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "benchmarks" / "results"
EXAMPLE = REPO / "hgca_core" / "examples"

# (module, attribute, part): the functions the timers wrap. Exclusive time, so nesting is fine.
TIMED = [
    ("hgca_core.geometry.freespace", "observed_empty", "free-space ray walk"),
    ("hgca_core.geometry.freespace", "confident", "free-space ray walk"),
    ("hgca_core.models.gca", "GCAKernel.bev", "planner"),
    ("hgca_core.geometry.coords", "dilate", "neighbourhood (dilate)"),
    ("hgca_core.nn.sparse", "submanifold_map", "kernel maps"),
    ("hgca_core.nn.sparse", "downsample_map", "kernel maps"),
    ("hgca_core.nn.sparse", "upsample_map", "kernel maps"),
    ("hgca_core.nn.sparse", "SparseTensor.keys", "kernel maps"),
    ("hgca_core.nn.kernel_map", "KernelMap.table", "kernel maps"),
    ("hgca_core.nn.sparse", "conv_gemm", "sparse conv (gather-GEMM-scatter)"),
    ("hgca_core.nn.sparse", "SparseBatchNorm.forward", "BatchNorm"),
    ("hgca_core.nn.sparse", "SparseReLU.forward", "ReLU, skip concat"),
    ("hgca_core.nn.sparse", "sparse_cat", "ReLU, skip concat"),
    ("hgca_core.models.gca", "GCAKernel.forward", "kernel input features, SPADE"),
    ("hgca_core.models.cgca", "CGCAKernel.forward", "kernel input features, SPADE"),
    ("hgca_core.models.cgca", "CGCAKernel.project", "kernel input features, SPADE"),
    ("hgca_core.models.cgca", "initial_state", "fine initial state (encoder)"),
    ("hgca_core.meshing", "udf_grid", "mesh: decode"),
    ("hgca_core.geometry.udf_surface", "dual_surface", "mesh: extract"),
    ("hgca_core.geometry.mesh_clean", "clean_surface", "mesh: clean"),
    ("hgca_core.geometry.fairing", "fair_ground", "mesh: fair"),
    ("hgca_core.meshing", "decimate", "mesh: decimate"),
    ("hgca_core.geometry.nearest", "PointIndex.distances", "observed distances"),
    ("hgca_core.geometry.nearest", "PointIndex.nearest", "mesh: fair"),
]

# torch op name -> kind, by the first matching fragment
OP_KINDS = [
    (("aten::mm", "aten::addmm", "aten::matmul", "aten::linear"), "GEMM"),
    (("aten::index_add", "index_put", "aten::scatter", "aten::masked_scatter"), "scatter"),
    (("aten::index_select", "aten::index", "aten::take", "aten::gather"), "gather"),
    (("batch_norm",), "BatchNorm"),
    (("searchsorted", "aten::sort", "aten::unique", "aten::argsort", "aten::bincount", "aten::isin",
      "aten::nonzero", "aten::cumsum"), "search / sort / nonzero"),
    (("aten::copy_", "aten::to", "aten::cat", "aten::clone", "aten::_to_copy", "aten::contiguous",
      "aten::fill_", "aten::zero", "aten::empty", "aten::full"), "copy / fill / alloc"),
    (("aten::rand", "aten::randn", "aten::uniform", "aten::normal", "aten::bernoulli"), "random draws"),
]


def _resolve(mod_name: str, attr: str) -> tuple[object, str]:
    import importlib

    obj: object = importlib.import_module(mod_name)
    parts = attr.split(".")
    for p in parts[:-1]:
        obj = getattr(obj, p)
    return obj, parts[-1]


def install_timers() -> dict[str, float]:
    """Wrap every TIMED function; returns the dict of exclusive seconds per part it fills."""
    from functools import cached_property

    spent: dict[str, float] = defaultdict(float)
    stack: list[float] = []          # child seconds of each open timed call

    def timed(fn, part):
        @functools.wraps(fn)
        def inner(*a, **k):
            stack.append(0.0)
            t0 = time.perf_counter()
            try:
                return fn(*a, **k)
            finally:
                dt = time.perf_counter() - t0
                child = stack.pop()
                spent[part] += dt - child
                if stack:
                    stack[-1] += dt
        return inner

    for mod_name, attr, part in TIMED:
        owner, name = _resolve(mod_name, attr)
        raw = owner.__dict__[name] if isinstance(owner, type) else getattr(owner, name)
        if isinstance(raw, cached_property):
            new = cached_property(timed(raw.func, part))
            new.__set_name__(owner, name)
        elif isinstance(raw, property):
            new = property(timed(raw.fget, part))
        else:
            new = timed(raw, part)
        setattr(owner, name, new)
    return spent


def example_inputs():
    """The bundled example as `hgca demo` reads it: points, sensor origins, each point's origin, the region."""
    from hgca_core.geometry.freespace import ray_origins
    from hgca_core.geometry.region import Region
    from hgca_core.io.poses import load_poses
    from hgca_core.io.sequence import read_inputs

    poses = EXAMPLE / "poses.json"
    scans = [str(EXAMPLE / e.file) for e in load_poses(poses)]
    region = Region.parse(",".join(f"{v:.6f}" for v in json.loads(poses.read_text())["region"]))
    scan = read_inputs(scans, poses=str(poses))
    return scan.points, scan.origins, ray_origins(scan.origins, scan.attributes, scan.points), region


def worker(stage: str, threads: int, mode: str, trace: str | None) -> dict:
    """One completion of the example in this process; mode 'timers' or 'torch' (or 'plain', for py-spy)."""
    import torch

    from hgca_core.hardware import tune_allocator

    tune_allocator()
    torch.set_num_threads(threads)
    from hgca_core.pipeline import complete, load_models
    from hgca_core.progress import StageClock

    spent = install_timers() if mode == "timers" else None
    pts, origins, index, region = example_inputs()
    load_models(stage)
    clock = StageClock()
    t0 = time.perf_counter()
    if mode == "torch":
        from torch.profiler import ProfilerActivity, profile

        with profile(activities=[ProfilerActivity.CPU]) as prof:
            complete(pts, region=region, origins=origins, stage=stage, progress=clock, origin_index=index)
        kinds: dict[str, float] = defaultdict(float)
        top = []
        for ev in prof.key_averages():
            s = ev.self_cpu_time_total / 1e6
            kind = next((k for frags, k in OP_KINDS if any(f in ev.key for f in frags)), "other ops")
            kinds[kind] += s
            top.append((s, ev.key, ev.count))
        top.sort(reverse=True)
        extra = {"op_kinds_s": dict(kinds), "top_ops": [[k, round(s, 3), n] for s, k, n in top[:15]]}
    else:
        complete(pts, region=region, origins=origins, stage=stage, progress=clock, origin_index=index)
        extra = {"parts_s": dict(spent)} if spent is not None else {}
    total = time.perf_counter() - t0
    if spent is not None:
        extra["parts_s"]["rest (Python, sampling, frames)"] = total - sum(spent.values())
    return {"stage": stage, "threads": threads, "mode": mode, "seconds": total, "stages_s": dict(clock.seconds),
            **extra}


def run_worker(stage: str, threads: int, mode: str, pyspy: str | None = None) -> dict:
    cmd = [sys.executable, __file__, "--worker", stage, str(threads), mode]
    env = dict(os.environ, OMP_NUM_THREADS=str(threads), MKL_NUM_THREADS=str(threads))
    if pyspy:
        cmd = [pyspy, "record", "--format", "raw", "-r", "50", "-o", f"/tmp/pyspy_{os.getpid()}.txt", "--", *cmd]
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env)
    if proc.returncode != 0:
        raise SystemExit(proc.stderr[-3000:])
    row = json.loads([ln for ln in proc.stdout.splitlines() if ln.startswith("{")][-1])
    if pyspy:
        row["pyspy_top"] = pyspy_top(Path(f"/tmp/pyspy_{os.getpid()}.txt"))
    return row


def pyspy_top(raw: Path, n: int = 12) -> list[list]:
    """Share of samples per innermost hgca_core frame (function and file), from py-spy's collapsed stacks."""
    counts: Counter = Counter()
    total = 0
    for line in raw.read_text().splitlines():
        stack, _, c = line.rpartition(" ")
        frames = [f for f in stack.split(";") if "hgca_core" in f]
        total += int(c)
        if frames:
            f = frames[-1]
            name, _, loc = f.partition(" (")
            counts[f"{name} ({loc.split('/')[-1].split(':')[0]})"] += int(c)
    raw.unlink()
    return [[k, round(v / max(1, total), 4)] for k, v in counts.most_common(n)]


def cpu_flags() -> dict:
    import re

    text = subprocess.run(["lscpu"], capture_output=True, text=True).stdout
    model = re.search(r"Model name:\s*(.+)", text)
    flags = re.search(r"Flags:\s*(.+)", text)
    fl = flags.group(1).split() if flags else []
    return {"model": model.group(1).strip() if model else "?",
            "avx512": sorted(f for f in fl if f.startswith("avx512")), "amx": sorted(f for f in fl if "amx" in f),
            "avx2": "avx2" in fl}


def page(result: dict) -> str:
    cpu = result["cpu"]
    lines = ["# Where a completion's seconds go", "",
             "The default region of `hgca demo` (the bundled example, 38.4 x 38.4 x 8 m, 5 scans), the shipped "
             "weights, fp32, seed 0, one fresh process per row (`python benchmarks/profile_completion.py`), code at "
             f"commit {result['code']}.", "",
             f"CPU: {cpu['model']}; AVX-512: {', '.join(cpu['avx512']) or 'none'}; AMX: "
             f"{', '.join(cpu['amx']) or 'none'}; AVX2: {'yes' if cpu['avx2'] else 'no'}. "
             f"{result['cores']} cores, torch {result['torch']}, {result['date']} UTC, load average at the start "
             f"{result['load']}.", "",
             "## Stages (the pipeline's own progress events, timers run)", ""]
    rows = [r for r in result["rows"] if r["mode"] == "timers"]
    stages = sorted({k for r in rows for k in r["stages_s"]}, key=lambda k: -max(r["stages_s"].get(k, 0) for r in rows))
    head = ["stage, threads", "total (s)", *stages]
    lines += ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in rows:
        lines.append(f"| {r['stage']}, {r['threads']} | {r['seconds']:.1f} | "
                     + " | ".join(f"{r['stages_s'].get(s, 0):.2f}" for s in stages) + " |")
    lines += ["", "## Parts (exclusive seconds of the wrapped functions)", ""]
    parts = sorted({k for r in rows for k in r["parts_s"]}, key=lambda k: -max(r["parts_s"].get(k, 0) for r in rows))
    lines += ["| part | " + " | ".join(f"{r['stage']}, {r['threads']} thr (s)" for r in rows) + " | share (full, 2) |",
              "|---|" + "---:|" * (len(rows) + 1)]
    ref = next((r for r in rows if r["stage"] == "full" and r["threads"] == 2), rows[-1])
    for p in parts:
        lines.append(f"| {p} | " + " | ".join(f"{r['parts_s'].get(p, 0):.2f}" for r in rows)
                     + f" | {100 * ref['parts_s'].get(p, 0) / ref['seconds']:.0f} % |")
    trows = [r for r in result["rows"] if r["mode"] == "torch"]
    if trows:
        lines += ["", "## Torch ops (torch.profiler self CPU seconds by kind; the profiler's own cost included)", ""]
        kinds = sorted({k for r in trows for k in r["op_kinds_s"]}, key=lambda k: -max(r["op_kinds_s"].get(k, 0)
                                                                                      for r in trows))
        lines += ["| op kind | " + " | ".join(f"{r['stage']}, {r['threads']} thr (s)" for r in trows) + " |",
                  "|---|" + "---:|" * len(trows)]
        for k in kinds:
            lines.append(f"| {k} | " + " | ".join(f"{r['op_kinds_s'].get(k, 0):.2f}" for r in trows) + " |")
        for r in trows:
            lines += ["", f"Top ops, {r['stage']}, {r['threads']} thread(s): "
                      + "; ".join(f"`{k}` {s:.2f} s ({n} calls)" for k, s, n in r["top_ops"][:10]) + "."]
    srows = [r for r in result["rows"] if "pyspy_top" in r]
    for r in srows:
        lines += ["", f"py-spy, {r['stage']}, {r['threads']} thread(s), share of samples by innermost hgca_core "
                  "frame: " + "; ".join(f"`{k}` {100 * s:.0f} %" for k, s in r["pyspy_top"]) + "."]
    return "\n".join(lines) + "\n"


def plot(result: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = [r for r in result["rows"] if r["mode"] == "timers"]
    parts = sorted({k for r in rows for k in r["parts_s"]}, key=lambda k: -sum(r["parts_s"].get(k, 0) for r in rows))
    fig, ax = plt.subplots(figsize=(11, 1.2 + 0.7 * len(rows)))
    cmap = plt.get_cmap("tab20")
    for i, r in enumerate(rows):
        left = 0.0
        for j, p in enumerate(parts):
            w = r["parts_s"].get(p, 0)
            ax.barh(i, w, left=left, color=cmap(j % 20), label=p if i == 0 else None)
            left += w
    ax.set_yticks(range(len(rows)), [f"{r['stage']}, {r['threads']} thr" for r in rows])
    ax.invert_yaxis()
    ax.set_xlabel("seconds (exclusive, per part)")
    ax.set_title(f"default region of `hgca demo`, {result['cpu']['model']}")
    ax.legend(fontsize=7, ncol=3, loc="upper center", bbox_to_anchor=(0.5, -0.35))
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--stages", nargs="+", default=["coarse", "full"], choices=["coarse", "full"])
    ap.add_argument("--threads", nargs="+", type=int, default=[1, 2])
    ap.add_argument("--torch-threads", nargs="*", type=int, default=None,
                    help="thread counts of the torch.profiler runs (default: every --threads; none: skip them)")
    ap.add_argument("--pyspy-stages", nargs="*", default=None, help="stages py-spy samples (default: every one)")
    ap.add_argument("--no-pyspy", action="store_true", help="skip the py-spy runs")
    ap.add_argument("--out", default="profile")
    args = ap.parse_args()
    import torch

    pyspy = None if args.no_pyspy else (shutil.which("py-spy") or shutil.which("py-spy", path=str(Path(sys.executable).parent)))
    import hgca_core

    root = Path(hgca_core.__file__).resolve().parents[1]
    commit = subprocess.run(["git", "-C", str(root), "rev-parse", "--short", "HEAD"], capture_output=True,
                            text=True).stdout.strip()
    result = {"code": commit, "cpu": cpu_flags(), "cores": len(os.sched_getaffinity(0)), "torch": torch.__version__,
              "date": time.strftime("%Y-%m-%d %H:%M", time.gmtime()), "load": round(os.getloadavg()[0], 2), "rows": []}
    for stage in args.stages:
        for t in args.threads:
            torch_threads = args.threads if args.torch_threads is None else args.torch_threads
            for mode in ["timers"] + (["torch"] if t in torch_threads else []):
                result["rows"].append(run_worker(stage, t, mode))
                print(json.dumps({k: v for k, v in result["rows"][-1].items() if k in ("stage", "threads", "mode",
                                                                                      "seconds")}), flush=True)
            if pyspy and t == max(args.threads) and (args.pyspy_stages is None or stage in args.pyspy_stages):
                result["rows"].append(run_worker(stage, t, "plain", pyspy))
    print(write_page(RESULTS, args.out, result, page, plot))
    return 0


if __name__ == "__main__":
    if len(sys.argv) >= 5 and sys.argv[1] == "--worker":
        print(json.dumps(worker(sys.argv[2], int(sys.argv[3]), sys.argv[4], None)))
        sys.exit(0)
    sys.exit(main())
