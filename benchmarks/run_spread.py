"""How far runs of one training recipe land apart on the real logs, against what their scoring can resolve (run by
hand): `python benchmarks/run_spread.py --group "W41 recipe=A.json+B.json,C.json" --group "W38 recipe=D.json"
--out benchmarks/results/F.json`.

Why: weights have been selected one training run at a time, under a rule that compares a run's k-sample means with
their standard errors (`recipe_s38.md`). That rule is sound only if a second run of the same recipe lands within
those errors of the first. Runs that differ only in `hgca train --seed` (same scenes, same start, same steps) give
the spread between runs of one recipe directly; this puts it beside the within-run standard error of each log's
above-cut share. Each group is runs of one recipe; each run one `hgca eval-real` results file (A.json+B.json:
disjoint seeds of the same weights, pooled by `keep_sweep.pooled`), with `--cuts` holding 2.0.
"""
from __future__ import annotations

import argparse
import json
import math
import statistics
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from cut_frontier import _legend, page_out, points  # noqa: E402  (benchmarks reuse each other's readers)
from keep_sweep import pooled, scores  # noqa: E402


def parse_group(item: str) -> tuple[str, list[str]]:
    """'NAME=SPEC,SPEC' -> (NAME, [SPEC, ...]); a SPEC is a results file or several joined by '+'."""
    name, sep, runs = item.partition("=")
    specs = [s.strip() for s in runs.split(",") if s.strip()]
    if not sep or not name.strip() or not specs:
        raise ValueError(f"{item!r}: expected NAME=RUN.json[,RUN.json ...]")
    return name.strip(), specs


def _sd(values: list[float]) -> float | None:
    """Sample standard deviation (n - 1), None for a single run: one run says nothing about the spread."""
    return statistics.stdev(values) if len(values) > 1 else None


def spread(groups: dict[str, list[str]]) -> dict[str, dict[str, dict]]:
    """{log: {group: summary}}: per run (label, recall %, share %, s.e. %, k), the group's means, the standard
    deviation between its runs, the root mean square of the runs' own standard errors of the share (what one run's
    k samples resolve) and their ratio (about 1 where runs differ only by sampling; above, the runs themselves
    differ)."""
    labels = {g: [f"{g} #{i + 1}" for i in range(len(specs))] for g, specs in groups.items()}
    none = {"inputs": {}}   # real logs only: no val sweeps
    pts = points({lab: scores(none, pooled(spec)) for g, specs in groups.items()
                  for lab, spec in zip(labels[g], specs)})
    out: dict[str, dict[str, dict]] = {}
    for log, by_label in pts.items():
        for g in groups:
            runs = [(lab, *by_label[lab][:2], by_label[lab][3], by_label[lab][4])
                    for lab in labels[g] if lab in by_label]
            if not runs:
                continue
            recall, share = [r[1] for r in runs], [r[2] for r in runs]
            sems = [r[3] for r in runs if r[3] is not None]
            within = math.sqrt(statistics.fmean(s * s for s in sems)) if sems else None
            between = _sd(share)
            out.setdefault(log, {})[g] = {
                "runs": [dict(zip(("label", "recall", "share", "sem", "k"), r)) for r in runs],
                "recall_mean": statistics.fmean(recall), "recall_sd": _sd(recall),
                "share_mean": statistics.fmean(share), "share_sd": between, "share_sem_within": within,
                "ratio": between / within if between is not None and within else None}
    return out


def _num(v: float | None, fmt: str = ".1f") -> str:
    return "-" if v is None else format(v, fmt)


