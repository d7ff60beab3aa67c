"""How far do BatchNorm statistics alone move the coarse chain's growth on real scans? (run by hand)
`python benchmarks/bn_noise.py --data D --few 10 --many 400 --seeds 5 --out benchmarks/results/bn_noise.json`

Why: until session 15 the trainer's exported weights carried the live model's running statistics, a momentum-0.1
average of its last ~10 batches. This keeps every parameter of `--weights` and sets the statistics from `--few`
training batches (as such a copy holds) or from `--many` (precise BN), each with several seeds, then completes the
real inputs cut `--cut` m above the ground (coarse stage, sample 0; `violation_anatomy.anatomy`) and counts the
cells grown above the cut and the share of them where the uncut scans' rays saw empty. The weights' own
statistics are the first row. A spread over seeds of `--few` that is wide and one of `--many` that is narrow says
that checkpoints differ there by the draw of their last batches, not by what they learned.
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from precise_bn import add_args, precise, save  # noqa: E402
from violation_anatomy import REPO, anatomy  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    import torch

    from hgca_core.commands.eval_real import default_items
    from hgca_core.real_eval import input_rays

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_args(p)
    p.add_argument("--few", type=int, default=10, help="batches of a copied, last-batches estimate")
    p.add_argument("--many", type=int, default=400, help="batches of a precise estimate")
    p.add_argument("--seeds", type=int, default=5, help="draws of --few (--many gets 2)")
    p.add_argument("--inputs", default="0", help="comma list of indices into the eval-real inputs (0: AV2 7fab)")
    p.add_argument("--cut", type=float, default=2.0)
    p.add_argument("--real-dir", default=str(REPO.parent / "shared" / "fixtures" / "real"))
    p.add_argument("--out", required=True, help="results JSON (the table goes to .md beside it)")
    args = p.parse_args(argv)
    torch.set_num_threads(args.threads)
    fixtures = default_items(args.real_dir)
    items = {}
    for i in (int(k) for k in args.inputs.split(",")):
        items[fixtures[i]["name"]] = input_rays(fixtures[i])
    draws = [("own", 0, 0)] + [("few", args.few, s) for s in range(args.seeds)] + [("many", args.many, s)
                                                                                      for s in range(2)]
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for kind, batches, seed in draws:
            t = time.time()
            if kind == "own":
                w, what = args.weights, "the weights' own statistics"
            else:
                model, what = precise(args, "training", batches, seed)
                w = save(model, args.weights, what, str(Path(tmp) / f"bn_{batches}_{seed}.pt"))
            res = {name: anatomy(*rays, args.cut, w, 0) for name, rays in items.items()}
            rows.append({"kind": kind, "batches": batches, "seed": seed, "what": what, "wall_s": round(time.time() - t),
                         "inputs": {n: {"above_cut": r["above_cut"], "share_pct": r.get("share_pct", 0.0)}
                                    for n, r in res.items()}})
            print(json.dumps(rows[-1]), file=sys.stderr)
    out = Path(args.out)
    out.write_text(json.dumps({"weights": args.weights, "data": args.data, "cut_m": args.cut, "rows": rows},
                              indent=1) + "\n")
    names = list(items)
    data = " + ".join(args.data)
    lines = [f"Coarse weights {args.weights}, every parameter kept; BatchNorm statistics from training batches of "
             f"{data} (crop {args.crop}, focus {args.focus:g}, cut share {args.cut_share:g}); real inputs cut "
             f"{args.cut:g} m above the ground, coarse stage, sample 0.\n",
             "| statistics | " + " | ".join(f"{n}: cells above cut / in obs. empty %" for n in names) + " |",
             "|---|" + "---|" * len(names)]
    for r in rows:
        label = "own (as shipped)" if r["kind"] == "own" else f"{r['batches']} batches, seed {r['seed']}"
        lines.append(f"| {label} | " + " | ".join(f"{r['inputs'][n]['above_cut']:,} / {r['inputs'][n]['share_pct']:.1f}"
                                                 for n in names) + " |")
    for kind in ("few", "many"):
        sel = [r for r in rows if r["kind"] == kind]
        for n in names:
            a = [r["inputs"][n]["above_cut"] for r in sel]
            s = [r["inputs"][n]["share_pct"] for r in sel]
            lines.append(f"\n{sel[0]['batches']} batches, {n}: cells above {min(a):,}-{max(a):,} (max/min "
                         f"{max(a) / max(min(a), 1):.2f}), share {min(s):.1f}-{max(s):.1f} %.")
    out.with_suffix(".md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
