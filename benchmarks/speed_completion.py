"""Old code against new code on the default region of `hgca demo`, side by side in one interleaved timing call.

    git worktree add /tmp/old <commit>                      # the code to compare against
    python benchmarks/speed_completion.py --harness TIMER --old /tmp/old --new . [--stage full] [-n 2] [--out speed]
    python benchmarks/speed_completion.py --parse STAGE=FILE ...  # the page from saved timing reports

Each run is a fresh `hgca complete` process of the bundled example (5 scans, its 38.4 x 38.4 x 8 m region, seed 0,
fp32, the shipped weights) with the tree on PYTHONPATH; the harness (an A/B process timer called as
`TIMER -n N --warmup 0 --timeout S --vs B -- A`) runs new and old in turn (A B A B ...) and takes the ratio pair by
pair, so a drift of the machine's speed touches both alike. `--new-args` (e.g. "--t1 20 --t2 10") are passed to the
new side's `hgca complete` only. Wall, CPU and peak RSS are the
operating system's accounting of each finished process. Writes benchmarks/results/<out>.{md,json,png}.
"""
from __future__ import annotations

import argparse
import json
import re
import shlex
import subprocess
import time
from pathlib import Path

from common import write_page

REPO = Path(__file__).resolve().parents[1]
EXAMPLE = REPO / "hgca_core" / "examples"
RESULTS = REPO / "benchmarks" / "results"


def command(root: Path, stage: str, tag: str, python: str, extra: str = "") -> str:
    """One completion of the example as a shell command for the timer (output kept in /tmp/speed_<tag>.log)."""
    region = ",".join(f"{v:.6f}" for v in json.loads((EXAMPLE / "poses.json").read_text())["region"])
    scans = " ".join(str(EXAMPLE / f"street_scan{i}.laz") for i in range(5))
    inner = (f"cd /tmp && PYTHONPATH={root} exec {python} -m hgca_core.cli complete {scans} "
             f"--poses={EXAMPLE / 'poses.json'} --region={region} --stage {stage} --progress none {extra} "
             f"-o /tmp/speed_{tag}.ply >>/tmp/speed_{tag}.log 2>&1")
    return f"sh -c {shlex.quote(inner)}"


def parse(text: str) -> dict:
    """The medians (min, max) of a timing report: {"A wall s": [min, median, max], ...} and its header."""
    rows = {}
    for line in text.splitlines():
        m = re.match(r"^(A|B|A/B) ([a-z]+(?: [a-zA-Z]+)?)\s+([\d.]+)\s+([\d.]+)\s+([\d.]+)", line)
        if m:
            rows[f"{m.group(1)} {m.group(2)}"] = [float(m.group(k)) for k in (3, 4, 5)]
    first = text.splitlines()[0] if text else ""
    head = " | ".join(f.strip() for f in first.split("|")[1:])   # the date, cores and pinning, not the timer's name
    n = re.search(r"n: A (\d+), B (\d+)", text)
    return {"header": head, "runs": [int(n.group(1)), int(n.group(2))] if n else None, "rows": rows}


def page(result: dict) -> str:
    lines = ["# Completion speed, old code against new", "",
             "`python benchmarks/speed_completion.py`: interleaved fresh `hgca complete` processes of the bundled "
             "example (the default region of `hgca demo`, 38.4 x 38.4 x 8 m, 5 scans), new (A) and old (B) in turn, "
             "fp32, seed 0, the shipped weights. Median [min - max] of the runs; A/B is taken pair by pair.", ""]
    for cfg in result["configs"]:
        r = cfg["report"]["rows"]
        lines += [f"## Stage {cfg['stage']}", "", f"New: {cfg['new']}; old: {cfg['old']}. {cfg['report']['header']}",
                  f"Runs: {cfg['report']['runs']}" + (f"; load average (1 min) at the start {cfg['load']}." if "load" in cfg
                                                      else "."), "",
                  "| measure | new (A) | old (B) | new / old |", "|---|---:|---:|---:|"]
        for key, name in (("wall s", "wall (s)"), ("cpu s", "CPU, user + sys (s)"), ("peak MiB", "peak RSS (MiB)")):
            a, b, ab = r.get(f"A {key}"), r.get(f"B {key}"), r.get(f"A/B {key.split()[0]}")
            if a and b:
                ratio = f"{ab[1]:.3f} [{ab[0]:.3f} - {ab[2]:.3f}]" if ab else f"{a[1] / b[1]:.3f}"
                lines.append(f"| {name} | {a[1]:.1f} [{a[0]:.1f} - {a[2]:.1f}] | {b[1]:.1f} [{b[0]:.1f} - {b[2]:.1f}] "
                             f"| {ratio} |")
        lines.append("")
    for note in result.get("notes", []):
        lines += [note, ""]
    return "\n".join(lines) + "\n"


