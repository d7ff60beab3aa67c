"""Hostile-input campaign against the real `hgca` executable: every case of tests/hostile/ in its own
subprocess (`python -m hgca_core.cli ...`), checked for exit 2, an `error:` line, no traceback, untouched
inputs and no new files. Writes benchmarks/results/hostile_inputs.{json,md,png}.

    .venv/bin/python benchmarks/hostile_inputs.py [--only SUBSTRING] [--timeout 120]
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

from common import REPO  # noqa: I001  (puts tests/ on the path: the cases and folder_state are the tests')
from builders import folder_state
from hostile import CASES


def run_case(case, timeout: float) -> dict:
    with tempfile.TemporaryDirectory(prefix="hgca_hostile_") as tmp:
        folder = Path(tmp)
        argv = case.build(folder)
        before = folder_state(folder)
        env = dict(os.environ, OMP_NUM_THREADS="1")
        t0 = time.perf_counter()
        try:
            res = subprocess.run([sys.executable, "-m", "hgca_core.cli", *argv], capture_output=True, text=True,
                                 timeout=timeout, cwd=folder, env=env, stdin=subprocess.DEVNULL)
            code, err = res.returncode, res.stderr
        except subprocess.TimeoutExpired:
            code, err = None, f"timed out after {timeout} s"
        seconds = time.perf_counter() - t0
        unchanged = folder_state(folder) == before
    errors = [line for line in err.splitlines() if "error:" in line]
    problems = []
    if code != 2:
        problems.append(f"exit {code}")
    if "Traceback" in err:
        problems.append("traceback")
    if not errors:
        problems.append("no error line")
    if case.expect and case.expect not in err:
        problems.append(f"message lacks {case.expect!r}")
    if not unchanged:
        problems.append("files changed")
    return {"case": case.name, "group": case.group, "exit": code, "seconds": round(seconds, 2), "ok": not problems,
            "problems": problems, "message": errors[-1] if errors else err.strip()[-300:]}


GROUPS = {c.name: c.group for c in CASES}


def plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    groups = sorted({GROUPS[r["case"]] for r in rows}, reverse=True)
    ok = Counter(GROUPS[r["case"]] for r in rows if r["ok"])
    bad = Counter(GROUPS[r["case"]] for r in rows if not r["ok"])
    fig, ax = plt.subplots(figsize=(7.5, 3.4))
    ax.barh(groups, [ok[g] for g in groups], color="#4a8", label="exit 2, clear error, inputs unchanged")
    ax.barh(groups, [bad[g] for g in groups], left=[ok[g] for g in groups], color="#d53", label="failed a check")
    for i, g in enumerate(groups):
        ax.text(ok[g] + bad[g] + 0.5, i, f"{ok[g]}/{ok[g] + bad[g]}", va="center", fontsize=8)
    ax.set_xlim(0, max(ok[g] + bad[g] for g in groups) * 1.45)
    ax.set_xlabel("cases")
    ax.set_title(f"hgca hostile-input campaign: {sum(ok.values())} of {len(rows)} cases pass")
    ax.legend(loc="lower right", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--only", default="", help="run only cases whose name contains this")
    p.add_argument("--timeout", type=float, default=120.0)
    p.add_argument("--out", default=str(REPO / "benchmarks" / "results" / "hostile_inputs"))
    p.add_argument("--replot", action="store_true", help="only redraw the PNG from the JSON of an earlier run")
    args = p.parse_args()
    if args.replot:
        plot(json.loads(Path(args.out).with_suffix(".json").read_text())["rows"], Path(args.out).with_suffix(".png"))
        return 0
    cases = [c for c in CASES if args.only in c.name]
    rows = []
    t0 = time.perf_counter()
    for i, case in enumerate(cases):
        row = run_case(case, args.timeout)
        rows.append(row)
        mark = "ok  " if row["ok"] else "FAIL"
        print(f"[{i + 1:3d}/{len(cases)}] {mark} {row['seconds']:6.2f} s  {case.name}"
              + ("" if row["ok"] else f"  ({', '.join(row['problems'])})"), flush=True)
    total = time.perf_counter() - t0
    failed = [r for r in rows if not r["ok"]]
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    summary = {"cases": len(rows), "passed": len(rows) - len(failed), "failed": len(failed),
               "seconds": round(total, 1), "python": sys.version.split()[0], "rows": rows}
    out.with_suffix(".json").write_text(json.dumps(summary, indent=1) + "\n")
    lines = [f"# hgca hostile-input campaign", "",
             f"{len(rows)} cases, each a fresh `python -m hgca_core.cli` process; {len(rows) - len(failed)} pass "
             f"(exit 2, an `error:` line, no traceback, inputs unchanged, nothing written), {len(failed)} fail. "
             f"Wall time {total:.0f} s on this machine.", "", "![summary](hostile_inputs.png)", "",
             "| case | exit | s | message |", "|---|---|---|---|"]
    for r in rows:
        msg = r["message"].replace("|", "\\|")
        msg = msg if len(msg) < 160 else msg[:157] + "..."
        lines.append(f"| {r['case']} | {r['exit']}{'' if r['ok'] else ' **' + ', '.join(r['problems']) + '**'} "
                     f"| {r['seconds']} | {msg} |")
    out.with_suffix(".md").write_text("\n".join(lines) + "\n")
    plot(rows, out.with_suffix(".png"))
    print(f"{len(rows) - len(failed)}/{len(rows)} cases pass in {total:.0f} s; wrote {out}.{{json,md,png}}")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
