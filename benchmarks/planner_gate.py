"""Could the BEV planner's rough occupancy gate the coarse chain's growth above a cut? (run by hand)
`python benchmarks/planner_gate.py [--weights W] --out benchmarks/results/planner_gate.json`

Why: the cells the coarse stage grows above a 2 m cut on the real logs that lie where the uncut scan saw empty
(`hgca eval-real`) stand mostly in open air beside real structures (`violation_anatomy.py`). The planner sees the
whole region at once and predicts a rough occupancy per 60 cm pillar and 2 m height bin (paper Eq. 6), unused when
sampling; its GroupNorm layers do not carry the kernel's BatchNorm statistics. If it gave those cells low
probability and the real cells cut away high, dropping the cells of pillars and bins it deems empty would lower
the share without losing recall. For each real input (the eval-real defaults), cut at `--cut` m, this samples the
coarse chain once (seed 0) and reports the planner's probability at the generated cells above the cut, split into
those in observed-empty space and the rest, and at the real cells cut away; then, per threshold, the share of
generated cells kept, their share in observed-empty space, and the share of real cut-away cells kept.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
TAUS = (0.05, 0.1, 0.2, 0.3, 0.5)


def gate(points: np.ndarray, origins: np.ndarray, index: np.ndarray, cut: float, weights: str | None) -> dict:
    import torch

    import hgca_core
    import hgca_core.models.gca as gca
    from hgca_core.geometry.freespace import observed_empty
    from hgca_core.geometry.region import BELOW_GROUND, Region, height_layer
    from hgca_core.geometry.voxel import COARSE, voxelize
    from hgca_core.models.planner import PILLAR

    seen = {}
    plain = gca.sample

    def sample(model, s0, grid, steps, generator, progress=None, free=None, forbid=None):  # noqa: ANN001, ANN202
        model.eval()
        with torch.no_grad():
            seen["rough"] = torch.sigmoid(model.bev(s0, 1, grid, free).rough)[0].float().numpy()
        return plain(model, s0, grid, steps, generator, progress, free, forbid)

    gca.sample = sample
    try:
        region = Region.around(points, sensor=origins[0])
        local = region.to_local(points)
        shape = region.grid_shape(COARSE)
        empty = observed_empty(local, region.to_local(origins), index, shape)
        keep = local[:, 2] < BELOW_GROUND + cut
        real = voxelize(local[region.contains_local(local)], COARSE, region.size)
        res = hgca_core.complete(points[keep], region=region, origins=origins, samples=1, seed=0, stage="coarse",
                                 weights=weights, origin_index=index[keep])
    finally:
        gca.sample = plain
    rough = seen["rough"]
    top = height_layer(cut, COARSE)

    def prob(c: np.ndarray) -> np.ndarray:
        zb = np.clip(c[:, 2] * rough.shape[0] // shape[2], 0, rough.shape[0] - 1)
        return rough[zb, np.clip(c[:, 0] // PILLAR, 0, rough.shape[1] - 1), np.clip(c[:, 1] // PILLAR, 0,
                                                                                     rough.shape[2] - 1)]

    gen = res[0].coarse_cells
    up = gen[gen[:, 2] >= top]
    bad = empty[up[:, 0], up[:, 1], up[:, 2]]
    p_gen, p_real = prob(up), prob(real[real[:, 2] >= top])
    q = lambda a: np.percentile(a, [10, 25, 50, 75, 90]).round(3).tolist() if len(a) else []  # noqa: E731
    rows = []
    for tau in TAUS:
        k = p_gen >= tau
        rows.append({"tau": tau, "generated_kept_pct": round(100 * float(k.mean()), 1),
                     "share_in_empty_pct": round(100 * float(bad[k].mean()), 1) if k.any() else None,
                     "real_kept_pct": round(100 * float((p_real >= tau).mean()), 1)})
    return {"above_cut": int(len(up)), "share_in_empty_pct": round(100 * float(bad.mean()), 1),
            "p_in_empty": q(p_gen[bad]), "p_other_generated": q(p_gen[~bad]), "p_real_cut_away": q(p_real),
            "gates": rows}


def main(argv: list[str] | None = None) -> int:
    from hgca_core.commands.eval_real import default_items
    from hgca_core.real_eval import input_rays

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--weights", default=None, help="coarse weights (default: the shipped ones)")
    p.add_argument("--cut", type=float, default=2.0)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--real-dir", default=str(REPO.parent / "shared" / "fixtures" / "real"))
    p.add_argument("--out", required=True, help="JSON file (the table goes beside it as .md)")
    args = p.parse_args(argv)
    import torch

    torch.set_num_threads(args.threads)
    rows = {}
    for item in default_items(args.real_dir):
        name = item["name"]
        rows[name] = gate(*input_rays(item), args.cut, args.weights)
        print(name, rows[name], file=sys.stderr)
    out = Path(args.out)
    out.write_text(json.dumps({"weights": args.weights or "shipped", "cut_m": args.cut, "inputs": rows}, indent=1)
                   + "\n")
    lines = ["| input | cells above the cut | in observed empty (%) | planner p: in observed empty, p10/p50/p90 | "
             "other generated | real cut away | " + " | ".join(f"gate p >= {t:g}: kept / in empty / real kept (%)"
                                                              for t in TAUS) + " |",
             "|---|---:|---:|---|---|---|" + "---|" * len(TAUS)]
    pick = lambda v: " / ".join(f"{x:g}" for x in (v[0], v[2], v[4])) if v else "-"  # noqa: E731
    for name, r in rows.items():
        gates = " | ".join(f"{g['generated_kept_pct']} / {g['share_in_empty_pct']} / {g['real_kept_pct']}"
                           for g in r["gates"])
        lines.append(f"| {name} | {r['above_cut']:,} | {r['share_in_empty_pct']} | {pick(r['p_in_empty'])} | "
                     f"{pick(r['p_other_generated'])} | {pick(r['p_real_cut_away'])} | {gates} |")
    out.with_suffix(".md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
