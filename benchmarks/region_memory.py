"""Peak memory of one full completion, new code against old, in fresh interleaved processes.

    git worktree add /tmp/old <commit>                  # the code to compare against
    python benchmarks/region_memory.py run --old /tmp/old [--new .] [--pairs default=2 40x120=1] [--threads 2]
    python benchmarks/region_memory.py page             # the page again from the saved runs

Why: a region's peak resident memory decides whether it fits a machine at all (`hgca complete` refuses one that
cannot), so a speed change must not buy its seconds with memory. Each run is a fresh process with one tree on
PYTHONPATH doing `hgca_core.bench.run_one` (the benchmark's synthetic drive, its region, full stage, seed 0, fp32,
the tree's shipped weights) after `tune_allocator`, as `hgca bench` does. For each region new and old run in turn
(new, old, new, old ...), so a drift of the machine touches both alike and the ratio is taken pair by pair. The
parent reaps each child with `os.wait4`: user + system CPU seconds and wall are the operating system's accounting
of that one process. Peak RSS is the child's own high-water mark (VmHWM of /proc/self/status, read as it exits):
not wait4's ru_maxrss, which on Linux also counts the parent's resident set at the moment it spawned the child
(subprocess spawns with vfork, and exec records the shared address space's peak), so a child started from a
large process such as a test worker would report that process's memory. The child also hashes the mesh file it writes, so the page can
say whether old and new made the same mesh (cells, triangles, sha256 of the PLY bytes).

Runs are appended to runs/memory/runs.jsonl as they finish (a stopped call keeps what it measured; `run` adds
pairs to those already there); benchmarks/results/memory.{md,json,png} are written from that file.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import tempfile
import time
from pathlib import Path

from common import write_page

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "benchmarks" / "results"
LOG = REPO / "runs" / "memory" / "runs.jsonl"
# name: (width, depth) in metres of `hgca_core.bench.scene_inputs`; "default" is `hgca demo`'s 38.4 x 38.4 m
REGIONS = {"default": (38.4, 38.4), "40x120": (120.0, 40.0)}
NAMES = {"default": "38.4 x 38.4 m (default)", "40x120": "40 x 120 m"}

# The child: one completion as `hgca bench`'s worker does it, with the written mesh hashed before run_one deletes it.
CHILD = """
import hashlib, json, sys
import hgca_core, hgca_core.io as io
from hgca_core.hardware import tune_allocator
from hgca_core.bench import run_one
tune_allocator()
job = json.loads(sys.argv[1])
digest = {}
write = io.write_mesh
def hashed(path, mesh, *a, **k):
    out = write(path, mesh, *a, **k)
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    digest["sha256"] = h.hexdigest()
    return out
io.write_mesh = hashed
row = run_one(job["width"], job["depth"], "full", "cpu", None, 0)
print(json.dumps({**row, "mesh_sha256": digest.get("sha256"), "package": hgca_core.__file__}))
"""

# Runs CHILD (argv[1]) as __main__ and, however it ends, writes the process's own peak RSS to stderr. It reads
# VmHWM itself rather than calling hgca_core.hardware.peak_rss_bytes: the old tree compared against predates it.
PEAK = """
import sys
source = sys.argv.pop(1)
try:
    exec(compile(source, "<child>", "exec"), {"__name__": "__main__"})
finally:
    with open("/proc/self/status") as status:
        for line in status:
            if line.startswith("VmHWM:"):
                sys.stderr.write("hgca-peak-rss-kib " + line.split()[1] + "\\n")
"""


def _peak_kib(err: str) -> int | None:
    """The child's VmHWM line from its stderr (None on a system without /proc or a child that was killed)."""
    found = [line.split()[1] for line in err.splitlines() if line.startswith("hgca-peak-rss-kib ")]
    return int(found[-1]) if found else None


