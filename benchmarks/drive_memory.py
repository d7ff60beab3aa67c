"""A Ray worker's memory tile after tile (run by hand): one worker runs every tile of a synthetic drive.

    .venv/bin/python benchmarks/drive_memory.py --code old=/tmp/base --code new=. [--length 400] [--t1 2]

For each code tree (PYTHONPATH), at the same time so that both see the same machine: `hgca_core.drive` on the
drive of `benchmarks/drive.py` (`build_drive`), stage coarse, its Ray runner on one CPU so that one worker runs
all tiles. After each tile the worker writes its resident memory from /proc/self/status: private (RssAnon),
file-backed (RssFile: the libraries) and shared (RssShmem: the pages of Ray's object store it has touched), and
its peak. The slope of each against the tile count (least squares from the fourth tile on) says whether a
worker's memory follows the drive's length. Results: benchmarks/results/drive_memory.{md,json,png}.
"""
from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
FIELDS = ("VmRSS", "RssAnon", "RssFile", "RssShmem", "VmHWM")
SKIP = 3                    # tiles left out of the slope: the worker's start (imports, first allocations)


def probe(label: str, scans: Path, t1: int, log: Path) -> None:
    """In this process (the code under test on PYTHONPATH): the drive on a Ray of one CPU, each tile's task
    wrapped so that the worker appends its memory to `log` after the tile."""
    import shutil

    import hgca_core
    import hgca_core.tiling.run as run
    import hgca_core.tiling.runners as runners

    def measured(job, n_scans, *inputs):        # in the worker; shipped by value (this is __main__)
        import gc

        from hgca_core.tiling.runners import tile_task

        out = tile_task(job, n_scans, *inputs)
        gc.collect()
        text = open("/proc/self/status").read()
        rec = {k: int(re.search(rf"{k}:\s+(\d+)", text).group(1)) * 1024 for k in FIELDS}
        with open(log, "a") as f:
            f.write(json.dumps({"tile": job.index, "t": time.time(), **rec}) + "\n")
        return out

    runners.tile_task = measured
    run._runner = lambda workers, threads, address, memory: runners.RayRunner(1, threads, memory, None)
    out = log.with_suffix(".out")
    shutil.rmtree(out, ignore_errors=True)
    log.unlink(missing_ok=True)
    hgca_core.drive(sorted(scans.glob("scan_*.npz")), out, scans / "poses.json", stage="coarse", t1=t1, threads=1,
                    workers=2)
    shutil.rmtree(out, ignore_errors=True)


def slopes(rows: list[dict]) -> dict:
    n = np.arange(1, len(rows) + 1)
    return {k: round(float(np.polyfit(n[SKIP:], np.array([r[k] for r in rows[SKIP:]]) / 2**20, 1)[0]), 1)
            if len(rows) > SKIP + 1 else None for k in FIELDS}


def _name(label: str, run: dict) -> str:
    return f"{label}: {run['code']}" if run["code"] else label


def _mean(rows: list[dict], parity: int) -> float:
    """Mean private memory (MiB) after the tiles of one phase (index parity)."""
    v = [x["RssAnon"] for x in rows if x["tile"] % 2 == parity]
    return float(np.mean(v)) / 2**20 if v else float("nan")


def table(r: dict) -> str:
    m = r["machine"]
    lines = [f"# A Ray worker's memory tile after tile: {r['length_m']:.0f} m synthetic drive, {r['tiles']} tiles, "
             f"stage coarse, T1 = {r['t1']}", "",
             f"Machine: {m['cpu']}, {m['cores']} cores shared with other jobs, torch {m['torch']}, {m['date']}. "
             f"`benchmarks/drive_memory.py`: one Ray worker runs every tile (1 torch thread); the code trees ran "
             "at the same time. Resident memory after each tile (MiB), from the worker's /proc/self/status; "
             f"slope: least squares against the tile count from tile {SKIP + 1} on. {r.get('note', '')}", "",
             "| code | tiles | RSS after first / last tile | private (RssAnon) slope | shared (RssShmem) slope | "
             "RSS slope | peak slope | private, phase one / two tiles (mean) |",
             "|---|---:|---:|---:|---:|---:|---:|---:|"]
    for label, v in r["runs"].items():
        rows, s = v["rows"], v["slope_mib_per_tile"]
        lines.append(f"| {_name(label, v)} | {len(rows)} | {rows[0]['VmRSS'] / 2**20:.0f} / "
                     f"{rows[-1]['VmRSS'] / 2**20:.0f} | {s['RssAnon']} | {s['RssShmem']} | {s['VmRSS']} | "
                     f"{s['VmHWM']} | {_mean(rows, 0):.0f} / {_mean(rows, 1):.0f} |")
    lines += ["", "Private: the worker's own heap (torch, numpy); shared: the pages of Ray's object store the worker "
              "has read its tasks' scans from and written its results to; they stay in its resident set while "
              "the store keeps them, so a worker that meets new store pages every tile grows by them. A phase-two "
              "tile (odd index, completed with its neighbours' cells) holds more private memory than a phase-one "
              "tile; where the phase-one tiles all run first, the private slope also carries that step.", "",
              "![memory per tile](drive_memory.png)"]
    return "\n".join(lines) + "\n"


