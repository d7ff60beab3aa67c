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
neither (in front of a real surface, inside something rays see through, or in open air); and whether their
column is part of a thin wall along the region's grid axes or of a block 60 cm or more across (`column_kinds`),
beside the same shares for the rest of the growth above the cut and for the real cells above it. With rendering, `<out stem>_<input>.png` shows them from above and from the side.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
BANDS = ((2.0, 3.0), (3.0, 4.0), (4.0, 5.0), (5.0, 9.0))


def column_kinds(columns: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """(thin wall along the grid, block), (X, Y) bool each, for a set of 20 cm columns: a block is a column inside
    a filled 3 x 3 square of them (a volume at least 60 cm across, such as a crown or a solid mass); a thin wall
    along the grid is a column on a straight run of at least `n` along x or along y that is not in a block. A wall
    at the 15 deg of a real street to the axes is rasterised as runs of about 4 cells, so a 2 m run (10 cells) is
    a wall that follows the grid, as the synthetic streets are laid out, not the street."""
    from scipy.ndimage import binary_opening

    block = binary_opening(columns, structure=np.ones((3, 3), dtype=bool))
    runs = (binary_opening(columns, structure=np.ones((n, 1), dtype=bool))
            | binary_opening(columns, structure=np.ones((1, n), dtype=bool)))
    return runs & ~block, block


def render(png: Path, title: str, up: np.ndarray, bad: np.ndarray, real_up: np.ndarray, below: np.ndarray,
           sensor: np.ndarray) -> None:
    """Top and side view (20 cm cells of the region grid): the cut input (grey), the real cells above the cut the
    uncut input holds (red), what the model grew above the cut (blue) and the part of it the rays saw empty
    (black)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(16, 8), gridspec_kw={"width_ratios": [1, 1.2]})
    for ax, (i, j), label in zip(axes, ((0, 1), (0, 2)), ("top view: x, y", "side view: x, z")):
        ax.scatter(below[:, i], below[:, j], s=1, c="0.8", label="cut input (0.3 m above the ground and up)")
        ax.scatter(real_up[:, i], real_up[:, j], s=1, c="tab:red", label="real cells above the cut (uncut input)")
        ax.scatter(up[~bad, i], up[~bad, j], s=1, c="tab:blue", alpha=0.3, label="grown above the cut")
        ax.scatter(up[bad, i], up[bad, j], s=2, c="k", label="grown where the uncut input's rays saw empty")
        ax.plot(sensor[i], sensor[j], "g*", ms=14)
        ax.set_aspect("equal")
        ax.set_title(label, fontsize=10)
        ax.set_xlabel("20 cm cells")
    axes[0].legend(loc="upper left", fontsize=8, markerscale=4)
    fig.suptitle(title + " (green star: the sensor)", fontsize=11)
    fig.tight_layout()
    fig.savefig(png, dpi=70)
    plt.close(fig)


def anatomy(points: np.ndarray, origins: np.ndarray, index: np.ndarray, cut: float, weights: str | None,
            seed: int, yaw_deg: float = 0.0, png: Path | None = None) -> dict:
    from scipy.ndimage import binary_dilation, distance_transform_edt, maximum_filter

    import hgca_core
    from hgca_core.geometry.freespace import observed_empty
    from hgca_core.geometry.region import BELOW_GROUND, Region, height_layer
    from hgca_core.geometry.voxel import COARSE, column_tops, voxelize

    region = Region.around(points, sensor=origins[0], yaw=float(np.radians(yaw_deg)))
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
    layer = lambda h: height_layer(h, COARSE)  # noqa: E731
    gen = res[0].coarse_cells
    up = gen[gen[:, 2] >= layer(cut)]
    is_bad = empty[up[:, 0], up[:, 1], up[:, 2]]
    bad = up[is_bad]
    real_up = np.argwhere(occ[:, :, layer(cut):])
    real_up[:, 2] += layer(cut)
    if png is not None:
        below = np.argwhere(cut_occ[:, :, layer(0.3):])
        below[:, 2] += layer(0.3)
        render(png, f"{png.stem}: cut {cut:g} m, {len(up):,} cells grown above it, {len(bad):,} "
               f"({100.0 * len(bad) / max(len(up), 1):.1f} %) where the rays saw empty", up, is_bad, real_up, below,
               region.to_local(origins)[0] / COARSE)
    if not len(bad):
        return {"above_cut": len(up), "in_seen_empty": 0}
    grown_cols = np.zeros(shape[:2], dtype=bool)
    grown_cols[up[:, 0], up[:, 1]] = True
    real_cols = occ[:, :, layer(cut):].any(axis=2)
    grown_wall, grown_block = column_kinds(grown_cols, int(round(2.0 / COARSE)))
    real_wall, _ = column_kinds(real_cols, int(round(2.0 / COARSE)))
    ok = up[~is_bad]
    col = (bad[:, 0], bad[:, 1])
    height = (bad[:, 2] + 0.5) * COARSE - BELOW_GROUND
    dist = distance_transform_edt(~occ)[bad[:, 0], bad[:, 1], bad[:, 2]] * COARSE
    base = occ[:, :, layer(1.6):layer(2.0)].any(axis=2)
    top = column_tops(cut_occ)
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
            "only_ground_within_60cm_pct": pct(near_top < 0.5),
            "thin_grid_wall_pct": {"these": pct(grown_wall[col]), "rest_of_growth": pct(grown_wall[ok[:, 0], ok[:, 1]]),
                                   "real_above_cut": pct(real_wall[real_up[:, 0], real_up[:, 1]])},
            "block_pct": {"these": pct(grown_block[col]), "rest_of_growth": pct(grown_block[ok[:, 0], ok[:, 1]])},
            "ray_within_1m_pct": {
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


def _slash(d: dict | None) -> str:
    return "-" if d is None else " / ".join(f"{v:g}" for v in d.values())


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
    p.add_argument("--yaw", type=float, default=0.0,
                   help="region yaw in degrees (0: the frame's axes, as `hgca complete` places the default region)")
    p.add_argument("--no-render", action="store_true", help="skip the PNG per input (<out stem>_<input>.png)")
    p.add_argument("--out", required=True, help="JSON file (the table goes beside it as .md)")
    args = p.parse_args(argv)
    import torch

    torch.set_num_threads(args.threads)
    if args.adapt_bn:
        adapt_bn()
    rows = {}
    for item in default_items(args.real_dir):
        name = item["name"]
        png = None if args.no_render else Path(args.out).with_name(f"{Path(args.out).stem}_{name}.png")
        rows[name] = anatomy(*input_rays(item), args.cut, args.weights, args.seed, args.yaw, png)
        print(name, rows[name], file=sys.stderr)
    out = Path(args.out)
    out.write_text(json.dumps({"weights": args.weights or "shipped", "cut_m": args.cut, "seed": args.seed,
                               "adapt_bn": args.adapt_bn, "yaw_deg": args.yaw, "inputs": rows}, indent=1) + "\n")
    head = ("| input | above cut | in seen-empty (%) | height p10/p50/p90 (m) | distance to real p10/p50/p90 (m) | "
            "over a 1.6-2 m structure (%) | within 20 cm (%) | within 60 cm (%) | only ground within 60 cm (%) | "
            "along the ray within 1 m: real behind only / behind and before / before only / neither (%) | "
            "thin wall along the grid: these / rest of the growth / real cells above the cut (%) | "
            "in a 60 cm block: these / rest of the growth (%) |")
    lines = [head, "|---|---:|---:|---|---|---:|---:|---:|---:|---|---|---|"]
    for name, r in rows.items():
        if not r["in_seen_empty"]:
            lines.append(f"| {name} | {r['above_cut']:,} | 0 | - | - | - | - | - | - | - | - | - |")
            continue
        lines.append(f"| {name} | {r['above_cut']:,} | {r['share_pct']:.1f} | "
                     f"{' / '.join(f'{v:g}' for v in r['height_m_p10_p50_p90'])} | "
                     f"{' / '.join(f'{v:g}' for v in r['distance_m_p10_p50_p90'])} | {r['over_structure_pct']} | "
                     f"{r['within_20cm_pct']} | {r['within_60cm_pct']} | {r['only_ground_within_60cm_pct']} | "
                     f"{' / '.join(f'{v:g}' for v in r['ray_within_1m_pct'].values())} | "
                     f"{_slash(r.get('thin_grid_wall_pct'))} | {_slash(r.get('block_pct'))} |")
    out.with_suffix(".md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
