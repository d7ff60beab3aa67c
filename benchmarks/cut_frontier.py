"""Recall against the growth in seen-empty space above a 2 m cut, of weights scored before (run by hand):
`python benchmarks/cut_frontier.py --row shipped=VAL.json,REAL.json --row e=... --out benchmarks/results/F.json`.

Why: every fine-tune so far that put less of its above-cut growth where the rays saw empty also grew less and
recovered less of the cut-away cells (`recipe_s24.md` ... `recipe_s30.md`), so a lower share alone is not progress.
One plot per input set (the av2-profile synthetic val sweeps of `val_cut.py --profiles av2`, each real log of
`hgca eval-real`) puts every row at (2 m recall, above-cut share): a recipe that helps lies below and to the right
of the shipped weights, not on the line the others trace. The rows' files come from `val_cut.py` and `hgca
eval-real` with `--cuts` holding 2.0; `keep_sweep.known_rows` reads them, pooling runs of other seeds given as
A.json+B.json (`keep_sweep.pooled`).
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from keep_sweep import known_rows, row_files  # noqa: E402  (benchmarks reuse each other's readers)

from hgca_core.errors import InputError  # noqa: E402
from hgca_core.io.paths import check_outputs  # noqa: E402

CUT = "cut_2"


Point = tuple  # (recall %, above-cut share %, cells grown above, standard error of the share % or None, samples k)


def _sem(cuts: list[dict]) -> float | None:
    """Standard error (%) of the mean of the cuts' above-cut shares, each known to its own standard error."""
    sems = [c.get("above_empty_sem") for c in cuts]
    return None if None in sems else 100 * float(sum(e * e for e in sems)) ** 0.5 / len(sems)


def points(rows: dict[str, dict], val_name: str = "synthetic val sweeps") -> dict[str, dict[str, Point]]:
    """{input set: {label: Point}}; val sweeps averaged into one set. The standard error says which gaps the k
    samples can tell apart: a real log's share moves 1-2 points from one draw of k = 3 to the next."""
    out: dict[str, dict[str, Point]] = {}
    for label, sc in rows.items():
        val = [v[CUT] for k, v in sc.items() if k.startswith("val/")]
        if val:
            out.setdefault(val_name, {})[label] = (*(
                sum(v[f] for v in val) / len(val) * s for f, s in
                (("recall", 100), ("above_empty_share", 100), ("generated_above", 1))),
                _sem(val), min(v.get("k", 0) for v in val))
        for k, v in sc.items():
            if not k.startswith("val/"):
                c = v[CUT]
                out.setdefault(k, {})[label] = (100 * c["recall"], 100 * c["above_empty_share"], c["generated_above"],
                                                _sem([c]), c.get("k", 0))
    return out


def _cell(p: Point) -> str:
    rec, share, cells, sem, k = p
    return f"{rec:.1f} / {share:.1f}{'' if sem is None else f' ± {sem:.1f}'} / {cells:,.0f} / {k}"


def _labels(pts: dict[str, dict[str, Point]]) -> list[str]:
    """Every row's label once, in the order given (a row scored on the real logs only is in no val set)."""
    return list(dict.fromkeys(label for rows in pts.values() for label in rows))


def table(pts: dict[str, dict[str, Point]]) -> str:
    sets = list(pts)
    head = " | ".join(f"{s}: recall % / above-cut in obs. empty % ± s.e. / cells above / k" for s in sets)
    lines = [f"| weights | {head} |", "|---|" + "---|" * len(sets)]
    for label in _labels(pts):
        cells = " | ".join(_cell(pts[s][label]) if label in pts[s] else "-" for s in sets)
        lines.append(f"| {label} | {cells} |")
    return "\n".join(lines) + "\n"


def agreement(pts: dict[str, dict[str, Point]], val_name: str) -> dict[str, tuple[float, float, int]]:
    """{input set: (Spearman rank correlation of recall, of above-cut share, rows)} between the val sweeps and each
    other set, over the rows both hold. Why: selecting on the val sweeps helps only where they rank weights as the
    real logs do; with fewer than 4 rows a rank correlation says nothing, so none is given."""
    from scipy.stats import spearmanr

    val = pts.get(val_name, {})
    out = {}
    for name, rows in pts.items():
        both = [k for k in rows if k in val and name != val_name]
        if len(both) >= 4:
            rho = [float(spearmanr([val[k][i] for k in both], [rows[k][i] for k in both])[0]) for i in (0, 1)]
            out[name] = (rho[0], rho[1], len(both))
    return out


