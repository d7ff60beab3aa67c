"""The Blender user's whole way, timed step by step on each Blender line: zip, Install Core, import, Complete, Solid view.

    .venv/bin/python benchmarks/blender_done.py [--lines 50,45,42]        (runs the slow test on each line)
    .venv/bin/python benchmarks/blender_done.py --from-json A.json B.json  (a page from runs made already)

Each line runs tests/blender/test_blender_done.py (marked slow) in its own bpy: bpy 5.0 from .venv, the LTS lines
from .venv-bpy45 / .venv-bpy42 (`make .venv-bpy45/.installed`), with HGCA_STEP_TIMES set so the test writes its
step times. Install Core reads torch and the other wheels from a folder the test fills with `pip download` (the
offline path). Writes benchmarks/results/blender_done.{md,json,png}.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PYTHONS = {"50": REPO / ".venv" / "bin" / "python", "45": REPO / ".venv-bpy45" / "bin" / "python",
           "42": REPO / ".venv-bpy42" / "bin" / "python"}


def run_line(line: str) -> dict:
    out = Path(tempfile.mkdtemp(prefix="hgca_done_")) / "steps.json"
    env = {**os.environ, "HGCA_STEP_TIMES": str(out), "HGCA_PYTHON": str(PYTHONS["50"])}
    proc = subprocess.run([str(PYTHONS[line]), "-m", "pytest", "-q", "-s", "-p", "no:cacheprovider",
                           "--confcutdir=tests/blender", "tests/blender/test_blender_done.py", "-m", "slow"],
                          cwd=REPO, env=env, capture_output=True, text=True, timeout=3600)
    if proc.returncode != 0 or not out.is_file():
        raise RuntimeError(f"bpy {line}: the test failed ({proc.returncode}):\n{proc.stdout[-4000:]}")
    return json.loads(out.read_text())


def chart(runs: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    steps = list(runs[0]["seconds"])
    fig, ax = plt.subplots(figsize=(10, 3.2))
    left = [0.0] * len(runs)
    for step in steps:
        values = [r["seconds"].get(step, 0.0) for r in runs]
        ax.barh([r["blender"] for r in runs], values, left=left, label=step)
        left = [a + b for a, b in zip(left, values)]
    ax.set_xlabel("seconds")
    ax.set_title("From the zip to confidence in Solid view, per step")
    ax.legend(fontsize=7, loc="center left", bbox_to_anchor=(1.0, 0.5))
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def write_page(runs: list[dict], out_dir: Path) -> None:
    steps = list(runs[0]["seconds"])
    lines = ["# Blender without a terminal, step by step", "",
             "Each Blender line (the `bpy` module from PyPI) goes the whole way in a fresh user folder: build the "
             "extension zip, install it from disk, *Install Core* (a venv in the extension's user folder, hgca from "
             "the zip, torch 2.13 CPU and the rest from a local folder of wheels), *Check* (imports torch, loads the "
             "shipped weights), import the real nuScenes sweep, *Complete* (9.6 m region, full stage, 2 samples) "
             "and see the result coloured by observed/generated and by agreement in Solid view (Workbench, read back). "
             f"Measured by `benchmarks/blender_done.py` (tests/blender/test_blender_done.py) on {platform.machine()}, "
             f"{os.cpu_count()} cores; 1-minute load average at the start and end of each line: "
             + ", ".join(f"{r['blender']} {r['load_average'][0]} / {r['load_average'][1]}"
                         for r in runs if "load_average" in r) + ".", "",
             "![step times](blender_done.png)", "",
             "| step | " + " | ".join(r["blender"] for r in runs) + " |",
             "|---|" + "---:|" * len(runs)]
    for step in steps:
        lines.append(f"| {step} | " + " | ".join(f"{r['seconds'].get(step, float('nan')):.1f}" for r in runs) + " |")
    lines.append("| total | " + " | ".join(f"{sum(r['seconds'].values()):.1f}" for r in runs) + " |")
    lines += ["", "All times in seconds. *Check* includes torch's first import in the new environment.", ""]
    shown = [k for k in runs[0].get("feedback", {})]
    if shown:
        lines += ["While *Complete* runs (the job's timer driven as Blender's loop does; the longest call is the "
                  "longest freeze the job causes):", "",
                  "| what | " + " | ".join(r["blender"] for r in runs) + " |", "|---|" + "---:|" * len(runs)]
        lines += [f"| {k} | " + " | ".join(f"{r.get('feedback', {}).get(k, float('nan')):g}" for r in runs) + " |"
                  for k in shown]
        lines.append("")
    (out_dir / "blender_done.md").write_text("\n".join(lines))
    (out_dir / "blender_done.json").write_text(json.dumps(runs, indent=2))
    chart(runs, out_dir / "blender_done.png")


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--lines", default="50,45,42", help="bpy lines to run: 50 (.venv), 45, 42")
    p.add_argument("--from-json", nargs="*", type=Path, default=None, help="step-time files the test wrote")
    p.add_argument("--out-dir", type=Path, default=REPO / "benchmarks" / "results")
    args = p.parse_args()
    if args.from_json:
        runs = [json.loads(f.read_text()) for f in args.from_json]
    else:
        runs = [run_line(line) for line in args.lines.split(",")]
    args.out_dir.mkdir(parents=True, exist_ok=True)
    write_page(runs, args.out_dir)
    for r in runs:
        print(r["blender"], r["seconds"])
    return 0


if __name__ == "__main__":
    sys.exit(main())
