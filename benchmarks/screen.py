"""Screen coarse weights on the synthetic val sweeps before the real logs (run by hand):
`python benchmarks/screen.py --data data/synth2f --row t=runs/t.pt --row c=runs/c.pt
--prefix benchmarks/results/recipe_s35 --recall-min 71 --share-max 7.1 --yaw30-share-max 5.8`.

Why: scoring a weights file on the three real logs takes 7.5 min a process and their above-cut shares swing by a
point or two between draws, so candidates are screened first on `val_cut.py`'s val sweeps, scored in two settings
(session 33-34, `recipe_s34.md`): as they are (yaw 0), whose recall ranks weights as every real log does, and with the
region turned 30 deg (`--yaw 30`), whose above-cut share ranks them as the AV2 logs do (their streets cross the grid).
Each row is scored in both settings (results `PREFIX_val_NAME.json` and `PREFIX_valyaw30_NAME.json`; files that exist
and are complete are read, not scored again, so a screen resumes and a row scored earlier costs nothing), then judged
against the thresholds given, written down before the screen runs: the table (`PREFIX_screen.md`) says which clause
each row fails.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import val_cut  # noqa: E402  (benchmarks reuse each other's readers)
from cut_frontier import CUT, points  # noqa: E402
from keep_sweep import known_rows, run_all  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
SETTINGS = {"val": 0.0, "valyaw30": 30.0}   # results-file tag -> region yaw (deg)


def result_file(prefix: str, tag: str, name: str) -> Path:
    return Path(f"{prefix}_{tag}_{name}.json")


def complete(path: Path, count: int, samples: int) -> bool:
    """Whether a results file holds every sweep's cut case with `samples` samples: `hgca eval-real` saves after each
    input, so a screen stopped midway leaves a file that must be scored again, not read."""
    try:
        inputs = json.loads(path.read_text())["inputs"]
        return len(inputs) >= count and all(
            len(v["cases"][CUT]["rows"]["hgca"]["per_sample"]) >= samples for v in inputs.values())
    except (OSError, ValueError, KeyError, TypeError):
        return False


def commands(rows: dict[str, str], prefix: str, data: str, count: int, samples: int) -> list[list[str]]:
    """val_cut.py commands for every (row, setting) whose results file is not there yet or is incomplete."""
    cmds = []
    for name, weights in rows.items():
        for tag, yaw in SETTINGS.items():
            out = result_file(prefix, tag, name)
            if not complete(out, count, samples):
                cmds.append(val_cut.command(weights, out, data, samples, count=count, yaw=yaw))
    return cmds


def verdicts(rows: dict[str, str], prefix: str, rule: dict[str, float | None]) -> dict[str, dict]:
    """{row: {"val": (recall %, share %, cells above), "valyaw30": (...), "fails": [clauses]}} from the results
    files."""
    out = {}
    for name in rows:
        got = {}
        for tag in SETTINGS:
            pts = points(known_rows([f"{name}={result_file(prefix, tag, name)},"]), tag)
            got[tag] = tuple(round(v, 2) for v in pts[tag][name][:3])
        fails = []
        if rule["recall_min"] is not None and got["val"][0] < rule["recall_min"]:
            fails.append(f"yaw-0 recall {got['val'][0]:.1f} < {rule['recall_min']:g}")
        if rule["share_max"] is not None and got["val"][1] > rule["share_max"]:
            fails.append(f"yaw-0 share {got['val'][1]:.1f} > {rule['share_max']:g}")
        if rule["yaw30_share_max"] is not None and got["valyaw30"][1] > rule["yaw30_share_max"]:
            fails.append(f"yaw-30 share {got['valyaw30'][1]:.1f} > {rule['yaw30_share_max']:g}")
        out[name] = {**got, "fails": fails}
    return out


def table(found: dict[str, dict]) -> str:
    lines = ["| weights | yaw 0: recall % / above-cut share % / cells above | yaw 30: recall % / share % / cells above "
             "| screen |", "|---|---|---|---|"]
    for name, v in found.items():
        cell = lambda p: f"{p[0]:.1f} / {p[1]:.1f} / {p[2]:,.0f}"
        lines.append(f"| {name} | {cell(v['val'])} | {cell(v['valyaw30'])} | "
                     f"{'fails: ' + '; '.join(v['fails']) if v['fails'] else 'passes'} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--row", action="append", required=True, metavar="NAME=WEIGHTS", help="a coarse weights file")
    p.add_argument("--prefix", required=True, help="results path prefix: PREFIX_val_NAME.json, ..._screen.md")
    p.add_argument("--data", default=str(REPO / "data" / "synth2f"), help="dataset folder with a val split")
    p.add_argument("--count", type=int, default=4, help="val scenes (their first sweeps)")
    p.add_argument("--samples", type=int, default=3)
    p.add_argument("--jobs", type=int, default=2, help="scoring processes at a time (one thread each)")
    p.add_argument("--recall-min", type=float, default=None, help="yaw-0 2 m recall (%%) a row needs")
    p.add_argument("--share-max", type=float, default=None, help="yaw-0 above-cut share (%%) a row may have")
    p.add_argument("--yaw30-share-max", type=float, default=None, help="yaw-30 above-cut share (%%) a row may have")
    args = p.parse_args(argv)
    rows = {}
    for item in args.row:
        name, eq, weights = item.partition("=")
        if not eq or not name.replace("_", "").replace("-", "").isalnum() or not Path(weights).is_file():
            p.error(f"--row {item!r}: expected NAME=WEIGHTS, NAME of letters, digits, _ and -, WEIGHTS a file")
        if name in rows:
            p.error(f"--row {item!r}: the name {name} is given twice")
        rows[name] = weights
    cmds = commands(rows, args.prefix, args.data, args.count, args.samples)
    if cmds and not run_all(cmds, max(1, args.jobs)):
        return 2
    rule = {"recall_min": args.recall_min, "share_max": args.share_max, "yaw30_share_max": args.yaw30_share_max}
    found = verdicts(rows, args.prefix, rule)
    out = Path(f"{args.prefix}_screen.json")
    out.write_text(json.dumps({"rows": rows, "rule": rule, "data": args.data, "count": args.count,
                               "samples": args.samples, "screen": found}, indent=1))
    md = ("# Screen on the synthetic val sweeps, as they are (yaw 0) and turned 30 deg\n\n"
          f"`benchmarks/screen.py`: the first sweeps of {args.count} val scenes of `{args.data}`, k = {args.samples}, "
          f"cut 2 m; rule: {', '.join(f'{k} {v:g}' for k, v in rule.items() if v is not None) or 'none (table only)'}."
          "\n\n" + table(found))
    out.with_suffix(".md").write_text(md)
    print(md)
    return 0


if __name__ == "__main__":
    sys.exit(main())
