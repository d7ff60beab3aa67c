"""Few-step students against the teacher, paired per scene, with the teacher's seed-to-seed band from the same run.

    .venv/bin/python benchmarks/students.py --data data/synth2f [--count 8] [--samples 3] [--full-count 4]
    .venv/bin/python benchmarks/students.py --page-only      (the page again from the JSON files of a run)

Runs `hgca eval` on the synthetic test split (IoU, ReSim, Street CD and their TMD, k samples per scene) for:
the teacher (coarse.pt, T1 30) at two seeds, the coarse student (coarse_student.pt, T1 10) and the teacher run
for the student's 10 steps untrained (what the training adds) at the first; then the full stage on the first
`--full-count` scenes the same way: best (coarse.pt + fine.pt) at two seeds, fast (both students), and the
teacher's files on 10 + 5 steps. A student holds a measure when its mean paired difference from the teacher is no worse than the
teacher's own mean seed-to-seed difference on those scenes. Each eval is its own process (one at a time, so their
seconds per completion are comparable). Writes benchmarks/results/students.{json,md,png}.
"""
from __future__ import annotations

import argparse
import json
import platform
import subprocess
import sys
from pathlib import Path

import numpy as np

from common import REPO, write_page

WEIGHTS = REPO / "hgca_core" / "weights"
OUT = REPO / "benchmarks" / "results"
SEEDS = (0, 1000)
STUDENT_STEPS = (10, 5)   # T1, T2 of the students
# metric: (label, higher is better)
METRICS = {"iou": ("IoU", True), "resim_min": ("ReSim min", False), "resim_avg": ("ReSim avg", False),
           "street_cd_min": ("Street CD min", False), "street_cd_avg": ("Street CD avg", False),
           "tmd": ("TMD (diversity)", True)}


def run_eval(name: str, args: argparse.Namespace, stage: str, count: int, seed: int, coarse: Path,
             fine: Path | None, work: Path, steps: tuple[int, int] | None = None) -> dict:
    out = work / f"{name}.json"
    if out.is_file():
        return json.loads(out.read_text())
    method = "hgca-full" if stage == "full" else "hgca"
    cmd = [sys.executable, "-m", "hgca_core.cli", "eval", "--data", args.data, "--split", "test", "--stage", stage,
           "--methods", method, "--count", str(count), "--samples", str(args.samples), "--seed", str(seed),
           "--weights", str(coarse), "-o", str(out)]
    if fine is not None:
        cmd += ["--fine-weights", str(fine)]
    if steps is not None:
        cmd += ["--t1", str(steps[0]), "--t2", str(steps[1])]
    print("$", " ".join(cmd), flush=True)
    subprocess.run(cmd, cwd=REPO, check=True)
    return json.loads(out.read_text())


REAL_METRICS = {"recall": ("2 m cut recall", True), "above_empty_share": ("above-cut share in observed empty", False),
                "above_core_share": ("above-cut share in its core", False)}


def run_real(name: str, args: argparse.Namespace, seed: int, coarse: Path, work: Path) -> dict:
    """`hgca eval-real` of the coarse stage (the real fixtures, cut 2 m above the ground)."""
    out = work / f"{name}.json"
    if not out.is_file():
        cmd = [sys.executable, "-m", "hgca_core.cli", "eval-real", "--methods", "hgca", "--cuts", "2",
               "--samples", str(args.samples), "--seed", str(seed), "--weights", str(coarse),
               "--threads", "1", "--no-render", "-o", str(out)]
        print("$", " ".join(cmd), flush=True)
        subprocess.run(cmd, cwd=REPO, check=True)
    return json.loads(out.read_text())


def real_rows(result: dict) -> dict:
    """{"per_scene": {metric: [per input]}} of an eval-real result (the cut case's mean over its samples)."""
    per: dict[str, list[float]] = {k: [] for k in REAL_METRICS}
    for name in sorted(result["inputs"]):
        case = next(v for k, v in result["inputs"][name]["cases"].items() if k.startswith("cut"))
        summary = case["rows"]["hgca"]["summary"]
        for key in REAL_METRICS:
            per[key].append(float(summary[key]["mean"]))
    seconds = [float(next(v for k, v in result["inputs"][n]["cases"].items() if k.startswith("cut"))["rows"]["hgca"]
                     ["seconds_per_completion"]) for n in sorted(result["inputs"])]
    return {"per_scene": per, "n": len(result["inputs"]), "seconds_per_completion": float(np.mean(seconds))}


def row(result: dict) -> dict:
    """The eval's row of the product: the coarse stage's one row, or the full stage's mesh (implicit) row."""
    rows = result["rows"]
    if len(rows) == 1:
        return next(iter(rows.values()))
    return next(v for k, v in rows.items() if "implicit" in k)


