"""What stands above low objects, in real sweeps and in the synthetic sweeps the coarse model trains on (run by hand).

Why: above a 2 m cut the fine-tunes of session 22 grow round masses over objects the cut left below 2 m, where the
uncut real scans' rays saw empty (`results/recipe_s22.md`). If the synthetic streets put structure over such objects
(crowns over trunks, upper storeys over shop fronts) far more often than real streets do, that prior is in the data,
and the fix is the data. Measured on the scans alone (no model): columns of 20 cm cells whose highest occupied cell
below the cut lies 1 m or more above the ground ("low-object columns"), and for each, what the same sweep observed
in the 3 m above the cut: an occupied cell ("structure above"), else a cell its rays crossed ("seen open above"),
else nothing ("unseen"). Shares over low-object columns, per input; the synthetic inputs are the first sweep of each
scene (one sensor position, as the nuScenes sweep; the AV2 inputs are two sweeps).
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]


def tops_above(points: np.ndarray, origins: np.ndarray, index: np.ndarray, cut: float = 2.0, low: float = 1.0,
               reach: float = 3.0) -> dict:
    """The shares of the module docstring for one input (world-frame points, sensor origins, each point's origin)."""
    from hgca_core.geometry.freespace import observed_empty
    from hgca_core.geometry.region import Region, height_layer
    from hgca_core.geometry.voxel import COARSE, column_tops, voxelize

    region = Region.around(points, sensor=origins[0])
    local = region.to_local(points)
    shape = region.grid_shape(COARSE)
    empty = observed_empty(local, region.to_local(origins), index, shape)
    occ = np.zeros(shape, dtype=bool)
    c = voxelize(local[region.contains_local(local)], COARSE, region.size)
    occ[c[:, 0], c[:, 1], c[:, 2]] = True
    layer = lambda h: height_layer(h, COARSE)  # noqa: E731
    columns = column_tops(occ[:, :, : layer(cut)]) >= layer(low)
    band = slice(layer(cut), min(layer(cut + reach), shape[2]))
    structure = occ[:, :, band].any(axis=2) & columns
    seen_open = empty[:, :, band].any(axis=2) & columns & ~structure
    n = int(columns.sum())
    share = lambda m: round(100.0 * float(m.sum()) / max(n, 1), 1)  # noqa: E731
    # the returns that can mark space above the cut seen open: those above the sensor (upward rays that came back)
    offset = points - origins[index]
    up = offset[:, 2] > 0.5
    rng = np.linalg.norm(offset[:, :2], axis=1)
    return {"low_object_columns": n, "structure_above_pct": share(structure), "seen_open_above_pct": share(seen_open),
            "unseen_pct": share(columns & ~structure & ~seen_open),
            "returns_above_sensor_pct": round(100.0 * float(up.mean()), 1),
            "their_range_m_p50_p90": np.percentile(rng[up], [50, 90]).round(1).tolist() if up.any() else None}


def synthetic_inputs(data: Path, split: str, count: int) -> list[tuple[str, tuple]]:
    """(name, (points, origins, index)) of the first sweep of the first `count` scenes of a split."""
    from val_cut import first_sweeps

    return [(f"{data.name}/{split}/{stem}", (points, origin, np.zeros(len(points), np.int64)))
            for stem, points, origin in first_sweeps(data, split, count)]


def main(argv: list[str] | None = None) -> int:
    from hgca_core.commands.eval_real import default_items
    from hgca_core.real_eval import input_rays

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", nargs="+", default=[], metavar="DIR:SPLIT:COUNT",
                   help="synthetic datasets, e.g. /work/data/synth7vt:train:12")
    p.add_argument("--real-dir", default=str(REPO.parent / "shared" / "fixtures" / "real"))
    p.add_argument("--cut", type=float, default=2.0)
    p.add_argument("--out", required=True, help="JSON file (the table goes beside it as .md)")
    args = p.parse_args(argv)
    rows = {}
    for item in default_items(args.real_dir):
        rows[item["name"]] = {"kind": "real", **tops_above(*input_rays(item), cut=args.cut)}
        print(item["name"], rows[item["name"]], file=sys.stderr)
    for spec in args.data:
        folder, split, count = spec.rsplit(":", 2)
        for name, rays in synthetic_inputs(Path(folder), split, int(count)):
            rows[name] = {"kind": "synthetic", **tops_above(*rays, cut=args.cut)}
            print(name, rows[name], file=sys.stderr)
    out = Path(args.out)
    out.write_text(json.dumps({"cut_m": args.cut, "inputs": rows}, indent=1) + "\n")
    lines = ["| input | low-object columns | structure above (%) | seen open above (%) | unseen (%) | "
             "returns 0.5 m or more above the sensor (%) | their horizontal range p50 / p90 (m) |",
             "|---|---:|---:|---:|---:|---:|---|"]
    for name, r in rows.items():
        far = r["their_range_m_p50_p90"]
        lines.append(f"| {name} | {r['low_object_columns']:,} | {r['structure_above_pct']} | "
                     f"{r['seen_open_above_pct']} | {r['unseen_pct']} | {r['returns_above_sensor_pct']} | "
                     f"{'-' if far is None else ' / '.join(f'{v:g}' for v in far)} |")
    synth = [r for r in rows.values() if r["kind"] == "synthetic"]
    if synth:
        keys = ("structure_above_pct", "seen_open_above_pct", "unseen_pct", "returns_above_sensor_pct")
        mean = [np.mean([r[k] for r in synth]) for k in keys]
        lines.append(f"| synthetic, mean of {len(synth)} | - | {mean[0]:.1f} | {mean[1]:.1f} | {mean[2]:.1f} | "
                     f"{mean[3]:.1f} | - |")
    out.with_suffix(".md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
