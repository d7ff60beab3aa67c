"""Coarse weights interpolated between two files, on val sweeps and on the real logs (run by hand):
`python benchmarks/blend_sweep.py --a hgca_core/weights/coarse.pt --b checkpoints/coarse_v7_4951.pt --ts 0.25,0.5
--out benchmarks/results/blend_sweep.json`.

Why: a fine-tune moves the model toward its new data and away from what it did well before; interpolating the
fine-tuned weights back toward the ones it started from (WiSE-FT, Wortsman et al., CVPR 2022) often keeps the gain
and the old strengths, and is most robust off the training distribution, which the real logs are. Each fraction t
gives `(1 - t) * a + t * b` (`hgca_core.models.weights.blend_files`), scored as `keep_sweep.py` scores thresholds:
`benchmarks/val_cut.py` (val sweeps, cut 2 m) and `hgca eval-real` (coarse stage, k = 3, cuts 2 m and 1.5 m).
Rows already scored the same way (the two end points) come in with `--known LABEL=VAL.json,REAL.json`.
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from keep_sweep import REPO, jobs, known_rows, machine_info, run_all, scored, table  # noqa: E402


def blended(a: str, b: str, t: float, folder: Path) -> Path:
    from hgca_core.models.weights import blend_files, save_file

    return save_file(blend_files(a, b, t), folder / f"coarse_blend{t:g}.pt")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--a", required=True, help="the weights the fine-tune started from (t = 0)")
    p.add_argument("--b", required=True, help="the fine-tuned weights (t = 1)")
    p.add_argument("--ts", default="0.25,0.5,0.75", help="comma list of fractions of b in [0, 1]")
    p.add_argument("--known", action="append", default=[], metavar="LABEL=VAL.json,REAL.json",
                   help="a row scored before by val_cut.py and hgca eval-real (repeatable)")
    p.add_argument("--data", default=str(REPO / "data" / "synth2"), help="dataset folder with a val split")
    p.add_argument("--samples", type=int, default=3)
    p.add_argument("--jobs", type=int, default=2, help="scoring processes at once (1 thread each)")
    p.add_argument("--keep-weights", default=None, metavar="DIR", help="also keep the blended files here")
    p.add_argument("--out", required=True, help="results JSON (the table goes to .md beside it)")
    args = p.parse_args(argv)
    ts = [float(t) for t in args.ts.split(",")] if args.ts else []
    results = known_rows(args.known)
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(args.keep_weights or tmp)
        folder.mkdir(parents=True, exist_ok=True)
        cmds = [c for t in ts for c in jobs(blended(args.a, args.b, t, folder), f"t{t:g}", folder, args.data,
                                             args.samples)]
        if not run_all(cmds, args.jobs):
            return 1
        results.update({f"t = {t:g}": scored(folder, f"t{t:g}") for t in ts})
    out = Path(args.out)
    info = {**machine_info(argparse.Namespace(weights=f"{args.a} (t = 0) and {args.b} (t = 1)", samples=args.samples,
                                              data=args.data)), "a": args.a, "b": args.b, "ts": ts,
            "known": args.known}
    out.write_text(json.dumps({**info, "results": results}, indent=1))
    head = (f"Coarse weights `(1 - t) * a + t * b`, a = {args.a}, b = {args.b} (`blend_files`); k = {args.samples}; "
            f"val: the first sweep of the first 4 val scenes of {args.data} (generator version {info['generator']}), "
            f"cut 2 m; real: `hgca eval-real` coarse stage. Machine: {info['machine']}, torch {info['torch']}, "
            f"1 thread per scoring process, precision {info['precision']}.\n\n")
    out.with_suffix(".md").write_text(head + table(results, label="weights"))
    print(out.with_suffix(".md").read_text())
    return 0


if __name__ == "__main__":
    sys.exit(main())