def plot(result: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cfgs = result["configs"]
    fig, axes = plt.subplots(1, 3, figsize=(11, 3.6))
    for ax, (key, name) in zip(axes, (("wall s", "wall (s)"), ("cpu s", "CPU (s)"), ("peak MiB", "peak RSS (MiB)"))):
        for i, cfg in enumerate(cfgs):
            r = cfg["report"]["rows"]
            for j, (side, colour) in enumerate((("B", "#999999"), ("A", "#1f77b4"))):
                v = r.get(f"{side} {key}")
                if v:
                    ax.bar(i * 3 + j, v[1], color=colour, yerr=[[v[1] - v[0]], [v[2] - v[1]]], capsize=3,
                           label=("old" if side == "B" else "new") if i == 0 else None)
        ax.set_xticks([i * 3 + 0.5 for i in range(len(cfgs))], [c["stage"] for c in cfgs])
        ax.set_title(name)
    axes[0].legend()
    fig.suptitle("default region of `hgca demo`: old vs new code, same timing call (median, min-max)")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--harness", default=None, help="the A/B process timer to run (needed unless --parse)")
    ap.add_argument("--new-args", default="", help="extra `hgca complete` options of the new side")
    ap.add_argument("--old", type=Path, help="tree of the old code (a git worktree)")
    ap.add_argument("--new", type=Path, default=REPO)
    ap.add_argument("--stage", nargs="+", default=["full"], choices=["coarse", "full"])
    ap.add_argument("-n", type=int, default=2, help="runs of each side")
    ap.add_argument("--timeout", type=int, default=3000)
    ap.add_argument("--python", default=str(REPO / ".venv" / "bin" / "python"))
    ap.add_argument("--parse", nargs="*", default=None, metavar="STAGE=FILE",
                    help="build the page from saved timing reports instead of running")
    ap.add_argument("--label-old", default=None)
    ap.add_argument("--label-new", default=None)
    ap.add_argument("--note", action="append", default=[], help="a paragraph for the page's end")
    ap.add_argument("--out", default="speed")
    args = ap.parse_args()
    configs = []
    if args.parse is not None:
        for item in args.parse:
            stage, _, file = item.partition("=")
            configs.append({"stage": stage, "old": args.label_old, "new": args.label_new,
                            "report": parse(Path(file).read_text())})
    else:
        for stage in args.stage:
            a, b = (command(args.new.resolve(), stage, f"new_{stage}", args.python, args.new_args),
                    command(args.old.resolve(), stage, f"old_{stage}", args.python))
            load = round(__import__("os").getloadavg()[0], 1)
            out = subprocess.run([args.harness, "-n", str(args.n), "--warmup", "0", "--timeout", str(args.timeout),
                                  "--vs", b, "--", *shlex.split(a)], capture_output=True, text=True).stdout
            configs.append({"stage": stage, "old": args.label_old or str(args.old), "new": args.label_new or
                            str(args.new), "load": load, "report": parse(out),
                            "raw": "\n".join(out.splitlines()[1:])})   # the figure rows, not the timer's banner
    result = {"date": time.strftime("%Y-%m-%d %H:%M", time.gmtime()), "configs": configs, "notes": args.note}
    print(write_page(RESULTS, args.out, result, page, plot))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