def plot(pts: dict[str, dict[str, Point]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    labels = _labels(pts)   # one colour a row in every panel, none repeated, the first (reference) a star
    colours = [f"C{i}" for i in range(10)] if len(labels) <= 10 else list(plt.cm.tab20.colors)
    fig, axes = plt.subplots(1, len(pts), figsize=(4.2 * len(pts), 4), squeeze=False)
    for ax, (name, rows) in zip(axes[0], pts.items()):
        for label, (rec, share, _, sem, _) in rows.items():
            i = labels.index(label)
            ax.errorbar(rec, share, yerr=sem, fmt="*" if i == 0 else "o", ms=13 if i == 0 else 7,
                        color=colours[i % len(colours)], capsize=3, label=label)
        ax.set_title(name, fontsize=9)
        ax.set_xlabel("2 m recall (%) ↑")
        ax.set_ylabel("above-cut growth in observed empty (%) ↓")
        ax.grid(alpha=0.3)
    axes[0][0].legend(*_legend(axes[0]), fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _legend(axes) -> tuple[list, list[str]]:
    """Handles and labels of every panel's rows, each label once (no panel need hold them all)."""
    seen: dict[str, object] = {}
    for ax in axes:
        for h, lab in zip(*ax.get_legend_handles_labels()):
            seen.setdefault(lab, h)
    return list(seen.values()), list(seen)


def page_out(p: argparse.ArgumentParser, out: str, inputs: list[str]) -> Path:
    """`--out` of a results page: a .json path (the .md and .png are named from it: without the suffix the JSON has
    none) whose three files overwrite no input (the project's one output check: by path or inode, a writable
    folder); argparse's error, exit 2, otherwise."""
    path = Path(out)
    if path.suffix != ".json":
        p.error(f"--out {path}: name a .json file (the .md and .png are written beside it)")
    try:
        check_outputs([path, path.with_suffix(".md"), path.with_suffix(".png")], inputs)
    except InputError as e:
        p.error(f"--out {e}")
    return path


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--row", action="append", required=True, metavar="LABEL=VAL.json,REAL.json",
                   help="one weights file's val_cut.py and eval-real results (repeatable; the first is the reference); "
                        "either may be A.json+B.json, runs of the same weights with disjoint seeds, pooled; either "
                        "may be left out, not both: LABEL=,REAL.json (scored on the real logs only), LABEL=VAL.json, "
                        "(screened out on the val sweeps)")
    p.add_argument("--val-name", default="synthetic val sweeps",
                   help="what the rows' val files hold, for the table and plot (e.g. 'av2-profile val sweeps')")
    p.add_argument("--out", required=True, help="results JSON (.md and .png beside it)")
    args = p.parse_args(argv)
    try:
        rows = known_rows(args.row)
    except (ValueError, OSError) as e:   # a malformed --row, a results file missing or not JSON
        p.error(f"--row {e}")
    out = page_out(p, args.out, row_files(args.row))
    pts = points(rows, args.val_name)
    ranks = agreement(pts, args.val_name)
    out.write_text(json.dumps({"rows": args.row, "val_name": args.val_name, "points": pts, "rank_agreement": ranks},
                              indent=1))
    said = "".join(f"| {n} | {r:+.2f} | {s:+.2f} | {k} |\n" for n, (r, s, k) in ranks.items())
    said = ("\nDo the val sweeps rank the weights as each input set does? Spearman rank correlation over the rows "
            "(1: the same order, 0: unrelated):\n\n| input set | recall | above-cut share | rows |\n|---|---:|---:|---:|\n"
            + said) if said else ""
    out.with_suffix(".md").write_text("# Recall against above-cut growth in observed empty space (cut 2 m)\n\n"
                                      "Means over k samples (k in each cell); ± the standard error of the share's "
                                      "mean over the samples (val: of the sweeps' mean).\n\n"
                                      + table(pts) + said + f"\nRendering: `{out.with_suffix('.png').name}`.\n")
    plot(pts, out.with_suffix(".png"))
    print(out.with_suffix(".md").read_text())
    return 0


if __name__ == "__main__":
    sys.exit(main())