def table(result: dict[str, dict[str, dict]], specs: dict[str, list[str]]) -> str:
    lines = ["| log | group | runs | recall % (each run) | above-cut share % ± s.e. (each run) | recall mean / sd "
             "| share mean / sd between runs | s.e. within a run (rms) | sd between / s.e. within |",
             "|---|---|---:|---|---|---|---|---:|---:|"]
    for log, groups in result.items():
        for g, s in groups.items():
            each_r = ", ".join(f"{r['recall']:.1f}" for r in s["runs"])
            each_s = ", ".join(f"{r['share']:.1f}" + ("" if r["sem"] is None else f" ± {r['sem']:.1f}")
                               for r in s["runs"])
            lines.append(f"| {log} | {g} | {len(s['runs'])} | {each_r} | {each_s} | {s['recall_mean']:.1f} / "
                         f"{_num(s['recall_sd'])} | {s['share_mean']:.1f} / {_num(s['share_sd'])} | "
                         f"{_num(s['share_sem_within'])} | {_num(s['ratio'], '.2f')} |")
    runs = "\n".join(f"- {g}: " + "; ".join(f"#{i + 1} `{spec}`" for i, spec in enumerate(v)) for g, v in specs.items())
    return "\n".join(lines) + "\n\nRuns:\n" + runs + "\n"


def plot(result: dict[str, dict[str, dict]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(dict.fromkeys(g for groups in result.values() for g in groups))
    fig, axes = plt.subplots(1, len(result), figsize=(4.2 * len(result), 4), squeeze=False)
    for ax, (log, groups) in zip(axes[0], result.items()):
        for g, s in groups.items():
            c = f"C{names.index(g) % 10}"
            for r in s["runs"]:
                ax.errorbar(r["recall"], r["share"], yerr=r["sem"], fmt="o", ms=6, color=c, capsize=3, alpha=0.8)
            ax.errorbar(s["recall_mean"], s["share_mean"], xerr=s["recall_sd"], yerr=s["share_sd"], fmt="x", ms=12,
                        mew=2, color=c, capsize=5, label=f"{g} (n = {len(s['runs'])})")
        ax.set_title(log, fontsize=9)
        ax.set_xlabel("2 m recall (%) ↑")
        ax.set_ylabel("above-cut growth in observed empty (%) ↓")
        ax.grid(alpha=0.3)
    # one legend under the panels: group names are long, and inside a panel they hide its points
    fig.legend(*_legend(axes[0]), loc="lower center", ncol=1, fontsize=8, frameon=False)
    fig.suptitle("runs (o, ± s.e. of k samples) and their group mean (x, ± sd between runs)", fontsize=9)
    fig.tight_layout(rect=(0, 0.05 * len(names) + 0.02, 1, 1))
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--group", action="append", required=True, metavar="NAME=RUN.json[,RUN.json ...]",
                   help="runs of one recipe (repeatable), each an eval-real results file or A.json+B.json pooled")
    p.add_argument("--out", required=True, help="results JSON (.md and .png beside it)")
    args = p.parse_args(argv)
    try:
        groups = dict(parse_group(g) for g in args.group)
    except ValueError as e:
        p.error(f"--group {e}")
    # before `spread` reads them: an output over an input was once reported as a --group error
    out = page_out(p, args.out, [f for specs in groups.values() for spec in specs for f in spec.split("+")])
    try:
        result = spread(groups)
    except (ValueError, OSError) as e:   # a results file missing, not JSON or not poolable
        p.error(f"--group {e}")
    out.write_text(json.dumps({"groups": groups, "spread": result}, indent=1))
    out.with_suffix(".md").write_text(
        "# Spread between training runs of one recipe on the real logs (cut 2 m)\n\n"
        "Each run: its k-sample mean and the standard error of that mean. Per group: the mean over its runs, the "
        "standard deviation between them, and the ratio of that deviation to the runs' own standard error (about 1 "
        "where runs differ by sampling alone).\n\n" + table(result, groups)
        + f"\nRendering: `{out.with_suffix('.png').name}`.\n")
    plot(result, out.with_suffix(".png"))
    print(out.with_suffix(".md").read_text())
    return 0


if __name__ == "__main__":
    sys.exit(main())
