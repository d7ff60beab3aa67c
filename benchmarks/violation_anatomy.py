"""Where does growth above a cut land in space the real rays saw empty? (run by hand)
`python benchmarks/violation_anatomy.py --weights W --out benchmarks/results/violation_anatomy_<tag>.json`

Why: `hgca eval-real` counts the share of cells generated above a 2 m cut that lie where the uncut scan's rays saw
empty, but not what they are. A model that extends walls upward past their real tops needs streets whose walls end
lower; one that grows structures thicker or beside the real ones needs a loss that weighs that space. For each
real input (the eval-real defaults) this completes the input cut `--cut` m above the ground (coarse stage, sample 0
of `--seed`) and describes those cells: their height above the ground; their distance to the nearest cell the
uncut input holds (cells next to a hit are never seen empty, so the least is 0.4 m); whether their column stands
over, or within 20 / 60 cm of, a column the uncut input holds 1.6-2.0 m up (a structure the cut crossed); and the
tallest cut-input cell within 60 cm (only ground there: a structure grown over open ground); and whether the line
from the sensor through the cell meets a cell the uncut input holds within 1 m behind it, before it, both or
neither (in front of a real surface, inside something rays see through, or in open air).
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
BANDS = ((2.0, 3.0), (3.0, 4.0), (4.0, 5.0), (5.0, 9.0))


def anatomy(points: np.ndarray, origins: np.ndarray, index: np.ndarray, cut: float, weights: str | None,
            seed: int) -> dict:
    from scipy.ndimage import binary_dilation, distance_transform_edt, maximum_filter

    import hgca_core
    from hgca_core.geometry.freespace import observed_empty
    from hgca_core.geometry.region import BELOW_GROUND, Region
    from hgca_core.geometry.voxel import COARSE, voxelize

    region = Region.around(points, sensor=origins[0])
    local = region.to_local(points)
    shape = region.grid_shape(COARSE)
    inside = region.contains_local(local)
    empty = observed_empty(local, region.to_local(origins), index, shape)
    keep = local[:, 2] < BELOW_GROUND + cut

    def grid(mask: np.ndarray) -> np.ndarray:
        g = np.zeros(shape, dtype=bool)
        c = voxelize(local[mask], COARSE, region.size)
        g[c[:, 0], c[:, 1], c[:, 2]] = True
        return g

    occ, cut_occ = grid(inside), grid(inside & keep)
    res = hgca_core.complete(points[keep], region=region, origins=origins, samples=1, seed=seed, stage="coarse",
                             weights=weights, origin_index=index[keep])
    layer = lambda h: int(np.floor((BELOW_GROUND + h) / COARSE + 1e-9))  # noqa: E731
    gen = res[0].coarse_cells
    up = gen[gen[:, 2] >= layer(cut)]
    bad = up[empty[up[:, 0], up[:, 1], up[:, 2]]]
    if not len(bad):
        return {"above_cut": len(up), "in_seen_empty": 0}
    col = (bad[:, 0], bad[:, 1])
    height = (bad[:, 2] + 0.5) * COARSE - BELOW_GROUND
    dist = distance_transform_edt(~occ)[bad[:, 0], bad[:, 1], bad[:, 2]] * COARSE
    base = occ[:, :, layer(1.6):layer(2.0)].any(axis=2)
    top = np.where(cut_occ.any(axis=2), shape[2] - 1 - np.argmax(cut_occ[:, :, ::-1], axis=2), -1)
    near_top = (maximum_filter(top, size=7)[col] + 0.5) * COARSE - BELOW_GROUND
    pct = lambda m: round(100.0 * float(np.mean(m)), 1)  # noqa: E731
    sensor = region.to_local(origins)[0]
    back, front = along_ray(bad, occ, sensor, 1.0), along_ray(bad, occ, sensor, -1.0)
    return {"above_cut": len(up), "in_seen_empty": len(bad), "share_pct": round(100.0 * len(bad) / len(up), 1),
            "height_m_p10_p50_p90": np.percentile(height, [10, 50, 90]).round(2).tolist(),
            "height_bands": {f"{a:g}-{b:g}": int(((height >= a) & (height < b)).sum()) for a, b in BANDS},
            "distance_m_p10_p50_p90": np.percentile(dist, [10, 50, 90]).round(2).tolist(),
            "over_structure_pct": pct(base[col]), "within_20cm_pct": pct(binary_dilation(base, iterations=1)[col]),
            "within_60cm_pct": pct(binary_dilation(base, iterations=3)[col]),
            "only_ground_within_60cm_pct": pct(near_top < 0.5), "ray_within_1m_pct": {
                "real_behind_only": pct(back & ~front), "real_behind_and_before": pct(back & front),
                "real_before_only": pct(front & ~back), "neither": pct(~back & ~front)}}


def along_ray(cells: np.ndarray, occ: np.ndarray, sensor: np.ndarray, reach: float) -> np.ndarray:
    """Per cell: does the line from the sensor through its centre meet a cell the uncut input holds within |reach|
    metres beyond it (reach > 0) or before it, toward the sensor (reach < 0)? Behind only: grown in front of a real
    surface; behind and before: inside something the rays see through (a tree crown, a fence); neither: open air,
    e.g. above where a structure ends."""
    from hgca_core.geometry.voxel import COARSE

    centre = (cells + 0.5) * COARSE
    ray = centre - sensor
    ray /= np.linalg.norm(ray, axis=1, keepdims=True)
    hit = np.zeros(len(cells), dtype=bool)
    for s in np.sign(reach) * np.arange(COARSE, abs(reach) + 1e-9, COARSE / 2):
        c = np.floor((centre + s * ray) / COARSE).astype(np.int64)
        ok = np.all((c >= 0) & (c < occ.shape), axis=1)
        hit[ok] |= occ[c[ok, 0], c[ok, 1], c[ok, 2]]
    return hit


def adapt_bn() -> None:
    """Test-time BatchNorm statistics (AdaBN, Li et al. 2016): every coarse chain first runs once on its own input
    in train mode to set the statistics (`recompute_bn`), samples with them, and puts the weights' own back."""
    import copy

    import hgca_core.models.gca as gca
    from hgca_core.training.precise_bn import recompute_bn

    plain = gca.sample

    def adapted(model, s0, grid, steps, generator, progress=None, free=None, forbid=None):  # noqa: ANN001, ANN202
        saved = copy.deepcopy(model.state_dict())
        recompute_bn(model, [(s0[:, 1:], None if free is None else free[0])], grid, steps, seed=123)
        try:
            return plain(model, s0, grid, steps, generator, progress, free, forbid)
        finally:
            model.load_state_dict(saved)

    gca.sample = adapted