def paired(teacher: dict, band: dict, student: dict, metrics: dict = METRICS) -> dict:
    """Per metric: the teacher's mean, the student's mean paired difference, the teacher's seed-to-seed band (mean
    absolute per-scene difference between its two seeds) and whether the student holds (no worse than the band)."""
    out = {}
    for key, (label, higher) in metrics.items():
        t = np.asarray(teacher["per_scene"].get(key, []), dtype=np.float64)
        b = np.asarray(band["per_scene"].get(key, []), dtype=np.float64)
        s = np.asarray(student["per_scene"].get(key, []), dtype=np.float64)
        if not (len(t) and len(t) == len(b) == len(s)):
            continue
        ok = np.isfinite(t) & np.isfinite(b) & np.isfinite(s)
        delta = (s - t)[ok]
        noise = float(np.mean(np.abs(b - t)[ok]))
        worse = -float(delta.mean()) if higher else float(delta.mean())   # > 0: the student is worse
        out[key] = {"label": label, "teacher": float(t[ok].mean()), "student": float(s[ok].mean()),
                    "delta": float(delta.mean()), "band": noise, "scenes": int(ok.sum()),
                    "student_better_scenes": int(((delta > 0) if higher else (delta < 0)).sum()),
                    "holds": bool(worse <= noise)}
    return out


def cpu() -> dict:
    info = {"machine": platform.machine(), "python": platform.python_version()}
    try:
        text = Path("/proc/cpuinfo").read_text()
        info["model"] = next(ln.split(":", 1)[1].strip() for ln in text.splitlines() if ln.startswith("model name"))
        flags = next(ln.split(":", 1)[1].split() for ln in text.splitlines() if ln.startswith("flags"))
        info["flags"] = sorted(f for f in flags if f.startswith(("avx", "amx", "fma")))
    except (OSError, StopIteration):
        pass
    import os

    info["cores"] = os.cpu_count()
    return info


def page(r: dict) -> str:
    where = (f"on the synthetic test split (`{r['data']}`), paired per scene, {r['samples']} samples per scene"
             if set(r["pairs"]) - {"real"} else "on the real scans, paired per scan")
    lines = ["# Few-step students against the teacher", "",
             "What `--quality fast` (the students, `hgca train --recipe coarse-student` / `fine-student`) costs in "
             f"quality against `--quality best` (the teacher chains of the paper), {where}. The band is the teacher's own "
             "seed-to-seed difference (seeds 0 and 1000), measured in the same run: a student *holds* a measure when "
             "its mean difference from the teacher is no worse than that band. Made by `benchmarks/students.py`.", "",
             f"Machine: {r['cpu'].get('model', '?')}, {r['cpu'].get('cores')} cores, "
             f"flags {' '.join(r['cpu'].get('flags', []))}.", ""]
    student = Path(r.get("coarse_student", "coarse_student.pt")).name
    if student != "coarse_student.pt":
        lines += [f"The coarse student here is `{r['coarse_student']}`, not the shipped one (made by "
                  "`hgca train --recipe coarse-student --set distill=1.0`, selected on val, exported with "
                  "`--export`).", ""]
    titles = (("coarse", f"Coarse stage: {student} (T1 10) vs coarse.pt (T1 30)"),
              ("coarse_short", "Coarse stage, untrained: coarse.pt run for 10 steps vs its own 30"),
              ("full", "Full stage: fast (both students, T1 10 + T2 5) vs best (T1 30 + T2 15)"),
              ("full_short", "Full stage, untrained: coarse.pt + fine.pt run for 10 + 5 steps vs 30 + 15"),
              ("real", f"Real scans (`hgca eval-real`, cut 2 m above the ground): {student} vs coarse.pt"))
    for part, title in titles:
        if part not in r["pairs"]:
            continue
        p = r["pairs"][part]
        base = part.split("_")[0]   # coarse_short -> coarse
        who = "short" if part.endswith("_short") else "student"
        k = f", k = {r.get('real_samples')} samples each" if part == "real" else ""
        lines += [f"## {title}", "", f"{r['scenes'][base]} scenes{k}; seconds per completion: teacher "
                  f"{r['seconds'][base]['teacher']:.1f}, {who} {r['seconds'][base].get(who, float('nan')):.1f} "
                  "(in the eval's process, one at a time).", "",
                  f"| measure | teacher | {who} | {who} - teacher | teacher seed band | {who} better on | holds |",
                  "|---|---:|---:|---:|---:|---:|---|"]
        for m in p.values():
            lines.append(f"| {m['label']} | {m['teacher']:.4f} | {m['student']:.4f} | {m['delta']:+.4f} | "
                         f"{m['band']:.4f} | {m['student_better_scenes']}/{m['scenes']} | "
                         f"{'yes' if m['holds'] else 'no'} |")
        lines.append("")
    lines += ["IoU at 20 cm over visible cells (higher is better); ReSim and Street CD are Chamfer-type distances, "
              "x10 in metres as in the paper (lower is better); TMD is the spread between a scene's samples "
              "(higher: more diverse). Real scans: each input's mean over its samples; recall is the share of the "
              "cells cut away above 2 m that the completion brings back, the shares are of the generated cells above "
              "the cut that lie where the sensor saw empty space (lower is better).", "",
              f"![{r.get('page', 'students')}]({r.get('page', 'students')}.png)", ""]
    return "\n".join(lines)