def measure(root: Path, region: str, threads: int, python: str, timeout: int) -> dict:
    """One completion of `region` with the tree `root` in a fresh process; its row with the OS's accounting."""
    width, depth = REGIONS[region]
    env = {**os.environ, "PYTHONPATH": str(root), "OMP_NUM_THREADS": str(threads), "MKL_NUM_THREADS": str(threads)}
    load = os.getloadavg()[0]
    with tempfile.TemporaryFile("w+") as out, tempfile.TemporaryFile("w+") as err:
        t0 = time.perf_counter()
        proc = subprocess.Popen([python, "-c", PEAK, CHILD, json.dumps({"width": width, "depth": depth})], cwd="/tmp",
                                env=env, stdout=out, stderr=err, text=True)
        while True:                     # reaped here, not by Popen, so that wait4 hands over its rusage
            pid, status, usage = os.wait4(proc.pid, os.WNOHANG)
            if pid:
                break
            if time.perf_counter() - t0 > timeout:
                proc.kill()
                _, status, usage = os.wait4(proc.pid, 0)
                break
            time.sleep(0.5)
        wall = time.perf_counter() - t0
        proc.returncode = os.waitstatus_to_exitcode(status)
        out.seek(0)
        err.seek(0)
        out, err = out.read(), err.read()
    peak = _peak_kib(err)
    err = "\n".join(line for line in err.splitlines() if not line.startswith("hgca-peak-rss-kib "))
    row = {"region": region, "root": str(root), "threads": threads, "load_at_start": round(load, 1),
           "exit": proc.returncode, "peak_rss_mib": round(peak / 1024, 1) if peak else None,
           "cpu_s": round(usage.ru_utime + usage.ru_stime, 1), "user_s": round(usage.ru_utime, 1),
           "sys_s": round(usage.ru_stime, 1), "wall_s": round(wall, 1),
           "date": time.strftime("%Y-%m-%d %H:%M", time.gmtime())}
    if proc.returncode != 0 or not out.strip():
        return {**row, "error": (err.strip().splitlines() or ["no output"])[-1]}
    if peak is None:
        return {**row, "error": "the child reported no peak RSS (no /proc/self/status?)"}
    child = json.loads(out.strip().splitlines()[-1])
    if not child["package"].startswith(str(root)):
        raise SystemExit(f"region_memory: error: the child imported {child['package']}, not the tree {root}")
    return {**row, **{k: child[k] for k in ("coarse_cells", "triangles", "mesh_sha256", "points", "stages_s",
                                            "seconds")}}


def run(new: Path, old: Path, pairs: dict[str, int], threads: int, python: str, timeout: int) -> None:
    """`pairs[region]` more pairs per region (new then old), each run appended to the log as it ends."""
    LOG.parent.mkdir(parents=True, exist_ok=True)
    for region, n in pairs.items():
        for _ in range(n):
            for side, root in (("new", new), ("old", old)):
                row = {"side": side, **measure(root, region, threads, python, timeout)}
                with LOG.open("a") as f:
                    f.write(json.dumps(row) + "\n")
                print(json.dumps(row), flush=True)


def summary(rows: list[dict], labels: dict[str, str]) -> dict:
    """Per region: the medians of each side, the pair-by-pair ratios and whether the outputs agree."""
    regions = {}
    for region in REGIONS:
        runs = [r for r in rows if r["region"] == region and "error" not in r]
        new = [r for r in runs if r["side"] == "new"]
        old = [r for r in runs if r["side"] == "old"]
        if not new or not old:
            continue
        pairs = list(zip(new, old))
        entry = {"threads": sorted({r["threads"] for r in runs}), "runs": [len(new), len(old)],
                 "load_at_start": [min(r["load_at_start"] for r in runs), max(r["load_at_start"] for r in runs)]}
        for key in ("peak_rss_mib", "cpu_s", "wall_s"):
            entry[key] = {"new": _spread([r[key] for r in new]), "old": _spread([r[key] for r in old]),
                          "ratio": _spread([a[key] / b[key] for a, b in pairs], 3)}
        for key in ("coarse_cells", "triangles", "mesh_sha256"):
            entry[key] = {"new": sorted({r[key] for r in new}), "old": sorted({r[key] for r in old})}
        entry["same_output"] = all(len(set(entry[k]["new"] + entry[k]["old"])) == 1
                                   for k in ("coarse_cells", "triangles", "mesh_sha256"))
        regions[region] = entry
    return {"date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), "labels": labels, "regions": regions,
            "runs": rows}


def _spread(values: list[float], digits: int = 1) -> list[float]:
    """[min, median, max]."""
    return [round(min(values), digits), round(statistics.median(values), digits), round(max(values), digits)]