def main(argv: list[str] | None = None) -> int:
    from hgca_core.commands.eval_real import default_items
    from hgca_core.real_eval import input_rays

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--weights", default=None, help="coarse weights (default: the shipped ones)")
    p.add_argument("--cut", type=float, default=2.0, help="cut height above the ground (metres)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--threads", type=int, default=1, help="torch CPU threads")
    p.add_argument("--real-dir", default=str(REPO.parent / "shared" / "fixtures" / "real"))
    p.add_argument("--adapt-bn", action="store_true",
                   help="recompute BatchNorm statistics on each cut input's own chain before sampling (AdaBN)")
    p.add_argument("--out", required=True, help="JSON file (the table goes beside it as .md)")
    args = p.parse_args(argv)
    import torch

    torch.set_num_threads(args.threads)
    if args.adapt_bn:
        adapt_bn()
    rows = {}
    for item in default_items(args.real_dir):
        name = item["name"]
        rows[name] = anatomy(*input_rays(item), args.cut, args.weights, args.seed)
        print(name, rows[name], file=sys.stderr)
    out = Path(args.out)
    out.write_text(json.dumps({"weights": args.weights or "shipped", "cut_m": args.cut, "seed": args.seed,
                               "adapt_bn": args.adapt_bn, "inputs": rows}, indent=1) + "\n")
    head = ("| input | above cut | in seen-empty (%) | height p10/p50/p90 (m) | distance to real p10/p50/p90 (m) | "
            "over a 1.6-2 m structure (%) | within 20 cm (%) | within 60 cm (%) | only ground within 60 cm (%) | "
            "along the ray within 1 m: real behind only / behind and before / before only / neither (%) |")
    lines = [head, "|---|---:|---:|---|---|---:|---:|---:|---:|---|"]
    for name, r in rows.items():
        if not r["in_seen_empty"]:
            lines.append(f"| {name} | {r['above_cut']:,} | 0 | - | - | - | - | - | - | - |")
            continue
        lines.append(f"| {name} | {r['above_cut']:,} | {r['share_pct']:.1f} | "
                     f"{' / '.join(f'{v:g}' for v in r['height_m_p10_p50_p90'])} | "
                     f"{' / '.join(f'{v:g}' for v in r['distance_m_p10_p50_p90'])} | {r['over_structure_pct']} | "
                     f"{r['within_20cm_pct']} | {r['within_60cm_pct']} | {r['only_ground_within_60cm_pct']} | "
                     f"{' / '.join(f'{v:g}' for v in r['ray_within_1m_pct'].values())} |")
    out.with_suffix(".md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