def plot(r: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    parts = [p for p in ("coarse", "coarse_short", "full", "full_short", "real") if p in r["pairs"]]
    fig, axes = plt.subplots(1, len(parts), figsize=(4.5 * len(parts), 3.6), squeeze=False)
    for ax, part in zip(axes[0], parts):
        items = list(r["pairs"][part].values())
        x = np.arange(len(items))
        ax.bar(x, [m["delta"] for m in items], color=["tab:green" if m["holds"] else "tab:red" for m in items])
        ax.errorbar(x, np.zeros(len(items)), yerr=[m["band"] for m in items], fmt="none", ecolor="k", capsize=4,
                    label="teacher seed band")
        ax.axhline(0, color="grey", lw=0.8)
        ax.set_xticks(x, [m["label"] for m in items], rotation=30, ha="right", fontsize=8)
        ax.set_title(f"{part}: student - teacher (green: holds)", fontsize=9)
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", default="data/synth2f")
    ap.add_argument("--count", type=int, default=8, help="test scenes for the coarse stage")
    ap.add_argument("--full-count", type=int, default=4, help="test scenes for the full stage (0: none)")
    ap.add_argument("--samples", type=int, default=3)
    ap.add_argument("--work", default="runs/students_eval", help="the evals' JSON files (a rerun reuses them)")
    ap.add_argument("--parts", default="coarse,full", help="which parts to run (two invocations, one part each, "
                                                             "can share a machine's cores)")
    ap.add_argument("--page-only", action="store_true")
    ap.add_argument("--coarse-student", default=None, help="another coarse student's weights against the teacher "
                                                            "(default: the shipped coarse_student.pt)")
    ap.add_argument("--page", default="students", help="the results page's name (benchmarks/results/NAME.md)")
    args = ap.parse_args()
    work = REPO / args.work
    work.mkdir(parents=True, exist_ok=True)
    coarse_t = WEIGHTS / "coarse.pt"
    coarse_s = Path(args.coarse_student).resolve() if args.coarse_student else WEIGHTS / "coarse_student.pt"
    fine_t, fine_s = WEIGHTS / "fine.pt", WEIGHTS / "fine_student.pt"
    # "short": the teacher's weights run on the students' short chains untrained (what the training adds)
    runs = {"coarse": {"teacher": ("coarse", args.count, SEEDS[0], coarse_t, None),
                       "band": ("coarse", args.count, SEEDS[1], coarse_t, None),
                       "student": ("coarse", args.count, SEEDS[0], coarse_s, None),
                       "short": ("coarse", args.count, SEEDS[0], coarse_t, None, STUDENT_STEPS)}}
    if args.full_count:
        runs["full"] = {"teacher": ("full", args.full_count, SEEDS[0], coarse_t, fine_t),
                        "band": ("full", args.full_count, SEEDS[1], coarse_t, fine_t),
                        "student": ("full", args.full_count, SEEDS[0], coarse_s, fine_s),
                        "short": ("full", args.full_count, SEEDS[0], coarse_t, fine_t, STUDENT_STEPS)}
    result = {"data": args.data, "samples": args.samples, "cpu": cpu(), "pairs": {}, "scenes": {}, "seconds": {},
              "weights": {}}
    wanted = set(args.parts.split(","))
    for part, named in runs.items():
        if part not in wanted and not args.page_only:
            continue
        rows = {}
        for who, spec in named.items():
            name = f"{part}_{who}"
            if args.page_only and not (work / f"{name}.json").is_file():
                break
            res = run_eval(name, args, *spec[:5], work, *spec[5:])
            rows[who] = row(res)
            result["weights"][name] = res.get("weights_sha256")
        if len(rows) < 3:
            continue
        result["pairs"][part] = paired(rows["teacher"], rows["band"], rows["student"])
        if "short" in rows:
            result["pairs"][f"{part}_short"] = paired(rows["teacher"], rows["band"], rows["short"])
        result["scenes"][part] = rows["teacher"]["n"]
        result["seconds"][part] = {w: float(rows[w].get("seconds_per_completion", float("nan"))) for w in rows}
    if "real" in wanted or args.page_only:
        names = {"teacher": (SEEDS[0], coarse_t), "band": (SEEDS[1], coarse_t), "student": (SEEDS[0], coarse_s)}
        rows = {}
        for who, (seed, weights) in names.items():
            if args.page_only and not (work / f"real_{who}.json").is_file():
                break
            res = run_real(f"real_{who}", args, seed, weights, work)
            rows[who] = real_rows(res)
            result["real_samples"] = res["config"]["samples"]
        if len(rows) == 3:
            result["pairs"]["real"] = paired(rows["teacher"], rows["band"], rows["student"], REAL_METRICS)
            result["scenes"]["real"] = rows["teacher"]["n"]
            result["seconds"]["real"] = {w: rows[w]["seconds_per_completion"] for w in rows}
    result["page"] = args.page
    result["coarse_student"] = str(coarse_s.relative_to(REPO)) if coarse_s.is_relative_to(REPO) else str(coarse_s)
    print(write_page(OUT, args.page, result, page, plot))
    return 0


if __name__ == "__main__":
    sys.exit(main())