def page(result: dict) -> str:
    lab = result["labels"]
    lines = ["# Peak memory of one completion, new code against old", "",
             "`python benchmarks/region_memory.py run --old TREE`: fresh processes, each one full completion "
             "(`hgca_core.bench.run_one`: the benchmark's synthetic drive, full stage, seed 0, fp32, the tree's "
             "shipped weights, `tune_allocator` as in the CLI), new and old in turn; CPU (user + sys) and wall are "
             "the operating system's accounting of each process (`wait4`), peak RSS its own high-water mark (VmHWM "
             "of /proc/self/status as it exits). Median [min - max] of the runs; "
             f"new / old is taken pair by pair. New: {lab['new']}; old: {lab['old']}.", "",
             "| region | measure | new | old | new / old |", "|---|---|---:|---:|---:|"]
    for region, e in result["regions"].items():
        for key, name in (("peak_rss_mib", "peak RSS (MiB)"), ("cpu_s", "CPU (s)"), ("wall_s", "wall (s)")):
            n, o, r = e[key]["new"], e[key]["old"], e[key]["ratio"]
            lines.append(f"| {NAMES.get(region, region)} | {name} | {n[1]:,.1f} [{n[0]:,.1f} - {n[2]:,.1f}] | {o[1]:,.1f} "
                         f"[{o[0]:,.1f} - {o[2]:,.1f}] | {r[1]:.3f} [{r[0]:.3f} - {r[2]:.3f}] |")
    lines += ["", "| region | runs (new, old) | threads | load at start | coarse cells | triangles | mesh sha256 "
              "| same output |", "|---|---|---|---|---:|---:|---|---|"]
    for region, e in result["regions"].items():
        def both(key: str) -> str:
            vals = sorted(set(e[key]["new"] + e[key]["old"]))
            return ", ".join(f"{v:,}" if isinstance(v, int) else f"`{v[:12]}…`" for v in vals)
        lines.append(f"| {NAMES.get(region, region)} | {e['runs'][0]}, {e['runs'][1]} | {', '.join(map(str, e['threads']))} "
                     f"| {e['load_at_start'][0]} - {e['load_at_start'][1]} | {both('coarse_cells')} "
                     f"| {both('triangles')} | {both('mesh_sha256')} | {'yes' if e['same_output'] else '**no**'} |")
    same = [NAMES.get(r, r) for r, e in result["regions"].items() if e["same_output"]]
    lines += ["", ("Same output: old and new made the same coarse cells, the same triangle count and the same PLY "
                   f"bytes (sha256 of the mesh file) in every run of {' and '.join(same)}.") if same else
              "Old and new made different outputs (see the table): the memory figures compare different meshes."]
    for note in result.get("notes", []):
        lines += ["", note]
    return "\n".join(lines) + "\n"


def plot(result: dict, path: Path) -> None:
    """Bars: peak RSS and CPU of each region, old (grey) and new (blue), medians with their min-max."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    regions = list(result["regions"])
    fig, axes = plt.subplots(1, 2, figsize=(9, 3.6))
    for ax, (key, name) in zip(axes, (("peak_rss_mib", "peak RSS (MiB)"), ("cpu_s", "CPU, user + sys (s)"))):
        for i, region in enumerate(regions):
            e = result["regions"][region][key]
            for j, (side, colour) in enumerate((("old", "#999999"), ("new", "#1f77b4"))):
                lo, mid, hi = e[side]
                ax.bar(i * 3 + j, mid, color=colour, yerr=[[mid - lo], [hi - mid]], capsize=3,
                       label=side if i == 0 else None)
                ax.annotate(f"{mid:,.0f}", (i * 3 + j, mid), ha="center", va="bottom", fontsize=8,
                            xytext=(0, 2), textcoords="offset points")
        ax.set_xticks([i * 3 + 0.5 for i in range(len(regions))],
                      [NAMES.get(r, r).replace(" (default)", "") for r in regions])
        ax.set_title(name)
    axes[0].legend(loc="lower center")
    fig.suptitle("one full completion, old vs new code, interleaved fresh processes (median, min-max)", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("run", help="measure more pairs, then write the page")
    r.add_argument("--old", type=Path, required=True, help="tree of the old code (a git worktree)")
    r.add_argument("--new", type=Path, default=REPO)
    r.add_argument("--pairs", nargs="+", default=["default=2", "40x120=1"], metavar="REGION=N")
    r.add_argument("--threads", type=int, default=2)
    r.add_argument("--timeout", type=int, default=3000, help="seconds before one run is killed")
    r.add_argument("--python", default=str(REPO / ".venv" / "bin" / "python"))
    for p in (r, sub.add_parser("page", help="the page from the saved runs")):
        p.add_argument("--label-old", default="acca0b5 (the code before the speed work)")
        p.add_argument("--label-new", default="this tree")
        p.add_argument("--note", action="append", default=[], help="a paragraph for the page's end")
    args = ap.parse_args()
    if args.cmd == "run":
        pairs = dict(item.split("=") for item in args.pairs)
        unknown = sorted(set(pairs) - set(REGIONS))
        if unknown:
            ap.error(f"unknown region {', '.join(unknown)} (known: {', '.join(REGIONS)})")
        run(args.new.resolve(), args.old.resolve(), {k: int(v) for k, v in pairs.items()}, args.threads,
            args.python, args.timeout)
    rows = [json.loads(line) for line in LOG.read_text().splitlines() if line.strip()] if LOG.exists() else []
    result = {**summary(rows, {"new": args.label_new, "old": args.label_old}), "notes": args.note}
    print(write_page(RESULTS, "memory", result, page, plot))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
