"""Per-scene paired differences between `hgca eval` JSONs of the same split (run by hand), e.g.
`python benchmarks/paired_eval.py runs/x_test.json runs/y_test.json` against the shipped weights' record.

Why: eight test scenes differ from each other far more than two weights differ on one scene, so a mean IoU moves by
a point between two evaluations of the same weights (sampling), while the per-scene difference of two weights is
tight (three evaluations of the shipped weights agreed within 0.3 points, recipe_s25.md). A candidate is judged by
the mean paired difference +- its standard error and how many scenes it lowers, not by its mean alone.
"""
from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

KEYS = {"iou": 100.0, "resim_min": 10.0, "street_cd_min": 10.0}   # metric -> scale as the tables print it
ROW = "hGCA coarse (planner)"


def standard_error(values: list[float]) -> float:
    """Standard error of the mean (sample standard deviation over sqrt(n); NaN for fewer than two values): how far
    a mean over n scenes, or over k samples, may move on a re-draw."""
    n = len(values)
    if n < 2:
        return float("nan")
    mean = sum(values) / n
    return math.sqrt(sum((v - mean) ** 2 for v in values) / (n - 1) / n)


def paired(candidate: dict, base: dict, row: str = ROW) -> dict[str, dict]:
    """{metric: {mean, diff, se, lower, n}} of candidate - base on the scenes both scored."""
    if candidate["files"] != base["files"]:
        raise SystemExit("the two evaluations scored different scenes: pair only runs of the same --split/--count")
    out = {}
    for key, scale in KEYS.items():
        x = candidate["rows"][row]["per_scene"][key]
        y = base["rows"][row]["per_scene"][key]
        d = [scale * (a - b) for a, b in zip(x, y)]
        n = len(d)
        mean = sum(d) / n
        out[key] = {"mean": scale * sum(x) / n, "diff": mean, "se": standard_error(d), "lower": sum(v < 0 for v in d),
                    "n": n}
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("candidates", nargs="+", help="hgca eval --out JSONs")
    p.add_argument("--base", default=str(Path(__file__).resolve().parents[1] / "hgca_core/weights/eval_test.json"))
    p.add_argument("--row", default=ROW)
    args = p.parse_args(argv)
    base = json.loads(Path(args.base).read_text())
    for f in args.candidates:
        r = paired(json.loads(Path(f).read_text()), base, args.row)
        cols = [f"{k} {v['mean']:.2f} (diff {v['diff']:+.2f} +- {v['se']:.2f}, {v['lower']}/{v['n']} lower)"
                for k, v in r.items()]
        print(f"{f} | " + " | ".join(cols))
    return 0


if __name__ == "__main__":
    sys.exit(main())