def plot(r: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(12, 4.2), sharex=True)
    for c, (label, v) in enumerate(r["runs"].items()):
        n = np.arange(1, len(v["rows"]) + 1)
        for a, (key, name) in zip(ax, (("VmRSS", "resident (MiB)"), ("RssShmem", "of which object-store pages (MiB)"))):
            a.plot(n, [x[key] / 2**20 for x in v["rows"]], "o-", color=f"C{c}", label=_name(label, v))
            a.set_title(name)
    for a in ax:
        a.set_xlabel("tiles the worker has run")
        a.legend(fontsize=8)
        a.set_ylim(bottom=0)
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--code", action="append", default=[], help="LABEL=PATH of a code tree (PYTHONPATH)")
    ap.add_argument("--length", type=float, default=400.0)
    ap.add_argument("--t1", type=int, default=2)
    ap.add_argument("--work", type=Path, default=Path("/tmp/hgca_drive_memory"))
    ap.add_argument("--results", type=Path, default=REPO / "benchmarks" / "results")
    ap.add_argument("--note", default="", help="a sentence for the page: what the code trees are")
    ap.add_argument("--pages-only", action="store_true",
                    help="write the page from the logs in --work (LABEL.jsonl) of an earlier run")
    ap.add_argument("--probe", nargs=2, metavar=("LABEL", "LOG"), help=argparse.SUPPRESS)
    args = ap.parse_args()
    scans = args.work / f"scans_{args.length:g}"
    if args.probe:
        probe(args.probe[0], scans, args.t1, Path(args.probe[1]))
        return 0
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from drive import build_drive

    from hgca_core.hardware import machine

    if not (scans / "poses.json").is_file() and not args.pages_only:
        build_drive(scans, args.length, 8.0)
    codes = dict(c.split("=", 1) for c in args.code) or {"this": str(REPO)}
    procs = {}
    for label, code in codes.items():
        log = args.work / f"{label}.jsonl"
        env = {**os.environ, "PYTHONPATH": str(Path(code).resolve())}
        procs[label] = (None if args.pages_only else
                        subprocess.Popen([sys.executable, __file__, "--length", str(args.length), "--t1",
                                          str(args.t1), "--work", str(args.work), "--probe", label, str(log)],
                                         env=env, cwd=args.work), log, code)
    result = {"machine": machine(), "length_m": args.length, "t1": args.t1, "note": args.note, "runs": {}}
    for label, (proc, log, code) in procs.items():
        if proc is not None and proc.wait() != 0:
            raise SystemExit(f"{label}: the drive failed ({proc.returncode})")
        rows = sorted((json.loads(line) for line in log.read_text().splitlines()), key=lambda x: x["t"])
        rev = subprocess.run(["git", "-C", code, "rev-parse", "--short", "HEAD"], capture_output=True, text=True)
        result["runs"][label] = {"code": rev.stdout.strip(), "rows": rows, "slope_mib_per_tile": slopes(rows)}
    result["tiles"] = max(len(v["rows"]) for v in result["runs"].values())
    args.results.mkdir(parents=True, exist_ok=True)
    (args.results / "drive_memory.json").write_text(json.dumps(result, indent=1))
    (args.results / "drive_memory.md").write_text(table(result))
    plot(result, args.results / "drive_memory.png")
    print(table(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
